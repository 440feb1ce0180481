"""Maximum-likelihood radiance from each pixel's events, under the simulator's own model.

The forward model is the one of :mod:`asynhdr.sensor.pixel`: a pixel's comparator reads
its signal ``V(t; g)`` (``g = ln L``), the log irradiance
``ln(k_lens (T1(t) L + T2(t) L_const))`` of the rig's *transmitted* waveforms (panels
included), or the photoreceptor's low-pass output of it
(:mod:`asynhdr.sensor.photoreceptor`, the same integrator, tabulated here over a
log-radiance grid). An event fires when ``V`` leaves the band ``(ref - c_off, ref + c_on)``
around the pixel's reference; its timestamp is ``floor(t_c + jitter + latency)``; the
reference is then taken at the end of the dead time, ``t_e = t_f + latency + refractory``,
with reset noise (or, for a pixel without dead time, jitter or reset noise, moves to the
level crossed).

Per pixel and cycle the events ``(t_i, p_i)`` give one equation each, conditional on the
previous event (the chain the pixel itself follows)::

    r_i = V(t_c,i; g) - ref_i - p_i c_{p_i}  ~  N(0, s_i^2)

    t_c,i = t_i + res/2 - latency                  (the crossing, from the stamp)
    ref_i = V(t_e,i-1; g)                          (t_e = t_i-1 + res/2 + refractory)
    ref_i = V(0; g) + u + sum_{k<i} p_k c_{p_k}    (exact reset: the level walks by c)
    ref_1 = V(0; g) + u                            (the first event of the cycle)
    s_i^2 = sigma_reset^2 + V'(t_c,i)^2 (sigma_jitter^2 + res^2/12)
            + V'(t_e,i-1)^2 res^2 / 12             (the walk: V'(t_c,i)^2 res^2/12 only)

The walk holds for a pixel whose reference is exactly the level it crossed (no dead
time, jitter or reset noise); any of them makes each reference a new draw about the level
at the previous event, so the chain (a dead time of zero at least) is the model: a walk
would accumulate the reset noise along it, correlated from event to event.

``u`` is where the reference stood at the cycle's start relative to ``V(0)`` (unknown:
a prior uniform over ``(-c_on, c_off)``, used as a Gaussian of the same mean and
variance). The thresholds are parameters too, with the calibrated (or nominal) values as
Gaussian priors of their stated spread: the fit is over ``theta = (g, u, c_on, c_off)``,
by Gauss-Newton (iteratively reweighted least squares), from a start found by a
bracketing root search on ``sum_i r_i(g)`` (each ``r_i`` rises with ``g`` during a ramp).
Background events (leak, shot noise) are outliers at their rate ``lambda`` (per µs): an
event's weight is the posterior probability that it is signal,
``f_i / (f_i + lambda)`` with ``f_i = phi(r_i / s_i) |V'(t_c,i)| / s_i`` the signal's
density in time. Such an event still resets the pixel, which the chain keeps.

The image is ``L = exp(g_hat)`` in the scene's unit; the uncertainty is the standard
deviation of ``g_hat`` from the inverse of the information matrix at the estimate
(thresholds and ``u`` marginalised), the Cramér-Rao bound of this model for this pixel's
events, widened where the likelihood's profile shows mass the curvature does not see (a
second optimum: :func:`_probe`; for fits of 3 to 9 events, the profile's spread on a grid,
:func:`_few_events_kernel`). :func:`fisher_information` evaluates the same matrix at a
given ``g`` (the truth, on the noiseless event sequence): the bound to compare the
estimator's variance with.

What is approximate, and stated as such: ``s_i`` is held at the current estimate in each
step (the dependence of the noise on ``g`` through ``V'`` is not differentiated); the
density's Jacobian ``|V'(t_c)|`` enters the outlier weights only; the previous stamp's
quantum enters ``s_i`` as if independent of the next equation's; the prior on ``u`` is
Gaussian, not uniform; the
photoreceptor's state at the cycle start is the periodic steady state (two cycles
integrated); the readout's queueing delays (the arbiter) and hot pixels are not modelled;
crossings that the jitter clamps to the end of a dead time are treated as unclamped.

A pixel with fewer than two events is not fitted; its estimate is the mean of ``ln L``
under the likelihood of so few events (:data:`FLAG_FEW_EVENTS`): silence is likeliest
where the signal swings least, near ``L_const``, and a dead pixel explains it too, at the
sensor's share of them (then NaN, flag :data:`FLAG_NO_EVENTS`). Pixels whose estimate is
uncertain to a factor e or more carry no information (NaN, :data:`FLAG_UNINFORMED`). Pixels
whose estimate reaches a bound of the model's radiance range (or whose vague estimate lies
within one deviation of it) are flagged
:data:`FLAG_OUT_OF_RANGE` and hold the bound (brighter than the range: its top, as a
camera's saturated pixel; darker: its bottom); their standard deviation is NaN. The mask
(:attr:`MlResult.mask`) is False for all three. With a calibration's map of dead pixels
(:mod:`asynhdr.defects`), :func:`reconstruct_ml` fills the dead ones from their measured
neighbours and adds :data:`FLAG_FILLED`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numba as nb
import numpy as np
from numba import types
from numba.extending import intrinsic

from asynhdr._pool import block_order
from asynhdr.defects import fill_defects
from asynhdr.events import Recording
from asynhdr.rig import Rig
from asynhdr.sensor.params import SensorParams
from asynhdr.sensor.photoreceptor import Lowpass, lowpass_rows, time_grid

__all__ = [
    "DEFAULT_DLOG",
    "FAST_HOLD_SD",
    "FLAG_AMBIGUOUS",
    "FLAG_FEW_EVENTS",
    "FLAG_FILLED",
    "FLAG_NO_EVENTS",
    "FLAG_OUT_OF_RANGE",
    "FLAG_UNINFORMED",
    "LEARN_GATE",
    "LEARN_MIN_EVENTS",
    "LEARN_POPULATION_MIN",
    "LEARN_SD_FLOOR",
    "LearnedThresholds",
    "MlModel",
    "MlResult",
    "cached_model",
    "estimate",
    "fisher_information",
    "group_by_pixel",
    "ml_model",
    "reconstruct_ml",
    "sensor_of",
    "thresholds_prior",
    "valid_flags",
]

logger = logging.getLogger(__name__)

DEFAULT_DLOG = 0.08
"""Step (natural log of radiance) of the grid on which the photoreceptor output is
tabulated for ``ml``. Linear interpolation between rows errs by at most
``dlog^2 / 8 max|d^2 V / dg^2| <= dlog^2 / 32`` (2e-4 log units here), a fiftieth of the
IMX636's reset noise and a thousandth of a threshold. The table is the fit's memory
traffic: at 0.04 (5e-5) the default rig's table was 259 MB and ``ml`` about 15 % slower,
with the same chart figures."""

RANGE_MARGIN = 100.0
"""The model's radiance range reaches this factor beyond ``L_const min(T2) / max(T1)`` and
``L_const max(T2) / min(T1)``: pixels further out carry no usable timing."""

FLAG_NO_EVENTS = 1
"""Flag: the pixel fired fewer than ``min_events`` events in the window (two by default:
the first event's reference is unknown, so one event alone is not fitted) and has no
estimate from so few (:data:`FLAG_FEW_EVENTS`): its silence is likelier a dead pixel's, or
no radiance explains its one event: NaN."""
FLAG_OUT_OF_RANGE = 2
"""Flag: the estimate reached a bound of the model's radiance range: the pixel is at least
as bright as the upper bound (or at most as dark as the lower), and the image holds that
bound, as a saturated pixel of a camera holds its full scale; no standard deviation."""
FLAG_UNINFORMED = 4
"""Flag: the estimate's standard deviation of ``ln L`` is 1 or more (the events fix ``L``
to no better than a factor e: a plateau of the likelihood): NaN, the deviation kept (NaN
where it is infinite: a profile without curvature). A vague fit within one deviation of
a bound of the range is flagged :data:`FLAG_OUT_OF_RANGE` instead and holds the bound."""
FLAG_FILLED = 8
"""Flag (with :data:`FLAG_NO_EVENTS`): a dead pixel of the calibration's map, given the
median of its measured neighbours (:func:`asynhdr.defects.fill_defects`); no deviation."""
FLAG_FEW_EVENTS = 16
"""Flag: the pixel fired fewer than two events, and the estimate is the mean of ``ln L``
under the likelihood of so few (:func:`_sparse_kernel`; near ``L_const`` the signal swings
least, so silence is likeliest there): an estimate with its deviation, in the mask. With
:data:`FLAG_UNINFORMED`: that likelihood fixes ``L`` to no better than a factor e: NaN."""
FLAG_AMBIGUOUS = 32
"""Flag: a fit of few events (:data:`_FEW_EVENTS`) in a sharp optimum of its likelihood,
whose profile holds about as likely values a factor e or more away (another optimum):
the estimate is the fit's, in the mask, and its deviation (1 or more) the likelihood's
spread about it (:func:`_few_events_kernel`). Not a plateau (:data:`FLAG_UNINFORMED`):
the events make the fit's value as likely as any, and do not tell it from the others."""

_MAX_ITER = 16
_TOL_G = 1e-3
_MAX_STEP_G = 1.0
_BLOCK = 256
_CHI2_RESCUE = 2.0
_SD_RESCUE = 0.2
_VAR_INFORMED = 1.0
_PROFILE_STEP = 0.25
"""Step in ``ln L`` of the likelihood's profile that checks a fit the Gauss-Newton matrix
calls vague (:func:`_profile_walk`)."""
_NLL_TOL = 1e-3
"""A neighbour's start replaces a pixel's fit only when its objective (``-2 ln``
likelihood) is lower by more than this: the same optimum reached again is no move."""
_PROFILE_POLISH = 0.05
"""Half the bracket in ``ln L`` of the parabola that places a point the profile walk found
(:func:`_profile_polish`)."""
_OUTLIER_Z2 = 16.0
_INV_SQRT_2PI = 0.3989422804014327
"""``1 / sqrt(2 pi)``: the standard normal density's peak."""
_DENSITY_FLOOR = 1e-300
_THRESHOLD_Z = 2.5
_SCAN_STEP = 0.2
_PROBES = (0.15, 0.3, 0.5, 1.0, 1.5)
"""A pixel's fit is checked against the likelihood's profile these distances either side
in ``ln L`` (:func:`_probe`)."""
_PROBE_MARGIN = 2.0
"""... and fitted again from a point of that profile whose ``-2 ln`` likelihood is lower
by more than this (the Gauss-Newton fit is the likelihood's optimum only nearly: its
variances are held within a step)."""
_DESCENT_STEP = 0.08
"""The first compass step in ``ln L`` of the walk downhill on the likelihood's profile
(:func:`_profile_descent`); the steps halve from there ..."""
_DESCENT_LEVELS = 16
"""... at most this many times (0.08 / 2^15: 2.4e-6)."""
_MODE_EXCESS = 4.0
"""A point of the profile (:func:`_probe`) widens a fit's stated deviation when its ``-2 ln``
likelihood lies more than this below what the fit's own curvature predicts there."""
_FEW_EVENTS = (3, 10)
"""A fit from this many events (at least, fewer than), about as few as its parameters,
states the spread of its likelihood's profile on a grid (:func:`_few_events_kernel`): such
a profile can hold optima as narrow as the fit's curvature says, as likely as the fit and
between the distances :data:`_PROBES` (docs/ml.md, "Fits of few events"). One or two
events make no sharp optima. Not the fast fit's own fits (:func:`_fast_kernel`), whose
time it would double; its pixels fitted in full, yes."""
_FEW_STEP = 0.02
"""... the grid's spacing in ``ln L`` (it spans the model's whole range)."""
_HUBER = 3.0
"""Gauss-Newton's first phase weighs an equation more than this many standard deviations
off as if it were at that distance: a background event's pull is bounded before the
outlier weights (which can take a poor start's every event for background) come in."""


@dataclass(frozen=True, eq=False)
class MlModel:
    """Everything the estimator needs of the rig and the sensor, tabulated per whole µs of
    the window.

    Attributes
    ----------
    window_us : length of the window (µs from the cycle start) the tables cover.
    mode : 0: the exact log irradiance (no photoreceptor low-pass); 1: tabulated low-pass.
    g_lo, g_hi : the model's range of ``g = ln L``.
    dead : True when the pixel's reference is not exactly the level it crossed (latency or
        refractory > 0, jitter or reset noise): the reference is taken at the end of each
        dead time (the stamp, without one); else it walks by ``c``.
    reset_sigma, jitter_us, res_us : reset noise (log), jitter (µs), timestamp quantum (µs).
    noise_rate_per_us : background events per pixel per µs (outlier rate).
    exact : ``(W, 8)`` float64 per whole µs slot for mode 0: ``a1, b2, da1, db2`` at the
        crossing time ``m + res/2 - latency`` and at the dead time's end ``m + res/2 +
        refractory`` (``a1 = k_lens T1``, ``b2 = k_lens L_const T2``, ``d`` per µs); a
        single row of zeros in mode 1, which does not read it.
    v0 : ``(a1, b2)`` at the cycle start (mode 0).
    rows : ``(n_rows, K, 2)`` float32 photoreceptor output at grid time ``s_k`` for grid
        value ``g_j = g0 + j dlog``, and its increment to ``s_{k+1}`` (mode 1); the times
        are those of the low-pass's grid that interpolation needs (:data:`TABLE_TOL`).
    locate : ``(W, 6)`` float32 for mode 1, per whole µs slot: the grid interval ``k``
        and the fraction into it at the crossing time, the same at the dead time's end,
        and ``1 / (s[k+1] - s[k])`` of both intervals (one slot's entries side by side:
        an evaluation reads one cache line of them).
    net_g, net_v : the model's net change of ``V`` from the cycle start to slot
        ``split_us``, ``net_v``, at ``g = net_g`` (made non-decreasing): the fit's start.
    split_us : the slot where that net change tells ``g`` best (its spread over ``g`` is
        largest): the end of the window for a one-way rig, the turn of a round trip, after
        which the net change falls back. The start uses the events before it.
    split2_us, net_v2 : the same at the end of the first stretch of slots whose spread is
        within 1 % of the largest: ``split_us`` for one trip; for two, the first trip's
        turn, where the net change counts half the events (its error from the thresholds'
        mismatch is half as large). A fit starts from the better of the two.
    ext_t, ext, ext_g : the extremes of ``V`` that a pixel with fewer than two events is
        estimated from (:func:`_sparse_kernel`): the times (µs, from 0 to the last slot's
        crossing time) between which ``V`` is monotone or linear for every ``g`` (the
        waveforms' knots, or the table's times), and at each the running maximum and
        minimum of ``V`` from the window's start and to its end, ``(4, n_times, n_g)``
        float32, for ``g`` on the grid ``ext_g`` (the table's rows in mode 1).
    latency_us, refractory_us : the sensor's (a crossing precedes its stamp by the
        latency; the dead time ends a refractory period after the stamp).
    dead_fraction : the sensor's share of pixels that never fire: the other explanation of
        a silent pixel.
    """

    window_us: int
    mode: int
    g_lo: float
    g_hi: float
    dead: bool
    reset_sigma: float
    jitter_us: float
    res_us: float
    noise_rate_per_us: float
    exact: np.ndarray
    v0: tuple[float, float]
    rows: np.ndarray
    g0: float
    dlog: float
    locate: np.ndarray
    net_g: np.ndarray
    net_v: np.ndarray
    split_us: int
    split2_us: int
    net_v2: np.ndarray
    ext_t: np.ndarray
    ext: np.ndarray
    ext_g: np.ndarray
    latency_us: float
    refractory_us: float
    dead_fraction: float
    description: str = ""

    @property
    def n_bytes(self) -> int:
        return int(self.exact.nbytes + self.rows.nbytes + self.locate.nbytes
                   + self.ext.nbytes)


def _noise_rate_hz(sensor: SensorParams) -> float:
    """Background events per pixel per second: leak plus shot noise at its mid rate."""
    shot = sensor.shot_noise_rate_hz * 0.5 * (1.0 + sensor.shot_noise_bright_factor)
    return float(sensor.leak_rate_hz + shot)


def _split(net: np.ndarray) -> tuple[int, int]:
    """Indices (along axis 1 of ``net``, the net change of ``V`` per ``g`` row and time) of
    the last time whose spread over ``g`` is within 0.1 % of the largest, and of the same
    within the first stretch of times within 1 % of the largest; -1 for the last time
    given."""
    spread = net.max(axis=0) - net.min(axis=0)
    i = int(np.flatnonzero(spread >= 0.999 * spread.max())[-1])
    near = spread >= 0.99 * spread.max()
    i0 = int(np.argmax(near))
    i1 = i0
    while i1 + 1 < spread.size and near[i1 + 1]:
        i1 += 1
    part = spread[i0:i1 + 1]
    if i <= i1:
        j = i  # one stretch: the same time
    else:
        j = i0 + int(np.flatnonzero(part >= 0.999 * part.max())[-1])
    last = spread.size - 1
    return (-1 if i == last else i), (-1 if j == last else j)


TABLE_TOL = 1e-4
"""Largest error (log units) of the photoreceptor table's linear interpolation in time, at
the times of the low-pass's grid: the table keeps only the grid times it needs
(:func:`decimate_grid`), a hundredth of the IMX636's reset noise. On the default IMX636
rig it keeps 1,130 of 52,265 times (2.6 MB instead of 121 MB): the fit's passes over the
events then read a table in cache."""

_SPLIT_TIMES = 2048
"""Times (at most) at which :func:`ml_model` compares the net change's spread."""


def _rising(v: np.ndarray) -> np.ndarray:
    """``v`` made strictly increasing (a running maximum plus a tiny ramp)."""
    return np.maximum.accumulate(np.asarray(v, dtype=np.float64)) + 1e-9 * np.arange(v.size)


