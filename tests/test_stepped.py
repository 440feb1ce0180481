"""The time-stepped engine against the exact engine, closed forms and plain loops.

Expected values come from the exact engine (crossing times computed from the
piecewise-linear irradiance), from closed forms of the first-order low-pass and of a
log-linear ramp worked out here, or from a plain Python loop over a dense time grid.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

import asynhdr.sensor.stepped as stepped_mod
from asynhdr.events import EVENT_DTYPE
from asynhdr.rig import Rig, Waveform, cycle_waveform
from asynhdr.sensor.params import SensorParams
from asynhdr.sensor.stepped import (
    initial_state,
    simulate_cycle_stepped,
    simulate_stepped,
    step_times_us,
)
from asynhdr.simulate import simulate

IDEAL = SensorParams(name="ideal", threshold_sigma=0.0)


def per_pixel(ev: np.ndarray, x: int, y: int) -> np.ndarray:
    return ev[(ev["x"] == x) & (ev["y"] == y)]


def uniform(shape: tuple[int, int], c: float) -> tuple[np.ndarray, np.ndarray]:
    return np.full(shape, c), np.full(shape, c)


def log_ramp_rig(period_us: int = 100_000) -> Rig:
    """T1 exponential 0.001 -> 1 over the whole cycle, T2 = 0: ``log I`` rises at the
    constant rate ``ln(1000) / period_us``, whatever the radiance."""
    t1 = cycle_waveform("exponential", start=0.001, stop=1.0, ramp_fraction=1.0)
    t2 = Waveform.from_samples([0.0, 0.0])
    return Rig(period_us=period_us, t1=t1, t2=t2)


# ---------------------------------------------------------------- 1. exact engine


@pytest.mark.parametrize(("t1_shape", "t2_shape"), [("linear", "linear"),
                                                    ("exponential", "linear"),
                                                    ("exponential", "exponential")])
def test_ideal_pixel_agrees_with_exact_engine(t1_shape: str, t2_shape: str) -> None:
    rig = Rig(t1_shape=t1_shape, t2_shape=t2_shape)  # type: ignore[arg-type]
    height, width = 4, 16
    # 0.05 .. 2e4 lux against l_const = 10: OFF-only, falling-then-rising and ON pixels
    radiance = np.geomspace(0.05, 2e4, height * width).reshape(height, width)
    rng = np.random.default_rng(7)
    c_on = rng.uniform(0.1, 0.3, radiance.shape)
    c_off = rng.uniform(0.1, 0.3, radiance.shape)
    n_cycles = 3
    got = simulate_stepped(radiance, rig=rig, sensor=IDEAL, n_cycles=n_cycles, c_on=c_on,
                           c_off=c_off, seed=1, dt_us=5.0)
    want = simulate(radiance, rig=rig, sensor=IDEAL, n_cycles=n_cycles,
                    thresholds=(c_on, c_off)).events
    assert got.dtype == EVENT_DTYPE
    assert np.all(np.diff(got["t"]) >= 0)
    assert got.size == want.size
    off_then_on = 0
    for y in range(height):
        for x in range(width):
            a, b = per_pixel(got, x, y), per_pixel(want, x, y)
            assert a.size == b.size, (x, y, radiance[y, x])
            np.testing.assert_array_equal(a["p"], b["p"])
            assert np.max(np.abs(a["t"] - b["t"]), initial=0) <= 1, (x, y)
            ramp = a[a["t"] < rig.ramp_us]
            if ramp.size and ramp["p"][0] == -1 and np.any(ramp["p"] == 1):
                off_then_on += 1
    # the sweep covers the cases it claims to
    assert np.any(got["p"] == -1) and np.any(got["p"] == 1)
    if t1_shape == "exponential":
        assert off_then_on > 0


def test_timestamp_resolution_floors_times() -> None:
    rig = Rig()
    radiance = np.geomspace(1.0, 1e4, 8).reshape(2, 4)
    c_on, c_off = uniform(radiance.shape, 0.2)
    fine = simulate_stepped(radiance, rig=rig, sensor=IDEAL, n_cycles=1, c_on=c_on,
                            c_off=c_off, seed=0)
    coarse = simulate_stepped(radiance, rig=rig, sensor=IDEAL.with_(timestamp_resolution_us=10),
                              n_cycles=1, c_on=c_on, c_off=c_off, seed=0)
    np.testing.assert_array_equal(coarse["t"], fine["t"] // 10 * 10)


# ---------------------------------------------------------------- 2. low-pass


def test_lowpass_step_response_matches_first_order_closed_form() -> None:
    period = 20_000
    t_jump = 2_000.0
    # T1 jumps from 0.01 to 1 within 1 µs at t_jump and holds; T2 = 0
    t1 = Waveform(np.array([0.0, t_jump / period, (t_jump + 1.0) / period, 1.0]),
                  np.array([0.01, 0.01, 1.0, 1.0]))
    rig = Rig(period_us=period, t1=t1, t2=Waveform.from_samples([0.0, 0.0]))
    # tau(I) = tau_ref (1000 + 0.1) / (I + 0.1): 20 ms at I = 1, 2.2 ms at I = 10;
    # capped at 50 ms for I = 0.01. The dark irradiance (0.1) weighs in the ratio.
    tau_ref = 22.0
    sensor = IDEAL.with_(cutoff_hz=1e6 / (2 * math.pi * tau_ref), cutoff_irradiance=1000.0,
                         dark_irradiance=0.1, tau_max_us=50_000.0)
    levels = np.array([[1.0, 10.0, 0.01]])
    c = 1.0
    c_on, c_off = uniform(levels.shape, c)
    ev = simulate_stepped(levels, rig=rig, sensor=sensor, n_cycles=1, c_on=c_on, c_off=c_off,
                          seed=0, dt_us=5.0)
    assert np.all(ev["t"] >= t_jump)  # no event before the step of light
    jump_log = math.log(100.0)  # x1 - x0
    delays = []
    for x, lum in enumerate(levels[0]):
        tau = min(tau_ref * 1000.1 / (lum + 0.1), 50_000.0)
        want = -tau * math.log(1.0 - c / jump_log)
        first = per_pixel(ev, x, 0)
        assert first.size and first["p"][0] == 1
        got = float(first["t"][0]) - (t_jump + 0.5)
        assert got == pytest.approx(want, rel=0.01), (lum, got, want)
        delays.append(got)
    tau_ratio = (10.0 + 0.1) / (1.0 + 0.1)
    assert delays[0] / delays[1] == pytest.approx(tau_ratio, rel=0.01)


# ---------------------------------------------------------------- 3. refractory


def test_refractory_reference_taken_at_its_end() -> None:
    period = 100_000
    rig = log_ramp_rig(period)
    refr = 5_000.0
    sensor = IDEAL.with_(refractory_us=refr)
    c = np.array([[0.2, 0.15, 0.25, 0.3]])
    ev = simulate_stepped(np.full(c.shape, 50.0), rig=rig, sensor=sensor, n_cycles=1,
                          c_on=c, c_off=c.copy(), seed=0)
    rate = math.log(1000.0) / period  # d(log I)/dt, per µs
    for x in range(c.shape[1]):
        e = per_pixel(ev, x, 0)
        assert np.all(e["p"] == 1)
        assert np.all(np.diff(e["t"]) >= refr)
        climb = c[0, x] / rate  # µs for log I to rise by c
        # reference at the end of each refractory period: events every refr + climb
        n_end = 1 + math.floor((period - climb) / (refr + climb))
        want = climb + np.arange(n_end) * (refr + climb)
        assert e.size == n_end
        np.testing.assert_allclose(e["t"], np.floor(want), atol=1.0)
        # the other convention (reference stepped by c at each event) would fire every
        # max(refr, climb) µs: a different count
        n_at_event = 1 + math.floor((period - climb) / max(refr, climb))
        assert n_at_event != n_end


def test_refractory_holds_with_lowpass_and_noise() -> None:
    rig = Rig(period_us=20_000)
    radiance = np.geomspace(0.5, 1e5, 64).reshape(8, 8)
    sensor = IDEAL.with_(refractory_us=100.0, reset_noise_sigma=0.03,
                         cutoff_hz=1e6 / (2 * math.pi * 50.0))
    c_on, c_off = uniform(radiance.shape, 0.1)
    ev = simulate_stepped(radiance, rig=rig, sensor=sensor, n_cycles=2, c_on=c_on,
                          c_off=c_off, seed=3)
    assert ev.size > 1000
    order = np.lexsort((ev["t"], ev["y"].astype(np.int64) * 8 + ev["x"]))
    e = ev[order]
    same = (e["x"][1:] == e["x"][:-1]) & (e["y"][1:] == e["y"][:-1])
    assert np.min(np.diff(e["t"])[same]) >= 100


# ---------------------------------------------------------------- 4. reset noise


def test_reset_noise_reproducible_and_of_stated_size() -> None:
    rig = log_ramp_rig(100_000)
    shape = (8, 8)
    c_on, c_off = uniform(shape, 0.2)
    radiance = np.full(shape, 20.0)
    sigma = 0.02
    noisy = IDEAL.with_(reset_noise_sigma=sigma)

    def run(sensor: SensorParams, seed: int) -> np.ndarray:
        return simulate_stepped(radiance, rig=rig, sensor=sensor, n_cycles=1, c_on=c_on,
                                c_off=c_off, seed=seed)

    a = run(noisy, 11)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        a1 = run(noisy, 11)
    finally:
        numba.set_num_threads(threads)
    assert a.tobytes() == a1.tobytes()
    assert a.tobytes() == run(noisy, 11).tobytes()
    assert a.tobytes() != run(noisy, 12).tobytes()
    quiet = IDEAL.with_(reset_noise_sigma=0.0)
    q1 = run(quiet, 11)
    assert q1.tobytes() == run(quiet, 12).tobytes()
    # noiseless: every pixel steps exactly c per event
    rate = math.log(1000.0) / 100_000
    steps = []
    for y in range(shape[0]):
        for x in range(shape[1]):
            t = per_pixel(a, x, y)["t"].astype(np.float64)
            steps.append(np.diff(t) * rate)
            tq = per_pixel(q1, x, y)["t"].astype(np.float64)
            np.testing.assert_allclose(np.diff(tq) * rate, 0.2, atol=2 * rate)
    inc = np.concatenate(steps)
    # ref_k = ref_(k-1) + c + n_k and event k + 1 fires at ref_k + c: the log
    # irradiance between events k and k + 1 rises by c + n_k (mean c, deviation sigma)
    assert inc.size > 1500
    assert inc.mean() == pytest.approx(0.2, abs=0.003)
    assert inc.std() == pytest.approx(sigma, rel=0.1)


# ---------------------------------------------------------------- 5. moving scene


def test_moving_edge_fires_along_its_path() -> None:
    rig = Rig()  # 50 ms cycle, linear ramps over 45 ms
    height, width = 3, 40
    dark, bright = 1.0, 1000.0
    t_first = 5_000.0
    frame_dt = 1_000.0
    n_frames = width + 1
    frames = np.full((n_frames, height, width), dark)
    for i in range(n_frames):
        frames[i, :, :i] = bright  # the edge has passed columns x < i
    times = t_first + frame_dt * np.arange(n_frames)
    c_on, c_off = uniform((height, width), 0.2)
    ev = simulate_stepped(frames, rig=rig, sensor=IDEAL, n_cycles=1, c_on=c_on, c_off=c_off,
                          seed=0, frame_times_us=times)
    assert np.all(np.diff(ev["t"]) >= 0)
    first_on = np.empty(width)
    for x in range(width):
        on = ev[(ev["x"] == x) & (ev["y"] == 1) & (ev["p"] == 1)]
        first_on[x] = on["t"][0]
        # column x brightens between frames x and x + 1
        assert times[x] <= first_on[x] <= times[x + 1], x
    assert np.all(np.diff(first_on) > 0)


def test_constant_frames_equal_static_scene() -> None:
    rig = Rig(period_us=20_000)
    radiance = np.geomspace(0.3, 3e4, 24).reshape(4, 6)
    c_on, c_off = uniform(radiance.shape, 0.15)
    sensor = IDEAL.with_(cutoff_hz=500.0, refractory_us=50.0)
    static = simulate_stepped(radiance, rig=rig, sensor=sensor, n_cycles=2, c_on=c_on,
                              c_off=c_off, seed=0)
    frames = np.stack([radiance] * 3)
    moving = simulate_stepped(frames, rig=rig, sensor=sensor, n_cycles=2, c_on=c_on,
                              c_off=c_off, seed=0,
                              frame_times_us=np.array([0.0, 15_000.0, 30_000.0]))
    assert static.size > 100
    assert static.tobytes() == moving.tobytes()


# ---------------------------------------------------------------- 6. non-monotone


def dense_reference(lum: float, rig: Rig, c: float, *, tau_num: float = 0.0,
                    dark: float = 0.1, tau_max: float = 50_000.0, dt: float = 0.1
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Events of one pixel over one cycle by a plain loop on a dense grid (step ``dt``):
    ``y += (x - y) (1 - exp(-dt / tau))`` (or ``y = x``), then ``ref +/- c``; a level
    reached to within 1e-12 counts (a pixel back at its start level fires there)."""
    w1, w2 = rig.waveforms()
    t = np.arange(0.0, rig.period_us + dt / 2, dt)
    irr = rig.k_lens * (w1(t / rig.period_us) * lum + w2(t / rig.period_us) * rig.l_const)
    x = np.log(irr)
    if tau_num > 0:
        tau = np.minimum(tau_num / (irr + dark), tau_max)
        alpha = -np.expm1(-dt / tau)
        y = np.empty_like(x)
        yy = x[0]
        for j in range(x.size):
            yy += (x[j] - yy) * alpha[j]
            y[j] = yy
    else:
        y = x
    ref = float(y[0])
    times: list[float] = []
    pols: list[int] = []
    for j in range(y.size):
        v = float(y[j])
        while v >= ref + c - 1e-12:
            ref += c
            times.append(t[j])
            pols.append(1)
        while v <= ref - c + 1e-12:
            ref -= c
            times.append(t[j])
            pols.append(-1)
    return np.asarray(times), np.asarray(pols)


