"""An independent fine-step integration of the pixel model (docs/sensor.md), for tests.

Written apart from the engines: the photoreceptor is stepped at ``h_us`` by the exact
variation-of-constants integral (light time in closed form, the input integral by
Gauss-Legendre quadrature), and the comparator scans the fine grid point by point.
It shares with the engines only the model's definition: the per-event random draws
(``hash_normal2`` at ``(seed, pixel, cycle, event number)``) and the arrivals of the
background events, which the simulator draws in a documented order
(:func:`simulator_draws` repeats it).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from asynhdr.rig import Rig
from asynhdr.sensor._rng import hash_normal2, seed_from
from asynhdr.sensor.noise import draw_defects, noise_arrivals
from asynhdr.sensor.params import SensorParams
from asynhdr.simulate import draw_thresholds


def simulator_draws(radiance: np.ndarray, rig: Rig, sensor: SensorParams, *, n_cycles: int,
                    seed: int, sensor_seed: int):
    """The simulator's random inputs, drawn in its order: thresholds and defects from
    ``sensor_seed``; the hash seed, then each cycle's background arrivals, from ``seed``."""
    height, width = radiance.shape
    npix = width * height
    gen = np.random.default_rng(seed)
    sgen = np.random.default_rng(sensor_seed)
    c_on, c_off = draw_thresholds(sensor, width=width, height=height, rng=sgen)
    defects = draw_defects(sensor, n_pixels=npix, rng=sgen)
    hseed = seed_from(gen)
    w1, w2 = rig.waveforms()
    lum = radiance.ravel().astype(np.float64)
    arrivals = []
    for _ in range(n_cycles):
        if sensor.has_noise_events:
            def irr(pix, t):
                u = t / rig.period_us
                return rig.k_lens * (w1(u) * lum[pix] + w2(u) * rig.l_const)
            arrivals.append(noise_arrivals(sensor, irradiance_at=irr, n_pixels=npix,
                                           duration_us=float(rig.period_us), defects=defects,
                                           rng=gen))
        else:
            arrivals.append(None)
    alive = np.ones(npix, np.int8)
    alive[defects.dead] = 0
    return c_on.ravel(), c_off.ravel(), alive, hseed, arrivals


_GL_NODES = np.array([0.5 - math.sqrt(0.15), 0.5, 0.5 + math.sqrt(0.15)])
_GL_WEIGHTS = np.array([5.0 / 18.0, 8.0 / 18.0, 5.0 / 18.0])


@nb.njit(cache=True)
def _light_time(r0, r1, rmin, s):
    """int_0^s max(r0 + r1 u, rmin) du, the rate linear in u and floored at rmin."""
    if r1 == 0.0:
        return max(r0, rmin) * s
    u = (rmin - r0) / r1  # where the line meets the floor
    lin = r0 * s + 0.5 * r1 * s * s
    if r1 > 0.0:
        if u <= 0.0:
            return lin
        if u >= s:
            return rmin * s
        return rmin * u + (r0 * s + 0.5 * r1 * s * s) - (r0 * u + 0.5 * r1 * u * u)
    if u >= s:
        return lin
    if u <= 0.0:
        return rmin * s
    return (r0 * u + 0.5 * r1 * u * u) + rmin * (s - u)


