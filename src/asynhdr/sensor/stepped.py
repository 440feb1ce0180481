"""The time-stepped engine: the pixel state integrated on a time grid.

For what has no closed form (any sampled waveform, a moving scene, the photoreceptor
low-pass) each pixel's state is advanced step by step over every cycle. Sensor
irradiance at time ``t`` of a cycle that starts at ``t_c`` (Wu et al. 2024, Eq. 9)::

    I(t) = k_lens * (T1(u) * L(t) + T2(u) * L_const),      u = (t - t_c) / period_us

with ``L(t)`` the scene radiance, linear in time between frames (held before the first
and after the last). The grid has a step of ``dt_us``; the knots where either
waveform turns (a local extremum) and the frame times are added to it, so the grid
never cuts the peak off a piecewise-linear input.

Pixel model, per pixel and step ``[t_a, t_b]`` (``h = t_b - t_a``):

- input ``x = log I``;
- photoreceptor (``cutoff_hz > 0``): a first-order low-pass on the log signal,
  ``dy/dt = (x - y) / tau``, with ``tau = tau_ref (I_ref + I_dark) / (I + I_dark)``
  (capped at ``tau_max_us``; :meth:`SensorParams.tau_us`) at the step's mean
  irradiance. The update is the exact solution for an input linear within the step::

      y_b = y_a + (x_a - y_a) g + (x_b - x_a) (1 - g tau / h),    g = 1 - exp(-h / tau)

  Without the low-pass ``y = x`` and the step is interpolated in irradiance (linear in
  time between the step's ends, as the piecewise-linear input is), which agrees with
  the exact engine (:mod:`asynhdr.sensor.exact`);
- events: while ``y >= ref + c_on`` an ON event, ``ref += c_on``; while
  ``y <= ref - c_off`` an OFF event, ``ref -= c_off``. The event time is where the
  straight line between the step's ends crosses the level, not the step's end. A
  crossing of an exact level counts (relative tolerance ``1e-12`` in irradiance,
  ``1e-12`` absolute in log units);
- reset noise: each new reference gets ``reset_noise_sigma * N(0, 1)``, drawn with
  :func:`asynhdr.sensor._rng.hash_normal` from ``(seed, pixel, event number, 0)``:
  the same seed gives the same events on any number of threads;
- refractory period (``refractory_us > 0``): after an event the pixel ignores its input
  until ``t_event + refractory_us``; there the reference becomes ``y`` at that instant
  (plus the reset noise of that event). No two events of a pixel are closer than
  ``refractory_us``.

Initial state: ``y = ref = x`` at the start of the first cycle (an adapted pixel).
Event timestamps are floored to whole µs, then to ``timestamp_resolution_us``.

Cost is pixels x steps, whatever the event count. Per pixel, a first pass fills the
step tables in loops without calls, which vectorise: irradiance; with the low-pass,
``log(I_b / I_a)`` and the weights ``g``, ``1 - g tau / h`` by short series
(:func:`_lowpass_tables`; ``log`` is called only on steps where the irradiance changes
by more than about 13 %, and every 256 steps to re-anchor the running sum). A second,
sequential pass advances ``y`` (one multiply-add on the dependency chain) and compares
it with the two levels; events and refractory ends take the slow path. Event slots are
sized per pixel from the log variation of its input; a pixel that fires more (reset
noise) makes the cycle run again from the saved state with the exact counts (the
kernel is deterministic), so no event is dropped.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numba as nb
import numpy as np

from asynhdr.events import EVENT_DTYPE
from asynhdr.rig import Rig, Waveform
from asynhdr.sensor._rng import hash_normal
from asynhdr.sensor.exact import _gather_sorted
from asynhdr.sensor.params import SensorParams

__all__ = [
    "SteppedState",
    "initial_state",
    "simulate_cycle_stepped",
    "simulate_stepped",
    "step_times_us",
]

logger = logging.getLogger(__name__)

_EPS = 1e-12
_NO_REFRACTORY = -1e300
_MIN_STEP_US = 1e-6
"""Grid points closer than this (µs) are merged."""


# ----------------------------------------------------------------------------- kernels


@nb.njit(cache=True, inline="always")
def _levels(r, con, coff, lowpass):
    """Detection levels (with the tolerance) in the engine's domain for reference ``r``."""
    if lowpass:
        return r + con - _EPS, r - coff + _EPS
    return np.exp(r + con) * (1.0 - _EPS), np.exp(r - coff) * (1.0 + _EPS)


