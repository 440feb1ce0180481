"""The photoreceptor: what each pixel's comparator sees over one cycle, on a time grid.

The comparator (:mod:`asynhdr.sensor.pixel`) reads a pixel's signal ``V(t)`` as a
piecewise-linear function of time on a grid ``s_k`` (µs from the cycle's start). The
signal of pixel ``p`` is a combination of two *rows* of a table::

    V_p(s_k) = wa_p R[ia_p, k] + wb_p R[ib_p, k]

which covers three cases with one comparator:

- no photoreceptor low-pass, static scene (:func:`irradiance_rows`): the rows are
  ``k_lens T1(s_k)`` and ``k_lens L_const T2(s_k)`` on the waveforms' knots, the weights
  ``(L_p, 1)``: ``V`` is the sensor irradiance, exactly piecewise linear (Wu et al.
  2024, Eq. 9), and the comparator solves each crossing exactly;
- low-pass, static scene (:func:`lowpass_table`): the photoreceptor output ``y`` of a
  pixel depends only on its radiance (and on the cycle), so ``y`` is integrated once
  per value of a log-radiance grid (step ``dlog_radiance``) and each pixel interpolates
  linearly between its two neighbouring rows;
- low-pass or not, per pixel (:func:`pixel_rows`): each pixel's own row, for moving
  scenes and as an independent check of the table.

The low-pass is the first-order photoreceptor of ``SensorParams`` on the log
irradiance ``x = log I``::

    dy/dt = (x - y) / tau(I),    tau(I) = tau_ref (I_ref + I_dark) / (I + I_dark),
                                 capped at tau_max_us

integrated step by step with ``tau`` at the step's mean irradiance and the exact
response to the input's chord and to its bow (the irradiance is linear in time within
a step, so ``x`` bends; ``b = x(t_mid) - (x_a + x_b) / 2``)::

    y_b = y_a + (x_a - y_a) g + (x_b - x_a) (1 - g / q) + 4 b K(q),
    q = h / tau,  g = 1 - exp(-q),  K(q) = int_0^1 q exp(-q w) w (1 - w) dw

The grid holds the waveforms' knots, a uniform grid of ``dt_us`` and, where a
transmittance changes fast in relative terms (a ramp leaving its leakage floor),
points spaced so that ``log T1`` and ``log T2`` move by at most ``max_log_step`` per
step; ``x = log(rho T1 + T2) + const`` then moves by at most that much too, whatever
the radiance. Between grid points the comparator interpolates ``y`` linearly; the
error this makes in a crossing time is at most ``h dx / 8`` (``h`` the step, ``dx`` the
change of ``x`` over it): under 0.02 µs with the defaults. docs/sensor.md gives the
tolerances measured against a fine-step integration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

__all__ = [
    "DEFAULT_DLOG_RADIANCE",
    "DEFAULT_DT_US",
    "DEFAULT_MAX_LOG_STEP",
    "Lowpass",
    "Signal",
    "irradiance_rows",
    "lowpass_rows",
    "pixel_rows",
    "radiance_grid",
    "row_runs",
    "time_grid",
]

DEFAULT_DT_US = 5.0
"""Largest step of the time grid (µs) where the low-pass is integrated."""

DEFAULT_MAX_LOG_STEP = 0.005
"""Largest change of ``log T1`` or ``log T2`` over one grid step."""

DEFAULT_DLOG_RADIANCE = 0.005
"""Step of the log-radiance grid on which the low-pass is tabulated for a static scene."""


@dataclass(frozen=True)
class Lowpass:
    """The photoreceptor's time constant ``tau(I) = tau_num / (I + dark)``, capped.

    Attributes
    ----------
    tau_num : ``tau_ref_us (cutoff_irradiance + dark_irradiance)`` (µs x irradiance).
    dark_irradiance : the dark current as an irradiance.
    tau_max_us : the cap on ``tau``.
    """

    tau_num: float
    dark_irradiance: float
    tau_max_us: float


@dataclass(frozen=True, eq=False)
class Signal:
    """What the comparator reads: rows on a time grid and each pixel's combination.

    Attributes
    ----------
    s : float64 ``(K,)`` grid times, µs from the cycle start, ``s[0] = 0``,
        ``s[-1] = period_us``.
    rows : float64 ``(n_rows, K)``.
    ia, ib : int64 per pixel: the two rows it combines.
    wa, wb : float64 per pixel: their weights.
    log_domain : True when ``V`` is a log irradiance (low-pass output), False when it is
        an irradiance (compared with ``exp`` of the levels).
    pieces : ``(n, 2)`` int64 interval ranges on which ``wa R[0] + wb R[1]`` turns at
        most once (the irradiance rows), or None.
    run_key, run_off, run_tab : monotone runs shared by pixels (the other cases):
        pixel ``p`` uses rows ``run_off[run_key[p]] .. run_off[run_key[p] + 1]`` of
        ``run_tab`` (``[first knot, last knot, direction]``; direction 0 where the run's
        direction differs between its two rows).
    """

    s: np.ndarray
    rows: np.ndarray
    ia: np.ndarray
    ib: np.ndarray
    wa: np.ndarray
    wb: np.ndarray
    log_domain: bool
    pieces: np.ndarray | None = None
    run_key: np.ndarray | None = None
    run_off: np.ndarray | None = None
    run_tab: np.ndarray | None = None


# ----------------------------------------------------------------------------- grid


def _geometric_points(s: np.ndarray, v: np.ndarray, max_log_step: float) -> np.ndarray:
    """Times inside each interval of a piecewise-linear ``v(s) > 0`` where ``log v`` moves
    by at most ``max_log_step`` between consecutive points (geometric in ``v``)."""
    va, vb = v[:-1], v[1:]
    with np.errstate(divide="ignore", invalid="ignore"):
        dlog = np.abs(np.log(vb / va))
    need = np.flatnonzero(np.isfinite(dlog) & (dlog > max_log_step))
    if need.size == 0:
        return np.zeros(0)
    out = []
    for j in need:
        n = math.ceil(dlog[j] / max_log_step)
        vals = va[j] * (vb[j] / va[j]) ** (np.arange(1, n) / n)
        out.append(s[j] + (vals - va[j]) / (vb[j] - va[j]) * (s[j + 1] - s[j]))
    return np.concatenate(out)


def time_grid(
    phase: np.ndarray,
    t1: np.ndarray,
    t2: np.ndarray,
    *,
    period_us: float,
    dt_us: float = DEFAULT_DT_US,
    max_log_step: float = DEFAULT_MAX_LOG_STEP,
    extra_us: np.ndarray | None = None,
    tau_min_us: float | None = None,
) -> np.ndarray:
    """The cycle's grid (µs from its start): the knots, ``0, dt, 2 dt, ..``, the points
    where ``log T1`` or ``log T2`` would move more than ``max_log_step`` in a step, and
    ``extra_us`` (frame times of a moving scene). Points closer than 1e-6 µs merge.

    With ``tau_min_us`` (the photoreceptor's shortest time constant in the scene), points
    are added after every kink of the input (a knot where the slope of ``log T`` jumps,
    the cycle's start, a frame time) at ``tau_min_us x 2^(-3 .. 4)``: there the output
    bends within a few ``tau`` towards its new slope, which a straight line over a whole
    step would miss.
    """
    if not (math.isfinite(dt_us) and dt_us > 0):
        raise ValueError(f"dt_us must be a positive number of µs, got {dt_us}")
    if not (math.isfinite(max_log_step) and max_log_step > 0):
        raise ValueError(f"max_log_step must be positive, got {max_log_step}")
    period = float(period_us)
    knots = np.asarray(phase, dtype=np.float64) * period
    n = math.ceil(period / dt_us - 1e-9)
    parts = [knots, np.minimum(np.arange(n + 1, dtype=np.float64) * dt_us, period)]
    for v in (t1, t2):
        parts.append(_geometric_points(knots, np.asarray(v, dtype=np.float64), max_log_step))
    if extra_us is not None:
        e = np.asarray(extra_us, dtype=np.float64)
        parts.append(e[(e > 0) & (e < period)])
    if tau_min_us is not None and tau_min_us > 0:
        kinks = [np.zeros(1)]
        for v in (t1, t2):
            lv = np.log(np.maximum(np.asarray(v, dtype=np.float64), 1e-300))
            with np.errstate(divide="ignore", invalid="ignore"):
                slope = np.diff(lv) / np.diff(knots)
            jump = np.abs(np.diff(slope)) * tau_min_us
            kinks.append(knots[1:-1][np.isfinite(jump) & (jump > 1e-6)])
        if extra_us is not None:
            kinks.append(parts[-1])
        k = np.concatenate(kinks)
        offsets = tau_min_us * 2.0 ** np.arange(-3, 5)
        parts.append((k[:, None] + offsets[None, :]).ravel())
    s = np.unique(np.concatenate(parts))
    s = s[(s >= 0) & (s <= period)]
    keep = np.ones(s.size, dtype=bool)
    keep[1:] = np.diff(s) > 1e-6
    s = s[keep]
    s[0] = 0.0
    if s[-1] < period - 1e-6:
        s = np.append(s, period)
    s[-1] = period
    return s


# ----------------------------------------------------------------------------- low-pass


@nb.njit(cache=True, inline="always", error_model="numpy")
def _one_minus_phi1(q):
    """``1 - (1 - exp(-q)) / q`` without cancellation for small ``q``."""
    if q < 1e-3:
        return q * (0.5 - q * (1.0 / 6.0 - q * (1.0 / 24.0)))
    return 1.0 - (-math.expm1(-q)) / q


@nb.njit(cache=True, inline="always", error_model="numpy")
def _curvature_gain(q):
    """``K(q) = int_0^1 q exp(-q w) w (1 - w) dw``: the response at a step's end to an
    input ``4 w (1 - w)`` (a parabola through 0 at both ends and 1 in the middle)."""
    if q < 0.1:
        return q * (1.0 / 6.0 - q * (1.0 / 12.0 - q * (1.0 / 40.0 - q * (1.0 / 180.0
                                                                        - q / 1008.0))))
    e = math.exp(-q)
    return (1.0 - e * (1.0 + q)) / q - (2.0 - e * (q * q + 2.0 * q + 2.0)) / (q * q)


@nb.njit(cache=True, error_model="numpy")
def _lowpass_row(irr, s, y0, tau_num, dark, tau_max, out):
    """``out[k] = y(s_k)`` for the irradiance ``irr[k]`` at the grid points (linear in time
    between them), ``y(0) = y0``; returns ``y`` at the last point.

    Per step: the exact response to the input's chord plus that to its bow
    ``x(t_mid) - (x_a + x_b) / 2`` (a parabola), with ``tau`` at the step's mean
    irradiance.
    """
    y = y0
    out[0] = y
    xa = math.log(irr[0])
    for k in range(1, s.shape[0]):
        xb = math.log(irr[k])
        im = 0.5 * (irr[k - 1] + irr[k])
        bow = math.log(im) - 0.5 * (xa + xb)
        h = s[k] - s[k - 1]
        tau = tau_num / (im + dark)
        if tau > tau_max:
            tau = tau_max
        q = h / tau
        g = -math.expm1(-q)
        y = y + (xa - y) * g + (xb - xa) * _one_minus_phi1(q) + 4.0 * bow * _curvature_gain(q)
        out[k] = y
        xa = xb
    return y


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _lowpass_rows_static(radiance, a1, b2, s, y0, tau_num, dark, tau_max, out, y_end):
    n = radiance.shape[0]
    for r in nb.prange(n):
        irr = a1 * radiance[r] + b2
        y_end[r] = _lowpass_row(irr, s, y0[r], tau_num, dark, tau_max, out[r])


def lowpass_rows(radiance: np.ndarray, a1: np.ndarray, b2: np.ndarray, s: np.ndarray,
                 y0: np.ndarray, lowpass: Lowpass) -> tuple[np.ndarray, np.ndarray]:
    """Photoreceptor output rows ``y_r(s_k)`` for static radiances ``radiance[r]``.

    The irradiance of row ``r`` at grid point ``k`` is ``a1[k] radiance[r] + b2[k]``
    (``a1 = k_lens T1``, ``b2 = k_lens L_const T2``); ``y0[r]`` is the output at the
    cycle's start. Returns ``(rows (n, K), y at the cycle's end (n,))``.
    """
    radiance = np.ascontiguousarray(radiance, dtype=np.float64)
    out = np.empty((radiance.size, s.size), dtype=np.float64)
    y_end = np.empty(radiance.size, dtype=np.float64)
    _lowpass_rows_static(radiance, a1, b2, s, np.ascontiguousarray(y0, dtype=np.float64),
                         float(lowpass.tau_num), float(lowpass.dark_irradiance),
                         float(lowpass.tau_max_us), out, y_end)
    return out, y_end


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _pixel_rows(frames, fa, fw, a1, b2, s, y0, lowpass, tau_num, dark, tau_max, out, y_end):
    n = frames.shape[0]
    nk = s.shape[0]
    static = frames.shape[1] == 1
    for r in nb.prange(n):
        irr = np.empty(nk)
        for k in range(nk):
            if static:
                lum = frames[r, 0]
            else:
                i = fa[k]
                lum = frames[r, i] + fw[k] * (frames[r, i + 1] - frames[r, i])
            irr[k] = a1[k] * lum + b2[k]
        if lowpass:
            y_end[r] = _lowpass_row(irr, s, y0[r], tau_num, dark, tau_max, out[r])
        else:
            out[r, :] = irr
            y_end[r] = math.log(irr[nk - 1])


def pixel_rows(frames: np.ndarray, fa: np.ndarray, fw: np.ndarray, a1: np.ndarray,
               b2: np.ndarray, s: np.ndarray, y0: np.ndarray,
               lowpass: Lowpass | None) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's own row: irradiance (``lowpass`` None) or photoreceptor output.

    ``frames`` is ``(n_pixels, n_frames)`` radiance; grid point ``k`` sees
    ``frames[:, fa[k]] + fw[k] (frames[:, fa[k] + 1] - frames[:, fa[k]])`` (or the one
    frame). Returns ``(rows, log signal at the cycle's end)``.
    """
    n = frames.shape[0]
    out = np.empty((n, s.size), dtype=np.float64)
    y_end = np.empty(n, dtype=np.float64)
    lp = lowpass or Lowpass(1.0, 0.0, 1.0)
    _pixel_rows(np.ascontiguousarray(frames, dtype=np.float64), fa, fw, a1, b2, s,
                np.ascontiguousarray(y0, dtype=np.float64), lowpass is not None,
                float(lp.tau_num), float(lp.dark_irradiance), float(lp.tau_max_us), out, y_end)
    return out, y_end


def irradiance_rows(a1: np.ndarray, b2: np.ndarray) -> np.ndarray:
    """The two rows of the exact irradiance: ``(k_lens T1, k_lens L_const T2)``."""
    return np.ascontiguousarray(np.stack([a1, b2]), dtype=np.float64)


# ----------------------------------------------------------------------------- radiance grid


def radiance_grid(radiance: np.ndarray, *, dlog: float, floor: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Log-radiance grid for the tabulated low-pass.

    Each pixel's ``g = log(max(L, floor))`` lies between grid values ``g_j = g_0 + j dlog``
    and ``g_{j+1}``. Only the grid values some pixel needs are returned.

    Returns ``(values (n_rows,), lower row index per pixel, weight of the upper row per
    pixel)``: pixel ``p`` interpolates ``(1 - w) row[j] + w row[j + 1]``.
    """
    if not (math.isfinite(dlog) and dlog > 0):
        raise ValueError(f"dlog_radiance must be positive, got {dlog}")
    g = np.log(np.maximum(np.asarray(radiance, dtype=np.float64).ravel(), floor))
    g0 = float(g.min())
    pos = (g - g0) / dlog
    j = np.floor(pos).astype(np.int64)
    w = pos - j
    # the grid values in use and each pixel's rank among them: j is a small whole number
    present = np.zeros(int(j.max()) + 2, dtype=np.bool_)
    present[j] = True
    present[j + 1] = True
    used = np.flatnonzero(present)
    rank = np.cumsum(present) - 1
    values = np.exp(g0 + used * dlog)
    return values, rank[j].astype(np.int64), np.clip(w, 0.0, 1.0)


# ----------------------------------------------------------------------------- runs


@nb.njit(cache=True, error_model="numpy")
def _pair_runs(ra, rb, out):
    """Monotone runs of every combination ``wa ra + wb rb`` (``wa, wb >= 0``): ranges of
    knots where both rows move the same way (direction +1 or -1), or where they
    disagree (direction 0, scanned point by point). Flat intervals join the run they are
    in. Returns the number of runs written to ``out`` (``[a, b, dir]``)."""
    nk = ra.shape[0]
    nr = 0
    start = 0
    cur = 2  # 2: not known yet
    for k in range(nk - 1):
        da = ra[k + 1] - ra[k]
        db = rb[k + 1] - rb[k]
        if (da > 0 and db >= 0) or (da >= 0 and db > 0):
            d = 1
        elif (da < 0 and db <= 0) or (da <= 0 and db < 0):
            d = -1
        elif da == 0 and db == 0:
            continue
        else:
            d = 0
        if cur == 2:
            cur = d
        elif d != cur:
            out[nr, 0] = start
            out[nr, 1] = k
            out[nr, 2] = cur
            nr += 1
            start = k
            cur = d
    out[nr, 0] = start
    out[nr, 1] = nk - 1
    out[nr, 2] = 1 if cur == 2 else cur
    return nr + 1


@nb.njit(cache=True, error_model="numpy")
def _max_runs(ra, rb):
    """An upper bound on the runs of a pair: one more than the number of times the pair
    of interval slopes' signs changes."""
    n = 1
    pa = 2
    pb = 2
    for k in range(ra.shape[0] - 1):
        da = ra[k + 1] - ra[k]
        db = rb[k + 1] - rb[k]
        sa = 1 if da > 0 else (-1 if da < 0 else 0)
        sb = 1 if db > 0 else (-1 if db < 0 else 0)
        if (sa != pa or sb != pb) and pa != 2:
            n += 1
        pa = sa
        pb = sb
    return n


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _pair_caps(rows, pa, pb, out):
    for i in nb.prange(pa.shape[0]):
        out[i] = _max_runs(rows[pa[i]], rows[pb[i]])


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _all_pair_runs(rows, pa, pb, cap_off, counts, tab):
    for i in nb.prange(pa.shape[0]):
        counts[i] = _pair_runs(rows[pa[i]], rows[pb[i]], tab[cap_off[i]:cap_off[i + 1]])


def row_runs(rows: np.ndarray, pair_a: np.ndarray, pair_b: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Monotone runs of each row pair ``(rows[pair_a[i]], rows[pair_b[i]])``.

    Returns ``(run_off (n + 1,), run_tab (total, 3))``: pair ``i`` has runs
    ``run_tab[run_off[i]:run_off[i + 1]]`` (``[first knot, last knot, direction]``).
    """
    n = int(pair_a.size)
    caps = np.empty(n, dtype=np.int64)
    _pair_caps(rows, pair_a, pair_b, caps)
    cap_off = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(caps, out=cap_off[1:])
    tab = np.empty((int(cap_off[-1]), 3), dtype=np.int64)
    counts = np.zeros(n, dtype=np.int64)
    _all_pair_runs(rows, pair_a, pair_b, cap_off, counts, tab)
    off = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=off[1:])
    within = np.arange(tab.shape[0]) - np.repeat(cap_off[:-1], caps)
    return off, tab[within < np.repeat(counts, caps)]
