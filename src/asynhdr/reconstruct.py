"""Reconstruct one image per modulation cycle from the events.

The paper's temporal-weighted reconstruction (Wu et al. 2024, Eq. 14)::

    img(x, y) = L_const * exp( c * sum_i f(t_i) * p_i )      over the pixel's events

with ``t`` normalised to the integration window of the cycle (0 at the cycle start,
1 at the end of the ramp) and a decreasing weight ``f`` chosen by name:

=============  ===========================  ==========================
name           ``f(t)``                     paper
=============  ===========================  ==========================
``raw``        ``1``                        raw integral
``linear``     ``1 - t``                    linear weighted
``quadratic``  ``(1 - t)^2``                quadratic
``poly5``      ``(1 - t)^5``                high-order polynomial
``exp``        ``2^(-k t)`` (``k = 10``)    exponential (Eq. 20)
=============  ===========================  ==========================

A c-map (per-pixel threshold correction, see ``asynhdr.calibrate``) multiplies ``c``
pixel by pixel. The paper's ``img`` is monotone in radiance but not linear in it.

Baselines:

- ``ttfe`` (time to first event, the EvTemMap approach): grey from the time ``u`` of
  each pixel's first ON event in the cycle. With the rig's waveforms known, the first
  ON fires when ``T1(u) L + T2(u) L_const = e^c (T1(0) L + T2(0) L_const)``, so::

      L = L_const * (e^c T2(0) - T2(u)) / (T1(u) - e^c T1(0))

  which is linear in radiance (the event time is taken half a µs after its floored
  timestamp). Without a rig, ``L`` is taken ``∝ 1/u`` (a linear ramp).
  Pixels with no ON event in the window are 0.
- ``count``: ``L_const * exp(c * n_on)`` from the number of ON events alone.

Radiometric inversion (``invert``): every event is an equation for ``L``. After
``n_on`` ON and ``n_off`` OFF events since the cycle start, the pixel's irradiance has
moved by ``c_on n_on - c_off n_off`` in log, so with the rig's known waveforms::

    L = L_const * (e^level T2(0) - T2(u)) / (T1(u) - e^level T1(0))

per event; the image is the geometric mean of these estimates over the cycle's
events. It is linear in radiance (up to noise) and uses the c-map's per-pixel
thresholds when given. Pixels with no usable event are 0.

Maximum likelihood (``ml``, :mod:`asynhdr.ml`): each pixel's events inverted together
through the simulator's own pixel model (thresholds, dead time, reset noise, jitter,
photoreceptor, background events); linear radiance with a per-pixel uncertainty, NaN
where a pixel has no information. It needs the rig and the sensor model (the recording's
metadata, or a rig file, :mod:`asynhdr.io.rigfile`).

Per-pixel sums are one pass over the time-sorted events (numba), scatter-adding into
``(n_cycles, height * width)``.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numba as nb
import numpy as np

from asynhdr.events import Recording, sort_events
from asynhdr.rig import Rig

if TYPE_CHECKING:
    from asynhdr.calibrate import CMap
    from asynhdr.segment import Cycles

__all__ = [
    "METHODS",
    "WEIGHTINGS",
    "CycleWindows",
    "FileReconstruction",
    "first_on_phase",
    "plan_windows",
    "reconstruct",
    "reconstruct_file",
    "weight",
    "weighted_sums",
    "windows_for",
]

logger = logging.getLogger(__name__)

WEIGHTINGS: dict[str, int] = {"raw": 0, "linear": 1, "quadratic": 2, "poly5": 3, "exp": 4}
"""The paper's temporal weightings, name -> kernel code."""

METHODS: tuple[str, ...] = (*WEIGHTINGS, "ttfe", "count", "invert", "ml")
"""Every reconstruction method, selected by name."""

DEFAULT_K = 10.0
"""The exponential weighting's ``k`` (the paper chose 10)."""

DEFAULT_THRESHOLD = 0.2
"""Contrast threshold assumed when a recording does not say (v2e's nominal 0.2)."""


