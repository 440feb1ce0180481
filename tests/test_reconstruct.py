"""Reconstruction, calibration and chart metrics against hand-computed answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from asynhdr.calibrate import CMAP_MAX_GAIN, cmap_from_levels, estimate_cmap
from asynhdr.events import Recording, make_events, make_triggers, validate_events
from asynhdr.reconstruct import (
    METHODS,
    CycleWindows,
    reconstruct,
    weight,
    weighted_sums,
    windows_for,
)
from asynhdr.rig import Rig
from asynhdr.scene import flat_field
from asynhdr.simulate import simulate


def _rec(events, width=2, height=1, triggers=None, metadata=None) -> Recording:
    return Recording(events=events, width=width, height=height,
                     triggers=triggers if triggers is not None else make_triggers([0, 1000]),
                     metadata=metadata or {})


@pytest.mark.parametrize(
    ("method", "f"),
    [("raw", lambda u: 1.0), ("linear", lambda u: 1 - u), ("quadratic", lambda u: (1 - u) ** 2),
     ("poly5", lambda u: (1 - u) ** 5), ("exp", lambda u: 2 ** (-10 * u))],
)
def test_paper_formula_by_hand(method, f) -> None:
    # pixel 0: ON at 100 µs, ON at 250 µs, OFF at 600 µs in cycle 0 (window 1000 µs);
    # pixel 1: ON at 1100 µs (cycle 1, u = 0.1); an event past the window is ignored.
    ev = make_events(x=[0, 0, 0, 1, 1], y=[0] * 5, p=[1, 1, -1, 1, 1],
                     t=[100, 250, 600, 1100, 1950])
    rec = _rec(ev)
    win = CycleWindows(np.array([0, 1000]), 900.0)
    c, lc = 0.17, 3.0
    img = reconstruct(rec, method=method, windows=win, threshold_on=c, threshold_off=c,
                      l_const=lc)
    assert img.shape == (2, 1, 2)
    s00 = f(100 / 900) + f(250 / 900) - f(600 / 900)
    assert img[0, 0, 0] == pytest.approx(lc * math.exp(c * s00), rel=1e-6)
    assert img[0, 0, 1] == pytest.approx(lc, rel=1e-6)  # no events: L_const
    assert img[1, 0, 1] == pytest.approx(lc * math.exp(c * f(100 / 900)), rel=1e-6)
    assert img[1, 0, 0] == pytest.approx(lc, rel=1e-6)
    # ON events weigh c_on, OFF events c_off
    c_on, c_off = 0.134, 0.203
    img = reconstruct(rec, method=method, windows=win, threshold_on=c_on, threshold_off=c_off,
                      l_const=lc)
    level = c_on * (f(100 / 900) + f(250 / 900)) - c_off * f(600 / 900)
    assert img[0, 0, 0] == pytest.approx(lc * math.exp(level), rel=1e-6)


def test_weightings_decrease_and_start_at_one() -> None:
    u = np.linspace(0, 0.999, 50)
    for m in ("linear", "quadratic", "poly5", "exp"):
        w = weight(m, u)
        assert w[0] == pytest.approx(1.0)
        assert np.all(np.diff(w) < 0)
    assert weight("exp", np.array([0.5]), k=4)[0] == pytest.approx(0.25)


def test_cmap_scales_the_threshold_per_pixel() -> None:
    ev = make_events(x=[0, 0, 1], y=[0, 0, 0], p=[1, 1, 1], t=[10, 20, 30])
    rec = _rec(ev)
    win = CycleWindows(np.array([0]), 1000.0)
    cm = np.array([[0.5, 2.0]], dtype=np.float32)
    img = reconstruct(rec, method="raw", windows=win, cmap=cm, threshold_on=0.2, l_const=1.0)
    assert img[0, 0, 0] == pytest.approx(math.exp(0.2 * 0.5 * 2))
    assert img[0, 0, 1] == pytest.approx(math.exp(0.2 * 2.0 * 1))


def test_unsorted_events_are_sorted_before_summing() -> None:
    ev = make_events(x=[0, 1, 0], y=[0, 0, 0], p=[1, 1, 1], t=[1500, 200, 100])
    rec = _rec(ev)
    win = CycleWindows(np.array([0, 1000]), 1000.0)
    s = weighted_sums(rec, win, method="raw")
    assert s[0].tolist() == [[1.0, 1.0]] and s[1].tolist() == [[1.0, 0.0]]


def test_ttfe_inverts_the_waveform_linearly_in_radiance() -> None:
    """ttfe returns radiance: the first ON of an ideal pixel inverts exactly (up to the
    1 µs timestamp), so doubling L doubles the estimate."""
    rig = Rig(period_us=50_000)
    radiance = np.array([[40.0, 80.0, 500.0, 5000.0]])
    rec = simulate(radiance, rig=rig, sensor="ideal", n_cycles=1)
    img = reconstruct(rec, method="ttfe")[0]
    # dim pixels fire late: the 1 µs stamp is negligible; the brightest fires after
    # ~30 µs, where half a µs is ~2 % of the time
    np.testing.assert_allclose(img[0, :3], radiance[0, :3], rtol=3e-3)
    assert img[0, 3] == pytest.approx(radiance[0, 3], rel=0.03)


def test_invert_is_linear_in_radiance_on_the_ideal_pixel() -> None:
    """Every event inverts to the pixel's radiance; their geometric mean is it."""
    rig = Rig(period_us=50_000)
    radiance = np.array([[3.0, 12.0, 40.0, 500.0, 5000.0]])
    rec = simulate(radiance, rig=rig, sensor="ideal", n_cycles=2)
    img = reconstruct(rec, method="invert")
    np.testing.assert_allclose(img[1, 0], radiance[0], rtol=5e-3)


