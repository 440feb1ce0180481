"""Maximum-likelihood radiance (asynhdr.ml): known radiances recovered within the stated
uncertainty, the bound against the estimator's spread, pixels without information."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numba as nb
import numpy as np
import pytest

from asynhdr import ml
from asynhdr.design import default_rig, round_trip_rig, sequential_rig, two_round_trips_rig
from asynhdr.events import EVENT_DTYPE, Recording
from asynhdr.reconstruct import CycleWindows, reconstruct, windows_for
from asynhdr.rig import Rig
from asynhdr.scene import flat_field
from asynhdr.sensor.params import SensorParams, get_preset
from asynhdr.simulate import draw_thresholds, simulate

QUIET = dict(leak_rate_hz=0.0, shot_noise_rate_hz=0.0, hot_pixel_fraction=0.0,
             dead_pixel_fraction=0.0)

IMX636 = get_preset("imx636").region_of_interest()
"""The IMX636 pixel, its region read alone: these few pixels never queue at the readout,
whose delays are not in ml's model (benchmarks/bench_ml.py measures the whole array's)."""


LC105_RIG = dict(period_us=200_000, l_const=105.40925533894597, a=0.075, b=0.225)
"""The IMX636's designed rig before the design searched darker references (two round
trips at 5 cycles/s, ``L_const`` 105.4 lux): the rig the cases below were found on."""


def _lc105_rig() -> Rig:
    return two_round_trips_rig(**LC105_RIG)


def _scene(levels: np.ndarray, width: int) -> np.ndarray:
    return np.repeat(np.asarray(levels, dtype=np.float64)[:, None], width, axis=1)


def test_ideal_pixel_recovers_radiance_exactly() -> None:
    # ideal pixel, ideal panels: the events are exact crossings floored to 1 µs, so the
    # radiance is known to the timing quantum: well under 0.1 %
    rig = default_rig("ideal")
    sensor = get_preset("ideal")
    levels = np.array([0.5, 7.0, 90.0, 1500.0, 2.0e4, 2.0e5])
    rec = simulate(_scene(levels, 3), rig=rig, sensor=sensor, n_cycles=2, rng=0)
    model = ml.ml_model(rig, sensor)
    assert model.mode == 0 and not model.dead
    pri = ml.thresholds_prior(sensor, width=3, height=levels.size)
    res = ml.estimate(rec.events, width=3, height=levels.size,
                      starts_us=rig.cycle_starts_us(2), model=model, priors=pri)
    est = res.radiance[-1]
    assert np.all(res.flags[-1] == 0)
    np.testing.assert_allclose(est, _scene(levels, 3), rtol=1e-3)
    # and the stated uncertainty is the timing quantum's: small, positive
    assert np.all((res.sigma_log[-1] > 0) & (res.sigma_log[-1] < 0.01))


def test_recovers_radiance_within_stated_uncertainty() -> None:
    # the IMX636 model (photoreceptor, refractory period, reset noise, jitter, threshold
    # mismatch known from calibration): z = (ln L_hat - ln L) / sigma is about N(0, 1)
    rig = default_rig("imx636")
    sensor = IMX636.with_(name="imx636q", **QUIET)
    levels = np.geomspace(30.0, 3.0e4, 7)
    w = 40
    rec = simulate(_scene(levels, w), rig=rig, sensor=sensor, n_cycles=2, rng=3,
                   sensor_seed=1)
    c_on, c_off = draw_thresholds(sensor, width=w, height=levels.size,
                                  rng=np.random.default_rng(1))
    model = ml.ml_model(rig, sensor)
    assert model.mode == 1 and model.dead
    pri = ml.thresholds_prior(sensor, width=w, height=levels.size, c_on=c_on, c_off=c_off,
                              sigma=0.002)
    res = ml.estimate(rec.events, width=w, height=levels.size,
                      starts_us=rig.cycle_starts_us(2), model=model, priors=pri)
    g = np.log(res.radiance[-1])
    z = (g - np.log(_scene(levels, w))) / res.sigma_log[-1]
    assert np.all(np.isfinite(z))
    assert np.mean(np.abs(z) < 3.0) >= 0.95
    assert 0.6 < float(np.std(z)) < 1.5
    assert abs(float(np.median(z))) < 0.3
    # the image is linear in L: the per-level means within 2 % of the truth
    means = np.mean(res.radiance[-1], axis=1)
    np.testing.assert_allclose(means, levels, rtol=0.02)


def test_uncalibrated_dark_pixels_find_the_likelihoods_optimum() -> None:
    # IMX636 model, its designed rig, nominal thresholds only (the mismatch, 5 %, is
    # unknown to the estimator): at 30 lux the reference path carries most of the light,
    # the events' total drop says little about L, and what does is how evenly it is cut
    # into thresholds. The likelihood has a narrow optimum at the truth and a plateau at
    # L -> 0 where the reference path alone explains the events; a start on the plateau
    # must not be kept (a fit that stopped there left 4.9 % of these pixels NaN).
    rig = default_rig("imx636")
    sensor = IMX636
    w, h = 50, 60
    rec = simulate(np.full((h, w), 30.0), rig=rig, sensor=sensor, n_cycles=3, rng=1,
                   sensor_seed=1)
    model = ml.ml_model(rig, sensor)
    pri = ml.thresholds_prior(sensor, width=w, height=h)
    res = ml.estimate(rec.events, width=w, height=h, starts_us=rig.cycle_starts_us(3),
                      model=model, priors=pri)
    err = np.log(res.radiance[-1]) - math.log(30.0)
    assert np.mean(np.isnan(err)) < 0.01
    assert np.mean(np.abs(err[np.isfinite(err)]) > 1.0) < 0.05
    assert abs(float(np.nanmedian(err))) < 0.05
    # an estimate uncertain to a factor e is no estimate (NaN, flagged, its deviation kept)
    # where its likelihood is a plateau; a fit of few events in a sharp optimum among
    # others about as likely keeps its estimate, flagged ambiguous
    sd, fl = res.sigma_log[-1], res.flags[-1]
    wide = np.isfinite(err) & ~(sd < 1.0)
    assert np.all(fl[wide] == ml.FLAG_AMBIGUOUS) and np.all(res.n_events[-1][wide] < 10)
    assert np.mean(wide) < 0.01
    vague = fl == ml.FLAG_UNINFORMED
    # (the deviation of a vague fit is 1 or more, or NaN where it is infinite)
    assert np.all(np.isnan(err[vague])) and not np.any(sd[vague] < 1.0)
    assert np.all(np.isfinite(sd) | np.isnan(sd))  # never infinite: the EXR keeps it


def test_neighbours_fits_lead_stuck_pixels_to_their_own_likelier_optimum() -> None:
    # IMX636 model, two round trips (L_const 105.4 lux), nominal thresholds only, a flat
    # field at 0.15 lux: each pixel's two starts (the turns of the two round trips) put
    # some pixels in the basin of an optimum far brighter than the truth, with a fair
    # chi-square, while their events are far likelier at the truth, beyond the profile's
    # checks either side of the fit (at 1.35 lux those checks free them all: 0 of 1,200
    # stay, 26 before them). Started
    # again from the median of their neighbours' fits, these pixels find it; the estimate
    # stays each pixel's own fit.
    rig = _lc105_rig()
    sensor = IMX636
    w, h, lux = 40, 30, 0.15
    rec = simulate(np.full((h, w), lux), rig=rig, sensor=sensor, n_cycles=2, rng=2,
                   sensor_seed=2)
    model = ml.ml_model(rig, sensor)
    pri = ml.thresholds_prior(sensor, width=w, height=h)
    starts = rig.cycle_starts_us(2)[1:]
    err = {}
    for nbr in (False, True):
        res = ml.estimate(rec.events, width=w, height=h, starts_us=starts, model=model,
                          priors=pri, neighbours=nbr)
        err[nbr] = np.log(res.radiance[0].astype(np.float64)) - math.log(lux)
        assert np.all(np.isfinite(err[nbr]))
    alone, helped = err[False], err[True]
    assert np.mean(np.abs(alone) > 1.0) >= 0.01  # the case exists (71 of 1,200 when written)
    assert not np.any(np.abs(helped) > 1.0)
    assert abs(float(np.mean(np.exp(helped))) - 1.0) < 0.05  # a patch mean, not its median
    moved = helped != alone
    assert np.mean(np.abs(helped[moved]) < np.abs(alone[moved])) >= 0.95


def _one_pixel(t: list[int], p: list[int], c_on: float, c_off: float,
               sd: float) -> ml.MlResult:
    """``ml`` on one pixel of the IMX636 with the rig its events came from (two round
    trips, ``L_const`` 105.4 lux): its events (times from the window's start) and its
    calibrated thresholds as the prior."""
    ev = np.zeros(len(t), dtype=EVENT_DTYPE)
    ev["t"] = t
    ev["p"] = p
    rig = _lc105_rig()
    model = ml.cached_model(rig, IMX636, window_us=rig.ramp_us)
    pri = (np.array([c_on]), np.array([c_off]), np.array([sd]), np.array([sd]))
    return ml.estimate(ev, width=1, height=1, starts_us=np.array([0]), model=model,
                       priors=pri)


def _one_imx636_pixel(t: list[int], p: list[int]) -> ml.MlResult:
    """``ml`` on one pixel of the IMX636 (its whole model, background events included) with
    its default rig and the nominal thresholds: its events, times from the window's start."""
    ev = np.zeros(len(t), dtype=EVENT_DTYPE)
    ev["t"] = t
    ev["p"] = p
    sensor = get_preset("imx636")
    rig = default_rig("imx636")
    model = ml.cached_model(rig, sensor, window_us=rig.ramp_us)
    return ml.estimate(ev, width=1, height=1, starts_us=np.array([0]), model=model,
                       priors=ml.thresholds_prior(sensor, width=1, height=1))


def test_a_pull_bounded_on_the_way_does_not_keep_a_worse_optimum() -> None:
    # One pixel of the Desk scene (0.25 lux) simulated with the IMX636 and two round trips
    # (L_const 105.4 lux). The start (the first turn's net change) says 8.2 lux. From there, least
    # squares with Huber's weights bounds the pull of the events that say "darker" and
    # settles at 1.9 lux (-2 ln likelihood 708); plain least squares from the same start
    # reaches 0.32 lux (590). Where the bounded phase clipped and the fit then takes more
    # than two events for background, both are fitted and the likelier kept.
    t = [17741, 19500, 21400, 23578, 26382, 30126, 35488, 40249, 42004, 46283, 52025,
         67216, 68284, 69163, 69909, 70567, 71230, 71856, 72446, 73052, 73620, 74227,
         74819, 75675, 108087, 109896, 111905, 114367, 117240, 121415, 126959, 131350,
         135782, 141331, 148280, 156029, 157382, 158345, 159203, 159914, 160649, 161264,
         161897, 162494, 163072, 163653, 164278, 164924, 165955, 167811]
    p = [-1] * 8 + [1, -1, -1] + [1] * 13 + [-1] * 10 + [1] * 15 + [-1]
    res = _one_pixel(t, p, 0.18521524965763092, 0.2651984691619873, 0.0021567660383811408)
    assert abs(math.log(float(res.radiance[0, 0, 0]) / 0.25)) < math.log(2.0)


def test_a_fit_far_less_likely_does_not_win_by_its_small_deviation() -> None:
    # One pixel of Desk's darkest corner (0.0013 lux, near the model's lower bound of
    # 0.0011 lux) simulated as above. From the first turn's start the fit settles at
    # 2.7 lux with a deviation of 0.03 in ln L, taking 16 of its 62 events for background
    # (-2 ln likelihood 1066); from the second turn's, at the lower bound, where its
    # events are far likelier (746) and say only "this dark or darker". Fits are compared
    # by their likelihood alone: the confident fit 11 stops off is not kept.
    t = [16579, 17729, 18919, 19924, 21187, 22401, 23746, 25237, 26967, 29193, 32208,
         35562, 38480, 40640, 42703, 44827, 46782, 49549, 52754, 66699, 67946, 68839,
         69718, 70482, 71159, 71836, 72521, 73205, 73917, 74674, 75683, 107569, 108571,
         109734, 110891, 112243, 113579, 115146, 116809, 119315, 121766, 125135, 127941,
         130582, 131965, 134024, 136228, 138575, 141102, 145835, 156058, 157438, 158491,
         159349, 160220, 160942, 161623, 162334, 162970, 163663, 164386, 165212]
    p = ([-1] * 19 + [1] * 12 + [-1] * 9 + [1] + [-1] * 3 + [1] + [-1] * 5 + [1] * 12)
    res = _one_pixel(t, p, 0.2198391854763031, 0.15739542245864868, 0.002133710038975867)
    flag = int(res.flags[0, 0, 0])
    assert flag in (ml.FLAG_OUT_OF_RANGE, ml.FLAG_UNINFORMED)
    if flag == ml.FLAG_OUT_OF_RANGE:
        assert float(res.radiance[0, 0, 0]) < 0.01  # the lower bound, not the upper


def test_neighbours_that_disagree_offer_no_start() -> None:
    # a random scene (every pixel its own radiance, 0.3 to 300,000 lux): the neighbours'
    # fits agree on nothing, so no pixel is fitted again and the image is the same
    rig = default_rig("imx636")
    sensor = IMX636
    w, h = 24, 16
    scene = np.exp(np.random.default_rng(0).uniform(math.log(0.3), math.log(3e5), (h, w)))
    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=2, rng=2, sensor_seed=2)
    model = ml.ml_model(rig, sensor)
    pri = ml.thresholds_prior(sensor, width=w, height=h)
    a, b = (ml.estimate(rec.events, width=w, height=h, starts_us=rig.cycle_starts_us(2)[1:],
                        model=model, priors=pri, neighbours=nbr).radiance
            for nbr in (False, True))
    assert np.array_equal(a, b, equal_nan=True)