@nb.njit(cache=True, inline="always")
def _w(code: int, u: float, k: float) -> float:
    if code == 0:
        return 1.0
    if code == 1:
        return 1.0 - u
    if code == 2:
        return (1.0 - u) * (1.0 - u)
    if code == 3:
        v = 1.0 - u
        v2 = v * v
        return v2 * v2 * v
    return 2.0 ** (-k * u)


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
    """Integration windows: cycle ``i`` covers ``[start_us[i], start_us[i] + window_us)``."""

    start_us: np.ndarray
    window_us: float

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


@nb.njit(cache=True, parallel=True)
def _sums_kernel(x, y, p, t, starts, window_us, width, table, on_only, lo, hi, c0, row0,
                 acc, bad):
    """Scatter-add ``table[t - start] * p`` per cycle and pixel (events sorted by time).

    Events ``lo[k] .. hi[k]`` form part ``k``, summed in parallel into its own rows of
    ``acc`` (row ``row0[k] + cycle - c0[k]``), so no two threads add to one place.
    ``table`` holds the weight of every whole-µs offset in the window. ``bad[k]`` is the
    index of the first event of part ``k`` whose time steps back, or -1.
    """
    ncyc = starts.shape[0]
    n_tab = table.shape[0]
    for k in nb.prange(lo.shape[0]):
        bad[k] = -1
        c = c0[k]
        i0 = lo[k]
        prev = t[i0 - 1] if i0 > 0 else t[i0]
        for i in range(i0, hi[k]):
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
            pol = p[i]
            j = np.int64(y[i]) * width + x[i]
            r = row0[k] + c - c0[k]
            if on_only:
                if pol > 0:
                    acc[r, j] += 1.0
            else:
                acc[r, j] += table[dt] * pol


def _scatter_sums(ev: np.ndarray, windows: CycleWindows, width: int, npx: int,
                  table: np.ndarray, on_only: bool) -> tuple[np.ndarray, bool]:
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
                 table, on_only, lo, hi, c0, row0, acc, bad)
    if (bad >= 0).any():
        return acc, False
    if parts == 1 and rows[0] == windows.n_cycles and c0[0] == 0:
        return acc, True
    out = np.zeros((windows.n_cycles, npx), dtype=np.float64)
    for k in range(parts):
        out[c0[k]:c1[k] + 1] += acc[row0[k]:row0[k] + rows[k]]
    return out, True


@nb.njit(cache=True)
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


def _sorted_events(rec: Recording) -> np.ndarray:
    ev, moved = sort_events(rec.events)
    if moved:
        logger.warning("events were not sorted by time: %d moved by a stable sort", moved)
    return ev


def weighted_sums(
    rec: Recording,
    windows: CycleWindows,
    *,
    method: str = "exp",
    k: float = DEFAULT_K,
) -> np.ndarray:
    """``S = sum_i f(u_i) p_i`` per cycle and pixel, float64 ``(n_cycles, height, width)``.

    ``method`` is a weighting name, or ``"count"`` (the number of ON events). Times are
    whole µs, so ``f`` is tabulated once over the window's offsets and each event costs
    one look-up and one add; parts of the stream are summed on separate threads.
    Unsorted events are sorted stably first (and reported).
    """
    if method not in WEIGHTINGS and method != "count":
        raise ValueError(f"unknown weighting {method!r}; expected one of "
                         f"{[*WEIGHTINGS, 'count']}")
    n_tab = math.ceil(windows.window_us)
    table = (np.ones(n_tab) if method == "count"
             else weight(method, np.arange(n_tab) / windows.window_us, k=k))
    npx = rec.height * rec.width
    out, ok = _scatter_sums(rec.events, windows, rec.width, npx, table, method == "count")
    if not ok:
        out, ok = _scatter_sums(_sorted_events(rec), windows, rec.width, npx, table,
                                method == "count")
    return out.reshape(windows.n_cycles, rec.height, rec.width)