@nb.njit(cache=True)
def _y_row(irr, h, y0, lowpass, tau_num, dark, tau_max, out):
    """Photoreceptor output at the fine grid, irradiance linear between points.

    Per step, the exact solution ``y_b = y_a e^{-Lam(h)} + int_0^h e^{-(Lam(h) - Lam(s))}
    rate(s) x(s) ds`` with ``rate = 1 / tau(I(s))`` and ``Lam`` its integral (closed form),
    the integral by three-point Gauss-Legendre quadrature.
    """
    n = irr.shape[0]
    if not lowpass:
        for i in range(n):
            out[i] = math.log(irr[i])
        return
    rmin = 1.0 / tau_max
    y = y0
    out[0] = y
    for i in range(1, n):
        ia = irr[i - 1]
        ib = irr[i]
        r0 = (ia + dark) / tau_num
        r1 = (ib - ia) / (h * tau_num)
        lam_h = _light_time(r0, r1, rmin, h)
        acc = 0.0
        for j in range(3):
            sj = _GL_NODES[j] * h
            ij = ia + (ib - ia) * sj / h
            rate = max(r0 + r1 * sj, rmin)
            acc += _GL_WEIGHTS[j] * h * math.exp(-(lam_h - _light_time(r0, r1, rmin, sj))) \
                * rate * math.log(ij)
        y = y * math.exp(-lam_h) + acc
        out[i] = y


@nb.njit(cache=True)
def _y_at(y, h, t):
    i = int(t / h)
    if i >= y.shape[0] - 1:
        return y[y.shape[0] - 1]
    f = (t - i * h) / h
    return y[i] + f * (y[i + 1] - y[i])


@nb.njit(cache=True)
def reference_pixel(irr_cycles, h, lowpass, tau_num, dark, tau_max, con, coff, sigma, refr,
                    lat, jit, seed, p, nz_t, nz_pol, nz_cycle, period, out_t, out_p):
    """Events of one pixel over all cycles (``irr_cycles`` is ``(n_cycles, n_fine)``);
    returns the count written to ``out_t`` (absolute µs, float) and ``out_p``."""
    ncyc, nf = irr_cycles.shape
    pure = jit == 0.0 and lat == 0.0 and refr == 0.0
    y = np.empty(nf)
    y0 = math.log(irr_cycles[0, 0])
    ref = y0
    free = -1e300
    pend = False
    pz = 0.0
    ne = 0
    q = 0
    for c in range(ncyc):
        _y_row(irr_cycles[c], h, y0, lowpass, tau_num, dark, tau_max, y)
        y0 = y[nf - 1]
        t = max(free, 0.0)
        n = 0
        if t >= period:
            while q < nz_t.shape[0] and nz_cycle[q] == c:
                q += 1
            free -= period
            continue
        if pend:
            ref = _y_at(y, h, t) + sigma * pz
            pend = False
        while True:
            while q < nz_t.shape[0] and nz_cycle[q] == c and nz_t[q] < t:
                q += 1
            tn = nz_t[q] if (q < nz_t.shape[0] and nz_cycle[q] == c) else 1e300
            # the next crossing from t, point by point
            hi = ref + con
            lo = ref - coff
            v0 = _y_at(y, h, t)
            tc = -1.0
            up = True
            if v0 >= hi - 1e-12:
                tc = t
            elif v0 <= lo + 1e-12:
                tc = t
                up = False
            else:
                i = int(t / h) + 1
                ta = t
                va = v0
                while i < nf:
                    vb = y[i]
                    tb = i * h
                    if vb >= hi - 1e-12 or vb <= lo + 1e-12:
                        up = vb >= hi - 1e-12
                        lvl = hi if up else lo
                        f = (lvl - va) / (vb - va) if vb != va else 1.0
                        tc = ta + min(max(f, 0.0), 1.0) * (tb - ta)
                        break
                    ta = tb
                    va = vb
                    i += 1
            signal = tc >= 0.0 and tc <= tn
            if not signal and tn > period:
                break
            zj, zr = hash_normal2(seed, p, c, n)
            if signal:
                tf = tc + jit * zj
                if tf < free:
                    tf = free
                pol = 1 if up else -1
            else:
                tf = tn
                pol = nz_pol[q]
                q += 1
            out_t[ne] = c * period + tf + lat
            out_p[ne] = pol
            ne += 1
            n += 1
            if pure:
                if signal:
                    ref = (hi if up else lo) + sigma * zr
                    t = tc
                else:
                    t = tn
                    ref = _y_at(y, h, t) + sigma * zr
                free = t
                continue
            t_end = tf + lat + refr
            free = t_end
            if t_end >= period:
                pend = True
                pz = zr
                break
            t = max(t_end, 0.0)
            ref = _y_at(y, h, t) + sigma * zr
        while q < nz_t.shape[0] and nz_cycle[q] == c:
            q += 1
        free -= period
    return ne


