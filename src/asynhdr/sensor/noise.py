"""Events that do not come from the signal, and what the readout does to the stream.

- Background activity: leak arrivals (ON, rate ``leak_rate_hz``, independent of light)
  and shot-noise arrivals (ON or OFF with equal probability, rate ``shot_noise_rate_hz``
  in the dark, falling linearly to ``shot_noise_bright_factor`` times that at
  ``shot_noise_full_irradiance``; v2e's model). Each is a Poisson process per pixel:
  exponential inter-arrival times, drawn exactly (the irradiance-dependent rate by
  thinning a process at the dark rate). The arrivals go through the pixel
  (:mod:`asynhdr.sensor.pixel`): one that finds the pixel ready fires it and resets it
  like a signal event; one that finds it blind is lost.
- Hot pixels are pixels whose arrivals come at ``hot_pixel_rate_hz``; dead pixels fire
  nothing. Both sets are frozen per sensor.
- The arbiter: the whole array shares one readout that serves at most
  ``max_event_rate_hz`` events per second. Events queue (``delay``: timestamps move
  later) or are lost when the queue is full (``drop``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from asynhdr.events import EVENT_DTYPE
from asynhdr.sensor.params import SensorParams

__all__ = [
    "ArbiterStats",
    "NoiseArrivals",
    "PixelDefects",
    "apply_arbiter",
    "by_pixel_then_time",
    "draw_defects",
    "merge_sorted",
    "noise_arrivals",
    "poisson_times",
    "serve_queue",
]


@dataclass(frozen=True)
class PixelDefects:
    """Frozen per-sensor defects: flat pixel indices of hot and dead pixels."""

    hot: np.ndarray
    dead: np.ndarray


def draw_defects(sensor: SensorParams, *, n_pixels: int,
                 rng: np.random.Generator) -> PixelDefects:
    """Choose hot and dead pixels (disjoint), ``round(fraction * n_pixels)`` of each."""
    n_hot = round(sensor.hot_pixel_fraction * n_pixels) if sensor.hot_pixel_rate_hz > 0 \
        else 0
    n_dead = round(sensor.dead_pixel_fraction * n_pixels)
    pick = (rng.choice(n_pixels, n_hot + n_dead, replace=False) if n_hot + n_dead
            else np.zeros(0, int))
    return PixelDefects(hot=np.sort(pick[:n_hot]).astype(np.int64),
                        dead=np.sort(pick[n_hot:]).astype(np.int64))


def poisson_times(rate_hz: float, *, n_pixels: int, duration_us: float,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Independent Poisson processes of ``rate_hz`` on ``n_pixels`` pixels over
    ``[0, duration_us)``.

    Returns ``(pixel_index, t_us)`` (float64 µs) sorted by pixel, then time. The pooled
    count is Poisson with mean ``rate * duration * n_pixels``; each event falls on a
    pixel uniformly and at a uniform time. By the splitting property of Poisson
    processes this is exactly a Poisson process of ``rate_hz`` per pixel: exponential
    inter-arrival times of mean ``1e6 / rate_hz`` µs. Cost grows with the number of
    events, not pixels.
    """
    if rate_hz < 0 or n_pixels < 0 or duration_us < 0:
        raise ValueError("poisson_times: rate_hz, n_pixels and duration_us must be >= 0")
    mean = rate_hz * duration_us * 1e-6 * n_pixels
    n = int(rng.poisson(mean)) if mean > 0 else 0
    pix = rng.integers(0, n_pixels, n) if n else np.zeros(0, np.int64)
    t = rng.random(n) * duration_us
    order = by_pixel_then_time(pix, t, n_pixels)
    return pix[order].astype(np.int64), t[order]


@nb.njit(cache=True)
def _by_pixel_then_time(pix, t, n_pixels, start, order):
    for i in range(pix.shape[0]):
        start[pix[i] + 1] += 1
    for p in range(n_pixels):
        start[p + 1] += start[p]
    for i in range(pix.shape[0]):
        p = pix[i]
        d = start[p]
        order[d] = i
        start[p] = d + 1
    # each pixel's slots now end at start[p]; sort them by time (insertion sort: a pixel
    # holds a few arrivals)
    lo = 0
    for p in range(n_pixels):
        hi = start[p]
        for a in range(lo + 1, hi):
            k = order[a]
            b = a
            while b > lo and t[order[b - 1]] > t[k]:
                order[b] = order[b - 1]
                b -= 1
            order[b] = k
        lo = hi