def first_on_phase(rec: Recording, windows: CycleWindows) -> np.ndarray:
    """Phase ``u`` in [0, 1) of each pixel's first ON event per cycle; NaN where none."""
    ev = _sorted_events(rec)
    out = np.full((windows.n_cycles, rec.height * rec.width), np.nan, dtype=np.float64)
    _first_on_kernel(ev["x"], ev["y"], ev["p"], ev["t"], windows.start_us,
                     float(windows.window_us), rec.width, out)
    return out.reshape(windows.n_cycles, rec.height, rec.width)


def rig_of(rec: Recording) -> Rig | None:
    """The rig a simulated recording was made with, from its metadata."""
    return _rig_from(rec.metadata)


def _rig_from(metadata: dict[str, Any]) -> Rig | None:
    d = metadata.get("rig")
    return Rig.from_metadata(d) if isinstance(d, dict) else None


def threshold_of(rec: Recording) -> float:
    """The nominal contrast threshold of the recording's sensor (``DEFAULT_THRESHOLD``
    when the metadata does not say)."""
    s = rec.metadata.get("sensor")
    if isinstance(s, dict) and "threshold_on" in s:
        return float(s["threshold_on"])
    return DEFAULT_THRESHOLD


def windows_for(
    rec: Recording,
    *,
    window_us: float | None = None,
    period_us: float | None = None,
    single: bool = False,
    rig: Rig | None = None,
) -> CycleWindows:
    """Integration windows from the recording's rising trigger edges.

    With ``single`` the whole recording is one cycle starting at its first event (a
    single ramp, as in temporal-mapping captures).

    Otherwise as :func:`plan_windows`, the cycles coming, when there are neither
    triggers nor a simulated rig, from the event rate
    (:func:`asynhdr.segment.cycles_from_events`).
    """
    if single:
        if rec.events.size == 0:
            raise ValueError("recording has no events: nothing to reconstruct")
        t = rec.events["t"]
        t0 = int(t.min())
        span = float(int(t.max()) - t0 + 1)
        return CycleWindows(np.array([t0]), float(window_us or span))

    def from_rate(period: float | None) -> Cycles:
        from asynhdr.segment import cycles_from_events

        return cycles_from_events(_sorted_events(rec), period_us=period)

    meta = rec.metadata if rig is None else dict(rec.metadata, rig=rig.to_metadata())
    return plan_windows(rec.triggers, meta, from_rate, window_us=window_us,
                        period_us=period_us)


def plan_windows(
    triggers: np.ndarray,
    metadata: dict[str, Any],
    from_rate: Callable[[float | None], Cycles],
    *,
    window_us: float | None = None,
    period_us: float | None = None,
) -> CycleWindows:
    """Integration windows of a recording from what it holds besides its events.

    Cycle starts: the rising trigger edges when there are any
    (:func:`asynhdr.segment.cycles_from_triggers`), else, for a simulated recording,
    its rig's cycles (``metadata``), else ``from_rate(period_us)``, the cycles of the
    event-rate envelope (logged with the confidence). The window defaults to the rig's
    ramp (simulated recordings) or the period (at most the shortest cycle).
    """
    rig = _rig_from(metadata)
    rising = triggers["t"][triggers["rising"]] if triggers.size else np.zeros(0, np.int64)
    if rising.size:
        from asynhdr.segment import cycles_from_triggers

        cyc = cycles_from_triggers(triggers,
                                   period_us=period_us or (rig.period_us if rig else None))
        starts = np.asarray(cyc.start_us, dtype=np.int64)
        period = float(cyc.period_us)
    elif rig is not None:
        n = int(metadata.get("n_cycles", 1))
        starts = rig.cycle_starts_us(n, t0_us=int(metadata.get("t0_us", 0)))
        period = float(rig.period_us)
    else:
        from asynhdr.segment import MIN_RATE_CONFIDENCE

        cyc = from_rate(period_us)
        if cyc.confidence < MIN_RATE_CONFIDENCE:
            hint = ("treat it as one ramp (--single)" if period_us is not None else
                    "give the period (period_us, --period-us) or treat it as one ramp "
                    "(--single)")
            raise ValueError(
                f"no trigger edges, and no periodic bursts in the event rate (best guess: "
                f"period {cyc.period_us:.1f} µs, confidence {cyc.confidence:.2f} < "
                f"{MIN_RATE_CONFIDENCE}): the recording may not be modulated; {hint}")
        logger.warning("no triggers: cycles from the event rate (period %.1f µs, "
                       "confidence %.2f)", cyc.period_us, cyc.confidence)
        starts = np.asarray(cyc.start_us, dtype=np.int64)
        period = float(cyc.period_us)
    if window_us is None:
        window_us = rig.ramp_us if rig is not None else period
        if starts.size > 1:  # a fitted period can exceed a cycle by a fraction of a µs
            window_us = min(float(window_us), float(np.min(np.diff(starts))))
    return CycleWindows(starts, float(window_us))