def reference_events(radiance: np.ndarray, rig: Rig, sensor: SensorParams, *,
                     n_cycles: int, seed: int, sensor_seed: int, h_us: float = 0.5):
    """Per pixel: (times µs, polarities) of the reference model, floored like the
    simulator's timestamps."""
    c_on, c_off, alive, hseed, arrivals = simulator_draws(radiance, rig, sensor,
                                                          n_cycles=n_cycles, seed=seed,
                                                          sensor_seed=sensor_seed)
    w1, w2 = rig.waveforms()
    nf = round(rig.period_us / h_us) + 1
    u = np.arange(nf) * h_us / rig.period_us
    t1, t2 = w1(u), w2(u)
    lum = radiance.ravel().astype(np.float64)
    lowpass = sensor.cutoff_hz > 0
    tau_num = sensor.tau_ref_us * (sensor.cutoff_irradiance + sensor.dark_irradiance)
    out = []
    cap = 10_000
    for p in range(lum.size):
        if not alive[p]:
            out.append((np.zeros(0, np.int64), np.zeros(0, np.int8)))
            continue
        irr = rig.k_lens * (t1 * lum[p] + t2 * rig.l_const)
        irr_c = np.ascontiguousarray(np.broadcast_to(irr, (n_cycles, nf)))
        zt, zp, zc = [], [], []
        for c, a in enumerate(arrivals):
            if a is None:
                continue
            lo, hi = a.offsets[p], a.offsets[p + 1]
            zt.append(a.t_us[lo:hi])
            zp.append(a.polarity[lo:hi])
            zc.append(np.full(hi - lo, c))
        nz_t = np.concatenate(zt) if zt else np.zeros(0)
        nz_p = np.concatenate(zp).astype(np.int8) if zp else np.zeros(0, np.int8)
        nz_c = np.concatenate(zc).astype(np.int64) if zc else np.zeros(0, np.int64)
        ot = np.empty(cap)
        op = np.empty(cap, np.int8)
        n = reference_pixel(irr_c, h_us, lowpass, tau_num, sensor.dark_irradiance,
                            sensor.tau_max_us, c_on[p], c_off[p], sensor.reset_noise_sigma,
                            sensor.refractory_us, sensor.latency_us, sensor.jitter_sigma_us,
                            np.uint64(hseed), p, nz_t, nz_p, nz_c, float(rig.period_us), ot, op)
        out.append((np.floor(ot[:n]).astype(np.int64), op[:n].copy()))
    return out