def test_uncalibrated_fit_keeps_its_thresholds_out_of_the_collapse() -> None:
    # IMX636 round trip, nominal thresholds only: Gauss-Newton on the residuals alone can
    # slide to a much darker L with thresholds near zero (the signal then passes close to
    # every event's level, at times it makes unlikely). Judged by the likelihood of the
    # event times, with such a fit tried again with its thresholds held, at most 0.5 % of
    # the pixels from 2,000 lux up are off by more than 0.3 in ln L, where the model's
    # bound is 0.03 to 0.09 (judged by the residuals: 21 of 1,600, 1.3 %, their
    # thresholds at 0.003 to 0.01 against 0.22). The rig is the one the case was found on.
    rig = round_trip_rig(period_us=50_000, l_const=452.8253292719891, a=0.2, b=0.45)
    sensor = IMX636
    levels = np.geomspace(2.6, 3e5, 8)
    n = 400
    c_on, c_off = draw_thresholds(sensor, width=n, height=levels.size,
                                  rng=np.random.default_rng(5))
    rec = simulate(_scene(levels, n), rig=rig, sensor=sensor, n_cycles=2, rng=3,
                   thresholds=(c_on, c_off))
    model = ml.ml_model(rig, sensor)
    pri = ml.thresholds_prior(sensor, width=n, height=levels.size)
    res = ml.estimate(rec.events, width=n, height=levels.size,
                      starts_us=rig.cycle_starts_us(2)[1:], model=model, priors=pri)
    bright = levels >= 2000.0
    err = np.log(res.radiance[0][bright].astype(np.float64)) - np.log(levels[bright])[:, None]
    assert np.all(np.isfinite(err))
    assert np.mean(np.abs(err) > 0.3) <= 0.005
    assert np.mean(res.c_on[0][bright] < sensor.threshold_on - 4 * sensor.threshold_sigma) \
        <= 0.005


def test_reset_noise_does_not_bias_the_estimate() -> None:
    # an event is a time: its density carries |dV/dt| at the crossing, which depends on L.
    # Least squares on the levels leaves that out and is biased by about the reset noise's
    # variance (DAVIS346 model, its default rig, reset noise 0.02, true thresholds, no
    # readout limit: median error -0.064 in ln L at 30,000 lux); with the term in the
    # likelihood's gradient it is +0.011, and within 0.03 here
    rig = default_rig("davis346")
    sensor = get_preset("davis346").with_(
        name="davis-reset", max_event_rate_hz=0.0, jitter_sigma_us=0.0,
        reset_noise_sigma=0.02, **QUIET)
    n, level = 120, 3.0e4
    c_on, c_off = draw_thresholds(sensor, width=n, height=1, rng=np.random.default_rng(5))
    rec = simulate(np.full((1, n), level), rig=rig, sensor=sensor, n_cycles=2, rng=3,
                   thresholds=(c_on, c_off))
    model = ml.ml_model(rig, sensor)
    pri = ml.thresholds_prior(sensor, width=n, height=1, c_on=c_on, c_off=c_off, sigma=0.002)
    res = ml.estimate(rec.events, width=n, height=1, starts_us=rig.cycle_starts_us(2)[1:],
                      model=model, priors=pri)
    err = np.log(res.radiance[0].astype(np.float64)) - math.log(level)
    assert np.mean(np.isfinite(err)) > 0.99
    assert abs(float(np.nanmedian(err))) < 0.03
    # the spread is the reset noise's, not a bias: most pixels within three stated sigmas
    z = err / res.sigma_log[0]
    assert np.mean(np.abs(z[np.isfinite(z)]) < 3.0) >= 0.9


def test_bound_matches_estimator_spread() -> None:
    # reset noise only: the estimator's spread over many pixels of one radiance is the
    # model's Cramér-Rao bound evaluated at the truth on noiseless events
    rig = default_rig("imx636")
    base = IMX636
    sensor = base.with_(name="reset-only", threshold_sigma=0.0, jitter_sigma_us=0.0, **QUIET)
    quiet = sensor.with_(reset_noise_sigma=0.0)
    level, n = 300.0, 200
    scene = np.full((1, n), level)
    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=2, rng=5)
    clean = simulate(scene, rig=rig, sensor=quiet, n_cycles=2, rng=5)
    model = ml.ml_model(rig, sensor)
    pri = ml.thresholds_prior(sensor, width=n, height=1, c_on=np.full(n, sensor.threshold_on),
                              c_off=np.full(n, sensor.threshold_off), sigma=1e-4)
    res = ml.estimate(rec.events, width=n, height=1, starts_us=rig.cycle_starts_us(2),
                      model=model, priors=pri)
    spread = float(np.std(np.log(res.radiance[-1])))
    bound = ml.fisher_information(clean.events, width=n, height=1,
                                  start_us=int(rig.period_us), model=model, priors=pri,
                                  log_radiance=np.log(scene))
    crb = float(np.median(bound))
    assert 0.7 < spread / crb < 1.4, (spread, crb)


def test_silent_and_one_event_pixels_are_estimated_from_how_few_they_fired() -> None:
    # the paper's rig (linear ramps, t2_stop 0.5) has a blind band at 0.5 L_const: a
    # pixel there sees rho dT1 + dT2 = 0 and its log irradiance swings by
    # |ln((L T1(1) + L_const T2(1)) / (L T1(0) + L_const T2(0)))| over the ramp, which is
    # under c_on + c_off = 0.4 from about 3.2 to 7.1 lux: silence (or one event at the
    # band's edges) says L lies there. Each such pixel is estimated (FLAG_FEW_EVENTS),
    # its truth within two of its stated deviations, which are wide; a pixel with events
    # enough keeps its fit
    rig = Rig(l_const=10.0, contrast_ratio_1=1000.0, contrast_ratio_2=1000.0)
    sensor = get_preset("ideal")
    levels = 5.0 * np.exp(np.linspace(-0.8, 0.8, 17))
    rec = simulate(_scene(np.append(levels, 1000.0), 2), rig=rig, sensor=sensor, n_cycles=2,
                   rng=0)
    out: dict = {}
    img = reconstruct(rec, method="ml", ml_options={"out": out})[-1][:, 0]
    n, fl, sd = out["n_events"][-1][:, 0], out["flags"][-1][:, 0], out["sigma_log"][-1][:, 0]
    few = n < 2
    assert few[:-1].sum() >= 10 and np.any(n[:-1] == 0) and np.any(n[:-1] == 1)
    assert np.all(fl[few] == ml.FLAG_FEW_EVENTS) and np.all(fl[~few] == 0)
    truth = np.append(levels, 1000.0)
    z = np.log(img / truth) / sd
    assert np.all(np.abs(z[few]) < 2.0)
    assert np.all((sd[few] > 0.1) & (sd[few] < 0.6))
    assert img[-1] == pytest.approx(1000.0, rel=1e-3)
    assert ml.valid_flags(fl).all()


def test_a_silent_pixel_far_from_l_const_is_taken_for_dead() -> None:
    # a sensor with 5 % dead pixels: in a patch at 1000 lux (it swings far beyond both
    # thresholds) a silent pixel is dead: FLAG_NO_EVENTS, and in the image the median of
    # its measured neighbours (FLAG_FILLED, no deviation), as a calibration's map of dead
    # pixels would have it; in a patch in the paper rig's blind band (5 lux) its
    # neighbours' fits say silence is likely: estimated
    rig = Rig(l_const=10.0, contrast_ratio_1=1000.0, contrast_ratio_2=1000.0)
    sensor = dataclasses.replace(get_preset("ideal"), dead_pixel_fraction=0.05)
    scene = np.full((12, 24), 1000.0)
    scene[:, 12:] = 15.0  # two events or more: fitted, the blind band's neighbours
    scene[4:8, 16:20] = 5.0
    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=2, rng=0, sensor_seed=3)
    out: dict = {}
    img = reconstruct(rec, method="ml", ml_options={"out": out})[-1]
    n, fl = out["n_events"][-1], out["flags"][-1]
    bright = (n == 0) & (scene == 1000.0)
    assert bright.sum() >= 3
    assert np.all(fl[bright] == ml.FLAG_NO_EVENTS | ml.FLAG_FILLED)
    assert np.all(np.abs(np.log(img[bright] / 1000.0)) < 0.05)
    assert np.isnan(out["sigma_log"][-1][bright]).all()
    assert not ml.valid_flags(fl[bright]).any()
    band = scene == 5.0
    assert np.all(n[band] == 0) and np.all(fl[band] == ml.FLAG_FEW_EVENTS)
    assert np.all(np.abs(np.log(img[band] / 5.0)) < 2.0 * out["sigma_log"][-1][band])
    # the same silence with no dead pixels in the sensor's model: estimated everywhere
    out2: dict = {}
    reconstruct(rec, method="ml", ml_options={"out": out2,
                                               "sensor": get_preset("ideal")})
    assert np.all(out2["flags"][-1][bright] == ml.FLAG_FEW_EVENTS)
    model = ml.cached_model(rig, sensor, window_us=rig.ramp_us)
    with pytest.raises(ValueError, match=r"dead_fraction .* \[0, 1\); got 1.5"):
        ml.estimate(rec.events, width=24, height=12, starts_us=np.array([0]), model=model,
                    priors=ml.thresholds_prior(sensor, width=24, height=12),
                    dead_fraction=1.5)