def _paper(method: str) -> Callable[..., np.ndarray]:
    def run(rec: Recording, windows: CycleWindows, *, k: float, threshold: float,
            l_const: float, cmap: np.ndarray | None, rig: Rig | None) -> np.ndarray:
        s = weighted_sums(rec, windows, method=method, k=k)
        scale = threshold if cmap is None else threshold * cmap
        return (l_const * np.exp(scale * s)).astype(np.float32)
    return run


def _count(rec: Recording, windows: CycleWindows, *, k: float, threshold: float,
           l_const: float, cmap: np.ndarray | None, rig: Rig | None) -> np.ndarray:
    s = weighted_sums(rec, windows, method="count")
    scale = threshold if cmap is None else threshold * cmap
    return (l_const * np.exp(scale * s)).astype(np.float32)


def _ttfe(rec: Recording, windows: CycleWindows, *, k: float, threshold: float,
          l_const: float, cmap: np.ndarray | None, rig: Rig | None) -> np.ndarray:
    u = first_on_phase(rec, windows)
    if rig is None:
        logger.warning("ttfe: no rig in the recording's metadata; assuming a linear ramp "
                       "(radiance proportional to 1/t)")
        with np.errstate(divide="ignore"):
            img = np.where(np.isnan(u), 0.0, 1.0 / np.maximum(u, 1e-9))
        return img.astype(np.float32)
    w1, w2 = rig.waveforms()
    c = threshold if cmap is None else threshold * cmap
    ec = np.exp(c)
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
    return (l_const * np.maximum(rho, 0.0)).astype(np.float32)


@nb.njit(cache=True, inline="always")
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


@nb.njit(cache=True)
def _invert_kernel(x, y, p, t, starts, window_us, period_us, width, c_on, c_off, knots,
                   t1, t2, n_on, n_off, last_cycle, acc, cnt):
    """Per event: the level reached since the cycle start is ``c_on n_on - c_off n_off``;
    ``rho T1(u) + T2(u) = e^level (rho T1(0) + T2(0))`` gives one estimate of ``rho``.
    Accumulates ``log rho`` per cycle and pixel."""
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
        level = c_on[j] * n_on[j] - c_off[j] * n_off[j]
        u = (dt + 0.5) / period_us
        e = np.exp(level)
        den = _interp(knots, t1, u) - e * t10
        num = e * t20 - _interp(knots, t2, u)
        if den > 0.0 and num > 0.0:
            acc[c, j] += np.log(num / den)
            cnt[c, j] += 1.0


def _invert(rec: Recording, windows: CycleWindows, *, k: float, threshold: float,
            l_const: float, cmap: np.ndarray | None, rig: Rig | None) -> np.ndarray:
    if rig is None:
        raise ValueError("method 'invert' needs the rig's waveforms (a simulated recording, "
                         "or a rig given in the recording's metadata)")
    w1, w2 = rig.waveforms()
    knots = np.union1d(w1.phase, w2.phase)
    c = np.full(rec.height * rec.width, threshold) if cmap is None else \
        (threshold * np.asarray(cmap, dtype=np.float64)).ravel()
    npx = rec.height * rec.width
    acc = np.zeros((windows.n_cycles, npx))
    cnt = np.zeros((windows.n_cycles, npx))
    ev = _sorted_events(rec)
    _invert_kernel(ev["x"], ev["y"], ev["p"], ev["t"], windows.start_us,
                   float(windows.window_us), float(rig.period_us), rec.width, c, c, knots,
                   w1(knots), w2(knots), np.zeros(npx, np.int64), np.zeros(npx, np.int64),
                   np.full(npx, -1, np.int64), acc, cnt)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.where(cnt > 0, np.exp(acc / np.maximum(cnt, 1.0)), 0.0)
    return (l_const * rho).reshape(windows.n_cycles, rec.height, rec.width).astype(np.float32)