def held_reference_events(radiance: np.ndarray, rig: Rig, sensor: SensorParams, *,
                          n_cycles: int, seed: int, sensor_seed: int):
    """Per pixel: (timestamps, polarities) of the pixel model without a photoreceptor and
    without background events behind a readout that holds a waiting pixel until it is read,
    simulated event by event in time order (one global queue; the next request of every
    pixel in a heap), written apart from the simulator's slices: the irradiance is
    ``L a(t) + b(t)``, linear between the waveforms' knots, and a crossing is solved on the
    interval where it happens. Timestamps are the reads, floored."""
    import heapq

    if sensor.cutoff_hz > 0 or sensor.has_noise_events or sensor.latency_us:
        raise ValueError("the held reference has no photoreceptor, background or latency")
    c_on, c_off, alive, hseed, _ = simulator_draws(radiance, rig, sensor, n_cycles=n_cycles,
                                                   seed=seed, sensor_seed=sensor_seed)
    w1, w2 = rig.waveforms()
    knots = w1.phase if np.array_equal(w1.phase, w2.phase) else np.union1d(w1.phase, w2.phase)
    period = float(rig.period_us)
    s = np.asarray(knots, dtype=np.float64) * period
    a = rig.k_lens * np.asarray(w1(knots), dtype=np.float64)
    b = rig.k_lens * rig.l_const * np.asarray(w2(knots), dtype=np.float64)
    lum = radiance.ravel().astype(np.float64)
    service = 1e6 / sensor.max_event_rate_hz
    refr, jit, sigma = sensor.refractory_us, sensor.jitter_sigma_us, sensor.reset_noise_sigma

    def v_at(p: int, t: float) -> float:
        k = min(max(int(np.searchsorted(s, t, side="right")) - 1, 0), s.size - 2)
        f = (t - s[k]) / (s[k + 1] - s[k])
        va, vb = lum[p] * a[k] + b[k], lum[p] * a[k + 1] + b[k + 1]
        return va + (vb - va) * min(max(f, 0.0), 1.0)

    def crossing(p: int, t: float, ref: float) -> tuple[float, int] | None:
        hi, lo = math.exp(ref + c_on[p]), math.exp(ref - c_off[p])
        v0 = v_at(p, t)
        if v0 >= hi * (1 - 1e-12):
            return t, 1
        if v0 <= lo * (1 + 1e-12):
            return t, -1
        k = int(np.searchsorted(s, t, side="right"))
        t0 = t
        for j in range(k, s.size):
            v1 = lum[p] * a[j] + b[j]
            if v1 >= hi * (1 - 1e-12) or v1 <= lo * (1 + 1e-12):
                up = v1 >= hi * (1 - 1e-12)
                lvl = hi if up else lo
                f = (lvl - v0) / (v1 - v0) if v1 != v0 else 1.0
                return t0 + min(max(f, 0.0), 1.0) * (s[j] - t0), (1 if up else -1)
            t0, v0 = s[j], v1
        return None

    npix = lum.size
    ref = [math.log(v_at(p, 0.0)) for p in range(npix)]
    free = [-1e300] * npix  # end of the dead time, µs from the cycle's start
    pend_z: list[float | None] = [None] * npix
    out_t: list[list[int]] = [[] for _ in range(npix)]
    out_p: list[list[int]] = [[] for _ in range(npix)]
    def schedule(heap: list[tuple[int, int, float, int]], p: int, t: float, c: int,
                 k: int) -> None:
        """Push pixel ``p``'s next request (its ``k``-th event of cycle ``c``) from ``t``."""
        z = pend_z[p]
        if z is not None:
            ref[p] = math.log(v_at(p, t)) + sigma * z
            pend_z[p] = None
        x = crossing(p, t, ref[p])
        if x is None:
            return
        zj, _ = hash_normal2(np.uint64(hseed), p, c, k)
        tf = max(x[0] + jit * zj, free[p])
        heapq.heappush(heap, (math.floor(tf), p, tf, x[1]))

    free_at = -1e300
    for c in range(n_cycles):
        n = [0] * npix
        heap: list[tuple[int, int, float, int]] = []
        for p in range(npix):
            if alive[p] and max(free[p], 0.0) < period:
                schedule(heap, p, max(free[p], 0.0), c, 0)
        while heap:
            tb, p, tf, pol = heapq.heappop(heap)
            read = max(float(c * period + tb), free_at)
            free_at = read + service
            out_t[p].append(math.floor(read))
            out_p[p].append(pol)
            _, zr = hash_normal2(np.uint64(hseed), p, c, n[p])
            n[p] += 1
            free[p] = max(tf, read - c * period) + refr
            pend_z[p] = zr
            if free[p] < period:
                schedule(heap, p, free[p], c, n[p])
        for p in range(npix):
            free[p] -= period
    return [(np.asarray(out_t[p], np.int64), np.asarray(out_p[p], np.int8))
            for p in range(npix)]