def ml_model(rig: Rig, sensor: SensorParams, *, window_us: float | None = None,
             dlog: float = DEFAULT_DLOG, g_range: tuple[float, float] | None = None,
             dt_us: float | None = None, from_rest: bool = False) -> MlModel:
    """Tabulate the forward model of ``rig`` and ``sensor`` over a window of the cycle.

    ``window_us`` defaults to the ramp; ``g_range`` (``ln L`` bounds) to the rig's range
    widened by :data:`RANGE_MARGIN`; ``dt_us`` (the low-pass grid) to the simulator's.
    ``from_rest``: the photoreceptor starts the cycle settled at its input (a single ramp
    from rest, or the first cycle of a simulation) instead of in the periodic steady state.
    """
    from asynhdr.sensor.photoreceptor import DEFAULT_DT_US

    period = float(rig.period_us)
    w_us = math.ceil(window_us if window_us is not None else rig.ramp_us)
    w_us = max(1, min(w_us, int(rig.period_us)))
    w1, w2 = rig.waveforms()
    knots = np.union1d(w1.phase, w2.phase)
    t1v, t2v = w1(knots), w2(knots)
    if g_range is None:
        lo = rig.l_const * float(t2v.min()) / float(t1v.max()) / RANGE_MARGIN
        hi = rig.l_const * float(t2v.max()) / max(float(t1v.min()), 1e-12) * RANGE_MARGIN
        g_range = (math.log(lo), math.log(hi))
    g_lo, g_hi = float(g_range[0]), float(g_range[1])
    if not g_hi > g_lo:
        raise ValueError(f"ml: empty radiance range {g_range}")
    res = float(sensor.timestamp_resolution_us)
    lat = float(sensor.latency_us)
    refr = float(sensor.refractory_us)
    m = np.arange(w_us, dtype=np.float64)
    tc = np.clip(m + 0.5 * res - lat, 0.0, period)
    te = np.clip(m + 0.5 * res + refr, 0.0, period)
    # the chain of events conditional on the previous one whenever the reference is not
    # exactly the level crossed (a dead time, jitter or reset noise); the walk by ``c``
    # only for a pixel whose reference is (its levels' errors would accumulate along it)
    dead = lat > 0 or refr > 0 or sensor.jitter_sigma_us > 0 or sensor.reset_noise_sigma > 0
    kl, lc = rig.k_lens, rig.l_const
    ks = knots * period
    a1k = kl * t1v
    b2k = kl * lc * t2v
    with np.errstate(divide="ignore", invalid="ignore"):
        da1k = np.diff(a1k) / np.diff(ks)
        db2k = np.diff(b2k) / np.diff(ks)

    def slope(d: np.ndarray, t: np.ndarray) -> np.ndarray:
        j = np.clip(np.searchsorted(ks, t, side="right") - 1, 0, d.size - 1)
        return d[j]

    exact = np.stack([np.interp(tc, ks, a1k), np.interp(tc, ks, b2k), slope(da1k, tc),
                      slope(db2k, tc), np.interp(te, ks, a1k), np.interp(te, ks, b2k),
                      slope(da1k, te), slope(db2k, te)], axis=1)
    v0 = (float(a1k[0]), float(b2k[0]))
    common = dict(window_us=w_us, g_lo=g_lo, g_hi=g_hi, dead=dead,
                  reset_sigma=float(sensor.reset_noise_sigma),
                  jitter_us=float(sensor.jitter_sigma_us), res_us=res,
                  noise_rate_per_us=_noise_rate_hz(sensor) * 1e-6, exact=exact, v0=v0,
                  latency_us=lat, refractory_us=refr,
                  dead_fraction=float(sensor.dead_pixel_fraction))
    t_end = float(tc[-1])
    if sensor.cutoff_hz <= 0:
        xg = np.arange(g_lo, g_hi + 0.5 * dlog, dlog)
        xt = _node_times(ks, t_end)
        xv = np.log(np.interp(xt, ks, a1k)[:, None] * np.exp(xg)[None, :]
                    + np.interp(xt, ks, b2k)[:, None])
        common.update(ext_t=xt, ext=_extremes(xv), ext_g=xg)
        ng = np.linspace(g_lo, g_hi, 512)
        e = np.exp(ng)
        slots = np.unique(np.append(np.arange(0, w_us, max(1, w_us // _SPLIT_TIMES)),
                                    w_us - 1))
        ec = e[::8, None]
        ii = _split(np.log(exact[slots, 0] * ec + exact[slots, 1])
                    - np.log(v0[0] * ec + v0[1]))
        nvs = []
        for i in ii:
            m_s = int(slots[i])
            nv = np.log(exact[m_s, 0] * e + exact[m_s, 1]) - np.log(v0[0] * e + v0[1])
            nvs.append((_rising(nv), w_us if i < 0 else m_s + 1))
        return MlModel(mode=0, rows=np.zeros((2, 2, 2), np.float32), g0=g_lo, dlog=1.0,
                       locate=np.zeros((1, 6)), net_g=ng,
                       net_v=nvs[0][0], split_us=nvs[0][1], net_v2=nvs[1][0],
                       split2_us=nvs[1][1], description="exact log irradiance",
                       **common)  # type: ignore[arg-type]
    if not (dlog > 0 and math.isfinite(dlog)):
        raise ValueError(f"ml: dlog must be positive, got {dlog}")
    lp = Lowpass(sensor.tau_ref_us * (sensor.cutoff_irradiance + sensor.dark_irradiance),
                 sensor.dark_irradiance, sensor.tau_max_us)
    n_rows = math.ceil((g_hi - g_lo) / dlog) + 2
    grid = np.exp(g_lo + dlog * np.arange(n_rows))
    i_max = kl * (float(grid[-1]) * float(t1v.max()) + lc * float(t2v.max()))
    tau_min = min(lp.tau_num / (i_max + lp.dark_irradiance), lp.tau_max_us)
    s = time_grid(knots, t1v, t2v, period_us=period,
                  dt_us=DEFAULT_DT_US if dt_us is None else dt_us, tau_min_us=tau_min)
    u = s / period
    a1 = kl * w1(u)
    b2 = kl * lc * w2(u)
    # the periodic steady state: one cycle from rest, then the cycle that is kept
    y0 = np.log(a1[0] * grid + b2[0])
    rows, y_end = lowpass_rows(grid, a1, b2, s, y0, lp)
    if not from_rest:
        rows, _ = lowpass_rows(grid, a1, b2, s, y_end, lp)
    kmax = s.size - 2

    def loc(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k = np.clip(np.searchsorted(s, t, side="right") - 1, 0, kmax)
        h = s[k + 1] - s[k]
        return k.astype(np.float64), np.clip((t - s[k]) / h, 0.0, 1.0), 1.0 / h

    kc, fc, _ = loc(tc)
    k_end = int(kc[-1])
    nv_end = (rows[:, k_end] + fc[-1] * (rows[:, k_end + 1] - rows[:, k_end])) - rows[:, 0]
    ks = np.unique(np.append(np.arange(0, k_end + 1, max(1, (k_end + 1) // _SPLIT_TIMES)),
                             k_end))
    nvs = []
    for i in _split(rows[::8, ks] - rows[::8, :1]):
        nv = nv_end
        m_split = w_us
        if i >= 0:
            nv = rows[:, ks[i]] - rows[:, 0]
            m_split = max(1, min(int(np.searchsorted(tc, s[ks[i]], side="right")), w_us))
        nvs.append((_rising(nv), m_split))
    # the table keeps the grid times that linear interpolation in time needs
    keep = decimate_grid(s, rows, TABLE_TOL)
    s = s[keep]
    rows = rows[:, keep]
    xt = _node_times(s, t_end)
    xv = np.stack([np.interp(xt, s, r) for r in rows], axis=1)
    common.update(ext_t=xt, ext=_extremes(xv), ext_g=g_lo + dlog * np.arange(n_rows))
    kmax = s.size - 2
    kc, fc, hc = loc(tc)
    ke, fe, he = loc(te)
    # radiance-major, value and increment to the next grid time side by side: a pass over
    # a pixel's events at one ``g`` walks two rows of the table forward (a few kB, in the
    # core's first-level cache), not one line of a 2.7 MB table per event
    tab = np.empty((n_rows, s.size, 2), dtype=np.float32)
    tab[:, :, 0] = rows
    tab[:, :-1, 1] = np.diff(rows, axis=1)
    tab[:, -1, 1] = 0.0
    common["exact"] = np.zeros((1, 8))  # read in mode 0 only
    return MlModel(mode=1, rows=tab, g0=g_lo, dlog=float(dlog),
                   locate=np.stack([kc, fc, ke, fe, hc, he], axis=1).astype(np.float32),
                   net_g=g_lo + dlog * np.arange(n_rows), net_v=nvs[0][0],
                   split_us=nvs[0][1], net_v2=nvs[1][0], split2_us=nvs[1][1],
                   description=f"photoreceptor low-pass tabulated ({n_rows} radiances x "
                   f"{s.size} times)", **common)  # type: ignore[arg-type]


def _node_times(knots: np.ndarray, t_end: float) -> np.ndarray:
    """The times of ``knots`` inside ``(0, t_end)``, with 0 and ``t_end``."""
    k = np.asarray(knots, dtype=np.float64)
    return np.unique(np.concatenate([[0.0], k[(k > 0.0) & (k < t_end)], [t_end]]))


def _extremes(v: np.ndarray) -> np.ndarray:
    """``(4, n_times, n_g)`` float32: the running maximum and minimum of ``v`` (``(n_times,
    n_g)``) from the first time to each, then from each to the last."""
    return np.stack([np.maximum.accumulate(v, axis=0), np.minimum.accumulate(v, axis=0),
                     np.maximum.accumulate(v[::-1], axis=0)[::-1],
                     np.minimum.accumulate(v[::-1], axis=0)[::-1]]).astype(np.float32)


def decimate_grid(s: np.ndarray, rows: np.ndarray, tol: float) -> np.ndarray:
    """Indices of the times ``s`` (increasing, first and last kept) to keep so that every
    row of ``rows`` (``(n, s.size)``), interpolated linearly between kept times, is within
    ``tol`` of its value at every dropped time. Greedy: from each kept time, the furthest
    next one whose segment holds (doubling, then bisection); each kept segment is checked.
    """
    s = np.asarray(s, dtype=np.float64)
    rows = np.asarray(rows, dtype=np.float64)
    n = s.size

    def holds(a: int, b: int) -> bool:
        if b <= a + 1:
            return True
        f = (s[a + 1:b] - s[a]) / (s[b] - s[a])
        line = rows[:, a, None] + f[None, :] * (rows[:, b] - rows[:, a])[:, None]
        return bool(np.abs(line - rows[:, a + 1:b]).max() <= tol)

    kept = [0]
    a = 0
    while a < n - 1:
        step = 1
        while a + 2 * step <= n - 1 and holds(a, a + 2 * step):
            step *= 2
        good = a + step  # holds (a step of one always does)
        bad = min(a + 2 * step, n - 1)
        if bad > good and holds(a, bad):
            good = bad
        else:
            while bad - good > 1:
                mid = (good + bad) // 2
                if holds(a, mid):
                    good = mid
                else:
                    bad = mid
        kept.append(good)
        a = good
    return np.asarray(kept, dtype=np.int64)


# ----------------------------------------------------------------------------- model values


@nb.njit(cache=True, inline="always", error_model="numpy")
def _at_g(mode, g, g0, dlog, nr):
    """What :func:`_eval` needs of ``g = ln L``, computed once per pass over the events:
    the grid row ``j`` below ``g`` and the weight ``w`` of the row above (mode 1), or
    ``L`` itself (mode 0)."""
    if mode == 0:
        return 0, 0.0, math.exp(g)
    x = (g - g0) / dlog
    j = int(math.floor(x))  # noqa: RUF046 (numba)
    if j < 0:
        j = 0
    elif j > nr - 2:
        j = nr - 2
    return j, x - j, 0.0


@nb.njit(cache=True, inline="always", error_model="numpy")
def _slot(mode, m, end, exact, locate):
    """What :func:`_eval_slot` needs of whole µs slot ``m >= 0`` (``end``: the dead time's
    end), whatever ``g``: the transmitted waveforms and their slopes (mode 0), or the grid
    interval, the weight within it and the time scale (mode 1). Read once per event where
    one pass evaluates several ``g``."""
    if mode == 0:
        o = 4 if end else 0
        return exact[m, o], exact[m, o + 1], exact[m, o + 2], exact[m, o + 3]
    o = 2 if end else 0
    # as float64 (the slot index is float32): a tuple unified with mode 0's
    return (np.float64(locate[m, o]), np.float64(locate[m, o + 1]),
            np.float64(locate[m, 4 + o // 2]), 0.0)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _eval_slot(mode, j, w, e, s0, s1, s2, s3, rows, dlog):
    """``(V, dV/dg, dV/dt)`` at the slot that :func:`_slot` read as ``(s0, .., s3)``, for
    the ``g`` that :func:`_at_g` gave ``(j, w, e)``."""
    if mode == 0:
        irr = s0 * e + s1
        return math.log(irr), s0 * e / irr, (s2 * e + s3) / irr
    k = int(s0)
    da = rows[j, k, 1]
    db = rows[j + 1, k, 1]
    va = rows[j, k, 0] + s1 * da
    vb = rows[j + 1, k, 0] + s1 * db
    return va + w * (vb - va), (vb - va) / dlog, (da + w * (db - da)) * s2


@nb.njit(cache=True, inline="always", error_model="numpy")
def _eval_row(mode, j, e, s0, s1, s2, s3, rows):
    """``(V, dV/dt)`` of :func:`_eval_slot` at grid row ``j``'s own ``g`` (mode 1: one row
    read), or at ``L = e`` (mode 0)."""
    if mode == 0:
        irr = s0 * e + s1
        return math.log(irr), (s2 * e + s3) / irr
    k = int(s0)
    d = rows[j, k, 1]
    return rows[j, k, 0] + s1 * d, d * s2


@nb.njit(cache=True, inline="always", error_model="numpy")
def _eval(mode, j, w, e, m, end, exact, v0a, v0b, rows, dlog, locate):
    """``(V, dV/dg, dV/dt)`` at whole µs slot ``m`` (``end``: the dead time's end; ``m < 0``:
    the cycle start) for the ``g`` that :func:`_at_g` gave ``(j, w, e)``."""
    if m < 0:
        if mode == 0:
            irr = v0a * e + v0b
            return math.log(irr), v0a * e / irr, 0.0
        va = rows[j, 0, 0]
        vb = rows[j + 1, 0, 0]
        return va + w * (vb - va), (vb - va) / dlog, 0.0
    s0, s1, s2, s3 = _slot(mode, m, end, exact, locate)
    return _eval_slot(mode, j, w, e, s0, s1, s2, s3, rows, dlog)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _slope_slot(mode, j, e, s0, s1, s2, s3, rows, dlog):
    """``d(dV/dt)/dg`` at the crossing slot that :func:`_slot` read as ``(s0, .., s3)``,
    for the ``g`` whose grid row :func:`_at_g` gave as ``j`` (mode 1), or ``L = e``."""
    if mode == 0:
        irr = s0 * e + s1
        return e * (s2 * s1 - s3 * s0) / (irr * irr)
    k = int(s0)
    return (rows[j + 1, k, 1] - rows[j, k, 1]) * s2 / dlog


@nb.njit(cache=True, inline="always", error_model="numpy")
def _slope_g(mode, j, w, e, m, exact, rows, dlog, locate):
    """``d(dV/dt)/dg`` at the crossing time of whole µs slot ``m`` (``m >= 0``), for the
    ``g`` that :func:`_at_g` gave ``(j, w, e)``."""
    s0, s1, s2, s3 = _slot(mode, m, False, exact, locate)
    return _slope_slot(mode, j, e, s0, s1, s2, s3, rows, dlog)


def _bitcast(source: Any, target: Any) -> Any:
    """A compiled function giving a ``source`` value's bits as a ``target`` value."""
    def typing(typingctx: Any, x: Any) -> Any:
        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            return builder.bitcast(args[0], context.get_value_type(target))
        return target(source), codegen
    return intrinsic(typing)


_float_bits = _bitcast(types.float64, types.int64)
"""A float64's bits as an int64 (compiled code only)."""
_bits_float = _bitcast(types.int64, types.float64)
"""An int64's bits as a float64 (compiled code only)."""


_LOG_BELOW = (-1.4932219202734505, 2.1126370614416494, -0.7291075269713446,
              0.1096903857189042)
"""The cubic of :func:`_log_below`: the best cubic in ``m`` to ``ln m`` over ``[1, 2]``
(within 4.5e-4), less its largest excess and 2e-6: below ``ln m`` everywhere there, by
2e-6 to 8.9e-4."""


@nb.njit(cache=True, inline="always", error_model="numpy")
def _log_below(x):
    """A lower bound of ``ln x`` for a positive normal or infinite ``x``, within 8.9e-4 of
    it: ``x = 2^e m`` with ``1 <= m < 2`` (read from its bits), ``ln m`` bounded by the
    cubic :data:`_LOG_BELOW` (no division: rounding adds less than 1e-12, against the
    cubic's 2e-6 margin). Infinity gives about 710; a subnormal ``x`` (below 2.2e-308)
    has no bound."""
    b = _float_bits(x)
    m = _bits_float((b & 0xFFFFFFFFFFFFF) | 0x3FF0000000000000)
    c0, c1, c2, c3 = _LOG_BELOW
    return ((b >> 52) - 1023) * 0.6931471805599453 + (c0 + m * (c1 + m * (c2 + m * c3)))


@nb.njit(cache=True, inline="always", error_model="numpy")
def _time_density(z2, slope, iw):
    """An event's density in time, ``phi(z) |dV/dt| / s``, from ``z2 = z^2``, ``slope =
    dV/dt`` at the crossing and ``iw = 1 / s^2``: every fit's likelihood and outlier
    weight."""
    return math.exp(-0.5 * z2) * abs(slope) * math.sqrt(iw) * _INV_SQRT_2PI


_JACOBIAN_MAX = 10.0
"""Bound on ``|d ln|dV/dt| / dg|`` per event in the fit's gradient (near a turn of ``V``,
where ``dV/dt`` passes zero, the term is large and means little)."""


@nb.njit(cache=True, error_model="numpy")
def _moment(mode, g, t, p, lo, hi, dead, con, coff, u, exact, v0a, v0b, rows, g0, dlog,
            locate, wmax, skip, skip2, split):
    """``sum_i r_i(g)`` over the events before slot ``split``, at fixed thresholds and
    ``u``: rises with ``g`` while the net change does (:attr:`MlModel.split_us`). With a
    dead time the first event is left out (its reference, ``u``, is unknown), unless it
    is the only one. Event ``skip`` is a background event (see :func:`_normal`)."""
    acc = 0.0
    jg, wg, eg = _at_g(mode, g, g0, dlog, rows.shape[0])
    vs, _, _ = _eval(mode, jg, wg, eg, -1, False, exact, v0a, v0b, rows, dlog, locate)
    level = 0.0
    base = vs + u
    prev = -1
    for i in range(lo, hi):
        m = t[i]
        if m >= split:
            break
        if m >= wmax:
            m = wmax - 1
        vc, _, _ = _eval(mode, jg, wg, eg, m, False, exact, v0a, v0b, rows, dlog, locate)
        if i == skip or i == skip2:
            prev = m
            base = vc
            level = 0.0
            continue
        step = con if p[i] > 0 else -coff
        if dead:
            if prev < 0:
                if hi - lo == 1:
                    acc += vc - vs - u - step
            else:
                ref, _, _ = _eval(mode, jg, wg, eg, prev, True, exact, v0a, v0b, rows,
                                  dlog, locate)
                acc += vc - ref - step
            prev = m
        else:
            level += step
            acc += vc - base - level
    return acc


@nb.njit(cache=True, inline="always", error_model="numpy")
def _mirror(h):
    """The normal matrix made whole: :func:`_normal` fills its lower triangle, copied here
    above the diagonal; and a tiny ridge on its ``ln L`` entry."""
    for a2 in range(4):
        for c in range(a2 + 1, 4):
            h[a2, c] = h[c, a2]
    h[0, 0] += 1e-12


@nb.njit(cache=True, inline="always", error_model="numpy")
def _inv_diag(lmat, k, z):
    """``(h^-1)[k, k] = || L^-1 e_k ||^2`` from the Cholesky factor ``lmat`` of a 4x4
    ``h`` (:func:`_solve4`); ``z`` is work space."""
    for i in range(4):
        s = 1.0 if i == k else 0.0
        for j in range(i):
            s -= lmat[i, j] * z[j]
        z[i] = s / lmat[i, i]
    v = 0.0
    for i in range(4):
        v += z[i] * z[i]
    return v


@nb.njit(cache=True, inline="always", error_model="numpy")
def _solve4(h, b, x, lmat, y, z):
    """Solve the symmetric positive-definite ``h x = b`` (4x4, Cholesky; ``lmat``, ``y``,
    ``z`` are work space); also returns ``(h^-1)[0, 0]``. False when ``h`` is not positive
    definite."""
    for i in range(4):
        for j in range(i + 1):
            s = h[i, j]
            for k in range(j):
                s -= lmat[i, k] * lmat[j, k]
            if i == j:
                if s <= 0.0:
                    return False, 0.0
                lmat[i, i] = math.sqrt(s)
            else:
                lmat[i, j] = s / lmat[j, j]
    for i in range(4):
        s = b[i]
        for k in range(i):
            s -= lmat[i, k] * y[k]
        y[i] = s / lmat[i, i]
    for i in range(3, -1, -1):
        s = y[i]
        for k in range(i + 1, 4):
            s -= lmat[k, i] * x[k]
        x[i] = s / lmat[i, i]
    return True, _inv_diag(lmat, 0, z)


@nb.njit(cache=True, error_model="numpy")
def _normal(mode, g, uu, con, coff, t, p, lo, hi, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
            rows, g0, dlog, locate, wmax, h, b, first_var, skip, skip2, stat, lam_nll, huber):
    """Accumulate the Gauss-Newton normal equations of the events ``lo..hi`` at
    ``theta = (g, u, c_on, c_off)`` into ``h`` and ``b`` (``b = -sum w r J``); returns
    ``chi2 = sum w r^2``. ``first_var`` is added to the variance of the equations that hold
    ``u`` (a scan at fixed ``u`` gives them the prior's spread). Event ``skip`` is taken
    for a background event: no equation of its own, but it resets the pixel (the walk of
    a pixel without dead time restarts at its level). ``stat`` receives the largest
    ``(r / s)^2``, the index of its event, the unweighted chi-square, the number of
    events the outlier weights take for signal and, when ``lam_nll >= 0``, the events'
    negative log-likelihood ``-2 sum ln(f_i + lam_nll)`` (:func:`_fit_nll`). ``huber > 0``:
    an equation more than ``huber`` standard deviations off weighs as if it were at that
    distance (Huber's weights: its pull bounded, not gone)."""
    chi2 = 0.0
    nll = 0.0
    jg, wg, eg = _at_g(mode, g, g0, dlog, rows.shape[0])
    vs, dgs, _ = _eval(mode, jg, wg, eg, -1, False, exact, v0a, v0b, rows, dlog, locate)
    n_on = 0.0
    n_off = 0.0
    prev = -1
    k_ev = 0
    base = vs
    dbase = dgs
    has_u = 1.0
    z_max = 0.0
    i_max = -1
    z_sum = 0.0
    n_signal = 0.0
    b0 = b1 = b2 = b3 = 0.0
    h00 = h10 = h20 = h30 = h11 = h21 = h31 = h22 = h32 = h33 = 0.0
    for i in range(lo, hi):
        m = t[i]
        if m >= wmax:
            m = wmax - 1
        vc, dgc, dtc = _eval(mode, jg, wg, eg, m, False, exact, v0a, v0b, rows, dlog,
                             locate)
        if i == skip or i == skip2:
            if dead:
                prev = m
            else:
                base = vc
                dbase = dgc
                has_u = 0.0
                n_on = 0.0
                n_off = 0.0
                k_ev = 0
            continue
        k_ev += 1
        j0 = 0.0
        j1 = 0.0
        j2 = 0.0
        j3 = 0.0
        if dead:
            if prev < 0:
                ref = vs + uu
                dref = dgs
                j1 = -1.0
                var = sr2 + dtc * dtc * tq2 + first_var
            else:
                ref, dref, dte = _eval(mode, jg, wg, eg, prev, True, exact, v0a, v0b,
                                       rows, dlog, locate)
                var = sr2 + dtc * dtc * tq2 + dte * dte * eq2
            if p[i] > 0:
                r = vc - ref - con
                j2 = -1.0
            else:
                r = vc - ref + coff
                j3 = 1.0
            j0 = dgc - dref
            prev = m
        else:
            if p[i] > 0:
                n_on += 1.0
            else:
                n_off += 1.0
            r = vc - base - has_u * uu - (con * n_on - coff * n_off)
            j0 = dgc - dbase
            j1 = -has_u
            j2 = -n_on
            j3 = n_off
            var = sr2 * k_ev + dtc * dtc * tq2 + has_u * first_var
        if var < 1e-12:
            var = 1e-12
        # the event is a time: its density is phi(r / s) |dV/dt| / s, so the likelihood's
        # gradient in g has, besides the residual's, d ln|dV/dt| / dg (what least squares
        # on the levels leaves out; without it the fit is biased by about the reset
        # noise's variance)
        jac = 0.0
        if dtc != 0.0:
            jac = _slope_g(mode, jg, wg, eg, m, exact, rows, dlog, locate) / dtc
            jac = min(max(jac, -_JACOBIAN_MAX), _JACOBIAN_MAX)
        iw = 1.0 / var
        w = iw
        z2 = r * r * w
        z_sum += z2
        if z2 > z_max:
            z_max = z2
            i_max = i
        if huber > 0.0 and z2 > huber * huber:
            hw = huber / math.sqrt(z2)
            w *= hw
            jac *= hw
        if lam > 0.0 or lam_nll >= 0.0:
            f = _time_density(z2, dtc, iw)
            if lam_nll >= 0.0:
                nll -= 2.0 * math.log(max(f + lam_nll, _DENSITY_FLOOR))
            if lam > 0.0:
                gam = f / (f + lam)
                w *= gam
                jac *= gam
                n_signal += gam
            else:
                n_signal += 1.0
        else:
            n_signal += 1.0
        wr = w * r
        chi2 += wr * r
        b0 += jac - wr * j0
        b1 -= wr * j1
        b2 -= wr * j2
        b3 -= wr * j3
        w0 = w * j0
        h00 += w0 * j0
        h10 += w0 * j1
        h20 += w0 * j2
        h30 += w0 * j3
        w1 = w * j1
        h11 += w1 * j1
        h21 += w1 * j2
        h31 += w1 * j3
        w2 = w * j2
        h22 += w2 * j2
        h32 += w2 * j3
        h33 += w * j3 * j3
    # the sums live in registers during the loop (stores into h would be reloaded each event)
    b[0] += b0
    b[1] += b1
    b[2] += b2
    b[3] += b3
    h[0, 0] += h00
    h[1, 0] += h10
    h[2, 0] += h20
    h[3, 0] += h30
    h[1, 1] += h11
    h[2, 1] += h21
    h[3, 1] += h31
    h[2, 2] += h22
    h[3, 2] += h32
    h[3, 3] += h33
    stat[0] = z_max
    stat[1] = i_max
    stat[2] = z_sum
    stat[3] = n_signal
    stat[4] = nll
    return chi2


@nb.njit(cache=True, error_model="numpy")
def _initial(net, net_g, net_v):
    """``g`` where the model's net level change over the window, ``net_v`` (rising along
    ``net_g``), equals ``net`` (linear interpolation, clamped)."""
    n = net_g.shape[0]
    if net <= net_v[0]:
        return net_g[0]
    if net >= net_v[n - 1]:
        return net_g[n - 1]
    lo = 0
    hi = n - 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if net_v[mid] <= net:
            lo = mid
        else:
            hi = mid
    d = net_v[hi] - net_v[lo]
    f = (net - net_v[lo]) / d if d > 0.0 else 0.5
    return net_g[lo] + f * (net_g[hi] - net_g[lo])


@nb.njit(cache=True, error_model="numpy")
def _start(lo, hi, t, p, mode, dead, exact, v0a, v0b, rows, g0, dlog, locate, wmax,
           g_lo, g_hi, net_g, net_v, c1, c2, mu_u, skip, skip2, split):
    """The fit's starting ``g``: where the model's net level change matches the events';
    then a bracket around it, widened until the moment sum changes sign, and false
    position (Illinois) to 0.02."""
    net = 0.0
    n_before = 0
    for i in range(lo, hi):
        if t[i] >= split:
            break
        n_before += 1
        if i != skip and i != skip2:
            net += c1 if p[i] > 0 else -c2
    if n_before < 2:
        # (almost) nothing before the split: the whole window, whose net change is the
        # model's at the split only approximately
        split = wmax
        net = 0.0
        for i in range(lo, hi):
            if i != skip and i != skip2:
                net += c1 if p[i] > 0 else -c2
    g = _initial(net, net_g, net_v)
    width = 0.25
    a = max(g - width, g_lo)
    bb = min(g + width, g_hi)
    fa = _moment(mode, a, t, p, lo, hi, dead, c1, c2, mu_u, exact, v0a, v0b, rows, g0, dlog,
                 locate, wmax, skip, skip2, split)
    fb = _moment(mode, bb, t, p, lo, hi, dead, c1, c2, mu_u, exact, v0a, v0b, rows, g0, dlog,
                 locate, wmax, skip, skip2, split)
    while fa > 0.0 and a > g_lo:
        bb = a
        fb = fa
        width *= 2.0
        a = max(a - width, g_lo)
        fa = _moment(mode, a, t, p, lo, hi, dead, c1, c2, mu_u, exact, v0a, v0b, rows, g0,
                     dlog, locate, wmax, skip, skip2, split)
    while fb < 0.0 and bb < g_hi:
        a = bb
        fa = fb
        width *= 2.0
        bb = min(bb + width, g_hi)
        fb = _moment(mode, bb, t, p, lo, hi, dead, c1, c2, mu_u, exact, v0a, v0b, rows, g0,
                     dlog, locate, wmax, skip, skip2, split)
    if fa >= 0.0:
        return a
    if fb <= 0.0:
        return bb
    side = 0
    for _ in range(40):
        g = (a * fb - bb * fa) / (fb - fa)
        if bb - a < 0.02:
            break
        fg = _moment(mode, g, t, p, lo, hi, dead, c1, c2, mu_u, exact, v0a, v0b, rows, g0,
                     dlog, locate, wmax, skip, skip2, split)
        if fg > 0.0:
            bb = g
            fb = fg
            if side == -1:
                fa *= 0.5
            side = -1
        else:
            a = g
            fa = fg
            if side == 1:
                fb *= 0.5
            side = 1
    return g


@nb.njit(cache=True, error_model="numpy")
def _gauss_newton(g, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                  g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp, sgp,
                  n_iter, skip, skip2, h, bvec, x, lmat, wy, wz, stat, res, robust0,
                  huber=_HUBER):
    """Gauss-Newton from ``g``: least squares with Huber's weights (constant ``huber``; 0:
    plain least squares) until converged (or half the iterations), then with the outlier
    weights; with ``robust0`` the outlier weights from the first step. A step that turns
    back on the last one by more than half of it is cut to the secant's point between
    them (the gradient has the density's Jacobian term, the matrix not: the plain
    iteration can swing between two points). ``res`` gets ``(g,
    var_g, u, c_on, c_off, chi2)``; ``stat`` the last pass's largest ``z^2``, its event and
    the unweighted chi2. Returns whether Huber's weights bounded an equation's pull in the
    first phase (without it, plain least squares takes the same steps)."""
    uu = mu_u
    cc1 = c1
    cc2 = c2
    v00 = np.nan
    chi2 = 0.0
    robust = lam <= 0.0 or robust0
    clipped = False
    last = 0.0
    for it in range(n_iter + 1):
        h[:, :] = 0.0
        bvec[:] = 0.0
        chi2 = _normal(mode, g, uu, cc1, cc2, t, p, lo, hi, dead, sr2, tq2, eq2,
                       lam if robust else 0.0, exact, v0a, v0b, rows, g0, dlog, locate,
                       wmax, h, bvec, 0.0, skip, skip2, stat, -1.0,
                       0.0 if robust else huber)
        if not robust and huber > 0.0 and stat[0] > huber * huber:
            clipped = True
        h[1, 1] += 1.0 / (su * su)
        bvec[1] += (mu_u - uu) / (su * su)
        h[2, 2] += 1.0 / (s1 * s1)
        bvec[2] += (c1 - cc1) / (s1 * s1)
        h[3, 3] += 1.0 / (s2 * s2)
        bvec[3] += (c2 - cc2) / (s2 * s2)
        if sgp > 0.0:
            h[0, 0] += 1.0 / (sgp * sgp)
            bvec[0] += (gp - g) / (sgp * sgp)
        _mirror(h)
        ok, v00 = _solve4(h, bvec, x, lmat, wy, wz)
        if not ok:
            v00 = np.nan
            break
        if it == n_iter:
            break
        dg = min(max(x[0], -_MAX_STEP_G), _MAX_STEP_G)
        f = 1.0
        if dg * last < 0.0 and abs(dg) > 0.5 * abs(last):
            # the step turns back on the last one by more than half of it: the iteration
            # overshoots (the density's Jacobian term is in the gradient, not in the
            # matrix) and would swing between two points; the secant's point between them
            f = abs(last) / (abs(last) + abs(dg))
        dg *= f
        gn = min(max(g + dg, g_lo), g_hi)
        uu += f * x[1]
        cc1 = max(cc1 + f * x[2], 1e-3)
        cc2 = max(cc2 + f * x[3], 1e-3)
        done = abs(gn - g) < _TOL_G
        last = gn - g
        g = gn
        if done or it == n_iter // 2 - 1:
            if robust:
                break  # the variance from this last matrix, a step of < _TOL_G away
            robust = True
            last = 0.0  # another objective: its first step may turn back
    res[0] = g
    res[1] = v00
    res[2] = uu
    res[3] = cc1
    res[4] = cc2
    res[5] = chi2
    return clipped


@nb.njit(cache=True, error_model="numpy")
def _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
             dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, skip, skip2, h, bvec, st):
    """What a fit ``res`` (:func:`_gauss_newton`'s) is judged by against another: twice the
    negative log-likelihood of the event *times*, ``-2 sum ln(f_i + lambda)`` with
    ``f_i = phi(r_i / s_i) |V'(t_c,i)| / s_i`` the signal's density at the event's time and
    ``lambda`` the background's (an event the signal cannot explain costs ``-2 ln
    lambda``), ``-2 ln lambda`` per event taken for background (``skip``), and the priors'
    terms. The residuals alone (the chi-square) would favour a slow signal with thresholds
    near zero, whose level passes close to every event's but at times it makes unlikely.
    ``h``, ``bvec``, ``st`` (5) are work space."""
    h[:, :] = 0.0
    bvec[:] = 0.0
    lam_nll = max(lam, 0.0)
    _normal(mode, res[0], res[2], res[3], res[4], t, p, lo, hi, dead, sr2, tq2, eq2, 0.0,
            exact, v0a, v0b, rows, g0, dlog, locate, wmax, h, bvec, 0.0, skip, skip2,
            st, lam_nll, 0.0)
    n_bg = (1 if skip >= 0 else 0) + (1 if skip2 >= 0 else 0)
    bg = -2.0 * math.log(max(lam_nll, _DENSITY_FLOOR)) * n_bg
    return st[4] + bg + ((res[3] - c1) / s1) ** 2 + ((res[4] - c2) / s2) ** 2 \
        + ((res[2] - mu_u) / su) ** 2


@nb.njit(cache=True, inline="always", error_model="numpy")
def _level_change(mode, j, w, e, m, prev, dead, base, k_ev, sr2, tq2, eq2, exact, v0a, v0b,
                  rows, dlog, locate):
    """An event's level change at slot ``m`` for the ``g`` that :func:`_at_g` gave ``(j, w,
    e)`` (:func:`_normal`'s equation without its thresholds and start offset): ``V`` at its
    crossing less its reference (the level at the end of the dead time after slot ``prev``,
    else ``base``: the cycle start's level, or the walk's), that equation's variance
    without the start offset's (``k_ev``: the walk's events so far), and ``V'`` at the
    crossing."""
    vc, _, dtc = _eval(mode, j, w, e, m, False, exact, v0a, v0b, rows, dlog, locate)
    if not dead:
        return vc - base, sr2 * k_ev + dtc * dtc * tq2, dtc
    if prev < 0:
        return vc - base, sr2 + dtc * dtc * tq2, dtc
    ref, _, dte = _eval(mode, j, w, e, prev, True, exact, v0a, v0b, rows, dlog, locate)
    return vc - ref, sr2 + dtc * dtc * tq2 + dte * dte * eq2, dtc


@nb.njit(cache=True, error_model="numpy")
def _profile_scan(a0, step, n_g, mode, con, coff, t, p, lo, hi, dead, sr2, tq2, eq2, exact,
                  v0a, v0b, rows, g0, dlog, locate, wmax, uu, first_var, s1, s2, skip,
                  skip2, work):
    """The ``g`` of ``a0 + i step`` (``i < n_g``) where the profile objective is least: the
    chi-square of :func:`_normal`'s equations (plain least squares, ``u`` at ``uu`` with
    ``first_var`` added to its equations' variance) less what the thresholds gain by moving
    to their best values under their priors, ``b_c^T H_c^-1 b_c`` (exact, the residuals
    being linear in the thresholds). One pass over the events for every ``g`` at once:
    only a residual's value and variance depend on ``g``, and the tables' rows of one time
    are read together. ``work`` holds at least ``(n_g, 10)``."""
    nr = rows.shape[0]
    for q in range(n_g):
        jq, wq, eq = _at_g(mode, a0 + q * step, g0, dlog, nr)
        vs, _, _ = _eval(mode, jq, wq, eq, -1, False, exact, v0a, v0b, rows, dlog, locate)
        work[q, 0] = jq
        work[q, 1] = wq
        work[q, 2] = eq
        work[q, 3] = vs  # the level the walk starts from (no dead time)
        for c in range(4, 10):
            work[q, c] = 0.0  # chi2, H_c (on-on, off-on, off-off), b_c (on, off)
    n_on = 0.0
    n_off = 0.0
    prev = -1
    k_ev = 0
    has_u = 1.0
    for i in range(lo, hi):
        m = t[i]
        if m >= wmax:
            m = wmax - 1
        if i == skip or i == skip2:
            if dead:
                prev = m
            else:
                for q in range(n_g):
                    jq = int(work[q, 0])
                    work[q, 3], _, _ = _eval(mode, jq, work[q, 1], work[q, 2], m, False,
                                             exact, v0a, v0b, rows, dlog, locate)
                has_u = 0.0
                n_on = 0.0
                n_off = 0.0
                k_ev = 0
            continue
        k_ev += 1
        on = p[i] > 0
        if dead:
            j2 = -1.0 if on else 0.0
            j3 = 0.0 if on else 1.0
            step_c = con if on else -coff
        else:
            if on:
                n_on += 1.0
            else:
                n_off += 1.0
            j2 = -n_on
            j3 = n_off
            step_c = con * n_on - coff * n_off
        for q in range(n_g):
            jq = int(work[q, 0])
            wq = work[q, 1]
            eq = work[q, 2]
            d, var, _ = _level_change(mode, jq, wq, eq, m, prev, dead, work[q, 3], k_ev, sr2,
                                      tq2, eq2, exact, v0a, v0b, rows, dlog, locate)
            if dead:
                if prev < 0:
                    r = d - uu - step_c
                    var = var + first_var
                else:
                    r = d - step_c
            else:
                r = d - has_u * uu - step_c
                var = var + has_u * first_var
            if var < 1e-12:
                var = 1e-12
            w = 1.0 / var
            wr = w * r
            work[q, 4] += wr * r
            work[q, 5] += w * j2 * j2
            work[q, 6] += w * j3 * j2
            work[q, 7] += w * j3 * j3
            work[q, 8] -= wr * j2
            work[q, 9] -= wr * j3
        if dead:
            prev = m
    best = np.inf
    g_best = a0
    p1 = 1.0 / (s1 * s1)
    p2 = 1.0 / (s2 * s2)
    for q in range(n_g):
        h22 = work[q, 5] + p1
        h32 = work[q, 6]
        h33 = work[q, 7] + p2
        b2 = work[q, 8]
        b3 = work[q, 9]
        det = h22 * h33 - h32 * h32
        gain = (h33 * b2 * b2 - 2.0 * h32 * b2 * b3 + h22 * b3 * b3) / det if det > 0.0 else 0.0
        cs = work[q, 4] - gain
        if cs < best:
            best = cs
            g_best = a0 + q * step
    return g_best


@nb.njit(cache=True, error_model="numpy")
def _held_thresholds(g, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                     g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp,
                     sgp, skip, skip2, h, bvec, x, lmat, wy, wz, stat, res, st_o):
    """Guard a fit ``res`` (from start ``g``) whose thresholds left their prior by more than
    :data:`_THRESHOLD_Z` of its spread: Gauss-Newton minimises the residuals alone, and a
    slow signal with thresholds near zero passes close to every event's level (at times
    it makes unlikely). The fit again with the thresholds held near their prior (a tenth
    of its spread) replaces it when its likelihood (:func:`_fit_nll`) is higher; its
    variance of ``ln L`` is then evaluated with the real priors."""
    if abs(res[3] - c1) <= _THRESHOLD_Z * s1 and abs(res[4] - c2) <= _THRESHOLD_Z * s2:
        return
    nll0 = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                    g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, skip, skip2, h,
                    bvec, st_o)
    res2 = np.empty(6)
    stat2 = np.empty(5)
    _gauss_newton(g, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
                  dlog, locate, wmax, g_lo, g_hi, c1, c2, 0.1 * s1, 0.1 * s2, su, mu_u,
                  gp, sgp, np.int64(_MAX_ITER), skip, skip2, h, bvec, x, lmat, wy, wz, stat2,
                  res2, False)
    nll1 = _fit_nll(res2, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                    rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, skip,
                    skip2, h, bvec, st_o)
    if not nll1 < nll0:
        return
    for k in range(6):
        res[k] = res2[k]
    for k in range(5):
        stat[k] = stat2[k]
    # the information at that fit with the real priors (no step)
    _gauss_newton(res2[0], lo, hi, t, p, mode, dead, sr2, tq2, eq2, 0.0, exact, v0a, v0b,
                  rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u,
                  gp, sgp, np.int64(0), skip, skip2, h, bvec, x, lmat, wy, wz, stat2, res2, False)
    res[1] = res2[1]


@nb.njit(cache=True, error_model="numpy")
def _fit_from(g, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
              dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp, sgp, skip,
              skip2, h, bvec, x, lmat, wy, wz, stat, res, st_o, robust0=False,
              huber=_HUBER):
    """Gauss-Newton from ``g`` (:func:`_gauss_newton`, into ``res`` and ``stat``), guarded
    by :func:`_held_thresholds`. Returns whether Huber's weights bounded a pull."""
    clipped = _gauss_newton(g, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                            rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su,
                            mu_u, gp, sgp, np.int64(_MAX_ITER), skip, skip2, h, bvec, x,
                            lmat, wy, wz, stat, res, robust0, huber)
    _held_thresholds(g, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                     g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp, sgp,
                     skip, skip2, h, bvec, x, lmat, wy, wz, stat, res, st_o)
    return clipped


@nb.njit(cache=True, inline="always", error_model="numpy")
def _workspace():
    """A fit's work arrays: ``(h, bvec, x, lmat, wy, wz, stat, st_o)``."""
    return (np.zeros((4, 4)), np.zeros(4), np.zeros(4), np.zeros((4, 4)), np.zeros(4),
            np.zeros(4), np.zeros(5), np.zeros(5))


@nb.njit(cache=True, inline="always", error_model="numpy")
def _fit_space(g_lo, g_hi):
    """:func:`_fit_pixel`'s own work arrays besides :func:`_workspace`'s: ``(res, saved,
    work, scan)``."""
    return (np.zeros(6), np.zeros(22), np.zeros(6),
            np.zeros((int((g_hi - g_lo) / (2.0 * _SCAN_STEP)) + 2, 10)))


@nb.njit(cache=True, inline="always", error_model="numpy")
def _fit_flag(g, var, g_lo, g_hi):
    """The flag of a fit at ``g`` with variance ``var``: :data:`FLAG_OUT_OF_RANGE` at a bound
    of the range, :data:`FLAG_UNINFORMED` when ``var`` is not below
    :data:`_VAR_INFORMED`, else 0."""
    if g <= g_lo + 1e-9 or g >= g_hi - 1e-9:
        return FLAG_OUT_OF_RANGE
    if not var < _VAR_INFORMED:
        return FLAG_UNINFORMED
    return 0


@nb.njit(cache=True, inline="always", error_model="numpy")
def _save(res, stat, saved, at):
    """Keep a fit (``res``, ``stat``) in ``saved[at:at + 11]``."""
    for c in range(6):
        saved[at + c] = res[c]
    for c in range(5):
        saved[at + 6 + c] = stat[c]


@nb.njit(cache=True, inline="always", error_model="numpy")
def _load(res, stat, saved, at):
    """Take back the fit :func:`_save` kept at ``at``."""
    for c in range(6):
        res[c] = saved[at + c]
    for c in range(5):
        stat[c] = saved[at + 6 + c]


@nb.njit(cache=True, error_model="numpy")
def _likelier_variant(g, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                      g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp, sgp,
                      skip, skip2, h, bvec, x, lmat, wy, wz, stat, res, st_o, saved, robust0,
                      huber, n_bg_max):
    """The fit in ``res`` and ``stat`` against the fit from the same start ``g`` with
    another first phase (``robust0``, ``huber``: :func:`_gauss_newton`): the likelier
    (:func:`_fit_nll`) is left there. With ``n_bg_max >= 0`` the other is not kept when it
    takes more than ``n_bg_max`` events for background. ``saved[11:22]`` is work space."""
    o_a = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                   g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, skip, skip2, h, bvec,
                   st_o)
    _save(res, stat, saved, 11)
    _fit_from(g, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
              dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp, sgp, skip, skip2,
              h, bvec, x, lmat, wy, wz, stat, res, st_o, robust0, huber)
    o_b = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                   g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, skip, skip2, h, bvec,
                   st_o)
    if (n_bg_max >= 0 and stat[3] < (hi - lo) - n_bg_max - 0.5) or not o_b < o_a:
        _load(res, stat, saved, 11)


@nb.njit(cache=True, error_model="numpy")
def _profile_at(ga, out, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, h, bvec, x,
                lmat, wy, wz, st, st_o):
    """The likelihood's profile at ``ln L = ga``: the thresholds and ``u`` fitted with
    ``ln L`` held (into ``out``), and its objective (:func:`_fit_nll`)."""
    none = np.int64(-1)
    _gauss_newton(ga, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                  g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, ga, 1e-6,
                  np.int64(_MAX_ITER), none, none, h, bvec, x, lmat, wy, wz, st, out, False)
    return _fit_nll(out, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                    g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, none, none, h, bvec,
                    st_o)


@nb.njit(cache=True, error_model="numpy")
def _profile_step(g, sgn, out, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                  rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, h, bvec,
                  x, lmat, wy, wz, st, st_o):
    """:func:`_profile_at` one :data:`_PROFILE_STEP` from ``g`` (down for ``sgn < 0``),
    within the range: ``(ln L, objective)``, the objective infinite where ``g`` is at the
    bound already."""
    ga = min(max(g + sgn * _PROFILE_STEP, g_lo), g_hi)
    if ga == g:
        return ga, np.inf
    return ga, _profile_at(ga, out, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a,
                           v0b, rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su,
                           mu_u, h, bvec, x, lmat, wy, wz, st, st_o)


@nb.njit(cache=True, error_model="numpy")
def _profile_walk(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                  g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, h, bvec, x,
                  lmat, wy, wz, st_o):
    """A fit the Gauss-Newton matrix calls vague (``res[1] >= 1``), checked on the
    likelihood's profile over ``ln L`` (:func:`_profile_at`, steps of
    :data:`_PROFILE_STEP`): walked downhill to the profile's lowest point, or to a bound
    of the range, and its variance taken from the profile's curvature there. ``res`` is
    replaced when the profile's point is likelier. The Gauss-Newton matrix leaves out the
    curvature of the density's Jacobian term, which can carry the information (a pixel
    beyond the top of the range: its events crowd at the start of the ramp, and ``u``
    and ``ln L`` are pinned by their times alone)."""
    none = np.int64(-1)
    o_fit = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                     rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, none, none, h,
                     bvec, st_o)
    # rows 0, 1, 2: the step below, the point, the step above (fit, objective, ln L)
    buf = np.empty((3, 6))
    o = np.full(3, np.inf)
    gs = np.empty(3)
    st = np.empty(5)
    gs[1] = min(max(res[0], g_lo), g_hi)
    o[1] = _profile_at(gs[1], buf[1], lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact,
                       v0a, v0b, rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2,
                       su, mu_u, h, bvec, x, lmat, wy, wz, st, st_o)
    for j in (0, 2):
        gs[j], o[j] = _profile_step(gs[1], j - 1, buf[j], lo, hi, t, p, mode, dead, sr2, tq2,
                                    eq2, lam, exact, v0a, v0b, rows, g0, dlog, locate, wmax,
                                    g_lo, g_hi, c1, c2, s1, s2, su, mu_u, h, bvec, x, lmat,
                                    wy, wz, st, st_o)
    j = 0 if o[0] < o[1] and o[0] <= o[2] else (2 if o[2] < o[1] else 1)
    while j != 1:
        # downhill, one way: the point becomes the step behind, the step the point
        k = 2 - j
        buf[k, :] = buf[1]
        o[k] = o[1]
        gs[k] = gs[1]
        buf[1, :] = buf[j]
        o[1] = o[j]
        gs[1] = gs[j]
        gs[j], o[j] = _profile_step(gs[1], j - 1, buf[j], lo, hi, t, p, mode, dead, sr2, tq2,
                                    eq2, lam, exact, v0a, v0b, rows, g0, dlog, locate, wmax,
                                    g_lo, g_hi, c1, c2, s1, s2, su, mu_u, h, bvec, x, lmat,
                                    wy, wz, st, st_o)
        if not o[j] < o[1]:
            break
    if not o[1] < o_fit:
        return
    g = gs[1]
    for k in range(6):
        res[k] = buf[1, k]
    res[0] = g
    res[1] = np.nan
    if g_lo < g < g_hi:
        # -2 ln L ~ (g - g_hat)^2 / var near the optimum, which the two steps bracket: the
        # second derivative of the parabola through the three points
        a = g - gs[0]
        b = gs[2] - g
        curv = 2.0 * (o[0] * b + o[2] * a - o[1] * (a + b)) / (a * b * (a + b))
        res[1] = 2.0 / curv if curv > 0.0 and o[0] < np.inf and o[2] < np.inf else np.inf


@nb.njit(cache=True, error_model="numpy")
def _profile_polish(res, step, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                    rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, h,
                    bvec, x, lmat, wy, wz, st_o):
    """A point ``res`` of the likelihood's profile (:func:`_profile_at`) moved to the
    vertex of the parabola through the profile at ``res[0]`` and ``step`` either side
    (within that bracket) when likelier, its variance from that parabola's curvature:
    the profile walk's steps are coarse. Returns the objective of ``res``."""
    buf = np.empty((4, 6))
    o = np.empty(4)
    st = np.empty(5)
    g = res[0]
    gs = (g - step, g, g + step)
    for k in range(3):
        ga = min(max(gs[k], g_lo), g_hi)
        o[k] = _profile_at(ga, buf[k], lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact,
                           v0a, v0b, rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1,
                           s2, su, mu_u, h, bvec, x, lmat, wy, wz, st, st_o)
        buf[k, 0] = ga
    curv = (o[0] + o[2] - 2.0 * o[1]) / (step * step)
    best = 1
    if o[0] < o[best]:
        best = 0
    if o[2] < o[best]:
        best = 2
    if curv > 0.0 and g_lo < g - step and g + step < g_hi:
        gv = g - 0.5 * step * (o[2] - o[0]) / (o[0] + o[2] - 2.0 * o[1])
        gv = min(max(gv, g - step), g + step)
        o[3] = _profile_at(gv, buf[3], lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact,
                           v0a, v0b, rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1,
                           s2, su, mu_u, h, bvec, x, lmat, wy, wz, st, st_o)
        buf[3, 0] = gv
        if o[3] < o[best]:
            best = 3
    for k in range(6):
        res[k] = buf[best, k]
    # -2 ln L ~ (g - g_hat)^2 / var: var = 2 / curvature
    res[1] = 2.0 / curv if curv > 0.0 else np.inf
    return o[best]


@nb.njit(cache=True, inline="always", error_model="numpy")
def _u_prior(c1, c2, u_sd):
    """The prior of the start offset ``u``: ``(sd, mean)``. Uniform over the band the
    thresholds ``c1``, ``c2`` leave (its moments), or ``N(0, u_sd^2)`` for a pixel that
    starts settled at its reference (``u_sd > 0``)."""
    if u_sd > 0.0:
        return u_sd, 0.0
    return (c1 + c2) / math.sqrt(12.0), 0.5 * (c2 - c1)


@nb.njit(cache=True, error_model="numpy")
def _settle(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0, dlog,
            locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, h, bvec, x, lmat, wy, wz,
            st_o):
    """A pixel's chosen fit ``res`` made final: walked on the likelihood's profile when the
    Gauss-Newton matrix calls it vague (:func:`_profile_walk`); returns its flag
    (:func:`_fit_flag`)."""
    if not res[1] < _VAR_INFORMED:
        _profile_walk(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                      rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, h,
                      bvec, x, lmat, wy, wz, st_o)
    return _fit_flag(res[0], res[1], g_lo, g_hi)


@nb.njit(cache=True, error_model="numpy")
def _profile_values(gs, lo, hi, t, p, mode, dead, sr2, tq2, eq2, exact, v0a, v0b, rows, g0,
                    dlog, locate, wmax, buf):
    """One pass over the events ``lo..hi`` for every ``ln L`` of ``gs`` at once: with
    ``ln L`` held, each residual is linear in ``(u, c_on, c_off)``, ``r_i = d_i + a_i .
    (u, c_on, c_off)`` (:func:`_normal`'s equations, no event taken for background).
    ``buf[k]`` (event ``lo + k``) receives ``a_i`` in columns 0 to 2, then per ``gs[q]``
    ``d_i``, the variance and ``|V'(t_c)|`` in columns ``3 + 3q`` to ``5 + 3q``."""
    n_g = gs.shape[0]
    nr = rows.shape[0]
    js = np.empty(n_g, np.int64)
    ws = np.empty(n_g)
    es = np.empty(n_g)
    vs = np.empty(n_g)
    for q in range(n_g):
        js[q], ws[q], es[q] = _at_g(mode, gs[q], g0, dlog, nr)
        vs[q], _, _ = _eval(mode, js[q], ws[q], es[q], -1, False, exact, v0a, v0b, rows, dlog,
                            locate)
    prev = -1
    n_on = 0.0
    n_off = 0.0
    for i in range(lo, hi):
        k = i - lo
        m = t[i]
        if m >= wmax:
            m = wmax - 1
        on = p[i] > 0
        if dead:
            buf[k, 0] = -1.0 if prev < 0 else 0.0
            buf[k, 1] = -1.0 if on else 0.0
            buf[k, 2] = 0.0 if on else 1.0
        else:
            if on:
                n_on += 1.0
            else:
                n_off += 1.0
            buf[k, 0] = -1.0
            buf[k, 1] = -n_on
            buf[k, 2] = n_off
        for q in range(n_g):
            d, var, dtc = _level_change(mode, js[q], ws[q], es[q], m, prev, dead, vs[q], k + 1,
                                        sr2, tq2, eq2, exact, v0a, v0b, rows, dlog, locate)
            buf[k, 3 + 3 * q] = d
            buf[k, 4 + 3 * q] = max(var, 1e-12)
            buf[k, 5 + 3 * q] = abs(dtc)
        if dead:
            prev = m


@nb.njit(cache=True, error_model="numpy")
def _profile_from_values(buf, n, q, lam, c1, c2, s1, s2, su, mu_u, th):
    """The likelihood's profile at ``gs[q]`` of :func:`_profile_values`: ``(u, c_on,
    c_off)`` fitted with ``ln L`` held (weighted least squares with their priors, Huber's
    weights to convergence and then, with background events, two steps with the outlier
    weights), and the objective there (:func:`_fit_nll`'s). ``th`` holds the start (a fit's
    nearby, which Huber's phase then reaches in few steps) and receives the result.
    Linear in those three, each step is exact for its weights: no pass over the tables."""
    col = 3 + 3 * q
    th0 = th[0]
    th1 = th[1]
    th2 = th[2]
    p0 = 1.0 / (su * su)
    p1 = 1.0 / (s1 * s1)
    p2 = 1.0 / (s2 * s2)
    phase = 0 if lam > 0.0 else 1
    n_robust = 0
    for _it in range(8):
        h00 = p0
        h11 = p1
        h22 = p2
        h01 = h02 = h12 = 0.0
        b0 = p0 * mu_u
        b1 = p1 * c1
        b2 = p2 * c2
        for k in range(n):
            a0 = buf[k, 0]
            a1 = buf[k, 1]
            a2 = buf[k, 2]
            d = buf[k, col]
            var = buf[k, col + 1]
            r = d + a0 * th0 + a1 * th1 + a2 * th2
            w = 1.0 / var
            z2 = r * r * w
            if phase == 0:
                if z2 > _HUBER * _HUBER:
                    w *= _HUBER / math.sqrt(z2)
            elif lam > 0.0:
                f = _time_density(z2, buf[k, col + 2], w)
                w *= f / (f + lam)
            h00 += w * a0 * a0
            h01 += w * a0 * a1
            h02 += w * a0 * a2
            h11 += w * a1 * a1
            h12 += w * a1 * a2
            h22 += w * a2 * a2
            b0 -= w * a0 * d
            b1 -= w * a1 * d
            b2 -= w * a2 * d
        # (h) theta = b, 3x3 by Cramer's rule (h is positive definite: the priors)
        c00 = h11 * h22 - h12 * h12
        c01 = h02 * h12 - h01 * h22
        c02 = h01 * h12 - h02 * h11
        det = h00 * c00 + h01 * c01 + h02 * c02
        if not det > 0.0:
            break
        n0 = (c00 * b0 + c01 * b1 + c02 * b2) / det
        n1 = (c01 * b0 + (h00 * h22 - h02 * h02) * b1 + (h01 * h02 - h00 * h12) * b2) / det
        n2 = (c02 * b0 + (h01 * h02 - h00 * h12) * b1 + (h00 * h11 - h01 * h01) * b2) / det
        n1 = max(n1, 1e-3)
        n2 = max(n2, 1e-3)
        moved = abs(n0 - th0) + abs(n1 - th1) + abs(n2 - th2)
        th0 = n0
        th1 = n1
        th2 = n2
        n_robust += phase
        if moved < 1e-4 or n_robust >= 2:
            if phase == 1:
                break
            phase = 1
    nll = 0.0
    lam_nll = max(lam, 0.0)
    for k in range(n):
        d = buf[k, col]
        var = buf[k, col + 1]
        r = d + buf[k, 0] * th0 + buf[k, 1] * th1 + buf[k, 2] * th2
        iw = 1.0 / var
        f = _time_density(r * r * iw, buf[k, col + 2], iw)
        nll -= 2.0 * math.log(max(f + lam_nll, _DENSITY_FLOOR))
    th[0] = th0
    th[1] = th1
    th[2] = th2
    return nll + ((th1 - c1) / s1) ** 2 + ((th2 - c2) / s2) ** 2 + ((th0 - mu_u) / su) ** 2


@nb.njit(cache=True, error_model="numpy")
def _profile_descent(res, o, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                     rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u):
    """A point ``res`` of the likelihood's profile (``ln L``, and ``(u, c_on, c_off)`` in
    ``res[2:5]``; objective ``o``) walked downhill on that profile by compass steps (from
    :data:`_DESCENT_STEP`, each as long as it gains, then halved; one pass over the events
    for both sides, :func:`_profile_values`) until a step is a quarter of the width the
    parabola through the last three points gives, then to that parabola's vertex when
    likelier. No derivative is taken: the walk finds the profile's optimum where
    Gauss-Newton's fixed point is not it (an event near a turn of the signal, whose time
    says much about ``L``, makes the profile rugged). Returns the objective at ``res``;
    ``res[1]`` is left for :func:`_information`."""
    n = hi - lo
    buf = np.empty((n, 9))
    gs = np.empty(2)
    th = np.empty(3)
    ob = np.empty(2)
    g = res[0]
    step = _DESCENT_STEP
    for _level in range(_DESCENT_LEVELS):
        moved = True
        for _rep in range(4):
            gs[0] = max(g - step, g_lo)
            gs[1] = min(g + step, g_hi)
            _profile_values(gs, lo, hi, t, p, mode, dead, sr2, tq2, eq2, exact, v0a, v0b,
                            rows, g0, dlog, locate, wmax, buf)
            best = -1
            for q in range(2):
                ob[q] = np.inf
                if gs[q] == g:
                    continue
                th[0] = res[2]
                th[1] = res[3]
                th[2] = res[4]
                ob[q] = _profile_from_values(buf, n, q, lam, c1, c2, s1, s2, su, mu_u, th)
                if ob[q] < o and (best < 0 or ob[q] < ob[best]):
                    best = q
                    res[2] = th[0]
                    res[3] = th[1]
                    res[4] = th[2]
            if best < 0:
                moved = False
                break
            o = ob[best]
            g = gs[best]
        if not moved and ob[0] < np.inf and ob[1] < np.inf:
            den = ob[0] + ob[1] - 2.0 * o
            if den > 0.0:
                # -2 ln L ~ (g - g_hat)^2 / var: the parabola's width sqrt(var)
                width = step * math.sqrt(2.0 / den)
                if step <= 0.25 * width:
                    gv = g - 0.5 * step * (ob[1] - ob[0]) / den
                    gs[0] = gv
                    gs[1] = gv
                    _profile_values(gs, lo, hi, t, p, mode, dead, sr2, tq2, eq2, exact,
                                    v0a, v0b, rows, g0, dlog, locate, wmax, buf)
                    th[0] = res[2]
                    th[1] = res[3]
                    th[2] = res[4]
                    ov = _profile_from_values(buf, n, 0, lam, c1, c2, s1, s2, su, mu_u, th)
                    if ov < o:
                        o = ov
                        g = gv
                        res[2] = th[0]
                        res[3] = th[1]
                        res[4] = th[2]
                    break
        step *= 0.5
    res[0] = g
    return o


@nb.njit(cache=True, error_model="numpy")
def _information(g, u, con, coff, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a,
                 v0b, rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su, h, bvec, x, lmat, wy,
                 wz, stat):
    """The Gauss-Newton matrix at ``(g, u, c_on, c_off)`` (the events with the outlier
    weights, and the priors), factored into ``lmat`` (:func:`_solve4`): ``(ok, var_g)``,
    the variance of ``ln L`` with the others marginalised."""
    h[:, :] = 0.0
    bvec[:] = 0.0
    _normal(mode, g, u, con, coff, t, p, lo, hi, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
            rows, g0, dlog, locate, wmax, h, bvec, 0.0, np.int64(-1), np.int64(-1), stat,
            -1.0, 0.0)
    h[1, 1] += 1.0 / (su * su)
    h[2, 2] += 1.0 / (s1 * s1)
    h[3, 3] += 1.0 / (s2 * s2)
    _mirror(h)
    return _solve4(h, bvec, x, lmat, wy, wz)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _mixture_weight(o, o_fit):
    """The weight of a point of the likelihood's profile (``-2 ln L`` there: ``o``) in the
    mixture that states a fit's spread: its likelihood relative to the fit's (``o_fit``),
    :data:`_PROBE_MARGIN` likelier at most."""
    return math.exp(-0.5 * max(o - o_fit, -_PROBE_MARGIN))


@nb.njit(cache=True, error_model="numpy")
def _probe(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0, dlog,
           locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp, sgp, h, bvec, x, lmat, wy,
           wz, stat, st_o, saved):
    """The chosen fit ``res`` against the likelihood's profile at the distances
    :data:`_PROBES` either side of it (:func:`_profile_values`, one pass for all):
    wherever the profile is likelier, the fit from there, likeliest first (the profile can
    have a second, shallower optimum, and a start biased by the thresholds' mismatch
    falls into it); where Gauss-Newton leaves that point for a less likely one, the point
    itself walked down the profile (:func:`_profile_descent`). The likeliest fit stays in
    ``res``; its deviation is widened where the profile either side says the likelihood
    has mass its curvature does not see. ``saved[0:11]`` is work space."""
    none = np.int64(-1)
    o_fit = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                     rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, none, none, h,
                     bvec, st_o)
    g = res[0]
    n_p = len(_PROBES)
    gs = np.empty(2 * n_p + 1)
    for k in range(n_p):
        gs[2 * k] = min(max(g - _PROBES[k], g_lo), g_hi)
        gs[2 * k + 1] = min(max(g + _PROBES[k], g_lo), g_hi)
    n = hi - lo
    n_g = 2 * n_p
    buf = np.empty((n, 3 + 3 * n_g))
    _profile_values(gs[:n_g], lo, hi, t, p, mode, dead, sr2, tq2, eq2, exact, v0a, v0b, rows,
                    g0, dlog, locate, wmax, buf)
    obj = np.empty(n_g + 1)
    th = np.empty((n_g, 3))
    for q in range(n_g):
        obj[q] = np.inf
        if abs(gs[q] - g) >= 0.5 * _PROBES[0]:
            th[q, 0] = mu_u
            th[q, 1] = c1
            th[q, 2] = c2
            obj[q] = _profile_from_values(buf, n, q, lam, c1, c2, s1, s2, su, mu_u, th[q])
    gs[n_g] = g  # the first fit, a point of the profile once another is chosen
    obj[n_g] = o_fit
    for q in np.argsort(obj[:n_g]):
        if not obj[q] < o_fit - _PROBE_MARGIN:
            break
        _save(res, stat, saved, 0)
        _fit_from(gs[q], lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                  g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp, sgp, none,
                  none, h, bvec, x, lmat, wy, wz, stat, res, st_o)
        o_new = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                         rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, none, none,
                         h, bvec, st_o)
        if not o_new < obj[q]:
            # Gauss-Newton went from the likelier point to a less likely one (its fixed
            # point solves the likelihood's equations only nearly, and its first phase,
            # Huber's, can lead to another basin): the point itself, walked downhill
            res[0] = gs[q]
            res[2] = th[q, 0]
            res[3] = th[q, 1]
            res[4] = th[q, 2]
            o_new = _profile_descent(res, obj[q], lo, hi, t, p, mode, dead, sr2, tq2, eq2,
                                     lam, exact, v0a, v0b, rows, g0, dlog, locate, wmax,
                                     g_lo, g_hi, c1, c2, s1, s2, su, mu_u)
            ok, v = _information(res[0], res[2], res[3], res[4], lo, hi, t, p, mode, dead,
                                 sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0, dlog, locate,
                                 wmax, c1, c2, s1, s2, su, h, bvec, x, lmat, wy, wz, st_o)
            res[1] = v if ok else np.nan
        if o_new < o_fit:
            o_fit = o_new
        else:
            _load(res, stat, saved, 0)
    if res[1] > 0.0:
        # where the profile lies well below what the fit's own curvature predicts there,
        # the likelihood has mass the curvature does not see (a second optimum of
        # near-equal likelihood); the variance is that of the mixture of the fit and those
        # points (the first fit among them when another was chosen), each as wide as the
        # fit and weighed by its likelihood
        v = res[1]
        sw = 1.0
        m1 = 0.0
        m2 = 0.0
        for q in range(n_g + 1):
            d = gs[q] - res[0]
            if not obj[q] < np.inf or d * d / v - (obj[q] - o_fit) <= _MODE_EXCESS:
                continue
            w = _mixture_weight(obj[q], o_fit)
            sw += w
            m1 += w * d
            m2 += w * d * d
        if sw > 1.0:
            res[1] = v + m2 / sw - (m1 / sw) ** 2


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _few_events_kernel(todo, off, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                       rows, g0, dlog, locate, wmax, g_lo, g_hi, con0, coff0, scon, scoff,
                       u_sd, out_g, out_sd, out_u, out_con, out_coff, out_flag):
    """The stated deviation of each fit ``todo`` (few events, :data:`_FEW_EVENTS`) widened
    to its likelihood's spread about it, where that is wider: the profile (``u`` and the
    thresholds fitted, :func:`_profile_from_values`) on a grid :data:`_FEW_STEP` apart
    over the model's range, walked outwards from the fit, each point weighed
    by its likelihood relative to the fit's (:data:`_PROBE_MARGIN` likelier at most), the
    fit itself a point. Only the deviation changes (and the flag, :data:`FLAG_AMBIGUOUS`,
    where it reaches a factor e): nothing the fits do reads them again."""
    n_max = int((g_hi - g_lo) / _FEW_STEP) + 2
    for q0 in nb.prange(todo.shape[0]):
        px = todo[q0]
        lo = off[px]
        hi = off[px + 1]
        n = hi - lo
        c1 = con0[px]
        c2 = coff0[px]
        s1 = max(scon[px], 1e-6)
        s2 = max(scoff[px], 1e-6)
        su, mu_u = _u_prior(c1, c2, u_sd)
        g = out_g[px]
        res = np.zeros(6)
        res[0] = g
        res[2] = out_u[px]
        res[3] = out_con[px]
        res[4] = out_coff[px]
        h = np.zeros((4, 4))
        bvec = np.zeros(4)
        st = np.zeros(5)
        none = np.int64(-1)
        o_fit = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                         rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, none, none,
                         h, bvec, st)
        gs = np.empty(n_max)
        n_g = 0
        for side in (-1.0, 1.0):
            for k in range(1, n_max + 1):
                gq = g + side * k * _FEW_STEP
                if gq < g_lo or gq > g_hi:
                    break
                gs[n_g] = gq
                n_g += 1
        buf = np.empty((n, 3 + 3 * n_g))
        _profile_values(gs[:n_g], lo, hi, t, p, mode, dead, sr2, tq2, eq2, exact, v0a, v0b,
                        rows, g0, dlog, locate, wmax, buf)
        th = np.empty(3)
        sw = 1.0
        m2 = 0.0
        for q in range(n_g):
            if q == 0 or (gs[q] - g) * (gs[q - 1] - g) < 0.0:
                # each side's walk starts at the fit's own u and thresholds
                th[0] = res[2]
                th[1] = res[3]
                th[2] = res[4]
            o = _profile_from_values(buf, n, q, lam, c1, c2, s1, s2, su, mu_u, th)
            d = gs[q] - g
            w = _mixture_weight(o, o_fit)
            sw += w
            m2 += w * d * d
        var = m2 / sw
        if var > out_sd[px] ** 2:
            out_sd[px] = math.sqrt(var)
            if var >= _VAR_INFORMED:
                out_flag[px] = FLAG_AMBIGUOUS