@nb.njit(cache=True, error_model="numpy")
def _pixel_irradiance(frames, fa, fw, a1, b2, p, out):
    """``out[k] = a1[k] L_p(t_k) + b2[k]``: the pixel's irradiance at every grid point."""
    nst = a1.shape[0]
    if frames.shape[1] == 1:
        lum = frames[p, 0]
        for k in range(nst):
            out[k] = a1[k] * lum + b2[k]
    else:
        for k in range(nst):
            i = fa[k]
            la = frames[p, i]
            out[k] = a1[k] * (la + fw[k] * (frames[p, i + 1] - la)) + b2[k]


@nb.njit(cache=True, inline="always")
def _dlog_series(i0, i1):
    """``log(i1 / i0) = 2 atanh(d)``, ``d = (i1 - i0) / (i1 + i0)``, by six terms of its
    series: relative error under 3e-15 for ``|d| <= 1/16``; NaN beyond."""
    d = (i1 - i0) / (i1 + i0)
    d2 = d * d
    d4 = d2 * d2
    sr = 2.0 * d * ((1.0 + d2 * (1.0 / 3.0)) + d4 * ((1.0 / 5.0 + d2 * (1.0 / 7.0))
                                                    + d4 * (1.0 / 9.0 + d2 * (1.0 / 11.0))))
    return sr if abs(d) <= 0.0625 else np.nan


@nb.njit(cache=True, inline="always")
def _p6(q):
    """``P(q) = (1 - exp(-q)) / q = sum_n (-q)^n / (n + 1)!`` to six terms: relative
    error under 2e-11 for ``0 <= q <= 1/16``."""
    q2 = q * q
    return (1.0 - q * 0.5) + q2 * ((1.0 / 6.0 - q * (1.0 / 24.0))
                                   + q2 * (1.0 / 120.0 - q * (1.0 / 720.0)))


@nb.njit(cache=True, inline="always")
def _p12(q):
    """``P(q)`` to twelve terms: relative error under 3e-10 for ``0 <= q <= 1``."""
    q2 = q * q
    q4 = q2 * q2
    return ((1.0 - q * 0.5) + q2 * (1.0 / 6.0 - q * (1.0 / 24.0))) + q4 * (
        ((1.0 / 120.0 - q * (1.0 / 720.0)) + q2 * (1.0 / 5040.0 - q * (1.0 / 40320.0)))
        + q4 * ((1.0 / 362880.0 - q * (1.0 / 3628800.0))
                + q2 * (1.0 / 39916800.0 - q * (1.0 / 479001600.0))))


@nb.njit(cache=True, inline="always")
def _exp_neg(q):
    """``exp(-q)`` for ``q >= 0`` as ``exp(-q / 64)^64`` (series to thirteen terms,
    ``q`` capped at 40): relative error of ``1 - exp(-q)`` under 1e-10 for ``q >= 1``."""
    r = (q if q < 40.0 else 40.0) * (1.0 / 64.0)
    r2 = r * r
    r4 = r2 * r2
    e = ((1.0 - r) + r2 * (1.0 / 2.0 - r * (1.0 / 6.0))) + r4 * (
        ((1.0 / 24.0 - r * (1.0 / 120.0)) + r2 * (1.0 / 720.0 - r * (1.0 / 5040.0)))
        + r4 * ((1.0 / 40320.0 - r * (1.0 / 362880.0))
                + r2 * (1.0 / 3628800.0 - r * (1.0 / 39916800.0))
                + r4 * (1.0 / 479001600.0 - r * (1.0 / 6227020800.0))))
    for _ in range(6):
        e = e * e
    return e