@pytest.mark.parametrize("lowpass", [False, True])
def test_non_monotone_waveform_matches_dense_loop(lowpass: bool) -> None:
    # T1 rises, falls, rises, holds, returns; T2 falls, holds, returns
    phase = np.array([0.0, 0.25, 0.45, 0.75, 0.85, 1.0])
    t1 = Waveform(phase, np.array([0.01, 0.6, 0.15, 1.0, 1.0, 0.01]))
    t2 = Waveform(phase, np.array([1.0, 0.8, 0.7, 0.5, 0.5, 1.0]))
    rig = Rig(period_us=10_000, t1=t1, t2=t2, l_const=10.0)
    lums = np.array([[0.3, 3.0, 10.0, 30.0, 300.0, 3000.0]])
    c = 0.2
    tau_ref = 60.0
    sensor = IDEAL
    tau_num = 0.0
    if lowpass:
        sensor = IDEAL.with_(cutoff_hz=1e6 / (2 * math.pi * tau_ref), cutoff_irradiance=100.0,
                             dark_irradiance=0.1)
        tau_num = tau_ref * (100.0 + 0.1)
    c_on, c_off = uniform(lums.shape, c)
    ev = simulate_stepped(lums, rig=rig, sensor=sensor, n_cycles=1, c_on=c_on, c_off=c_off,
                          seed=0, dt_us=5.0)
    total = 0
    for x, lum in enumerate(lums[0]):
        t_ref, p_ref = dense_reference(float(lum), rig, c, tau_num=tau_num)
        e = per_pixel(ev, x, 0)
        assert e.size == t_ref.size, (lum, e.size, t_ref.size)
        np.testing.assert_array_equal(e["p"], p_ref)
        np.testing.assert_allclose(e["t"], t_ref, atol=2.0)
        total += e.size
    assert total > 30