@nb.njit(cache=True, error_model="numpy")
def _fit_pixel(lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
               dlog, locate, wmax, g_lo, g_hi, net_g, net_v, c1, c2, s1, s2, gp, sgp,
               fixed, h, bvec, x, lmat, wy, wz, out, u_sd, stat, res, scan, split, st_o,
               net_v2, split2, saved):
    """One pixel (module docstring). Writes ``(g, sd, c_on, c_off, flag, u)`` into ``out``.
    ``u_sd > 0``: the pixel starts settled at its reference (``u ~ N(0, u_sd^2)``).
    ``stat`` (5), ``st_o`` (5), ``res`` (6), ``saved`` (22) and ``scan``
    (:func:`_profile_scan`) are work space.

    The fit: a start (:func:`_start`), Gauss-Newton; when the fit is poor or vague, a scan
    of the profile objective (:func:`_profile_scan`) over the range, kept when better;
    and, when background events are modelled and an event lies four sigma off, the fit
    with the outlier weights from its first step (least squares may have followed that
    event elsewhere), then the same again with the worst event taken for a background
    event, each kept when its likelihood is higher (:func:`_fit_nll`: the background
    event is priced at its own density). The chosen fit is checked on the likelihood's
    profile either side (:func:`_probe`), and a fit left vague is walked on
    that profile (:func:`_profile_walk`)."""
    su, mu_u = _u_prior(c1, c2, u_sd)
    if fixed:
        _gauss_newton(gp, lo, hi, t, p, mode, dead, sr2, tq2, eq2, 0.0, exact, v0a, v0b, rows,
                      g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp,
                      sgp, np.int64(0), np.int64(-1), np.int64(-1), h, bvec, x, lmat, wy, wz, stat,
                      res, False)
        out[0] = gp
        out[1] = math.sqrt(res[1]) if res[1] == res[1] and res[1] >= 0.0 else np.nan
        out[2] = c1
        out[3] = c2
        out[4] = 0.0
        out[5] = mu_u
        return
    best_g = np.nan
    best_v = np.nan
    best_c1 = c1
    best_c2 = c2
    best_u = mu_u
    best_obj = np.inf
    n = hi - lo
    # typed int64 from the start: literals would compile every callee once more
    skip = np.int64(-1)
    skip2 = np.int64(-1)
    n_try = 1
    cand = 0
    collapsed = False
    attempt = 0
    g_other = np.nan  # a second start (two trips), fitted beside the first; its fit in saved
    while attempt < n_try:
        if attempt > 0:
            if collapsed:
                skip = lo + cand
            cand += 1
        if 0.0 < sgp < 1e-3:
            g = gp
        else:
            g = _start(lo, hi, t, p, mode, dead, exact, v0a, v0b, rows, g0, dlog, locate, wmax,
                       g_lo, g_hi, net_g, net_v, c1, c2, mu_u, skip, skip2, split)
            if attempt == 0 and split2 != split:
                # two trips: the start from the first turn too; the fit that is likelier
                g2 = _start(lo, hi, t, p, mode, dead, exact, v0a, v0b, rows, g0, dlog,
                            locate, wmax, g_lo, g_hi, net_g, net_v2, c1, c2, mu_u,
                            skip, skip2, split2)
                if abs(g2 - g) > 0.02:
                    g_other = g2
        if g_other == g_other:
            _fit_from(g_other, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                      rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp,
                      sgp, skip, skip2, h, bvec, x, lmat, wy, wz, stat, res, st_o)
            o_other = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a,
                               v0b, rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su,
                               mu_u, skip, skip2, h, bvec, st_o)
            _save(res, stat, saved, 0)
        clipped = _fit_from(g, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a,
                            v0b, rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2,
                            su, mu_u, gp, sgp, skip, skip2, h, bvec, x, lmat, wy, wz, stat,
                            res, st_o)
        if attempt == 0 and clipped and stat[3] < n - 2.5:
            # Huber's weights bounded a pull on the way: plain least squares from the same
            # start may reach another optimum (a good event's large residual at a poor
            # start is bounded too)
            _likelier_variant(g, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a,
                              v0b, rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2,
                              su, mu_u, gp, sgp, skip, skip2, h, bvec, x, lmat, wy, wz,
                              stat, res, st_o, saved, False, 0.0, -1)
        if g_other == g_other:
            o_this = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a,
                              v0b, rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su,
                              mu_u, skip, skip2, h, bvec, st_o)
            if o_other < o_this:
                _load(res, stat, saved, 0)
            g_other = np.nan
        if attempt == 0 and lam > 0.0 and stat[0] >= _OUTLIER_Z2:
            # an event far off: least squares may have followed a background event to
            # another optimum before the outlier weights came in; the fit with them from
            # its first step (not kept if it takes more than two events for background:
            # it would explain the pixel away, not what this fit is for)
            _likelier_variant(g, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a,
                              v0b, rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2,
                              su, mu_u, gp, sgp, skip, skip2, h, bvec, x, lmat, wy, wz,
                              stat, res, st_o, saved, True, _HUBER, 2)
        n_bg = (1 if skip >= 0 else 0) + (1 if skip2 >= 0 else 0)
        n_eq = n - n_bg
        obj = np.inf
        if (res[5] > n_eq + _CHI2_RESCUE * math.sqrt(2.0 * n_eq) + 2.0
                or not res[1] < _SD_RESCUE * _SD_RESCUE):
            # a poor fit (chi-square beyond its spread) or a vague one (a plateau where
            # the reference path alone explains the events): perhaps a wrong optimum; restart
            # from the best of a coarse scan of the profile objective (the thresholds at
            # their best for each g), coarse to fine: steps of 2 x _SCAN_STEP over the
            # range, then _SCAN_STEP / 2 around the best; keep whichever fit is better
            obj = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                           rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, skip,
                           skip2, h, bvec, st_o)
            r0, r1, r2, r3, r4, r5 = res[0], res[1], res[2], res[3], res[4], res[5]
            z0, z1, z2, z3 = stat[0], stat[1], stat[2], stat[3]
            gbest = res[0]
            for level in range(2):
                step = _SCAN_STEP * (2.0 if level == 0 else 0.5)
                a0 = g_lo if level == 0 else max(g_lo, gbest - 2.0 * _SCAN_STEP)
                a1 = g_hi if level == 0 else min(g_hi, gbest + 2.0 * _SCAN_STEP)
                n_g = min(int((a1 - a0) / step + 1e-9) + 1, scan.shape[0])
                gbest = _profile_scan(a0, step, n_g, mode, c1, c2, t, p, lo, hi, dead, sr2,
                                      tq2, eq2, exact, v0a, v0b, rows, g0, dlog, locate,
                                      wmax, mu_u, su * su, s1, s2, skip, skip2, scan)
            _fit_from(gbest, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                      rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp,
                      sgp, skip, skip2, h, bvec, x, lmat, wy, wz, stat, res, st_o)
            obj1 = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a,
                            v0b, rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u,
                            skip, skip2, h, bvec, st_o)
            if obj1 < obj:
                obj = obj1
            else:
                res[0], res[1], res[2], res[3], res[4], res[5] = r0, r1, r2, r3, r4, r5
                stat[0], stat[1], stat[2], stat[3] = z0, z1, z2, z3
        if attempt == 0 and lam > 0.0 and n >= 3:
            if stat[3] < 0.5 * n:
                # the outlier weights took most events for background: a collapsed fit;
                # try each event in turn as the background event
                collapsed = True
                n_try = 1 + n
            elif stat[0] >= _OUTLIER_Z2 and stat[1] >= 0:
                skip = np.int64(stat[1])
                n_try = 2
        if n_try > 1 and obj == np.inf:
            # hypotheses to compare: this one's likelihood (:func:`_fit_nll`); attempt 0
            # took no event for background (skip is already the next attempt's)
            sk = skip
            sk2 = skip2
            if attempt == 0:
                sk = np.int64(-1)
                sk2 = np.int64(-1)
            obj = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                           rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, sk,
                           sk2, h, bvec, st_o)
        improved = best_obj == np.inf or obj < best_obj
        if improved:
            best_obj = obj
            best_g = res[0]
            best_v = res[1]
            best_c1 = res[3]
            best_c2 = res[4]
            best_u = res[2]
        if (attempt > 0 and attempt == n_try - 1 and not collapsed and skip >= 0 and skip2 < 0
                and improved and stat[0] >= _OUTLIER_Z2 and stat[1] >= 0 and n >= 5):
            # a second background event in the same cycle
            skip2 = np.int64(stat[1])
            n_try += 1
        attempt += 1
    res[0] = best_g
    res[1] = best_v
    res[2] = best_u
    res[3] = best_c1
    res[4] = best_c2
    if not (0.0 < sgp < 1e-3):
        _probe(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
               dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, gp, sgp, h, bvec, x,
               lmat, wy, wz, stat, st_o, saved)
    flag = _settle(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
                   dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, h, bvec, x, lmat,
                   wy, wz, st_o)
    out[0] = res[0]
    out[1] = math.sqrt(res[1]) if res[1] == res[1] and res[1] >= 0.0 else np.nan
    out[2] = res[3]
    out[3] = res[4]
    out[4] = float(flag)
    out[5] = res[2]


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _estimate_kernel(off, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
                     dlog, locate, wmax, g_lo, g_hi, net_g, net_v, min_events, con0,
                     coff0, scon, scoff, g_prior, sg_prior, fixed, out_g, out_sd, out_con,
                     out_coff, out_flag, u_sd, split, net_v2, split2, order, out_u):
    """Fit every pixel (module docstring), in blocks of ``_BLOCK``, taken in the order
    ``order`` (:func:`asynhdr._pool.block_order`). ``fixed``: evaluate the information at
    ``g_prior`` with no fit (the bound); ``sg_prior > 0``: a Gaussian prior on ``g``."""
    npx = off.shape[0] - 1
    nblk = order.shape[0]
    for bi in nb.prange(nblk):
        blk = order[bi]
        h, bvec, x, lmat, wy, wz, stat, st_o = _workspace()
        res, saved, work, scan = _fit_space(g_lo, g_hi)
        for px in range(blk * _BLOCK, min(npx, (blk + 1) * _BLOCK)):
            lo = off[px]
            hi = off[px + 1]
            if hi - lo < min_events:
                out_g[px] = np.nan
                out_sd[px] = np.nan
                out_con[px] = con0[px]
                out_coff[px] = coff0[px]
                out_flag[px] = 1
                continue
            _fit_pixel(lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                       g0, dlog, locate, wmax, g_lo, g_hi, net_g, net_v, con0[px],
                       coff0[px], max(scon[px], 1e-6), max(scoff[px], 1e-6), g_prior[px],
                       sg_prior[px], fixed, h, bvec, x, lmat, wy, wz, res, u_sd, stat, work,
                       scan, split, st_o, net_v2, split2, saved)
            out_g[px] = res[0]
            out_sd[px] = res[1]
            out_con[px] = res[2]
            out_coff[px] = res[3]
            out_flag[px] = np.uint8(res[4])
            out_u[px] = res[5]