def test_pixels_beyond_the_range_hold_its_bound_and_are_flagged() -> None:
    # the ideal pixel on the ideal preset's designed rig, 10x above the top of ml's model
    # range and 10x below its bottom: the events cannot tell how far beyond, so the
    # image holds the bound (a saturated pixel, not a hole), flagged, without a deviation;
    # a pixel inside the range keeps its estimate
    rig = default_rig("ideal")
    sensor = get_preset("ideal")
    model = ml.cached_model(rig, sensor, window_us=rig.ramp_us)
    top, bottom = math.exp(model.g_hi), math.exp(model.g_lo)
    scene = np.array([[10.0 * top, bottom / 10.0, 1000.0]])
    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=2, rng=0)
    out: dict = {}
    img = reconstruct(rec, method="ml", ml_options={"out": out})[-1]
    assert img[0, 0] == pytest.approx(top, rel=1e-6)
    assert img[0, 1] == pytest.approx(bottom, rel=1e-6)
    assert img[0, 2] == pytest.approx(1000.0, rel=1e-3)
    assert list(out["flags"][-1, 0]) == [ml.FLAG_OUT_OF_RANGE, ml.FLAG_OUT_OF_RANGE, 0]
    assert np.isnan(out["sigma_log"][-1, 0, :2]).all()
    assert np.isfinite(out["sigma_log"][-1, 0, 2])


def test_a_fit_called_vague_is_walked_down_the_likelihoods_profile() -> None:
    # One pixel of the StillLife scene at 4.5 million lux, beyond the top (a million) of
    # the paper's rig with v2e; thresholds from a c-map as the prior. Its 38 ON events
    # crowd at the start of the ramp. From a start at 0.44 million lux (a neighbour's),
    # Gauss-Newton stops at 0.83 million lux, and its matrix (which leaves out the
    # curvature of the density's Jacobian) calls the fit vague: a hole, black, 19 stops
    # off. The likelihood disagrees: with the thresholds and u fitted again at the same
    # ln L its objective falls from 541 to 66, and further toward the top. Walked down
    # the profile, the fit reaches the top: held there and flagged, as a saturated pixel.
    t = np.array([11, 22, 36, 52, 71, 94, 122, 155, 194, 242, 298, 366, 447, 544, 661,
                  800, 967, 1166, 1405, 1691, 2034, 2444, 2935, 3523, 4226, 5069, 6077,
                  7285, 8730, 10460, 12532, 15012, 17981, 21536, 25791, 30886, 36985,
                  44287], dtype=np.int32)
    p = np.ones(t.size, dtype=np.int8)
    rig = Rig()
    sensor = get_preset("v2e")
    m = ml.cached_model(rig, sensor, window_us=rig.ramp_us)
    c, sc = 0.1783783793449402, 0.01
    su, mu_u = 2.0 * c / math.sqrt(12.0), 0.0
    tq2 = m.jitter_us ** 2 + m.res_us ** 2 / 12.0
    eq2 = m.res_us ** 2 / 12.0 + (m.jitter_us ** 2 if m.dead else 0.0)
    none = np.int64(-1)
    lo, hi = np.int64(0), np.int64(t.size)
    model = (m.mode, m.dead, m.reset_sigma ** 2, tq2, eq2, m.noise_rate_per_us, m.exact,
             m.v0[0], m.v0[1], m.rows, m.g0, m.dlog, m.locate, np.int64(m.window_us))
    h, bvec, x, lmat, wy, wz, stat, st_o = (np.zeros((4, 4)), np.zeros(4), np.zeros(4),
                                            np.zeros((4, 4)), np.zeros(4), np.zeros(4),
                                            np.zeros(5), np.zeros(5))
    res = np.zeros(6)
    ml._fit_from(13.0, lo, hi, t, p, *model, m.g_lo, m.g_hi, c, c, sc, sc, su, mu_u, 0.0,
                 0.0, none, none, h, bvec, x, lmat, wy, wz, stat, res, st_o)
    assert res[1] >= 1.0 and res[0] < m.g_hi - 0.1  # vague by the matrix, below the top
    o_fit = ml._fit_nll(res, lo, hi, t, p, *model, c, c, sc, sc, su, mu_u, none, none, h,
                        bvec, st_o)
    ml._profile_walk(res, lo, hi, t, p, *model, m.g_lo, m.g_hi, c, c, sc, sc, su, mu_u, h,
                     bvec, x, lmat, wy, wz, st_o)
    assert res[0] == pytest.approx(m.g_hi)
    assert ml._fit_nll(res, lo, hi, t, p, *model, c, c, sc, sc, su, mu_u, none, none, h,
                       bvec, st_o) < o_fit - 100.0
    assert ml._fit_flag(res[0], res[1], m.g_lo, m.g_hi) == ml.FLAG_OUT_OF_RANGE


def test_reconstruct_ml_needs_rig() -> None:
    rec = simulate(np.full((2, 2), 100.0), rig=default_rig("ideal"), sensor="ideal")
    bare = Recording(events=rec.events, width=2, height=2, triggers=rec.triggers,
                     metadata={})
    with pytest.raises(ValueError, match="needs the rig"):
        reconstruct(bare, method="ml", windows=CycleWindows(np.array([0]), 45_000.0))


def test_sequential_rig_has_no_blind_band() -> None:
    # every radiance from 1e-3 to 1e3 L_const moves the signal by at least ln 2 each way
    rig = sequential_rig(period_us=50_000, l_const=100.0, a=0.3, b=0.7)
    levels = np.geomspace(0.1, 1e5, 13)
    rec = simulate(_scene(levels, 1), rig=rig, sensor="ideal", n_cycles=1, rng=0)
    counts = np.bincount(rec.events["y"], minlength=levels.size)
    # ln 2 / 0.2 = 3.5: at least three events up and three down
    assert counts.min() >= 6, counts


def test_round_trip_rig_crosses_twice_and_ends_where_it_began() -> None:
    rig = round_trip_rig(period_us=50_000, l_const=100.0, a=0.15, b=0.4)
    for w in rig.target_waveforms():
        assert float(w(np.array([0.0]))[0]) == pytest.approx(float(w(np.array([1.0]))[0]))
    # each half moves every signal by at least ln 2 each way: 3 + 3 events per half
    levels = np.geomspace(0.1, 1e5, 13)
    rec = simulate(_scene(levels, 1), rig=rig, sensor="ideal", n_cycles=1, rng=0)
    counts = np.bincount(rec.events["y"], minlength=levels.size)
    assert counts.min() >= 12, counts


def test_two_round_trips_cross_four_times_and_end_where_they_began() -> None:
    rig = round_trip_rig(period_us=50_000, l_const=100.0, a=0.1, b=0.225, trips=2)
    for w in rig.target_waveforms():
        assert float(w(np.array([0.0]))[0]) == pytest.approx(float(w(np.array([1.0]))[0]))
        # the second trip is the first, shifted by 2 b
        u = np.linspace(0.0, 0.45, 101)
        assert np.allclose(w(u + 0.45), w(u))
    levels = np.geomspace(0.1, 1e5, 13)
    rec = simulate(_scene(levels, 1), rig=rig, sensor="ideal", n_cycles=1, rng=0)
    counts = np.bincount(rec.events["y"], minlength=levels.size)
    assert counts.min() >= 24, counts


def test_cli_simulate_rig_out_then_reconstruct_ml_with_rig(tmp_path) -> None:
    # a recording file that does not keep the rig (EVT 3.0) reconstructs with --rig
    from typer.testing import CliRunner

    from asynhdr.cli import _register, app
    from asynhdr.io.images import read_image

    _register()
    runner = CliRunner()
    rec = tmp_path / "flat.raw"
    rig = tmp_path / "rig.toml"
    r = runner.invoke(app, ["simulate", "flat:300", "-o", str(rec), "--width", "16",
                            "--height", "8", "--preset", "ideal", "--n-cycles", "2",
                            "--rig-out", str(rig)])
    assert r.exit_code == 0, r.output
    assert rig.is_file()
    out = tmp_path / "img"
    r = runner.invoke(app, ["reconstruct", str(rec), "-o", str(out), "--method", "ml",
                            "--rig", str(rig), "--formats", "exr"])
    assert r.exit_code == 0, r.output
    assert "no --calibration" not in r.output  # the ideal pixel has no mismatch to fit
    img = read_image(out / "flat_ml_0001.exr")
    sig = read_image(out / "flat_ml_0001_sigma.exr")
    assert (out / "flat_ml_0001_valid.png").is_file()
    np.testing.assert_allclose(img, 300.0, rtol=2e-3)
    assert np.all(sig < 0.01)


def test_table_keeps_the_kinks_and_interpolates_within_its_tolerance() -> None:
    # a polyline with kinks at 3 and 7 on a grid of 0.5: exactly the ends and the kinks
    # are needed; a parabola sampled finely: every dropped value within the tolerance
    s = np.arange(0.0, 10.01, 0.5)
    kinked = np.interp(s, [0.0, 3.0, 7.0, 10.0], [0.0, 3.0, -1.0, 2.0])
    keep = ml.decimate_grid(s, np.stack([kinked, 2.0 * kinked]), 1e-9)
    assert s[keep].tolist() == [0.0, 3.0, 7.0, 10.0]
    fine = np.linspace(0.0, 1.0, 2001)
    curve = np.stack([fine ** 2, np.sin(3.0 * fine)])
    tol = 1e-4
    keep = ml.decimate_grid(fine, curve, tol)
    assert keep[0] == 0 and keep[-1] == fine.size - 1
    for row in curve:
        err = np.abs(np.interp(fine, fine[keep], row[keep]) - row)
        assert err.max() <= tol
    # a segment of length h on x^2 errs by h^2 / 4: h = 0.02 at most, so at least 50
    # segments, and the greedy choice keeps no more than about twice that
    assert 50 <= keep.size - 1 <= 110


def test_photoreceptor_table_reproduces_the_fine_grid() -> None:
    # the decimated table, interpolated at the model's slots, against the low-pass on its
    # full grid, within TABLE_TOL (float32 storage adds ~1e-6)
    from asynhdr.sensor.photoreceptor import DEFAULT_DT_US, Lowpass, lowpass_rows, time_grid

    rig = default_rig("imx636")
    model = ml.ml_model(rig, IMX636, window_us=20_000.0)
    # the table spans the cycle: a twentieth of the low-pass's grid times at most
    assert model.mode == 1 and model.rows.shape[1] < 0.05 * rig.period_us / DEFAULT_DT_US
    j = np.arange(0, model.rows.shape[0] - 1, 17)
    w1, w2 = rig.waveforms()
    knots = np.union1d(w1.phase, w2.phase)
    sensor = IMX636
    lp = Lowpass(sensor.tau_ref_us * (sensor.cutoff_irradiance + sensor.dark_irradiance),
                 sensor.dark_irradiance, sensor.tau_max_us)
    grid = np.exp(model.g0 + model.dlog * np.arange(model.rows.shape[0]))
    i_max = rig.k_lens * (grid[-1] * w1(knots).max() + rig.l_const * w2(knots).max())
    s = time_grid(knots, w1(knots), w2(knots), period_us=float(rig.period_us),
                  tau_min_us=min(lp.tau_num / (i_max + lp.dark_irradiance), lp.tau_max_us))
    u = s / rig.period_us
    a1, b2 = rig.k_lens * w1(u), rig.k_lens * rig.l_const * w2(u)
    _, y_end = lowpass_rows(grid[j], a1, b2, s, np.log(a1[0] * grid[j] + b2[0]), lp)
    fine, _ = lowpass_rows(grid[j], a1, b2, s, y_end, lp)
    m = np.arange(0, 20_000, 7)
    tc = m + 0.5 * sensor.timestamp_resolution_us - sensor.latency_us
    want = np.stack([np.interp(tc, s, row) for row in fine])
    k = model.locate[m, 0].astype(np.int64)
    f = model.locate[m, 1].astype(np.float64)
    got = model.rows[j][:, k, 0] + f[None, :] * model.rows[j][:, k, 1]
    assert np.abs(got - want).max() <= ml.TABLE_TOL + 1e-5