def by_pixel_then_time(pix: np.ndarray, t: np.ndarray, n_pixels: int) -> np.ndarray:
    """The order that sorts arrivals by pixel, then time (stable; ``np.lexsort((t, pix))``)
    by a counting sort over the pixels: it costs the arrivals and the pixels, no
    comparison sort."""
    order = np.empty(pix.size, dtype=np.int64)
    _by_pixel_then_time(np.asarray(pix, dtype=np.int64), np.asarray(t, dtype=np.float64),
                        int(n_pixels), np.zeros(int(n_pixels) + 1, dtype=np.int64), order)
    return order


@dataclass(frozen=True, eq=False)
class NoiseArrivals:
    """Background-event arrivals of one cycle, grouped by pixel.

    Attributes
    ----------
    offsets : int64 ``(n_pixels + 1,)``: pixel ``p``'s arrivals are
        ``offsets[p]:offsets[p + 1]``.
    t_us : float64 arrival times, µs from the cycle's start, increasing per pixel.
    polarity : int8, +1 or -1.
    """

    offsets: np.ndarray
    t_us: np.ndarray
    polarity: np.ndarray

    def select(self, lo: int, hi: int) -> NoiseArrivals:
        """The arrivals of pixels ``lo .. hi - 1`` (offsets from 0)."""
        a, b = int(self.offsets[lo]), int(self.offsets[hi])
        return NoiseArrivals(self.offsets[lo:hi + 1] - a, self.t_us[a:b], self.polarity[a:b])


def noise_arrivals(
    sensor: SensorParams,
    *,
    irradiance_at: object,
    n_pixels: int,
    duration_us: float,
    defects: PixelDefects,
    rng: np.random.Generator,
) -> NoiseArrivals:
    """Leak, shot-noise and hot-pixel arrivals over ``[0, duration_us)``, none on dead
    pixels. Each is a Poisson process per pixel (:func:`poisson_times`):

    - leak: ON, ``leak_rate_hz``, independent of light;
    - shot noise: ON or OFF with equal probability, ``shot_noise_rate_hz`` in the dark,
      falling linearly with irradiance to ``shot_noise_bright_factor`` of it at
      ``shot_noise_full_irradiance`` (v2e's model), drawn by thinning: an arrival of the
      dark-rate process is kept with probability ``rate(I(t)) / rate_dark``;
    - hot pixels: ON or OFF, ``hot_pixel_rate_hz``.

    ``irradiance_at(pixel_index, t_us) -> irradiance`` gives the sensor irradiance for the
    thinning. The pixel model (:mod:`asynhdr.sensor.pixel`) decides which arrivals fire.
    """
    parts_p: list[np.ndarray] = []
    parts_t: list[np.ndarray] = []
    parts_pol: list[np.ndarray] = []
    if sensor.leak_rate_hz > 0:
        pix, t = poisson_times(sensor.leak_rate_hz, n_pixels=n_pixels,
                               duration_us=duration_us, rng=rng)
        parts_p.append(pix)
        parts_t.append(t)
        parts_pol.append(np.ones(pix.size, np.int8))
    if sensor.shot_noise_rate_hz > 0:
        pix, t = poisson_times(sensor.shot_noise_rate_hz, n_pixels=n_pixels,
                               duration_us=duration_us, rng=rng)
        if pix.size:
            irr = np.asarray(irradiance_at(pix, t), dtype=np.float64)  # type: ignore[operator]
            frac = np.minimum(irr / sensor.shot_noise_full_irradiance, 1.0)
            factor = 1.0 + (sensor.shot_noise_bright_factor - 1.0) * frac
            keep = rng.random(pix.size) < factor
            pix, t = pix[keep], t[keep]
        parts_p.append(pix)
        parts_t.append(t)
        parts_pol.append(np.where(rng.random(pix.size) < 0.5, 1, -1).astype(np.int8))
    if defects.hot.size and sensor.hot_pixel_rate_hz > 0:
        pix, t = poisson_times(sensor.hot_pixel_rate_hz, n_pixels=int(defects.hot.size),
                               duration_us=duration_us, rng=rng)
        parts_p.append(defects.hot[pix])
        parts_t.append(t)
        parts_pol.append(np.where(rng.random(pix.size) < 0.5, 1, -1).astype(np.int8))
    if not parts_p:
        return NoiseArrivals(np.zeros(n_pixels + 1, np.int64), np.zeros(0), np.zeros(0, np.int8))
    pix = np.concatenate(parts_p)
    t = np.concatenate(parts_t)
    pol = np.concatenate(parts_pol)
    if defects.dead.size:
        keep = ~np.isin(pix, defects.dead)
        pix, t, pol = pix[keep], t[keep], pol[keep]
    order = by_pixel_then_time(pix, t, n_pixels)
    offsets = np.zeros(n_pixels + 1, dtype=np.int64)
    np.cumsum(np.bincount(pix, minlength=n_pixels), out=offsets[1:])
    return NoiseArrivals(offsets, t[order], pol[order])