def _ml(rec: Recording, windows: CycleWindows, *, k: float, threshold: float,
        l_const: float, cmap: np.ndarray | None, rig: Rig | None,
        extra: dict[str, Any] | None = None) -> np.ndarray:
    from asynhdr.ml import reconstruct_ml

    if rig is None:
        raise ValueError("method 'ml' needs the rig (a simulated recording, or --rig with a "
                         "rig file)")
    return reconstruct_ml(rec, windows, rig=rig, l_const=l_const, cmap=cmap,
                          threshold=threshold, **(extra or {}))


_TABLE: dict[str, Callable[..., np.ndarray]] = {
    **{m: _paper(m) for m in WEIGHTINGS},
    "count": _count,
    "ttfe": _ttfe,
    "invert": _invert,
    "ml": _ml,
}


def reconstruct(
    rec: Recording,
    *,
    method: str = "exp",
    k: float = DEFAULT_K,
    cmap: CMap | np.ndarray | None = None,
    windows: CycleWindows | None = None,
    threshold: float | None = None,
    l_const: float | None = None,
    rig: Rig | None = None,
    ml_options: dict[str, Any] | None = None,
) -> np.ndarray:
    """One image per cycle, float32 ``(n_cycles, height, width)``.

    Parameters
    ----------
    rec : the recording (events are sorted stably by time first if they are not).
    method : one of ``METHODS``.
    k : the exponential weighting's ``k``.
    cmap : a ``CMap`` (its map for this method is used) or a ``(height, width)`` array
        multiplying the threshold per pixel; ``None`` for no correction.
    windows : integration windows (default: from the triggers, see ``windows_for``).
    threshold : the nominal contrast threshold ``c`` (default: the recording's sensor).
    l_const : the reference radiance (default: the rig's, else 1).
    rig : the rig (default: the recording's metadata), e.g. from a rig file.
    ml_options : for ``ml``: keyword options of :func:`asynhdr.ml.reconstruct_ml`
        (``sensor``, ``thresholds``, ``out``: a dict that receives the uncertainty).

    Returns
    -------
    Images in the unit of ``l_const`` (the scene's unit for simulated recordings).
    """
    if method not in _TABLE:
        raise ValueError(f"unknown method {method!r}; expected one of {list(METHODS)}")
    if not (k > 0 and math.isfinite(k)):
        raise ValueError(f"k must be positive, got {k}")
    rig = rig if rig is not None else rig_of(rec)
    windows = windows or windows_for(rec, rig=rig)
    c = threshold_of(rec) if threshold is None else float(threshold)
    if not (c > 0 and math.isfinite(c)):
        raise ValueError(f"threshold must be positive, got {c}")
    lc = (rig.l_const if rig is not None else 1.0) if l_const is None else float(l_const)
    cm: np.ndarray | None
    if cmap is None:
        cm = None
    elif isinstance(cmap, np.ndarray):
        cm = cmap
    else:
        cm = cmap.for_method(method, k=k)
    if cm is not None and cm.shape != (rec.height, rec.width):
        raise ValueError(f"c-map shape {cm.shape} does not match the sensor "
                         f"({rec.height}, {rec.width})")
    kwargs: dict[str, Any] = dict(k=float(k), threshold=c, l_const=lc, cmap=cm, rig=rig)
    if method == "ml":
        kwargs["extra"] = ml_options
    return _TABLE[method](rec, windows, **kwargs)


