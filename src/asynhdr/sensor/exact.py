"""The exact engine: threshold-crossing times computed, not sampled.

Within a cycle both transmittances are piecewise linear on shared knots ``u_j``, so a
pixel's irradiance (in units of ``k_lens * L_const``)::

    E(u) = rho * T1(u) + T2(u),      rho = L / L_const

is piecewise linear too, and between its turning points it is monotone. The cycle is
cut once into *pieces* (runs of knot intervals on which the sign of ``dE/du`` can
change at most once for every ``rho >= 0``: ``dT1`` keeps its sign and
``-dT2/dT1`` is monotone). Per pixel, a binary search finds the turning point inside
each piece; inside each monotone run, a binary search over the knots finds the
interval where ``E`` reaches the next level ``exp(ref +/- c)`` and a linear solve
gives the exact phase. Cost grows with the number of events (times ``log2`` of the
knot count), not with pixels x time steps.

The reference level is reset to the level reached at each event, so a pixel whose
irradiance falls and then rises fires OFF events and then ON events with the
hysteresis this gives. Crossing an exact level counts (a pixel that returns to a
level it left fires there), within a relative tolerance of ``1e-12``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from asynhdr.events import EVENT_DTYPE
from asynhdr.sensor._rng import hash_normal2

__all__ = ["cycle_pieces", "simulate_cycle_exact"]

_EPS = 1e-12


def cycle_pieces(t1: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """Cut the knot intervals into pieces on which ``E`` turns at most once.

    Returns an ``(n_pieces, 2)`` int64 array of ``[first interval, end interval)``.
    On a piece, ``dT1`` has one sign (or is zero throughout with ``dT2`` of one sign)
    and ``r = -dT2/dT1`` is monotone, so ``sign(rho dT1 + dT2)`` switches at most once
    along the piece for any ``rho >= 0``.
    """
    d1 = np.diff(np.asarray(t1, dtype=np.float64))
    d2 = np.diff(np.asarray(t2, dtype=np.float64))
    n = d1.size
    pieces: list[tuple[int, int]] = []
    start = 0
    direction = 0  # monotone direction of r within the current piece: 0 unknown, +1, -1

    def sign(v: float) -> int:
        return int(v > 0) - int(v < 0)

    for j in range(1, n):
        s_prev, s_cur = sign(d1[j - 1]), sign(d1[j])
        cut = False
        if s_cur != s_prev:
            cut = True
        elif s_cur == 0:
            if sign(d2[j]) != sign(d2[j - 1]) and sign(d2[j]) != 0 and sign(d2[j - 1]) != 0:
                cut = True
        else:
            r_prev = -d2[j - 1] / d1[j - 1]
            r_cur = -d2[j] / d1[j]
            # rounding in the knots makes r of a straight ramp wobble by ~1e-16: ignore
            tol = 1e-9 * max(abs(r_prev), abs(r_cur), 1e-300)
            step = sign(r_cur - r_prev) if abs(r_cur - r_prev) > tol else 0
            if step != 0:
                if direction == 0:
                    direction = step
                elif step != direction:
                    cut = True
        if cut:
            pieces.append((start, j))
            start = j
            direction = 0
    pieces.append((start, n))
    return np.asarray(pieces, dtype=np.int64)


@nb.njit(cache=True, inline="always")
def _first_reaching(r, t1, t2, lo, hi, target, up):
    """First knot j in [lo, hi] where E_j = r t1_j + t2_j reaches ``target``.

    ``up``: E is non-decreasing on [lo, hi] and we look for E_j >= target; else E is
    non-increasing and we look for E_j <= target. Returns hi + 1 when none does.
    Galloping search from ``lo`` (the next crossing is usually close), then bisection.
    """
    step = 1
    prev = lo
    j = lo
    while True:
        e = r * t1[j] + t2[j]
        if (e >= target) if up else (e <= target):
            break
        if j == hi:
            return hi + 1
        prev = j
        j = min(hi, j + step)
        step *= 2
    if j == lo:
        return lo
    a = prev + 1
    b = j
    while a < b:
        mid = (a + b) >> 1
        e = r * t1[mid] + t2[mid]
        if (e >= target) if up else (e <= target):
            b = mid
        else:
            a = mid + 1
    return a


@nb.njit(cache=True)
def _pixel_runs(rho, d1, d2, pieces, runs):
    """Fill ``runs`` (n, 3: first knot, last knot, +1/-1) for one pixel; return count."""
    nr = 0
    for q in range(pieces.shape[0]):
        a = pieces[q, 0]
        b = pieces[q, 1]  # intervals a .. b-1, knots a .. b
        pos_first = rho * d1[a] + d2[a] >= 0.0
        pos_last = rho * d1[b - 1] + d2[b - 1] >= 0.0
        if pos_first == pos_last:
            m = b
        else:
            lo = a + 1
            hi = b - 1
            while lo < hi:
                mid = (lo + hi) >> 1
                if (rho * d1[mid] + d2[mid] >= 0.0) == pos_last:
                    hi = mid
                else:
                    lo = mid + 1
            m = lo
        runs[nr, 0] = a
        runs[nr, 1] = m
        runs[nr, 2] = 1 if pos_first else -1
        nr += 1
        if m < b:
            runs[nr, 0] = m
            runs[nr, 1] = b
            runs[nr, 2] = 1 if pos_last else -1
            nr += 1
    return nr


@nb.njit(cache=True, parallel=True)
def _bounds(rho, c_on, c_off, t1, t2, pieces, c_scale, reset_sigma, out_bound):
    """Upper bound on each pixel's events in one cycle: log variation over the pixel's
    smallest effective step (threshold less six sigma of reset noise, times
    ``c_scale``), plus slack per run."""
    d1 = t1[1:] - t1[:-1]
    d2 = t2[1:] - t2[:-1]
    npix = rho.shape[0]
    for p in nb.prange(npix):
        runs = np.empty((2 * pieces.shape[0], 3), dtype=np.int64)
        nr = _pixel_runs(rho[p], d1, d2, pieces, runs)
        cmin = min(c_on[p], c_off[p])
        cmin = max(cmin - 6.0 * reset_sigma, 0.25 * cmin) * c_scale
        total = 0.0
        for k in range(nr):
            ea = rho[p] * t1[runs[k, 0]] + t2[runs[k, 0]]
            eb = rho[p] * t1[runs[k, 1]] + t2[runs[k, 1]]
            total += abs(np.log(eb) - np.log(ea)) / cmin + 3.0
        out_bound[p] = np.int64(total) + 2


@nb.njit(cache=True, inline="always")
def _e_at(r, u, t1, t2, a, ph):
    """E at phase ``ph`` inside knot interval ``a``."""
    ea = r * t1[a] + t2[a]
    eb = r * t1[a + 1] + t2[a + 1]
    w = (ph - u[a]) / (u[a + 1] - u[a])
    return ea + (eb - ea) * w


@nb.njit(cache=True, inline="always")
def _interval_of(u, lo, hi, ph):
    """Largest knot index j in [lo, hi] with u[j] <= ph (u[lo] <= ph assumed)."""
    while lo < hi:
        mid = (lo + hi + 1) >> 1
        if u[mid] <= ph:
            lo = mid
        else:
            hi = mid - 1
    return lo


@nb.njit(cache=True, parallel=True)
def _fill(rho, c_on, c_off, ref, blind, pending, u, t1, t2, pieces, period_us, offsets,
          slot_t, slot_p, counts, overflow, seed, cycle, reset_sigma, refr_us, lag_scale,
          tau_num, dark_irr, tau_max_us, latency_us, jitter_us, t_lo, nbins, alive):
    """Events of one cycle per pixel into slots ``offsets[p] ..``.

    Per-pixel state carried across cycles: ``ref`` (reference log level), ``blind``
    (phase, relative to this cycle's start, before which the pixel cannot fire: the
    end of its last refractory period or its last event), ``pending`` (the reference
    is to be reset to the level at ``blind``: end of a refractory period).
    Slot times are µs offsets from ``t_lo`` (cycle start + t_lo is bin 0).
    """
    d1 = t1[1:] - t1[:-1]
    d2 = t2[1:] - t2[:-1]
    npix = rho.shape[0]
    refr_ph = refr_us / period_us
    use_lag = tau_num > 0.0
    draws = jitter_us > 0.0 or reset_sigma > 0.0
    for p in nb.prange(npix):
        if alive[p] == 0:
            counts[p] = 0
            continue
        runs = np.empty((2 * pieces.shape[0], 3), dtype=np.int64)
        z_reset = 0.0
        r = rho[p]
        nr = _pixel_runs(r, d1, d2, pieces, runs)
        lvl = ref[p]
        con = c_on[p]
        coff = c_off[p]
        res = blind[p]
        pend = pending[p] != 0
        o = offsets[p]
        n = 0
        cap = offsets[p + 1] - o
        last_t = -1e300
        for k in range(nr):
            a = runs[k, 0]
            b = runs[k, 1]
            up = runs[k, 2] > 0
            if u[b] <= res:
                continue
            if u[a] < res:
                a = _interval_of(u, a, b - 1, res)
            while True:
                if n >= cap:
                    overflow[p] = 1
                    break
                ph0 = max(u[a], res)
                e0 = _e_at(r, u, t1, t2, a, ph0) if ph0 > u[a] else r * t1[a] + t2[a]
                if pend:
                    lvl = np.log(e0) + reset_sigma * z_reset
                    pend = False
                level = lvl + con if up else lvl - coff
                target = np.exp(level)
                if (e0 >= target * (1.0 - _EPS)) if up else (e0 <= target * (1.0 + _EPS)):
                    ph = ph0
                    jint = a
                else:
                    if a + 1 > b:
                        break
                    j = _first_reaching(r, t1, t2, a + 1, b, target * (1.0 - _EPS)
                                        if up else target * (1.0 + _EPS), up)
                    if j > b:
                        break
                    if j - 1 == a:
                        lo_ph = ph0
                        lo_e = e0
                    else:
                        lo_ph = u[j - 1]
                        lo_e = r * t1[j - 1] + t2[j - 1]
                    hi_e = r * t1[j] + t2[j]
                    de = hi_e - lo_e
                    f = (target - lo_e) / de if de != 0.0 else 1.0
                    f = min(max(f, 0.0), 1.0)
                    ph = lo_ph + f * (u[j] - lo_ph)
                    jint = j - 1
                t_us = ph * period_us + latency_us
                if use_lag:
                    tau = tau_num / (lag_scale * target + dark_irr)
                    t_us += min(tau, tau_max_us)
                if draws:
                    z_jit, z_reset = hash_normal2(seed, p, cycle, n)
                    t_us += jitter_us * z_jit
                if t_us < last_t:
                    t_us = last_t
                last_t = t_us
                tb = np.int64(np.floor(t_us)) - t_lo
                slot_t[o + n] = min(max(tb, np.int64(0)), nbins - 1)
                slot_p[o + n] = 1 if up else -1
                n += 1
                if refr_ph > 0.0:
                    res = ph + refr_ph
                    pend = True
                    if res >= u[b]:
                        break
                    a = _interval_of(u, jint, b - 1, res)
                else:
                    lvl = level + reset_sigma * z_reset
                    res = ph
                    a = jint
        if pend and res <= u[u.shape[0] - 1]:
            # the refractory period ended in a stretch no run covered: reset there
            jj = _interval_of(u, 0, u.shape[0] - 2, max(res, 0.0))
            lvl = np.log(_e_at(r, u, t1, t2, jj, max(res, 0.0)))
            pend = False
        counts[p] = n
        ref[p] = lvl
        blind[p] = res - 1.0
        pending[p] = 1 if pend else 0


@nb.njit(cache=True, parallel=True)
def _gather_sorted(offsets, counts, slot_t, slot_p, width, t_first, nbins, out):
    """Counting sort of one cycle's events by time into ``out`` (structured, EVENT_DTYPE).

    Stable: among equal times, pixel order (row-major), then each pixel's own order.
    Pixels are split into contiguous blocks, one histogram per block, so blocks can
    scatter in parallel without changing the order. Bin ``i`` is time ``t_first + i``.
    """
    npix = counts.shape[0]
    nblk = 16
    bsize = (npix + nblk - 1) // nblk
    hist = np.zeros((nblk, nbins), dtype=np.int64)
    for b in nb.prange(nblk):
        p0 = b * bsize
        p1 = min(npix, p0 + bsize)
        for p in range(p0, p1):
            o = offsets[p]
            for k in range(counts[p]):
                hist[b, slot_t[o + k]] += 1
    acc = np.int64(0)
    for i in range(nbins):
        for b in range(nblk):
            c = hist[b, i]
            hist[b, i] = acc
            acc += c
    for b in nb.prange(nblk):
        p0 = b * bsize
        p1 = min(npix, p0 + bsize)
        for p in range(p0, p1):
            o = offsets[p]
            y = p // width
            x = p - y * width
            for k in range(counts[p]):
                tb = slot_t[o + k]
                d = hist[b, tb]
                hist[b, tb] = d + 1
                out[d].x = x
                out[d].y = y
                out[d].p = slot_p[o + k]
                out[d].t = t_first + tb


class ExactState:
    """Per-pixel state of the exact engine carried from cycle to cycle."""

    def __init__(self, ref: np.ndarray) -> None:
        self.ref = np.ascontiguousarray(ref, dtype=np.float64)
        self.blind = np.full(ref.shape[0], -1.0, dtype=np.float64)
        self.pending = np.zeros(ref.shape[0], dtype=np.int8)


def simulate_cycle_exact(
    rho: np.ndarray,
    c_on: np.ndarray,
    c_off: np.ndarray,
    state: ExactState,
    phase: np.ndarray,
    t1: np.ndarray,
    t2: np.ndarray,
    *,
    width: int,
    period_us: int,
    t_start_us: int,
    pieces: np.ndarray | None = None,
    cycle: int = 0,
    seed: int = 0,
    reset_noise_sigma: float = 0.0,
    refractory_us: float = 0.0,
    irradiance_scale: float = 1.0,
    tau_ref_us: float = 0.0,
    cutoff_irradiance: float = 1.0,
    dark_irradiance: float = 0.0,
    tau_max_us: float = 0.0,
    latency_us: float = 0.0,
    jitter_sigma_us: float = 0.0,
    alive: np.ndarray | None = None,
) -> np.ndarray:
    """Events of one cycle of the pixel array, sorted by time.

    Parameters
    ----------
    rho : float64 ``(n_pixels,)``, radiance over ``L_const`` (row-major pixels).
    c_on, c_off : float64 per-pixel thresholds (log units).
    state : per-pixel state, updated in place.
    phase, t1, t2 : the cycle's knots and transmittances.
    width : sensor width (pixel index ``p = y * width + x``).
    period_us, t_start_us : cycle length and start, µs.
    cycle, seed : counters for the per-event random draws (reset noise, jitter).
    reset_noise_sigma, refractory_us, latency_us, jitter_sigma_us : see ``SensorParams``.
    irradiance_scale : ``k_lens * L_const``: turns ``E`` into sensor irradiance.
    tau_ref_us, cutoff_irradiance, dark_irradiance, tau_max_us : the photoreceptor's
        time constant ``tau_ref (I_ref + I_dark) / (I + I_dark)`` (capped), applied as
        the lag of a first-order low-pass behind a slowly varying input: each event is
        delayed by ``tau`` at the irradiance where it fires. 0 disables.
    alive : int8 per pixel, 0 for dead pixels (they fire nothing); default all alive.

    Returns
    -------
    Events (``EVENT_DTYPE``) sorted by ``t``; times may reach past the cycle's end by
    the latency, lag and jitter.
    """
    if pieces is None:
        pieces = cycle_pieces(t1, t2)
    npix = rho.shape[0]
    t_lo = -math.ceil(6.0 * jitter_sigma_us) - 1 if jitter_sigma_us > 0 else 0
    lag_max = min(tau_max_us, tau_ref_us * (cutoff_irradiance + dark_irradiance)
                  / max(dark_irradiance, 1e-300)) if tau_ref_us > 0 else 0.0
    t_hi = math.ceil(period_us + latency_us + lag_max + 6.0 * jitter_sigma_us) + 1
    nbins = t_hi - t_lo + 1
    tau_num = tau_ref_us * (cutoff_irradiance + dark_irradiance) if tau_ref_us > 0 else 0.0
    c_scale = 1.0
    if alive is None:
        alive = np.ones(npix, dtype=np.int8)
    bound = np.empty(npix, dtype=np.int64)
    for _attempt in range(6):
        _bounds(rho, c_on, c_off, t1, t2, pieces, c_scale, float(reset_noise_sigma), bound)
        offsets = np.zeros(npix + 1, dtype=np.int64)
        np.cumsum(bound, out=offsets[1:])
        total = int(offsets[-1])
        slot_t = np.empty(total, dtype=np.int64)
        slot_p = np.empty(total, dtype=np.int8)
        counts = np.empty(npix, dtype=np.int64)
        overflow = np.zeros(npix, dtype=np.int8)
        saved = (state.ref.copy(), state.blind.copy(), state.pending.copy())
        _fill(rho, c_on, c_off, state.ref, state.blind, state.pending, phase, t1, t2, pieces,
              float(period_us), offsets, slot_t, slot_p, counts, overflow, np.uint64(seed),
              np.int64(cycle), float(reset_noise_sigma), float(refractory_us),
              float(irradiance_scale), float(tau_num), float(dark_irradiance),
              float(tau_max_us), float(latency_us), float(jitter_sigma_us), np.int64(t_lo),
              np.int64(nbins), alive)
        if not overflow.any():
            break
        state.ref[:], state.blind[:], state.pending[:] = saved
        c_scale *= 0.5
    else:
        raise RuntimeError("exact engine: event bound exceeded repeatedly")
    out = np.empty(int(counts.sum()), dtype=EVENT_DTYPE)
    _gather_sorted(offsets, counts, slot_t, slot_p, width, np.int64(t_start_us + t_lo),
                   np.int64(nbins), out)
    return out