# ----------------------------------------------------------------------------- fast


_FAST_ITER = 12
"""The fast fit's Newton steps at most (:func:`_fast_kernel`)."""
_FAST_TOL = 0.1
"""... until a step is below this share of the fit's standard deviation (or of the full
fit's tolerance, :data:`_TOL_G`, for a fit more precise than that)."""
_FAST_PROBES = (-0.25, 0.25, -0.5, 0.5, -1.0, 1.0, -2.0)
"""... and where the held thresholds' likelihood is higher at one of these distances from
the fast fit (by :data:`_PROBE_MARGIN`). Newton's method stops in optima 0.3 to 2.9
above the truth's from a start too bright, and about 1.0 below it beside ``L_const / 2``
(docs/ml.md): the points 0.25 away see an optimum 0.3 away in ``ln L`` that those 0.5
away step over, and the point 1.0 above the one 1.0 below. With the photoreceptor's
table, each point is the table's grid row nearest it (within ``dlog / 2``), whose values
are read from one row instead of interpolated between two (:func:`_fast_check`)."""
_KEEP_STEP = 4.0
"""... and the fast fit's Newton pass keeps :func:`_fast_check`'s sum at its point when the
step before it was under this many deviations: on the speed's cycle (docs/ml.md) the pass
after such a step is most often the last (the median fit that converges in two passes
steps 3.8 deviations, then 0.02)."""
_FAST_OUTLIER_Z2 = 9.0
"""... with the outlier weights from the first step under :data:`_KEEP_STEP` deviations
on, when an event lies three deviations off."""
_COARSE_EVENTS = 16
"""The fast fit first converges on every ``n // 16``-th of a pixel's ``n`` events
(:func:`_fast_coarse`), where that stride is at least 2 ..."""
_COARSE_TOL = 0.5
"""... until a step is under this share of that subset's deviation ..."""
_COARSE_FACTOR = 4
"""... then takes one step on every ``1 / 4`` as many events, and so on."""
_FAST_MATH = {"contract", "afn", "reassoc", "arcp"}
"""The fast fit's passes may fuse, reorder and approximate floating-point operations
(LLVM's fast-math flags, without those that assume no infinity or NaN)."""
_FAST_CHI2_Z = 3.0
"""A fast fit whose chi-square lies more than this many of its standard deviations
(``sqrt(2 n)``) above its ``n`` events is fitted in full."""