class FileReconstruction:
    """Reconstruct a recording file cycle by cycle, holding one cycle's events at a time.

    Made by :func:`reconstruct_file`. ``windows`` and ``metadata`` are known before the
    first image; iterating yields ``(cycle, start_us, image)`` with the image exactly as
    :func:`reconstruct` gives it for that cycle from the whole recording.
    """

    def __init__(self, path: str | os.PathLike[str], windows: CycleWindows,
                 metadata: dict[str, Any], width: int, height: int, n_events: int,
                 options: dict[str, Any], read: dict[str, Any]) -> None:
        self.path = path
        self.windows = windows
        self.metadata = metadata
        self.width = width
        self.height = height
        self.n_events = n_events
        """Events in the file (all of them, inside the windows or not)."""
        self._options = options
        self._read = read

    def __len__(self) -> int:
        return self.windows.n_cycles

    def __iter__(self) -> Iterator[tuple[int, int, np.ndarray]]:
        from asynhdr.io.windows import iter_windows

        w = self.windows
        starts = w.start_us
        stops = np.ceil(starts + w.window_us).astype(np.int64)  # t < start + window
        once = _OncePerMessage()  # what holds for every cycle is logged once
        logger.addFilter(once)
        try:
            for win in iter_windows(self.path, starts, stops, **self._read):
                ev, _ = sort_events(win.events)
                rec = Recording(events=ev, width=self.width, height=self.height,
                                triggers=win.triggers, metadata=self.metadata)
                one = CycleWindows(np.array([win.start_us]), w.window_us)
                yield win.i, win.start_us, reconstruct(rec, windows=one, **self._options)[0]
        finally:
            logger.removeFilter(once)


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


def reconstruct_file(
    path: str | os.PathLike[str],
    *,
    method: str = "exp",
    k: float = DEFAULT_K,
    cmap: CMap | np.ndarray | None = None,
    window_us: float | None = None,
    period_us: float | None = None,
    threshold: float | None = None,
    l_const: float | None = None,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
    progress: Callable[[int], None] | None = None,
    rig: Rig | None = None,
    ml_options: dict[str, Any] | None = None,
) -> FileReconstruction:
    """Plan the reconstruction of a recording file, to run cycle by cycle.

    One streaming pass over the file finds its geometry, triggers and metadata; the
    cycles come as in :func:`windows_for` (the event-rate case takes two more
    streaming passes, :func:`asynhdr.segment.cycles_from_file`). Iterating the result
    reads the file once more, one cycle at a time (memory flat in file size). Arguments
    as in :func:`reconstruct` and :func:`asynhdr.io.open_recording`; ``progress(n)``
    is called with the events scanned so far during the first pass.
    """
    from asynhdr.io import scan_recording
    from asynhdr.segment import cycles_from_file

    if method not in _TABLE:
        raise ValueError(f"unknown method {method!r}; expected one of {list(METHODS)}")
    read: dict[str, Any] = dict(width=width, height=height, time_unit=time_unit)
    scan = scan_recording(path, progress=progress, **read)
    info = scan.info
    if info["width"] is None or info["height"] is None:
        raise ValueError(f"{path}: no sensor geometry; give width and height")
    head_meta = info["header"].get("metadata")
    metadata = dict(head_meta) if isinstance(head_meta, dict) else {}
    if rig is not None:  # a rig file: its cycles, its ramp, its waveforms
        metadata["rig"] = rig.to_metadata()

    def from_rate(period: float | None) -> Cycles:
        return cycles_from_file(path, period_us=period, scan=scan, **read)

    windows = plan_windows(scan.triggers, metadata, from_rate, window_us=window_us,
                           period_us=period_us)
    options: dict[str, Any] = dict(method=method, k=k, cmap=cmap, threshold=threshold,
                                   l_const=l_const, rig=rig, ml_options=ml_options)
    return FileReconstruction(path, windows, metadata, int(info["width"]),
                              int(info["height"]), int(info["events"]), options, read)
