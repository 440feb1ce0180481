"""Simulate the rig: scene radiance -> two modulated light paths -> DVS pixels -> recording.

One pixel model (:mod:`asynhdr.sensor.pixel`) reads each pixel's signal from the
photoreceptor (:mod:`asynhdr.sensor.photoreceptor`); two engines compute that signal:

- ``"exact"`` (static scenes): without the photoreceptor low-pass the signal is the
  sensor irradiance itself, piecewise linear in time, and every crossing time is solved
  exactly; with the low-pass, the photoreceptor output is integrated once per value of a
  log-radiance grid (a pixel's output depends only on its radiance) and each pixel
  interpolates between its two neighbouring rows;
- ``"stepped"``: each pixel's own signal is integrated on the time grid (moving scenes,
  and an independent check of the table).

The tolerances of both, against a fine-step integration, are in docs/sensor.md.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from asynhdr import __version__
from asynhdr.events import EVENT_DTYPE, Recording
from asynhdr.rig import Rig
from asynhdr.sensor._rng import Z_MAX, normal_pairs, seed_from
from asynhdr.sensor.noise import (
    NoiseArrivals,
    apply_arbiter,
    draw_defects,
    merge_sorted,
    noise_arrivals,
    serve_queue,
)
from asynhdr.sensor.params import SensorParams, get_preset
from asynhdr.sensor.photoreceptor import (
    DEFAULT_DLOG_RADIANCE,
    DEFAULT_DT_US,
    Lowpass,
    irradiance_rows,
    lowpass_rows,
    pixel_rows,
    radiance_grid,
    row_runs,
    time_grid,
)
from asynhdr.sensor.pixel import (
    CycleFiring,
    PixelState,
    cycle_pieces,
    fire_cycle,
    gather_sorted,
    place_events,
    sort_keys,
)

__all__ = ["DEFAULT_SENSOR", "ENGINES", "CycleEvents", "draw_thresholds", "finish_recording",
           "holds_pixels", "simulate", "simulate_cycles"]

logger = logging.getLogger(__name__)


ENGINES = ("exact", "stepped")
DEFAULT_SENSOR = "v2e"  # the preset simulate uses when none is named

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``, the project's progress protocol
(:data:`asynhdr.source.Progress`) with the total always known."""

_STEPPED_CHUNK = 2048
"""Pixels integrated at once by the stepped engine (their rows are held in memory)."""


class _HasRadiance(Protocol):
    @property
    def radiance(self) -> np.ndarray: ...


