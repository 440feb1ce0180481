"""Tests of asynhdr.segment: cycles from triggers, from the event rate, and splitting."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from asynhdr.events import EVENT_DTYPE, TRIGGER_DTYPE, make_triggers
from asynhdr.segment import (
    Cycles,
    cycles_from_events,
    cycles_from_rate,
    cycles_from_triggers,
    estimate_period_from_rate,
    event_rate,
    split_cycles,
)

# ----------------------------------------------------------------------------- helpers


def burst_events(
    rng: np.random.Generator,
    *,
    n_cycles: int,
    period_us: float,
    first_start_us: float,
    width: int = 32,
    height: int = 24,
    lead_us: float | None = None,
    noise_hz: float = 2_000.0,
    jitter_us: float = 20.0,
    drop_cycles: tuple[int, ...] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """A recording whose pixels fire a burst each cycle, and its true cycle starts.

    Each pixel has a brightness ``b`` in [0, 1) and fires three ON events per cycle at
    ``start_k + 0.4 P (1 - b) + j 0.03 P`` (j = 0, 1, 2) plus Gaussian jitter: the
    brightest pixels fire right at the cycle start, as behind the rising panel. Sparse
    uniform noise (random pixels and polarities) covers the whole recording, which
    begins ``lead_us`` before the first start (mid-way through a previous cycle).
    """
    p = float(period_us)
    lead = 0.3 * p if lead_us is None else lead_us
    starts = first_start_us + np.arange(n_cycles) * p
    b = rng.uniform(0.0, 1.0, size=height * width)
    delay = 0.4 * p * (1.0 - b)
    ys, xs = np.divmod(np.arange(height * width), width)
    chunks_t, chunks_x, chunks_y, chunks_p = [], [], [], []
    for k in range(n_cycles):
        if k in drop_cycles:
            continue
        for j in range(3):
            t = starts[k] + delay + j * 0.03 * p + rng.normal(0.0, jitter_us, size=delay.size)
            chunks_t.append(t)
            chunks_x.append(xs)
            chunks_y.append(ys)
            chunks_p.append(np.ones(delay.size, dtype=np.int8))
    t_begin, t_end = starts[0] - lead, starts[-1] + 0.9 * p
    n_noise = rng.poisson(noise_hz * (t_end - t_begin) * 1e-6)
    chunks_t.append(rng.uniform(t_begin, t_end, size=n_noise))
    chunks_x.append(rng.integers(0, width, size=n_noise))
    chunks_y.append(rng.integers(0, height, size=n_noise))
    chunks_p.append(rng.choice(np.array([-1, 1], dtype=np.int8), size=n_noise))
    t_all = np.rint(np.concatenate(chunks_t)).astype(np.int64)
    ev = np.empty(t_all.size, dtype=EVENT_DTYPE)
    ev["t"] = t_all
    ev["x"] = np.concatenate(chunks_x)
    ev["y"] = np.concatenate(chunks_y)
    ev["p"] = np.concatenate(chunks_p)
    ev = ev[np.argsort(ev["t"], kind="stable")]
    return ev, np.rint(starts).astype(np.int64)


def periodic_triggers(n: int, period_us: int, t0_us: int, *, jitter: np.ndarray | None = None,
                      with_falling: bool = True, channel: int = 0) -> np.ndarray:
    """Rising edges at ``t0 + k P (+ jitter)``; falling edges half a period later."""
    rising = t0_us + np.arange(n, dtype=np.int64) * period_us
    if jitter is not None:
        rising = rising + jitter
    if not with_falling:
        return make_triggers(rising, True, channel)
    t = np.concatenate([rising, rising + period_us // 2])
    r = np.concatenate([np.ones(n, bool), np.zeros(n, bool)])
    order = np.argsort(t, kind="stable")
    return make_triggers(t[order], r[order], channel)


# ----------------------------------------------------------------------------- triggers


def test_triggers_exact_starts() -> None:
    rng = np.random.default_rng(3)
    jit = rng.integers(-3, 4, size=30)
    tr = periodic_triggers(30, 50_000, 1_234_567, jitter=jit)
    c = cycles_from_triggers(tr)
    expected = 1_234_567 + np.arange(30) * 50_000 + jit
    np.testing.assert_array_equal(c.start_us, expected)
    assert c.source == "triggers"
    assert c.confidence == 1.0
    assert c.missing.size == 0 and c.extra.size == 0
    # Least-squares slope of the edges; the jitter is ±3 µs over 29 periods.
    assert abs(c.period_us - 50_000) < 1.0


def test_triggers_missing_edge_is_reported_and_filled(caplog: pytest.LogCaptureFixture) -> None:
    tr = periodic_triggers(25, 40_000, 10_000, with_falling=False)
    lost = int(tr["t"][9])
    tr = tr[tr["t"] != lost]
    with caplog.at_level(logging.WARNING, logger="asynhdr.segment"):
        c = cycles_from_triggers(tr)
    np.testing.assert_array_equal(c.missing, [lost])
    np.testing.assert_array_equal(c.start_us, 10_000 + np.arange(25) * 40_000)
    assert c.extra.size == 0
    assert c.confidence == pytest.approx(24 / 25)
    assert any("missing" in r.getMessage() for r in caplog.records)
    # Without filling, the gap stays and the cycle before it keeps its own length.
    c2 = cycles_from_triggers(tr, fill_missing=False)
    assert len(c2) == 24
    np.testing.assert_array_equal(c2.missing, [lost])
    i = int(np.searchsorted(c2.start_us, lost)) - 1
    assert c2.stop_us[i] == c2.start_us[i] + 40_000


def test_triggers_extra_edge_is_reported_not_used(caplog: pytest.LogCaptureFixture) -> None:
    tr = periodic_triggers(25, 40_000, 10_000)
    glitch = 10_000 + 5 * 40_000 + 13_000
    t = np.concatenate([tr["t"], [glitch]])
    r = np.concatenate([tr["rising"], [True]])
    o = np.argsort(t, kind="stable")
    tr2 = make_triggers(t[o], r[o], 0)
    with caplog.at_level(logging.WARNING, logger="asynhdr.segment"):
        c = cycles_from_triggers(tr2)
    np.testing.assert_array_equal(c.extra, [glitch])
    np.testing.assert_array_equal(c.start_us, 10_000 + np.arange(25) * 40_000)
    assert c.missing.size == 0
    assert c.confidence == pytest.approx(25 / 26)
    assert any("extra" in r.getMessage() for r in caplog.records)


def test_triggers_extra_first_edge_does_not_shift_the_grid() -> None:
    tr = periodic_triggers(20, 50_000, 100_000, with_falling=False)
    tr2 = make_triggers(np.concatenate([[70_000], tr["t"]]), True, 0)
    c = cycles_from_triggers(tr2)
    np.testing.assert_array_equal(c.extra, [70_000])
    np.testing.assert_array_equal(c.start_us, tr["t"])


def test_triggers_period_check_and_channels() -> None:
    tr = periodic_triggers(10, 50_000, 0)
    with pytest.raises(ValueError, match="period_us=25000"):
        cycles_from_triggers(tr, period_us=25_000)
    two = np.concatenate([tr, periodic_triggers(10, 20_000, 5, channel=1)])
    two = two[np.argsort(two["t"], kind="stable")]
    with pytest.raises(ValueError, match="several channels"):
        cycles_from_triggers(two)
    c = cycles_from_triggers(two, channel=1)
    np.testing.assert_array_equal(c.start_us, 5 + np.arange(10) * 20_000)
    with pytest.raises(ValueError, match="cycles_from_events"):
        cycles_from_triggers(make_triggers([10, 20], False, 0))
    with pytest.raises(ValueError, match="pass period_us"):
        cycles_from_triggers(make_triggers([10], True, 0))
    one = cycles_from_triggers(make_triggers([10], True, 0), period_us=1000)
    np.testing.assert_array_equal(one.start_us, [10])


# ----------------------------------------------------------------------------- event rate


@pytest.mark.parametrize(
    ("period_us", "first_start_us", "seed"),
    [(50_000.0, 2_000_000.0, 1), (33_333.3, 123_456.7, 2), (8_000.0, 40_000.0, 3)],
)
def test_cycles_from_events_period_and_phase(period_us: float, first_start_us: float,
                                             seed: int) -> None:
    rng = np.random.default_rng(seed)
    ev, true_starts = burst_events(rng, n_cycles=24, period_us=period_us,
                                   first_start_us=first_start_us)
    c = cycles_from_events(ev)
    assert c.source == "event_rate"
    assert abs(c.period_us - period_us) / period_us < 1e-3
    assert len(c) == true_starts.size
    err = np.abs(c.start_us - true_starts)
    assert err.max() < 0.01 * period_us, err.max()
    assert c.confidence > 0.8
    assert c.missing.size == 0


def test_cycles_from_events_with_known_period_keeps_it() -> None:
    rng = np.random.default_rng(7)
    ev, true_starts = burst_events(rng, n_cycles=22, period_us=25_000.0,
                                   first_start_us=500_000.0)
    c = cycles_from_events(ev, period_us=25_000.0)
    assert c.period_us == 25_000.0
    assert np.abs(c.start_us - true_starts).max() < 250


def test_cycles_from_events_reports_a_cycle_without_burst() -> None:
    rng = np.random.default_rng(11)
    ev, true_starts = burst_events(rng, n_cycles=24, period_us=20_000.0,
                                   first_start_us=100_000.0, drop_cycles=(10,))
    c = cycles_from_events(ev)
    assert c.missing.size == 1
    assert abs(int(c.missing[0]) - int(true_starts[10])) < 200
    assert np.abs(c.start_us - true_starts).max() < 200


def test_cycles_from_events_unsorted_input() -> None:
    rng = np.random.default_rng(5)
    ev, true_starts = burst_events(rng, n_cycles=20, period_us=10_000.0,
                                   first_start_us=30_000.0)
    shuffled = ev[rng.permutation(ev.size)]
    c = cycles_from_events(shuffled)
    assert np.abs(c.start_us - true_starts).max() < 100


def test_noise_only_gives_low_confidence_or_error() -> None:
    rng = np.random.default_rng(9)
    n = 20_000
    ev = np.zeros(n, dtype=EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, 2_000_000, size=n))
    ev["p"] = 1
    try:
        c = cycles_from_events(ev, period_range_us=(5_000, 200_000))
    except ValueError:
        return
    assert c.confidence < 0.5


def test_estimate_period_prefers_fundamental() -> None:
    # A burst every 37 bins: the autocorrelation also peaks at 74, 111 ...
    x = np.zeros(37 * 30)
    x[::37] = 100.0
    x[1::37] = 50.0
    p, strength = estimate_period_from_rate(x, bin_us=10.0, period_range_us=(100, 2_000))
    assert p == pytest.approx(370.0, abs=1.0)
    assert strength > 0.9


def test_event_rate_counts_by_hand() -> None:
    t = np.array([100, 101, 109, 110, 135], dtype=np.int64)
    np.testing.assert_array_equal(event_rate(t, bin_us=10), [3, 1, 0, 1])
    np.testing.assert_array_equal(event_rate(t, bin_us=10, t0_us=105), [2, 0, 0, 1])


def test_cycles_from_rate_rejects_coarse_bins() -> None:
    with pytest.raises(ValueError, match="too coarse"):
        cycles_from_rate(np.ones(100), bin_us=1000.0, t0_us=0, period_us=5000.0)


# ----------------------------------------------------------------------------- splitting


def test_split_cycles_matches_brute_force() -> None:
    rng = np.random.default_rng(2)
    ev, _ = burst_events(rng, n_cycles=5, period_us=10_000.0, first_start_us=20_000.0,
                         width=8, height=6)
    tr = periodic_triggers(5, 10_000, 20_000, with_falling=False)
    c = cycles_from_triggers(tr)
    bounds = split_cycles(ev, c)
    assert len(bounds) == 5
    for (a, b), s, e in zip(bounds, c.start_us, c.stop_us, strict=True):
        mask = (ev["t"] >= s) & (ev["t"] < e)
        idx = np.nonzero(mask)[0]
        assert (a, b) == (int(idx[0]), int(idx[-1]) + 1)
    # Last cycle: start + period.
    assert c.stop_us[-1] == c.start_us[-1] + 10_000
    parts = c.split(ev)
    assert sum(p.size for p in parts) == sum(b - a for a, b in bounds)
    np.testing.assert_array_equal(c.events_of(ev, 2), ev[bounds[2][0]:bounds[2][1]])


def test_split_cycles_sorts_stably(caplog: pytest.LogCaptureFixture) -> None:
    ev = np.zeros(6, dtype=EVENT_DTYPE)
    ev["t"] = [5, 15, 12, 25, 31, 29]
    ev["x"] = np.arange(6)
    ev["p"] = 1
    c = Cycles(start_us=np.array([10, 20], dtype=np.int64), period_us=10.0,
               source="triggers", confidence=1.0)
    with caplog.at_level(logging.INFO, logger="asynhdr"):
        bounds = split_cycles(ev, c)
    # Sorted: 5, 12, 15, 25, 29, 31 -> cycle 0 = [10, 20): indices 1..3, cycle 1 = [20, 30).
    assert bounds == [(1, 3), (3, 5)]
    assert any("moved" in r.getMessage() for r in caplog.records)
    parts = c.split(ev)
    np.testing.assert_array_equal(parts[0]["x"], [2, 1])
    with pytest.raises(ValueError, match="not sorted"):
        c.events_of(ev, 0)


def test_cycles_validation() -> None:
    with pytest.raises(ValueError, match="increase strictly"):
        Cycles(start_us=np.array([10, 10]), period_us=5.0, source="triggers", confidence=1.0)
    with pytest.raises(ValueError, match="source"):
        Cycles(start_us=np.array([10]), period_us=5.0, source="guess", confidence=1.0)
    with pytest.raises(ValueError, match="confidence"):
        Cycles(start_us=np.array([10]), period_us=5.0, source="triggers", confidence=1.5)
    c = Cycles(start_us=np.array([0, 100, 250, 300]), period_us=100.0, source="triggers",
               confidence=1.0)
    # 250 - 100 = 150 is not < 1.5 periods: cycle 1 keeps its own length.
    np.testing.assert_array_equal(c.stop_us, [100, 200, 300, 400])
    np.testing.assert_array_equal(c.within(0, 310).start_us, [0, 100, 250])
    np.testing.assert_array_equal(c.within(0, 298).start_us, [0, 100])
    np.testing.assert_array_equal(c.within(50, 400).start_us, [100, 250, 300])
    assert c.summary()["cycles"] == 4
    assert TRIGGER_DTYPE.names == ("t", "rising", "id")


def test_simulated_recording_without_triggers_recovers_period_and_starts() -> None:
    """The project's own simulator, 24 cycles of the step chart with leak noise (v2e):
    with triggers the starts are exact; without, the event-rate envelope gives the
    period within 0.1 % and every start within 1 % of the period. (A sensor with a slow
    photoreceptor shifts the whole envelope by its latency, which no event-rate method
    can see: the imx636 model at 10 lux starts it about 2 % of the period late.)"""
    from asynhdr.rig import Rig
    from asynhdr.scene import step_chart
    from asynhdr.simulate import simulate

    rig = Rig(period_us=20_000)
    rec = simulate(step_chart(width=74, height=34), rig=rig, sensor="v2e", n_cycles=24,
                   rng=2, t0_us=3_100)
    truth = rig.cycle_starts_us(24, t0_us=3_100)
    with_trig = cycles_from_triggers(rec.triggers)
    assert np.array_equal(with_trig.start_us, truth)
    cyc = cycles_from_events(rec.events)
    assert abs(cyc.period_us - 20_000) <= 0.001 * 20_000
    # match each true start to the nearest detected one
    k = np.searchsorted(cyc.start_us, truth)
    k = np.clip(k, 1, cyc.start_us.size - 1)
    nearest = np.where(np.abs(cyc.start_us[k] - truth) < np.abs(cyc.start_us[k - 1] - truth),
                       cyc.start_us[k], cyc.start_us[k - 1])
    assert np.max(np.abs(nearest - truth)) <= 0.01 * 20_000


def test_no_period_to_fold_by_is_an_error_not_a_crash() -> None:
    from asynhdr.segment import _fold

    for bad in (float("nan"), 0.0, -5.0, float("inf")):
        with pytest.raises(ValueError, match="no period to fold"):
            _fold(np.ones(16), 10.0, bad, 0.0)