@nb.njit(cache=True, error_model="numpy")
def _read_slots(mode, lo, hi, t, dead, exact, locate, wmax, sl):
    """What every pass over a pixel's events reads of the model (:func:`_slot`), read once
    into ``sl`` (``(>= hi - lo, 8)``): event ``i``'s crossing slot in ``sl[i - lo, :4]``
    and, with a dead time, the end of the one before's in ``sl[i - lo, 4:]``."""
    prev = -1
    for i in range(lo, hi):
        m = min(t[i], wmax - 1)
        r = i - lo
        sl[r, 0], sl[r, 1], sl[r, 2], sl[r, 3] = _slot(mode, m, False, exact, locate)
        if dead and prev >= 0:
            sl[r, 4], sl[r, 5], sl[r, 6], sl[r, 7] = _slot(mode, prev, True, exact, locate)
        prev = m


@nb.njit(cache=True, error_model="numpy", fastmath=_FAST_MATH)
def _fast_pass(mode, g, lo, hi, sl, p, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
               dlog, locate, c1, c2, mu_u, su2, robust, keep, acc, stride):
    """One pass over a pixel's events at ``g`` with the thresholds held at ``c1``, ``c2``
    and the start offset at its prior's mean ``mu_u`` (variance ``su2``, added to the
    first equation's): the Newton sums of the one-parameter likelihood into ``acc``:
    ``(sum w r J - sum jac, sum w J^2, sum_on w J, -sum_off w J, max z^2, sum w r^2)``
    (the model of :func:`_normal`, its gradient's Jacobian term included; ``robust``: the
    outlier weights at ``g``; ``sl``: the events' slots, :func:`_read_slots`); with
    ``keep``, ``acc[6]``: the events' ``-2 sum ln(f_i + lambda)`` at ``g``, as
    :func:`_fast_check` sums it for its first point. With a dead time each event's term
    stands alone, and ``stride`` > 1 sums the first event and every ``stride``-th after
    it (:func:`_fast_coarse`); without one the walk is taken from the first event's level
    (``u`` drops out) and ``stride`` must be 1. Each of
    the model's four kinds (:data:`MlModel.mode`, with or without a dead time) runs its
    own loop (:func:`_fast_sums`)."""
    if mode == 1:
        if dead:
            _fast_sums(1, True, g, lo, hi, sl, p, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                       g0, dlog, locate, c1, c2, mu_u, su2, robust, keep, acc, stride)
        else:
            _fast_sums(1, False, g, lo, hi, sl, p, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                       g0, dlog, locate, c1, c2, mu_u, su2, robust, keep, acc, stride)
    elif dead:
        _fast_sums(0, True, g, lo, hi, sl, p, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
                   dlog, locate, c1, c2, mu_u, su2, robust, keep, acc, stride)
    else:
        _fast_sums(0, False, g, lo, hi, sl, p, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
                   dlog, locate, c1, c2, mu_u, su2, robust, keep, acc, stride)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _fast_sums(mode, dead, g, lo, hi, sl, p, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
               dlog, locate, c1, c2, mu_u, su2, robust, keep, acc, stride):
    """:func:`_fast_pass` for one kind of model (``mode`` and ``dead`` constants where it
    is inlined): the first event apart, and no branch on an event's values in the loop."""
    if hi <= lo:
        acc[:] = 0.0
        return
    jg, wg, eg = _at_g(mode, g, g0, dlog, rows.shape[0])
    vc, dgc, dtc = _eval_slot(mode, jg, wg, eg, sl[0, 0], sl[0, 1], sl[0, 2], sl[0, 3], rows,
                              dlog)
    a = 0.0
    b = 0.0
    b_on = 0.0
    b_off = 0.0
    z_max = 0.0
    chi2 = 0.0
    nl = 0.0
    prod = 1.0
    if dead:
        vs, dgs, _ = _eval(mode, jg, wg, eg, -1, False, exact, v0a, v0b, rows, dlog, locate)
        # the first event from the cycle start's level
        a, b, b_on, b_off, z_max, chi2, nl, prod = _fast_term(
            mode, jg, wg, eg, sl, 0, p[lo] > 0, vc, dgc, dtc, vs + mu_u, dgs,
            sr2 + dtc * dtc * tq2 + su2, c1, c2, lam, robust, keep, rows, dlog,
            a, b, b_on, b_off, z_max, chi2, nl, prod)
    # without a dead time, the walk from the first event's level, the crossing it stamps
    base = vc
    dbase = dgc
    var0 = dtc * dtc * tq2
    level = 0.0
    for i in range(lo + stride, hi, stride):
        r = i - lo
        vc, dgc, dtc = _eval_slot(mode, jg, wg, eg, sl[r, 0], sl[r, 1], sl[r, 2], sl[r, 3],
                                  rows, dlog)
        on = p[i] > 0
        step = c1 if on else -c2
        if dead:
            ref, dref, dte = _eval_slot(mode, jg, wg, eg, sl[r, 4], sl[r, 5], sl[r, 6],
                                        sl[r, 7], rows, dlog)
            var = sr2 + dtc * dtc * tq2 + dte * dte * eq2
        else:
            level += step
            ref = base + level - step
            dref = dbase
            var = sr2 * r + dtc * dtc * tq2 + var0
        a, b, b_on, b_off, z_max, chi2, nl, prod = _fast_term(
            mode, jg, wg, eg, sl, r, on, vc, dgc, dtc, ref, dref, var, c1, c2, lam, robust,
            keep, rows, dlog, a, b, b_on, b_off, z_max, chi2, nl, prod)
    acc[6] = nl - 2.0 * math.log(prod)
    acc[0] = a
    acc[1] = b
    acc[2] = b_on
    acc[3] = b_off
    acc[4] = z_max
    acc[5] = chi2


@nb.njit(cache=True, error_model="numpy", fastmath=_FAST_MATH)
def _fast_term(mode, jg, wg, eg, sl, r, on, vc, dgc, dtc, ref, dref, var, c1, c2, lam,
               robust, keep, rows, dlog, a, b, b_on, b_off, z_max, chi2, nl, prod):
    """One event's terms of :func:`_fast_pass`'s sums, added (the event's slots in
    ``sl[r]``; with ``keep``, its density multiplied into ``prod``, :func:`_point_terms`)."""
    step = c1 if on else -c2
    res = vc - ref - step
    jj = dgc - dref
    w = 1.0 / max(var, 1e-12)
    z2 = res * res * w
    z_max = max(z_max, z2)
    # dV/dt's own slope read whatever dV/dt (the slot is valid): no branch before it
    jac = _slope_slot(mode, jg, eg, sl[r, 0], sl[r, 1], sl[r, 2], sl[r, 3], rows,
                      dlog) / dtc
    jac = min(max(jac, -_JACOBIAN_MAX), _JACOBIAN_MAX) if dtc != 0.0 else 0.0
    if robust or keep:
        f = _time_density(z2, dtc, w)
        if keep:
            nl, prod = _density_product(f + lam, nl, prod)
        if robust:
            gam = f / (f + lam)
            w *= gam
            jac *= gam
    wj = w * jj
    chi2 += w * res * res
    a += w * res * jj - jac
    b += wj * jj
    b_on += wj if on else 0.0
    b_off -= 0.0 if on else wj
    return a, b, b_on, b_off, z_max, chi2, nl, prod


@nb.njit(cache=True, inline="always", error_model="numpy")
def _density_product(d, nl, prod):
    """An event's density ``d`` (``f + lambda``) into a sum ``-2 sum ln d`` held as ``nl -
    2 ln prod``: multiplied into ``prod``, whose logarithm is taken into ``nl`` before the
    product could leave float64's range."""
    d = max(d, _DENSITY_FLOOR)
    q = prod * d
    if q < 1e-150 or q > 1e150:
        return nl - 2.0 * (math.log(prod) + math.log(d)), 1.0
    return nl, q


@nb.njit(cache=True, error_model="numpy")
def _fast_check(mode, gs, nk, lo, hi, sl, p, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                rows, g0, dlog, locate, c1, c2, mu_u, su2, nl, have, prune, least, t, wmax,
                tail):
    """The events' ``-2 sum ln(f_i + lambda)`` (:func:`_fit_nll`'s density) under
    :func:`_fast_pass`'s model, at each of the ``nk`` points ``gs[:nk]``, into ``nl[:nk]``
    (the events' slots ``sl``, :func:`_read_slots`). With the table (mode 1) the points
    after the first (the fit's own) are moved to their nearest grid rows in ``gs``, each
    read from its row alone (:func:`_eval_row`). With ``prune``, a point after the first
    stops once its sum is sure to end at least :data:`_PROBE_MARGIN` above the first's less
    (:func:`_least_terms`, with ``least`` from :func:`_least_slots`, the events' times
    ``t`` and ``tail`` work of ``hi - lo + 1``), and ``nl`` holds that bound for it
    instead: the same decision, a fraction of the events read. Each point is summed in its
    own pass (:func:`_point_nll`); with ``have``, ``nl[0]`` holds the first's already."""
    nr = rows.shape[0]
    floor = -np.inf
    lb = -2.0 * math.log(lam) if lam > 0.0 else np.inf  # the background's own term
    for k in range(nk):
        if mode == 1 and k > 0:
            # a probe at its nearest grid row: one row read per event (the row's index
            # kept, as g0 + j dlog need not floor back to j)
            j = min(max(round((gs[k] - g0) / dlog), 0), nr - 2)
            w = 0.0
            e = 0.0
            gs[k] = g0 + dlog * j
        else:
            j, w, e = _at_g(mode, gs[k], g0, dlog, nr)
        vs, _, _ = _eval(mode, j, w, e, -1, False, exact, v0a, v0b, rows, dlog, locate)
        if k > 0 or not have:
            nl[k] = _point_nll(mode, dead, k == 0, j, w, e, vs, lo, hi, sl, p, sr2, tq2,
                               eq2, lam, lb, rows, dlog, c1, c2, mu_u, su2, floor,
                               tail)
        if k == 0 and prune and nk > 1:
            floor = nl[0] - _PROBE_MARGIN
            _least_terms(lo, hi, t, wmax, least, tail)


_CHECK_EVERY = 4
""":func:`_fast_check`'s points look whether they may stop after every this many events."""


def _steepest_slopes(rows: np.ndarray) -> np.ndarray:
    """The photoreceptor table's steepest ``|dV|`` over all its radiances, at each of its
    time intervals (:func:`_least_slots`)."""
    return np.abs(np.asarray(rows)[:, :, 1]).max(axis=0).astype(np.float64)


@nb.njit(cache=True, error_model="numpy")
def _least_slots(mode, wmax, exact, locate, dmax, sr2, tq2, lam):
    """For each whole µs slot of the window, the least that an event crossing there can add
    to :func:`_fast_check`'s sum at any ``g``. An event's variance holds at least ``sr2 +
    (dV/dt)^2 tq2``, and its density ``|dV/dt| / s phi(z)`` rises with ``|dV/dt|``, which
    is at most ``dmax`` (:func:`_steepest_slopes`) at the slot's table interval times its
    time scale (mode 1); in mode 0 ``f <= 1 / sqrt(2 pi tq2)`` alone (none without timing
    noise)."""
    out = np.empty(wmax)
    for m in range(wmax):
        if mode == 1:
            s0, _, s2, _ = _slot(mode, m, False, exact, locate)
            x = dmax[int(s0)] * abs(s2)
            v = sr2 + x * x * tq2
            f = x / math.sqrt(v) * _INV_SQRT_2PI if v > 0.0 else np.inf
        else:
            f = _INV_SQRT_2PI / math.sqrt(tq2) if tq2 > 0.0 else np.inf
        out[m] = -2.0 * math.log(max(f + lam, _DENSITY_FLOOR))
    return out


@nb.njit(cache=True, error_model="numpy")
def _least_terms(lo, hi, t, wmax, least, tail):
    """``tail[r]``: the least that events ``lo + r`` on (times ``t``) can add to
    :func:`_fast_check`'s sum at any ``g``, from the slots' ``least``
    (:func:`_least_slots`)."""
    acc = 0.0
    tail[hi - lo] = 0.0
    for r in range(hi - lo - 1, -1, -1):
        acc += least[min(t[lo + r], wmax - 1)]
        tail[r] = acc


@nb.njit(cache=True, error_model="numpy", fastmath=_FAST_MATH)
def _point_nll(mode, dead, own, j, w, e, vs, lo, hi, sl, p, sr2, tq2, eq2, lam, lb, rows, dlog,
               c1, c2, mu_u, su2, floor, tail):
    """:func:`_fast_check`'s sum at one point (what :func:`_at_g` gave as ``j, w, e``, and
    ``vs``, the cycle start's level there): read between two grid rows (``own``) or at row
    ``j`` alone (:func:`_eval_row`). Once the sum is sure to end at ``floor`` or above (the
    events from ``lo + r`` on add at least ``tail[r]``, :func:`_least_terms`), that bound
    instead. A point not the fit's own is first summed as a lower bound, each event's term
    by :func:`_term_below` (no exponential or logarithm per event): where that reaches
    the floor, the exact sum would too, and the bound is the answer; otherwise the exact
    sum follows (:func:`_point_kinds`). ``lb``: ``-2 ln lam``, the background's own term
    (:func:`_term_below`)."""
    jj = int(j)
    if own:
        return _point_kinds(mode, dead, True, False, jj, w, e, vs, lo, hi, sl, p, sr2, tq2,
                            eq2, lam, lb, rows, dlog, c1, c2, mu_u, su2, floor, tail)
    if floor > -np.inf:
        b = _point_kinds(mode, dead, False, True, jj, w, e, vs, lo, hi, sl, p, sr2, tq2, eq2,
                         lam, lb, rows, dlog, c1, c2, mu_u, su2, floor, tail)
        if b >= floor:
            return b
    return _point_kinds(mode, dead, False, False, jj, w, e, vs, lo, hi, sl, p, sr2, tq2, eq2,
                        lam, lb, rows, dlog, c1, c2, mu_u, su2, floor, tail)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _point_kinds(mode, dead, own, below, j, w, e, vs, lo, hi, sl, p, sr2, tq2, eq2, lam, lb,
                 rows, dlog, c1, c2, mu_u, su2, floor, tail):
    """:func:`_point_terms` for each of the model's four kinds, each its own loop (``own``
    and ``below`` constants where this is inlined)."""
    if mode == 1:
        if dead:
            return _point_terms(1, True, own, below, j, w, e, vs, lo, hi, sl, p, sr2, tq2,
                                eq2, lam, lb, rows, dlog, c1, c2, mu_u, su2, floor, tail)
        return _point_terms(1, False, own, below, j, w, e, vs, lo, hi, sl, p, sr2, tq2, eq2,
                            lam, lb, rows, dlog, c1, c2, mu_u, su2, floor, tail)
    if dead:
        return _point_terms(0, True, own, below, j, w, e, vs, lo, hi, sl, p, sr2, tq2, eq2,
                            lam, lb, rows, dlog, c1, c2, mu_u, su2, floor, tail)
    return _point_terms(0, False, own, below, j, w, e, vs, lo, hi, sl, p, sr2, tq2, eq2, lam, lb,
                        rows, dlog, c1, c2, mu_u, su2, floor, tail)


_TERM_MAX = -2.0 * math.log(_DENSITY_FLOOR)
"""The most one event adds to a likelihood's ``-2 sum ln(f_i + lambda)``."""


@nb.njit(cache=True, inline="always", error_model="numpy")
def _term_below(z2, var, slope, lb):
    """A lower bound of an event's ``-2 ln(max(f + lambda, floor))``
    (:func:`_time_density`'s ``f`` from ``z2``, the variance ``var`` and ``slope``;
    ``lb = -2 ln lambda``) without ``f``'s exponential: ``a = -2 ln f = z^2 + ln(2 pi var /
    slope^2)`` bounded below by :func:`_log_below`, and ``-2 ln(f + lambda) = min(a, lb) -
    2 ln(1 + e^(-|a - lb| / 2))`` with the last term bounded by a power of two built from
    bits. Within 1e-3 of the exact term where ``|a - lb| > 45``; at most 0.6 below it
    where the two meet (an event about as likely from the background as from the
    pixel)."""
    a = z2 + _log_below(6.283185307179586 * var / (slope * slope))
    # -2 ln(1 + e^(-d / 2)) >= -2 e^(-d / 2) = -2^(1 - d / (2 ln 2)), and >= -2 ln 2; the
    # power of two at most the float whose bits are (1024 - d / (2 ln 2)) 2^52 (its
    # mantissa 1 + f >= 2^f, to within the bits' truncation: 1e-15)
    d = min(abs(a - lb), 1400.0)  # the exponent then at least 14
    corr = min(1.3862943611198906, _bits_float(np.int64((1024.0 - 0.7213475204444817 * d)
                                                        * 4503599627370496.0)))
    # less 1e-9 for rounding, here and in the exact term
    return min(min(a, lb) - corr, _TERM_MAX) - 1e-9


@nb.njit(cache=True, inline="always", error_model="numpy")
def _point_read(mode, own, j, w, e, s0, s1, s2, s3, rows, dlog):
    """``(V, dV/dt)`` at a slot for :func:`_point_terms`."""
    if own:
        v, _, dt = _eval_slot(mode, j, w, e, s0, s1, s2, s3, rows, dlog)
        return v, dt
    return _eval_row(mode, j, e, s0, s1, s2, s3, rows)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _point_term(below, res, var, slope, lam, lb, nl, prod):
    """One event's term into :func:`_point_terms`'s sum ``nl - 2 ln prod`` from its
    residual ``res`` and variance ``var``: its density multiplied into ``prod``
    (:func:`_density_product`), or (``below``) the lower bound of its term
    (:func:`_term_below`) added to ``nl``."""
    iw = 1.0 / var
    z2 = res * res * iw
    if below:
        return nl + _term_below(z2, var, slope, lb), prod
    return _density_product(_time_density(z2, slope, iw) + lam, nl, prod)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _point_terms(mode, dead, own, below, j, w, e, vs, lo, hi, sl, p, sr2, tq2, eq2, lam,
                 lb, rows, dlog, c1, c2, mu_u, su2, floor, tail):
    """:func:`_point_nll` for one kind of model, reading and sum (``mode``, ``dead``,
    ``own`` and ``below`` constants where it is inlined): the first event apart, then the
    others, with :func:`_fast_pass`'s model. The densities are multiplied, the logarithm
    taken before the product could leave float64's range and every :data:`_CHECK_EVERY`
    events, where the bound is looked at; or (``below``) each term's lower bound added."""
    if hi <= lo:
        return 0.0
    nl = 0.0
    prod = 1.0
    vc, dtc = _point_read(mode, own, j, w, e, sl[0, 0], sl[0, 1], sl[0, 2], sl[0, 3], rows,
                          dlog)
    # without a dead time, the walk from the first event's level
    base = vc
    var0 = dtc * dtc * tq2
    level = 0.0
    if dead:
        # the first event from the cycle start's level
        res = vc - (vs + mu_u) - (c1 if p[lo] > 0 else -c2)
        var = max(sr2 + dtc * dtc * tq2 + su2, 1e-12)
        nl, prod = _point_term(below, res, var, dtc, lam, lb, nl, prod)
    check = floor > -np.inf
    for i in range(lo + 1, hi):
        r = i - lo
        vc, dtc = _point_read(mode, own, j, w, e, sl[r, 0], sl[r, 1], sl[r, 2], sl[r, 3],
                              rows, dlog)
        step = c1 if p[i] > 0 else -c2
        if dead:
            ref, dte = _point_read(mode, own, j, w, e, sl[r, 4], sl[r, 5], sl[r, 6],
                                   sl[r, 7], rows, dlog)
            var = sr2 + dtc * dtc * tq2 + dte * dte * eq2
        else:
            level += step
            ref = base + level - step
            var = sr2 * r + dtc * dtc * tq2 + var0
        res = vc - ref - step
        var = max(var, 1e-12)
        nl, prod = _point_term(below, res, var, dtc, lam, lb, nl, prod)
        if check and (r + 1) % _CHECK_EVERY == 0:
            bound = (nl if below else nl - 2.0 * math.log(prod)) + tail[r + 1]
            if bound >= floor:
                return bound
    return nl if below else nl - 2.0 * math.log(prod)


@nb.njit(cache=True, error_model="numpy")
def _fast_newton(mode, g, lo, hi, sl, p, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
                 dlog, locate, c1, c2, mu_u, su2, g_lo, g_hi, acc, stride=1, tol=_FAST_TOL,
                 iters=_FAST_ITER):
    """The fast fit's Newton iterations from ``g`` (:func:`_fast_pass`; the outlier weights
    once an event lies three deviations off), at most ``iters``, until a step is under
    ``tol`` deviations: ``(g, converged, keep)``, with the last pass's sums in ``acc`` and,
    when ``keep``, the check's sum at the fit in ``acc[6]``. With ``stride`` > 1, on every
    ``stride``-th event (:func:`_fast_coarse`): no outlier weights, no check's sum."""
    robust = False
    converged = False
    last = 0.0
    acc[:] = 0.0
    keep = False
    # the optimum's bracket: the points whose step went up, and down
    b_lo = -np.inf
    b_hi = np.inf
    for it in range(iters):
        # the check's sum at the fit kept from a pass likely to be the last (the step
        # before under _KEEP_STEP deviations): the converged fit lies within _FAST_TOL
        # deviations of it
        keep = stride == 1 and it > 0 and abs(last) * math.sqrt(acc[1]) < _KEEP_STEP
        _fast_pass(mode, g, lo, hi, sl, p, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                   g0, dlog, locate, c1, c2, mu_u, su2, robust, keep, acc, stride)
        if not acc[1] > 0.0:
            break
        dg = min(max(-acc[0] / acc[1], -_MAX_STEP_G), _MAX_STEP_G)
        if dg > 0.0:
            b_lo = g
        else:
            b_hi = g
        if dg * last < 0.0 and abs(dg) > 0.5 * abs(last):
            # turning back by more than half the last step: the secant's point
            dg *= abs(last) / (abs(last) + abs(dg))
        gn = min(max(g + dg, g_lo), g_hi)
        if not b_lo < gn < b_hi and b_lo > -np.inf and b_hi < np.inf:
            # a step out of the bracket (the table's rows make the curvature jump, and
            # Newton's method may cycle about the optimum): its middle
            gn = 0.5 * (b_lo + b_hi)
        last = gn - g
        g = gn
        if abs(last) < max(tol / math.sqrt(acc[1]), _FAST_TOL * _TOL_G):
            if robust or acc[4] < _FAST_OUTLIER_Z2 or lam <= 0.0 or stride > 1:
                converged = True
                break
            robust = True
            last = 0.0
            b_lo = -np.inf
            b_hi = np.inf
        elif not robust and acc[4] >= _FAST_OUTLIER_Z2 and lam > 0.0 and stride == 1 and \
                abs(last) * math.sqrt(acc[1]) < _KEEP_STEP:
            # near enough for the residuals to tell the outliers
            robust = True
            last = 0.0
            b_lo = -np.inf
            b_hi = np.inf
    return g, converged, keep


