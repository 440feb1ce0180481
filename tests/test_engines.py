"""Both engines against an independent fine-step integration, closed forms and plain loops.

The reference (``pixel_reference.py``) integrates the photoreceptor at 0.5 µs by the
variation-of-constants integral and scans the comparator point by point: code written
apart from the engines, sharing only the model's definition (the per-event draws and the
background arrivals, drawn in the simulator's documented order). Other expected values
come from closed forms of the first-order low-pass and of a log-linear ramp worked out
here, or from a plain Python loop over a dense time grid.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

import asynhdr.sensor.pixel as pixel_mod
from asynhdr.events import EVENT_DTYPE
from asynhdr.rig import Rig, Waveform, cycle_waveform
from asynhdr.sensor.params import PRESETS, SensorParams, get_preset
from asynhdr.sensor.photoreceptor import time_grid
from asynhdr.simulate import ENGINES, simulate
from pixel_reference import reference_events

IDEAL = SensorParams(name="ideal", threshold_sigma=0.0)
IMX636_CUTOFF_HZ = PRESETS["imx636"].cutoff_hz


def per_pixel(ev: np.ndarray, width: int, npix: int) -> list[np.ndarray]:
    pix = ev["y"].astype(np.int64) * width + ev["x"]
    order = np.argsort(pix, kind="stable")
    pix, ev = pix[order], ev[order]
    off = np.searchsorted(pix, np.arange(npix + 1))
    return [ev[off[i]:off[i + 1]] for i in range(npix)]


def uniform(shape: tuple[int, int], c: float) -> tuple[np.ndarray, np.ndarray]:
    return np.full(shape, c), np.full(shape, c)


def log_ramp_rig(period_us: int = 100_000) -> Rig:
    """T1 exponential 0.001 -> 1 over the whole cycle, T2 = 0: ``log I`` rises at the
    constant rate ``ln(1000) / period_us``, whatever the radiance."""
    t1 = cycle_waveform("exponential", start=0.001, stop=1.0, ramp_fraction=1.0)
    t2 = Waveform.from_samples([0.0, 0.0])
    return Rig(period_us=period_us, t1=t1, t2=t2)


# ------------------------------------------------ 1. engines against the fine-step model

RADIANCE = np.geomspace(1e-3, 2e5, 12 * 16)[np.random.default_rng(3).permutation(12 * 16)]
RADIANCE = RADIANCE.reshape(12, 16)
"""The chart's range, 1e-3 .. 2e5 lux, pixels in random order."""


def compare_with_reference(rig: Rig, sensor: SensorParams, engine: str, ref: list
                           ) -> tuple[float, float, int]:
    """(share of pixels with the same events and polarities, share of their events
    within 2 µs, largest time difference in µs)."""
    h, w = RADIANCE.shape
    rec = simulate(RADIANCE, rig=rig, sensor=sensor, n_cycles=2, rng=5, sensor_seed=9,
                   engine=engine)
    got = per_pixel(rec.events, w, h * w)
    same = 0
    close = 0
    total = 0
    worst = 0
    for p in range(h * w):
        rt, rp = ref[p]
        g = got[p]
        if g.size == rt.size and np.array_equal(g["p"], rp):
            same += 1
            d = np.abs(g["t"] - rt)
            close += int(np.sum(d <= 2))
            total += d.size
            worst = max(worst, int(d.max(initial=0)))
    return same / (h * w), close / max(total, 1), worst


@pytest.mark.parametrize("lowpass", [False, True], ids=["no-lowpass", "lowpass"])
@pytest.mark.parametrize("preset", ["ideal", "v2e", "davis346", "imx636"])
def test_engines_match_fine_step_integration(preset: str, lowpass: bool) -> None:
    # the pixels alone: their region read alone, so the readout (after the pixel, not in
    # the reference) keeps up
    sensor = get_preset(preset).region_of_interest().with_(
        name=preset, cutoff_hz=IMX636_CUTOFF_HZ if lowpass else 0.0)
    rig = Rig()
    ref = reference_events(RADIANCE, rig, sensor, n_cycles=2, seed=5, sensor_seed=9)
    assert sum(r[0].size for r in ref) > 2000
    for engine in ENGINES:
        same, close, worst = compare_with_reference(rig, sensor, engine, ref)
        assert same >= 0.99, (engine, same)
        assert close >= 0.999, (engine, close, worst)


