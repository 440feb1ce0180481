"""The pixel: comparator, reset, refractory period, latency, jitter and noise events.

One model for every engine. Each pixel reads its signal ``V(t)`` (the log irradiance
after the photoreceptor, or the irradiance itself when there is no low-pass) as a
piecewise-linear function on the cycle's grid (:mod:`asynhdr.sensor.photoreceptor`)
and keeps a reference level ``ref`` (log units). Per pixel and cycle:

1. **Crossing.** The pixel is ready from ``t_ready`` on. The next signal crossing is the
   first ``t_c >= t_ready`` where ``log V >= ref + c_on`` (ON) or ``<= ref - c_off``
   (OFF), ``c_on``/``c_off`` the pixel's frozen thresholds. Within a grid interval the
   crossing is solved exactly (linear interpolation of ``V``).
2. **Noise events.** Background events (leak, shot noise, hot pixels) arrive as Poisson
   processes (:mod:`asynhdr.sensor.noise`). An arrival at ``t_n`` while the pixel is
   ready fires the pixel, exactly like a crossing, with the arrival's polarity; an
   arrival while the pixel is blind is lost. Signal and noise events alike reset the
   pixel and start its dead time.
3. **Firing.** A crossing fires at ``t_f = t_c + jitter_sigma_us z`` (Gaussian timing
   noise of the front end, ``z`` a standard normal draw), never before the end of the
   previous dead time; a noise arrival fires at ``t_f = t_n``. The timestamp is
   ``t_f + latency_us``, floored to whole µs (then to ``timestamp_resolution_us``).
4. **Reset.** The pixel is acknowledged (``latency_us`` after firing), resets, and is
   blind for ``refractory_us``: its dead time ends at
   ``t_end = t_f + latency_us + refractory_us``, when the new reference is taken:
   ``ref = log V(t_end) + reset_noise_sigma z'``. Without latency, jitter and refractory
   period (the ideal pixel) a crossing resets the reference to the level just crossed,
   ``ref +/- c`` (plus reset noise), and the pixel is ready at once.

So no two timestamps of a pixel are closer than ``refractory_us + latency_us``, signal
or noise. ``z`` and ``z'`` of a pixel's ``n``-th event of cycle ``m`` are the two
standard normals of :func:`asynhdr.sensor._rng.hash_normal2` at ``(seed, pixel, m, n)``
(ziggurat draws from a counter-based hash): the same seed gives the same events on any
number of threads.

Finding crossings: the grid is cut into runs on which the pixel's ``V`` is monotone
(for the exact irradiance, per pixel from the turning point of ``L T1 + L_const T2``
inside each piece of the waveform; for tabulated rows, from the rows' own turns), so
the next crossing of a level is a search from the current point: on tabulated rows a
ladder of levels per run (:func:`level_index`) brackets it with one look-up, on the exact
irradiance secant steps from the local slope do; a bisection ends both. Runs whose
direction the two interpolated rows do not agree on are scanned point by point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numba as nb
import numpy as np

from asynhdr._pool import block_order
from asynhdr.events import EVENT_DTYPE
from asynhdr.sensor._rng import hash_normal2_at, hash_stream

__all__ = ["CycleFiring", "PixelState", "SortKeys", "cycle_pieces", "fire_cycle", "gather_sorted",
           "place_events", "sort_keys"]

_EPS = 1e-12
_NEVER = -1e300
_INF = 1e300


class PixelState:
    """What a pixel carries from one cycle to the next.

    Attributes
    ----------
    ref : float64 reference level (log irradiance units).
    ready : float64, µs relative to the next cycle's start: the end of the last dead time
        (the pixel cannot fire before it).
    pending : int8, 1 when the dead time ends after the cycle did: the reference is then
        taken at ``ready`` in the next cycle.
    pending_z : float64, the reset-noise draw of that pending reset.
    resume : float64, µs from the cycle's start, within a cycle fired in slices: where the
        pixel's search for its next event goes on (``-inf`` at a cycle's start).
    done : int64, the events the pixel fired so far in the cycle (the index of its next
        event's draws).
    next_fire : float64, within a cycle fired in slices: no event of the pixel fires before
        it (the next event's time where a slice found it beyond its end; ``-inf`` when
        nothing is known).
    """

    def __init__(self, ref: np.ndarray) -> None:
        self.ref = np.ascontiguousarray(ref, dtype=np.float64).copy()
        n = self.ref.size
        self.ready = np.full(n, _NEVER, dtype=np.float64)
        self.pending = np.zeros(n, dtype=np.int8)
        self.pending_z = np.zeros(n, dtype=np.float64)
        self.resume = np.full(n, _NEVER, dtype=np.float64)
        self.done = np.zeros(n, dtype=np.int64)
        self.next_fire = np.full(n, _NEVER, dtype=np.float64)

    def copy(self, *, slices: bool = True) -> PixelState:
        """A copy; without ``slices`` one to restore with ``slices=False`` only (its slice
        fields are empty)."""
        if slices:
            out = PixelState(self.ref)
            out.restore(self)
            return out
        out = PixelState.__new__(PixelState)
        out.ref = self.ref.copy()
        out.ready = self.ready.copy()
        out.pending = self.pending.copy()
        out.pending_z = self.pending_z.copy()
        out.resume = np.empty(0)
        out.done = np.empty(0, dtype=np.int64)
        out.next_fire = np.empty(0)
        return out

    def restore(self, other: PixelState, *, slices: bool = True) -> None:
        """Take ``other``'s values (without ``slices``, not the slice fields)."""
        self.ref[:] = other.ref
        self.ready[:] = other.ready
        self.pending[:] = other.pending
        self.pending_z[:] = other.pending_z
        if slices:
            self.resume[:] = other.resume
            self.done[:] = other.done
            self.next_fire[:] = other.next_fire


# ----------------------------------------------------------------------------- runs


def cycle_pieces(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cut the knot intervals into pieces on which ``wa a + wb b`` turns at most once for
    every ``wa, wb >= 0``.

    Returns an ``(n_pieces, 2)`` int64 array of ``[first interval, end interval)``. On a
    piece, ``da`` has one sign (or is zero throughout with ``db`` of one sign) and
    ``r = -db / da`` is monotone, so ``sign(wa da + wb db)`` switches at most once.
    """
    d1 = np.diff(np.asarray(a, dtype=np.float64))
    d2 = np.diff(np.asarray(b, dtype=np.float64))
    n = d1.size
    pieces: list[tuple[int, int]] = []
    start = 0
    direction = 0

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


@nb.njit(cache=True, error_model="numpy")
def _pixel_runs(wa, wb, d1, d2, pieces, runs):
    """Monotone runs ``[first knot, last knot, +1/-1]`` of ``wa a + wb b`` from the
    pieces: a bisection finds the turning point inside each. Returns the count."""
    nr = 0
    for q in range(pieces.shape[0]):
        a = pieces[q, 0]
        b = pieces[q, 1]
        pos_first = wa * d1[a] + wb * d2[a] >= 0.0
        pos_last = wa * d1[b - 1] + wb * d2[b - 1] >= 0.0
        if pos_first == pos_last:
            m = b
        else:
            lo = a + 1
            hi = b - 1
            while lo < hi:
                mid = (lo + hi) >> 1
                if (wa * d1[mid] + wb * d2[mid] >= 0.0) == pos_last:
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


@nb.njit(cache=True, inline="always", error_model="numpy")
def _runs_of(i, mode, wa, wb, d1, d2, pieces, run_key, run_off, run_tab, local):
    """The runs of listed pixel ``i``: its own (mode 0, into ``local``) or shared."""
    if mode == 0:
        nr = _pixel_runs(wa, wb, d1, d2, pieces, local)
        return local, nr
    key = run_key[i]
    lo = run_off[key]
    return run_tab[lo:run_off[key + 1]], run_off[key + 1] - lo


# ----------------------------------------------------------------------------- search


@nb.njit(cache=True, inline="always", error_model="numpy")
def _val(rows, ia, ib, wa, wb, k):
    return wa * rows[ia, k] + wb * rows[ib, k]


@nb.njit(cache=True, inline="always", error_model="numpy")
def _reaches(e, thr, up):
    return (e >= thr) if up else (e <= thr)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _bisect(rows, ia, ib, wa, wb, b, a, thr, up):
    """First knot in ``[b, a]`` that reaches ``thr``, given that ``a`` does (branch-free
    halving)."""
    while b < a:
        mid = (a + b) >> 1
        hit = _reaches(_val(rows, ia, ib, wa, wb, mid), thr, up)
        a = mid if hit else a
        b = b if hit else mid + 1
    return a


@nb.njit(cache=True, inline="always", error_model="numpy")
def _first(rows, ia, ib, wa, wb, lo, hi, thr, up, v_prev):
    """First knot ``j`` in ``[lo, hi]`` where ``V_j >= thr`` (``up``; ``V`` non-decreasing
    there) or ``V_j <= thr`` (non-increasing); ``hi + 1`` when none.

    ``v_prev`` is ``V`` just before ``lo``. Three secant steps from the local slope
    bracket the level (the signal is smooth, so they land close; each step moves one end
    of the bracket, chosen without a branch), a gallop extends the bracket in the rare
    case they did not reach the level, and a branch-free bisection finds the knot.
    """
    v_lo = _val(rows, ia, ib, wa, wb, lo)
    if _reaches(v_lo, thr, up):
        return lo
    if lo == hi:
        return hi + 1
    a = lo
    va = v_lo
    slope = v_lo - v_prev
    b = hi + 1
    for _ in range(3):
        room = b - 1 - a
        if room < 1:
            break
        ahead = (thr - va) / slope if ((slope > 0.0) if up else (slope < 0.0)) else 2.0
        step = 1 if ahead < 1.0 else (room if ahead >= room else np.int64(ahead))
        g = a + step
        e = _val(rows, ia, ib, wa, wb, g)
        hit = _reaches(e, thr, up)
        slope = (e - va) / step
        b = g if hit else b
        va = va if hit else e
        a = a if hit else g
    if b > hi:
        if a == hi:
            return hi + 1
        # not bracketed yet: gallop forward from a
        step = 1
        while True:
            g = min(hi, a + step)
            if _reaches(_val(rows, ia, ib, wa, wb, g), thr, up):
                b = g
                break
            if g == hi:
                return hi + 1
            a = g
            step *= 2
    return _bisect(rows, ia, ib, wa, wb, a + 1, b, thr, up)


@nb.njit(cache=True, error_model="numpy")
def _index_row(x, k0, k1, sg, vmin, dq, out, col):
    """``out[q, col]``: the first knot ``k`` in ``[k0, k1]`` where ``sg x[k] >= vmin + q dq``
    (``k1 + 1`` when none); ``sg x`` is non-decreasing there, so one forward pass."""
    k = k0
    for q in range(out.shape[0]):
        lvl = vmin + q * dq
        while k <= k1 and sg * x[k] < lvl:
            k += 1
        out[q, col] = k


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _build_index(rows, rep_a, rep_b, run_off, run_tab, inv_off, inv_lvl, inv_tab):
    for key in nb.prange(rep_a.shape[0]):
        if rep_a[key] < 0:
            continue
        xa = rows[rep_a[key]]
        xb = rows[rep_b[key]]
        for g in range(run_off[key], run_off[key + 1]):
            inv_lvl[g, 1] = 0.0
            m = inv_off[g + 1] - inv_off[g] - 1
            d = run_tab[g, 2]
            if d == 0 or m < 1:
                continue
            k0 = run_tab[g, 0]
            k1 = run_tab[g, 1]
            sg = 1.0 if d > 0 else -1.0
            vmin = min(sg * xa[k0], sg * xb[k0])
            vmax = max(sg * xa[k1], sg * xb[k1])
            if not vmax > vmin:
                continue
            dq = (vmax - vmin) / m
            part = inv_tab[inv_off[g]:inv_off[g + 1]]
            _index_row(xa, k0, k1, sg, vmin, dq, part, 0)
            _index_row(xb, k0, k1, sg, vmin, dq, part, 1)
            inv_lvl[g, 0] = vmin
            inv_lvl[g, 1] = 1.0 / dq


def level_index(rows: np.ndarray, ia: np.ndarray, ib: np.ndarray, run_key: np.ndarray,
                run_off: np.ndarray, run_tab: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each row of a monotone run reaches each of a ladder of levels.

    For run ``g`` (both rows of its pair move one way, ``sg = +1`` up or ``-1`` down)
    the levels are ``vmin + q dq`` in ``sg V``, as many as the run has intervals, from
    the rows' lower start to their higher end; ``inv_tab[inv_off[g] + q]`` holds the
    first knot where each of the two rows reaches level ``q``. A pixel's signal lies
    between its two rows, so its first crossing of a level lies between the rows'
    crossings of the ladder's levels on either side: one look-up brackets it.
    Returns ``(inv_off, inv_lvl, inv_tab)``; ``inv_lvl[g] = (vmin, 1 / dq)``, with
    ``1 / dq = 0`` where run ``g`` has no ladder (mixed direction, flat, one interval).
    """
    nkeys = run_off.size - 1
    span = run_tab[:, 1] - run_tab[:, 0]
    m = np.where(run_tab[:, 2] != 0, span, 0)
    inv_off = np.zeros(run_tab.shape[0] + 1, dtype=np.int64)
    np.cumsum(m + 1, out=inv_off[1:])
    rep = np.full(nkeys, -1, dtype=np.int64)
    rep[run_key[::-1]] = np.arange(run_key.size - 1, -1, -1)
    rep_a = np.where(rep >= 0, ia[np.maximum(rep, 0)], -1).astype(np.int64)
    rep_b = np.where(rep >= 0, ib[np.maximum(rep, 0)], -1).astype(np.int64)
    inv_lvl = np.zeros((run_tab.shape[0], 2), dtype=np.float64)
    inv_tab = np.empty((int(inv_off[-1]), 2), dtype=np.int32)
    _build_index(rows, rep_a, rep_b, run_off, run_tab, inv_off, inv_lvl, inv_tab)
    return inv_off, inv_lvl, inv_tab


@nb.njit(cache=True, inline="always", error_model="numpy")
def _first_indexed(rows, ia, ib, wa, wb, lo, hi, thr, up, g, inv_off, inv_lvl, inv_tab):
    """:func:`_first` on run ``g`` of a pair with a level ladder (:func:`level_index`):
    the same knot, bracketed by one look-up instead of secant steps (:func:`_first` itself
    where the run has no ladder)."""
    inv = inv_lvl[g, 1]
    if inv != 0.0:
        if _reaches(_val(rows, ia, ib, wa, wb, lo), thr, up):
            return lo
        if lo == hi:
            return hi + 1
        sg = 1.0 if up else -1.0
        x = (sg * thr - inv_lvl[g, 0]) * inv
        base = inv_off[g]
        m = inv_off[g + 1] - base - 1
        if x >= m + 1.0:
            return hi + 1
        q = np.int64(x) if x > 0.0 else np.int64(0)
        # levels q - 1 and q + 2: one either side of thr whatever the rounding of x
        ql = q - 1 if q >= 1 else 0
        a = max(lo + 1, min(np.int64(inv_tab[base + ql, 0]), np.int64(inv_tab[base + ql, 1])))
        b = hi
        if q + 2 <= m:
            b = min(hi, max(np.int64(inv_tab[base + q + 2, 0]),
                            np.int64(inv_tab[base + q + 2, 1])))
        if _reaches(_val(rows, ia, ib, wa, wb, b), thr, up):
            return _bisect(rows, ia, ib, wa, wb, min(a, b), b, thr, up)
        if b == hi:
            return hi + 1
    return _first(rows, ia, ib, wa, wb, lo, hi, thr, up, _val(rows, ia, ib, wa, wb, lo - 1))


@nb.njit(cache=True, inline="always", error_model="numpy")
def _locate(s, idx, lo, hi, t):
    """Interval index ``k`` in ``[lo, hi]`` with ``s[k] <= t < s[k + 1]`` (``s[lo] <= t``):
    ``idx[m]`` is the last grid point at or before ``m`` µs, so the answer is a few steps
    on from ``idx[floor(t)]``."""
    m = int(t)
    m = min(max(m, 0), idx.shape[0] - 1)
    j = idx[m]
    if j < lo:
        j = lo
    elif j > hi:
        j = hi
    while j < hi and s[j + 1] <= t:
        j += 1
    return j


@nb.njit(cache=True, inline="always", error_model="numpy")
def _run_at(runs, nr, r, t, s):
    """Index of the run containing time ``t``, searching from run ``r`` either way."""
    while r > 0 and s[runs[r, 0]] > t:
        r -= 1
    while r < nr - 1 and s[runs[r, 1]] <= t:
        r += 1
    return r


@nb.njit(cache=True, inline="always", error_model="numpy")
def _at(rows, ia, ib, wa, wb, s, k, t):
    """``V(t)`` inside interval ``k``."""
    va = _val(rows, ia, ib, wa, wb, k)
    if t <= s[k]:
        return va
    vb = _val(rows, ia, ib, wa, wb, k + 1)
    return va + (vb - va) * ((t - s[k]) / (s[k + 1] - s[k]))


@nb.njit(cache=True, inline="always", error_model="numpy")
def _levels(r_lvl, con, coff, log_domain):
    """The ON and OFF levels for reference ``r_lvl``, in the signal's domain."""
    if log_domain:
        return r_lvl + con, r_lvl - coff
    return math.exp(r_lvl + con), math.exp(r_lvl - coff)


# ----------------------------------------------------------------------------- one cycle


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _fire(pix, act, order, s, idx, rows, ia, ib, wa, wb, log_domain, mode, d1, d2, pieces, run_key,
          run_off, run_tab, inv_off, inv_lvl, inv_tab, c_on, c_off, ref, ready, pending,
          pending_z, resume, done, next_fire, alive, nz_off, nz_q, nz_t, nz_pol, seed, cycle, sigma,
          refr_us, lat_us, jit_us, period_us, t_stop, final, held, sliced, offsets, slot_t,
          slot_p,
          counts, overflow, n_lost, t_lo, nbins, block):
    """Events of one cycle for the listed pixels ``pix`` (module docstring).

    ``act`` lists the listed pixels to fire (only their outputs are written), ``order``
    its blocks of ``block`` in the order threads take them.
    Per listed pixel ``i``: slots ``offsets[i] .. offsets[i + 1]`` receive the events
    (time bin relative to ``t_lo`` and polarity); ``counts[i]`` is the number written,
    ``overflow[i]`` is set when the slots ran out (the caller runs the cycle again),
    ``n_lost[i]`` counts noise arrivals lost in dead time. State arrays are indexed by
    the global pixel ``pix[i]``; noise arrivals by ``i`` (``nz_q[i]``: the first not yet
    met).

    A cycle is fired whole (``final``, ``t_stop = period_us``) or in slices: a slice fires
    the events whose firing time lies before ``t_stop`` and leaves each pixel where its
    search stood (``resume``); the last slice is ``final`` (it moves the state to the next
    cycle). With ``held`` a pixel fires at most one event per call and stays pending, its
    dead time counted from the request until the caller moves ``ready`` to the end of the
    dead time after the readout's acknowledge. Without ``sliced`` (a cycle fired whole,
    never sliced) the slice state (``resume``, ``done``, ``next_fire``) is neither read nor
    written.
    """
    n = act.shape[0]
    pure = jit_us == 0.0 and lat_us == 0.0 and refr_us == 0.0
    draws = jit_us > 0.0 or sigma > 0.0
    nruns_max = 2 * pieces.shape[0] if mode == 0 else 1
    nblk = order.shape[0]
    for bi in nb.prange(nblk):
        local = np.empty((nruns_max, 3), dtype=np.int64)
        b0 = order[bi] * block
        for ii in range(b0, min(n, b0 + block)):
            i = act[ii]
            p = pix[i]
            counts[i] = 0
            n_lost[i] = 0
            if alive[p] == 0 or (not final and next_fire[p] >= t_stop):
                continue
            ra = ia[i]
            rb = ib[i]
            xa = wa[i]
            xb = wb[i]
            con = c_on[p]
            coff = c_off[p]
            e_on = 1.0 if log_domain else math.exp(con)
            e_off = 1.0 if log_domain else math.exp(-coff)
            runs, nr = _runs_of(i, mode, xa, xb, d1, d2, pieces, run_key, run_off, run_tab,
                                local)
            g0 = run_off[run_key[i]] if mode == 1 else 0
            cnt0 = done[p] if sliced else 0
            o = offsets[i] - cnt0
            cap = offsets[i + 1] - o
            cnt = cnt0
            lost = 0
            free = ready[p]
            pend = pending[p] != 0
            pz = pending_z[p]
            r_lvl = ref[p]
            q = nz_q[i]
            qe = nz_off[i + 1]
            t = max(free, resume[p], 0.0) if sliced else max(free, 0.0)
            nxt = _NEVER
            if t >= t_stop:
                # blind for the whole slice
                while q < qe and nz_t[q] < t_stop:
                    q += 1
                    lost += 1
                nz_q[i] = q
                n_lost[i] = lost
                if final:
                    ready[p] = free - period_us
                    if sliced:
                        resume[p] = _NEVER
                        done[p] = 0
                        next_fire[p] = _NEVER
                continue
            r = _run_at(runs, nr, 0, t, s)
            k = _locate(s, idx, runs[r, 0], runs[r, 1] - 1, t)
            v = _at(rows, ra, rb, xa, xb, s, k, t)
            if pend:
                r_lvl = (v if log_domain else math.log(v)) + sigma * pz
                pend = False
            thi, tlo = _levels(r_lvl, con, coff, log_domain)
            zc = -1
            zj = 0.0
            zr = 0.0
            zs = hash_stream(seed, p, cycle)
            while True:
                if draws and zc != cnt:
                    # the next event's draws, before the search that does not need them:
                    # their arithmetic overlaps its loads
                    zj, zr = hash_normal2_at(zs, cnt)
                    zc = cnt
                chi = thi - _EPS if log_domain else thi * (1.0 - _EPS)
                clo = tlo + _EPS if log_domain else tlo * (1.0 + _EPS)
                while q < qe and nz_t[q] < t:
                    q += 1
                    lost += 1
                tn = nz_t[q] if q < qe else _INF
                b = runs[r, 1]
                d = runs[r, 2]
                found = False
                up = True
                tc = 0.0
                kc = k
                vc = v
                if v >= chi:
                    found = True
                    tc = t
                elif v <= clo:
                    found = True
                    up = False
                    tc = t
                elif d != 0:
                    up = d > 0
                    lvl = thi if up else tlo
                    if mode == 1:
                        j = _first_indexed(rows, ra, rb, xa, xb, k + 1, b, chi if up else clo,
                                           up, g0 + r, inv_off, inv_lvl, inv_tab)
                    else:
                        j = _first(rows, ra, rb, xa, xb, k + 1, b, chi if up else clo, up,
                                   _val(rows, ra, rb, xa, xb, k))
                    if j <= b:
                        found = True
                        if j - 1 == k:
                            t0 = t
                            v0 = v
                        else:
                            t0 = s[j - 1]
                            v0 = _val(rows, ra, rb, xa, xb, j - 1)
                        v1 = _val(rows, ra, rb, xa, xb, j)
                        dv = v1 - v0
                        f = (lvl - v0) / dv if dv != 0.0 else 1.0
                        f = min(max(f, 0.0), 1.0)
                        tc = t0 + f * (s[j] - t0)
                        vc = v0 + f * dv
                        kc = j - 1
                else:
                    t0 = t
                    v0 = v
                    for j in range(k + 1, b + 1):
                        v1 = _val(rows, ra, rb, xa, xb, j)
                        if v1 >= chi or v1 <= clo:
                            found = True
                            up = v1 >= chi
                            lvl = thi if up else tlo
                            dv = v1 - v0
                            f = (lvl - v0) / dv if dv != 0.0 else 1.0
                            f = min(max(f, 0.0), 1.0)
                            tc = t0 + f * (s[j] - t0)
                            vc = v0 + f * dv
                            kc = j - 1
                            break
                        t0 = s[j]
                        v0 = v1
                signal = found and tc <= tn
                if not signal and not (tn <= s[b]):
                    if r == nr - 1:
                        nxt = _INF  # no event before the cycle's end
                        break
                    r += 1
                    k = runs[r, 0]
                    t = s[k]
                    v = _val(rows, ra, rb, xa, xb, k)
                    continue
                if signal:
                    tf = tc + jit_us * zj if jit_us > 0.0 else tc
                    if tf < free:
                        tf = free
                    pol = 1 if up else -1
                else:
                    tf = tn
                    pol = nz_pol[q]
                if tf >= t_stop and not final:
                    nxt = tf  # a later slice's event: found again from t then
                    break
                if cnt >= cap:
                    overflow[i] = 1
                    break
                if not signal:
                    q += 1
                tb = np.int64(math.floor(tf + lat_us)) - t_lo
                slot_t[o + cnt] = min(max(tb, 0), nbins - 1)
                slot_p[o + cnt] = pol
                cnt += 1
                if pure:
                    if signal:
                        t = tc
                        k = kc
                        v = vc
                        step = (con if up else -coff) + sigma * zr
                        r_lvl += step
                        if log_domain:
                            thi += step
                            tlo += step
                        else:
                            # the levels move by the same factor: one exp per event, none
                            # without reset noise
                            if sigma > 0.0:
                                f = math.exp(step)
                            else:
                                f = e_on if up else e_off
                            thi *= f
                            tlo *= f
                    else:
                        t = tn
                        r = _run_at(runs, nr, r, t, s)
                        k = _locate(s, idx, runs[r, 0], runs[r, 1] - 1, t)
                        v = _at(rows, ra, rb, xa, xb, s, k, t)
                        r_lvl = (v if log_domain else math.log(v)) + sigma * zr
                        thi, tlo = _levels(r_lvl, con, coff, log_domain)
                    free = t
                    continue
                t_end = tf + lat_us + refr_us
                free = t_end
                if held or t_end >= period_us:
                    # the reference is taken when the dead time ends, in a later call
                    pend = True
                    pz = zr
                    t = t_end
                    nxt = t_end  # nothing fires before
                    break
                t = t_end if t_end > 0.0 else 0.0
                r = _run_at(runs, nr, r, t, s)
                k = _locate(s, idx, runs[r, 0], runs[r, 1] - 1, t)
                v = _at(rows, ra, rb, xa, xb, s, k, t)
                r_lvl = (v if log_domain else math.log(v)) + sigma * zr
                thi, tlo = _levels(r_lvl, con, coff, log_domain)
            if final:
                while q < qe:
                    if nz_t[q] < free:
                        lost += 1
                    q += 1
            counts[i] = cnt - cnt0
            n_lost[i] = lost
            nz_q[i] = q
            ref[p] = r_lvl
            ready[p] = free - period_us if final else free
            pending[p] = 1 if pend else 0
            pending_z[p] = pz
            if sliced:
                resume[p] = _NEVER if final else t
                done[p] = 0 if final else cnt
                next_fire[p] = _NEVER if final else nxt


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _bounds(pix, order, s, rows, ia, ib, wa, wb, log_domain, mode, d1, d2, pieces, run_key,
            run_off, run_tab, c_on, c_off, alive, nz_off, sigma, c_scale, out, block):
    """Upper bound on each listed pixel's events in the cycle: over every monotone run,
    its log variation over the smallest effective step (threshold less six sigma of
    reset noise, times ``c_scale``) plus one; the point-by-point variation of the runs
    scanned whole; plus the noise arrivals and two."""
    n = pix.shape[0]
    nruns_max = 2 * pieces.shape[0] if mode == 0 else 1
    for bi in nb.prange(order.shape[0]):
        local = np.empty((nruns_max, 3), dtype=np.int64)
        b0 = order[bi] * block
        for i in range(b0, min(n, b0 + block)):
            p = pix[i]
            if alive[p] == 0:
                out[i] = 0
                continue
            runs, nr = _runs_of(i, mode, wa[i], wb[i], d1, d2, pieces, run_key, run_off,
                                run_tab, local)
            cmin = min(c_on[p], c_off[p])
            cmin = max(cmin - 6.0 * sigma, 0.25 * cmin) * c_scale
            total = 0.0
            for r in range(nr):
                a = runs[r, 0]
                b = runs[r, 1]
                if runs[r, 2] != 0:
                    va = _val(rows, ia[i], ib[i], wa[i], wb[i], a)
                    vb = _val(rows, ia[i], ib[i], wa[i], wb[i], b)
                    dv = abs(vb - va) if log_domain else abs(math.log(vb) - math.log(va))
                else:
                    dv = 0.0
                    prev = _val(rows, ia[i], ib[i], wa[i], wb[i], a)
                    for j in range(a + 1, b + 1):
                        cur = _val(rows, ia[i], ib[i], wa[i], wb[i], j)
                        dv += abs(cur - prev) if log_domain else abs(math.log(cur / prev))
                        prev = cur
                total += dv / cmin + 1.0
            out[i] = np.int64(total) + 2 + (nz_off[i + 1] - nz_off[i])


_BLOCK = 64


class CycleFiring:
    """One cycle of the listed pixels ``pix``, prepared once and fired whole or in slices.

    ``s`` is the cycle's time grid (µs from its start) and ``rows`` the signal tabulated on
    it; listed pixel ``i`` reads ``wa[i] rows[ia[i]] + wb[i] rows[ib[i]]``. The exact
    irradiance gives ``pieces`` (:func:`cycle_pieces`); tabulated rows give each pixel's
    ``run_key`` into the monotone runs ``run_off, run_tab``. Time bins of the slots count
    from ``t_lo``, ``nbins`` of them.
    """

    def __init__(self, pix: np.ndarray, s: np.ndarray, rows: np.ndarray, ia: np.ndarray,
                 ib: np.ndarray, wa: np.ndarray, wb: np.ndarray, *, log_domain: bool,
                 pieces: np.ndarray | None, run_key: np.ndarray | None,
                 run_off: np.ndarray | None, run_tab: np.ndarray | None, period_us: float,
                 t_lo: int, nbins: int) -> None:
        n = int(pix.size)
        self.n = n
        self.pix, self.s, self.rows, self.ia, self.ib, self.wa, self.wb = (
            pix, s, rows, ia, ib, wa, wb)
        self.log_domain = bool(log_domain)
        self.mode = 0 if pieces is not None else 1
        self.d1 = np.diff(rows[0]) if self.mode == 0 else np.zeros(1)
        self.d2 = np.diff(rows[1]) if self.mode == 0 else np.zeros(1)
        self.pieces = pieces if pieces is not None else np.zeros((1, 2), dtype=np.int64)
        self.run_key = run_key if run_key is not None else np.zeros(1, dtype=np.int64)
        self.run_off = run_off if run_off is not None else np.zeros(2, dtype=np.int64)
        self.run_tab = run_tab if run_tab is not None else np.zeros((1, 3), dtype=np.int64)
        if self.mode == 1:
            assert run_key is not None and run_off is not None and run_tab is not None
            self.index = level_index(rows, ia, ib, run_key, run_off, run_tab)
        else:
            self.index = (np.zeros(2, dtype=np.int64), np.zeros((1, 2)),
                          np.zeros((1, 2), dtype=np.int32))
        self.order = block_order(n, _BLOCK)
        # the order pixels are fired in: those reading one pair of rows one after another,
        # so the pair's rows and ladder stay in the core's cache (the events are the same
        # in any order)
        self.all_pixels = self._by_pair(np.arange(n, dtype=np.int64))
        self.idx = (np.searchsorted(s, np.arange(math.ceil(float(s[-1])) + 1,
                                                 dtype=np.float64), side="right")
                    - 1).astype(np.int64)
        self.period_us = float(period_us)
        self.t_lo = int(t_lo)
        self.nbins = int(nbins)
        self._held_buffers: tuple[np.ndarray, ...] | None = None
        self._sliced = False  # a slice was fired: the state's slice fields are in use

    def _by_pair(self, act: np.ndarray) -> np.ndarray:
        """The listed pixels ``act`` grouped by the pair of rows they read (stable)."""
        if self.mode == 0 or act.size < 2:
            return act.astype(np.int64)
        keys = self.run_key[act]
        if self.run_off.size - 1 <= 1 << 16:
            keys = keys.astype(np.uint16)  # a radix sort, 10x a merge sort's speed
        return act[np.argsort(keys, kind="stable")].astype(np.int64)

    def fire(self, *, c_on: np.ndarray, c_off: np.ndarray, state: PixelState,
             alive: np.ndarray, noise_off: np.ndarray, noise_q: np.ndarray,
             noise_t: np.ndarray, noise_pol: np.ndarray, seed: int, cycle: int,
             reset_noise_sigma: float, refractory_us: float, latency_us: float,
             jitter_sigma_us: float, t_stop: float | None = None, held: bool = False
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
        """Fire the events whose firing time lies before ``t_stop`` (µs from the cycle's
        start; default the cycle's end, which also moves ``state`` to the next cycle);
        ``state`` is advanced in place, ``noise_q`` (per listed pixel, starting at
        ``noise_off[:-1]``) too. With ``held`` each pixel fires at most one event and stays
        pending until the caller sets its ``ready`` (:class:`_fire`'s docstring), and only
        the pixels whose next event may fire before ``t_stop`` are run (the others'
        ``counts`` are 0).

        Returns ``(counts, slot_t, slot_p, offsets, lost)``: listed pixel ``i`` fired
        ``counts[i]`` events, in slots ``offsets[i] ..`` (time bins from ``t_lo``,
        polarity); ``lost`` noise arrivals fell in dead time.
        """
        n = self.n
        final = t_stop is None or t_stop >= self.period_us
        stop = self.period_us if final else float(t_stop)  # type: ignore[arg-type]
        sliced = held or self._sliced or not final
        self._sliced = sliced
        inputs = (c_on, c_off, state, alive, noise_off, noise_q, noise_t, noise_pol, seed,
                  cycle, reset_noise_sigma, refractory_us, latency_us, jitter_sigma_us)
        if held:
            if self._held_buffers is None:  # one slot per pixel, kept from slice to slice
                self._held_buffers = (np.arange(n + 1, dtype=np.int64),
                                      np.empty(n, dtype=np.int32), np.empty(n, dtype=np.int8),
                                      np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int8),
                                      np.zeros(n, dtype=np.int64))
            offsets, slot_t, slot_p, counts, overflow, lost = self._held_buffers
            counts[:] = 0
            lost[:] = 0
            act = (self.all_pixels if final else
                   self._by_pair(np.flatnonzero(state.next_fire[self.pix] < stop)))
            self._kernel(act, block_order(act.size, _BLOCK), stop, final, True, True,
                         self._held_buffers, inputs)
            if overflow.any():
                raise RuntimeError("pixel model: a held pixel fired more than one event")
            return counts, slot_t, slot_p, offsets, int(lost.sum())
        bound = np.empty(n, dtype=np.int64)
        c_scale = 1.0
        saved = state.copy(slices=sliced)
        saved_q = noise_q.copy()
        act = self.all_pixels
        for _attempt in range(8):
            _bounds(self.pix, self.order, self.s, self.rows, self.ia, self.ib, self.wa, self.wb,
                    self.log_domain, self.mode, self.d1, self.d2, self.pieces, self.run_key,
                    self.run_off, self.run_tab, c_on, c_off, alive, noise_off,
                    float(reset_noise_sigma), c_scale, bound, _BLOCK)
            offsets = np.zeros(n + 1, dtype=np.int64)
            np.cumsum(bound, out=offsets[1:])
            total = int(offsets[-1])
            # a slot holds a time bin as int32 (one compiled kernel for any cycle length)
            buffers = (offsets, np.empty(total, dtype=np.int32), np.empty(total, dtype=np.int8),
                       np.empty(n, dtype=np.int64), np.zeros(n, dtype=np.int8),
                       np.empty(n, dtype=np.int64))
            self._kernel(act, self.order, stop, final, False, sliced, buffers, inputs)
            _, slot_t, slot_p, counts, overflow, lost = buffers
            if not overflow.any():
                return counts, slot_t, slot_p, offsets, int(lost.sum())
            state.restore(saved, slices=sliced)
            noise_q[:] = saved_q
            c_scale *= 0.5
        raise RuntimeError("pixel model: the event bound was exceeded repeatedly")

    def _kernel(self, act: np.ndarray, order: np.ndarray, stop: float, final: bool,
                held: bool, sliced: bool, buffers: tuple[np.ndarray, ...],
                inputs: tuple[Any, ...]) -> None:
        """One call of :func:`_fire` for the listed pixels ``act`` into ``buffers``
        (offsets, slot times, slot polarities, counts, overflow, lost)."""
        (c_on, c_off, state, alive, noise_off, noise_q, noise_t, noise_pol, seed, cycle,
         sigma, refractory_us, latency_us, jitter_sigma_us) = inputs
        offsets, slot_t, slot_p, counts, overflow, lost = buffers
        inv_off, inv_lvl, inv_tab = self.index
        _fire(self.pix, act, order, self.s, self.idx, self.rows, self.ia, self.ib, self.wa,
              self.wb, self.log_domain, self.mode, self.d1, self.d2, self.pieces, self.run_key,
              self.run_off, self.run_tab, inv_off, inv_lvl, inv_tab, c_on, c_off, state.ref,
              state.ready, state.pending, state.pending_z, state.resume, state.done,
              state.next_fire, alive, noise_off, noise_q, noise_t, noise_pol, np.uint64(seed),
              np.int64(cycle), float(sigma), float(refractory_us), float(latency_us),
              float(jitter_sigma_us), self.period_us, stop, final, held, sliced, offsets,
              slot_t, slot_p, counts, overflow, lost, np.int64(self.t_lo),
              np.int64(self.nbins), _BLOCK)


def fire_cycle(
    pix: np.ndarray,
    s: np.ndarray,
    rows: np.ndarray,
    ia: np.ndarray,
    ib: np.ndarray,
    wa: np.ndarray,
    wb: np.ndarray,
    *,
    log_domain: bool,
    pieces: np.ndarray | None,
    run_key: np.ndarray | None,
    run_off: np.ndarray | None,
    run_tab: np.ndarray | None,
    c_on: np.ndarray,
    c_off: np.ndarray,
    state: PixelState,
    alive: np.ndarray,
    noise_off: np.ndarray,
    noise_t: np.ndarray,
    noise_pol: np.ndarray,
    seed: int,
    cycle: int,
    reset_noise_sigma: float,
    refractory_us: float,
    latency_us: float,
    jitter_sigma_us: float,
    period_us: float,
    t_lo: int,
    nbins: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """One whole cycle of the listed pixels ``pix`` (:class:`CycleFiring`); ``state`` is
    advanced in place.

    Returns ``(counts, slot_t, slot_p, offsets, lost)``: listed pixel ``i`` fired
    ``counts[i]`` events, in slots ``offsets[i] ..`` (time bins from ``t_lo``, polarity);
    ``lost`` noise arrivals fell in dead time.
    """
    cyc = CycleFiring(pix, s, rows, ia, ib, wa, wb, log_domain=log_domain, pieces=pieces,
                      run_key=run_key, run_off=run_off, run_tab=run_tab, period_us=period_us,
                      t_lo=t_lo, nbins=nbins)
    return cyc.fire(
        c_on=c_on, c_off=c_off, state=state, alive=alive, noise_off=noise_off,
        noise_q=noise_off[:-1].copy(), noise_t=noise_t, noise_pol=noise_pol, seed=seed,
        cycle=cycle, reset_noise_sigma=reset_noise_sigma, refractory_us=refractory_us,
        latency_us=latency_us, jitter_sigma_us=jitter_sigma_us)


# ----------------------------------------------------------------------------- output


_FINE_BITS = 8  # a coarse time bin holds 2**_FINE_BITS µs bins


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _sort_keys(offsets, counts, slot_t, slot_p, first_bin, nbins, keys, start):
    """The first half of a counting sort of the slots by time bin: each listed pixel's
    events go to their coarse bin as packed keys (listed pixel, fine bin, polarity), in
    listed-pixel order, then each pixel's own order; ``start[f]`` receives the first
    output place of µs bin ``f`` (``start[-1]`` the number of events)."""
    npix = counts.shape[0]
    fb = _FINE_BITS
    fmask = (1 << fb) - 1
    ncoarse = (nbins + fmask) >> fb
    nblk = 16
    bsize = (npix + nblk - 1) // nblk
    hist = np.zeros((nblk, ncoarse << fb), dtype=np.int64)
    for b in nb.prange(nblk):
        for i in range(b * bsize, min(npix, (b + 1) * bsize)):
            o = offsets[i]
            for k in range(counts[i]):
                hist[b, slot_t[o + k] - first_bin] += 1
    # start of every µs bin in the output, and of every block's share of a coarse bin
    cpos = np.empty((nblk, ncoarse), dtype=np.int64)
    acc = np.int64(0)
    for c in range(ncoarse):
        for b in range(nblk):
            cpos[b, c] = acc
            for f in range(c << fb, (c + 1) << fb):
                acc += hist[b, f]
    acc = np.int64(0)
    for f in range(ncoarse << fb):
        start[f] = acc
        for b in range(nblk):
            acc += hist[b, f]
    start[ncoarse << fb] = acc
    for b in nb.prange(nblk):
        for i in range(b * bsize, min(npix, (b + 1) * bsize)):
            o = offsets[i]
            head = np.int64(i) << (fb + 1)
            for k in range(counts[i]):
                tb = np.int64(slot_t[o + k]) - first_bin
                cb = tb >> fb
                d = cpos[b, cb]
                cpos[b, cb] = d + 1
                keys[d] = head | ((tb & fmask) << 1) | (1 if slot_p[o + k] > 0 else 0)


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _place_keys(keys, start, xs, ys, t_first, out):
    """The second half: each coarse bin's keys to their places in ``out``, in the order
    they come (a stable sort)."""
    fb = _FINE_BITS
    fmask = (1 << fb) - 1
    ncoarse = (start.shape[0] - 1) >> fb
    for c in nb.prange(ncoarse):
        pos = start[c << fb:(c + 1) << fb].copy()
        tbase = t_first + (np.int64(c) << fb)
        for j in range(start[c << fb], start[(c + 1) << fb]):
            key = np.int64(keys[j])
            fine = (key >> 1) & fmask
            d = pos[fine]
            pos[fine] = d + 1
            li = key >> (fb + 1)
            out[d].x = xs[li]
            out[d].y = ys[li]
            out[d].p = 1 if (key & 1) else -1
            out[d].t = tbase + fine


@nb.njit(cache=True)
def _bin_range(offsets, counts, slot_t):
    lo = np.int64(2**62)
    hi = np.int64(-2**62)
    for i in range(counts.shape[0]):
        o = offsets[i]
        for k in range(counts[i]):
            b = np.int64(slot_t[o + k])
            lo = min(lo, b)
            hi = max(hi, b)
    return lo, hi


@dataclass(frozen=True)
class SortKeys:
    """A cycle's events as sort keys, between :func:`sort_keys` and :func:`place_events`:
    ``keys`` (listed pixel, fine time bin, polarity) grouped by coarse time bin, ``start``
    the first output place of every µs bin, ``t_first_us`` the time of bin 0."""

    keys: np.ndarray
    start: np.ndarray
    t_first_us: int

    @property
    def n(self) -> int:
        return int(self.start[-1])


def sort_keys(offsets: np.ndarray, counts: np.ndarray, slot_t: np.ndarray,
              slot_p: np.ndarray, *, t_first_us: int, nbins: int,
              first_bin: int | None = None) -> SortKeys:
    """The slots' events as :class:`SortKeys`, the first half of :func:`gather_sorted`.

    Its result no longer needs the slots: a caller that lets go of them before
    :func:`place_events` gives their memory back before the events array is first
    written (a cycle's slots are hundreds of MB on a large sensor, and fresh memory is
    written fastest where the kernel has just taken some back)."""
    n = int(counts.sum())
    if first_bin is None:
        first_bin = 0
    elif n:
        lo, hi = _bin_range(offsets, counts, slot_t)
        end = max(first_bin + nbins, hi + 1)
        first_bin = min(first_bin, lo)
        nbins = end - first_bin
    # keys hold (listed pixel, fine bin, polarity): 32 bits while they fit
    key_dtype = np.uint32 if counts.size < 1 << (31 - _FINE_BITS) else np.int64
    keys = np.empty(n, dtype=key_dtype)
    fmask = (1 << _FINE_BITS) - 1
    start = np.empty((((nbins + fmask) >> _FINE_BITS) << _FINE_BITS) + 1, dtype=np.int64)
    _sort_keys(offsets, counts, slot_t, slot_p, np.int64(first_bin), np.int64(nbins), keys,
               start)
    return SortKeys(keys, start, int(t_first_us + first_bin))


def place_events(sk: SortKeys, pix: np.ndarray, *, width: int) -> np.ndarray:
    """The events (``EVENT_DTYPE``) of :func:`sort_keys`'s result, sorted by time;
    ``pix`` are the listed pixels' flat indices on a sensor ``width`` wide."""
    out = np.empty(sk.n, dtype=EVENT_DTYPE)
    ys, xs = np.divmod(pix, width)
    _place_keys(sk.keys, sk.start, xs.astype(np.uint16), ys.astype(np.uint16),
                np.int64(sk.t_first_us), out)
    return out


def gather_sorted(offsets: np.ndarray, counts: np.ndarray, slot_t: np.ndarray,
                  slot_p: np.ndarray, pix: np.ndarray, *, width: int, t_first_us: int,
                  nbins: int, first_bin: int | None = None) -> np.ndarray:
    """Events (``EVENT_DTYPE``) from the slots, sorted by time by a counting sort over the
    ``nbins`` µs bins (bin ``b`` is time ``t_first_us + b``). With ``first_bin`` only the
    bins from it on, ``nbins`` of them, where the events are expected, are counted (widened
    to every event's bin). Stable: among equal times, listed-pixel order, then each
    pixel's own order. :func:`sort_keys`, then :func:`place_events`."""
    return place_events(sort_keys(offsets, counts, slot_t, slot_p, t_first_us=t_first_us,
                                  nbins=nbins, first_bin=first_bin), pix, width=width)