@nb.njit(cache=True, error_model="numpy")
def _fast_coarse(mode, g, lo, hi, sl, p, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                 g0, dlog, locate, c1, c2, mu_u, su2, g_lo, g_hi, acc):
    """The fast fit's start brought near its optimum on subsets of the events (with a
    dead time, where each event's term stands alone): Newton's method on every ``s``-th
    event (``s = n //`` :data:`_COARSE_EVENTS`) until a step is under
    :data:`_COARSE_TOL` of that subset's deviations, then one step on every ``s / 4``-th,
    and so on while the stride exceeds 1 (:func:`_fast_newton`). The optimum on every
    ``s``-th event lies about ``sqrt(s - 1)`` of the fit's deviations from the fit on
    every event (its own deviation is ``sqrt(s)`` times the fit's), so each step starts a
    few of its subset's deviations off, and the fit on every event typically starts
    under :data:`_KEEP_STEP` of its own: one plain pass, then the pass that keeps the
    check's sum. ``g`` unchanged without a dead time or with fewer than ``2 *``
    :data:`_COARSE_EVENTS` events."""
    s = (hi - lo) // _COARSE_EVENTS if dead else 0
    iters = _FAST_ITER  # to convergence on the first subset, one step on each after
    while s > 1:
        g, _, _ = _fast_newton(mode, g, lo, hi, sl, p, dead, sr2, tq2, eq2, lam, exact, v0a,
                               v0b, rows, g0, dlog, locate, c1, c2, mu_u, su2, g_lo, g_hi,
                               acc, s, _COARSE_TOL, iters)
        s //= _COARSE_FACTOR
        iters = 1
    return g


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _fast_kernel(off, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0, dlog,
                 locate, wmax, g_lo, g_hi, net_g, net_v, min_events, con0, coff0, scon,
                 scoff, out_g, out_sd, out_con, out_coff, out_flag, u_sd, split, net_v2,
                 split2, order, out_u, out_full, hold_sd, least, out_retry):
    """Every pixel's fast fit (docs/ml.md, "The fast fit"): ``g`` alone, the thresholds
    held at their priors (a calibration's, or learned ones whose spreads are at most
    ``hold_sd``: the others are fitted in full), by Newton's method on the likelihood from
    the net change's start (:func:`_fast_newton`), brought near on subsets of the events
    first (:func:`_fast_coarse`). Where the likelihood is lower by more
    than :data:`_PROBE_MARGIN` at one of the points :data:`_FAST_PROBES` away (another
    optimum), the fit is made again from the likeliest of them, once. A fit that does not
    converge, reaches a bound or is vague, whose chi-square lies beyond its spread with no
    likelier point near, or that still finds a likelier point, is fitted in full
    (:func:`_fit_pixel`; ``out_full[px]`` set; ``out_retry[px]`` where it was made
    again). The variance adds the thresholds' spread
    through ``dg/dc``. ``split2`` and ``net_v2`` are the full fit's."""
    npx = off.shape[0] - 1
    nblk = order.shape[0]
    for bi in nb.prange(nblk):
        blk = order[bi]
        h, bvec, x, lmat, wy, wz, stat, st_o = _workspace()
        acc = np.zeros(7)
        gs = np.empty(len(_FAST_PROBES) + 1)
        nl = np.empty(len(_FAST_PROBES) + 1)
        res, saved, work, scan = _fit_space(g_lo, g_hi)
        n_max = 0
        for px in range(blk * _BLOCK, min(npx, (blk + 1) * _BLOCK)):
            n_max = max(n_max, off[px + 1] - off[px])
        sl = np.empty((n_max, 8))
        tail = np.empty(n_max + 1)
        for px in range(blk * _BLOCK, min(npx, (blk + 1) * _BLOCK)):
            lo = off[px]
            hi = off[px + 1]
            c1 = con0[px]
            c2 = coff0[px]
            out_con[px] = c1
            out_coff[px] = c2
            if hi - lo < min_events:
                out_g[px] = np.nan
                out_sd[px] = np.nan
                out_flag[px] = FLAG_NO_EVENTS
                continue
            s1 = max(scon[px], 1e-6)
            s2 = max(scoff[px], 1e-6)
            su, mu_u = _u_prior(c1, c2, u_sd)
            net = 0.0
            for i in range(lo, hi):
                if t[i] >= split:
                    break
                net += c1 if p[i] > 0 else -c2
            g = _initial(net, net_g, net_v)
            held = s1 <= hold_sd and s2 <= hold_sd
            poor = True
            n = hi - lo
            var = np.inf
            flag = 0
            if held:
                _read_slots(mode, lo, hi, t, dead, exact, locate, wmax, sl)
            for _attempt in range(2 if held else 0):
                g = _fast_coarse(mode, g, lo, hi, sl, p, dead, sr2, tq2, eq2, lam, exact, v0a,
                                 v0b, rows, g0, dlog, locate, c1, c2, mu_u, su * su, g_lo,
                                 g_hi, acc)
                g, converged, keep = _fast_newton(mode, g, lo, hi, sl, p, dead, sr2, tq2, eq2,
                                                  lam, exact, v0a, v0b, rows, g0, dlog, locate,
                                                  c1, c2, mu_u, su * su, g_lo, g_hi, acc)
                var = 1.0 / acc[1] if acc[1] > 0.0 else np.inf
                # the thresholds held: their spread moves g by dg/dc = sum w J / sum w J^2
                var += (acc[2] * acc[2] * s1 * s1 + acc[3] * acc[3] * s2 * s2) * var * var
                flag = _fit_flag(g, var, g_lo, g_hi)
                if not converged or flag != 0:
                    break
                # the likelihood's profile (thresholds held) at a few points about the fit:
                # a likelier one means another optimum
                gs[0] = g
                nl[0] = acc[6]
                nk = 1
                for d in _FAST_PROBES:
                    gq = min(max(g + d, g_lo), g_hi)
                    if gq != g:
                        gs[nk] = gq
                        nk += 1
                _fast_check(mode, gs, nk, lo, hi, sl, p, dead, sr2, tq2, eq2, lam, exact, v0a,
                            v0b, rows, g0, dlog, locate, c1, c2, mu_u, su * su, nl, keep,
                            True, least, t, wmax, tail)
                best = 0
                for k in range(1, nk):
                    if nl[k] < nl[0] - _PROBE_MARGIN and nl[k] < nl[best]:
                        best = k
                fits = acc[5] <= n + _FAST_CHI2_Z * math.sqrt(2.0 * n) + 2.0
                if best == 0 and fits:
                    poor = False
                    break
                if best == 0:
                    # a chi-square beyond its spread with no likelier point near: the
                    # thresholds held do not explain the events
                    break
                # another optimum: the fit again from the likeliest point (once)
                g = gs[best]
                out_retry[px] = 1
            if poor:
                _fit_pixel(lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                           rows, g0, dlog, locate, wmax, g_lo, g_hi, net_g, net_v, c1, c2, s1,
                           s2, 0.0, 0.0, False, h, bvec, x, lmat, wy, wz, res, u_sd, stat,
                           work, scan, split, st_o, net_v2, split2, saved)
                out_g[px] = res[0]
                out_sd[px] = res[1]
                out_con[px] = res[2]
                out_coff[px] = res[3]
                out_flag[px] = np.uint8(res[4])
                out_u[px] = res[5]
                out_full[px] = 1
                continue
            out_g[px] = g
            out_sd[px] = math.sqrt(var)
            out_flag[px] = flag
            out_u[px] = mu_u