@nb.njit(cache=True, error_model="numpy", fastmath={"contract"})
def _lowpass_tables(irr, s, h_max, tau_inv, dark_irr, qmin_per_us, dl, gg, ww):
    """Per step ``k`` (from grid point ``k - 1`` to ``k``): ``dl ~ log(I_k / I_(k-1))``
    (NaN where the caller must take ``log``), ``g = 1 - exp(-q)`` and ``w = 1 - g / q``
    with ``q = h / tau(I_mean)``, ``tau`` capped (``q >= h / tau_max``).

    No calls, so the loops vectorise. ``g = q P``, ``w = 1 - P`` (:func:`_p6` where
    every ``q`` of the pixel is at most 1/16, :func:`_p12` where at most 1); where some
    ``q`` exceeds 1, those steps take ``g = 1 - exp(-q)`` (:func:`_exp_neg`).
    """
    nst = irr.shape[0]
    dl[0] = 0.0
    gg[0] = 0.0
    ww[0] = 0.0
    i_max = irr[0]
    for k in range(1, nst):
        i_max = max(i_max, irr[k])
    q_top = h_max * max((i_max + dark_irr) * tau_inv, qmin_per_us)
    if q_top <= 0.0625:
        for k in range(1, nst):
            i0 = irr[k - 1]
            i1 = irr[k]
            dl[k] = _dlog_series(i0, i1)
            h = s[k] - s[k - 1]
            q = max(h * (0.5 * (i0 + i1) + dark_irr) * tau_inv, h * qmin_per_us)
            pp = _p6(q)
            gg[k] = q * pp
            ww[k] = 1.0 - pp
    elif q_top <= 1.0:
        for k in range(1, nst):
            i0 = irr[k - 1]
            i1 = irr[k]
            dl[k] = _dlog_series(i0, i1)
            h = s[k] - s[k - 1]
            q = max(h * (0.5 * (i0 + i1) + dark_irr) * tau_inv, h * qmin_per_us)
            pp = _p12(q)
            gg[k] = q * pp
            ww[k] = 1.0 - pp
    else:
        for k in range(1, nst):
            i0 = irr[k - 1]
            i1 = irr[k]
            dl[k] = _dlog_series(i0, i1)
            h = s[k] - s[k - 1]
            q = max(h * (0.5 * (i0 + i1) + dark_irr) * tau_inv, h * qmin_per_us)
            pp = _p12(q)
            big = q > 1.0
            g = 1.0 - _exp_neg(q) if big else q * pp
            gg[k] = g
            ww[k] = (1.0 - g / q) if big else 1.0 - pp


_CHUNK = 32
"""Pixels per task of the parallel loop (each task allocates its step tables once)."""