@pytest.mark.parametrize("offset", [-0.15, 0.0, 0.1])
def test_invert_needs_no_reference_at_the_start_level(offset: float) -> None:
    """By hand: a pixel of rho = 10 on the paper's rig whose reference stands ``offset``
    above the signal's start level fires ON at ``ref + k c``; each crossing time is
    ``V^-1`` of its level. ``invert`` fits one unknown start level for the cycle, so it
    returns 100 (L_const = 10) whatever the offset; taking the reference at the start
    level would read ``e^offset`` wrong."""
    rig = Rig(period_us=100_000, l_const=10.0)
    w1, w2 = rig.waveforms()
    rho, c = 10.0, 0.2
    u = np.linspace(0.0, rig.ramp_fraction, 200_001)
    v = np.log(rho * w1(u) + w2(u))  # rising on the ramp
    levels = v[0] + offset + c * np.arange(1, 60)
    levels = levels[levels < v[-1]]
    t = np.floor(np.interp(levels, v, u) * rig.period_us).astype(np.int64)
    ev = make_events(x=[0] * t.size, y=[0] * t.size, p=[1] * t.size, t=t)
    rec = Recording(events=ev, width=1, height=1, triggers=make_triggers([0]),
                    metadata={"rig": rig.to_metadata(), "n_cycles": 1,
                              "sensor": {"threshold_on": c, "threshold_off": c}})
    img = reconstruct(rec, method="invert", windows=CycleWindows(np.array([0]),
                                                                 rig.ramp_us))
    assert t.size >= 10
    assert img[0, 0, 0] == pytest.approx(100.0, rel=2e-3)


def test_invert_holds_on_panels_that_lag_their_drive() -> None:
    """The ideal pixel behind TN panels driven without pre-emphasis: the signal first
    dips (the panel still closing) and comes back to its start level exactly at the
    cycle's end, where the pixel's last crossing falls into the next cycle. Every cycle
    still inverts to the flat's 100 (the start level taken as the reference read 40)."""
    rig = Rig(panel="tn", pre_emphasis=False)
    rec = simulate(np.full((4, 6), 100.0), rig=rig, sensor="ideal", n_cycles=3, rng=0)
    img = reconstruct(rec, method="invert")
    np.testing.assert_allclose(np.median(img.reshape(3, -1), axis=1), 100.0, rtol=1e-3)


def test_every_method_runs_and_is_monotone_on_a_ramp_of_radiances() -> None:
    radiance = np.geomspace(15.0, 5000.0, 12).reshape(1, 12)
    rec = simulate(radiance, sensor="ideal", n_cycles=2)
    for m in METHODS:
        img = reconstruct(rec, method=m)[-1, 0]
        assert np.all(np.diff(img) >= 0), m


