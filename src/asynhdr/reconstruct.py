"""Reconstruct one image per modulation cycle from the events.

The paper's temporal-weighted reconstruction (Wu et al. 2024, Eq. 14)::

    img(x, y) = L_const * exp( sum_i f(t_i) * c_i * p_i )      over the pixel's events

with ``t`` normalised to the integration window of the cycle (0 at the cycle start,
1 at the end of the ramp), ``c_i`` the pixel's ON threshold for an ON event and its
OFF threshold for an OFF event (the paper has one ``c``; a sensor whose thresholds
differ, such as the DAVIS346 with 0.134 ON and 0.203 OFF, needs both) and a
decreasing weight ``f`` chosen by name:

=============  ===========================  ==========================
name           ``f(t)``                     paper
=============  ===========================  ==========================
``raw``        ``1``                        raw integral
``linear``     ``1 - t``                    linear weighted
``quadratic``  ``(1 - t)^2``                quadratic
``poly5``      ``(1 - t)^5``                high-order polynomial
``exp``        ``2^(-k t)`` (``k = 10``)    exponential (Eq. 20)
=============  ===========================  ==========================

A c-map (per-pixel threshold correction, see ``asynhdr.calibrate``) multiplies both
thresholds pixel by pixel. The paper's ``img`` is monotone in radiance but not linear in
it. A pixel whose ``L_const exp(level)`` float32 cannot hold (hundreds more ON than OFF
events: a hot pixel, or a window far longer than a ramp; a cycle swings the log
irradiance by at most the log of the panel's contrast ratio, about 35 thresholds) is
set to the largest float32, and how many were is logged.

Baselines:

- ``ttfe`` (time to first event, the EvTemMap approach): grey from the time ``u`` of
  each pixel's first ON event in the cycle. With the rig's waveforms known, the first
  ON fires when ``T1(u) L + T2(u) L_const = e^c_on (T1(0) L + T2(0) L_const)``, so::

      L = L_const * (e^c_on T2(0) - T2(u)) / (T1(u) - e^c_on T1(0))

  which is linear in radiance (the event time is taken half a µs after its floored
  timestamp). Without a rig, ``L`` is taken ``∝ 1/u`` (a linear ramp).
  Pixels with no ON event in the window are 0.
- ``count``: ``L_const * exp(c_on * n_on)`` from the number of ON events alone.

Radiometric inversion (``invert``): every event is an equation for ``L``. After
``n_on`` ON and ``n_off`` OFF events in the cycle, the pixel's irradiance has moved by
``l = c_on n_on - c_off n_off`` in log from its reference at the cycle's start, so with
the rig's known waveforms and ``rho = L / L_const``::

    rho T1(u) + T2(u) = e^(l + d) (rho T1(0) + T2(0))

where ``d`` is how far above the start level the reference stood when the cycle began:
not 0 in general (the last cycle left it anywhere within a threshold of it). A first
pass finds ``d`` per pixel and cycle: the points ``(T1 e^-l, T2 e^-l)`` of its events lie
on the line ``y = K - rho x``, ``K = (rho T1(0) + T2(0)) e^d``, fitted in least
squares, ``d`` held within ``(-c_on, c_off)`` (0 without a line, and in a warm-up cycle,
whose pixels start on the start level). The second solves each event for ``rho``; the
image is their mean in log, each weighted by its inverse variance: the level's error
grows with the events since the start (a random walk of resets), and an event where the
signal is back at its start level says little. Exact for the ideal pixel on any
waveforms, linear in radiance (up to noise); it uses the c-map's per-pixel thresholds
when given. Pixels with no usable event are 0.

Maximum likelihood (``ml``, :mod:`asynhdr.ml`): each pixel's events inverted together
through the simulator's own pixel model (thresholds, dead time, reset noise, jitter,
photoreceptor, background events); linear radiance with a per-pixel uncertainty, NaN
where a pixel has no information, the model range's bound where the estimate reached it
(as a saturated pixel holds full scale). It needs the rig and the sensor model (the recording's
metadata, or a rig file, :mod:`asynhdr.io.rigfile`).

Methods are records (:class:`Method` in :data:`METHODS`): a new method is one function
and one entry. Per-pixel sums are one pass over the time-sorted events (numba),
scatter-adding ``f(u) c_on`` or ``-f(u) c_off`` into ``(n_cycles, height * width)``.

Everything here takes a :class:`~asynhdr.source.Source` (or a Recording) and never
opens a file: :func:`reconstruct` works on a whole recording in memory,
:func:`reconstruct_cycles` streams a source one cycle at a time.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

import numba as nb
import numpy as np

from asynhdr.events import Recording, sort_events
from asynhdr.rig import Rig
from asynhdr.segment import Cycles, cycles_from_triggers, find_cycles
from asynhdr.sensor.params import PRESETS, SensorParams
from asynhdr.source import Progress, Source, Window, as_source

__all__ = [
    "DEFAULT_K",
    "DEFAULT_METHOD",
    "METHODS",
    "RELATIVE_L_CONST",
    "RIG_PERIOD_TOLERANCE",
    "WEIGHTINGS",
    "CycleImages",
    "CycleWindows",
    "Method",
    "first_on_phase",
    "reconstruct",
    "reconstruct_cycles",
    "rig_of",
    "thresholds_of",
    "weight",
    "weighted_sums",
    "windows_for",
]

logger = logging.getLogger(__name__)

DEFAULT_METHOD = "exp"
"""The method used when none is named: the paper's best weighting."""