@nb.njit(cache=True, parallel=True, fastmath={"contract"})
def _cycle_kernel(frames, fa, fw, s, a1, b2, c_on, c_off, y, ref, refr_end, nev,
                  lowpass, tau_num, dark_irr, tau_max_us, refr_us, sigma, seed,
                  offsets, slot_t, slot_p, counts, period_us):
    """One cycle of every pixel; events into slots ``offsets[p] ..`` (counted past them).

    ``frames`` is ``(n_pixels, n_frames)``; grid point ``k`` (time ``s[k]`` µs from the
    cycle start) sees radiance ``frames[p, fa[k]] + fw[k] (frames[p, fa[k] + 1] - ..)``
    (or ``frames[p, 0]`` when there is one frame) and irradiance ``a1[k] L + b2[k]``.
    State updated in place: ``y`` (log), ``ref`` (log), ``refr_end`` (µs, relative to
    the cycle start on entry, to the next cycle's start on exit), ``nev`` (events so
    far). ``counts[p]`` is the number of events, which may exceed the slots: the caller
    then runs the cycle again from the saved state with more room.

    Per pixel: first the step tables (irradiance; with the low-pass the log steps and
    filter weights), then the sequential pass over the steps (state and events).
    """
    npix = c_on.shape[0]
    nst = s.shape[0]
    tau_inv = 1.0 / tau_num if lowpass else 0.0
    qmin_per_us = 1.0 / tau_max_us if lowpass else 0.0
    use_refr = refr_us > 0.0
    noisy = sigma > 0.0
    nchunk = (npix + _CHUNK - 1) // _CHUNK
    h_max = 0.0
    for k in range(1, nst):
        h_max = max(h_max, s[k] - s[k - 1])
    for c in nb.prange(nchunk):
        irr = np.empty(nst)
        dl = np.empty(nst if lowpass else 1)
        gg = np.empty(nst if lowpass else 1)
        ww = np.empty(nst if lowpass else 1)
        for p in range(c * _CHUNK, min(npix, (c + 1) * _CHUNK)):
            _pixel_irradiance(frames, fa, fw, a1, b2, p, irr)
            if lowpass:
                _lowpass_tables(irr, s, h_max, tau_inv, dark_irr, qmin_per_us, dl, gg, ww)
            con = c_on[p]
            coff = c_off[p]
            r = ref[p]
            te = refr_end[p]
            ne = nev[p]
            o = offsets[p]
            cap = offsets[p + 1] - o
            n = 0
            if lowpass:
                x0 = np.log(irr[0])
                v0 = y[p]
            else:
                x0 = 0.0
                v0 = irr[0]
            hi, lo = _levels(r, con, coff, lowpass)
            s0 = s[0]
            for k in range(nst):
                s1 = s[k]
                if lowpass:
                    dk = dl[k]
                    if (k & 255) == 0 or dk != dk:
                        x1 = np.log(irr[k])  # a big step, or an anchor of the running sum
                    else:
                        x1 = x0 + dk
                    g = gg[k]
                    # y_b = y_a (1 - g) + x_a g + (x_b - x_a) w: one multiply-add on y
                    v1 = v0 * (1.0 - g) + (x0 * g + (x1 - x0) * ww[k])
                else:
                    x1 = 0.0
                    v1 = irr[k]
                if te > s0 or v1 >= hi or v1 <= lo:
                    ta = s0
                    va = v0
                    while True:
                        if te > ta:
                            if te > s1:
                                break  # still refractory at the step's end
                            if s1 > ta:
                                va = va + (v1 - va) * ((te - ta) / (s1 - ta))
                            ta = te
                            te = _NO_REFRACTORY
                            r = va if lowpass else np.log(va)
                            if noisy:
                                r += sigma * hash_normal(seed, p, ne - 1, 0)
                            hi, lo = _levels(r, con, coff, lowpass)
                        if v1 >= hi:
                            up = True
                            lvl = r + con
                        elif v1 <= lo:
                            up = False
                            lvl = r - coff
                        else:
                            break
                        target = lvl if lowpass else np.exp(lvl)
                        d = v1 - va
                        f = (target - va) / d if d != 0.0 else 0.0
                        f = min(max(f, 0.0), 1.0)
                        tc = ta + f * (s1 - ta)
                        if n < cap:
                            slot_t[o + n] = np.int32(np.floor(tc))
                            slot_p[o + n] = 1 if up else -1
                        n += 1
                        va = va + f * d
                        ta = tc
                        r = lvl
                        if use_refr:
                            te = tc + refr_us
                        else:
                            if noisy:
                                r += sigma * hash_normal(seed, p, ne, 0)
                            hi, lo = _levels(r, con, coff, lowpass)
                        ne += 1
                v0 = v1
                x0 = x1
                s0 = s1
            counts[p] = n
            ref[p] = r
            nev[p] = ne
            refr_end[p] = te - period_us if te > _NO_REFRACTORY else _NO_REFRACTORY
            y[p] = v0 if lowpass else np.log(irr[nst - 1])


@nb.njit(cache=True, inline="always")
def _irr(frames, fa, fw, a_k, b_k, k, p, static, l_static):
    """Irradiance of pixel ``p`` at grid point ``k``: ``A_k L(t_k) + B_k``."""
    if static:
        return a_k * l_static + b_k
    i = fa[k]
    la = frames[p, i]
    lb = frames[p, i + 1]
    return a_k * (la + fw[k] * (lb - la)) + b_k


@nb.njit(cache=True, parallel=True)
def _estimate_slots(frames, fa, fw, a1, b2, samples, c_on, c_off, y, ref, lowpass,
                    sigma, out):
    """Slots per pixel: the log variation at the grid points ``samples`` over the
    smaller threshold, with margins (the fill counts past them; see the kernel)."""
    npix = c_on.shape[0]
    static = frames.shape[1] == 1
    for p in nb.prange(npix):
        l_static = frames[p, 0]
        k0 = samples[0]
        xp = np.log(_irr(frames, fa, fw, a1[k0], b2[k0], k0, p, static, l_static))
        start = y[p] if lowpass else xp
        tv = abs(start - xp) + abs(ref[p] - start)
        for j in range(1, samples.shape[0]):
            k = samples[j]
            x = np.log(_irr(frames, fa, fw, a1[k], b2[k], k, p, static, l_static))
            tv += abs(x - xp)
            xp = x
        cmin = min(c_on[p], c_off[p])
        c_eff = max(0.25 * cmin, cmin - 3.0 * sigma)
        out[p] = np.int64(1.25 * tv / c_eff) + 4