# ---------------------------------------------------------------- API


def test_cycle_by_cycle_equals_whole_run() -> None:
    rig = Rig(period_us=10_000)
    radiance = np.geomspace(0.2, 5e4, 30).reshape(5, 6)
    c_on, c_off = uniform(radiance.shape, 0.18)
    sensor = IDEAL.with_(cutoff_hz=300.0, reset_noise_sigma=0.02, refractory_us=30.0)
    whole = simulate_stepped(radiance, rig=rig, sensor=sensor, n_cycles=3, c_on=c_on,
                             c_off=c_off, seed=5, t0_us=1_000)
    state = initial_state(radiance, rig=rig, t0_us=1_000)
    parts = [simulate_cycle_stepped(state, radiance, rig=rig, sensor=sensor, c_on=c_on,
                                    c_off=c_off, seed=5) for _ in range(3)]
    assert state.t_us == 31_000
    assert whole.tobytes() == np.concatenate(parts).tobytes()
    assert whole["t"].min() >= 1_000


def test_too_few_slots_are_rerun_not_dropped(monkeypatch: pytest.MonkeyPatch) -> None:
    rig = Rig(period_us=10_000)
    radiance = np.geomspace(0.2, 5e4, 30).reshape(5, 6)
    c_on, c_off = uniform(radiance.shape, 0.18)
    sensor = IDEAL.with_(reset_noise_sigma=0.05)
    want = simulate_stepped(radiance, rig=rig, sensor=sensor, n_cycles=2, c_on=c_on,
                            c_off=c_off, seed=2)

    def no_slots(*args: object) -> None:
        out = args[-1]
        assert isinstance(out, np.ndarray)
        out[:] = 0

    monkeypatch.setattr(stepped_mod, "_estimate_slots", no_slots)
    got = simulate_stepped(radiance, rig=rig, sensor=sensor, n_cycles=2, c_on=c_on,
                           c_off=c_off, seed=2)
    assert want.size > 100
    assert got.tobytes() == want.tobytes()