@pytest.mark.parametrize("panel", ["tn", "fast_shutter"])
def test_engines_match_fine_step_integration_through_real_panels(panel: str) -> None:
    sensor = get_preset("imx636").region_of_interest()
    rig = Rig(panel=panel)
    ref = reference_events(RADIANCE, rig, sensor, n_cycles=2, seed=5, sensor_seed=9)
    for engine in ENGINES:
        same, close, worst = compare_with_reference(rig, sensor, engine, ref)
        assert same >= 0.99, (engine, same)
        assert close >= 0.999, (engine, close, worst)


def test_engines_agree_on_a_chart_and_obey_the_refractory_period() -> None:
    """The realistic preset on a step chart, both engines: per-pixel counts within one per
    cycle on at least 95 % of pixels; no two events of a pixel closer than the refractory
    period."""
    from asynhdr.scene import step_chart

    chart = step_chart(width=80, height=60)
    n_cycles = 3
    # the pixels' own timestamps: read alone, as a region of interest the readout keeps up
    # with (a queue stamps events late by different amounts and can bring two of a pixel
    # closer than its refractory period, docs/sensor.md)
    sensor = get_preset("imx636").region_of_interest()
    recs = {e: simulate(chart, sensor=sensor, n_cycles=n_cycles, rng=0, sensor_seed=1,
                        engine=e) for e in ENGINES}
    npix = 80 * 60
    counts = {}
    for e, rec in recs.items():
        ev = rec.events
        pix = ev["y"].astype(np.int64) * 80 + ev["x"]
        order = np.lexsort((ev["t"], pix))
        t, pp = ev["t"][order], pix[order]
        same = pp[1:] == pp[:-1]
        gap = np.diff(t)[same]
        assert gap.min() >= sensor.refractory_us, (e, gap.min())
        counts[e] = np.bincount(pix, minlength=npix)
    agree = np.abs(counts["exact"] - counts["stepped"]) <= n_cycles
    assert agree.mean() >= 0.95
    assert counts["exact"].sum() > 100_000


# ------------------------------------------------ 2. the ideal pixel: exact on both engines


@pytest.mark.parametrize(("t1_shape", "t2_shape"), [("linear", "linear"),
                                                    ("exponential", "linear"),
                                                    ("exponential", "exponential")])
def test_ideal_pixel_engines_give_the_same_events(t1_shape: str, t2_shape: str) -> None:
    rig = Rig(t1_shape=t1_shape, t2_shape=t2_shape)  # type: ignore[arg-type]
    height, width = 4, 16
    # 0.05 .. 2e4 lux against l_const = 10: OFF-only, falling-then-rising and ON pixels
    radiance = np.geomspace(0.05, 2e4, height * width).reshape(height, width)
    rng = np.random.default_rng(7)
    c_on = rng.uniform(0.1, 0.3, radiance.shape)
    c_off = rng.uniform(0.1, 0.3, radiance.shape)
    a, b = (simulate(radiance, rig=rig, sensor=IDEAL, n_cycles=3, thresholds=(c_on, c_off),
                     engine=e).events for e in ENGINES)
    assert a.dtype == EVENT_DTYPE
    assert np.all(np.diff(a["t"]) >= 0) and np.all(np.diff(b["t"]) >= 0)
    assert a.size == b.size
    for ea, eb in zip(per_pixel(a, width, height * width), per_pixel(b, width, height * width),
                      strict=True):
        np.testing.assert_array_equal(ea["p"], eb["p"])
        assert np.max(np.abs(ea["t"] - eb["t"]), initial=0) <= 1
    assert np.any(a["p"] == -1) and np.any(a["p"] == 1)