# ----------------------------------------------------------------------------- state


@dataclass(eq=False)
class SteppedState:
    """Per-pixel state of the stepped engine, carried from cycle to cycle.

    Attributes
    ----------
    y : float64 ``(n_pixels,)``: photoreceptor output ``y`` (log irradiance) at
        ``t_us``.
    ref : float64 ``(n_pixels,)``: reference log level.
    refractory_end_us : float64 ``(n_pixels,)``: end of the running refractory period,
        µs relative to ``t_us`` (a huge negative number when none runs).
    n_events : int64 ``(n_pixels,)``: events emitted so far (the reset-noise counter).
    t_us : start time of the next cycle (µs).
    """

    y: np.ndarray
    ref: np.ndarray
    refractory_end_us: np.ndarray
    n_events: np.ndarray
    t_us: int

    def copy(self) -> SteppedState:
        """An independent copy."""
        return SteppedState(self.y.copy(), self.ref.copy(), self.refractory_end_us.copy(),
                            self.n_events.copy(), int(self.t_us))


# ----------------------------------------------------------------------------- inputs


@dataclass(frozen=True, eq=False)
class _Scene:
    frames: np.ndarray  # (n_pixels, n_frames), float64
    times_us: np.ndarray  # (n_frames,), float64, absolute
    width: int
    height: int


def _as_scene(radiance: np.ndarray, frame_times_us: np.ndarray | None) -> _Scene:
    rad = np.asarray(radiance)
    if rad.ndim not in (2, 3):
        raise ValueError("stepped engine: radiance must be (height, width) or "
                         f"(n_frames, height, width), got shape {rad.shape}")
    if not (np.issubdtype(rad.dtype, np.floating) or np.issubdtype(rad.dtype, np.integer)):
        raise ValueError(f"stepped engine: radiance must be numeric, got dtype {rad.dtype}")
    if rad.ndim == 2:
        rad = rad[None]
    n_frames, height, width = rad.shape
    if n_frames < 1 or height < 1 or width < 1:
        raise ValueError(f"stepped engine: radiance is empty (shape {rad.shape})")
    if width > 65535 or height > 65535:
        raise ValueError(f"stepped engine: sensor too large for uint16 coordinates: "
                         f"{width}x{height}")
    bad = ~np.isfinite(rad)
    if bad.any():
        raise ValueError(f"stepped engine: radiance has {int(bad.sum())} NaN or infinite "
                         "values")
    if (rad < 0).any():
        raise ValueError(f"stepped engine: radiance has {int((rad < 0).sum())} negative "
                         "values")
    if frame_times_us is None:
        if n_frames > 1:
            raise ValueError(f"stepped engine: radiance has {n_frames} frames but "
                             "frame_times_us is None; give one time (µs) per frame")
        times = np.zeros(1, dtype=np.float64)
    else:
        times = np.asarray(frame_times_us, dtype=np.float64)
        if times.shape != (n_frames,):
            raise ValueError(f"stepped engine: frame_times_us must have one time per frame "
                             f"({n_frames}), got shape {times.shape}")
        if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
            raise ValueError("stepped engine: frame_times_us must be finite and strictly "
                             "increasing")
    frames = np.ascontiguousarray(rad.reshape(n_frames, -1).T, dtype=np.float64)
    return _Scene(frames, times, width, height)


def _as_thresholds(c_on: np.ndarray, c_off: np.ndarray, scene: _Scene
                   ) -> tuple[np.ndarray, np.ndarray]:
    shape = (scene.height, scene.width)
    out = []
    for name, c in (("c_on", c_on), ("c_off", c_off)):
        a = np.asarray(c, dtype=np.float64)
        if a.shape != shape:
            raise ValueError(f"stepped engine: {name} must have the scene's shape {shape} "
                             f"(height, width), got {a.shape}")
        if not np.all(np.isfinite(a)) or np.any(a <= 0):
            raise ValueError(f"stepped engine: {name} must be finite and positive")
        out.append(np.ascontiguousarray(a.ravel()))
    return out[0], out[1]