def test_grid_includes_turning_knots() -> None:
    phase = np.array([0.0, 0.3331, 1.0])
    rig = Rig(period_us=1_000, t1=Waveform(phase, np.array([0.1, 1.0, 0.1])))
    s = step_times_us(rig, dt_us=5.0)
    assert s[0] == 0.0 and s[-1] == 1_000.0
    assert np.any(np.isclose(s, 333.1))
    assert np.all(np.diff(s) > 0)


def test_bad_inputs_raise_clear_errors() -> None:
    rig = Rig()
    r = np.ones((2, 3))
    c_on, c_off = uniform((2, 3), 0.2)
    kw = {"rig": rig, "sensor": IDEAL, "n_cycles": 1, "seed": 0}
    with pytest.raises(ValueError, match="frame_times_us"):
        simulate_stepped(np.ones((2, 2, 3)), c_on=c_on, c_off=c_off, **kw)
    with pytest.raises(ValueError, match="c_on must have the scene's shape"):
        simulate_stepped(r, c_on=np.ones((3, 2)), c_off=c_off, **kw)
    with pytest.raises(ValueError, match="negative"):
        simulate_stepped(-r, c_on=c_on, c_off=c_off, **kw)
    with pytest.raises(ValueError, match="dt_us"):
        simulate_stepped(r, c_on=c_on, c_off=c_off, dt_us=0.0, **kw)
    with pytest.raises(ValueError, match="n_cycles"):
        simulate_stepped(r, c_on=c_on, c_off=c_off, **{**kw, "n_cycles": 0})
    closed = Rig(t2=Waveform.from_samples([1.0, 0.0]))
    with pytest.raises(ValueError, match="irradiance reaches zero"):
        simulate_stepped(np.zeros((2, 3)), c_on=c_on, c_off=c_off, **{**kw, "rig": closed})


def test_simulate_moving_scene_through_the_top_level() -> None:
    """``simulate`` passes frames to the stepped engine and refuses them on the exact one."""
    from asynhdr.simulate import simulate as top

    frames = np.full((3, 4, 6), 5.0)
    frames[1, :, :3] = 500.0
    frames[2, :, :] = 500.0
    times = np.array([0.0, 20_000.0, 40_000.0])
    rec = top(frames, rig=Rig(period_us=50_000), sensor="ideal", engine="stepped",
              frame_times_us=times)
    assert rec.events.size > 0 and rec.width == 6 and rec.height == 4
    with pytest.raises(ValueError, match="stepped"):
        top(frames, sensor="ideal", frame_times_us=times)
    with pytest.raises(ValueError, match="frame_times_us"):
        top(frames, sensor="ideal")