def test_few_events_state_the_spread_of_a_profile_with_two_optima() -> None:
    # the seven events of a pixel at 34.95 lux beside L_const (the bench's chart, seed 0,
    # first cycle, row 86, column 325), nominal thresholds: the likelihood's profile has
    # two optima of equal height 1.65 apart in ln L, each about 0.05 wide, between the
    # probe's distances; the fit sits in the one 1.7 below the truth (its curvature says
    # 0.13), and its stated deviation covers the other (at a factor e or more the pixel
    # is flagged ambiguous, its estimate kept)
    rig = default_rig("imx636")
    t = [14199, 29252, 32347, 72526, 123133, 162191, 174242]
    ev = np.zeros(len(t), EVENT_DTYPE)
    ev["t"] = t
    ev["p"] = [1, -1, -1, 1, -1, 1, 1]
    out: dict = {}
    img = ml.reconstruct_ml(Recording(events=ev, width=1, height=1, metadata={}),
                            CycleWindows(np.array([0]), rig.ramp_us), rig=rig,
                            sensor=get_preset("imx636"), learn=False, out=out)
    err = math.log(float(img[0, 0, 0]) / 34.95)
    sd = float(out["sigma_log"][0, 0, 0])
    assert out["flags"][0, 0, 0] == (ml.FLAG_AMBIGUOUS if sd >= 1.0 else 0)
    assert abs(err) > 1.0  # the other optimum: the estimate is no better than its events
    assert 0.5 < sd and abs(err) < 2.0 * sd


def test_ml_reports_its_fits_as_they_go_with_the_same_images() -> None:
    # the fits in parts, each reported: pixel-cycles rising to their total (two cycles and
    # the first fitted again once the second has taught the thresholds), and the same
    # images and deviations as in one part
    rig = default_rig("imx636")
    gen = np.random.default_rng(3)
    scene = np.exp(gen.uniform(math.log(1.0), math.log(1e4), (24, 48)))
    rec = simulate(scene, rig=rig, sensor=IMX636, n_cycles=2, rng=0)
    w = CycleWindows(np.array([0, int(rig.period_us)]), rig.ramp_us)
    seen: list[tuple[str, int, int]] = []
    out_a: dict = {}
    out_b: dict = {}
    a = ml.reconstruct_ml(rec, w, rig=rig, out=out_a)
    b = ml.reconstruct_ml(rec, w, rig=rig, out=out_b,
                          progress=lambda *args: seen.append(args))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(out_a["sigma_log"], out_b["sigma_log"])
    total = 3 * 24 * 48
    done = [d for _, d, _ in seen]
    assert {s for s, _, _ in seen} == {"ml: pixels fitted"}
    assert all(t == total for _, _, t in seen)
    assert done == sorted(done) and done[-1] == total
    assert len(done) >= 2 * 4  # several reports a cycle


def test_learned_thresholds_update_by_hand() -> None:
    # one cycle of four pixels, prior 0.2 +- 0.05 (both thresholds): pixel 0 is fitted at
    # 0.25 +- 0.01 from 12 events and learns it; pixel 1 fired 9 events (fewer than
    # LEARN_MIN_EVENTS): unchanged; pixel 2's fit lies 0.16 off, more than LEARN_GATE x
    # 0.05: unchanged; pixel 3's stated spread 0.001 is raised to LEARN_SD_FLOOR
    sensor = get_preset("imx636").with_(threshold_on=0.2, threshold_off=0.2,
                                        threshold_sigma=0.05)
    lt = ml.LearnedThresholds()
    pri = lt.priors(sensor, width=4, height=1)
    np.testing.assert_array_equal(pri[0], 0.2)
    np.testing.assert_array_equal(pri[2], 0.05)
    c = np.array([[[0.25, 0.25, 0.36, 0.21]]], np.float32)
    sd = np.array([[[0.01, 0.01, 0.01, 0.001]]], np.float32)
    n = np.array([[[12, 9, 40, 40]]], np.int32)
    res = ml.MlResult(radiance=np.ones((1, 1, 4), np.float32), sigma_log=sd, flags=n * 0,
                      c_on=c, c_off=c, n_events=n, sd_on=sd, sd_off=sd)
    lt.update(res)
    on, off, s_on, s_off = lt.priors(sensor, width=4, height=1)
    assert lt.cycles == 1
    np.testing.assert_allclose(on, [0.25, 0.2, 0.2, 0.21], rtol=1e-6)
    np.testing.assert_allclose(off, on)
    np.testing.assert_allclose(s_on, [0.01, 0.05, 0.05, ml.LEARN_SD_FLOOR], rtol=1e-6)
    np.testing.assert_allclose(s_off, s_on)
    with pytest.raises(ValueError, match="4 pixels"):
        lt.priors(sensor, width=2, height=1)
    with pytest.raises(ValueError, match="threshold spreads"):
        lt.update(dataclasses.replace(res, sd_on=None))


def test_first_cycle_priors_by_hand() -> None:
    # prior 0.2 +- 0.05 on three pixels; the first cycle fits 0.25 +- 0.01 on each; the
    # second, from that prior: pixel 0 at 0.24 +- 0.008, which taught it 1/0.008^2 -
    # 1/0.01^2 = 5625 of precision about (0.24/0.008^2 - 0.25/0.01^2) / 5625 = 0.2222;
    # the first cycle's prior again with that: precision 400 + 5625 = 6025, mean
    # (0.2 * 400 + 1250) / 6025 = 0.22075, spread 6025^-0.5 = 0.012883. Pixel 1 fired 9
    # events in the second cycle, pixel 2's fit is no narrower than its prior: neither
    # taught anything, so both keep the nominal prior, not what their own first cycle
    # taught
    sensor = get_preset("imx636").with_(threshold_on=0.2, threshold_off=0.2,
                                        threshold_sigma=0.05)
    lt = ml.LearnedThresholds()
    with pytest.raises(ValueError, match="nothing learned"):
        lt.first_cycle_priors()
    lt.priors(sensor, width=3, height=1)

    def cycle(c: list[float], sd: list[float], n: list[int]) -> ml.MlResult:
        ca = np.array([[c]], np.float32)
        sa = np.array([[sd]], np.float32)
        na = np.array([[n]], np.int32)
        return ml.MlResult(radiance=np.ones((1, 1, 3), np.float32), sigma_log=sa,
                           flags=na * 0, c_on=ca, c_off=ca, n_events=na, sd_on=sa, sd_off=sa)

    lt.update(cycle([0.25] * 3, [0.01] * 3, [40] * 3))
    lt.update(cycle([0.24, 0.24, 0.24], [0.008, 0.008, 0.012], [40, 9, 40]))
    on, off, s_on, s_off = lt.first_cycle_priors()
    np.testing.assert_allclose(on, [0.22075, 0.2, 0.2], rtol=1e-4)
    np.testing.assert_allclose(s_on, [0.012883, 0.05, 0.05], rtol=1e-4)
    np.testing.assert_allclose(off, on)
    np.testing.assert_allclose(s_off, s_on)


def test_first_cycle_fitted_again_with_what_the_second_taught() -> None:
    # the IMX636 pixel without calibration, six radiances from 0.2 to 5,000 lux: the first
    # cycle, fitted again from what the second taught of the thresholds, lies nearer the
    # truth than the same cycle fitted alone from the nominal thresholds (RMS of the error
    # in ln L 0.048 against 0.056), and about as near as the second cycle (0.046), which
    # had the first's
    rig = default_rig("imx636")
    sensor = IMX636.with_(**QUIET)
    levels = np.array([0.2, 1.0, 60.0, 120.0, 400.0, 5.0e3])
    scene = _scene(levels, 64)
    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=2, rng=6, sensor_seed=3)
    both = reconstruct(rec, method="ml")
    w = windows_for(rec, rig=rig)
    alone = reconstruct(rec, method="ml",
                        windows=CycleWindows(w.start_us[:1], w.window_us, warmup=w.warmup))

    def rms(img: np.ndarray) -> float:
        return float(np.sqrt(np.nanmean(np.log(img / scene) ** 2)))

    assert rms(both[0]) < 0.92 * rms(alone[0])
    assert rms(both[0]) < 1.15 * rms(both[1])
    # without the refit (a caller that keeps the last cycle): the first cycle as fitted
    # alone, the second the same
    kept = reconstruct(rec, method="ml", ml_options={"refit_first": False})
    np.testing.assert_array_equal(kept[0], alone[0])
    np.testing.assert_array_equal(kept[1], both[1])


def test_thresholds_learned_from_the_recordings_own_cycles() -> None:
    # the IMX636 pixel (mismatch 0.05 about 0.22), its default rig, four mid and bright
    # radiances, five cycles: what four cycles teach puts the thresholds nearer the truth
    # than the nominal by far (rms 0.05), with spreads that cover their errors; the last
    # cycle's image, fitted from them, is nearer the truth than without learning; and a
    # recording reconstructed cycle by cycle (the CLI's way) learns the same
    from asynhdr.reconstruct import reconstruct_cycles

    rig = default_rig("imx636")
    sensor = IMX636.with_(**QUIET)
    levels = np.array([10.0, 300.0, 5.0e3, 1.0e5])
    scene = _scene(levels, 24)
    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=5, rng=3, sensor_seed=7)
    c_on, c_off = draw_thresholds(sensor, width=24, height=4, rng=np.random.default_rng(7))
    lt = ml.LearnedThresholds()
    learned = reconstruct(rec, method="ml", ml_options={"learner": lt})
    assert lt.cycles == 5
    on, off, s_on, s_off = lt.priors(sensor, width=24, height=4)
    for est, sd, truth in ((on, s_on, c_on.ravel()), (off, s_off, c_off.ravel())):
        err = est - truth
        assert math.sqrt(np.mean(err ** 2)) < 0.01
        assert math.sqrt(np.mean((truth - sensor.threshold_on) ** 2)) > 0.03
        assert np.mean(np.abs(err) > 3 * sd) < 0.1
    plain = reconstruct(rec, method="ml", ml_options={"learn": False})
    e_learned = np.log(learned[-1] / scene)
    e_plain = np.log(plain[-1] / scene)
    assert np.sqrt(np.nanmean(e_learned ** 2)) < np.sqrt(np.nanmean(e_plain ** 2))
    out: dict = {}
    whole: dict = {}
    reconstruct(rec, method="ml", ml_options={"out": whole})
    streamed = []
    for i, _, img in reconstruct_cycles(rec, method="ml", ml_options={"out": out}):
        streamed.append(img)
        # the out dict holds the yielded cycle's outputs, the first two cycles' too
        # (fitted in one call)
        np.testing.assert_array_equal(out["sigma_log"], whole["sigma_log"][i:i + 1])
        np.testing.assert_array_equal(out["flags"], whole["flags"][i:i + 1])
    np.testing.assert_array_equal(np.stack(streamed), learned)