def _turning_phases(w: Waveform) -> np.ndarray:
    """Interior knots where the waveform's slope changes sign (its local extrema)."""
    sgn = np.sign(np.diff(w.values))
    j = np.flatnonzero(sgn[1:] != sgn[:-1]) + 1
    return w.phase[j]


def step_times_us(rig: Rig, *, dt_us: float,
                  extra_us: np.ndarray | None = None) -> np.ndarray:
    """The grid of one cycle, µs from its start: ``0, dt, 2 dt, .., period_us``, plus
    the waveforms' turning knots and ``extra_us`` (times within the cycle)."""
    if not (math.isfinite(dt_us) and dt_us > 0):
        raise ValueError(f"stepped engine: dt_us must be a positive number, got {dt_us}")
    period = float(rig.period_us)
    n = math.ceil(period / dt_us - 1e-9)
    grid = np.minimum(np.arange(n + 1, dtype=np.float64) * dt_us, period)
    w1, w2 = rig.waveforms()
    parts = [grid, _turning_phases(w1) * period, _turning_phases(w2) * period]
    if extra_us is not None:
        e = np.asarray(extra_us, dtype=np.float64)
        parts.append(e[(e > 0) & (e < period)])
    s = np.unique(np.concatenate(parts))
    keep = np.ones(s.size, dtype=bool)
    keep[1:] = np.diff(s) > _MIN_STEP_US
    keep[-1] = True
    s = s[keep]
    if s.size >= 2 and s[-2] >= period - _MIN_STEP_US:
        s = np.delete(s, -2)
    s[0] = 0.0
    s[-1] = period
    return s