def test_cmap_from_flat_fields_removes_threshold_mismatch() -> None:
    rig = Rig()
    flat = flat_field(width=40, height=30, radiance=1600.0)
    caps = [simulate(flat, rig=rig, sensor="v2e", n_cycles=1, rng=i, sensor_seed=5)
            for i in range(2)]
    cmap = estimate_cmap(caps)
    test = simulate(flat, rig=rig, sensor="v2e", n_cycles=1, rng=9, sensor_seed=5)
    for m in ("raw", "exp"):
        plain = reconstruct(test, method=m)[0]
        fixed = reconstruct(test, method=m, cmap=cmap)[0]
        cv_plain = plain.std() / plain.mean()
        cv_fixed = fixed.std() / fixed.mean()
        assert cv_fixed < 0.5 * cv_plain, (m, cv_plain, cv_fixed)
    # a pixel with a larger threshold fires less on the flat field and gets a larger map
    c_on = np.full((30, 40), 0.2)
    c_on[3, 7] = 0.3
    caps = [simulate(flat, rig=rig, sensor="ideal", thresholds=(c_on, c_on))]
    m = estimate_cmap(caps).maps["raw"]
    assert m[3, 7] > 1.2 and abs(float(np.median(m)) - 1.0) < 1e-6


def test_cmap_keeps_nominal_thresholds_where_the_flat_level_measures_none() -> None:
    # levels summed over 4 cycles: median 2.0 per cycle; 0.5 -> gain 4 (kept), 1e-3 ->
    # gain 2000 (noise, not a threshold), -1 (wrong sign) and 0 (no events) -> 1
    per_cycle = np.full((3, 4), 2.0)
    per_cycle[0, 1] = 0.5
    per_cycle[1, 2] = 1e-3
    per_cycle[2, 0] = -1.0
    per_cycle[2, 3] = 0.0
    m, n_nominal = cmap_from_levels(4 * per_cycle, 4)
    assert m[0, 1] == pytest.approx(4.0)
    assert m[1, 2] == 1.0 and m[2, 0] == 1.0 and m[2, 3] == 1.0
    assert n_nominal == 3
    assert m.max() <= CMAP_MAX_GAIN and m.min() >= 1.0 / CMAP_MAX_GAIN


def test_windows_from_triggers_and_from_metadata() -> None:
    rig = Rig(period_us=10_000, ramp_fraction=0.8)
    rec = simulate(np.full((2, 2), 100.0), rig=rig, n_cycles=3, t0_us=500)
    win = windows_for(rec)
    assert win.start_us.tolist() == [500, 10_500, 20_500]
    assert win.window_us == pytest.approx(8_000)
    no_trig = Recording(events=rec.events, width=2, height=2, metadata=rec.metadata)
    assert windows_for(no_trig).start_us.tolist() == [500, 10_500, 20_500]


@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda e: e.__setitem__("x", np.array([0, 5], np.uint16)), "outside the sensor"),
        (lambda e: e.__setitem__("t", np.array([10, 5])), "not sorted"),
        (lambda e: e.__setitem__("p", np.array([1, 0], np.int8)), "polarity"),
    ],
)
def test_event_validation_names_the_problem(mutate, match) -> None:
    ev = make_events(x=[0, 1], y=[0, 0], p=[1, -1], t=[1, 2])
    mutate(ev)
    with pytest.raises(ValueError, match=match):
        validate_events(ev, width=2, height=1)
    with pytest.raises(ValueError, match="dtype"):
        validate_events(ev.astype([("x", "u2"), ("y", "u2"), ("p", "i2"), ("t", "i8")]))


def test_weighted_sums_in_parallel_parts_equal_a_bincount_reference() -> None:
    """More than a million events are summed in parts on separate threads; parts
    straddle cycle boundaries. The sums equal a plain numpy computation."""
    rng = np.random.default_rng(4)
    n, w, h = 2_500_000, 40, 30
    t = np.sort(rng.integers(0, 5 * 10_000, n))
    ev = make_events(rng.integers(0, w, n), rng.integers(0, h, n),
                     np.where(rng.random(n) < 0.6, 1, -1), t)
    rec = Recording(events=ev, width=w, height=h)
    win = CycleWindows(np.arange(5) * 10_000, 9_000.0)
    s = weighted_sums(rec, win, method="exp", k=10.0)
    cyc = t // 10_000
    dt = t - cyc * 10_000
    keep = dt < 9_000
    wgt = np.exp2(-10.0 * dt / 9_000.0) * ev["p"]
    idx = cyc * (w * h) + ev["y"].astype(np.int64) * w + ev["x"]
    ref = np.bincount(idx[keep], weights=wgt[keep], minlength=5 * w * h).reshape(5, h, w)
    np.testing.assert_allclose(s, ref, rtol=1e-9, atol=1e-9)
    # the same events shuffled are sorted first and give the same sums
    shuffled = Recording(events=ev[rng.permutation(n)], width=w, height=h)
    np.testing.assert_allclose(weighted_sums(shuffled, win, method="exp", k=10.0), ref,
                               rtol=1e-9, atol=1e-9)