DEFAULT_K = 10.0
"""The exponential weighting's ``k`` (the paper chose 10)."""

RELATIVE_L_CONST = 1.0
"""``L_const`` when the recording has no rig: images are then relative to the reference
radiance (the unit the metadata's ``radiance_unit`` says, ``"relative"`` by default)."""

FLOAT32_MAX = float(np.finfo(np.float32).max)
LOG_FLOAT32_MAX = math.log(FLOAT32_MAX)
"""``ln`` of the largest float32 (3.4e38): the highest log radiance an image holds."""

WEIGHTINGS: dict[str, int] = {"raw": 0, "linear": 1, "quadratic": 2, "poly5": 3, "exp": 4}
"""The paper's temporal weightings, name -> kernel code."""


def weight(method: str, u: np.ndarray, *, k: float = DEFAULT_K) -> np.ndarray:
    """The weighting ``f(u)`` of ``method`` at normalised times ``u``."""
    if method not in WEIGHTINGS:
        raise ValueError(f"unknown weighting {method!r}; expected one of {list(WEIGHTINGS)}")
    u = np.asarray(u, dtype=np.float64)
    return {
        "raw": lambda: np.ones_like(u),
        "linear": lambda: 1.0 - u,
        "quadratic": lambda: (1.0 - u) ** 2,
        "poly5": lambda: (1.0 - u) ** 5,
        "exp": lambda: np.exp2(-k * u),
    }[method]()


@dataclass(frozen=True)
class CycleWindows:
    """Integration windows: cycle ``i`` covers ``[start_us[i], start_us[i] + window_us)``.

    ``warmup``: how many leading cycles are warm-up cycles (see
    :func:`asynhdr.segment.find_cycles`)."""

    start_us: np.ndarray
    window_us: float
    warmup: int = 0

    def __post_init__(self) -> None:
        s = np.asarray(self.start_us, dtype=np.int64)
        object.__setattr__(self, "start_us", s)
        if s.ndim != 1 or s.size == 0:
            raise ValueError("CycleWindows: start_us must be a non-empty 1-D array")
        if np.any(np.diff(s) <= 0):
            raise ValueError("CycleWindows: cycle starts must increase strictly")
        if not (self.window_us > 0 and math.isfinite(self.window_us)):
            raise ValueError(f"CycleWindows: window_us must be positive, got {self.window_us}")
        if s.size > 1 and self.window_us > float(np.min(np.diff(s))):
            raise ValueError(
                f"CycleWindows: window_us={self.window_us} is longer than the shortest cycle "
                f"({int(np.min(np.diff(s)))} µs)"
            )

    @property
    def n_cycles(self) -> int:
        return int(self.start_us.size)


# --------------------------------------------------------------------------- sums


_SUMS_CHUNK = 2048
"""Events per chunk in :func:`_sums_kernel`: each chunk's places and weights are worked
out first, then added in a loop of nothing else (one that keeps many of the scattered
adds in flight at once)."""


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _sums_kernel(x, y, p, t, starts, window_us, width, table, w_on, w_off, lo, hi, c0, row0,
                 acc, bad):
    """Scatter-add ``table[t - start] * w`` per cycle and pixel (events sorted by time),
    ``w = w_on`` for an ON event and ``-w_off`` for an OFF event.

    Events ``lo[k] .. hi[k]`` form part ``k``, summed in parallel into its own rows of
    ``acc`` (row ``row0[k] + cycle - c0[k]``), so no two threads add to one place.
    ``table`` holds the weight of every whole-µs offset in the window. ``bad[k]`` is the
    index of the first event of part ``k`` whose time steps back, or -1. Within a part
    the adds happen in event order.
    """
    ncyc = starts.shape[0]
    n_tab = table.shape[0]
    npx = acc.shape[1]
    flat = acc.reshape(-1)
    for k in nb.prange(lo.shape[0]):
        bad[k] = -1
        place = np.empty(_SUMS_CHUNK, dtype=np.int64)
        value = np.empty(_SUMS_CHUNK, dtype=np.float64)
        sign = np.empty(2, dtype=np.float64)
        sign[0] = -w_off
        sign[1] = w_on
        c = c0[k]
        i0 = lo[k]
        prev = t[i0 - 1] if i0 > 0 else t[i0]
        for a in range(i0, hi[k], _SUMS_CHUNK):
            m = 0
            for i in range(a, min(hi[k], a + _SUMS_CHUNK)):
                ti = t[i]
                if ti < prev:
                    bad[k] = i
                    break
                prev = ti
                while c + 1 < ncyc and ti >= starts[c + 1]:
                    c += 1
                dt = ti - starts[c]
                if dt < 0 or dt >= n_tab or dt >= window_us:
                    continue
                place[m] = (row0[k] + c - c0[k]) * npx + np.int64(y[i]) * width + x[i]
                value[m] = table[dt] * sign[np.int64(p[i] > 0)]
                m += 1
            for q in range(m):
                flat[place[q]] += value[q]
            if bad[k] >= 0:
                break


