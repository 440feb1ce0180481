"""The pixel's non-idealities against answers from theory."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from asynhdr.events import EVENT_DTYPE
from asynhdr.rig import Rig
from asynhdr.sensor.noise import apply_arbiter, by_pixel_then_time, poisson_times
from asynhdr.sensor.params import PRESETS, SensorParams
from asynhdr.simulate import simulate

QUIET = SensorParams(threshold_sigma=0.0)


def per_pixel(ev: np.ndarray, width: int) -> dict[int, np.ndarray]:
    pix = ev["y"].astype(np.int64) * width + ev["x"]
    order = np.argsort(pix, kind="stable")
    pix, ev = pix[order], ev[order]
    cuts = np.flatnonzero(np.diff(pix)) + 1
    return {int(g[0]): e for g, e in zip(np.split(pix, cuts), np.split(ev, cuts), strict=True)}


def test_refractory_no_two_events_closer_and_fewer_events() -> None:
    radiance = np.geomspace(20.0, 1e5, 40).reshape(5, 8)
    rig = Rig(period_us=20_000)
    free = simulate(radiance, rig=rig, sensor=QUIET, n_cycles=2)
    refr = simulate(radiance, rig=rig, sensor=QUIET.with_(refractory_us=300.0), n_cycles=2)
    for _, e in per_pixel(refr.events, 8).items():
        assert np.all(np.diff(e["t"]) >= 300 - 1)  # 1 µs: timestamps are floored
    # bright pixels fire faster than every 300 µs early in the ramp: the period must bite
    assert refr.events.size < free.events.size
    # the pixel, blind while the irradiance keeps rising, takes its new reference at the
    # end of the period, so its next event comes one threshold above that level: for the
    # brightest pixel the first two ON times must differ by more than 300 µs
    e = per_pixel(refr.events, 8)[39]
    assert e["t"][1] - e["t"][0] > 300


def test_refractory_longer_than_cycle_is_an_error() -> None:
    with pytest.raises(ValueError, match="refractory_us"):
        simulate(np.ones((2, 2)), rig=Rig(period_us=1000),
                 sensor=QUIET.with_(refractory_us=2000.0))


def test_background_rate_and_exponential_inter_arrivals() -> None:
    rng = np.random.default_rng(5)
    rate_hz, n_pix, duration_us = 0.4, 2_000, 1e9  # 2e6 pixel-seconds
    pix, t = poisson_times(rate_hz, n_pixels=n_pix, duration_us=duration_us, rng=rng)
    expected = rate_hz * n_pix * duration_us * 1e-6
    assert abs(pix.size - expected) < 3 * math.sqrt(expected)
    gaps = np.concatenate([np.diff(t[pix == p]) for p in range(200)])
    res = stats.kstest(gaps, "expon", args=(0, 1e6 / rate_hz))
    assert res.pvalue > 1e-3
    # and a wrong rate is rejected by the same test
    assert stats.kstest(gaps, "expon", args=(0, 0.8e6 / rate_hz)).pvalue < 1e-3


@pytest.mark.parametrize(("n", "n_pixels"), [(0, 4), (1, 1), (3_000, 7), (20_000, 50_000)])
def test_arrivals_are_grouped_by_pixel_then_time_as_a_sort_would(n: int,
                                                                  n_pixels: int) -> None:
    rng = np.random.default_rng(n)
    pix = rng.integers(0, n_pixels, n)
    t = np.round(rng.random(n) * 50.0, 1)  # whole tenths: equal times in one pixel occur
    order = by_pixel_then_time(pix, t, n_pixels)
    assert np.array_equal(order, np.lexsort((t, pix)))  # stable: ties keep their order


def test_leak_events_through_the_simulator_match_their_rate() -> None:
    # a uniform field at L_const with a flat reference: no signal, only leak events
    rig = Rig(period_us=100_000, t1_shape="linear", t2_shape="linear", t2_stop=0.0,
              contrast_ratio_1=1.0, contrast_ratio_2=1.0)
    sensor = SensorParams(threshold_sigma=0.0, leak_rate_hz=2.0)
    n_cycles = 50
    rec = simulate(np.full((40, 50), 5.0), rig=rig, sensor=sensor, n_cycles=n_cycles, rng=3)
    assert rec.metadata["counts"]["signal"] == 0
    pixel_s = 40 * 50 * n_cycles * 0.1
    expected = 2.0 * pixel_s
    assert abs(rec.events.size - expected) < 3 * math.sqrt(expected)
    assert np.all(rec.events["p"] == 1)


def test_hot_pixels_fire_at_their_rate_and_dead_pixels_never() -> None:
    rig = Rig(period_us=100_000, t2_stop=0.0, contrast_ratio_1=1.0, contrast_ratio_2=1.0)
    sensor = SensorParams(threshold_sigma=0.0, hot_pixel_fraction=0.01, hot_pixel_rate_hz=50.0,
                          dead_pixel_fraction=0.05)
    n_cycles = 20
    rec = simulate(np.full((50, 80), 5.0), rig=rig, sensor=sensor, n_cycles=n_cycles, rng=1,
                   sensor_seed=9)
    assert rec.metadata["counts"]["hot_pixels"] == 40
    expected = 40 * 50.0 * n_cycles * 0.1
    assert abs(rec.events.size - expected) < 3 * math.sqrt(expected)
    assert len(per_pixel(rec.events, 80)) <= 40

    # a bright ramp: every live pixel fires, dead ones never
    live = simulate(np.full((50, 80), 500.0), rig=Rig(period_us=20_000),
                    sensor=sensor.with_(hot_pixel_fraction=0.0), n_cycles=1, sensor_seed=9)
    fired = per_pixel(live.events, 80)
    n_dead = live.metadata["counts"]["dead_pixels"]
    assert n_dead == 200
    assert len(fired) == 50 * 80 - n_dead


def _burst(n: int, t_us: int) -> np.ndarray:
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = t_us
    ev["p"] = 1
    return ev


@pytest.mark.parametrize("mode", ["delay", "drop"])
def test_arbiter_rate_limit_and_accounting(mode: str) -> None:
    rng = np.random.default_rng(0)
    # bursts: every pixel at once, as the panels make them
    ev = np.sort(np.concatenate([_burst(5_000, 1_000), _burst(3_000, 4_000),
                                 _burst(10, 50_000)]), order="t")
    ev["x"] = rng.integers(0, 100, ev.size)
    rate_hz = 1e6  # one event per µs
    sensor = SensorParams(max_event_rate_hz=rate_hz, arbiter=mode, arbiter_buffer_events=500)
    out, st = apply_arbiter(ev, sensor, n_pixels=100)
    assert st.emitted == ev.size
    assert st.delivered + st.dropped == st.emitted
    assert out.size == st.delivered
    assert np.all(np.diff(out["t"]) >= 0)
    # no window of W µs carries more than W * rate + 1 events
    t = out["t"]
    for w in (1, 10, 100, 1000):
        counts = np.searchsorted(t, t + w, side="left") - np.arange(t.size)
        assert counts.max() <= w * rate_hz * 1e-6 + 1
    if mode == "delay":
        assert st.dropped == 0 and st.delayed > 0
        assert out.size == ev.size
    else:
        assert st.dropped > 0
        assert out.size < ev.size


@pytest.mark.parametrize("n_pixels", [100, 1000])
def test_readout_share_keeps_the_per_pixel_load(n_pixels: int) -> None:
    """A simulation of n pixels of a 1000-pixel array gets n/1000 of its readout: every
    pixel firing once at t = 0 leaves the last event (n - 1) service times late, one
    service time being 1000 / (n rate), so the queue empties after the same 999 µs at
    any size (rate 1e6/s: 1 µs per event for the whole array)."""
    ev = _burst(n_pixels, 0)
    ev["x"] = np.arange(n_pixels) % 100
    sensor = SensorParams(max_event_rate_hz=1e6, array_pixels=1000)
    assert sensor.readout(n_pixels) == (1e6 * n_pixels / 1000, max(1.0, 1024 * n_pixels / 1000))
    out, st = apply_arbiter(ev, sensor, n_pixels=n_pixels)
    service = 1000 / n_pixels
    assert st.max_delay_us == pytest.approx((n_pixels - 1) * service)
    assert int(out["t"][-1]) == math.floor((n_pixels - 1) * service)
    # without the share (a region read alone) the same burst clears n times faster
    alone = sensor.region_of_interest()
    assert alone.readout(n_pixels) == (1e6, 1024.0)
    # regions of 10 pixels: n / 10 of them, each with the whole readout
    assert sensor.region_of_interest(10).readout(n_pixels)[0] == pytest.approx(1e6 * n_pixels / 10)
    _, st1 = apply_arbiter(_burst(n_pixels, 0), alone, n_pixels=n_pixels)
    assert st1.max_delay_us == pytest.approx(n_pixels - 1)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_every_preset_same_seed_same_events(preset: str) -> None:
    radiance = np.geomspace(0.1, 1e5, 600).reshape(20, 30)
    rig = Rig(period_us=10_000)
    a = simulate(radiance, rig=rig, sensor=preset, n_cycles=2, rng=11, sensor_seed=4)
    b = simulate(radiance, rig=rig, sensor=preset, n_cycles=2, rng=11, sensor_seed=4)
    assert a.events.tobytes() == b.events.tobytes()
    assert a.events.size > 0
    assert np.all(np.diff(a.events["t"]) >= 0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"leak_rate_hz": -1.0}, "leak_rate_hz"),
        ({"shot_noise_rate_hz": -0.1}, "shot_noise_rate_hz"),
        ({"refractory_us": -5.0}, "refractory_us"),
        ({"hot_pixel_fraction": 1.5}, "hot_pixel_fraction"),
        ({"max_event_rate_hz": float("inf")}, "max_event_rate_hz"),
        ({"arbiter": "queue"}, "arbiter"),
        ({"cutoff_hz": -3.0}, "cutoff_hz"),
        ({"array_pixels": -1}, "array_pixels"),
        ({"array_pixels": 2.5}, "array_pixels"),
    ],
)
def test_bad_sensor_parameters_name_the_parameter(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        SensorParams(**kwargs)


def test_the_queue_reads_one_request_per_service_time_in_arrival_order() -> None:
    from asynhdr.sensor.noise import serve_queue

    req = np.array([0, 0, 0, 5, 20], dtype=np.int64)
    read = np.empty(req.size)
    free_at = serve_queue(req, 2.0, -1e300, read)
    np.testing.assert_array_equal(read, [0.0, 2.0, 4.0, 6.0, 20.0])
    assert free_at == 22.0
    # a busy queue carries over: the next request at 21 waits for 22
    assert serve_queue(np.array([21]), 2.0, free_at, read[:1]) == 24.0 and read[0] == 22.0


def test_a_pixel_waiting_for_the_readout_is_held_until_read(caplog) -> None:
    """A DAVIS346's readout (12 Mev/s for the array; these pixels' share) cannot keep up
    with the chart's bursts. With ``arbiter="hold"`` a pixel whose event waits is held:
    it fires again only
    ``refractory_us`` after its event was read, so a pixel's timestamps (its reads) are
    never closer than that. Simulated apart (pixel ranges), pixels are not held: they fire
    while their event waits, more events come out and some pixels' reads crowd closer than
    the refractory period, and the log says so."""
    from asynhdr.design import default_rig
    from asynhdr.scene import step_chart
    from asynhdr.simulate import finish_recording, simulate_cycles

    sensor = PRESETS["davis346"].with_(name="davis346", arbiter="hold")
    chart = step_chart(width=48, height=32)
    kw = dict(rig=default_rig("davis346"), sensor=sensor, n_cycles=2, rng=3, sensor_seed=1)
    held = simulate(chart, **kw)
    npix = 48 * 32
    with caplog.at_level("WARNING", logger="asynhdr.simulate"):
        apart = finish_recording([simulate_cycles(chart, pixels=r, **kw)
                                  for r in ((0, npix // 2), (npix // 2, npix))])
    assert "fired on as if read at once" in caplog.text

    def closest(rec) -> int:
        ev = rec.events
        pix = ev["y"].astype(np.int64) * 48 + ev["x"]
        o = np.lexsort((ev["t"], pix))
        same = pix[o][1:] == pix[o][:-1]
        return int(np.diff(ev["t"][o])[same].min())

    ro = held.metadata["readout"]
    assert ro["pixels_held"] and ro["held_cycles"] == 2 and ro["max_delay_us"] > 100
    assert closest(held) >= sensor.refractory_us
    assert closest(apart) < sensor.refractory_us
    assert not apart.metadata["readout"]["pixels_held"]
    assert held.events.size < 0.95 * apart.events.size
    # the preset's readout ("delay") fires on as if read at once: as the split one
    free = simulate(chart, **{**kw, "sensor": PRESETS["davis346"]})
    assert free.events.tobytes() == apart.events.tobytes()
    assert not free.metadata["readout"]["pixels_held"]


def test_cli_simulate_hold(tmp_path) -> None:
    from typer.testing import CliRunner

    from asynhdr.cli import _register, app
    from asynhdr.io import open_recording

    _register()
    out = tmp_path / "held.h5"
    r = CliRunner().invoke(app, ["simulate", "chart", "--preset", "davis346", "--width", "48",
                                 "--height", "32", "--n-cycles", "2", "--seed", "3",
                                 "--sensor-seed", "1", "--hold", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert "held until read in 2 of 2 cycles" in " ".join(r.output.split())
    assert open_recording(out).metadata["readout"]["pixels_held"]
    # without --hold the queue only moves timestamps, and the output says how to hold
    r = CliRunner().invoke(app, ["simulate", "chart", "--preset", "davis346", "--width", "48",
                                 "--height", "32", "--n-cycles", "2", "-o",
                                 str(tmp_path / "free.h5")])
    assert r.exit_code == 0, r.output
    assert "fired on as if read at once (--hold holds them)" in " ".join(r.output.split())
    bad = tmp_path / "bad.h5"
    r = CliRunner().invoke(app, ["simulate", "chart", "--width", "8", "--height", "8",
                                 "--hold", "--engine", "stepped", "-o", str(bad)])
    assert r.exit_code == 2 and "exact engine" in r.output and not bad.exists()


def test_held_readout_matches_an_event_by_event_reference() -> None:
    """Sixteen pixels of different radiance behind a readout of one event per 100 µs (their
    refractory period): events wait up to about a millisecond. The simulator (a first
    pass, then slices of the refractory period) and an event-by-event reference
    (tests/pixel_reference.py: one heap of every pixel's next request) give each pixel the
    same timestamps and polarities; the readout that does not hold gives about a third
    more events."""
    from pixel_reference import held_reference_events

    rig = Rig()
    sensor = SensorParams(name="held", threshold_sigma=0.05, refractory_us=100.0,
                          reset_noise_sigma=0.01, jitter_sigma_us=2.0,
                          max_event_rate_hz=1e4, arbiter="hold")
    radiance = np.geomspace(2.0, 2e4, 16).reshape(4, 4) * rig.l_const / 100.0
    rec = simulate(radiance, rig=rig, sensor=sensor, n_cycles=2, rng=5, sensor_seed=2)
    ro = rec.metadata["readout"]
    assert ro["pixels_held"] and ro["held_cycles"] == 2 and ro["max_delay_us"] > 100
    want = held_reference_events(radiance, rig, sensor, n_cycles=2, seed=5, sensor_seed=2)
    ev = rec.events
    pix = ev["y"].astype(np.int64) * 4 + ev["x"]
    assert sum(w[0].size for w in want) == ev.size > 200
    for p, (t, pol) in enumerate(want):
        mine = ev[pix == p]
        np.testing.assert_array_equal(mine["t"], t, err_msg=f"pixel {p}")
        np.testing.assert_array_equal(mine["p"], pol, err_msg=f"pixel {p}")
    free = simulate(radiance, rig=rig, sensor=sensor.with_(arbiter="delay"), n_cycles=2,
                    rng=5, sensor_seed=2)
    assert free.events.size > 1.2 * ev.size