def draw_thresholds(
    sensor: SensorParams, *, width: int, height: int, rng: np.random.Generator | int | None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ON and OFF thresholds ``(height, width)``, frozen mismatch.

    ``c = N(c_nominal, threshold_sigma)``, raised to ``threshold_min`` (as v2e does).
    One seed is taken from ``rng`` (when there is mismatch); pixel ``i``'s two normals
    are :func:`asynhdr.sensor._rng.normal_pairs` of it.
    """
    shape = (height, width)
    if not sensor.threshold_sigma > 0:
        return (np.full(shape, sensor.threshold_on, dtype=np.float64),
                np.full(shape, sensor.threshold_off, dtype=np.float64))
    z_on, z_off = normal_pairs(seed_from(np.random.default_rng(rng)), width * height)
    c_on = z_on.reshape(shape)
    c_off = z_off.reshape(shape)
    for c, nominal in ((c_on, sensor.threshold_on), (c_off, sensor.threshold_off)):
        c *= sensor.threshold_sigma
        c += nominal
        np.maximum(c, sensor.threshold_min, out=c)
    return c_on, c_off


def _as_radiance(scene: Any, *, frames: bool = False) -> tuple[np.ndarray, dict[str, Any]]:
    radiance = getattr(scene, "radiance", scene)
    radiance = np.asarray(radiance)
    info: dict[str, Any] = {}
    for attr in ("name", "unit"):
        if hasattr(scene, attr):
            info[attr] = getattr(scene, attr)
    extra = getattr(scene, "metadata", None)
    info["metadata"] = dict(extra) if isinstance(extra, dict) else {}
    if frames and radiance.ndim != 3:
        raise ValueError(f"a moving scene must be a 3-D (n_frames, height, width) array, got "
                         f"shape {radiance.shape}")
    if not frames and radiance.ndim != 2:
        raise ValueError(f"scene radiance must be a 2-D (height, width) array, got shape "
                         f"{radiance.shape}; a moving scene needs frame_times_us")
    if not np.issubdtype(radiance.dtype, np.floating) and \
            not np.issubdtype(radiance.dtype, np.integer):
        raise ValueError(f"scene radiance must be numeric, got dtype {radiance.dtype}")
    if radiance.size == 0:
        raise ValueError(f"scene radiance is empty (shape {radiance.shape})")
    bad = ~np.isfinite(radiance)
    if bad.any():
        raise ValueError(f"scene radiance has {int(bad.sum())} NaN or infinite values")
    if (radiance < 0).any():
        raise ValueError(f"scene radiance has {int((radiance < 0).sum())} negative values")
    return radiance, info


def _concat_sorted(chunks: list[np.ndarray]) -> np.ndarray:
    """Concatenate per-cycle chunks, each sorted; where late events of one cycle reach
    into the next (latency, jitter), merge the overlap stably."""
    if not chunks:
        return np.zeros(0, EVENT_DTYPE)
    out: list[np.ndarray] = [chunks[0]]
    for c in chunks[1:]:
        if c.size == 0:
            continue
        prev = out[-1]
        if prev.size and prev["t"][-1] > c["t"][0]:
            cut = int(np.searchsorted(prev["t"], c["t"][0], side="right"))
            tail = prev[cut:]
            out[-1] = prev[:cut]
            out.append(merge_sorted(tail, c))
        else:
            out.append(c)
    return out[0] if len(out) == 1 else np.concatenate(out)


def _frame_weights(times_us: np.ndarray, t_abs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frame index ``i`` and weight ``w`` so that ``L = (1 - w) L_i + w L_{i+1}``."""
    nf = times_us.size
    if nf == 1:
        return np.zeros(t_abs.size, dtype=np.int64), np.zeros(t_abs.size)
    i = np.clip(np.searchsorted(times_us, t_abs, side="right") - 1, 0, nf - 2)
    w = (t_abs - times_us[i]) / (times_us[i + 1] - times_us[i])
    return i.astype(np.int64), np.clip(w, 0.0, 1.0)


def _check_frame_times(frame_times_us: Any, n_frames: int) -> np.ndarray:
    times = np.asarray(frame_times_us, dtype=np.float64)
    if times.shape != (n_frames,):
        raise ValueError(f"frame_times_us must have one time per frame ({n_frames}), got "
                         f"shape {times.shape}")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise ValueError("frame_times_us must be finite and strictly increasing")
    return times


class _Engine:
    """What one engine needs to run a cycle of the whole array."""

    def __init__(self, *, kind: str, rig: Rig, sensor: SensorParams, frames: np.ndarray,
                 times_us: np.ndarray, dt_us: float, dlog_radiance: float,
                 width: int, t0_us: int) -> None:
        self.kind = kind
        self.rig = rig
        self.width = width
        self.frames = frames  # (n_pixels, n_frames)
        self.times_us = times_us
        w1, w2 = rig.waveforms()
        if np.array_equal(w1.phase, w2.phase):
            knots, t1v, t2v = w1.phase, w1.values, w2.values
        else:
            knots = np.union1d(w1.phase, w2.phase)
            t1v, t2v = w1(knots), w2(knots)
        self.w1, self.w2 = w1, w2
        period = float(rig.period_us)
        lum_min = float(frames.min())
        if not float(np.min(lum_min * t1v + rig.l_const * t2v)) > 0:
            raise ValueError(
                "the sensor irradiance reaches zero during the cycle (T2 closes fully while "
                "some pixels have zero radiance); give the panels a leakage floor (contrast "
                "ratio)")
        self.lowpass = (Lowpass(sensor.tau_ref_us * (sensor.cutoff_irradiance
                                                      + sensor.dark_irradiance),
                                sensor.dark_irradiance, sensor.tau_max_us)
                        if sensor.cutoff_hz > 0 else None)
        moving = frames.shape[1] > 1
        if kind == "exact" and self.lowpass is None:
            self.s = np.asarray(knots, dtype=np.float64) * period
            self.a1 = rig.k_lens * np.asarray(t1v, dtype=np.float64)
            self.b2 = rig.k_lens * rig.l_const * np.asarray(t2v, dtype=np.float64)
        else:
            tau_min = None
            if self.lowpass is not None:
                i_max = rig.k_lens * (float(frames.max()) * float(np.max(t1v))
                                      + rig.l_const * float(np.max(t2v)))
                tau_min = min(self.lowpass.tau_num / (i_max + self.lowpass.dark_irradiance),
                              self.lowpass.tau_max_us)
            self._grid_args = dict(phase=knots, t1=t1v, t2=t2v, period_us=period, dt_us=dt_us,
                                   tau_min_us=tau_min)
            self._set_grid(None)
        npix = frames.shape[0]
        self.pix = np.arange(npix, dtype=np.int64)
        if kind == "exact" and self.lowpass is None:
            self.rows = irradiance_rows(self.a1, self.b2)
            self.pieces = cycle_pieces(self.rows[0], self.rows[1])
            self.ia = np.zeros(npix, dtype=np.int64)
            self.ib = np.ones(npix, dtype=np.int64)
            self.wa = np.ascontiguousarray(frames[:, 0])
            self.wb = np.ones(npix)
            self.ref0 = np.log(self.wa * self.a1[0] + self.b2[0])
        elif kind == "exact":
            t1max = float(np.max(t1v))
            floor = 1e-7 * rig.l_const * float(np.min(t2v)) / max(t1max, 1e-300)
            self.grid_radiance, lower, w = radiance_grid(frames[:, 0], dlog=dlog_radiance,
                                                         floor=floor)
            self.ia = lower
            self.ib = lower + 1
            self.wa = 1.0 - w
            self.wb = w
            self.y = np.log(self.a1[0] * self.grid_radiance + self.b2[0])
            present = np.bincount(lower) > 0  # the row pairs in use, by rank
            self.pairs = np.flatnonzero(present)
            self.run_key = (np.cumsum(present) - 1)[lower].astype(np.int64)
            self.ref0 = self.wa * self.y[self.ia] + self.wb * self.y[self.ib]
        else:
            lum0 = frames[:, 0] if not moving else self._lum_at(np.array([float(t0_us)]))[:, 0]
            irr0 = rig.k_lens * (float(w1(0.0)) * lum0 + float(w2(0.0)) * rig.l_const)
            self.y = np.log(irr0)
            self.ref0 = self.y.copy()

    def _set_grid(self, extra_us: np.ndarray | None) -> None:
        self.s = time_grid(**self._grid_args, extra_us=extra_us)  # type: ignore[arg-type]
        u = self.s / self.rig.period_us
        self.a1 = self.rig.k_lens * self.w1(u)
        self.b2 = self.rig.k_lens * self.rig.l_const * self.w2(u)

    def _lum_at(self, t_abs: np.ndarray) -> np.ndarray:
        fa, fw = _frame_weights(self.times_us, t_abs)
        f = self.frames
        if f.shape[1] == 1:
            return np.repeat(f[:, :1], t_abs.size, axis=1)
        return f[:, fa] + fw * (f[:, fa + 1] - f[:, fa])

    def irradiance_at(self, t_start_us: int) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        rig = self.rig

        def at(pix: np.ndarray, t_off_us: np.ndarray) -> np.ndarray:
            u = np.asarray(t_off_us) / rig.period_us
            f = self.frames
            if f.shape[1] == 1:
                lum = f[pix, 0]
            else:
                fa, fw = _frame_weights(self.times_us, t_start_us + np.asarray(t_off_us))
                lum = f[pix, fa] + fw * (f[pix, fa + 1] - f[pix, fa])
            return rig.k_lens * (self.w1(u) * lum + self.w2(u) * rig.l_const)

        return at

    def run_cycle(self, *, cycle: int, t_start_us: int, state: PixelState, c_on: np.ndarray,
                  c_off: np.ndarray, alive: np.ndarray, noise: NoiseArrivals, seed: int,
                  sensor: SensorParams, t_lo: int, nbins: int, lo: int, hi: int,
                  readout: HeldReadout | None = None) -> tuple[np.ndarray, int]:
        """Events of pixels ``lo .. hi - 1`` in one cycle (time-sorted, stable in pixel
        order) and how many background arrivals met a blind pixel. With ``readout`` (the
        exact engine) a pixel whose event waits for the readout is held until it is read
        (:class:`HeldReadout`)."""
        common = dict(c_on=c_on, c_off=c_off, state=state, alive=alive, seed=seed, cycle=cycle,
                      reset_noise_sigma=sensor.reset_noise_sigma,
                      refractory_us=sensor.refractory_us, latency_us=sensor.latency_us,
                      jitter_sigma_us=sensor.jitter_sigma_us,
                      period_us=float(self.rig.period_us), t_lo=t_lo, nbins=nbins)
        sel = slice(lo, hi)
        nz = noise.select(lo, hi)
        pix = self.pix[sel]
        if self.kind == "exact":
            geometry = dict(period_us=float(self.rig.period_us), t_lo=t_lo, nbins=nbins)
            if self.lowpass is None:
                cyc = CycleFiring(pix, self.s, self.rows, self.ia[sel], self.ib[sel],
                                  self.wa[sel], self.wb[sel], log_domain=False,
                                  pieces=self.pieces, run_key=None, run_off=None,
                                  run_tab=None, **geometry)  # type: ignore[arg-type]
            else:
                rows, y_end = lowpass_rows(self.grid_radiance, self.a1, self.b2, self.s,
                                           self.y, self.lowpass)
                self.y = y_end
                run_off, run_tab = row_runs(rows, self.pairs, self.pairs + 1)
                cyc = CycleFiring(pix, self.s, rows, self.ia[sel], self.ib[sel], self.wa[sel],
                                  self.wb[sel], log_domain=True, pieces=None,
                                  run_key=self.run_key[sel], run_off=run_off,
                                  run_tab=run_tab, **geometry)  # type: ignore[arg-type]
            kw = {k: v for k, v in common.items() if k not in geometry}
            kw.update(noise_off=nz.offsets, noise_t=nz.t_us, noise_pol=nz.polarity)
            if readout is not None and readout.busy:
                return readout.held_cycle(cyc, kw, nz.offsets, pix, width=self.width,
                                          t_start_us=t_start_us)
            saved = state.copy() if readout is not None else None
            counts, st, sp, off, lost = cyc.fire(
                noise_q=nz.offsets[:-1].copy(), **kw)  # type: ignore[arg-type]
            keys = sort_keys(off, counts, st, sp, t_first_us=t_start_us + t_lo, nbins=nbins)
            del st, sp  # the slots' memory goes back before the events array is written
            ev = place_events(keys, pix, width=self.width)
            del keys
            if readout is None or readout.free(ev["t"]):
                return ev, lost
            assert saved is not None
            state.restore(saved)
            return readout.held_cycle(cyc, kw, nz.offsets, pix, width=self.width,
                                      t_start_us=t_start_us,
                                      free_until_us=readout.first_late_us - t_start_us)
        # stepped: each pixel's own row, a chunk of pixels at a time
        if self.frames.shape[1] > 1:
            self._set_grid(self.times_us - t_start_us)
        fa, fw = _frame_weights(self.times_us, t_start_us + self.s)
        all_counts: list[np.ndarray] = []
        all_t: list[np.ndarray] = []
        all_p: list[np.ndarray] = []
        lost_total = 0
        for a in range(lo, hi, _STEPPED_CHUNK):
            b = min(hi, a + _STEPPED_CHUNK)
            rows, y_end = pixel_rows(self.frames[a:b], fa, fw, self.a1, self.b2, self.s,
                                     self.y[a:b], self.lowpass)
            self.y[a:b] = y_end
            local = np.arange(b - a, dtype=np.int64)
            run_off, run_tab = row_runs(rows, local, local)
            nzc = noise.select(a, b)
            counts, st, sp, off, lost = fire_cycle(
                self.pix[a:b], self.s, rows, local, local, np.ones(b - a),
                np.zeros(b - a), log_domain=self.lowpass is not None, pieces=None,
                run_key=local, run_off=run_off, run_tab=run_tab, noise_off=nzc.offsets,
                noise_t=nzc.t_us, noise_pol=nzc.polarity, **common)  # type: ignore[arg-type]
            lost_total += lost
            keep = (np.arange(st.size) - np.repeat(off[:-1], np.diff(off))
                    < np.repeat(counts, np.diff(off)))
            all_counts.append(counts)
            all_t.append(st[keep])
            all_p.append(sp[keep])
        counts = np.concatenate(all_counts) if all_counts else np.zeros(0, np.int64)
        off = np.zeros(counts.size + 1, dtype=np.int64)
        np.cumsum(counts, out=off[1:])
        ev = gather_sorted(off, counts,
                           np.concatenate(all_t) if all_t else np.zeros(0, np.int32),
                           np.concatenate(all_p) if all_p else np.zeros(0, np.int8), pix,
                           width=self.width, t_first_us=t_start_us + t_lo, nbins=nbins)
        return ev, lost_total


def simulate(
    scene: _HasRadiance | np.ndarray,
    *,
    rig: Rig | None = None,
    sensor: SensorParams | str = DEFAULT_SENSOR,
    n_cycles: int = 1,
    rng: np.random.Generator | int | None = 0,
    t0_us: int = 0,
    thresholds: tuple[np.ndarray, np.ndarray] | None = None,
    sensor_seed: int | None = None,
    engine: str = "auto",
    dt_us: float = DEFAULT_DT_US,
    dlog_radiance: float = DEFAULT_DLOG_RADIANCE,
    frame_times_us: np.ndarray | None = None,
    progress: Progress | None = None,
) -> Recording:
    """Simulate ``n_cycles`` modulation cycles.

    Parameters
    ----------
    scene : a ``Scene`` (anything with a ``radiance`` attribute) or a ``(height, width)``
        radiance array, in the same unit as ``rig.l_const``.
    rig : the optics (default ``Rig()``), its panels included.
    sensor : pixel parameters or a preset name.
    n_cycles : number of cycles; one rising trigger at each cycle start.
    rng : seed or generator for everything random in this capture (reset noise,
        jitter, background activity; and the frozen sensor maps when ``sensor_seed``
        is not given). Same seed, same events, bit for bit.
    t0_us : start time of the first cycle.
    thresholds : optional ``(c_on, c_off)`` maps to use instead of drawing them.
    sensor_seed : when given, the sensor's frozen maps (threshold mismatch, hot and
        dead pixels) are drawn from this seed rather than from ``rng``: the same seed
        is the same physical sensor across captures.
    engine : ``"auto"`` (``"exact"`` for a static scene, ``"stepped"`` for a moving one),
        ``"exact"`` (static scenes: crossings solved on the exact irradiance, or on
        the photoreceptor output tabulated over radiance) or ``"stepped"`` (each pixel's
        signal integrated on the time grid; needed for a moving scene).
    dt_us : largest step of the time grid where a signal is integrated (the
        photoreceptor low-pass, the stepped engine).
    dlog_radiance : step of the log-radiance grid of the exact engine's low-pass table.
    frame_times_us : for a moving scene, ``scene`` is ``(n_frames, height, width)`` and
        these are the frames' times (µs, same clock as ``t0_us``; radiance is linear in
        time between frames and held outside them); a scene with ``times_us`` (a
        :class:`asynhdr.scene.MovingScene`) gives its own. Needs the stepped engine.
    progress : called as ``progress("simulate", done_cycles, n_cycles)`` after each cycle.

    Returns
    -------
    A ``Recording`` whose metadata holds the rig (its panel included), the sensor, the
    engine, the seeds, how many events the signal and the background made, and what the
    readout did (``"readout"``: emitted, delivered, delayed, dropped events).
    """
    parts = simulate_cycles(
        scene, rig=rig, sensor=sensor, n_cycles=n_cycles, rng=rng, t0_us=t0_us,
        thresholds=thresholds, sensor_seed=sensor_seed, engine=engine, dt_us=dt_us,
        dlog_radiance=dlog_radiance, frame_times_us=frame_times_us, progress=progress)
    return finish_recording([parts])


@dataclass
class CycleEvents:
    """The events of a range of pixels, cycle by cycle, before the readout.

    Made by :func:`simulate_cycles`; :func:`finish_recording` joins the parts of a
    sensor into the recording :func:`simulate` returns.

    Attributes
    ----------
    pixels : ``(lo, hi)``: the row-major pixel range.
    cycles : per cycle, the range's events sorted by time (stable in pixel order).
    n_arrivals, n_lost : background arrivals on the range, and those that met a blind
        pixel.
    context : what the recording's metadata says besides the counts and the readout,
        the sensor, the geometry and the triggers.
    held_cycles : cycles fired in slices because the readout held pixels
        (:class:`HeldReadout`).
    """

    pixels: tuple[int, int]
    cycles: list[np.ndarray]
    n_arrivals: int
    n_lost: int
    context: dict[str, Any]
    held_cycles: int = 0


class HeldReadout:
    """The sensor's readout queue as the pixels see it: a pixel whose event waits is held
    (no new reference, no new event) until the readout reads it, and its dead time runs
    from then (``refractory_us`` after the read).

    Requests are served one after the other, each ``1 / max_event_rate_hz`` (the array's
    share for the simulated pixels), first come first served, as
    :func:`asynhdr.sensor.noise.apply_arbiter` serves them afterwards. A cycle whose
    events wait at most ``tolerance_us`` (the timestamp's resolution) runs with the pixels
    independent: a pixel would be held less than that. Otherwise the cycle is fired again
    in slices of ``refractory_us`` (a pixel fires at most once in a slice), each slice's
    requests are read in time order, and each requesting pixel's dead time is set from
    its read; the slices before the first request that waited longer than the tolerance
    are fired at once, as in the first pass, and so are windows of slices once the queue
    has stayed empty (:meth:`held_cycle`). After a cycle in which events waited longer
    than the tolerance even so (``busy``), the next cycle goes to the slices at once: the
    independent pass would be thrown away.
    """

    def __init__(self, sensor: SensorParams, n_pixels: int) -> None:
        rate, _ = sensor.readout(n_pixels)
        self.service_us = 1e6 / rate
        self.step = int(sensor.timestamp_resolution_us)
        self.slice_us = float(sensor.refractory_us)
        self.refractory_us = float(sensor.refractory_us)
        self.tolerance_us = float(self.step)
        self.free_at = -1e300
        self.held_cycles = 0
        self.busy = False
        self.first_late_us = 0.0

    @staticmethod
    def applies(sensor: SensorParams, engine: str) -> bool:
        """Whether a readout holds ``sensor``'s pixels: a rate limit whose arbiter holds
        (``arbiter="hold"``), a dead time to slice the cycle by, the exact engine."""
        return (sensor.max_event_rate_hz > 0 and sensor.arbiter == "hold"
                and sensor.refractory_us >= 1.0 and engine == "exact")

    def _serve(self, t: np.ndarray, free_at: float) -> tuple[np.ndarray, float]:
        """Read times (µs) of requests at integer times ``t`` (sorted) and the queue's
        state after them."""
        req = (t // self.step) * self.step if self.step > 1 else t
        read = np.empty(req.size, dtype=np.float64)
        free_at = serve_queue(req, self.service_us, free_at, read)
        return read - req, free_at

    def free(self, t: np.ndarray) -> bool:
        """Serve a cycle's requests fired with independent pixels: True (and the queue
        advanced) when none waited longer than the tolerance."""
        wait, free_at = self._serve(t, self.free_at)
        late = np.flatnonzero(wait > self.tolerance_us)
        if late.size:
            self.first_late_us = float(t[late[0]])
            return False
        self.free_at = free_at
        return True

    def held_cycle(self, cyc: CycleFiring, kw: dict[str, Any], noise_off: np.ndarray,
                   pix: np.ndarray, *, width: int, t_start_us: int, free_until_us: float = 0.0
                   ) -> tuple[np.ndarray, int]:
        """The cycle fired in slices, each pixel held until its event is read.

        Where no request waits longer than the tolerance the slices are fired at once, with
        the pixels independent, as in the first pass: before ``free_until_us`` (µs from the
        cycle's start), and, once the queue has ended ``_IDLE_SLICES`` slices in a row
        empty with nothing in them late, a window of slices is tried so: kept whole when
        none of its requests waits longer than the tolerance (the next window twice as
        long), else up to the slice of its first late request, and the slices go on.
        """
        state: PixelState = kw["state"]
        period = cyc.period_us
        step = self.slice_us
        lat = float(kw["latency_us"])
        noise_q = noise_off[:-1].copy()
        n_slices = max(1, math.ceil(period / step))
        chunks: list[np.ndarray] = []
        lost = 0
        longest = 0.0

        def free_run(j_from: int, j_stop: int) -> tuple[np.ndarray, int]:
            """Fire slices ``j_from + 1 .. j_stop`` with the pixels independent: their events
            fire from ``j_from step`` on and before ``j_stop step``, so only those time
            bins are sorted."""
            final = j_stop >= n_slices
            counts, st, sp, off, n_lost = cyc.fire(
                noise_q=noise_q, t_stop=None if final else j_stop * step, **kw)
            b0 = max(0, math.floor(j_from * step + lat) - cyc.t_lo)
            b1 = cyc.nbins if final else min(cyc.nbins, math.floor(j_stop * step + lat)
                                             - cyc.t_lo + 1)
            return gather_sorted(off, counts, st, sp, pix, width=width,
                                 t_first_us=t_start_us + cyc.t_lo, nbins=b1 - b0,
                                 first_bin=b0), n_lost

        j = min(int(free_until_us // step), n_slices - 1)  # slices 1 .. j are done
        if j >= 1:
            ev, lost = free_run(0, j)
            wait, self.free_at = self._serve(ev["t"], self.free_at)
            longest = float(wait.max(initial=0.0))
            chunks.append(ev)
        idle = 0
        window = _IDLE_SLICES
        while j < n_slices:
            if idle >= _IDLE_SLICES:
                # the queue has been empty a while: a window with the pixels independent
                saved = state.copy()
                saved_q = noise_q.copy()
                j_stop = min(j + window, n_slices)
                ev, n_lost = free_run(j, j_stop)
                wait, free_at = self._serve(ev["t"], self.free_at)
                bad = np.flatnonzero(wait > self.tolerance_us)
                if not bad.size:
                    self.free_at = free_at
                    chunks.append(ev)
                    lost += n_lost
                    j = j_stop
                    window *= 2
                    continue
                state.restore(saved)
                noise_q[:] = saved_q
                j_late = int((float(ev["t"][bad[0]]) - t_start_us) // step)
                if j_late > j:
                    ev, n_lost = free_run(j, j_late)
                    wait, self.free_at = self._serve(ev["t"], self.free_at)
                    longest = max(longest, float(wait.max(initial=0.0)))
                    chunks.append(ev)
                    lost += n_lost
                    j = j_late
                idle = 0
                window = _IDLE_SLICES
                continue
            j += 1
            final = j == n_slices
            counts, st, sp, off, n_lost = cyc.fire(
                noise_q=noise_q, t_stop=None if final else j * step, held=True, **kw)
            lost += n_lost
            who = np.flatnonzero(counts)
            late = 0.0
            if who.size:
                bins = st[off[who]].astype(np.int64)
                order = np.argsort(bins, kind="stable")
                who, bins = who[order], bins[order]
                t = t_start_us + cyc.t_lo + bins
                wait, self.free_at = self._serve(t, self.free_at)
                late = float(wait.max())
                longest = max(longest, late)
                read = (t // self.step) * self.step + wait - t_start_us  # from the cycle's start
                p = pix[who]
                shift = period if final else 0.0
                state.ready[p] = np.maximum(state.ready[p], read + self.refractory_us - shift)
                if not final:
                    state.next_fire[p] = state.ready[p]
                ev = np.empty(who.size, dtype=EVENT_DTYPE)
                ev["x"] = p % width
                ev["y"] = p // width
                ev["t"] = t
                ev["p"] = sp[off[who]]
                chunks.append(ev)
            quiet = late <= self.tolerance_us and self.free_at <= t_start_us + j * step
            idle = idle + 1 if quiet else 0
        self.held_cycles += 1
        self.busy = longest > self.tolerance_us
        out = np.concatenate(chunks) if chunks else np.zeros(0, EVENT_DTYPE)
        return out, lost


_IDLE_SLICES = 8  # empty slices before a held cycle tries a window of independent pixels


def _engine_for(engine: str, *, moving: bool) -> str:
    """The engine ``"auto"`` means: stepped for a moving scene, else exact."""
    if engine != "auto":
        return engine
    return "stepped" if moving else "exact"


def holds_pixels(scene: Any, *, sensor: SensorParams | str = DEFAULT_SENSOR,
                 engine: str = "auto", frame_times_us: Any = None, **_: Any) -> bool:
    """Whether :func:`simulate` with these arguments holds a pixel whose event waits for
    the readout (:class:`HeldReadout`), which couples every pixel: such a sensor cannot
    be split into pixel ranges."""
    sp = get_preset(sensor) if isinstance(sensor, str) else sensor
    moving = frame_times_us is not None or getattr(scene, "times_us", None) is not None
    return HeldReadout.applies(sp, _engine_for(engine, moving=moving))


def simulate_cycles(
    scene: _HasRadiance | np.ndarray,
    *,
    rig: Rig | None = None,
    sensor: SensorParams | str = DEFAULT_SENSOR,
    n_cycles: int = 1,
    rng: np.random.Generator | int | None = 0,
    t0_us: int = 0,
    thresholds: tuple[np.ndarray, np.ndarray] | None = None,
    sensor_seed: int | None = None,
    engine: str = "auto",
    dt_us: float = DEFAULT_DT_US,
    dlog_radiance: float = DEFAULT_DLOG_RADIANCE,
    frame_times_us: np.ndarray | None = None,
    progress: Progress | None = None,
    pixels: tuple[int, int] | None = None,
) -> CycleEvents:
    """The cycles of :func:`simulate` for the pixels ``pixels = (lo, hi)`` (row-major,
    default all), before the readout: the work of one part when a sensor is split
    across processes or machines (:mod:`asynhdr.distributed`).

    Everything random is drawn as for the whole sensor (thresholds, hot and dead pixels,
    each cycle's background arrivals; per-event draws are a hash of the pixel), and the
    grids that depend on the scene (the log-radiance table, the time grid) come from the
    whole scene, so the parts of a sensor joined by :func:`finish_recording` are the
    events of one :func:`simulate` call, bit for bit. Arguments as in :func:`simulate`.
    """
    rig = rig or Rig()
    if isinstance(sensor, str):
        sensor = get_preset(sensor)
    if int(n_cycles) != n_cycles or n_cycles < 1:
        raise ValueError(f"n_cycles must be a whole number >= 1, got {n_cycles}")
    if int(t0_us) != t0_us:
        raise ValueError(f"t0_us must be a whole number of µs, got {t0_us}")
    if frame_times_us is None and getattr(scene, "times_us", None) is not None:
        frame_times_us = scene.times_us  # type: ignore[union-attr]
    engine = _engine_for(engine, moving=frame_times_us is not None)
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; expected 'auto' or one of {ENGINES}")
    dead_us = sensor.refractory_us + sensor.latency_us
    if dead_us >= rig.period_us:
        raise ValueError(f"refractory_us + latency_us ({dead_us:g}) must be shorter than the "
                         f"cycle (period_us={rig.period_us})")
    moving = frame_times_us is not None
    radiance, info = _as_radiance(scene, frames=moving)
    if moving and engine != "stepped":
        raise ValueError("a moving scene (frame_times_us) needs engine='stepped'")
    height, width = radiance.shape[-2:]
    if width > 65535 or height > 65535:
        raise ValueError(f"sensor too large for uint16 coordinates: {width}x{height}")
    npix = width * height
    lo, hi = (0, npix) if pixels is None else (int(pixels[0]), int(pixels[1]))
    if not 0 <= lo <= hi <= npix:
        raise ValueError(f"pixels must be a range (lo, hi) within 0 .. {npix}, got {pixels}")
    if moving:
        times = _check_frame_times(frame_times_us, radiance.shape[0])
        frames = np.ascontiguousarray(radiance.reshape(radiance.shape[0], -1).T,
                                      dtype=np.float64)
    else:
        times = np.zeros(1)
        frames = np.ascontiguousarray(radiance.reshape(-1, 1), dtype=np.float64)
    gen = np.random.default_rng(rng)
    sensor_gen = gen if sensor_seed is None else np.random.default_rng(sensor_seed)

    if thresholds is None:
        c_on, c_off = draw_thresholds(sensor, width=width, height=height, rng=sensor_gen)
    else:
        c_on, c_off = (np.asarray(a, dtype=np.float64) for a in thresholds)
        if c_on.shape != (height, width) or c_off.shape != (height, width):
            raise ValueError(
                f"thresholds must have the sensor's shape {(height, width)}, got {c_on.shape} "
                f"and {c_off.shape}"
            )
        if not (np.all(np.isfinite(c_on)) and np.all(np.isfinite(c_off))) or \
                (c_on <= 0).any() or (c_off <= 0).any():
            raise ValueError("thresholds must be finite and positive")
    defects = draw_defects(sensor, n_pixels=npix, rng=sensor_gen)
    hash_seed = seed_from(gen)
    eng = _Engine(kind=engine, rig=rig, sensor=sensor, frames=frames, times_us=times,
                  dt_us=dt_us, dlog_radiance=dlog_radiance, width=width, t0_us=int(t0_us))
    state = PixelState(eng.ref0)
    alive = np.ones(npix, dtype=np.int8)
    alive[defects.dead] = 0
    c_on_f = np.ascontiguousarray(c_on.ravel())
    c_off_f = np.ascontiguousarray(c_off.ravel())
    starts = rig.cycle_starts_us(n_cycles, t0_us=t0_us)
    spread = Z_MAX * sensor.jitter_sigma_us  # bounds the stamps' spread around the cycle
    t_lo = -(math.ceil(spread) + 1) if spread > 0 else 0
    nbins = math.ceil(rig.period_us + sensor.latency_us + spread) + 2 - t_lo
    no_noise = NoiseArrivals(np.zeros(npix + 1, np.int64), np.zeros(0), np.zeros(0, np.int8))

    # a readout that holds its pixels couples them all: the whole sensor in one call only
    readout = (HeldReadout(sensor, npix) if HeldReadout.applies(sensor, engine)
               and (lo, hi) == (0, npix) else None)
    chunks: list[np.ndarray] = []
    n_arrivals = 0
    n_lost = 0
    for k in range(n_cycles):
        t_start = int(starts[k])
        if sensor.has_noise_events:
            noise = noise_arrivals(sensor, irradiance_at=eng.irradiance_at(t_start),
                                   n_pixels=npix, duration_us=float(rig.period_us),
                                   defects=defects, rng=gen)
        else:
            noise = no_noise
        ev, lost = eng.run_cycle(cycle=k, t_start_us=t_start, state=state, c_on=c_on_f,
                                 c_off=c_off_f, alive=alive, noise=noise, seed=hash_seed,
                                 sensor=sensor, t_lo=t_lo, nbins=nbins, lo=lo, hi=hi,
                                 readout=readout)
        n_arrivals += int(noise.offsets[hi] - noise.offsets[lo])
        n_lost += lost
        chunks.append(ev)
        if progress is not None:
            progress("simulate", k + 1, n_cycles)
    context: dict[str, Any] = {
        "simulated": True,
        "asynhdr_version": __version__,
        "engine": engine,
        "dt_us": float(dt_us),
        "dlog_radiance": float(dlog_radiance),
        "rig": rig.to_metadata(),
        "sensor": sensor.to_metadata(),
        "n_cycles": int(n_cycles),
        "t0_us": int(t0_us),
        "seed": rng if isinstance(rng, int) else None,
        "sensor_seed": sensor_seed,
        "radiance_unit": info.get("unit", "relative"),
        "scene": info.get("name", ""),
        "width": int(width),
        "height": int(height),
        "hot_pixels": int(defects.hot.size),
        "dead_pixels": int(defects.dead.size),
        "scene_metadata": info["metadata"],
        "readout_holds": readout is not None,
    }
    return CycleEvents(pixels=(lo, hi), cycles=chunks, n_arrivals=n_arrivals, n_lost=n_lost,
                       context=context, held_cycles=readout.held_cycles if readout else 0)


def finish_recording(parts: list[CycleEvents]) -> Recording:
    """The recording of a sensor from the parts :func:`simulate_cycles` made for
    consecutive pixel ranges covering it (in pixel order): each cycle's events joined in
    time order (stable: pixel order among equal times, as one call makes them), the
    cycles joined, timestamps floored to the sensor's resolution, then the readout
    (:func:`asynhdr.sensor.noise.apply_arbiter`) over the whole stream."""
    if not parts:
        raise ValueError("finish_recording: no parts")
    parts = sorted(parts, key=lambda p: p.pixels[0])
    ctx = parts[0].context
    npix = ctx["width"] * ctx["height"]
    edges = [p.pixels for p in parts]
    if edges[0][0] != 0 or edges[-1][1] != npix or any(
            a[1] != b[0] for a, b in itertools.pairwise(edges)):
        raise ValueError(f"finish_recording: the parts {edges} do not cover the sensor's "
                         f"{npix} pixels once, in order")
    sensor = SensorParams.from_metadata(ctx["sensor"])
    n_cycles = ctx["n_cycles"]
    chunks = []
    for k in range(n_cycles):
        cyc = [p.cycles[k] for p in parts if p.cycles[k].size]
        if len(cyc) <= 1:
            chunks.append(cyc[0] if cyc else np.zeros(0, EVENT_DTYPE))
            continue
        joined = np.concatenate(cyc)
        chunks.append(joined[np.argsort(joined["t"], kind="stable")])
    n_arrivals = sum(p.n_arrivals for p in parts)
    n_lost = sum(p.n_lost for p in parts)
    events = _concat_sorted(chunks)
    step = sensor.timestamp_resolution_us
    if step > 1:
        events["t"] = (events["t"] // step) * step
    n_emitted = int(events.size)
    n_background = n_arrivals - n_lost
    events, stats = apply_arbiter(events, sensor, n_pixels=npix)
    holds = bool(ctx["readout_holds"])
    if not holds and stats.max_delay_us > sensor.timestamp_resolution_us:
        why = ("a split sensor" if len(parts) > 1 or parts[0].pixels != (0, npix)
               else f"the {ctx['engine']} engine" if sensor.arbiter == "hold"
               else f"arbiter={sensor.arbiter!r}")
        (logger.warning if sensor.arbiter == "hold" else logger.info)(
            "the readout made events wait up to %.0f µs, but their pixels fired on as if read "
            "at once (%s); arbiter='hold', the exact engine and the whole sensor in one call "
            "hold a waiting pixel until it is read", stats.max_delay_us, why)
    metadata = {k: v for k, v in ctx.items()
                if k not in ("width", "height", "hot_pixels", "dead_pixels", "scene_metadata",
                             "readout_holds")}
    metadata["counts"] = {"signal": n_emitted - n_background, "background": n_background,
                          "background_lost_in_dead_time": n_lost,
                          "hot_pixels": ctx["hot_pixels"], "dead_pixels": ctx["dead_pixels"]}
    metadata["readout"] = {"emitted": stats.emitted, "delivered": stats.delivered,
                           "delayed": stats.delayed, "dropped": stats.dropped,
                           "max_delay_us": stats.max_delay_us,
                           "rate_hz": sensor.readout(npix)[0],
                           "pixels_held": holds,
                           "held_cycles": sum(p.held_cycles for p in parts)}
    for key, value in ctx["scene_metadata"].items():  # what the scene says of itself (a CFA)
        metadata.setdefault(key, value)
    width, height = ctx["width"], ctx["height"]
    logger.info("simulated %d events over %d cycles on %dx%d (%s engine)", events.size,
                n_cycles, width, height, ctx["engine"])
    rig = Rig.from_metadata(ctx["rig"])
    # every event was made inside the sensor with polarity +1 or -1, sorted by time
    return Recording.from_checked(events=events, width=width, height=height,
                                  triggers=rig.triggers(n_cycles, t0_us=ctx["t0_us"]),
                                  metadata=metadata)