@nb.njit(cache=True)
def _merge(a, b, out):
    i = 0
    j = 0
    k = 0
    while i < a.shape[0] and j < b.shape[0]:
        if b[j].t < a[i].t:
            out[k] = b[j]
            j += 1
        else:
            out[k] = a[i]
            i += 1
        k += 1
    while i < a.shape[0]:
        out[k] = a[i]
        i += 1
        k += 1
    while j < b.shape[0]:
        out[k] = b[j]
        j += 1
        k += 1


def merge_sorted(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Merge two time-sorted event arrays (stable: ``a`` first among equal times)."""
    if b.size == 0:
        return a
    if a.size == 0:
        return b
    out = np.empty(a.size + b.size, EVENT_DTYPE)
    _merge(a, b, out)
    return out


@dataclass
class ArbiterStats:
    """What the readout did: emitted = delivered + dropped; delayed counts delivered
    events whose timestamp moved."""

    emitted: int = 0
    delivered: int = 0
    delayed: int = 0
    dropped: int = 0
    max_delay_us: float = 0.0


@nb.njit(cache=True)
def _arbiter(t, service_us, drop, buffer, free_at, keep, t_out):
    delayed = 0
    dropped = 0
    max_delay = 0.0
    for i in range(t.shape[0]):
        ti = float(t[i])
        if drop:
            if (free_at - ti) > buffer * service_us:
                keep[i] = False
                dropped += 1
                continue
            keep[i] = True
        start = ti if ti > free_at else free_at
        free_at = start + service_us
        ts = np.int64(np.floor(start))
        if ts > t[i]:
            t_out[i] = ts
            delayed += 1
            if start - ti > max_delay:
                max_delay = start - ti
    return free_at, delayed, dropped, max_delay


@nb.njit(cache=True)
def serve_queue(req, service_us, free_at, read):
    """First come, first served: ``read[i]``, when request ``i`` (times ``req``, sorted) is
    read, one every ``service_us``; returns when the queue is free after them."""
    for i in range(req.shape[0]):
        ti = float(req[i])
        start = ti if ti > free_at else free_at
        read[i] = start
        free_at = start + service_us
    return free_at


class Arbiter:
    """The shared readout, with its queue carried from chunk to chunk."""

    def __init__(self, max_event_rate_hz: float, *, mode: str = "delay",
                 buffer_events: float = 1024) -> None:
        self.service_us = 1e6 / max_event_rate_hz
        self.drop = mode == "drop"
        self.buffer = float(buffer_events)
        self.free_at = -1e300
        self.stats = ArbiterStats()

    def __call__(self, events: np.ndarray) -> np.ndarray:
        """Serve ``events`` (time-sorted); their timestamps are updated in place."""
        keep = np.empty(events.size if self.drop else 0, np.bool_)  # read only when dropping
        t = events["t"]
        self.free_at, delayed, dropped, max_delay = _arbiter(
            t, self.service_us, self.drop, self.buffer, self.free_at, keep, t)
        out = events[keep] if dropped else events
        s = self.stats
        s.emitted += int(events.size)
        s.delivered += int(out.size)
        s.delayed += int(delayed)
        s.dropped += int(dropped)
        s.max_delay_us = max(s.max_delay_us, float(max_delay))
        return out


def apply_arbiter(events: np.ndarray, sensor: SensorParams, *,
                  n_pixels: int) -> tuple[np.ndarray, ArbiterStats]:
    """Pass time-sorted events of ``n_pixels`` simulated pixels through their share of the
    readout of ``sensor`` (:meth:`SensorParams.readout`), all at once."""
    rate, buffer = sensor.readout(n_pixels)
    if rate <= 0:
        n = int(events.size)
        return events, ArbiterStats(emitted=n, delivered=n)
    arb = Arbiter(rate, mode=sensor.arbiter, buffer_events=buffer)
    out = arb(events)
    return out, arb.stats