@pytest.mark.parametrize("engine", ENGINES)
def test_timestamp_resolution_floors_times(engine: str) -> None:
    radiance = np.geomspace(1.0, 1e4, 8).reshape(2, 4)
    th = uniform(radiance.shape, 0.2)
    fine = simulate(radiance, sensor=IDEAL, thresholds=th, engine=engine).events
    coarse = simulate(radiance, sensor=IDEAL.with_(timestamp_resolution_us=10), thresholds=th,
                      engine=engine).events
    np.testing.assert_array_equal(coarse["t"], fine["t"] // 10 * 10)


# ------------------------------------------------ 3. the low-pass


@pytest.mark.parametrize("engine", ENGINES)
def test_lowpass_step_response_matches_first_order_closed_form(engine: str) -> None:
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
    ev = simulate(levels, rig=rig, sensor=sensor, thresholds=uniform(levels.shape, c),
                  engine=engine).events
    assert np.all(ev["t"] >= t_jump)  # no event before the step of light
    jump_log = math.log(100.0)  # x1 - x0
    delays = []
    for x, lum in enumerate(levels[0]):
        tau = min(tau_ref * 1000.1 / (lum + 0.1), 50_000.0)
        want = -tau * math.log(1.0 - c / jump_log)
        first = ev[ev["x"] == x]
        assert first.size and first["p"][0] == 1
        got = float(first["t"][0]) - (t_jump + 0.5)
        assert got == pytest.approx(want, rel=0.01), (lum, got, want)
        delays.append(got)
    tau_ratio = (10.0 + 0.1) / (1.0 + 0.1)
    assert delays[0] / delays[1] == pytest.approx(tau_ratio, rel=0.01)


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


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("lowpass", [False, True])
def test_non_monotone_waveform_matches_dense_loop(lowpass: bool, engine: str) -> None:
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
    ev = simulate(lums, rig=rig, sensor=sensor, thresholds=uniform(lums.shape, c),
                  engine=engine).events
    total = 0
    for x, lum in enumerate(lums[0]):
        t_ref, p_ref = dense_reference(float(lum), rig, c, tau_num=tau_num)
        e = ev[ev["x"] == x]
        assert e.size == t_ref.size, (lum, e.size, t_ref.size)
        np.testing.assert_array_equal(e["p"], p_ref)
        np.testing.assert_allclose(e["t"], t_ref, atol=2.0)
        total += e.size
    assert total > 30


# ------------------------------------------------ 4. refractory, reset noise, jitter


@pytest.mark.parametrize("engine", ENGINES)
def test_refractory_reference_taken_at_its_end(engine: str) -> None:
    period = 100_000
    rig = log_ramp_rig(period)
    refr = 5_000.0
    sensor = IDEAL.with_(refractory_us=refr)
    c = np.array([[0.2, 0.15, 0.25, 0.3]])
    ev = simulate(np.full(c.shape, 50.0), rig=rig, sensor=sensor, thresholds=(c, c.copy()),
                  engine=engine).events
    rate = math.log(1000.0) / period  # d(log I)/dt, per µs
    for x in range(c.shape[1]):
        e = ev[ev["x"] == x]
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


@pytest.mark.parametrize("engine", ENGINES)
def test_latency_and_jitter_move_the_reset_and_keep_the_dead_time(engine: str) -> None:
    """Timestamps are ``t_c + jitter z + latency``; the pixel resets at its timestamp and
    stays blind for the refractory period: no two timestamps of a pixel are closer than
    ``refractory + latency``, and the mean delay against the noiseless pixel is the
    latency."""
    rig = log_ramp_rig(100_000)
    radiance = np.full((4, 8), 50.0)
    th = uniform(radiance.shape, 0.2)
    base = IDEAL.with_(refractory_us=1000.0)
    quiet = simulate(radiance, rig=rig, sensor=base, thresholds=th, engine=engine).events
    lat = 40.0
    noisy = simulate(radiance, rig=rig, sensor=base.with_(latency_us=lat, jitter_sigma_us=5.0),
                     thresholds=th, rng=1, engine=engine).events
    for x in range(8):
        q = quiet[(quiet["x"] == x) & (quiet["y"] == 0)]["t"]
        n = noisy[(noisy["x"] == x) & (noisy["y"] == 0)]["t"]
        assert np.all(np.diff(n) >= 1000 + lat)
        # the first event has no earlier reset to shift it: latency plus jitter only
        assert abs(float(n[0] - q[0]) - lat) <= 4 * 5.0 + 1
        # each later event waits for the reset delayed by the latency and its own jitter
        # (each reset happens at the jittered firing time): the mean spacing grows by the
        # latency plus the mean of n - 1 jitter draws (4 sigma: 4 x 5 / sqrt(n - 1))
        tol = 4 * 5.0 / math.sqrt(n.size - 1) + 0.1
        assert float(np.mean(np.diff(n)) - np.mean(np.diff(q))) == pytest.approx(lat, abs=tol)


@pytest.mark.parametrize("engine", ENGINES)
def test_reset_noise_reproducible_and_of_stated_size(engine: str) -> None:
    rig = log_ramp_rig(100_000)
    shape = (8, 8)
    th = uniform(shape, 0.2)
    radiance = np.full(shape, 20.0)
    sigma = 0.02
    noisy = IDEAL.with_(reset_noise_sigma=sigma)

    def run(sensor: SensorParams, seed: int) -> np.ndarray:
        return simulate(radiance, rig=rig, sensor=sensor, thresholds=th, rng=seed,
                        engine=engine).events

    a = run(noisy, 11)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        a1 = run(noisy, 11)
    finally:
        numba.set_num_threads(threads)
    assert a.tobytes() == a1.tobytes()
    assert a.tobytes() != run(noisy, 12).tobytes()
    quiet = IDEAL.with_(reset_noise_sigma=0.0)
    q1 = run(quiet, 11)
    assert q1.tobytes() == run(quiet, 12).tobytes()
    rate = math.log(1000.0) / 100_000
    steps = []
    for e, eq in zip(per_pixel(a, 8, 64), per_pixel(q1, 8, 64), strict=True):
        steps.append(np.diff(e["t"].astype(np.float64)) * rate)
        np.testing.assert_allclose(np.diff(eq["t"].astype(np.float64)) * rate, 0.2,
                                   atol=2 * rate)
    inc = np.concatenate(steps)
    # ref_k = ref_(k-1) + c + n_k and event k + 1 fires at ref_k + c: the log
    # irradiance between events k and k + 1 rises by c + n_k (mean c, deviation sigma)
    assert inc.size > 1500
    assert inc.mean() == pytest.approx(0.2, abs=0.003)
    assert inc.std() == pytest.approx(sigma, rel=0.1)


# ------------------------------------------------ 5. noise events are the pixel's


@pytest.mark.parametrize("engine", ENGINES)
def test_noise_events_reset_the_pixel_and_respect_its_dead_time(engine: str) -> None:
    """Shot noise at a rate far above the refractory limit: every event, signal or noise,
    starts a dead time (no two events of a pixel closer than the refractory period), and
    arrivals during it are lost and counted."""
    sensor = IDEAL.with_(refractory_us=2_000.0, shot_noise_rate_hz=2_000.0,
                         shot_noise_bright_factor=1.0)
    radiance = np.geomspace(0.01, 1e5, 48).reshape(6, 8)
    rec = simulate(radiance, sensor=sensor, n_cycles=2, rng=4, engine=engine)
    ev = rec.events
    for e in per_pixel(ev, 8, 48):
        assert np.all(np.diff(e["t"]) >= 2_000)
    counts = rec.metadata["counts"]
    # 2 kHz x 0.1 s x 48 pixels = 9,600 arrivals expected; most meet a blind pixel
    assert counts["background"] + counts["background_lost_in_dead_time"] == \
        pytest.approx(9_600, rel=0.1)
    assert counts["background_lost_in_dead_time"] > counts["background"]
    # at most one event per refractory period: 0.1 s / 2 ms = 50 per pixel
    assert ev.size <= 48 * 51


@pytest.mark.parametrize("engine", ENGINES)
def test_a_noise_event_moves_the_reference(engine: str) -> None:
    """A pixel under constant light with an ON noise event: the reference is reset to the
    light's level, so the pixel fires no signal event afterwards; one whose reference had
    drifted would. Without noise the same pixel fires nothing at all."""
    rig = Rig(t1=Waveform.from_samples([0.5, 0.5]), t2=Waveform.from_samples([0.5, 0.5]))
    sensor = IDEAL.with_(leak_rate_hz=200.0)
    rec = simulate(np.full((4, 4), 30.0), rig=rig, sensor=sensor, n_cycles=3, rng=2,
                   engine=engine)
    counts = rec.metadata["counts"]
    assert rec.events.size == counts["background"] > 0
    assert counts["signal"] == 0
    assert np.all(rec.events["p"] == 1)


@pytest.mark.parametrize("engine", ENGINES)
def test_hot_pixels_are_refractory_pixels(engine: str) -> None:
    sensor = IDEAL.with_(hot_pixel_fraction=0.05, hot_pixel_rate_hz=5_000.0,
                         refractory_us=1_000.0, dead_pixel_fraction=0.05)
    rec = simulate(np.full((10, 20), 30.0), sensor=sensor, n_cycles=2, rng=1, sensor_seed=3,
                   engine=engine)
    assert rec.metadata["counts"]["hot_pixels"] == 10
    ev = rec.events
    hot = per_pixel(ev, 20, 200)
    busy = [e for e in hot if e.size > 20]
    assert len(busy) == 10
    for e in busy:
        assert np.all(np.diff(e["t"]) >= 1_000)
        # 5 kHz arrivals through a 1 ms dead time: at most one per ms
        assert e.size <= 101
    assert rec.metadata["counts"]["dead_pixels"] == 10


# ------------------------------------------------ 6. moving scenes


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
    ev = simulate(frames, rig=rig, sensor=IDEAL, thresholds=uniform((height, width), 0.2),
                  engine="stepped", frame_times_us=times).events
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
    th = uniform(radiance.shape, 0.15)
    sensor = IDEAL.with_(cutoff_hz=500.0, refractory_us=50.0)
    static = simulate(radiance, rig=rig, sensor=sensor, n_cycles=2, thresholds=th,
                      engine="stepped").events
    frames = np.stack([radiance] * 3)
    moving = simulate(frames, rig=rig, sensor=sensor, n_cycles=2, thresholds=th,
                      engine="stepped", frame_times_us=np.array([0.0, 15_000.0, 30_000.0]))
    assert static.size > 100
    # the frame times add grid points: same events, times within the grid's tolerance
    assert static.size == moving.events.size
    np.testing.assert_array_equal(static["p"], moving.events["p"])
    assert np.max(np.abs(static["t"] - moving.events["t"])) <= 1


def test_moving_scene_needs_the_stepped_engine() -> None:
    frames = np.full((3, 4, 6), 5.0)
    frames[1, :, :3] = 500.0
    frames[2, :, :] = 500.0
    times = np.array([0.0, 20_000.0, 40_000.0])
    rec = simulate(frames, rig=Rig(period_us=50_000), sensor="ideal", engine="stepped",
                   frame_times_us=times)
    assert rec.events.size > 0 and rec.width == 6 and rec.height == 4
    # the default engine picks the stepped one for a moving scene; the exact one refuses
    auto = simulate(frames, rig=Rig(period_us=50_000), sensor="ideal", frame_times_us=times)
    assert auto.metadata["engine"] == "stepped"
    assert auto.events.tobytes() == rec.events.tobytes()
    with pytest.raises(ValueError, match="stepped"):
        simulate(frames, sensor="ideal", frame_times_us=times, engine="exact")
    with pytest.raises(ValueError, match="frame_times_us"):
        simulate(frames, sensor="ideal")


# ------------------------------------------------ 7. the machinery


def test_too_few_slots_are_rerun_not_dropped(monkeypatch: pytest.MonkeyPatch) -> None:
    rig = Rig(period_us=10_000)
    radiance = np.geomspace(0.2, 5e4, 30).reshape(5, 6)
    th = uniform(radiance.shape, 0.18)
    sensor = IDEAL.with_(reset_noise_sigma=0.05, cutoff_hz=300.0)
    want = simulate(radiance, rig=rig, sensor=sensor, n_cycles=2, thresholds=th, rng=2)
    real = pixel_mod._bounds
    calls = []

    def scant(*args: object) -> None:
        real(*args)
        out = args[-2]
        assert isinstance(out, np.ndarray)
        if not calls:
            out[:] = out // 4  # too few slots the first time
        calls.append(1)

    monkeypatch.setattr(pixel_mod, "_bounds", scant)
    got = simulate(radiance, rig=rig, sensor=sensor, n_cycles=2, thresholds=th, rng=2)
    assert want.events.size > 100
    assert len(calls) > 2
    assert got.events.tobytes() == want.events.tobytes()


def test_grid_holds_knots_kinks_and_ramp_start() -> None:
    phase = np.array([0.0, 0.3331, 1.0])
    t1 = np.array([0.001, 1.0, 0.001])
    s = time_grid(phase, t1, np.full(3, 0.5), period_us=1_000.0, dt_us=5.0,
                  max_log_step=0.01, tau_min_us=0.5)
    assert s[0] == 0.0 and s[-1] == 1_000.0
    assert np.all(np.diff(s) > 0)
    assert np.any(np.isclose(s, 333.1))
    assert np.any(np.isclose(s, 333.1 + 0.0625))  # tau_min / 8 after the kink
    # log T1 moves at most 0.01 between points along the ramp from the floor
    t = np.interp(s, phase * 1_000.0, t1)
    assert np.max(np.abs(np.diff(np.log(t)))) <= 0.01 + 1e-9


def test_panels_are_in_the_loop_and_named_in_the_metadata() -> None:
    """A TN scene panel cannot close in the 5 ms between ramps: the cycle starts with the
    panel still closing, so a bright pixel first sees its light fall (OFF events) where the
    ideal panel makes it rise at once; the recording names the panel."""
    bright = np.array([[1e5]])
    ideal = simulate(bright, rig=Rig(), sensor=IDEAL, n_cycles=2)
    tn = simulate(bright, rig=Rig(panel="tn"), sensor=IDEAL, n_cycles=2)
    assert ideal.metadata["rig"]["panel"] == "ideal"
    assert tn.metadata["rig"]["panel"] == "tn"
    assert tn.metadata["rig"]["pre_emphasis"] is True
    assert ideal.events["p"][0] == 1
    assert tn.events["p"][0] == -1
    w1, _ = Rig(panel="tn").waveforms()
    assert w1.values[0] > 10 / 1000.0  # starts above ten times its floor
    # round trip of the rig through the metadata
    assert Rig.from_metadata(tn.metadata["rig"]) == Rig(panel="tn")


def test_pre_emphasis_brings_the_panels_closer_to_the_target() -> None:
    rig = Rig(panel="fast_shutter")
    plain = Rig(panel="fast_shutter", pre_emphasis=False)
    target, _ = rig.target_waveforms()
    u = np.linspace(0.0, rig.ramp_fraction, 2000)

    def err(r: Rig) -> float:
        w1, _ = r.waveforms()
        return float(np.sqrt(np.mean(np.log(w1(u) / target(u)) ** 2)))

    assert err(rig) < 0.2 * err(plain)


def test_bad_inputs_raise_clear_errors() -> None:
    r = np.ones((2, 3))
    with pytest.raises(ValueError, match="frame_times_us"):
        simulate(np.ones((2, 2, 3)), sensor=IDEAL, engine="stepped",
                 frame_times_us=np.array([0.0]))
    with pytest.raises(ValueError, match="thresholds must have the sensor's shape"):
        simulate(r, sensor=IDEAL, thresholds=(np.ones((3, 2)), np.ones((3, 2))))
    with pytest.raises(ValueError, match="negative"):
        simulate(-r, sensor=IDEAL)
    with pytest.raises(ValueError, match="dt_us"):
        simulate(r, sensor=IDEAL.with_(cutoff_hz=100.0), dt_us=0.0)
    with pytest.raises(ValueError, match="n_cycles"):
        simulate(r, sensor=IDEAL, n_cycles=0)
    with pytest.raises(ValueError, match="unknown panel"):
        Rig(panel="oled")
    with pytest.raises(ValueError, match="refractory_us \\+ latency_us"):
        simulate(r, sensor=IDEAL.with_(refractory_us=40_000.0, latency_us=20_000.0))
    closed = Rig(t2=Waveform.from_samples([1.0, 0.0]))
    with pytest.raises(ValueError, match="irradiance reaches zero"):
        simulate(np.zeros((2, 3)), rig=closed, sensor=IDEAL)


@pytest.mark.parametrize("nbins", [300, 70_000])
def test_gather_is_a_stable_sort_by_time(nbins: int) -> None:
    """The events leave the counting sort ordered by time and, among equal times, by
    listed pixel then by each pixel's own order, as a stable argsort would put them
    (16-bit slots for short cycles, 32-bit beyond 65,536 bins)."""
    rng = np.random.default_rng(3)
    width = 37
    pix = np.sort(rng.choice(37 * 29, size=500, replace=False)).astype(np.int64)
    counts = rng.integers(0, 12, pix.size).astype(np.int64)
    offsets = np.zeros(pix.size + 1, dtype=np.int64)
    np.cumsum(counts + 3, out=offsets[1:])  # spare slots, as the bound leaves them
    slot_t = np.full(int(offsets[-1]), nbins - 1,
                     dtype=np.uint16 if nbins <= 1 << 16 else np.int32)
    slot_p = np.zeros(int(offsets[-1]), dtype=np.int8)
    want_t, want_x, want_y, want_p = [], [], [], []
    for i in range(pix.size):
        t = np.sort(rng.integers(0, nbins, counts[i]))
        p = rng.choice(np.array([-1, 1], dtype=np.int8), counts[i])
        o = offsets[i]
        slot_t[o:o + counts[i]] = t
        slot_p[o:o + counts[i]] = p
        want_t.append(t)
        want_p.append(p)
        want_x.append(np.full(counts[i], pix[i] % width))
        want_y.append(np.full(counts[i], pix[i] // width))
    t_all = np.concatenate(want_t)
    order = np.argsort(t_all, kind="stable")
    ev = pixel_mod.gather_sorted(offsets, counts, slot_t, slot_p, pix, width=width,
                                 t_first_us=-5, nbins=nbins)
    assert ev.dtype == EVENT_DTYPE and ev.size == counts.sum()
    np.testing.assert_array_equal(ev["t"], t_all[order] - 5)
    np.testing.assert_array_equal(ev["x"], np.concatenate(want_x)[order])
    np.testing.assert_array_equal(ev["y"], np.concatenate(want_y)[order])
    np.testing.assert_array_equal(ev["p"], np.concatenate(want_p)[order])


def test_level_ladder_finds_the_first_crossing_a_plain_scan_finds() -> None:
    """The look-up that brackets a crossing (``level_index``) returns, for any weights and
    level, the first knot where a plain scan of ``wa A + wb B`` reaches the level: rows
    that rise, then fall, with flat stretches and steps of every size."""
    from asynhdr.sensor.photoreceptor import row_runs

    rng = np.random.default_rng(7)
    nk = 400
    steps = rng.exponential(1.0, (2, nk - 1)) * (rng.random((2, nk - 1)) < 0.8)
    steps[:, nk // 2:] *= -1.0  # rise over the first half, fall over the second
    rows = np.concatenate([np.zeros((2, 1)), np.cumsum(steps, axis=1)], axis=1)
    rows[1] += 0.3
    key = np.zeros(1, dtype=np.int64)
    run_off, run_tab = row_runs(rows, key, key + 1)
    assert sorted(run_tab[:, 2].tolist()) == [-1, 1]
    ia = np.zeros(1, dtype=np.int64)
    inv_off, inv_lvl, inv_tab = pixel_mod.level_index(rows, ia, ia + 1, key, run_off, run_tab)
    checked = 0
    for _ in range(3000):
        w = float(rng.random())
        g = int(rng.integers(run_tab.shape[0]))
        k0, k1, d = (int(v) for v in run_tab[g])
        v = (1.0 - w) * rows[0] + w * rows[1]
        lo = int(rng.integers(max(k0, 1), k1 + 1))  # the kernel searches after a knot
        up = d > 0
        thr = float(rng.uniform(v[k0:k1 + 1].min() - 1.0, v[k0:k1 + 1].max() + 1.0))
        hit = [j for j in range(lo, k1 + 1) if (v[j] >= thr if up else v[j] <= thr)]
        want = hit[0] if hit else k1 + 1
        got = pixel_mod._first_indexed(rows, 0, 1, 1.0 - w, w, lo, k1, thr, up, g, inv_off,
                                       inv_lvl, inv_tab)
        assert got == want, (g, lo, thr, w)
        checked += bool(hit) and want > lo
    assert checked > 500  # most cases are real searches, not the first knot or none