def _frame_weights(times_us: np.ndarray, t_abs: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Frame index ``i`` and weight ``w`` so that ``L = (1 - w) L_i + w L_{i+1}``."""
    nf = times_us.size
    if nf == 1:
        return np.zeros(t_abs.size, dtype=np.int64), np.zeros(t_abs.size)
    i = np.clip(np.searchsorted(times_us, t_abs, side="right") - 1, 0, nf - 2)
    w = (t_abs - times_us[i]) / (times_us[i + 1] - times_us[i])
    return i.astype(np.int64), np.clip(w, 0.0, 1.0)


@dataclass(frozen=True, eq=False)
class _Grid:
    s: np.ndarray
    a1: np.ndarray
    b2: np.ndarray
    fa: np.ndarray
    fw: np.ndarray
    samples: np.ndarray


def _make_grid(rig: Rig, scene: _Scene, t_start_us: int, dt_us: float) -> _Grid:
    extra = None
    if scene.times_us.size > 1:
        extra = scene.times_us - t_start_us
    s = step_times_us(rig, dt_us=dt_us, extra_us=extra)
    w1, w2 = rig.waveforms()
    u = s / rig.period_us
    a1 = rig.k_lens * w1(u)
    b2 = rig.k_lens * rig.l_const * w2(u)
    fa, fw = _frame_weights(scene.times_us, t_start_us + s)
    l_min = float(scene.frames.min())
    if not float(np.min(a1 * l_min + b2)) > 0:
        raise ValueError(
            "stepped engine: the sensor irradiance reaches zero during the cycle (T2 closes "
            "fully while some pixels have zero radiance); give the panels a leakage floor "
            "(contrast ratio)")
    # grid points for the slot estimate: about 512 evenly, plus the turning knots and
    # frame times (where a piecewise-linear input turns)
    stride = max(1, (s.size - 1) // 512)
    marks: list[np.ndarray] = [np.arange(0, s.size, stride), np.array([s.size - 1])]
    special = np.concatenate([_turning_phases(w1), _turning_phases(w2)]) * rig.period_us
    if extra is not None:
        special = np.concatenate([special, extra])
    marks.append(np.searchsorted(s, special[(special > 0) & (special < rig.period_us)]))
    samples = np.unique(np.concatenate(marks)).astype(np.int64)
    return _Grid(s, a1, b2, fa, fw, samples)


def _initial(scene: _Scene, rig: Rig, t0_us: int) -> SteppedState:
    w1, w2 = rig.waveforms()
    fa, fw = _frame_weights(scene.times_us, np.array([float(t0_us)]))
    f = scene.frames
    lum = f[:, 0] if f.shape[1] == 1 else f[:, fa[0]] + fw[0] * (f[:, fa[0] + 1] - f[:, fa[0]])
    irr = rig.k_lens * (float(w1(0.0)) * lum + float(w2(0.0)) * rig.l_const)
    if not np.all(irr > 0):
        raise ValueError("stepped engine: zero sensor irradiance at the start of the first "
                         "cycle; give the panels a leakage floor (contrast ratio)")
    x = np.log(irr)
    npix = x.size
    return SteppedState(y=x.copy(), ref=x.copy(),
                        refractory_end_us=np.full(npix, _NO_REFRACTORY),
                        n_events=np.zeros(npix, dtype=np.int64), t_us=int(t0_us))


def _check_common(rig: Rig, sensor: SensorParams, seed: int) -> None:
    if sensor.refractory_us >= rig.period_us:
        raise ValueError(f"stepped engine: refractory_us ({sensor.refractory_us}) must be "
                         f"shorter than the cycle (period_us={rig.period_us})")
    if int(seed) != seed or not 0 <= seed < 2**64:
        raise ValueError(f"stepped engine: seed must be a whole number in [0, 2**64), got "
                         f"{seed}")


# ----------------------------------------------------------------------------- cycles


def _run_cycle(scene: _Scene, grid: _Grid, state: SteppedState, c_on: np.ndarray,
               c_off: np.ndarray, rig: Rig, sensor: SensorParams, seed: int) -> np.ndarray:
    npix = c_on.size
    lowpass = sensor.cutoff_hz > 0
    tau_num = sensor.tau_ref_us * (sensor.cutoff_irradiance + sensor.dark_irradiance)
    sigma = float(sensor.reset_noise_sigma)
    slots = np.empty(npix, dtype=np.int64)
    _estimate_slots(scene.frames, grid.fa, grid.fw, grid.a1, grid.b2, grid.samples, c_on,
                    c_off, state.y, state.ref, lowpass, sigma, slots)
    saved = state.copy()
    counts = np.empty(npix, dtype=np.int64)
    for attempt in range(2):
        offsets = np.zeros(npix + 1, dtype=np.int64)
        np.cumsum(slots, out=offsets[1:])
        slot_t = np.empty(int(offsets[-1]), dtype=np.int32)
        slot_p = np.empty(int(offsets[-1]), dtype=np.int8)
        _cycle_kernel(scene.frames, grid.fa, grid.fw, grid.s, grid.a1, grid.b2, c_on, c_off,
                      state.y, state.ref, state.refractory_end_us, state.n_events, lowpass,
                      float(tau_num), float(sensor.dark_irradiance), float(sensor.tau_max_us),
                      float(sensor.refractory_us), sigma, np.uint64(seed), offsets, slot_t,
                      slot_p, counts, float(rig.period_us))
        over = counts > slots
        if not over.any():
            break
        if attempt == 1:
            raise RuntimeError("stepped engine: the event count changed when a cycle was "
                               "run again from the same state")
        logger.debug("stepped engine: %d pixels exceeded their event slots; running the "
                     "cycle again with the exact counts", int(over.sum()))
        # the kernel is deterministic: the counts just measured are the exact need
        slots = counts.copy()
        state.y[:] = saved.y
        state.ref[:] = saved.ref
        state.refractory_end_us[:] = saved.refractory_end_us
        state.n_events[:] = saved.n_events
    out = np.empty(int(counts.sum()), dtype=EVENT_DTYPE)
    _gather_sorted(offsets, counts, slot_t, slot_p, scene.width, np.int64(state.t_us),
                   np.int64(rig.period_us + 1), out)
    step = int(sensor.timestamp_resolution_us)
    if step > 1:
        out["t"] = (out["t"] // step) * step
    state.t_us = int(state.t_us + rig.period_us)
    return out


def initial_state(
    radiance: np.ndarray,
    *,
    rig: Rig,
    t0_us: int = 0,
    frame_times_us: np.ndarray | None = None,
) -> SteppedState:
    """The adapted pixel array at ``t0_us``: ``y = ref = log I(t0_us)``.

    ``radiance`` and ``frame_times_us`` as in :func:`simulate_stepped`.
    """
    return _initial(_as_scene(radiance, frame_times_us), rig, int(t0_us))


def simulate_cycle_stepped(
    state: SteppedState,
    radiance: np.ndarray,
    *,
    rig: Rig,
    sensor: SensorParams,
    c_on: np.ndarray,
    c_off: np.ndarray,
    seed: int,
    dt_us: float = 5.0,
    frame_times_us: np.ndarray | None = None,
) -> np.ndarray:
    """One cycle, starting at ``state.t_us``; ``state`` is advanced in place.

    Calling this ``n`` times from :func:`initial_state` gives the events of
    :func:`simulate_stepped` cycle by cycle (same arguments, same events).

    Returns
    -------
    Events (``EVENT_DTYPE``) of the cycle, sorted by ``t`` (stable: among equal times,
    pixel order, then each pixel's own order), ``t`` in ``[state.t_us, state.t_us +
    period_us]`` before the call.
    """
    _check_common(rig, sensor, seed)
    scene = _as_scene(radiance, frame_times_us)
    con, coff = _as_thresholds(c_on, c_off, scene)
    if state.y.shape != (scene.width * scene.height,):
        raise ValueError(f"stepped engine: state has {state.y.shape[0]} pixels, the scene "
                         f"{scene.width * scene.height}")
    grid = _make_grid(rig, scene, int(state.t_us), dt_us)
    return _run_cycle(scene, grid, state, con, coff, rig, sensor, int(seed))


def simulate_stepped(
    radiance: np.ndarray,
    *,
    rig: Rig,
    sensor: SensorParams,
    n_cycles: int,
    c_on: np.ndarray,
    c_off: np.ndarray,
    seed: int,
    dt_us: float = 5.0,
    frame_times_us: np.ndarray | None = None,
    t0_us: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Events of ``n_cycles`` cycles from the time-stepped pixel model (module docstring).

    Parameters
    ----------
    radiance : ``(height, width)`` static scene, or ``(n_frames, height, width)`` moving
        scene, in the unit of ``rig.l_const``; linear, non-negative.
    rig : the optics: waveforms (any sampled ones, non-monotone allowed), ``k_lens``,
        ``l_const``, ``period_us``.
    sensor : pixel parameters; used here: ``reset_noise_sigma``, ``refractory_us``,
        ``cutoff_hz`` (with ``cutoff_irradiance``, ``dark_irradiance``, ``tau_max_us``)
        and ``timestamp_resolution_us``. Thresholds come from ``c_on``/``c_off``; noise
        events, latency, jitter and the readout are left to the caller.
    n_cycles : number of cycles, the first starting at ``t0_us``.
    c_on, c_off : float64 ``(height, width)`` frozen per-pixel thresholds (log units).
    seed : 64-bit seed of the reset-noise draws.
    dt_us : integration step (µs).
    frame_times_us : one time (µs, same clock as ``t0_us``) per frame of a moving scene;
        radiance is linear in time between frames and held outside them.
    t0_us : start of the first cycle (µs).
    progress : called as ``progress(done_cycles, n_cycles)`` after each cycle.

    Returns
    -------
    Events (``EVENT_DTYPE``) sorted by ``t`` (stable: pixel order, then time within a
    pixel).
    """
    if int(n_cycles) != n_cycles or n_cycles < 1:
        raise ValueError(f"stepped engine: n_cycles must be a whole number >= 1, got "
                         f"{n_cycles}")
    if int(t0_us) != t0_us:
        raise ValueError(f"stepped engine: t0_us must be a whole number of µs, got {t0_us}")
    _check_common(rig, sensor, seed)
    scene = _as_scene(radiance, frame_times_us)
    con, coff = _as_thresholds(c_on, c_off, scene)
    state = _initial(scene, rig, int(t0_us))
    chunks: list[np.ndarray] = []
    grid: _Grid | None = None
    for k in range(int(n_cycles)):
        if grid is None or scene.times_us.size > 1:
            grid = _make_grid(rig, scene, int(state.t_us), dt_us)
        chunks.append(_run_cycle(scene, grid, state, con, coff, rig, sensor, int(seed)))
        if progress is not None:
            progress(k + 1, int(n_cycles))
    events = chunks[0] if len(chunks) == 1 else np.concatenate(chunks)
    logger.info("stepped engine: %d events over %d cycles on %dx%d (dt_us=%g)",
                events.size, n_cycles, scene.width, scene.height, dt_us)
    return events