@nb.njit(cache=True, error_model="numpy")
def _threshold_sd_at(px, off, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                     g0, dlog, locate, wmax, con0, coff0, scon, scoff, u_sd, fit_g, fit_sd,
                     fit_u, fit_con, fit_coff, fit_flag, out_son, out_soff, h, bvec, x, lmat,
                     wy, wz, stat):
    """:func:`_threshold_sd_kernel` for pixel ``px`` (the rest are work space)."""
    out_son[px] = np.nan
    out_soff[px] = np.nan
    if fit_flag[px] != 0:
        return
    c1 = con0[px]
    c2 = coff0[px]
    s1 = max(scon[px], 1e-6)
    s2 = max(scoff[px], 1e-6)
    su, _ = _u_prior(c1, c2, u_sd)
    ok, v_g = _information(fit_g[px], fit_u[px], fit_con[px], fit_coff[px], off[px],
                           off[px + 1], t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                           rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su, h, bvec, x, lmat,
                           wy, wz, stat)
    if not ok:
        return
    # wz holds L^-1 e_0: (h^-1)[k, 0] = (L^-1 e_k) . (L^-1 e_0)
    z0 = wz[0]
    z1 = wz[1]
    z2 = wz[2]
    z3 = wz[3]
    # the fit's variance of ln L beyond this matrix's (a second optimum, :func:`_probe`)
    # carries the thresholds along the ridge they share with ln L
    extra = max(fit_sd[px] * fit_sd[px] - v_g, 0.0) if v_g > 0.0 else 0.0
    for k in (2, 3):
        v = _inv_diag(lmat, k, wz)
        if extra > 0.0:
            cov = wz[0] * z0 + wz[1] * z1 + wz[2] * z2 + wz[3] * z3
            v += (cov / v_g) ** 2 * extra
        if k == 2:
            out_son[px] = math.sqrt(v)
        else:
            out_soff[px] = math.sqrt(v)


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _threshold_sd_kernel(off, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                         g0, dlog, locate, wmax, con0, coff0, scon, scoff, u_sd, fit_g,
                         fit_sd, fit_u, fit_con, fit_coff, fit_flag, out_son, out_soff):
    """The posterior standard deviations of every fitted pixel's ``c_on`` and ``c_off``
    (the others marginalised): the inverse of the Gauss-Newton matrix at its fit, its
    events with the outlier weights and its priors; NaN where the pixel has no fit (flag
    not 0) or the matrix is not positive definite."""
    npx = off.shape[0] - 1
    for blk in nb.prange((npx + _BLOCK - 1) // _BLOCK):
        h, bvec, x, lmat, wy, wz, stat, _ = _workspace()  # once per block of pixels
        for px in range(blk * _BLOCK, min(npx, (blk + 1) * _BLOCK)):
            _threshold_sd_at(px, off, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                             rows, g0, dlog, locate, wmax, con0, coff0, scon, scoff, u_sd,
                             fit_g, fit_sd, fit_u, fit_con, fit_coff, fit_flag, out_son,
                             out_soff, h, bvec, x, lmat, wy, wz, stat)


_NEIGHBOUR_GAP = 0.5
"""A pixel whose ``ln L`` lies further than this from the median of its neighbours' is
fitted again from that median (:func:`_neighbour_starts`)."""
_NEIGHBOUR_SPREAD = 0.5
"""... when its neighbours agree: their median absolute deviation from their median in
``ln L`` at most this (a textured or random neighbourhood offers no start)."""
_NEIGHBOUR_SWEEPS = 3
"""At most this many sweeps of :func:`_neighbour_starts`, each over the neighbours of the
pixels the last one moved (a cluster of stuck pixels is reached from its edge inwards)."""


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _neighbour_starts(off, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows, g0,
                      dlog, locate, wmax, g_lo, g_hi, con0, coff0, scon, scoff, u_sd, width,
                      min_events, todo, out_g, out_sd, out_con, out_coff, out_flag, out_u,
                      moved):
    """The neighbours' fits as further starts (the propagation of PatchMatch): a listed
    pixel (``todo``) whose ``g`` lies more than :data:`_NEIGHBOUR_GAP` from the median of
    its 8 neighbours' informed fits, these agreeing (:data:`_NEIGHBOUR_SPREAD`), or whose
    own fit is uninformed or at a bound, is fitted again from that median; the new fit
    replaces the old when its events' likelihood is higher (:func:`_fit_nll`, priors
    included). A start is all a neighbour gives: the pixel's estimate
    remains its own events' best fit, never a blend. Reads the fits as they stood (so the
    result does not depend on the order of the pixels); ``moved[px]`` is set where a fit
    was replaced. Returns how many."""
    npx = off.shape[0] - 1
    height = npx // width
    g_in = out_g.copy()
    fl_in = out_flag.copy()
    n_moved = np.zeros(height, np.int64)
    for y in nb.prange(height):
        h, bvec, x, lmat, wy, wz, stat, st_o = _workspace()
        res = np.zeros(6)
        own = np.zeros(6)
        held = np.zeros(6)
        ng = np.zeros(8)
        dev = np.zeros(8)
        none = np.int64(-1)
        for xx in range(width):
            px = y * width + xx
            lo = off[px]
            hi = off[px + 1]
            if todo[px] == 0 or hi - lo < min_events:
                continue
            k = 0
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy = y + dy
                    x2 = xx + dx
                    if (dy == 0 and dx == 0) or yy < 0 or yy >= height or x2 < 0 \
                            or x2 >= width:
                        continue
                    q = yy * width + x2
                    if fl_in[q] == 0:
                        ng[k] = g_in[q]
                        k += 1
            if k < 3:
                continue
            med = np.median(ng[:k])
            for j in range(k):
                dev[j] = abs(ng[j] - med)
            if np.median(dev[:k]) > _NEIGHBOUR_SPREAD:
                continue
            gi = g_in[px]
            if fl_in[px] == 0 and abs(gi - med) <= _NEIGHBOUR_GAP:
                continue
            c1 = con0[px]
            c2 = coff0[px]
            s1 = max(scon[px], 1e-6)
            s2 = max(scoff[px], 1e-6)
            su, mu_u = _u_prior(c1, c2, u_sd)
            own_obj = np.inf
            if gi == gi:
                own[0] = gi
                own[2] = out_u[px]
                own[3] = out_con[px]
                own[4] = out_coff[px]
                own_obj = _fit_nll(own, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact,
                                   v0a, v0b, rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su,
                                   mu_u, none, none, h, bvec, st_o)
            _fit_from(med, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b, rows,
                      g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u, 0.0, 0.0,
                      none, none, h, bvec, x, lmat, wy, wz, stat, res, st_o)
            obj = _fit_nll(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                           rows, g0, dlog, locate, wmax, c1, c2, s1, s2, su, mu_u, none, none,
                           h, bvec, st_o)
            # the likelihood's profile walked from the median (thresholds and u fitted at
            # each ln L held): Gauss-Newton from the median, its thresholds starting at
            # their priors, can slide back to where the residuals' least squares is least
            # and the events' times are far less likely (the pixel's own fit)
            _profile_at(med, held, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a,
                        v0b, rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su,
                        mu_u, h, bvec, x, lmat, wy, wz, stat, st_o)
            held[0] = med
            held[1] = np.inf
            _profile_walk(held, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                          rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u,
                          h, bvec, x, lmat, wy, wz, st_o)
            obj2 = _profile_polish(held, _PROFILE_POLISH, lo, hi, t, p, mode, dead, sr2, tq2,
                                   eq2, lam, exact, v0a, v0b, rows, g0, dlog, locate, wmax,
                                   g_lo, g_hi, c1, c2, s1, s2, su, mu_u, h, bvec, x, lmat, wy,
                                   wz, st_o)
            if obj2 < obj and held[1] < _VAR_INFORMED:
                obj = obj2
                res[:] = held
            if not obj < own_obj - _NLL_TOL:
                continue
            flag = _settle(res, lo, hi, t, p, mode, dead, sr2, tq2, eq2, lam, exact, v0a, v0b,
                           rows, g0, dlog, locate, wmax, g_lo, g_hi, c1, c2, s1, s2, su, mu_u,
                           h, bvec, x, lmat, wy, wz, st_o)
            out_g[px] = res[0]
            out_sd[px] = math.sqrt(res[1]) if res[1] == res[1] and res[1] >= 0.0 else np.nan
            out_con[px] = res[3]
            out_coff[px] = res[4]
            out_u[px] = res[2]
            out_flag[px] = flag
            moved[px] = 1
            n_moved[y] += 1
    return n_moved.sum()


# ----------------------------------------------------------------------------- few events


@nb.njit(cache=True, inline="always", error_model="numpy")
def _cdf(z):
    return 0.5 * math.erfc(-z * 0.7071067811865476)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _node_at(ext_t, x):
    """Index of the last of the times ``ext_t`` at or before ``x`` (0 before the first)."""
    lo = 0
    hi = ext_t.shape[0] - 1
    if x >= ext_t[hi]:
        return hi
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if ext_t[mid] <= x:
            lo = mid
        else:
            hi = mid
    return lo


@nb.njit(cache=True, inline="always", error_model="numpy")
def _silence(ext, j, c1, c2, s1, s2, u_sd):
    """The probability that grid row ``j``'s signal fires no event in the window. The start
    offset uniform over ``(-c_on, c_off)``: ``E[(C - swing)+] / C`` with ``C = c_on + c_off``
    Gaussian (its mean in the denominator, or the swing where that is larger: where the
    mass lies); settled (``u_sd > 0``): neither threshold reached from ``V(0)``."""
    last = ext.shape[1] - 1
    vmax = ext[0, last, j]
    vmin = ext[1, last, j]
    if u_sd > 0.0:
        v0 = ext[0, 0, j]
        return (_cdf((c1 - (vmax - v0)) / math.sqrt(s1 * s1 + u_sd * u_sd))
                * _cdf((c2 - (v0 - vmin)) / math.sqrt(s2 * s2 + u_sd * u_sd)))
    mu = c1 + c2
    sd = math.sqrt(s1 * s1 + s2 * s2)
    sw = vmax - vmin
    if sd > 0.0:
        z = (mu - sw) / sd
        exc = sd * math.exp(-0.5 * z * z) * _INV_SQRT_2PI + (mu - sw) * _cdf(z)
    else:
        exc = max(mu - sw, 0.0)
    return exc / max(mu, sw)


@nb.njit(cache=True, error_model="numpy")
def _one_event(m, sg, ext, ext_t, j, jj, ww, e, mode, exact, v0a, v0b, rows, dlog, locate,
               tc_off, te_off, t_end, s_t, sr2, c1, c2, s1, s2, u_sd):
    """The density (per µs) that grid row ``j``'s signal fires one event, of sign ``sg``, in
    whole µs slot ``m`` and none else in the window: its crossing is the signal's first
    exit from the band (a new extreme, the other threshold not reached before), after the
    dead time's reset none follows. In ``W = sg V``, with ``a`` the threshold crossed."""
    if sg > 0:
        ca, cb, sa, sb, ia, ib = c1, c2, s1, s2, 0, 1
    else:
        ca, cb, sa, sb, ia, ib = c2, c1, s2, s1, 1, 0
    n = ext_t.shape[0]
    vc, _, dvt = _eval(mode, jj, ww, e, m, False, exact, v0a, v0b, rows, dlog, locate)
    wc = sg * vc
    wd = sg * dvt
    if not wd > 0.0:
        return 0.0
    w0 = sg * ext[0, 0, j]
    tc = max(m + tc_off, 0.0)
    # a new extreme: above every earlier value, up to the timing's spread before it
    back = int(math.ceil(2.0 * s_t)) + 1  # noqa: RUF046 (numba)
    w_prev = w0
    if m - back >= 0:
        vp, _, _ = _eval(mode, jj, ww, e, m - back, False, exact, v0a, v0b, rows, dlog,
                         locate)
        i = _node_at(ext_t, max(m - back + tc_off, 0.0))
        w_prev = max(sg * vp, sg * ext[ia, i, j])
    first = _cdf((wc - w_prev) / (wd * s_t + 1e-12))
    i = _node_at(ext_t, tc)
    w_low = min(wc, sg * ext[ib, i, j])
    if u_sd > 0.0:
        va = sa * sa + u_sd * u_sd
        d = wc - w0 - ca
        dens = wd * math.exp(-0.5 * d * d / va) / math.sqrt(2.0 * math.pi * va)
        other = _cdf((cb - (w0 - w_low)) / math.sqrt(sb * sb + u_sd * u_sd))
    else:
        mu = ca + cb
        dens = wd / mu
        other = _cdf((mu - (wc - w_low)) / max(math.sqrt(sa * sa + sb * sb), 1e-6))
    # after the reset: the signal stays within both thresholds to the window's end
    after = 1.0
    te = m + te_off
    if te < t_end:
        ve, _, _ = _eval(mode, jj, ww, e, m, True, exact, v0a, v0b, rows, dlog, locate)
        we = sg * ve
        i = _node_at(ext_t, te) + 1
        w_hi = we
        w_lo = we
        if i < n:  # the running extremes to the end (W's maximum is V's, or -V's minimum)
            w_hi = max(we, sg * ext[ia + 2, i, j])
            w_lo = min(we, sg * ext[ib + 2, i, j])
        after = (_cdf((ca - (w_hi - we)) / math.sqrt(sa * sa + sr2 + 1e-12))
                 * _cdf((cb - (we - w_lo)) / math.sqrt(sb * sb + sr2 + 1e-12)))
    return dens * first * other * after


_SILENT_SWEEPS = 8
"""At most this many passes of :func:`_sparse_kernel`, each over the silent pixels the
last left without an estimate."""
_SILENT_PRIOR_SD = 0.5
"""The least spread (``ln L``) of the neighbours' prior that weighs a silent pixel's
silence against a dead pixel (:func:`_sparse_kernel`)."""


@nb.njit(cache=True, error_model="numpy")
def _neighbour_median(px, width, fit_g, fit_flag):
    """The median of pixel ``px``'s 8 neighbours' estimates (flag 0 or
    :data:`FLAG_FEW_EVENTS`) and their spread (1.4826 times the median absolute
    deviation); NaN with fewer than 3."""
    npx = fit_g.shape[0]
    height = npx // width
    y = px // width
    xx = px - y * width
    ng = np.empty(8)
    k = 0
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            yy = y + dy
            x2 = xx + dx
            if (dy == 0 and dx == 0) or yy < 0 or yy >= height or x2 < 0 or x2 >= width:
                continue
            q = yy * width + x2
            if fit_flag[q] == 0 or fit_flag[q] == FLAG_FEW_EVENTS:
                ng[k] = fit_g[q]
                k += 1
    if k < 3:
        return np.nan, np.nan
    med = np.median(ng[:k])
    for j in range(k):
        ng[j] = abs(ng[j] - med)
    return med, 1.4826 * np.median(ng[:k])


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _sparse_kernel(todo, off, t, p, mode, exact, v0a, v0b, rows, g0, dlog, locate, wmax,
                   ext_t, ext, ext_g, tc_off, te_off, tq2, sr2, lam, con0, coff0, scon,
                   scoff, u_sd, dead_fraction, width, fit_g, fit_flag, out_g, out_sd,
                   out_flag):
    """Pixels ``todo`` (fewer than two events: none, or one) estimated from the likelihood
    of so few events on the grid ``ext_g`` of ``ln L`` (flat prior over the model's
    range): its mean and standard deviation (with the grid's step). No event: the silence
    (:func:`_silence`), which a dead pixel explains too (``dead_fraction`` of all): the
    pixel keeps no estimate where that is likelier. The silence's evidence is weighed
    with the pixel's 8 neighbours' estimates (``fit_g`` where ``fit_flag`` is 0 or
    :data:`FLAG_FEW_EVENTS`) as the prior of ``ln L``, Gaussian about their median, of
    their spread and at least :data:`_SILENT_PRIOR_SD` (with fewer than 3 such
    neighbours, flat over the range): a silent pixel among neighbours near ``L_const`` is
    likely working, one in a patch far from it likely dead. The estimate itself is the
    silence's alone. One event: its density
    (:func:`_one_event`), or a background event (rate ``lam`` per µs) and silence. Flags
    :data:`FLAG_FEW_EVENTS` (with :data:`FLAG_UNINFORMED` where the deviation is 1 or more);
    the pixels whose events no ``g`` explains keep :data:`FLAG_NO_EVENTS`."""
    ng = ext_g.shape[0]
    t_end = ext_t[ext_t.shape[0] - 1]
    s_t = math.sqrt(tq2)
    for q in nb.prange(todo.shape[0]):
        px = todo[q]
        lo = off[px]
        n = off[px + 1] - lo
        c1 = con0[px]
        c2 = coff0[px]
        s1 = scon[px]
        s2 = scoff[px]
        z = 0.0
        m1 = 0.0
        m2 = 0.0
        m = min(t[lo], wmax - 1) if n == 1 else 0
        sg = 1.0 if n == 1 and p[lo] > 0 else -1.0
        silence = np.empty(ng)
        for j in range(ng):
            g = ext_g[j]
            jj, ww, e = _at_g(mode, g, g0, dlog, rows.shape[0])
            pr = _silence(ext, j, c1, c2, s1, s2, u_sd)
            silence[j] = pr
            if n == 1:
                pr = lam * pr + _one_event(m, sg, ext, ext_t, j, jj, ww, e, mode, exact, v0a,
                                           v0b, rows, dlog, locate, tc_off, te_off, t_end,
                                           s_t, sr2, c1, c2, s1, s2, u_sd)
            if not pr > 0.0:
                continue
            z += pr
            m1 += pr * g
            m2 += pr * g * g
        if not z > 0.0:
            continue
        if n == 0 and dead_fraction > 0.0:
            evidence = z / ng
            med, spread = _neighbour_median(px, width, fit_g, fit_flag)
            if med == med:
                sp = max(spread, _SILENT_PRIOR_SD)
                evidence = 0.0
                for j in range(ng):
                    d = (ext_g[j] - med) / sp
                    if d * d < 50.0:
                        evidence += silence[j] * math.exp(-0.5 * d * d)
                evidence *= (ext_g[1] - ext_g[0]) / (sp * 2.5066282746310002)
            if (1.0 - dead_fraction) * evidence <= dead_fraction:
                continue
        mean = m1 / z
        step = ext_g[1] - ext_g[0] if ng > 1 else 0.0
        var = max(m2 / z - mean * mean, 0.0) + step * step / 12.0
        out_g[px] = mean
        out_sd[px] = math.sqrt(var)
        out_flag[px] = FLAG_FEW_EVENTS | (FLAG_UNINFORMED if var >= _VAR_INFORMED else 0)


# ----------------------------------------------------------------------------- grouping


_GROUP_SHIFT = 13
"""The grouping puts the events into buckets of ``2**13`` consecutive pixels (a few MB of
events each), then sorts each bucket by pixel in cache. At most 16: a bucket holds a
pixel's index within it as ``uint16``."""


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _group_count(x, y, t, t0, t1, width, nbk, bounds):
    """:func:`group_by_pixel`'s first pass: per thread (its slice of the stream between
    ``bounds``), the events with ``t0 <= t < t1`` in each bucket of :data:`_GROUP_SHIFT`
    pixels, ``(threads, nbk)``."""
    nthr = bounds.shape[0] - 1
    bc = np.zeros((nthr, nbk), np.int64)
    for c in nb.prange(nthr):
        for i in range(bounds[c], bounds[c + 1]):
            if t[i] >= t0 and t[i] < t1:
                bc[c, (np.int64(y[i]) * width + x[i]) >> _GROUP_SHIFT] += 1
    return bc


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _group_fill(x, y, p, t, t0, t1, width, npx, bounds, cur, start, b_px, b_t, b_p, off,
                out_t, out_p):
    """:func:`group_by_pixel`'s second and third passes: each thread's events into the
    buckets from its cursors ``cur`` (so the stream's order is kept), as the pixel within
    the bucket, ``t - t0`` and ``p``; then each bucket (from ``start``), whose events and
    counts fit in cache, by pixel into ``off``, ``out_t`` and ``out_p``, and a pixel whose
    events are not in time order there (a stream that steps back) sorted by time, stably.
    Returns how many pixels were."""
    nthr = bounds.shape[0] - 1
    nbk = start.shape[0] - 1
    for c in nb.prange(nthr):
        cc = cur[c]
        for i in range(bounds[c], bounds[c + 1]):
            ti = t[i]
            if ti >= t0 and ti < t1:
                j = np.int64(y[i]) * width + x[i]
                k = j >> _GROUP_SHIFT
                d = cc[k]
                b_px[d] = j - (k << _GROUP_SHIFT)
                b_t[d] = ti - t0
                b_p[d] = p[i]
                cc[k] = d + 1
    resorted = np.zeros(nbk, np.int64)
    for k in nb.prange(nbk):
        p0 = k << _GROUP_SHIFT
        p1 = min(npx, (k + 1) << _GROUP_SHIFT)
        if p1 <= p0:
            continue
        cnt = np.zeros(p1 - p0 + 1, np.int64)
        for d in range(start[k], start[k + 1]):
            cnt[np.int64(b_px[d]) + 1] += 1
        cnt[0] = start[k]
        for j in range(p1 - p0):
            cnt[j + 1] += cnt[j]
        for j in range(p1 - p0):
            off[p0 + j] = cnt[j]
        for d in range(start[k], start[k + 1]):
            j = np.int64(b_px[d])
            e = cnt[j]
            out_t[e] = b_t[d]
            out_p[e] = b_p[d]
            cnt[j] = e + 1
        resorted[k] = _sort_pixels(off, out_t, out_p, p0, p1, start[k + 1])
    off[npx] = start[nbk]
    return resorted.sum()


@nb.njit(cache=True, error_model="numpy")
def _sort_pixels(off, t, p, p0, p1, end):
    """Pixels ``p0 .. p1 - 1``'s events (from ``off``, the last's up to ``end``) put in
    time order where they are not, stably; how many pixels were."""
    n = 0
    for px in range(p0, p1):
        lo = off[px]
        hi = off[px + 1] if px + 1 < p1 else end
        sorted_ = True
        for e in range(lo + 1, hi):
            if t[e] < t[e - 1]:
                sorted_ = False
                break
        if sorted_:
            continue
        n += 1
        order = np.argsort(t[lo:hi], kind="mergesort")
        ts = t[lo:hi][order]
        ps = p[lo:hi][order]
        t[lo:hi] = ts
        p[lo:hi] = ps
    return n


def group_by_pixel(events: np.ndarray, *, width: int, height: int, start_us: int,
                   window_us: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The events of ``[start_us, start_us + window_us)`` grouped by pixel, in time order
    within a pixel (stably: as if the stream had been sorted by time first):
    ``(offsets (n_pixels + 1,) int64, t (µs from start_us, int32), p (int8))``."""
    if not 0 < window_us < 2**31:
        raise ValueError(f"ml: a cycle's window is 1 µs to 2**31 µs (35 min); got "
                         f"{window_us} µs")
    # a stable counting sort by pixel in three passes, each on every thread: the events
    # counted per bucket of 2**_GROUP_SHIFT pixels, put into the buckets (each thread its
    # slice of the stream), then by pixel within each bucket. The buffers come from numpy,
    # whose large arrays Linux may map in huge pages: touching them costs about a third of
    # what arrays allocated in the compiled code do
    npx = width * height
    n = events.size
    nthr = nb.get_num_threads()
    bounds = np.array([n * c // nthr for c in range(nthr + 1)], dtype=np.int64)
    nbk = (npx >> _GROUP_SHIFT) + 1
    t0 = np.int64(start_us)
    t1 = np.int64(start_us + window_us)
    x, y, tt = events["x"], events["y"], events["t"]
    counts = _group_count(x, y, tt, t0, t1, np.int64(width), nbk, bounds)
    flat = counts.T.ravel()  # bucket-major, thread within
    cur_flat = np.concatenate([[0], np.cumsum(flat)[:-1]]).astype(np.int64)
    cur = np.ascontiguousarray(cur_flat.reshape(nbk, nthr).T)
    start = np.append(cur[0], cur_flat[-1] + flat[-1]).astype(np.int64)
    total = int(start[-1])
    off = np.empty(npx + 1, np.int64)
    t = np.empty(total, np.int32)
    p = np.empty(total, np.int8)
    resorted = _group_fill(x, y, events["p"], tt, t0, t1, np.int64(width), np.int64(npx),
                           bounds, cur, start, np.empty(total, np.uint16),
                           np.empty(total, np.int32), np.empty(total, np.int8), off, t, p)
    if resorted:
        logger.info("ml: %d pixels' events were not in time order in [%d, %d) µs; sorted",
                    resorted, start_us, start_us + window_us)
    return off, t, p


# ----------------------------------------------------------------------------- public


@dataclass(frozen=True, eq=False)
class MlResult:
    """What :func:`estimate` returns, per cycle, ``(n_cycles, height, width)``.

    Attributes
    ----------
    radiance : float32 ``L = exp(g_hat)`` in the unit of ``L_const``; NaN without events
        or information, the range's bound where the estimate reached it.
    sigma_log : float32 standard deviation of ``ln L`` (the bound at the estimate).
    flags : uint8, 0 (estimated), :data:`FLAG_NO_EVENTS`, :data:`FLAG_OUT_OF_RANGE`,
        :data:`FLAG_UNINFORMED`; :func:`reconstruct_ml` adds :data:`FLAG_FILLED`.
    c_on, c_off : float32 the thresholds fitted with the radiance (their priors where no
        event constrains them).
    n_events : int32 events used per pixel.
    sd_on, sd_off : float32 the thresholds' posterior standard deviations (NaN where the
        pixel has no fit), when :func:`estimate` was asked for them; else None.
    full_fits : int64 ``(n_cycles,)``, with the fast fit: the pixels of each cycle fitted
        in full (thresholds not yet learned, or a failed check); else None.
    """

    radiance: np.ndarray
    sigma_log: np.ndarray
    flags: np.ndarray
    c_on: np.ndarray
    c_off: np.ndarray
    n_events: np.ndarray
    sd_on: np.ndarray | None = None
    sd_off: np.ndarray | None = None
    full_fits: np.ndarray | None = None

    @staticmethod
    def concatenate(parts: Sequence[MlResult]) -> MlResult:
        """The cycles of ``parts``, in order, as one result."""
        def cat(name: str) -> Any:
            vals = [getattr(r, name) for r in parts]
            return None if any(v is None for v in vals) else np.concatenate(vals)
        return MlResult(**{f.name: cat(f.name) for f in dataclasses.fields(MlResult)})

    @property
    def mask(self) -> np.ndarray:
        """True where the pixel has an estimate inside the model's range (from its fit, an
        ambiguous one's too, :data:`FLAG_AMBIGUOUS`, or from how few events it fired:
        :data:`FLAG_FEW_EVENTS`)."""
        return valid_flags(self.flags)


def valid_flags(flags: np.ndarray) -> np.ndarray:
    """True where ``flags`` (:class:`MlResult`'s) mark an estimate inside the model's range:
    a fit (0; :data:`FLAG_AMBIGUOUS`) or an estimate from fewer than two events
    (:data:`FLAG_FEW_EVENTS`)."""
    f = np.asarray(flags)
    return (f == 0) | (f == FLAG_FEW_EVENTS) | (f == FLAG_AMBIGUOUS)


def thresholds_prior(sensor: SensorParams, *, width: int, height: int,
                     c_on: np.ndarray | None = None, c_off: np.ndarray | None = None,
                     sigma: float | np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel threshold priors ``(c_on, c_off, sigma_on, sigma_off)`` (flat arrays):
    the calibrated maps when given (``sigma`` their error, default 0.005), else the
    sensor's nominal thresholds with its mismatch ``threshold_sigma`` as the spread."""
    npx = width * height
    if c_on is None or c_off is None:
        on = np.full(npx, sensor.threshold_on)
        off = np.full(npx, sensor.threshold_off)
        s = np.full(npx, max(sensor.threshold_sigma, 0.0))
        return on, off, s, s.copy()
    on = np.asarray(c_on, dtype=np.float64).ravel()
    off = np.asarray(c_off, dtype=np.float64).ravel()
    if on.size != npx or off.size != npx:
        raise ValueError(f"threshold maps must have {height}x{width} pixels, got {on.size} "
                         f"and {off.size}")
    sg = 0.005 if sigma is None else sigma
    s = np.broadcast_to(np.asarray(sg, dtype=np.float64).ravel() if np.ndim(sg) else
                        np.asarray(sg, dtype=np.float64), (npx,)).astype(np.float64)
    return on, off, s, s.copy()


LEARN_SD_FLOOR = 0.005
"""The least spread :class:`LearnedThresholds` gives a learned threshold (the spread a
calibration file's thresholds get by default, :func:`thresholds_prior`): the posterior's
Gaussian approximation is not trusted below it."""

FAST_HOLD_SD = 0.01
"""The fast fit (``reconstruct_ml(..., fast=True)``) holds a learned threshold once its
spread is at most this (:class:`LearnedThresholds`); until then the pixel is fitted in
full, and learns."""

LEARN_MIN_EVENTS = 10
"""A cycle teaches :class:`LearnedThresholds` a pixel's thresholds only where the pixel
fired at least this many events in it: with as few events as parameters (``ln L``, the
start offset and two thresholds) the fit's matrix claims a precision its optimum does not
have (a pixel near ``L_const``, four events, a fit 1.5 off in ``ln L`` with thresholds of
0.10 and 0.16 against 0.29 and 0.34, stated to 0.007)."""

LEARN_GATE = 3.0
"""A cycle's fit moves a pixel's learned threshold only when it lies within this many of
the prior's standard deviations of the prior's mean: a fit further off is more likely a
wrong optimum than a threshold that far out."""


LEARN_POPULATION_MIN = 100
"""Pixels that must have learned a threshold, where learning selects none by its
threshold (:func:`_unselected`), before their median replaces the sensor's nominal
threshold as the prior of the pixels that have not learned (:class:`LearnedThresholds`)."""

LEARN_BIN = 0.5
"""Width in ``ln L`` of the radiance bins in which :class:`LearnedThresholds` checks that
learning selects no pixels by their thresholds."""

LEARN_POPULATION_SHARE = 0.95
"""Share of a radiance bin's fits that must have fired enough events to learn for the
bin's learned pixels to sample the population without selection."""


class LearnedThresholds:
    """Per-pixel ON and OFF thresholds learned from a recording's own events, one cycle
    after another: the thresholds stay while the scene changes, so each cycle's fit
    (radiance and thresholds jointly, :func:`estimate`) starts from what the cycles before
    it told. Sequential Bayes in the Gaussian approximation: the first cycle's prior is
    the sensor's nominal thresholds with its mismatch as their spread; each cycle's
    posterior (the fitted thresholds, and their standard deviations from the fit's
    matrix with radiance and start offset marginalised) is the next cycle's prior.
    A pixel's threshold is left as it was where the cycle gave no fit, fewer than
    :data:`LEARN_MIN_EVENTS` events, or a fit that moved it further than
    :data:`LEARN_GATE` standard deviations; spreads are kept at :data:`LEARN_SD_FLOOR` or
    more. The pixels that have learned nothing yet (dark ones, those near ``L_const``:
    few events) take the learned pixels' median as their prior's mean (empirical Bayes;
    the spread stays the mismatch's, or the learned pixels' if that is wider), once
    :data:`LEARN_POPULATION_MIN` pixels have learned where learning selects none by its
    threshold (radiances at which nearly every pixel fires enough events): a real
    sensor's thresholds sit where its biases put them, not at a datasheet's nominal
    value.

    ``cycles``: how many cycles it has learned from.

    The first cycle is fitted from the nominal thresholds alone: :meth:`first_cycle_priors`
    gives it what the cycle after it taught (the second update's likelihood, its
    posterior divided by its prior), so that :func:`reconstruct_ml` fits it again no worse
    informed than the second, and no cycle's events counted twice."""

    def __init__(self) -> None:
        self.cycles = 0
        self._state: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._initial: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        # the latest update's likelihood per threshold: (taught, c / sd^2 - m / sd0^2,
        # 1 / sd^2 - 1 / sd0^2), the fit's posterior over the prior it had
        self._taught: list[tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
        self._learned: list[np.ndarray] | None = None
        # the learned pixels that sample the population without selection (below)
        self._sample: list[np.ndarray] = []

    @property
    def learned(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Per pixel (flat), whether its ON and its OFF threshold have learned from a cycle
        yet; None before the first update."""
        if self._learned is None:
            return None
        return self._learned[0].copy(), self._learned[1].copy()

    def priors(self, sensor: SensorParams, *, width: int, height: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The priors for the next cycle (:func:`thresholds_prior`'s layout)."""
        if self._state is None:
            self._state = thresholds_prior(sensor, width=width, height=height)
            self._initial = self._state
        if self._state[0].size != width * height:
            raise ValueError(f"LearnedThresholds: learned on {self._state[0].size} pixels, "
                             f"asked for {width}x{height}")
        return self._state

    def update(self, res: MlResult, cycle: int = -1) -> None:
        """Learn from cycle ``cycle`` of ``res`` (which needs ``sd_on`` and ``sd_off``:
        :func:`estimate` with ``threshold_sd``)."""
        if self._state is None:
            raise ValueError("LearnedThresholds.update: priors() first")
        if res.sd_on is None or res.sd_off is None:
            raise ValueError("LearnedThresholds.update: the result has no threshold "
                             "spreads (estimate(..., threshold_sd=True))")
        m_on, m_off, s_on, s_off = self._state
        if self._learned is None:
            self._learned = [np.zeros(m_on.size, bool), np.zeros(m_on.size, bool)]
            self._sample = [np.zeros(m_on.size, bool), np.zeros(m_on.size, bool)]
        enough = np.asarray(res.n_events[cycle]).ravel() >= LEARN_MIN_EVENTS
        unselected = _unselected(res, cycle, enough)
        new = []
        taught = []
        for k, (m, sd0, c, sd) in enumerate(((m_on, s_on, res.c_on, res.sd_on),
                                             (m_off, s_off, res.c_off, res.sd_off))):
            c = np.asarray(c[cycle], dtype=np.float64).ravel()
            sd = np.asarray(sd[cycle], dtype=np.float64).ravel()
            with np.errstate(invalid="ignore"):
                ok = (enough & np.isfinite(c) & np.isfinite(sd) & (sd > 0)
                      & (np.abs(c - m) <= LEARN_GATE * sd0))
            mean = np.where(ok, c, m)
            spread = np.where(ok, np.maximum(sd, LEARN_SD_FLOOR), sd0)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                # the fit's own posterior (not floored) over the prior it had; one no
                # narrower than its prior taught nothing
                prec = np.where(ok, sd ** -2.0 - sd0 ** -2.0, 0.0)
                ok_t = ok & (prec > 0) & np.isfinite(prec)
                taught.append((ok_t, np.where(ok_t, c * sd ** -2.0 - m * sd0 ** -2.0, 0.0),
                               np.where(ok_t, prec, 0.0)))
            learned = self._learned[k] | ok
            self._learned[k] = learned
            self._sample[k] |= ok & unselected
            if np.count_nonzero(self._sample[k]) >= LEARN_POPULATION_MIN:
                mean, spread = _population_prior(mean, spread, learned, self._sample[k])
            new.append((mean, spread))
        self._state = (new[0][0], new[1][0], new[0][1], new[1][1])
        self._taught = taught
        self.cycles += 1

    def first_cycle_priors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The first cycle's priors (the nominal thresholds) with what the latest update's
        cycle taught, in the Gaussian approximation (precisions add; spreads at least
        :data:`LEARN_SD_FLOOR`); the pixels it taught nothing keep the current prior of
        the pixels that never learned (the nominal thresholds, or the population's: their
        own first cycle's fit is not in it). After the second update these are the priors
        that fit the first cycle again with the second's information and not its own
        (:func:`reconstruct_ml`)."""
        if self._initial is None or self._taught is None or self._learned is None \
                or self._state is None:
            raise ValueError("LearnedThresholds.first_cycle_priors: nothing learned yet")
        out = []
        for k in range(2):
            m0, s0 = self._initial[k], self._initial[2 + k]
            ok, num, prec = self._taught[k]
            p = s0 ** -2.0 + prec
            mean = np.where(ok, (m0 * s0 ** -2.0 + num) / p, m0)
            spread = np.where(ok, np.maximum(p ** -0.5, LEARN_SD_FLOOR), s0)
            if np.count_nonzero(self._sample[k]) >= LEARN_POPULATION_MIN:
                mu, mad = _population(self._state[k], self._sample[k])
                mean = np.where(ok, mean, mu)
                spread = np.where(ok, spread, np.maximum(s0, mad))
            out.append((mean, spread))
        return out[0][0], out[1][0], out[0][1], out[1][1]


def _unselected(res: MlResult, cycle: int, enough: np.ndarray) -> np.ndarray:
    """The pixels whose radiance lies where (nearly) every fitted pixel fired enough
    events to learn: a bin of ``ln L`` (:data:`LEARN_BIN`) with at least
    :data:`LEARN_POPULATION_SHARE` of its fits above :data:`LEARN_MIN_EVENTS`. Elsewhere
    the count selects: a pixel fires about ``swing / c`` events, so where the count hovers
    about the floor the pixels that learn are those of low thresholds (on a flat field at
    ``L_const`` their median was low enough to take every silent pixel for dead)."""
    g = np.log(np.asarray(res.radiance[cycle], dtype=np.float64).ravel())
    fit = (np.asarray(res.flags[cycle]).ravel() == 0) & np.isfinite(g)
    out = np.zeros(g.size, bool)
    if not fit.any():
        return out
    b = np.floor(g[fit] / LEARN_BIN).astype(np.int64)
    b -= b.min()
    total = np.bincount(b)
    learned = np.bincount(b, weights=enough[fit])
    good = (total >= 10) & (learned >= LEARN_POPULATION_SHARE * total)
    out[np.flatnonzero(fit)[good[b]]] = True
    return out


def _population_prior(mean: np.ndarray, spread: np.ndarray, learned: np.ndarray,
                      sample: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``mean`` and ``spread`` with the pixels not ``learned`` given the median of the
    ``sample`` pixels' learned values, and a spread no narrower than their own (the
    sensor's mismatch) nor than the sample's (1.4826 median absolute deviation): learned
    values are posterior means, drawn towards the prior, so their spread understates the
    population's."""
    mu, mad = _population(mean, sample)
    return np.where(learned, mean, mu), np.where(learned, spread, np.maximum(spread, mad))


def _population(mean: np.ndarray, sample: np.ndarray) -> tuple[float, float]:
    """The ``sample`` pixels' median of ``mean`` and their spread about it (1.4826 median
    absolute deviation)."""
    mu = float(np.median(mean[sample]))
    return mu, 1.4826 * float(np.median(np.abs(mean[sample] - mu)))


_PROGRESS_PARTS = 32
"""With a progress callback, a cycle's pixels are fitted in this many parts (each part on
every thread), and the callback told after each."""


def _run(model: MlModel, off: np.ndarray, t: np.ndarray, p: np.ndarray, npx: int,
         priors: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
         g_prior: np.ndarray | None, sg_prior: np.ndarray | None, fixed: bool,
         min_events: int = 2, start_sigma: float = 0.0,
         progress: Callable[[int], None] | None = None,
         width: int = 0, neighbours: bool = True, threshold_sd: bool = False,
         dead_fraction: float | None = None, fast: bool = False,
         hold_sd: float = math.inf, stats: dict[str, int] | None = None
         ) -> tuple[np.ndarray, ...]:
    """Every pixel's fit (:func:`_estimate_kernel`); ``progress(pixels_done)`` after each
    of :data:`_PROGRESS_PARTS` parts when given (the same fits, part by part). With
    ``width`` (the pixels an image of that width) and ``neighbours``, the neighbours' fits
    are tried as further starts (:func:`_neighbour_starts`), unless ``g`` has a prior or
    ``fixed``;
    then the pixels with fewer than two events are estimated from how few they fired
    (:func:`_sparse_kernel`; ``dead_fraction``: the share of dead pixels, default the
    model's).
    Returns ``(g, sd, c_on, c_off, flag, counts)``, and with ``threshold_sd`` the
    thresholds' posterior standard deviations (:func:`_threshold_sd_kernel`) after them.
    ``fast``: the fast fit (:func:`_fast_kernel`; the neighbours' starts for the pixels
    fitted in full only), holding the
    thresholds whose spreads are at most ``hold_sd``; the thresholds' deviations then come
    from the pixels fitted in full alone (NaN where they were held); ``stats["full"]``
    gets how many were fitted in full, ``stats["retried"]`` how many of the others were
    fitted again from a likelier point (:func:`_fast_kernel`)."""
    con, coff, scon, scoff = (np.ascontiguousarray(a) for a in priors)
    counts = np.diff(off)
    out_g = np.empty(npx)
    out_sd = np.empty(npx)
    out_con = np.empty(npx)
    out_coff = np.empty(npx)
    out_flag = np.zeros(npx, np.uint8)
    out_u = np.zeros(npx)
    gp = np.zeros(npx) if g_prior is None else np.ascontiguousarray(g_prior, dtype=np.float64)
    sp = np.zeros(npx) if sg_prior is None else np.ascontiguousarray(sg_prior,
                                                                      dtype=np.float64)
    tq2 = model.jitter_us ** 2 + model.res_us ** 2 / 12.0
    eq2 = model.res_us ** 2 / 12.0 + (model.jitter_us ** 2 if model.dead else 0.0)
    parts = 1 if progress is None else min(_PROGRESS_PARTS, max(1, npx // _BLOCK))
    edges = np.linspace(0, npx, parts + 1).astype(np.int64)
    full = np.zeros(npx, np.uint8)
    retry = np.zeros(npx, np.uint8)
    least = _least_slots(model.mode, np.int64(model.window_us), model.exact, model.locate,
                         _steepest_slopes(model.rows), model.reset_sigma ** 2, tq2,
                         model.noise_rate_per_us) if fast else np.empty(0)
    for a, b in zip(edges[:-1].tolist(), edges[1:].tolist(), strict=True):
        if fast and not fixed:
            _fast_kernel(off[a:b + 1], t, p, model.mode, model.dead, model.reset_sigma ** 2,
                         tq2, eq2, model.noise_rate_per_us, model.exact, model.v0[0],
                         model.v0[1], model.rows, model.g0, model.dlog, model.locate,
                         np.int64(model.window_us), model.g_lo, model.g_hi, model.net_g,
                         model.net_v, np.int64(min_events), con[a:b], coff[a:b], scon[a:b],
                         scoff[a:b], out_g[a:b], out_sd[a:b], out_con[a:b], out_coff[a:b],
                         out_flag[a:b], float(start_sigma), np.int64(model.split_us),
                         model.net_v2, np.int64(model.split2_us), block_order(b - a, _BLOCK),
                         out_u[a:b], full[a:b], float(hold_sd), least, retry[a:b])
            if progress is not None:
                progress(b)
            continue
        _estimate_kernel(off[a:b + 1], t, p, model.mode, model.dead, model.reset_sigma ** 2,
                         tq2, eq2, model.noise_rate_per_us, model.exact, model.v0[0],
                         model.v0[1], model.rows, model.g0, model.dlog, model.locate,
                         np.int64(model.window_us), model.g_lo, model.g_hi, model.net_g,
                         model.net_v, np.int64(1 if fixed else min_events), con[a:b],
                         coff[a:b], scon[a:b], scoff[a:b], gp[a:b], sp[a:b], fixed,
                         out_g[a:b], out_sd[a:b], out_con[a:b], out_coff[a:b],
                         out_flag[a:b], float(start_sigma), np.int64(model.split_us),
                         model.net_v2, np.int64(model.split2_us), block_order(b - a, _BLOCK),
                         out_u[a:b])
        if progress is not None:
            progress(b)
    if fast:
        n_retry = int(np.count_nonzero(retry & (full == 0)))
        logger.debug("ml: %d of %d pixels fitted in full; %d fitted again from a likelier "
                     "point", int(full.sum()), npx, n_retry)
        if stats is not None:
            stats["full"] = int(np.count_nonzero(full))
            stats["retried"] = n_retry
    image = width > 0 and npx % width == 0
    if neighbours and image and not fixed and not np.any(sp > 0.0):
        # the fast fit's pixels fitted in full try their neighbours' fits too
        todo = full.copy() if fast else np.ones(npx, np.uint8)
        for _ in range(_NEIGHBOUR_SWEEPS):
            moved = np.zeros(npx, np.uint8)
            n_moved = _neighbour_starts(
                off, t, p, model.mode, model.dead, model.reset_sigma ** 2, tq2, eq2,
                model.noise_rate_per_us, model.exact, model.v0[0], model.v0[1], model.rows,
                model.g0, model.dlog, model.locate, np.int64(model.window_us), model.g_lo,
                model.g_hi, con, coff, scon, scoff, float(start_sigma), np.int64(width),
                np.int64(min_events), todo, out_g, out_sd, out_con, out_coff, out_flag, out_u,
                moved)
            logger.debug("ml: %d pixels refitted from their neighbours' fits", n_moved)
            if n_moved == 0:
                break
            # the next sweep: the neighbours of what moved
            m = np.pad(moved.reshape(-1, width), 1)
            todo = np.zeros_like(m[1:-1, 1:-1])
            for dy in range(3):
                for dx in range(3):
                    np.maximum(todo, m[dy:dy + m.shape[0] - 2, dx:dx + m.shape[1] - 2],
                               out=todo)
            todo = todo.ravel()
    if not fixed and not np.any(sp > 0.0):
        few = np.flatnonzero(counts < min(min_events, 2)).astype(np.int64)
        for _ in range(_SILENT_SWEEPS):
            if not few.size:
                break
            # each sweep reads the estimates as they stood: the next one reaches the
            # silent pixels whose neighbours the last one estimated (a silent patch, from
            # its edge inwards)
            _sparse_kernel(few, off, t, p, model.mode, model.exact, model.v0[0], model.v0[1],
                           model.rows, model.g0, model.dlog, model.locate,
                           np.int64(model.window_us), model.ext_t, model.ext, model.ext_g,
                           0.5 * model.res_us - model.latency_us,
                           0.5 * model.res_us + model.refractory_us, tq2,
                           model.reset_sigma ** 2, model.noise_rate_per_us, con, coff, scon,
                           scoff, float(start_sigma),
                           model.dead_fraction if dead_fraction is None else dead_fraction,
                           np.int64(width if image else npx),
                           out_g.copy(), out_flag.copy(), out_g, out_sd, out_flag)
            left = few[out_flag[few] == FLAG_NO_EVENTS]
            if left.size == few.size:
                break
            few = left[counts[left] == 0]
    extra: tuple[np.ndarray, ...] = ()
    if threshold_sd:
        son = np.empty(npx)
        soff = np.empty(npx)
        _threshold_sd_kernel(off, t, p, model.mode, model.dead, model.reset_sigma ** 2, tq2,
                             eq2, model.noise_rate_per_us, model.exact, model.v0[0],
                             model.v0[1], model.rows, model.g0, model.dlog, model.locate,
                             np.int64(model.window_us), con, coff, scon, scoff,
                             float(start_sigma), out_g, out_sd, out_u, out_con, out_coff,
                             np.where(full != 0, out_flag, np.uint8(255)) if fast else
                             out_flag, son, soff)
        extra = (son, soff)
    if not fixed and not np.any(sp > 0.0):
        # last, as nothing above reads the fits' deviations again; the fast fit's own
        # fits are left as they are (the grid would double its time, docs/ml.md)
        few = np.flatnonzero((counts >= _FEW_EVENTS[0]) & (counts < _FEW_EVENTS[1])
                             & (out_flag == 0) & ((full != 0) | (not fast))
                             ).astype(np.int64)
        if few.size:
            _few_events_kernel(few, off, t, p, model.mode, model.dead, model.reset_sigma ** 2,
                               tq2, eq2, model.noise_rate_per_us, model.exact, model.v0[0],
                               model.v0[1], model.rows, model.g0, model.dlog, model.locate,
                               np.int64(model.window_us), model.g_lo, model.g_hi, con, coff,
                               scon, scoff, float(start_sigma), out_g, out_sd, out_u,
                               out_con, out_coff, out_flag)
    return (out_g, out_sd, out_con, out_coff, out_flag, counts, *extra)


def _beyond_range(g: np.ndarray, sd: np.ndarray, flags: np.ndarray, g_lo: float,
                  g_hi: float) -> None:
    """Vague fits (:data:`FLAG_UNINFORMED`) within one deviation of a bound of the range,
    and not of both, made fits at that bound (:data:`FLAG_OUT_OF_RANGE`), in place: the
    likelihood's plateau runs out of the range, so the events place the pixel beyond
    where they inform (a highlight above the range, or the dark end below it), and the
    image holds the bound there as for a fit that reached it, instead of a hole."""
    vague = (flags == FLAG_UNINFORMED) & np.isfinite(sd)
    top = vague & (g + sd >= g_hi) & (g - sd > g_lo)
    bottom = vague & (g - sd <= g_lo) & (g + sd < g_hi)
    g[top] = g_hi
    g[bottom] = g_lo
    flags[top | bottom] = FLAG_OUT_OF_RANGE


def estimate(
    events: np.ndarray,
    *,
    width: int,
    height: int,
    starts_us: np.ndarray,
    model: MlModel,
    priors: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    g_prior: np.ndarray | None = None,
    g_prior_sigma: np.ndarray | None = None,
    min_events: int = 2,
    start_sigma: float = 0.0,
    progress: Callable[[int, int], None] | None = None,
    pixel_progress: Callable[[int, int], None] | None = None,
    neighbours: bool = True,
    threshold_sd: bool = False,
    dead_fraction: float | None = None,
    fast: bool = False,
    hold_sd: float = math.inf,
) -> MlResult:
    """Maximum-likelihood radiance per pixel and cycle.

    Parameters
    ----------
    events : events (``EVENT_DTYPE``), in any order (each pixel's are put in time order,
        :func:`group_by_pixel`).
    starts_us : cycle starts (µs); each cycle uses ``[start, start + model.window_us)``.
    model : :func:`ml_model` of the rig and the sensor.
    priors : :func:`thresholds_prior`.
    min_events : fewer events than this: no estimate (:data:`FLAG_NO_EVENTS`).
    start_sigma : > 0 when every pixel starts the window settled at its reference (a
        single ramp from rest, as a shutter opening): the start offset ``u`` is then
        ``N(0, start_sigma^2)`` instead of the uniform band, and one event suffices.
    g_prior, g_prior_sigma : optional Gaussian prior on ``ln L`` per pixel (flat): a known
        flat field for calibration (then the thresholds are what is estimated).
    progress : ``progress(done_cycles, n_cycles)``.
    pixel_progress : ``pixel_progress(done, total)`` in pixel-cycles, several times a
        cycle (a 1280x720 cycle of the IMX636 takes about half a minute).
    neighbours : try the neighbours' fits as further starts where a pixel's fit stands
        apart from theirs, keeping the likelier (docs/ml.md; not with ``g_prior_sigma``).
        A fit's start, not a smoothing: each pixel's estimate is its own events' fit.
    threshold_sd : also the thresholds' posterior standard deviations (``sd_on``,
        ``sd_off``: one more pass over each fitted pixel's events).
    dead_fraction : the share of pixels that never fire, against which a silent pixel's
        estimate from its silence (:data:`FLAG_FEW_EVENTS`) is weighed; default the
        sensor's (:attr:`MlModel.dead_fraction`); 0 where a calibration's map names the
        dead pixels.
    fast : the fast fit (docs/ml.md): ``ln L`` alone, the thresholds held at ``priors``
        (a calibration's) wherever their spreads are at most ``hold_sd`` (default: all);
        the full fit for the other pixels and where the fast one fails its checks. Not
        with ``g_prior_sigma``; with ``threshold_sd``, the deviations of the thresholds
        fitted in full (NaN where held).
    """
    if fast and g_prior_sigma is not None:
        raise ValueError("ml: the fast fit estimates ln L with the thresholds held; it takes "
                         "no prior on ln L")
    if dead_fraction is not None and not 0.0 <= dead_fraction < 1.0:
        raise ValueError(f"ml: dead_fraction is the share of pixels that never fire, in "
                         f"[0, 1); got {dead_fraction}")
    starts = np.asarray(starts_us, dtype=np.int64)
    npx = width * height
    n = starts.size
    shape = (n, height, width)
    rad = np.empty(shape, np.float32)
    sd = np.empty(shape, np.float32)
    flags = np.empty(shape, np.uint8)
    con = np.empty(shape, np.float32)
    coff = np.empty(shape, np.float32)
    nev = np.empty(shape, np.int32)
    sd_on = np.empty(shape, np.float32) if threshold_sd else None
    sd_off = np.empty(shape, np.float32) if threshold_sd else None
    full_fits = np.zeros(n, np.int64) if fast else None
    for c in range(n):
        off, t, p = group_by_pixel(events, width=width, height=height,
                                   start_us=int(starts[c]), window_us=model.window_us)
        step = None
        if pixel_progress is not None:
            def step(done: int, c: int = c) -> None:
                pixel_progress(c * npx + done, n * npx)
        stats: dict[str, int] = {}
        g, s, c1, c2, fl, counts, *tsd = _run(
            model, off, t, p, npx, priors, g_prior, g_prior_sigma, False, min_events,
            start_sigma, progress=step, width=width, neighbours=neighbours,
            threshold_sd=threshold_sd, dead_fraction=dead_fraction, fast=fast,
            hold_sd=hold_sd, stats=stats)
        if full_fits is not None:
            full_fits[c] = stats["full"]
        _beyond_range(g, s, fl, model.g_lo, model.g_hi)
        if sd_on is not None and sd_off is not None:
            sd_on[c] = tsd[0].reshape(height, width)
            sd_off[c] = tsd[1].reshape(height, width)
        with np.errstate(over="ignore"):
            r = np.exp(g)  # a pixel out of the range keeps the bound it reached
        r[(fl & (FLAG_NO_EVENTS | FLAG_UNINFORMED)) != 0] = np.nan
        # no deviation where there is no estimate, and none where the likelihood's profile
        # has no curvature to give one (an infinite deviation: no information)
        s[(fl == FLAG_NO_EVENTS) | (fl == FLAG_OUT_OF_RANGE) | ~np.isfinite(s)] = np.nan
        rad[c] = r.reshape(height, width)
        sd[c] = s.reshape(height, width)
        flags[c] = fl.reshape(height, width)
        con[c] = c1.reshape(height, width)
        coff[c] = c2.reshape(height, width)
        nev[c] = counts.reshape(height, width)
        if progress is not None:
            progress(c + 1, n)
    n_none = int(np.count_nonzero(flags == FLAG_NO_EVENTS))
    n_out = int(np.count_nonzero(flags == FLAG_OUT_OF_RANGE))
    n_vague = int(np.count_nonzero(flags & FLAG_UNINFORMED))
    n_few = int(np.count_nonzero(flags == FLAG_FEW_EVENTS))
    n_amb = int(np.count_nonzero(flags == FLAG_AMBIGUOUS))
    if n_none or n_out or n_vague or n_few or n_amb:
        logger.info("ml: %d pixel-cycles without an estimate from fewer than two events, "
                    "and %d whose events fix L to no better than a factor e: NaN; %d "
                    "estimated from fewer than two events; %d fitted from few events "
                    "whose likelihood has other optima a factor e or more away; %d at a "
                    "bound of the model's range (%.3g to %.3g): the bound", n_none, n_vague,
                    n_few, n_amb, n_out, math.exp(model.g_lo), math.exp(model.g_hi))
    return MlResult(radiance=rad, sigma_log=sd, flags=flags, c_on=con, c_off=coff,
                    n_events=nev, sd_on=sd_on, sd_off=sd_off, full_fits=full_fits)


def fisher_information(
    events: np.ndarray,
    *,
    width: int,
    height: int,
    start_us: int,
    model: MlModel,
    priors: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    log_radiance: np.ndarray,
) -> np.ndarray:
    """The model's Cramér-Rao bound on ``ln L`` per pixel, ``(height, width)`` float64
    standard deviations: the information matrix of :func:`estimate` evaluated at the
    given ``log_radiance`` (the truth) over these events (for the expected bound: the
    noiseless events of that radiance), thresholds and ``u`` marginalised. NaN where the
    pixel has no event."""
    off, t, p = group_by_pixel(events, width=width, height=height, start_us=int(start_us),
                               window_us=model.window_us)
    g = np.ascontiguousarray(np.asarray(log_radiance, dtype=np.float64).ravel())
    _, sd, _, _, fl, _ = _run(model, off, t, p, width * height, priors, g, None, True)
    sd[fl == FLAG_NO_EVENTS] = np.nan
    return sd.reshape(height, width)


# ----------------------------------------------------------------------------- recordings

_MODEL_CACHE: dict[str, MlModel] = {}
_MODEL_CACHE_SIZE = 4


def cached_model(rig: Rig, sensor: SensorParams, *, window_us: float,
                 dlog: float = DEFAULT_DLOG, from_rest: bool = False) -> MlModel:
    """:func:`ml_model`, remembered for the last few (rig, sensor, window): a recording
    read cycle by cycle builds its tables once."""
    import hashlib
    import json

    key_src = json.dumps([rig.to_metadata(), sensor.to_metadata(), float(window_us),
                          float(dlog), bool(from_rest)], sort_keys=True, default=str)
    key = hashlib.sha1(key_src.encode()).hexdigest()
    m = _MODEL_CACHE.get(key)
    if m is None:
        m = ml_model(rig, sensor, window_us=window_us, dlog=dlog, from_rest=from_rest)
        if len(_MODEL_CACHE) >= _MODEL_CACHE_SIZE:
            _MODEL_CACHE.pop(next(iter(_MODEL_CACHE)))
        _MODEL_CACHE[key] = m
    return m


def sensor_of(metadata: dict[str, Any], *, threshold: float | None = None) -> SensorParams:
    """The pixel model of a recording: its metadata's sensor (simulated recordings, or a
    rig file's ``[sensor]``), else the preset its camera names (IMX636, DAVIS346), else
    the default :class:`~asynhdr.sensor.params.SensorParams` with ``threshold`` (logged)."""
    from asynhdr.sensor.params import PRESETS

    s = metadata.get("sensor")
    if isinstance(s, SensorParams):
        return s
    if isinstance(s, dict) and "threshold_on" in s:
        return SensorParams.from_metadata(s)
    text = " ".join(str(v) for v in (metadata.get("camera"), metadata.get("header"),
                                     metadata.get("sensor_name")) if v).lower()
    for name, preset in PRESETS.items():
        if name not in ("ideal", "v2e") and name in text:
            logger.info("ml: sensor model from the %s preset (named in the file)", name)
            return preset
    base = SensorParams()
    if threshold is not None:
        base = base.with_(threshold_on=threshold, threshold_off=threshold)
    logger.warning("ml: the recording does not say which sensor made it; assuming the "
                   "default pixel model (thresholds %.3g); give a rig file with a [sensor] "
                   "table", base.threshold_on)
    return base


def reconstruct_ml(
    rec: Recording,
    windows: Any,
    *,
    rig: Rig,
    l_const: float | None = None,
    cmap: np.ndarray | None = None,
    threshold: float | None = None,
    sensor: SensorParams | None = None,
    thresholds: tuple[np.ndarray, np.ndarray, np.ndarray | float] | None = None,
    defects: np.ndarray | None = None,
    out: dict[str, Any] | None = None,
    min_events: int | None = None,
    settled_start: bool = False,
    progress: Callable[[str, int, int], None] | None = None,
    neighbours: bool = True,
    learn: bool = True,
    learner: LearnedThresholds | None = None,
    refit_first: bool = True,
    fast: bool = False,
) -> np.ndarray:
    """``ml`` on a recording: float32 radiance ``(n_cycles, height, width)`` in the unit of
    ``L_const``, NaN where a pixel has no information.

    ``windows``: :class:`asynhdr.reconstruct.CycleWindows`. ``sensor``: the pixel model
    (default :func:`sensor_of` the recording). ``thresholds``: calibrated ``(c_on, c_off,
    sigma)`` maps (a calibration file); else a c-map ``cmap`` scales the nominal
    thresholds (spread 0.01), else the nominal ones with the sensor's mismatch as their
    spread. ``defects``: a calibration's map of dead pixels ``(height, width)``: those
    without an estimate (or silent) get the median of their measured neighbours
    (:data:`FLAG_FILLED`), and a silent pixel outside the map is taken to be working
    (its silence estimates it, :data:`FLAG_FEW_EVENTS`); without a map, the silent pixels
    the fit takes for dead (:data:`FLAG_NO_EVENTS`) are filled the same way. ``out``
    receives ``sigma_log``,
    ``flags``, ``c_on``, ``c_off`` and ``n_events`` (:class:`MlResult`'s fields), and with
    ``fast`` ``full_fits``.
    ``settled_start``: the pixels start the window at rest on their reference (a single
    ramp from a closed shutter): the start offset is then known to the reset noise (or
    0.02) and one event suffices.
    ``progress(stage, done, total)`` reports the fits as they go, in pixel-cycles
    (``stage``: "ml: pixels fitted", or "ml: pixels this cycle" for a single window).
    ``neighbours``: :func:`estimate`'s further starts from the neighbours' fits.
    ``learn``: without ``thresholds`` or ``cmap``, the thresholds are learned from the
    recording's own cycles, one after another (:class:`LearnedThresholds`; a warm-up
    cycle's pixels start from another state, which the fit's start offset takes up, so it
    teaches too); ``learner`` carries what was learned from one call
    to the next (a recording reconstructed cycle by cycle), else each call starts from
    the nominal thresholds. A call that starts the learning with two cycles or more fits
    its first cycle again once the second has taught the thresholds
    (:meth:`LearnedThresholds.first_cycle_priors`; not with ``fast``, nor with
    ``refit_first`` False: a caller that keeps only the last cycle).
    ``fast``: the fast fit (:func:`estimate`; docs/ml.md): ``ln L`` alone with the
    thresholds held: calibrated ones (``thresholds`` or ``cmap``), or, while learning,
    each pixel's once learned to :data:`FAST_HOLD_SD` (until then the full fit, which
    learns); 5x to 9x faster than the full fit on the bench. Without either (``learn=False``)
    it raises ``ValueError``, unless the sensor has no mismatch.
    """
    if l_const is not None and float(l_const) != float(rig.l_const):
        rig = dataclasses.replace(rig, l_const=float(l_const))
    sensor = sensor or sensor_of(rec.metadata, threshold=threshold)
    calibrated = thresholds is not None or cmap is not None
    learning = not calibrated and learn and sensor.threshold_sigma > 0
    if fast and not calibrated and not learning and sensor.threshold_sigma > 0:
        raise ValueError("ml --fast holds each pixel's thresholds where they are: it needs "
                         "them calibrated (a calibration file, --calibration, or a c-map) "
                         "or learned from the recording's cycles; without either, run the "
                         "full fit (it estimates them too)")
    model = cached_model(rig, sensor, window_us=float(windows.window_us),
                         from_rest=settled_start)
    w, h = rec.width, rec.height
    if thresholds is not None:
        c_on, c_off, sig = thresholds
        priors = thresholds_prior(sensor, width=w, height=h, c_on=c_on, c_off=c_off,
                                  sigma=sig)
    elif cmap is not None:
        cm = np.asarray(cmap, dtype=np.float64)
        priors = thresholds_prior(sensor, width=w, height=h, c_on=sensor.threshold_on * cm,
                                  c_off=sensor.threshold_off * cm, sigma=0.01)
    else:
        priors = thresholds_prior(sensor, width=w, height=h)
    ev = rec.events
    start_sigma = max(sensor.reset_noise_sigma, 0.02) if settled_start else 0.0
    # one cycle at a time (the CLI): its bar starts again with each cycle
    starts = windows.start_us
    stage = "ml: pixels fitted" if len(starts) > 1 else "ml: pixels this cycle"
    n_min = (1 if settled_start else 2) if min_events is None else int(min_events)
    kw: dict[str, Any] = dict(width=w, height=h, model=model, min_events=n_min,
                              start_sigma=start_sigma, neighbours=neighbours,
                              dead_fraction=None if defects is None else 0.0, fast=fast)
    if learning:
        own = learner is None
        learner = LearnedThresholds() if learner is None else learner
        # the first cycle fitted again once the second has taught its thresholds
        # (LearnedThresholds.first_cycle_priors): where this call starts the learning, and
        # not with the fast fit, whose held pixels learn nothing in the second cycle
        again = refit_first and learner.cycles == 0 and len(starts) > 1 and not fast
        n_fits = len(starts) + again
        parts = []
        npx = w * h

        def bar(k: int) -> Callable[[int, int], None] | None:
            """The bar's callback for the ``k``-th fit of ``n_fits``."""
            if progress is None:
                return None
            return lambda done, total: progress(stage, k * npx + done, n_fits * npx)

        for c, st in enumerate(starts.tolist()):
            # the last cycle's spreads serve only a learner that outlives this call
            last = own and c == len(starts) - 1 and not (again and c == 1)
            part = estimate(ev, starts_us=np.array([st]),
                            priors=learner.priors(sensor, width=w, height=h),
                            threshold_sd=not last, hold_sd=FAST_HOLD_SD,
                            pixel_progress=bar(c + (again and c > 1)), **kw)
            if part.sd_on is not None:
                learner.update(part)
            parts.append(dataclasses.replace(part, sd_on=None, sd_off=None))
            if again and c == 1:
                parts[0] = estimate(ev, starts_us=starts[:1],
                                    priors=learner.first_cycle_priors(),
                                    hold_sd=FAST_HOLD_SD, pixel_progress=bar(2), **kw)
        res = MlResult.concatenate(parts)
    else:
        res = estimate(ev, starts_us=starts, priors=priors,
                       pixel_progress=None if progress is None else
                       (lambda done, total: progress(stage, done, total)), **kw)
    mapped = None if defects is None else np.asarray(defects, dtype=bool)
    if mapped is not None and mapped.shape != (h, w):
        raise ValueError(f"ml: the defect map is {mapped.shape}, the recording {(h, w)}")
    for c in range(res.radiance.shape[0]):
        silent = res.n_events[c] == 0
        if mapped is not None:
            # a dead pixel's silence is no estimate from silence
            dead = mapped
            res.radiance[c][dead & silent] = np.nan
            res.sigma_log[c][dead & silent] = np.nan
            res.flags[c][dead & silent] = FLAG_NO_EVENTS
        else:
            # the silent pixels the fit took for dead (their neighbours say the signal
            # swung far enough to fire)
            dead = silent & (res.flags[c] == FLAG_NO_EVENTS)
        res.radiance[c], filled = fill_defects(res.radiance[c], dead)
        res.flags[c][filled] |= FLAG_FILLED
    if out is not None:
        out.update(sigma_log=res.sigma_log, flags=res.flags, c_on=res.c_on, c_off=res.c_off,
                   n_events=res.n_events)
        if res.full_fits is not None:
            out["full_fits"] = res.full_fits
    return res.radiance