def _scatter_sums(ev: np.ndarray, windows: CycleWindows, width: int, npx: int,
                  table: np.ndarray, w_on: float, w_off: float) -> tuple[np.ndarray, bool]:
    """Run ``_sums_kernel`` over ``ev`` in parts; ``(sums, sorted)``."""
    n = int(ev.size)
    starts = windows.start_us
    parts = max(1, min(nb.get_num_threads(), n // 1_000_000)) if n else 1
    bounds = np.linspace(0, n, parts + 1).astype(np.int64)
    lo, hi = bounds[:-1], bounds[1:]
    t = ev["t"]
    first = np.where(lo < n, t[np.minimum(lo, max(n - 1, 0))], 0) if n else np.zeros(1, np.int64)
    last = np.where(hi > 0, t[np.maximum(hi - 1, 0)], 0) if n else np.zeros(1, np.int64)
    c0 = np.maximum(np.searchsorted(starts, first, side="right") - 1, 0).astype(np.int64)
    c1 = np.maximum(np.searchsorted(starts, last, side="right") - 1, 0).astype(np.int64)
    c1 = np.maximum(c1, c0)
    rows = c1 - c0 + 1
    row0 = np.concatenate(([0], np.cumsum(rows)[:-1])).astype(np.int64)
    acc = np.zeros((int(rows.sum()), npx), dtype=np.float64)
    bad = np.empty(parts, dtype=np.int64)
    _sums_kernel(ev["x"], ev["y"], ev["p"], t, starts, float(windows.window_us), width,
                 table, float(w_on), float(w_off), lo, hi, c0, row0, acc, bad)
    if (bad >= 0).any():
        return acc, False
    if c0[0] == 0 and rows[0] == windows.n_cycles:
        out = acc[:rows[0]]  # the first part spans every cycle: the others add to it
    else:
        out = np.zeros((windows.n_cycles, npx), dtype=np.float64)
        out[c0[0]:c1[0] + 1] += acc[:rows[0]]
    for k in range(1, parts):
        out[c0[k]:c1[k] + 1] += acc[row0[k]:row0[k] + rows[k]]
    return out, True


def _sorted_events(rec: Recording) -> np.ndarray:
    ev, moved = sort_events(rec.events)
    if moved:
        logger.warning("events were not sorted by time: %d moved by a stable sort", moved)
    return ev


def weighted_sums(
    rec: Recording,
    windows: CycleWindows,
    *,
    method: str = DEFAULT_METHOD,
    k: float = DEFAULT_K,
    c_on: float = 1.0,
    c_off: float = 1.0,
) -> np.ndarray:
    """``S = sum_i f(u_i) c_i p_i`` per cycle and pixel, float64 ``(n_cycles, height,
    width)``, with ``c_i = c_on`` for an ON event and ``c_off`` for an OFF event (by
    default 1: the paper's weighted sum; the nominal thresholds: the level ``c_on S_on -
    c_off S_off`` that Eq. 14 exponentiates).

    ``method`` is a weighting name, or ``"count"`` (ON events counted, times ``c_on``).
    Times are whole µs, so ``f`` is tabulated once over the window's offsets and each
    event costs one look-up and one add; parts of the stream are summed on separate
    threads. Unsorted events are sorted stably first (and reported).
    """
    if method not in WEIGHTINGS and method != "count":
        raise ValueError(f"unknown weighting {method!r}; expected one of "
                         f"{[*WEIGHTINGS, 'count']}")
    n_tab = math.ceil(windows.window_us)
    table = (np.ones(n_tab) if method == "count"
             else weight(method, np.arange(n_tab) / windows.window_us, k=k))
    w_off = 0.0 if method == "count" else c_off
    npx = rec.height * rec.width
    out, ok = _scatter_sums(rec.events, windows, rec.width, npx, table, c_on, w_off)
    if not ok:
        out, ok = _scatter_sums(_sorted_events(rec), windows, rec.width, npx, table, c_on,
                                w_off)
    return out.reshape(windows.n_cycles, rec.height, rec.width)


@nb.njit(cache=True, error_model="numpy")
def _first_on_kernel(x, y, p, t, starts, window_us, width, out):
    ncyc = starts.shape[0]
    c = 0
    inv = 1.0 / window_us
    for i in range(t.shape[0]):
        ti = t[i]
        while c + 1 < ncyc and ti >= starts[c + 1]:
            c += 1
        dt = ti - starts[c]
        if dt < 0 or p[i] <= 0:
            continue
        u = dt * inv
        if u >= 1.0:
            continue
        j = np.int64(y[i]) * width + x[i]
        if np.isnan(out[c, j]):
            out[c, j] = u


def first_on_phase(rec: Recording, windows: CycleWindows) -> np.ndarray:
    """Phase ``u`` in [0, 1) of each pixel's first ON event per cycle; NaN where none."""
    ev = _sorted_events(rec)
    out = np.full((windows.n_cycles, rec.height * rec.width), np.nan, dtype=np.float64)
    _first_on_kernel(ev["x"], ev["y"], ev["p"], ev["t"], windows.start_us,
                     float(windows.window_us), rec.width, out)
    return out.reshape(windows.n_cycles, rec.height, rec.width)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _interp(knots, values, x):
    """Piecewise-linear interpolation at ``x`` (knots increasing, x clamped)."""
    n = knots.shape[0]
    if x <= knots[0]:
        return values[0]
    if x >= knots[n - 1]:
        return values[n - 1]
    lo = 0
    hi = n - 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if knots[mid] <= x:
            lo = mid
        else:
            hi = mid
    w = (x - knots[lo]) / (knots[hi] - knots[lo])
    return values[lo] + (values[hi] - values[lo]) * w


@nb.njit(cache=True, error_model="numpy")
def _invert_offsets(x, y, p, t, starts, window_us, period_us, width, c_on, c_off, knots,
                    t1, t2, level, sums, out):
    """Per pixel and cycle, where its reference stood at the start (``out[c, j] = d``, the
    log above the start level). After event ``i`` the pixel's level has moved
    ``l_i = c_on n_on - c_off n_off`` from that reference: ``rho T1(u_i) + T2(u_i) =
    K e^(l_i)`` with one unknown ``K`` for the cycle. So ``x_i = T1 e^-l_i`` and
    ``y_i = T2 e^-l_i`` lie on the line ``y = K - rho x``, fitted in least squares
    (:func:`_invert_finish`)."""
    ncyc = starts.shape[0]
    c = 0
    t10 = t1[0]
    t20 = t2[0]
    for i in range(t.shape[0]):
        ti = t[i]
        while c + 1 < ncyc and ti >= starts[c + 1]:
            _invert_finish(c, sums, level, t10, t20, c_on, c_off, out)
            c += 1
        dt = ti - starts[c]
        if dt < 0 or dt >= window_us:
            continue
        j = np.int64(y[i]) * width + x[i]
        level[j] += c_on[j] if p[i] > 0 else -c_off[j]
        lv = level[j]
        if lv > 300.0 or lv < -300.0:  # the sums would overflow: nothing from this event
            continue
        u = (dt + 0.5) / period_us
        a = _interp(knots, t1, u)
        b = _interp(knots, t2, u)
        g = np.exp(-lv)
        if sums[j, 0] == 0.0:  # x and y from the first event's: no cancellation in the sums
            sums[j, 5] = a * g
            sums[j, 6] = b * g
        xi = a * g - sums[j, 5]
        yi = b * g - sums[j, 6]
        sums[j, 0] += 1.0
        sums[j, 1] += xi
        sums[j, 2] += yi
        sums[j, 3] += xi * xi
        sums[j, 4] += xi * yi
    _invert_finish(c, sums, level, t10, t20, c_on, c_off, out)


@nb.njit(cache=True, error_model="numpy")
def _invert_finish(c, sums, level, t10, t20, c_on, c_off, out):
    """Close cycle ``c`` of :func:`_invert_offsets`: each pixel's ``d`` into ``out[c]``;
    its sums and level reset. ``sums[j]``: events, sum x, sum y, sum x^2, sum xy (x and y
    less the first event's), the first event's x and y.

    The line ``y = K - rho x`` gives ``K = (rho T1(0) + T2(0)) e^d``: where the reference
    stood at the start, ``d`` above the start level; a pixel that sat between its
    thresholds has ``-c_on < d < c_off``, and ``d`` is held in that band. Without a line
    (one event, one ``x``, a slope of the wrong sign) ``d = 0``."""
    for j in range(level.shape[0]):
        level[j] = 0.0  # the next cycle counts from its own start, events or not
        n = sums[j, 0]
        if n == 0.0:
            continue
        sx, sy, sxx, sxy, x0, y0 = (sums[j, 1], sums[j, 2], sums[j, 3], sums[j, 4],
                                    sums[j, 5], sums[j, 6])
        det = n * sxx - sx * sx
        d = 0.0
        if n >= 2.0 and det > 1e-9 * n * sxx:
            rho = -(n * sxy - sx * sy) / det  # the slope of y = K - rho x
            k = (sy + rho * sx) / n + y0 + rho * x0
            start = rho * t10 + t20
            if rho > 0.0 and k > 0.0 and start > 0.0:
                d = min(max(np.log(k / start), -c_on[j]), c_off[j])
        out[c, j] = d
        for q in range(7):
            sums[j, q] = 0.0


@nb.njit(cache=True, error_model="numpy")
def _invert_kernel(x, y, p, t, starts, window_us, period_us, width, c_on, c_off, knots,
                   t1, t2, offset, n_on, n_off, last_cycle, acc, cnt):
    """Per event: the level reached since the cycle start is ``c_on n_on - c_off n_off``
    above the reference there, which stood ``offset[c, j]`` above the start level;
    ``rho T1(u) + T2(u) = e^(level + offset) (rho T1(0) + T2(0))`` gives one estimate of
    ``rho``. Accumulates ``log rho`` per cycle and pixel, each weighted by its inverse
    variance (the level's error grows with the events since the start; an event where
    the signal is back at its start level says little of ``rho``: ``0 / 0``), and the
    weights."""
    ncyc = starts.shape[0]
    c = 0
    t10 = t1[0]
    t20 = t2[0]
    for i in range(t.shape[0]):
        ti = t[i]
        while c + 1 < ncyc and ti >= starts[c + 1]:
            c += 1
        dt = ti - starts[c]
        if dt < 0 or dt >= window_us:
            continue
        j = np.int64(y[i]) * width + x[i]
        if last_cycle[j] != c:
            last_cycle[j] = c
            n_on[j] = 0
            n_off[j] = 0
        if p[i] > 0:
            n_on[j] += 1
        else:
            n_off[j] += 1
        level = c_on[j] * n_on[j] - c_off[j] * n_off[j] + offset[c, j]
        if level > 700.0:  # exp would overflow: no finite estimate from this event
            continue
        u = (dt + 0.5) / period_us
        e = np.exp(level)
        den = _interp(knots, t1, u) - e * t10
        num = e * t20 - _interp(knots, t2, u)
        if den > 0.0 and num > 0.0:
            # weighted by its inverse variance: d log rho / d level = e (T2(0) / num +
            # T1(0) / den) times the level's error, which grows with the resets since
            # the start as a random walk (variance in proportion to the events)
            w = 1.0 / ((e * (t20 / num + t10 / den)) ** 2 * (n_on[j] + n_off[j]))
            acc[c, j] += w * np.log(num / den)
            cnt[c, j] += w


# --------------------------------------------------------------------------- methods


@dataclass(frozen=True)
class _Params:
    """What every method gets besides the events: the nominal ON and OFF thresholds, the
    c-map's per-pixel ``gain`` on both (None without a c-map), ``L_const``, the rig (or
    None), ``k``."""

    k: float
    c_on: float
    c_off: float
    gain: np.ndarray | None
    l_const: float
    rig: Rig | None
    ml: dict[str, Any] | None = None

    def with_gain(self, a: np.ndarray) -> np.ndarray:
        """``a`` (``(..., height, width)``) times the c-map, in place."""
        if self.gain is not None:
            a *= self.gain.reshape(a.shape[-2:])
        return a

    def per_pixel(self, c: float, npx: int) -> np.ndarray:
        """A nominal threshold as ``(npx,)`` per-pixel thresholds (the c-map applied)."""
        return c * self.gain if self.gain is not None else np.full(npx, c)


def _from_level(level: np.ndarray, l_const: float) -> np.ndarray:
    """``L_const exp(level)`` as float32; a level beyond what float32 holds is saturated
    at its largest value (and counted in a warning)."""
    log_img = np.add(level, math.log(l_const), out=level)  # level is the caller's own
    top = float(log_img.max()) if log_img.size else 0.0
    if top > LOG_FLOAT32_MAX:
        logger.warning(
            "%d pixel-cycles have a level beyond what a float32 image holds (log radiance "
            "up to %.0f > %.2f: hundreds more ON than OFF events, a hot pixel or a window "
            "longer than a ramp); set to the largest float32 (3.4e38)",
            int(np.count_nonzero(log_img > LOG_FLOAT32_MAX)), top, LOG_FLOAT32_MAX)
        np.minimum(log_img, 89.0, out=log_img)  # exp(89) > FLT_MAX: saturated below
    img = np.exp(log_img, out=log_img)
    if top > LOG_FLOAT32_MAX:
        np.minimum(img, FLOAT32_MAX, out=img)
    return img.astype(np.float32)


def _paper(method: str) -> Callable[[Recording, CycleWindows, _Params], np.ndarray]:
    def run(rec: Recording, windows: CycleWindows, p: _Params) -> np.ndarray:
        s = weighted_sums(rec, windows, method=method, k=p.k, c_on=p.c_on, c_off=p.c_off)
        return _from_level(p.with_gain(s), p.l_const)
    return run


def _count(rec: Recording, windows: CycleWindows, p: _Params) -> np.ndarray:
    s = weighted_sums(rec, windows, method="count", c_on=p.c_on)
    return _from_level(p.with_gain(s), p.l_const)


def _ttfe(rec: Recording, windows: CycleWindows, p: _Params) -> np.ndarray:
    u = first_on_phase(rec, windows)
    rig = p.rig
    if rig is None:
        logger.warning("ttfe: no rig in the recording's metadata; assuming a linear ramp "
                       "(radiance proportional to 1/t)")
        with np.errstate(divide="ignore"):
            img = np.where(np.isnan(u), 0.0, 1.0 / np.maximum(u, 1e-9))
        return img.astype(np.float32)
    w1, w2 = rig.waveforms()
    ec = np.exp(p.per_pixel(p.c_on, rec.height * rec.width).reshape(rec.height, rec.width))
    # u is in the window's units; the waveforms are in cycle phase. Timestamps are
    # floored to whole µs: the crossing lies on average half a µs after its stamp.
    ph = (u * windows.window_us + 0.5) / rig.period_us
    valid = ~np.isnan(ph)
    phv = np.where(valid, ph, 0.0)
    t1u, t2u = w1(phv), w2(phv)
    t10, t20 = float(w1.values[0]), float(w2.values[0])
    den = t1u - ec * t10
    num = ec * t20 - t2u
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(valid & (den > 0), num / den, 0.0)
    return (p.l_const * np.maximum(rho, 0.0)).astype(np.float32)


def _invert(rec: Recording, windows: CycleWindows, p: _Params) -> np.ndarray:
    rig = p.rig
    if rig is None:
        raise ValueError("method 'invert' needs the rig's waveforms (a simulated recording, "
                         "or a rig given in the recording's metadata)")
    w1, w2 = rig.waveforms()
    knots = np.union1d(w1.phase, w2.phase)
    npx = rec.height * rec.width
    ev = _sorted_events(rec)
    c_on, c_off = p.per_pixel(p.c_on, npx), p.per_pixel(p.c_off, npx)
    t1, t2 = w1(knots), w2(knots)
    args = (ev["x"], ev["y"], ev["p"], ev["t"], windows.start_us, float(windows.window_us),
            float(rig.period_us), rec.width, c_on, c_off, knots, t1, t2)
    offset = np.zeros((windows.n_cycles, npx))
    _invert_offsets(*args, np.zeros(npx), np.zeros((npx, 7)), offset)
    offset[:windows.warmup] = 0.0  # a warm-up cycle's pixels start on the start level
    acc = np.zeros((windows.n_cycles, npx))
    cnt = np.zeros((windows.n_cycles, npx))
    _invert_kernel(*args, offset, np.zeros(npx, np.int64), np.zeros(npx, np.int64),
                   np.full(npx, -1, np.int64), acc, cnt)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.where(cnt > 0, np.exp(acc / np.where(cnt > 0, cnt, 1.0)), 0.0)
    return (p.l_const * rho).reshape(windows.n_cycles, rec.height, rec.width).astype(np.float32)


def _ml(rec: Recording, windows: CycleWindows, p: _Params) -> np.ndarray:
    from asynhdr.ml import reconstruct_ml

    if p.rig is None:
        raise ValueError("method 'ml' needs the rig (a simulated recording, or a rig file: "
                         "--rig)")
    return reconstruct_ml(rec, windows, rig=p.rig, l_const=p.l_const, cmap=p.gain,
                          threshold=p.c_on, **(p.ml or {}))


@dataclass(frozen=True)
class Method:
    """A reconstruction method.

    Attributes
    ----------
    name : the name it is chosen by.
    function : ``function(recording, windows, params) -> (n_cycles, height, width)``
        float32 images.
    radiometric : the image is linear in radiance (in the unit of ``L_const``).
    needs_rig : it needs the rig's waveforms (``ttfe`` falls back to ``1/u`` without).
    cmap : which c-map it takes: ``"weighting"`` (the map calibrated with its own
        weighting), ``"threshold"`` (the per-pixel threshold ratio, the raw map) or None.
    description : one line for listings.
    """

    name: str
    function: Callable[[Recording, CycleWindows, _Params], np.ndarray]
    radiometric: bool
    needs_rig: bool
    cmap: str | None
    description: str


METHODS: dict[str, Method] = {
    m.name: m for m in (
        Method("raw", _paper("raw"), False, False, "weighting", "f = 1, the raw integral"),
        Method("linear", _paper("linear"), False, False, "weighting", "f = 1 - t"),
        Method("quadratic", _paper("quadratic"), False, False, "weighting", "f = (1 - t)^2"),
        Method("poly5", _paper("poly5"), False, False, "weighting", "f = (1 - t)^5"),
        Method("exp", _paper("exp"), False, False, "weighting",
               "f = 2^(-k t), the paper's best"),
        Method("ttfe", _ttfe, True, False, "threshold",
               "time to the first ON event (EvTemMap)"),
        Method("count", _count, False, False, "threshold", "L_const exp(c_on n_on)"),
        Method("invert", _invert, True, True, "threshold",
               "every event inverted through the rig's waveforms (where the reference "
               "stood at the cycle's start fitted first)"),
        Method("ml", _ml, True, True, "threshold",
               "maximum likelihood under the simulator's pixel model, with an uncertainty"),
    )
}
"""Every reconstruction method by name (the paper's weightings first)."""


class CMapLike(Protocol):
    """What :func:`reconstruct` needs of a c-map (:class:`asynhdr.calibrate.CMap`)."""

    def for_method(self, method: str, *, k: float = ...) -> np.ndarray | None: ...


# --------------------------------------------------------------------------- context


def rig_of(source: Source | Recording) -> Rig | None:
    """The rig a recording was made with, from its metadata (simulated recordings, and
    files written by asynhdr, which keep it)."""
    d = as_source(source).metadata.get("rig")
    return Rig.from_metadata(d) if isinstance(d, dict) else None


def thresholds_of(source: Source | Recording) -> tuple[float, float, str]:
    """The nominal ``(c_on, c_off)`` of the recording's sensor and where they come from:
    the sensor in its metadata (simulated recordings), else the sensor preset the file's
    camera is (a DAVIS346 or an IMX636 named in the header), else
    :class:`~asynhdr.sensor.params.SensorParams`' defaults."""
    meta = as_source(source).metadata
    s = meta.get("sensor")
    if isinstance(s, dict) and "threshold_on" in s:
        c_on = float(s["threshold_on"])
        return c_on, float(s.get("threshold_off", c_on)), "the recording's sensor"
    names = " ".join(str(v) for v in (meta.get("camera"), meta.get("header")) if v).lower()
    for name, preset in PRESETS.items():
        if name not in ("ideal", "v2e") and name in names:
            return preset.threshold_on, preset.threshold_off, f"the {name} preset"
    return SensorParams.threshold_on, SensorParams.threshold_off, "the default"


RIG_PERIOD_TOLERANCE = 0.01
"""How far (a fraction) a recording's cycle length may be from its rig's period: clocks of a
signal generator and a camera agree far better; a rig file of another rig does not."""


def _check_rig_period(src: Source, cyc: Cycles, rig: Rig) -> None:
    """Refuse a rig whose period the recording's cycles contradict: their own length, or
    the trigger edges' spacing where the edges did not fit the rig's period and the cycles
    came from the event rate at that period instead."""
    lengths = [(float(cyc.period_us), {
        "triggers": "from its trigger edges", "rig": "from the rig it was made with",
        "event_rate": "from its event rate"}.get(cyc.source, cyc.source))]
    tr = src.triggers
    if cyc.source == "event_rate" and tr.size and np.count_nonzero(tr["rising"]) > 1:
        ids, counts = np.unique(tr["id"][tr["rising"]], return_counts=True)
        try:
            edges = cycles_from_triggers(tr, channel=int(ids[int(np.argmax(counts))]))
            lengths.insert(0, (float(edges.period_us), "from its trigger edges"))
        except ValueError:
            pass  # edges of no period: the event rate's cycles stand alone
    for length, how in lengths:
        if abs(length / rig.period_us - 1.0) > RIG_PERIOD_TOLERANCE:
            raise ValueError(
                f"{src.name}: its cycles are {length:.7g} µs long ({how}), but the rig's "
                f"period is {rig.period_us:.7g} µs: the rig does not describe this recording")


def windows_for(
    source: Source | Recording,
    *,
    window_us: float | None = None,
    period_us: float | None = None,
    single: bool = False,
    cycles: Cycles | None = None,
    rig: Rig | None = None,
) -> CycleWindows:
    """Integration windows of a recording.

    With ``single`` the whole recording is one cycle (a single ramp, as in
    temporal-mapping captures) starting at the last rising trigger edge at or before its
    first event, else at its first event. Otherwise the cycles of
    :func:`asynhdr.segment.find_cycles` (or ``cycles``), each integrated over
    ``window_us``: by default the rig's ramp (simulated recordings, or ``rig``: a rig
    file's, whose period also guides the cycle search) or the period, at most the
    shortest cycle. A rig whose period differs from the cycles' by more than
    :data:`RIG_PERIOD_TOLERANCE` is refused (``ValueError``).
    """
    src = as_source(source)
    if rig is not None and period_us is None and not single:
        period_us = float(rig.period_us)
    if single:
        sc = src.scan()
        if sc.events == 0:
            raise ValueError(f"{src.name}: no events: nothing to reconstruct")
        t0 = int(sc.min_t_us)  # type: ignore[arg-type]
        tr = sc.triggers
        opening = tr["t"][tr["rising"] & (tr["t"] <= t0)] if tr.size else tr["t"][:0]
        if opening.size:  # the ramp's own start, as the rig signalled it
            t0 = int(opening[-1])
        span = float(int(sc.max_t_us) - t0 + 1)  # type: ignore[arg-type]
        return CycleWindows(np.array([t0]), float(window_us or span))
    cyc = cycles if cycles is not None else find_cycles(src, period_us=period_us)
    starts = np.asarray(cyc.start_us, dtype=np.int64)
    if starts.size == 0:
        raise ValueError(f"{src.name}: no cycles to reconstruct")
    if rig is not None:
        _check_rig_period(src, cyc, rig)
    if window_us is None:
        rig = rig if rig is not None else rig_of(src)
        window_us = rig.ramp_us if rig is not None else float(cyc.period_us)
        if starts.size > 1:  # a fitted period can exceed a cycle by a fraction of a µs
            window_us = min(float(window_us), float(np.min(np.diff(starts))))
    return CycleWindows(starts, float(window_us), warmup=int(cyc.warmup))


def _params(
    src: Source,
    method: str,
    k: float,
    cmap: CMapLike | np.ndarray | None,
    threshold_on: float | None,
    threshold_off: float | None,
    l_const: float | None,
    rig: Rig | None = None,
    ml_options: dict[str, Any] | None = None,
) -> _Params:
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {list(METHODS)}")
    if not (k > 0 and math.isfinite(k)):
        raise ValueError(f"k must be positive, got {k}")
    rig = rig if rig is not None else rig_of(src)
    c_on0, c_off0, _ = thresholds_of(src)
    c_on = c_on0 if threshold_on is None else float(threshold_on)
    c_off = c_off0 if threshold_off is None else float(threshold_off)
    for nm, v in (("threshold_on", c_on), ("threshold_off", c_off)):
        if not (v > 0 and math.isfinite(v)):
            raise ValueError(f"{nm} must be positive, got {v}")
    lc = (rig.l_const if rig is not None else RELATIVE_L_CONST) if l_const is None \
        else float(l_const)
    if not (lc > 0 and math.isfinite(lc)):
        raise ValueError(f"l_const must be positive, got {lc}")
    cm: np.ndarray | None
    if cmap is None or isinstance(cmap, np.ndarray):
        cm = cmap
    else:
        cm = cmap.for_method(method, k=k)
    gain = None
    if cm is not None:
        if cm.shape != (src.height, src.width):
            raise ValueError(f"c-map shape {cm.shape} does not match the sensor "
                             f"({src.height}, {src.width})")
        gain = np.asarray(cm, dtype=np.float64).ravel()
    return _Params(k=float(k), c_on=c_on, c_off=c_off, gain=gain, l_const=lc, rig=rig,
                   ml=ml_options)


def reconstruct(
    source: Source | Recording,
    *,
    method: str = DEFAULT_METHOD,
    k: float = DEFAULT_K,
    cmap: CMapLike | np.ndarray | None = None,
    windows: CycleWindows | None = None,
    threshold_on: float | None = None,
    threshold_off: float | None = None,
    l_const: float | None = None,
    rig: Rig | None = None,
    ml_options: dict[str, Any] | None = None,
) -> np.ndarray:
    """One image per cycle of a whole recording, float32 ``(n_cycles, height, width)``.

    Parameters
    ----------
    source : a :class:`~asynhdr.source.Source` or a Recording (read whole; events are
        sorted stably by time first if they are not).
    method : one of :data:`METHODS`.
    k : the exponential weighting's ``k``.
    cmap : a c-map (its map for this method is used) or a ``(height, width)`` array
        multiplying both thresholds per pixel; ``None`` for no correction.
    windows : integration windows (default: :func:`windows_for`).
    threshold_on, threshold_off : the nominal contrast thresholds (default: the
        recording's sensor, see :func:`thresholds_of`).
    l_const : the reference radiance (default: the rig's, else :data:`RELATIVE_L_CONST`).
    rig : the rig (default: the recording's metadata), e.g. from a rig file
        (:mod:`asynhdr.io.rigfile`).
    ml_options : for ``ml``: keyword options of :func:`asynhdr.ml.reconstruct_ml`
        (``sensor``, ``thresholds``, ``defects``, ``settled_start``, ``out``: a dict that
        receives the uncertainty and the flags).

    Returns
    -------
    Images in the unit of ``l_const`` (the scene's unit for simulated recordings).
    """
    src = as_source(source)
    p = _params(src, method, k, cmap, threshold_on, threshold_off, l_const, rig, ml_options)
    windows = windows or windows_for(src, rig=p.rig)
    return METHODS[method].function(src.read(), windows, p)


class CycleImages:
    """A recording reconstructed cycle by cycle, holding one cycle's events at a time (two
    for ``ml``'s first two cycles, fitted together: :func:`asynhdr.ml.reconstruct_ml`).

    Made by :func:`reconstruct_cycles`. ``windows``, ``metadata`` and the geometry are
    known before the first image; iterating yields ``(cycle, start_us, image)`` with the
    image exactly as :func:`reconstruct` gives it for that cycle from the whole
    recording, and calls ``progress("reconstruct", cycles_done, n_cycles)``.
    """

    def __init__(self, source: Source, windows: CycleWindows, method: str, params: _Params,
                 progress: Progress | None) -> None:
        self.source = source
        self.windows = windows
        self.method = METHODS[method]
        self.metadata = source.metadata
        self.width = source.width
        self.height = source.height
        self._params = params
        self._progress = progress

    def __len__(self) -> int:
        return self.windows.n_cycles

    @property
    def n_events(self) -> int:
        """Events in the recording (all of them, inside the windows or not)."""
        return self.source.scan().events

    def __iter__(self) -> Iterator[tuple[int, int, np.ndarray]]:
        w = self.windows
        stops = np.ceil(w.start_us + w.window_us).astype(np.int64)  # t < start + window
        once = _OncePerMessage()  # what holds for every cycle is logged once
        logger.addFilter(once)
        params = self._params
        ml = self.method.name == "ml"
        if ml and "learner" not in (params.ml or {}):
            # what ml learns of the thresholds goes from one cycle to the next, as it does
            # within one call over the whole recording (asynhdr.ml.LearnedThresholds)
            from asynhdr.ml import LearnedThresholds

            params = dataclasses.replace(params, ml={**(params.ml or {}),
                                                     "learner": LearnedThresholds()})
        held: list[Window] = []
        try:
            for win in self.source.windows(w.start_us, stops):
                held.append(win)
                if ml and win.i == 0 and len(self) > 1:
                    # ml fits the first cycle again once the second has taught the
                    # thresholds (asynhdr.ml.reconstruct_ml): the two go in one call
                    continue
                yield from self._images(held, params)
                held = []
            yield from self._images(held, params)
        finally:
            logger.removeFilter(once)

    def _images(self, wins: list[Window], params: _Params
                ) -> Iterator[tuple[int, int, np.ndarray]]:
        """The images of consecutive windows ``wins``, from one call of the method."""
        if not wins:
            return
        w = self.windows
        ev, trig = wins[0].events, wins[0].triggers
        for a, b in itertools.pairwise(wins):
            # windows may overlap: what the one before holds is not added twice
            ev = np.concatenate([ev, b.events[b.events["t"] >= a.stop_us]])
            trig = np.concatenate([trig, b.triggers[b.triggers["t"] >= a.stop_us]])
        ev, _ = sort_events(ev)
        rec = Recording(events=ev, width=self.width, height=self.height, triggers=trig,
                        metadata=self.metadata)
        cyc = CycleWindows(np.array([win.start_us for win in wins]), w.window_us,
                           warmup=sum(int(win.i < w.warmup) for win in wins))
        imgs = self.method.function(rec, cyc, params)
        sink = (params.ml or {}).get("out")
        whole = dict(sink) if sink is not None and len(wins) > 1 else None
        for k, win in enumerate(wins):
            if whole is not None and sink is not None:
                # the out dict holds the yielded cycle's outputs, as with one call each
                sink.update({key: v[k:k + 1] if isinstance(v, np.ndarray) else v
                             for key, v in whole.items()})
            yield win.i, win.start_us, imgs[k]
            if self._progress is not None:
                self._progress("reconstruct", win.i + 1, len(self))


class _OncePerMessage(logging.Filter):
    """Let each distinct log message through once."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[tuple[int, str]] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        key = (record.levelno, record.getMessage())
        if key in self.seen:
            return False
        self.seen.add(key)
        return True


def reconstruct_cycles(
    source: Source | Recording,
    *,
    method: str = DEFAULT_METHOD,
    k: float = DEFAULT_K,
    cmap: CMapLike | np.ndarray | None = None,
    windows: CycleWindows | None = None,
    window_us: float | None = None,
    period_us: float | None = None,
    single: bool = False,
    threshold_on: float | None = None,
    threshold_off: float | None = None,
    l_const: float | None = None,
    progress: Progress | None = None,
    rig: Rig | None = None,
    ml_options: dict[str, Any] | None = None,
) -> CycleImages:
    """Plan the reconstruction of a recording, to run cycle by cycle (memory flat in the
    recording's size): the cycles come from :func:`windows_for` (one streaming pass over
    the source, two more for the event rate without triggers); iterating the result
    reads the source once more, one cycle at a time. Arguments as in
    :func:`reconstruct` and :func:`windows_for`."""
    src = as_source(source)
    p = _params(src, method, k, cmap, threshold_on, threshold_off, l_const, rig, ml_options)
    if windows is None:
        src.scan(progress=progress)
        windows = windows_for(src, window_us=window_us, period_us=period_us, single=single,
                              rig=p.rig)
    return CycleImages(src, windows, method, p, progress)