def test_pixels_that_learn_nothing_take_the_learned_populations_thresholds(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # a sensor whose thresholds sit at 0.30 (mismatch 0.05) read as the IMX636 preset
    # (nominal 0.223): the bright half's pixels learn theirs in the first cycle; the
    # pixels near L_const (few events: they learn nothing) then take the learned
    # population's median and spread as their prior instead of the datasheet's, and
    # their estimates' large errors shrink (90th percentile of |error in ln L| over the
    # last two cycles: 0.039 against 0.076)
    rig = default_rig("imx636")
    true = IMX636.with_(threshold_on=0.30, threshold_off=0.30)
    w, h = 64, 48
    scene = np.full((h, w), 1000.0)
    scene[:, w // 2:] = rig.l_const
    rec = simulate(scene, rig=rig, sensor=true, n_cycles=3, rng=0, sensor_seed=2)
    near = scene == rig.l_const

    def run() -> tuple[ml.LearnedThresholds, np.ndarray]:
        lt = ml.LearnedThresholds()
        img = reconstruct(rec, method="ml", ml_options={"sensor": IMX636, "learner": lt})
        return lt, img

    lt, img = run()
    on, _, s_on, _ = lt.priors(IMX636, width=w, height=h)
    assert lt.learned is not None
    never = ~lt.learned[0]
    assert never[near.ravel()].mean() > 0.3 and never[~near.ravel()].mean() < 0.05
    assert np.median(on[never]) == pytest.approx(0.30, abs=0.005)
    assert 0.03 < np.median(s_on[never]) < 0.07
    monkeypatch.setattr(ml, "LEARN_POPULATION_MIN", 10 ** 9)
    lt0, img0 = run()
    assert np.median(lt0.priors(IMX636, width=w, height=h)[0][never]) == pytest.approx(
        IMX636.threshold_on)

    def p90(im: np.ndarray) -> float:
        e = np.log(im[1:][:, near] / rig.l_const)
        e = e[np.isfinite(e)]
        return float(np.percentile(np.abs(e - np.median(e)), 90))

    assert p90(img) < 0.8 * p90(img0)


def test_pixels_that_learn_at_l_const_are_no_sample_of_the_population() -> None:
    # a flat field at L_const: a pixel fires about swing / c events, so the pixels that
    # reach the learning floor are those of low thresholds; their median is no sample of
    # the population, and the pixels that learned nothing keep the nominal prior (a low
    # one would take the silent pixels, those of high thresholds, for dead)
    rig = default_rig("imx636")
    w, h = 64, 32
    rec = simulate(np.full((h, w), rig.l_const), rig=rig, sensor=IMX636, n_cycles=2, rng=0,
                   sensor_seed=1)
    lt = ml.LearnedThresholds()
    out: dict = {}
    reconstruct(rec, method="ml", ml_options={"sensor": IMX636, "learner": lt, "out": out})
    assert lt.learned is not None
    never = ~lt.learned[0]
    assert 0.05 < never.mean() < 0.95
    on = lt.priors(IMX636, width=w, height=h)[0]
    assert np.all(on[never] == IMX636.threshold_on)
    silent = out["n_events"][-1] == 0
    assert silent.sum() >= 3 and np.all(out["flags"][-1][silent] == ml.FLAG_FEW_EVENTS)


def test_cli_valid_mask_tells_fits_from_estimates_of_few_events(tmp_path) -> None:
    # the paper's rig (L_const 10 lux) on the ideal pixel: the rows at 5 lux, in its blind
    # band, fire nothing and are estimated from their silence (128 in _valid.png); the
    # rows at 300 lux are fitted (255); the CLI says how many of each
    import cv2
    from typer.testing import CliRunner

    from asynhdr.cli import _register, app

    _register()
    runner = CliRunner()
    scene = np.full((8, 16), 300.0, np.float32)
    scene[:4] = 5.0
    np.save(tmp_path / "scene.npy", scene)
    rec = tmp_path / "rec.h5"
    r = runner.invoke(app, ["simulate", str(tmp_path / "scene.npy"), "-o", str(rec),
                            "--preset", "ideal", "--l-const", "10", "--scale", "1",
                            "--width", "16", "--height", "8", "--n-cycles", "2"])
    assert r.exit_code == 0, r.output
    out = tmp_path / "img"
    r = runner.invoke(app, ["reconstruct", str(rec), "-o", str(out), "--method", "ml",
                            "--formats", "exr"])
    assert r.exit_code == 0, r.output
    valid = cv2.imread(str(out / "rec_ml_0001_valid.png"), cv2.IMREAD_UNCHANGED)
    assert valid.shape == (8, 16)
    assert np.all(valid[:4] == 128) and np.all(valid[4:] == 255)
    assert "128 of 128 pixels estimated" in " ".join(r.output.split())
    assert "64 of them from fewer than two events" in " ".join(r.output.split())


def test_gauss_newton_settles_where_it_used_to_swing() -> None:
    # One pixel at 1.74 lux simulated with the IMX636 and its default rig. The fit's
    # gradient has the density's Jacobian term, its matrix not: from the start, each step
    # overshot, and the iteration swung between two points 0.025 apart in ln L for as
    # long as it ran; the fit was whichever it stopped on. A step that turns back on the
    # last by more than half of it now goes to the secant's point between them: the fit
    # is the same whatever the iterations allowed.
    t = np.array([19117, 22107, 25974, 30819, 37522, 45063, 54886, 72245, 73820, 75162,
                  77071, 112699, 116831, 122529, 130668, 139261, 150361, 161417, 163208,
                  164649, 166033, 169211], dtype=np.int64)
    p = np.array([-1] * 7 + [1] * 4 + [-1] * 6 + [1] * 5, dtype=np.int8)
    sensor = get_preset("imx636")
    rig = default_rig("imx636")
    m = ml.cached_model(rig, sensor, window_us=float(rig.ramp_us))
    c1, c2, s1 = sensor.threshold_on, sensor.threshold_off, sensor.threshold_sigma
    su, mu = ml._u_prior(c1, c2, 0.0)
    tq2 = m.jitter_us ** 2 + m.res_us ** 2 / 12.0
    eq2 = m.res_us ** 2 / 12.0 + (m.jitter_us ** 2 if m.dead else 0.0)
    common = (m.mode, m.dead)
    tables = (m.exact, m.v0[0], m.v0[1], m.rows, m.g0, m.dlog, m.locate,
              np.int64(m.window_us), m.g_lo, m.g_hi)
    none = np.int64(-1)
    g0 = ml._start(0, t.size, t, p, *common, *tables, m.net_g, m.net_v, c1, c2, mu, none,
                   none, np.int64(m.split_us))
    fits = []
    for n_iter in (16, 17, 18):
        h, bvec, x, lmat, wy, wz, stat, _ = ml._workspace()
        res = np.zeros(6)
        ml._gauss_newton(g0, 0, t.size, t, p, *common, m.reset_sigma ** 2, tq2, eq2,
                         m.noise_rate_per_us, *tables, c1, c2, s1, s1, su, mu, 0.0, 0.0,
                         np.int64(n_iter), none, none, h, bvec, x, lmat, wy, wz, stat, res,
                         False)
        fits.append(res[0])
    assert max(fits) - min(fits) < 2e-3
    assert abs(fits[0] - math.log(1.7417)) < 0.1


def test_a_fit_in_the_profiles_shallower_optimum_is_moved_to_the_likelier_one() -> None:
    # One pixel at 0.33 lux simulated with the IMX636 (its OFF threshold near 0.30, the
    # nominal 0.223) and its default rig. Its likelihood's profile over ln L has two
    # optima: at 0.4 lux (-2 ln likelihood 371) and a shallower one at 2.1 lux (525).
    # Both starts, the net level changes at the nominal thresholds, say 10 lux and more,
    # and the fit fell into the shallower optimum with a deviation of 0.03 in ln L:
    # confidently 1.9 off. The profile 1.5 below the fit is likelier, and the fit from
    # there reaches the likelier optimum.
    t = [19191, 22599, 27247, 33511, 34486, 39824, 45105, 51394, 71664, 72865, 73788, 74725,
         75655, 76986, 79640, 110806, 114670, 120944, 126802, 132332, 137913, 145527,
         160839, 162244, 163363, 164268, 165088, 166106, 167749, 172137]
    p = [-1] * 4 + [1] + [-1] * 3 + [1] * 7 + [-1] * 7 + [1] * 8
    res = _one_imx636_pixel(t, p)
    assert int(res.flags[0, 0, 0]) == 0
    g = math.log(float(res.radiance[0, 0, 0]))
    assert abs(g - math.log(0.3286)) < 0.3  # 0.40 lux, deviation 0.07 (it was 1.85 off)


def test_a_fit_gauss_newton_holds_off_the_profiles_optimum_is_walked_there() -> None:
    # One pixel at 18.2 lux (half of L_const on the IMX636's default rig) of a simulated
    # chart, nominal thresholds as its prior (its own: 0.219 and 0.288). One OFF event
    # (96,311 us) sits near a turn of the signal, its level 0.02 from its reference: a
    # background event at the truth. Gauss-Newton settled at 24.9 lux with a deviation of
    # 0.016 (19 of them off), thresholds 0.189 and 0.222, and returned there from every
    # point of the profile: its fixed point solves the likelihood's equations only nearly.
    # The profile 0.3 below is likelier by 29 in -2 ln likelihood; that point, walked
    # downhill on the profile, is the fit.
    t = [14993, 21429, 26517, 40115, 69734, 72526, 74308, 96311, 105000, 111140, 116101,
         126923, 159990, 162691, 164410]
    p = [1, -1, -1, -1, 1, 1, 1, -1, 1, -1, -1, -1, 1, 1, 1]
    res = _one_imx636_pixel(t, p)
    assert int(res.flags[0, 0, 0]) == 0
    sd = float(res.sigma_log[0, 0, 0])
    err = math.log(float(res.radiance[0, 0, 0]) / 18.2335)
    assert abs(err) < 0.1  # 0.015 off, deviation 0.029 (it was 0.312 off)
    assert abs(err) < 3.0 * sd
    assert abs(float(res.c_off[0, 0, 0]) - 0.288) < 0.02


def test_an_optimum_a_factor_e_away_is_found_between_the_far_checks() -> None:
    # One pixel at 13.3 lux of the speed benchmark's scene (IMX636, default rig, nominal
    # thresholds). The fit sat at 37.0 lux, L_const, with a deviation of 0.19 (1.02 off
    # in ln L); the profile 1.0 below it was likelier by 48 in -2 ln likelihood, and the
    # checks at 0.5 and 1.5 either side did not see it. With a check at 1.0 the fit from
    # there is at the truth.
    t = [23187, 28635, 40929, 67436, 67641, 71270, 73377, 74843, 77780, 111620, 116916,
         126339, 160982, 163085, 164704]
    p = [-1, -1, -1, 1, 1, 1, 1, 1, -1, -1, -1, -1, 1, 1, 1]
    res = _one_imx636_pixel(t, p)
    assert int(res.flags[0, 0, 0]) == 0
    err = math.log(float(res.radiance[0, 0, 0]) / 13.322)
    assert abs(err) < 0.1  # 0.023 off, deviation 0.032
    assert abs(err) < 3.0 * float(res.sigma_log[0, 0, 0])


def test_half_l_const_fits_and_their_thresholds_within_their_stated_deviations() -> None:
    # A flat field at 18.2 lux, half of L_const on the IMX636's default rig: the signal
    # swings by ln 2 a ramp, 10 to 20 events a cycle, and ln L trades against the
    # thresholds along a ridge. The second cycle, nominal thresholds as the prior (the
    # pixels' own drawn with spread 0.05). Before the profile's walk and the thresholds'
    # widening along the ridge: RMS error in ln L 0.053, 69 of 2,304 fits more than three
    # stated deviations off, the OFF thresholds' errors 2.2 stated deviations RMS.
    w = h = 48
    sensor = get_preset("imx636")
    rig = default_rig("imx636")
    rec = simulate(flat_field(width=w, height=h, radiance=18.2), rig=rig, sensor=sensor,
                   n_cycles=2, rng=3, sensor_seed=5)
    c_on, c_off = draw_thresholds(sensor, width=w, height=h, rng=np.random.default_rng(5))
    res = ml.estimate(rec.events, width=w, height=h, starts_us=np.array([int(rig.period_us)]),
                      model=ml.cached_model(rig, sensor, window_us=rig.ramp_us),
                      priors=ml.thresholds_prior(sensor, width=w, height=h), threshold_sd=True)
    assert res.sd_on is not None and res.sd_off is not None
    ok = res.flags[0] == 0
    assert ok.mean() > 0.99
    err = np.log(res.radiance[0][ok] / 18.2)
    z = err / res.sigma_log[0][ok]
    z_on = (res.c_on[0] - c_on)[ok] / res.sd_on[0][ok]
    z_off = (res.c_off[0] - c_off)[ok] / res.sd_off[0][ok]
    assert math.sqrt(np.mean(err ** 2)) < 0.045  # 0.034
    assert np.mean(np.abs(z) > 3.0) < 0.02  # 20 of 2,304
    assert math.sqrt(np.mean(z_on ** 2)) < 1.25  # 1.05
    assert math.sqrt(np.mean(z_off ** 2)) < 1.6  # 1.28


def test_a_second_optimum_of_near_equal_likelihood_widens_the_stated_deviation() -> None:
    # One pixel at 16.3 lux, near L_const (37 lux) on the IMX636's default rig, 11 events,
    # nominal thresholds. Its fit lies at 23.5 lux with a curvature's deviation of 0.014 in
    # ln L, 26 of them from the truth: the likelihood's profile either side of the fit is
    # far likelier than that curvature says. The stated deviation is now that of the
    # mixture of the fit and the profile's points (0.24), the truth within 2 of it.
    t = [26105, 41762, 70109, 73010, 74938, 115149, 130823, 160373, 163101, 164970, 178534]
    p = [-1, -1, 1, 1, 1, -1, -1, 1, 1, 1, -1]
    res = _one_imx636_pixel(t, p)
    assert int(res.flags[0, 0, 0]) == 0
    sd = float(res.sigma_log[0, 0, 0])
    err = math.log(float(res.radiance[0, 0, 0]) / 16.3097)
    assert 0.1 < sd < 1.0
    assert abs(err) < 2.0 * sd


@pytest.mark.parametrize("preset", ["ideal", "imx636"])
def test_fast_fit_recovers_radiance_within_stated_uncertainty(preset: str) -> None:
    # the fast fit, thresholds held at the calibration's (here the sensor's own, known to
    # 0.002): the ideal pixel (no dead time: the walk) to the timing quantum, the IMX636's
    # (photoreceptor, refractory period, reset noise, jitter) with z about N(0, 1)
    rig = default_rig(preset)
    sensor = get_preset("ideal") if preset == "ideal" else IMX636.with_(name="imx636q",
                                                                          **QUIET)
    levels = np.array([0.5, 7.0, 90.0, 1500.0, 2.0e4, 2.0e5]) if preset == "ideal" \
        else np.geomspace(30.0, 3.0e4, 7)
    w = 40
    rec = simulate(_scene(levels, w), rig=rig, sensor=sensor, n_cycles=2, rng=3,
                   sensor_seed=1)
    c_on, c_off = draw_thresholds(sensor, width=w, height=levels.size,
                                  rng=np.random.default_rng(1))
    model = ml.ml_model(rig, sensor)
    pri = ml.thresholds_prior(sensor, width=w, height=levels.size, c_on=c_on, c_off=c_off,
                              sigma=0.002)
    res = ml.estimate(rec.events, width=w, height=levels.size,
                      starts_us=rig.cycle_starts_us(2), model=model, priors=pri, fast=True)
    assert np.all(res.flags[-1] == 0)
    # the thresholds are held, not fitted, but where a fit failed the fast fit's checks
    held = res.c_on[-1] == pri[0].reshape(levels.size, w).astype(np.float32)
    assert held.mean() >= 0.9
    if preset == "ideal":
        np.testing.assert_allclose(res.radiance[-1], _scene(levels, w), rtol=1e-3)
        return
    z = (np.log(res.radiance[-1]) - np.log(_scene(levels, w))) / res.sigma_log[-1]
    assert np.mean(np.abs(z) < 3.0) >= 0.95
    assert 0.6 < float(np.std(z)) < 1.5
    assert abs(float(np.median(z))) < 0.3
    np.testing.assert_allclose(np.mean(res.radiance[-1], axis=1), levels, rtol=0.02)


# Pixels whose fast fit (thresholds held at a calibration's) stops in another optimum that
# only one of the check's points sees; the check sends each to the full fit, which finds
# the truth's. ``(events' times, polarities, c_on, c_off, stated spread, radiance)``:
_CHECK_CASES = {
    # 1.35 lux (the bench's chart, seed 0, second cycle, row 123, column 155; thresholds
    # each 1 % off, stated 0.005): Newton's method stops 0.30 above the truth, stating
    # 0.035, 33 above the truth's optimum in -2 ln L; the points 0.5 away miss it (the one
    # below lands on the truth's steep side), the one 0.25 below does not
    "a quarter below": (
        [20362, 23411, 27576, 33225, 39999, 47182, 55993, 71475, 72911, 74071, 75049,
         76241, 78706, 110753, 114125, 118396, 124455, 131148, 134264, 142483, 161878,
         163272, 164348, 165259, 166564, 169754],
        [-1] * 7 + [1] * 6 + [-1] * 5 + [1, -1] + [1] * 6, 0.26442, 0.24450, 0.005, 1.350314),
    # 22.1 lux, beside L_const / 2 (MtTamWest through `asynhdr evaluate --preset imx636
    # --designed`, second cycle, row 420, column 307; the scenes' calibration): Newton's
    # method stops 1.0 below the truth, stating 0.047; the point 1.0 above sees the truth
    "a factor e above": (
        [21830, 27864, 73047, 75352, 85047, 105370, 111276, 117250, 133584, 160660, 163668],
        [-1, -1, 1, 1, 1, 1, -1, -1, -1, 1, 1], 0.26914, 0.28078, 0.0022, 22.1043),
}


@pytest.mark.parametrize("case", sorted(_CHECK_CASES))
def test_fast_fit_check_finds_the_truths_optimum(case: str) -> None:
    t, p, c_on, c_off, sigma, truth = _CHECK_CASES[case]
    ev = np.zeros(len(t), EVENT_DTYPE)
    ev["t"] = t
    ev["p"] = p
    pri = ml.thresholds_prior(IMX636, width=1, height=1, c_on=np.array([[c_on]]),
                              c_off=np.array([[c_off]]), sigma=sigma)
    res = ml.estimate(ev, width=1, height=1, starts_us=np.array([0]),
                      model=ml.ml_model(default_rig("imx636"), IMX636), priors=pri,
                      fast=True)
    assert res.full_fits is not None and int(res.full_fits[0]) == 1
    err = math.log(float(res.radiance[0, 0, 0]) / truth)
    sd = float(res.sigma_log[0, 0, 0])
    assert int(res.flags[0, 0, 0]) == 0 and sd < 0.1
    assert abs(err) < 3.0 * sd


def _fast_one_pixel(t: list[int], p: list[int], c_on: float, c_off: float
                    ) -> tuple[float, float, int, dict[str, int]]:
    """One IMX636 pixel's fast fit on its default rig, thresholds held at ``c_on``,
    ``c_off`` (stated 0.005): ``(ln L, its deviation, flag, the run's stats)``."""
    pri = ml.thresholds_prior(IMX636, width=1, height=1, c_on=np.array([[c_on]]),
                              c_off=np.array([[c_off]]), sigma=0.005)
    stats: dict[str, int] = {}
    rig = default_rig("imx636")
    g, sd, _, _, flag, _ = ml._run(ml.cached_model(rig, IMX636, window_us=rig.ramp_us),
                                   np.array([0, len(t)]), np.array(t, np.int32),
                                   np.array(p, np.int8), 1, pri, None, None, False, width=1,
                                   fast=True, stats=stats)
    return float(g[0]), float(sd[0]), int(flag[0]), stats


def test_fast_fit_again_from_a_likelier_point() -> None:
    # 0.766 lux (the bench's speed cycle, row 291, column 191; thresholds each 1 % off,
    # stated 0.005): Newton's method from the net change's start stops in another optimum
    # that one of the check's points beats; made again from that point it finds the
    # truth's, which the check then keeps: no full fit
    t = [19048, 22183, 26728, 32892, 39161, 45241, 53002, 71629, 72880, 73858, 74761, 75718,
         77128, 80029, 110376, 113910, 119001, 125812, 131699, 138226, 144254, 161482,
         162863, 163926, 164794, 165717, 167143, 170416]
    p = [-1] * 7 + [1] * 7 + [-1] * 6 + [1] * 8
    g, sd, flag, stats = _fast_one_pixel(t, p, 0.25481, 0.27476)
    assert stats == {"full": 0, "retried": 1}
    assert flag == 0 and sd < 0.1
    assert abs(g - math.log(0.765888)) < 3.0 * sd


def test_fast_fit_converges_where_newtons_method_cycles() -> None:
    # 17.7 lux (the bench's speed cycle, row 206, column 920; thresholds each 1 % off,
    # stated 0.005): nine events, the optimum between two of the table's rows, where the
    # curvature jumps; Newton's steps alone cycle about it for the fit's twelve passes
    # (the fit was then made in full), the bracket's middle ends the cycle
    t = [24157, 30064, 72138, 74286, 113766, 119547, 121272, 161823, 164054]
    p = [-1, -1, 1, 1, -1, -1, 1, 1, 1]
    g, sd, flag, stats = _fast_one_pixel(t, p, 0.25517, 0.25540)
    assert stats == {"full": 0, "retried": 0}
    assert flag == 0 and sd < 0.1
    assert abs(g - math.log(17.747497)) < 3.0 * sd


def _fast_checker(sensor: SensorParams, truth: float, seed: int = 1
                  ) -> tuple[ml.MlModel, Callable[[list[float], bool], tuple[np.ndarray,
                                                                           np.ndarray]],
                             float, int, Callable[..., np.ndarray],
                             Callable[[float], tuple[float, float, float]]]:
    """The fast fit's check (``ml._fast_check``) on one simulated flat pixel of radiance
    ``truth``, with the imx636 preset's designed rig: ``check(points, prune)`` gives the
    points as read (probes at their grid rows) and their ``-2 ln L``; then the least the
    events can add to such a sum (``ml._least_terms``), how many they are, and
    ``newton(g, robust, stride=1, hi=n)``: the fast fit's Newton sums at ``g``
    (``ml._fast_pass``) over the first ``hi`` events, every ``stride``-th, with the check's
    sum kept; ``coarse(g)``: the coarse start from ``g`` (``ml._fast_coarse``), the fit
    over every event from it (``ml._fast_newton``) and that fit's deviation."""
    rig = default_rig("imx636")
    m = ml.ml_model(rig, sensor)
    drawn = draw_thresholds(sensor, width=1, height=1, rng=np.random.default_rng(seed))
    ev = simulate(flat_field(width=1, height=1, radiance=truth), rig=rig, sensor=sensor,
                  n_cycles=1, rng=seed, sensor_seed=seed, thresholds=drawn).events
    ev = ev[ev["t"] < rig.cycle_starts_us(1)[0] + m.window_us]
    n = ev.size
    assert n >= 10
    tt = (ev["t"] - rig.cycle_starts_us(1)[0]).astype(np.int32)
    pp = ev["p"].astype(np.int8)
    c_on, c_off = (float(c[0, 0]) for c in drawn)
    sl = np.empty((n, 8))
    ml._read_slots(m.mode, 0, n, tt, m.dead, m.exact, m.locate, np.int64(m.window_us), sl)
    tq2 = m.jitter_us ** 2 + m.res_us ** 2 / 12.0
    eq2 = m.res_us ** 2 / 12.0 + (m.jitter_us ** 2 if m.dead else 0.0)
    su, mu_u = ml._u_prior(c_on, c_off, 0.0)
    wmax = np.int64(m.window_us)
    least = ml._least_slots(m.mode, wmax, m.exact, m.locate, ml._steepest_slopes(m.rows),
                            m.reset_sigma ** 2, tq2, m.noise_rate_per_us)

    def check(gs: list[float], prune: bool) -> tuple[np.ndarray, np.ndarray]:
        g = np.array(gs, dtype=np.float64)
        k = g.size
        nl = np.empty(k)
        ml._fast_check(m.mode, g, k, 0, n, sl, pp, m.dead, m.reset_sigma ** 2, tq2, eq2,
                       m.noise_rate_per_us, m.exact, m.v0[0], m.v0[1], m.rows, m.g0,
                       m.dlog, m.locate, c_on, c_off, mu_u, su * su, nl, False, prune,
                       least, tt, wmax, np.empty(n + 1))
        return g, nl

    common = (sl, pp, m.dead, m.reset_sigma ** 2, tq2, eq2, m.noise_rate_per_us, m.exact,
              m.v0[0], m.v0[1], m.rows, m.g0, m.dlog, m.locate, c_on, c_off, mu_u, su * su)

    def newton(g: float, robust: bool, stride: int = 1, hi: int = n) -> np.ndarray:
        acc = np.zeros(7)
        ml._fast_pass(m.mode, g, 0, hi, *common, robust, True, acc, stride)
        return acc

    def coarse(g: float) -> tuple[float, float, float]:
        acc = np.zeros(7)
        gc = ml._fast_coarse(m.mode, g, 0, n, *common, m.g_lo, m.g_hi, acc)
        fit, converged, _ = ml._fast_newton(m.mode, gc, 0, n, *common, m.g_lo, m.g_hi, acc)
        assert converged
        return gc, fit, 1.0 / math.sqrt(acc[1])

    tail = np.empty(n + 1)
    ml._least_terms(0, n, tt, wmax, least, tail)
    return m, check, float(tail[0]), n, newton, coarse


@pytest.mark.parametrize("refractory_us", [0.0, 40.0])
def test_fast_check_reads_its_points_at_table_rows_as_the_model_there(
        refractory_us: float) -> None:
    # the check's points after the first are moved to the table's nearest grid rows and
    # read from that row alone; the first (the fit's own) is interpolated between two.
    # At a row both readings are the same model: the same -2 ln L to rounding, with a
    # dead time and without one
    sensor = get_preset("ideal").with_(name="kind", cutoff_hz=3000.0,
                                       refractory_us=refractory_us,
                                       reset_noise_sigma=0.01 if refractory_us else 0.0)
    truth = 1.35
    m, check, _, _, _, _ = _fast_checker(sensor, truth)
    assert m.mode == 1 and m.dead == (refractory_us > 0)
    near = round((math.log(truth) - m.g0) / m.dlog)  # the row nearest L
    for j in range(near - 15, near + 16):  # g0 + j dlog floors to j - 1 for some
        at = m.g0 + j * m.dlog
        g, nl = check([at, at], False)
        assert g[1] == pytest.approx(at, abs=1e-12)
        assert nl[1] == pytest.approx(nl[0], rel=1e-9, abs=1e-9), j
    row = m.g0 + near * m.dlog
    g, nl = check([row, row, row - 0.25], False)
    # a point between rows goes to the nearest, and reads there as the fit's own would
    moved = g[2]
    assert abs(moved - (row - 0.25)) <= 0.5 * m.dlog + 1e-12
    assert (moved - m.g0) / m.dlog == pytest.approx(round((moved - m.g0) / m.dlog), abs=1e-9)
    _, nl2 = check([moved], False)
    assert nl[2] == pytest.approx(nl2[0], rel=1e-9, abs=1e-9)
    assert nl[2] != pytest.approx(nl[0], abs=1.0)  # a quarter away is another likelihood


@pytest.mark.parametrize("refractory_us", [0.0, 40.0])
def test_fast_fit_newton_pass_keeps_the_checks_own_sum(refractory_us: float) -> None:
    # the check takes the fit's -2 ln L from the Newton pass that converged: that pass's
    # kept sum is the check's own at the same point (a point between grid rows, read
    # interpolated by both), with the outlier weights or without, with a dead time or
    # without; and it changes with the point
    sensor = get_preset("ideal").with_(name="kind", cutoff_hz=3000.0,
                                       refractory_us=refractory_us,
                                       reset_noise_sigma=0.01 if refractory_us else 0.0,
                                       jitter_sigma_us=2.0 if refractory_us else 0.0)
    truth = 20.0
    m, check, _, _, newton, _ = _fast_checker(sensor, truth, seed=2)
    assert m.dead == (refractory_us > 0)
    sums = []
    for d in (-0.3, -0.013, 0.0, 0.021, 0.4):
        g = math.log(truth) + d
        assert (g - m.g0) / m.dlog % 1.0 > 1e-3  # between rows
        own = check([g], False)[1][0]
        for robust in (False, True):
            kept = newton(g, robust)[6]
            assert kept == pytest.approx(own, rel=1e-10, abs=1e-9), (d, robust)
        sums.append(own)
    assert min(sums[0], sums[-1]) > min(sums[1:4]) + 1.0


def _dead_sensor() -> SensorParams:
    """A sensor whose events each stand alone in the likelihood (a dead time)."""
    return get_preset("ideal").with_(name="kind", cutoff_hz=3000.0, refractory_us=40.0,
                                     reset_noise_sigma=0.01, jitter_sigma_us=2.0)


def test_fast_pass_with_a_stride_sums_every_strided_events_terms() -> None:
    # with a dead time each event's term stands alone: a pass on every s-th event sums
    # the terms of events 0, s, 2s, ..., each the difference of two passes over the
    # events up to it and up to the one before
    m, _, _, n, newton, _ = _fast_checker(_dead_sensor(), 2000.0, seed=4)
    assert m.dead and n >= 40
    g = math.log(2000.0) + 0.05
    prefix = np.array([newton(g, False, 1, k) for k in range(n + 1)])
    terms = np.diff(prefix, axis=0)
    sums = [0, 1, 2, 3, 5, 6]  # the Newton sums, the chi-square, -2 ln L (4: max z^2)
    for s in (1, 3, 7):
        got = newton(g, False, s)
        want = terms[::s]
        assert got[sums] == pytest.approx(want[:, sums].sum(axis=0), rel=1e-9, abs=1e-9), s
        # without outlier weights an event's chi-square term is its z^2
        assert got[4] == pytest.approx(np.max(want[:, 5]), rel=1e-9)
        assert s == 1 or got[1] < prefix[-1, 1] * 0.6  # fewer events, less curvature


@pytest.mark.parametrize("start", [-0.6, 0.6])
def test_fast_coarse_start_lands_within_a_few_deviations_of_the_fit(start: float) -> None:
    # the coarse start (Newton on every n // 16-th event, then one step on every
    # quarter-stride ...) brings a start 0.6 off in ln L (the net change's median error)
    # to within _KEEP_STEP deviations of the fit over all events, and the fit from there
    # is the fit from the truth
    m, _, _, n, _, coarse = _fast_checker(_dead_sensor(), 2000.0, seed=4)
    assert m.dead and n // ml._COARSE_EVENTS >= 2
    g = math.log(2000.0)
    gc, fit, sd = coarse(g + start)
    assert abs(gc - (g + start)) > 0.3  # it moved
    assert abs(gc - fit) < ml._KEEP_STEP * sd
    _, fit_truth, _ = coarse(g)
    assert fit == pytest.approx(fit_truth, abs=0.2 * sd)
    assert abs(fit - g) < 4.0 * sd
    # without a dead time, no subsets: the start is left as it is
    m2, _, _, n2, _, coarse2 = _fast_checker(get_preset("ideal").with_(
        name="kind", cutoff_hz=3000.0), 2000.0, seed=4)
    assert not m2.dead and n2 // ml._COARSE_EVENTS >= 2
    assert coarse2(g + start)[0] == g + start



@pytest.mark.parametrize("truth", [0.6, 20.0, 3000.0, 1e5])
def test_fast_check_leaves_out_only_points_it_can_bound_above_the_fit(truth: float) -> None:
    # pruned, a probe leaves the check's pass once the least its remaining events can add
    # keeps it above the fit's -2 ln L less the margin: the bound it reports is at most its
    # whole sum and at least that floor, and its decision is the unpruned one
    sensor = get_preset("ideal").with_(name="kind", cutoff_hz=3000.0, refractory_us=40.0,
                                       reset_noise_sigma=0.01, jitter_sigma_us=2.0)
    _, check, least, n, _, _ = _fast_checker(sensor, truth, seed=3)
    # the fit's point: the likeliest of a scan 0.02 apart about the truth
    scan = [math.log(truth) + 0.02 * i for i in range(-50, 51)]
    # the least the events can add: below every point's sum, the fit's by less than the
    # events' chi-square and a few units each (their timing noise at its least)
    nls = [check([x], False)[1][0] for x in scan]
    assert least <= min(nls)
    assert least >= min(nls) - 5.0 * n
    g = scan[int(np.argmin(nls))]
    points = [g] + [g + d for d in ml._FAST_PROBES]
    _, whole = check(points, False)
    _, pruned = check(points, True)
    assert pruned[0] == whole[0]
    floor = whole[0] - ml._PROBE_MARGIN
    left = 0
    for k in range(1, len(points)):
        if pruned[k] == whole[k]:
            continue
        left += 1
        assert floor <= pruned[k] <= whole[k] + 1e-9 * abs(whole[k]), k
        assert (pruned[k] < floor) == (whole[k] < floor)
    assert left >= 1  # at least the point 2.0 below leaves early


def test_probe_terms_bound_the_exact_terms_from_below() -> None:
    # the check's probes sum a lower bound of each event's -2 ln(f + lambda) without the
    # exponential: never above the exact term (so a probe left out is one the exact sum
    # would leave out), within 1e-3 of it where f and lambda lie far apart, and within
    # 0.6 where they meet; its logarithm's bound within 8.9e-4 below ln x
    @nb.njit
    def logs(x: np.ndarray) -> np.ndarray:
        out = np.empty_like(x)
        for i in range(x.size):
            out[i] = ml._log_below(x[i])
        return out

    @nb.njit(error_model="numpy")  # a zero slope divides by zero, as in the fits
    def terms(z2: np.ndarray, var: np.ndarray, slope: np.ndarray, lam: float
              ) -> tuple[np.ndarray, np.ndarray]:
        lb = -2.0 * math.log(lam) if lam > 0.0 else np.inf
        below = np.empty_like(z2)
        exact = np.empty_like(z2)
        for i in range(z2.size):
            below[i] = ml._term_below(z2[i], var[i], slope[i], lb)
            f = ml._time_density(z2[i], slope[i], 1.0 / var[i])
            exact[i] = -2.0 * math.log(max(f + lam, ml._DENSITY_FLOOR))
        return below, exact

    gen = np.random.default_rng(0)
    x = np.exp(gen.uniform(-700.0, 700.0, 200_000))
    x = np.concatenate([x, [1.0, 2.0, np.nextafter(2.0, 0.0), 0.5, 1e-300, 1e300]])
    gap = np.log(x) - logs(x)
    assert gap.min() >= 0.0
    assert gap.max() <= 8.9e-4
    # every mantissa: the cubic below ln m on a grid finer than its slope can turn on
    m = np.linspace(1.0, 2.0, 1_000_001)
    assert (np.log(m) - logs(m)).min() >= 1.9e-6
    assert logs(np.array([np.inf]))[0] == pytest.approx(1024 * math.log(2.0), abs=1e-3)
    n = 200_000
    z2 = gen.exponential(4.0, n) ** 2
    var = np.exp(gen.uniform(-8.0, 8.0, n))
    slope = np.exp(gen.uniform(-6.0, 4.0, n)) * gen.choice([-1.0, 1.0], n)
    slope[:10] = 0.0  # no density at all: lambda's term
    for lam in (0.0, 1e-9, 1e-3, 0.3):
        below, exact = terms(z2, var, slope, lam)
        gap = exact - below
        assert gap.min() >= 0.0, lam
        # without lambda, a zero slope's term (the density's floor) is bounded by 710
        assert gap[10 if lam == 0.0 else 0:].max() <= 0.6, lam
        if lam > 0.0:
            with np.errstate(divide="ignore"):
                a = z2 + np.log(2.0 * math.pi * var / slope ** 2)  # -2 ln f
            far = np.abs(a + 2.0 * math.log(lam)) > 45.0
            assert far.sum() > 1000
            assert gap[far].max() <= 1e-3, lam
        else:
            assert gap[10:].max() <= 1e-3


@pytest.mark.parametrize(("cutoff_hz", "refractory_us"),
                         [(0.0, 0.0), (0.0, 40.0), (3000.0, 0.0), (3000.0, 40.0)])
def test_fast_fit_agrees_with_the_full_fit_for_each_kind_of_model(
        cutoff_hz: float, refractory_us: float) -> None:
    # the fast fit runs one loop per kind of model (exact waveforms or the photoreceptor's
    # table, with or without a dead time). With a dead time (reset noise 0.01), its
    # estimate lies where the full fit's optimum does, to a small share of the deviation.
    # Without one, and without reset noise (which would make it a chain, below), the
    # reference walks by the threshold exactly: both fits then recover L to the timestamp
    # quantum's share
    rig = default_rig("ideal")
    dead = refractory_us > 0
    sensor = get_preset("ideal").with_(name="kind", cutoff_hz=cutoff_hz,
                                       refractory_us=refractory_us,
                                       reset_noise_sigma=0.01 if dead else 0.0)
    model = ml.ml_model(rig, sensor)
    assert (model.mode, model.dead) == (int(cutoff_hz > 0), dead)
    levels = np.geomspace(3.0, 3.0e4, 5)
    w = 24
    truth = _scene(levels, w)
    rec = simulate(truth, rig=rig, sensor=sensor, n_cycles=1, rng=5, sensor_seed=1)
    pri = ml.thresholds_prior(sensor, width=w, height=levels.size, sigma=0.001)
    fast, full = (ml.estimate(rec.events, width=w, height=levels.size,
                              starts_us=rig.cycle_starts_us(1), model=model, priors=pri,
                              fast=f) for f in (True, False))
    assert np.all(fast.flags[0] == 0) and np.all(full.flags[0] == 0)
    if not dead:
        for res in (fast, full):
            np.testing.assert_allclose(res.radiance[0], truth, rtol=1e-3)
        return
    d = np.abs(np.log(fast.radiance[0] / full.radiance[0]))
    assert np.mean(d <= 0.25 * full.sigma_log[0]) >= 0.9
    z = np.log(fast.radiance[0] / truth) / fast.sigma_log[0]
    assert np.mean(np.abs(z) < 3.0) >= 0.9


@pytest.mark.parametrize("fast", [False, True])
def test_reset_noise_without_a_dead_time_is_a_chain_with_honest_deviations(
        fast: bool) -> None:
    # no dead time, no jitter, reset noise 0.01: each reference is the level crossed plus
    # a fresh draw, so a walk by the threshold would accumulate the draws along it (its
    # errors correlated from event to event, taken as independent: with the walk the
    # RMS of the error over the stated deviation read 1.1 to 3.5 over these levels, and
    # the spread was up to twice the chain's). The chain conditional on each previous
    # event states deviations that the errors bear out
    rig = default_rig("ideal")
    sensor = get_preset("ideal").with_(name="reset", reset_noise_sigma=0.01)
    assert sensor.refractory_us == 0 and sensor.jitter_sigma_us == 0
    model = ml.ml_model(rig, sensor)
    assert model.dead
    levels = np.geomspace(3.0, 3.0e4, 5)
    w = 60
    truth = _scene(levels, w)
    rec = simulate(truth, rig=rig, sensor=sensor, n_cycles=1, rng=5, sensor_seed=1)
    pri = ml.thresholds_prior(sensor, width=w, height=levels.size, sigma=1e-6)
    res = ml.estimate(rec.events, width=w, height=levels.size,
                      starts_us=rig.cycle_starts_us(1), model=model, priors=pri, fast=fast)
    assert np.all(res.flags[0] == 0)
    z = np.log(res.radiance[0] / truth) / res.sigma_log[0]
    for row in z:
        assert 0.75 < float(np.sqrt(np.mean(row ** 2))) < 1.3


def test_fast_fit_needs_thresholds_calibrated_or_learned(tmp_path) -> None:
    from typer.testing import CliRunner

    from asynhdr.cli import _register, app

    rig = default_rig("imx636")
    rec = simulate(np.full((2, 3), 50.0), rig=rig, sensor=IMX636, n_cycles=1, rng=0)
    with pytest.raises(ValueError, match="calibrated"):
        ml.reconstruct_ml(rec, CycleWindows(rig.cycle_starts_us(1), rig.ramp_us), rig=rig,
                          fast=True, learn=False)
    # the command line: without --calibration, the thresholds are learned, then held
    _register()
    r = CliRunner().invoke(app, ["simulate", "flat:300", "-o", str(tmp_path / "f.raw"),
                                 "--width", "4", "--height", "2", "--preset", "imx636",
                                 "--n-cycles", "2", "--rig-out", str(tmp_path / "rig.toml")])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["reconstruct", str(tmp_path / "f.raw"), "-o",
                                 str(tmp_path / "img"), "--method", "ml", "--rig",
                                 str(tmp_path / "rig.toml"), "--fast", "--formats", "exr"])
    assert r.exit_code == 0, r.output
    said = " ".join(r.output.split())
    assert "--fast fitted in full the pixels whose thresholds were not yet learned" in said
    assert "in full (thresholds not yet learned, or a failed check" in said
    from asynhdr.io.images import read_metadata

    meta = read_metadata(sorted((tmp_path / "img").glob("*[0-9].exr"))[-1])
    assert "learned" in str(meta.get("ml_fit"))


def test_fast_fit_holds_thresholds_once_learned() -> None:
    # without a calibration the fast fit is the full fit until a pixel's thresholds are
    # learned to FAST_HOLD_SD; then it holds them, and the radiance stays within the
    # stated uncertainty
    rig = default_rig("imx636")
    sensor = IMX636.with_(name="imx636q", **QUIET)
    levels = np.geomspace(30.0, 3.0e4, 7)
    w = 40
    n = 4
    rec = simulate(_scene(levels, w), rig=rig, sensor=sensor, n_cycles=n, rng=3,
                   sensor_seed=1)
    starts = rig.cycle_starts_us(n)
    learners = {True: ml.LearnedThresholds(), False: ml.LearnedThresholds()}
    out: dict[bool, list[dict]] = {True: [], False: []}
    held = np.zeros(0)
    for c in range(n):
        for fast in (True, False):
            prior = learners[fast].priors(sensor, width=w, height=levels.size)
            fl: dict = {}
            fl["radiance"] = ml.reconstruct_ml(
                rec, CycleWindows(starts[c:c + 1], rig.ramp_us), rig=rig, sensor=sensor,
                learner=learners[fast], fast=fast, out=fl)
            out[fast].append(fl)
            if fast and c == n - 1:
                learned = (prior[2] <= ml.FAST_HOLD_SD) & (prior[3] <= ml.FAST_HOLD_SD)
                held = learned & (fl["c_on"][0].ravel() == prior[0].astype(np.float32))
    # the first cycle: nothing learned, every pixel fitted in full, as by the full fit
    for key in ("c_on", "sigma_log"):
        np.testing.assert_array_equal(out[True][0][key], out[False][0][key])
    assert out[True][0]["full_fits"][0] == w * levels.size
    assert "full_fits" not in out[False][0]
    # the last: most pixels hold what they learned
    assert held.mean() >= 0.5
    assert out[True][-1]["full_fits"][0] == np.count_nonzero(~held)
    fl = out[True][-1]
    assert np.all(fl["flags"][0] == 0)
    z = (np.log(fl["radiance"][0]) - np.log(_scene(levels, w))) / fl["sigma_log"][0]
    assert np.mean(np.abs(z) < 3.0) >= 0.95
    assert 0.6 < float(np.std(z)) < 1.5
    assert abs(float(np.median(z))) < 0.3
    np.testing.assert_allclose(np.mean(fl["radiance"][0], axis=1), levels, rtol=0.02)


@pytest.mark.parametrize("threads", [1, 2])
def test_grouping_by_pixel_puts_each_pixels_events_in_time_order(threads: int) -> None:
    """The counting sort against a stable sort by pixel, then time, on events out of time
    order (with ties, whose stream order is kept), some outside the window, on a sensor
    whose pixel count is no multiple of the buckets; a sorted stream's pixels keep their
    order, and one pixel's events stepping back are sorted."""
    import numba

    gen = np.random.default_rng(5)
    width, height, n = 346, 260, 200_000
    ev = np.zeros(n, EVENT_DTYPE)
    ev["x"] = gen.integers(0, width, n)
    ev["y"] = gen.integers(0, height, n)
    ev["p"] = gen.choice([-1, 1], n)
    ev["t"] = gen.integers(0, 50_000, n)  # unsorted, with ties
    start, window = 10_000, 30_000
    previous = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        off, t, p = ml.group_by_pixel(ev, width=width, height=height, start_us=start,
                                      window_us=window)
    finally:
        numba.set_num_threads(previous)
    kept = ev[(ev["t"] >= start) & (ev["t"] < start + window)]
    pix = kept["y"].astype(np.int64) * width + kept["x"]
    order = np.lexsort((kept["t"], pix))  # stable: ties keep the stream's order
    assert t.dtype == np.int32
    np.testing.assert_array_equal(t, kept["t"][order] - start)
    np.testing.assert_array_equal(p, kept["p"][order])
    np.testing.assert_array_equal(np.diff(off), np.bincount(pix, minlength=width * height))
    assert off[0] == 0 and off[-1] == kept.size
    # many events a pixel, most of them tied: a pixel sorted whole, ties in stream order
    few = np.zeros(20_000, EVENT_DTYPE)
    few["x"] = gen.integers(0, 4, few.size)
    few["y"] = gen.integers(0, 4, few.size)
    few["p"] = gen.choice([-1, 1], few.size)
    few["t"] = gen.integers(0, 100, few.size)
    off, t, p = ml.group_by_pixel(few, width=4, height=4, start_us=0, window_us=100)
    order = np.lexsort((few["t"], few["y"].astype(np.int64) * 4 + few["x"]))
    np.testing.assert_array_equal(t, few["t"][order])
    np.testing.assert_array_equal(p, few["p"][order])
    with pytest.raises(ValueError, match="window"):
        ml.group_by_pixel(ev, width=width, height=height, start_us=0, window_us=2**31)


def test_a_vague_fit_whose_plateau_leaves_the_range_holds_the_bound() -> None:
    # ln L range (0, 10); vague fits (deviation >= 1) within one deviation of a bound
    # become fits at that bound; the others, and fits without curvature, stay vague
    g = np.array([9.5, 0.4, 5.0, 9.5, 5.0, 8.0, 9.5])
    sd = np.array([1.2, 1.1, 1.5, np.inf, 6.0, 1.5, 0.3])
    flags = np.array([ml.FLAG_UNINFORMED] * 6 + [0], np.uint8)
    ml._beyond_range(g, sd, flags, 0.0, 10.0)
    np.testing.assert_array_equal(g, [10.0, 0.0, 5.0, 9.5, 5.0, 8.0, 9.5])
    u, o = ml.FLAG_UNINFORMED, ml.FLAG_OUT_OF_RANGE
    np.testing.assert_array_equal(flags, [o, o, u, u, u, u, 0])
