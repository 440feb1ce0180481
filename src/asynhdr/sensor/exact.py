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

import numba as nb
import numpy as np

from asynhdr.events import EVENT_DTYPE

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
            step = sign(r_cur - r_prev)
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
def _bounds(rho, c_on, c_off, t1, t2, pieces, out_bound):
    """Upper bound on each pixel's events in one cycle (log variation / c + 1 per run)."""
    d1 = t1[1:] - t1[:-1]
    d2 = t2[1:] - t2[:-1]
    npix = rho.shape[0]
    for p in nb.prange(npix):
        runs = np.empty((2 * pieces.shape[0], 3), dtype=np.int64)
        nr = _pixel_runs(rho[p], d1, d2, pieces, runs)
        cmin = min(c_on[p], c_off[p])
        total = 0.0
        for k in range(nr):
            ea = rho[p] * t1[runs[k, 0]] + t2[runs[k, 0]]
            eb = rho[p] * t1[runs[k, 1]] + t2[runs[k, 1]]
            total += abs(np.log(eb) - np.log(ea)) / cmin + 2.0
        out_bound[p] = np.int64(total) + 1


@nb.njit(cache=True, parallel=True)
def _fill(rho, c_on, c_off, ref, u, t1, t2, pieces, period_us, offsets, slot_t, slot_p,
          counts):
    """Events of one cycle per pixel into slots ``offsets[p] ..``; updates ``ref``."""
    d1 = t1[1:] - t1[:-1]
    d2 = t2[1:] - t2[:-1]
    npix = rho.shape[0]
    for p in nb.prange(npix):
        runs = np.empty((2 * pieces.shape[0], 3), dtype=np.int64)
        r = rho[p]
        nr = _pixel_runs(r, d1, d2, pieces, runs)
        lvl = ref[p]
        con = c_on[p]
        coff = c_off[p]
        o = offsets[p]
        n = 0
        cap = offsets[p + 1] - o
        for k in range(nr):
            a = runs[k, 0]
            b = runs[k, 1]
            up = runs[k, 2] > 0
            while n < cap:
                if up:
                    target = np.exp(lvl + con)
                    j = _first_reaching(r, t1, t2, a, b, target * (1.0 - _EPS), True)
                else:
                    target = np.exp(lvl - coff)
                    j = _first_reaching(r, t1, t2, a, b, target * (1.0 + _EPS), False)
                if j > b:
                    break
                if j == a:
                    ph = u[a]
                else:
                    e0 = r * t1[j - 1] + t2[j - 1]
                    e1 = r * t1[j] + t2[j]
                    de = e1 - e0
                    f = (target - e0) / de if de != 0.0 else 1.0
                    f = min(max(f, 0.0), 1.0)
                    ph = u[j - 1] + f * (u[j] - u[j - 1])
                    a = j - 1
                slot_t[o + n] = np.int64(np.floor(ph * period_us))
                slot_p[o + n] = 1 if up else -1
                n += 1
                lvl = lvl + con if up else lvl - coff
        counts[p] = n
        ref[p] = lvl


@nb.njit(cache=True, parallel=True)
def _gather_sorted(offsets, counts, slot_t, slot_p, width, t_start, period_us, out):
    """Counting sort of one cycle's events by time into ``out`` (structured, EVENT_DTYPE).

    Stable: among equal times, pixel order (row-major), then each pixel's own order.
    Pixels are split into contiguous blocks, one histogram per block, so blocks can
    scatter in parallel without changing the order.
    """
    npix = counts.shape[0]
    nbins = np.int64(period_us) + 1
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
    # exclusive prefix over (bin, block) in that order
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
                out[d].t = t_start + tb


def simulate_cycle_exact(
    rho: np.ndarray,
    c_on: np.ndarray,
    c_off: np.ndarray,
    ref: np.ndarray,
    phase: np.ndarray,
    t1: np.ndarray,
    t2: np.ndarray,
    *,
    width: int,
    period_us: int,
    t_start_us: int,
    pieces: np.ndarray | None = None,
) -> np.ndarray:
    """Events of one cycle of the ideal pixel array, sorted by time.

    Parameters
    ----------
    rho : float64 ``(n_pixels,)``, radiance over ``L_const`` (row-major pixels).
    c_on, c_off : float64 per-pixel thresholds (log units).
    ref : float64 per-pixel reference log level (``log E``); updated in place.
    phase, t1, t2 : the cycle's knots and transmittances.
    width : sensor width (pixel index ``p = y * width + x``).
    period_us, t_start_us : cycle length and start, µs.

    Returns
    -------
    Events (``EVENT_DTYPE``) sorted by ``t``.
    """
    if pieces is None:
        pieces = cycle_pieces(t1, t2)
    npix = rho.shape[0]
    bound = np.empty(npix, dtype=np.int64)
    _bounds(rho, c_on, c_off, t1, t2, pieces, bound)
    offsets = np.zeros(npix + 1, dtype=np.int64)
    np.cumsum(bound, out=offsets[1:])
    total = int(offsets[-1])
    slot_t = np.empty(total, dtype=np.int64)
    slot_p = np.empty(total, dtype=np.int8)
    counts = np.empty(npix, dtype=np.int64)
    _fill(rho, c_on, c_off, ref, phase, t1, t2, pieces, float(period_us), offsets, slot_t,
          slot_p, counts)
    out = np.empty(int(counts.sum()), dtype=EVENT_DTYPE)
    _gather_sorted(offsets, counts, slot_t, slot_p, width, np.int64(t_start_us),
                   np.int64(period_us), out)
    return out
