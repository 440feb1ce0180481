"""Rig files (round trip, errors), calibration from data (thresholds from flat fields,
the calibration file, panel sweeps, the response), and the design's prediction."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from asynhdr.calib import (
    Calibration,
    fit_panel_curves,
    fit_response,
    read_sweep_csv,
    simulate_sweep,
    thresholds_from_flats,
    write_sweep_csv,
)
from asynhdr.design import DESIGNED, default_rig, predict
from asynhdr.io.calibration import read_calibration, write_calibration
from asynhdr.io.rigfile import read_rig, write_rig
from asynhdr.panel import tn_panel
from asynhdr.rig import Rig
from asynhdr.scene import flat_field
from asynhdr.sensor.params import get_preset
from asynhdr.simulate import draw_thresholds, simulate


@pytest.mark.parametrize("rig", [
    Rig(l_const=42.0, t1_shape="exponential", k_lens=0.5, period_us=40_000),
    default_rig("imx636"),
    Rig(l_const=10.0, panel="tn", period_us=20_000),
], ids=["paper", "designed", "tn-panels"])
def test_rig_file_round_trip(tmp_path: Path, rig: Rig) -> None:
    sensor = get_preset("imx636").with_(name="imx636", refractory_us=50.0)
    p = write_rig(tmp_path / "rig.toml", rig, sensor=sensor, made={"by": "test"})
    f = read_rig(p)
    assert f.rig.period_us == rig.period_us and f.rig.l_const == rig.l_const
    assert f.rig.k_lens == rig.k_lens and f.rig.ramp_fraction == rig.ramp_fraction
    w1, w2 = rig.waveforms()
    v1, v2 = f.rig.waveforms()
    # the transmitted waveforms, exactly (repr of float64 round-trips)
    np.testing.assert_array_equal(w1(np.linspace(0, 1, 997)), v1(np.linspace(0, 1, 997)))
    np.testing.assert_array_equal(w2(np.linspace(0, 1, 997)), v2(np.linspace(0, 1, 997)))
    assert f.sensor is not None
    assert f.sensor.refractory_us == 50.0
    assert f.sensor.threshold_sigma == sensor.threshold_sigma
    assert f.made == {"by": "test"}
    assert f.radiance_unit == "lux"
    if rig.design_range is not None:
        assert f.rig.design_range == rig.design_range
    # a real panel's rig comes back as its transmitted waveforms: the file keeps the
    # working range they were made for (their extremes would give another), so automatic
    # exposure centres a scene on the same radiance
    assert f.rig.working_range() == pytest.approx(rig.working_range(), rel=1e-12)
    assert f.rig.mid_radiance() == pytest.approx(rig.mid_radiance(), rel=1e-12)


def test_mid_radiance_where_automatic_exposure_centres_a_scene() -> None:
    # the paper's rig: L_const sqrt(CR_1) = 10 x sqrt(1000) = 316.2 lux; a designed rig:
    # the middle of the range it was designed for, sqrt(0.1 x 316,228) = 177.8 lux,
    # whatever its L_const; the same rig without that range: the middle of L_const T2 / T1
    # over the ramp (both panels 1000:1, both to their floors: L_const itself)
    assert Rig(l_const=10.0).mid_radiance() == pytest.approx(10.0 * math.sqrt(1000.0))
    rig = default_rig("imx636")
    assert rig.design_range == pytest.approx((0.1, 10 ** 5.5))
    assert rig.mid_radiance() == pytest.approx(math.sqrt(0.1 * 10 ** 5.5))
    assert Rig.from_metadata(rig.to_metadata()).design_range == rig.design_range
    bare = dataclasses.replace(rig, design_range=None)
    assert bare.mid_radiance() == pytest.approx(rig.l_const, rel=1e-9)
    for bad in ((5.0, 1.0), (0.0, 1.0), (1.0,), "wide"):
        with pytest.raises(ValueError, match="design_range"):
            Rig(design_range=bad)  # type: ignore[arg-type]


def test_rig_file_errors_name_file_and_field(tmp_path: Path) -> None:
    p = tmp_path / "bad.toml"
    p.write_text('format = "asynhdr-rig"\nversion = 1\n[rig]\nl_const = 5.0\n')
    with pytest.raises(ValueError, match=r"bad.toml: rig.period_us: missing"):
        read_rig(p)
    p.write_text('format = "asynhdr-rig"\nversion = 1\n[rig]\nperiod_us = 50000\n'
                 'l_const = 5.0\nlconst = 3\n')
    with pytest.raises(ValueError, match=r"bad.toml: \[rig\]: unknown keys \['lconst'\]"):
        read_rig(p)
    p.write_text('format = "asynhdr-rig"\nversion = 1\n[rig]\nperiod_us = 50000\n'
                 'l_const = -5.0\n')
    with pytest.raises(ValueError, match=r"l_const must be positive"):
        read_rig(p)
    p.write_text('format = "asynhdr-rig"\nversion = 1\n[rig]\nperiod_us = 50000\n'
                 'l_const = 5.0\ndesign_range = 3.0\n')
    with pytest.raises(ValueError, match=r"bad.toml: rig.design_range: expected"):
        read_rig(p)
    p.write_text('format = "something"\n')
    with pytest.raises(ValueError, match=r"format"):
        read_rig(p)


def test_thresholds_from_flats_recover_simulated_thresholds(caplog) -> None:
    # flat fields 30x brighter (ON events) and 30x darker (OFF events) than L_const, 2
    # captures x 4 cycles each, IMX636 model with all its noise, captured through a
    # region of interest (the 384 pixels read alone: the readout keeps up): the per-pixel
    # ON and OFF thresholds come back within 0.005 (RMS; the mismatch is 0.05), and 90 %
    # of the pixels within three stated errors
    rig = default_rig("imx636")
    sensor = get_preset("imx636")
    roi = sensor.region_of_interest()
    w, h = 24, 16
    rads = [rig.l_const * 30, rig.l_const / 30] * 2
    caps = [simulate(flat_field(width=w, height=h, radiance=r), rig=rig, sensor=roi,
                     n_cycles=4, rng=i, sensor_seed=7) for i, r in enumerate(rads)]
    with caplog.at_level("WARNING", logger="asynhdr.calib"):
        cal = thresholds_from_flats(caps, radiance=rads, rig=rig, sensor=sensor)
    assert "readout delayed" not in caplog.text
    c_on, c_off = draw_thresholds(sensor, width=w, height=h, rng=np.random.default_rng(7))
    assert cal.c_on is not None and cal.c_off is not None
    assert cal.sigma_on is not None and cal.sigma_off is not None
    for est, true, err in ((cal.c_on, c_on, cal.sigma_on), (cal.c_off, c_off, cal.sigma_off)):
        e = est - true
        assert float(np.sqrt(np.mean(e ** 2))) < 0.005
        assert float(np.mean(np.abs(e) < 3 * err + 1e-3)) >= 0.9
        assert float(np.std(true)) > 0.03  # the mismatch it removes
        # the stated errors are the errors: hardly a pixel beyond three of them, none
        # beyond five (each pixel's scatter of six cycles alone put one at 5.6)
        z = e / err
        assert float(np.mean(np.abs(z) > 3)) < 0.01 and float(np.abs(z).max()) < 5.0
    assert cal.how["cycles"] == 12  # the first cycle of each capture is left out
    # the same flat field on the whole array (these pixels' share of its readout): every
    # pixel fires at once, the queue delays the events, and the calibration says so
    whole = simulate(flat_field(width=w, height=h, radiance=rads[0]), rig=rig, sensor=sensor,
                     n_cycles=2, rng=0, sensor_seed=7)
    assert whole.metadata["readout"]["max_delay_us"] > 10.0
    with caplog.at_level("WARNING", logger="asynhdr.calib"):
        thresholds_from_flats([whole], radiance=rads[0], rig=rig, sensor=sensor)
    assert "readout delayed" in caplog.text


def test_moderated_variances_are_not_small_by_chance() -> None:
    # 4,000 pixels of one true variance, each estimated from 3 samples (2 degrees of
    # freedom): alone, about 1 % of the estimates are below a tenth of the truth (chi-square
    # with 2 degrees: P(s2 < 0.1) = 1 - exp(-0.1) = 9.5 %, below 0.01: 1 %); moderated by the
    # others they all lie near it. Pixels of two true variances (1 and 9) keep them apart.
    from asynhdr.calib import moderated_variance

    rng = np.random.default_rng(3)
    dof = np.full(4000, 2.0)
    s2 = rng.chisquare(2, 4000) / 2.0
    assert 0.005 < float(np.mean(s2 < 0.01)) < 0.02
    m = moderated_variance(s2, dof, np.ones(4000, bool))
    assert float(m.min()) > 0.7 and float(m.max()) < 1.4
    assert float(np.mean(m)) == pytest.approx(1.0, abs=0.1)
    true = np.where(np.arange(4000) < 2000, 1.0, 9.0)
    s2 = true * rng.chisquare(20, 4000) / 20.0
    m = moderated_variance(s2, np.full(4000, 20.0), np.ones(4000, bool))
    assert float(np.median(m[:2000])) == pytest.approx(1.0, rel=0.2)
    assert float(np.median(m[2000:])) == pytest.approx(9.0, rel=0.2)


def test_flat_fields_find_the_dead_pixels_and_ml_fills_them() -> None:
    # an IMX636 with 3 % dead pixels: the flat fields' calibration names exactly the
    # simulator's dead pixels; ml on a flat scene by the same sensor, with the map, gives
    # each the median of its neighbours (the flat's radiance, where every other estimate
    # lies) and flags it; the other pixels do not change. Without the map ml takes the
    # same silent pixels for dead itself (at 2000 lux a working pixel swings far past both
    # thresholds) and fills them the same way
    from asynhdr.ml import FLAG_FILLED, FLAG_NO_EVENTS
    from asynhdr.reconstruct import reconstruct
    from asynhdr.sensor.noise import draw_defects

    rig = default_rig("imx636")
    sensor = get_preset("imx636").with_(dead_pixel_fraction=0.03)
    roi = sensor.region_of_interest()
    w, h = 16, 12
    rads = [rig.l_const * 30, rig.l_const / 30]
    caps = [simulate(flat_field(width=w, height=h, radiance=r), rig=rig, sensor=roi,
                     n_cycles=3, rng=i, sensor_seed=5) for i, r in enumerate(rads)]
    cal = thresholds_from_flats(caps, radiance=rads, rig=rig, sensor=sensor)
    g = np.random.default_rng(5)
    draw_thresholds(sensor, width=w, height=h, rng=g)  # the simulator's order of draws
    truth = np.zeros(w * h, dtype=bool)
    truth[draw_defects(sensor, n_pixels=w * h, rng=g).dead] = True
    assert cal.defects is not None
    assert truth.sum() == 6
    np.testing.assert_array_equal(cal.defects.ravel(), truth)
    assert cal.how["dead_pixels"] == 6
    lum = 2000.0
    rec = simulate(flat_field(width=w, height=h, radiance=lum), rig=rig, sensor=roi,
                   n_cycles=2, rng=9, sensor_seed=5)
    out: dict = {}
    out_plain: dict = {}
    plain = reconstruct(rec, method="ml", ml_options={"thresholds": cal.threshold_maps(),
                                                      "out": out_plain})[-1]
    filled = reconstruct(rec, method="ml", ml_options={
        "thresholds": cal.threshold_maps(), "defects": cal.defects, "out": out})[-1]
    dead = cal.defects
    assert np.isfinite(plain).all()
    np.testing.assert_array_equal(filled, plain)
    np.testing.assert_array_equal(out_plain["flags"][-1], out["flags"][-1])
    assert np.all(np.abs(filled[dead] / lum - 1.0) < 0.05)
    assert np.all(out["flags"][-1][dead] == FLAG_NO_EVENTS | FLAG_FILLED)
    assert np.isnan(out["sigma_log"][-1][dead]).all()


def test_calibration_file_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    sweep = simulate_sweep((tn_panel(normally_white=True), tn_panel(normally_white=False)),
                           rng=1)
    cal = Calibration(c_on=rng.uniform(0.1, 0.3, (4, 5)).astype(np.float32),
                      c_off=rng.uniform(0.1, 0.3, (4, 5)).astype(np.float32),
                      sigma_on=np.full((4, 5), 0.002, np.float32),
                      sigma_off=np.full((4, 5), 0.003, np.float32),
                      response=fit_response([1.0, 2.1, 3.9], [1.0, 2.0, 4.0]),
                      panel_curves=fit_panel_curves(sweep), sensor=get_preset("davis346"),
                      defects=rng.random((4, 5)) < 0.3, how={"kind": "test", "n": 3})
    p = write_calibration(tmp_path / "cal.npz", cal)
    back = read_calibration(p)
    np.testing.assert_array_equal(back.c_on, cal.c_on)
    np.testing.assert_array_equal(back.sigma_off, cal.sigma_off)
    assert back.defects is not None and back.defects.dtype == bool
    np.testing.assert_array_equal(back.defects, cal.defects)
    assert back.sensor == get_preset("davis346")
    assert back.how == {"kind": "test", "n": 3}
    assert back.response is not None
    np.testing.assert_allclose(back.response(np.array([2.1])), [2.0], rtol=1e-6)
    assert set(back.panel_curves) == {"1", "2"}
    thr = back.threshold_maps()
    assert thr is not None and thr[2].shape == (4, 5)
    with pytest.raises(ValueError, match="calibration"):
        write_calibration(tmp_path / "cal.npy", cal)


def test_panel_sweep_csv_round_trip_and_fit(tmp_path: Path) -> None:
    panels = (tn_panel(normally_white=True), tn_panel(normally_white=False))
    sweep = simulate_sweep(panels, noise=0.002, rng=3)
    p = write_sweep_csv(tmp_path / "sweep.csv", sweep)
    back = read_sweep_csv(p)
    for k in ("1", "2"):
        np.testing.assert_array_equal(back[k][0], sweep[k][0])
        np.testing.assert_array_equal(back[k][1], sweep[k][1])
    curves = fit_panel_curves(back)
    v = np.linspace(0.5, 4.5, 9)
    for k, pn in zip(("1", "2"), panels, strict=True):
        # the fitted curve follows the true one within a few noise sigmas
        assert np.max(np.abs(curves[k].transmittance(v) - pn.curve.transmittance(v))) < 0.01
    (tmp_path / "bad.csv").write_text("volts,t\n1,0.5\n")
    with pytest.raises(ValueError, match="voltage_v"):
        read_sweep_csv(tmp_path / "bad.csv")


def test_response_fit_is_monotone() -> None:
    r = fit_response([1.0, 3.0, 2.5, 10.0], [1.0, 2.0, 3.0, 4.0])
    y = r(np.array([1.0, 2.0, 2.75, 10.0, 20.0]))
    assert np.all(np.diff(y) >= 0)
    assert y[-1] == pytest.approx(4.0 * 2.0, rel=1e-6)  # slope 1 beyond the last patch


def test_designed_defaults_and_prediction() -> None:
    # the designed rig of the ideal preset predicts the whole 0.1 .. 316,000 lux range
    # (130 dB) at per-pixel SNR >= 20 dB; the paper's rig at most 90 dB (its blind band
    # and its floor at 0.5 L_const)
    assert set(DESIGNED) >= {"ideal", "v2e", "davis346", "imx636"}
    levels = np.geomspace(0.1, 10 ** 5.5, 14)
    pred = predict(default_rig("ideal"), get_preset("ideal"), levels=levels)
    db, lo, _, _ = pred.run(20.0)
    assert db == pytest.approx(130.0) and lo == pytest.approx(0.1)
    assert pred.readout_load == 0.0 and np.all(pred.bias == 0.0)  # no readout limit
    db_p, _, _, _ = predict(Rig(l_const=10.0), get_preset("ideal"), levels=levels).run(20.0)
    assert db_p <= 90.0


def test_design_families() -> None:
    # every designed default names a family design() knows, and builds; an unknown family
    # is refused before anything is simulated; a round trip needs room for both halves,
    # two round trips for four
    from asynhdr.design import FAMILIES, design, round_trip_rig

    for preset, p in DESIGNED.items():
        assert p["family"] in FAMILIES, preset
        assert default_rig(preset).period_us == round(1e6 / p["frame_rate_hz"])
    with pytest.raises(ValueError, match="unknown rig families"):
        design("ideal", families=("zigzag",))
    with pytest.raises(ValueError, match="2 b trips <= ramp_fraction"):
        round_trip_rig(period_us=50_000, l_const=100.0, a=0.2, b=0.5)
    with pytest.raises(ValueError, match="2 b trips <= ramp_fraction"):
        round_trip_rig(period_us=50_000, l_const=100.0, a=0.1, b=0.25, trips=2)
    with pytest.raises(ValueError, match="trips must be a whole number"):
        round_trip_rig(period_us=50_000, l_const=100.0, a=0.1, b=0.2, trips=0)


def test_design_ranks_range_then_the_simplest_rig_at_the_mean_snr() -> None:
    from asynhdr.design import _preference

    def best(*cands: tuple[float, float, int]) -> int:
        keys = [_preference(db, m, rank, 30.0) for db, m, rank in cands]
        return keys.index(max(keys))

    # the wider range wins, whatever its SNR and family
    assert best((115.0, 35.0, 0), (120.0, 26.0, 2)) == 1
    # equal ranges: of those at >= 30 dB, the simplest family
    assert best((120.0, 26.5, 0), (120.0, 31.3, 2), (120.0, 32.0, 1)) == 2
    # equal ranges, none at 30 dB: the higher mean SNR, whatever the family
    assert best((120.0, 26.5, 0), (120.0, 28.8, 1)) == 1
    # both at 30 dB: the sequential rig, though the round trip is better
    assert best((130.0, 74.2, 0), (130.0, 77.0, 1)) == 0
    # one family: the higher mean SNR
    assert best((130.0, 74.2, 0), (130.0, 75.0, 0)) == 1

    def best_m(*cands: tuple[float, float, float]) -> int:
        keys = [_preference(db, m, 2, 30.0, db_m) for db, db_m, m in cands]
        return keys.index(max(keys))

    # the range with the margin first: a wider range that ends on the line loses to a
    # narrower one with SNR to spare; equal ranges with the margin: the wider range
    assert best_m((125.0, 115.0, 31.0), (120.0, 120.0, 31.0)) == 1
    assert best_m((120.0, 120.0, 32.0), (125.0, 120.0, 31.0)) == 1


def test_reference_radiances_span_both_ends_of_the_scene() -> None:
    # 0.1 .. 316,000 lux through 1000:1 panels: the darkest level crosses for L_const <=
    # 100 lux, the brightest for L_const >= 316 lux; the search spans 10 to 3162 lux
    from asynhdr.design import reference_radiances

    lc = reference_radiances(0.1, 10 ** 5.5, 1000.0)
    assert len(lc) == 12 and lc[0] == pytest.approx(10.0)
    assert lc[-1] == pytest.approx(10 ** 3.5)
    assert np.allclose(np.diff(np.log(lc)), np.log(lc[1] / lc[0]))
    # a narrow scene (1 .. 1000 lux): the two ends swap, the span is the same rule
    lc = reference_radiances(1.0, 1000.0, 1000.0)
    assert lc[0] == pytest.approx(0.1) and lc[-1] == pytest.approx(10_000.0)


def test_cli_design_writes_the_rig_it_prints(tmp_path: Path) -> None:
    # the ideal pixel, sequential rigs at 20 cycles/s: the whole 0.1 .. 316,000 lux range
    # (130 dB, as the designed default predicts); the rig file holds the printed design
    # and reads back as a rig; bad ranges and families write nothing
    import json

    from typer.testing import CliRunner

    from asynhdr.cli import _register, app

    _register()
    runner = CliRunner()
    rig_p, js = tmp_path / "rig.toml", tmp_path / "design.json"
    res = runner.invoke(app, ["design", "--preset", "ideal", "--family", "sequential",
                              "--frame-rate-hz", "20", "-o", str(rig_p), "--json", str(js)])
    assert res.exit_code == 0, res.output
    d = json.loads(js.read_text())
    assert d["range_db"] == pytest.approx(130.0) and d["params"]["family"] == "sequential"
    assert f"{d['range_db']:.1f} dB" in res.output
    rig = read_rig(rig_p).rig
    assert rig.period_us == 50_000 and rig.l_const == pytest.approx(d["params"]["l_const"])
    db, _, _, _ = predict(rig, get_preset("ideal"),
                          levels=np.geomspace(0.1, 10 ** 5.5, 14)).run(20.0)
    assert db == pytest.approx(130.0)
    # the grid (12 L_const x 5 splits), then the best split's L_const beyond the grid's
    # end while the best sits there, then halfway and a quarter of the way to its
    # neighbours: the last four candidates, about the best of the grid and beyond
    from asynhdr.design import SPLITS, reference_radiances

    grid = reference_radiances(0.1, 10 ** 5.5, 1000.0)
    cands = d["candidates"]
    n_grid = len(grid) * len(SPLITS["sequential"])
    assert all(c["l_const"] in grid for c in cands[:n_grid])
    assert len(cands) - n_grid - 4 in (0, 1, 2)
    step = math.log(grid[1] / grid[0])
    last = [math.log(c["l_const"]) for c in cands[-4:]]
    assert last[1] - last[0] == pytest.approx(step, rel=1e-9)  # both sides of one
    assert last[3] - last[2] == pytest.approx(step / 2, rel=1e-9)  # then closer
    assert all(c["family"] == d["params"]["family"] for c in cands[n_grid:])
    for bad, message in ((["--family", "zigzag"], "unknown rig families"),
                         (["--l-min", "10", "--l-max", "1"], "--l-min < --l-max")):
        out = tmp_path / "bad.toml"
        res = runner.invoke(app, ["design", "--preset", "ideal", "-o", str(out), *bad])
        assert res.exit_code == 2 and message in " ".join(res.output.split())
        assert not out.exists()


def test_thresholds_from_results_weights_by_events() -> None:
    # hand-computed: pixel 0 fired 3 ON in cycle 0 (c_on 0.20) and 1 ON in cycle 1
    # (c_on 0.24): (3 * 0.20 + 1 * 0.24) / 4 = 0.21; no OFF event: NaN
    from asynhdr.calib import thresholds_from_results

    c_on = np.array([[[0.20]], [[0.24]]])
    c_off = np.array([[[0.3]], [[0.3]]])
    n_on = np.array([[[3]], [[1]]])
    n_off = np.zeros((2, 1, 1))
    with np.errstate(invalid="ignore"):
        on, off = thresholds_from_results(c_on, c_off, n_on, n_off)
    assert on[0, 0] == pytest.approx(0.21)
    assert np.isnan(off[0, 0])


def test_ml_fits_thresholds_jointly_where_the_events_identify_them() -> None:
    # one cycle of a flat field brighter and one darker than L_const: with a weak prior
    # (0.1) on the thresholds, ml's own joint fit of (L, c_on, c_off) lands closer to the
    # true thresholds than the nominal value on pixels with many events of a polarity
    from asynhdr import ml

    rig = default_rig("ideal")
    sensor = get_preset("ideal")
    w = 30
    c_on = np.full((2, w), 0.2) + np.linspace(-0.05, 0.05, w)
    c_off = np.full((2, w), 0.2) - np.linspace(-0.05, 0.05, w)
    scene = np.array([[rig.l_const * 100.0] * w, [rig.l_const / 100.0] * w])
    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=2, rng=0, thresholds=(c_on, c_off))
    model = ml.ml_model(rig, sensor)
    pri = ml.thresholds_prior(sensor, width=w, height=2, c_on=np.full((2, w), 0.2),
                              c_off=np.full((2, w), 0.2), sigma=0.1)
    res = ml.estimate(rec.events, width=w, height=2, starts_us=rig.cycle_starts_us(2),
                      model=model, priors=pri)
    # the bright row fires ON events: its c_on is identified; the dark row's c_off
    err_on = np.abs(res.c_on[-1, 0] - c_on[0])
    err_off = np.abs(res.c_off[-1, 1] - c_off[1])
    assert np.median(err_on) < 0.01 < np.median(np.abs(c_on[0] - 0.2))
    assert np.median(err_off) < 0.01


def test_cli_calibrate_thresholds_then_reconstruct_with_calibration(tmp_path: Path) -> None:
    # simulate --rig-out, flat fields above and below L_const (through a region of
    # interest the readout keeps up with), calibrate-thresholds, then reconstruct
    # --calibration: the file holds per-pixel maps and ml uses them
    from typer.testing import CliRunner

    from asynhdr.cli import _register, app
    from asynhdr.io.images import read_image

    _register()
    runner = CliRunner()
    rig = tmp_path / "rig.toml"
    lc = default_rig("imx636").l_const
    flats = []
    for i, r in enumerate((lc * 30, lc / 30)):
        f = tmp_path / f"flat{i}.h5"
        res = runner.invoke(app, ["simulate", f"flat:{r}", "-o", str(f), "--width", "12",
                                  "--height", "8", "--preset", "imx636", "--n-cycles", "3",
                                  "--seed", str(i), "--rig-out", str(rig), "--roi",
                                  "--overwrite"])
        assert res.exit_code == 0, res.output
        flats.append(str(f))
    cal = tmp_path / "cal.npz"
    # two values after one --radiance: the second would be read as a recording
    res = runner.invoke(app, ["calibrate-thresholds", *flats, "--radiance", "30",
                              "0.03", "--rig", str(rig), "-o", str(cal)])
    assert res.exit_code != 0 and not cal.exists()
    assert "0.03: no such recording; a radiance? Give --radiance once per value " \
        "(--radiance 30 --radiance 0.03)" in " ".join(res.output.split())
    res = runner.invoke(app, ["calibrate-thresholds", *flats, "--radiance", str(lc * 30),
                              "--radiance", str(lc / 30), "--rig", str(rig), "-o", str(cal)])
    assert res.exit_code == 0, res.output
    assert "0 dead pixels (no event in any cycle)" in " ".join(res.output.split())
    back = read_calibration(cal)
    c_on, c_off = draw_thresholds(get_preset("imx636"), width=12, height=8,
                                  rng=np.random.default_rng(1))
    assert back.c_on is not None and back.c_off is not None
    assert float(np.sqrt(np.mean((back.c_on - c_on) ** 2))) < 0.01
    assert float(np.sqrt(np.mean((back.c_off - c_off) ** 2))) < 0.01
    scene = tmp_path / "scene.h5"
    res = runner.invoke(app, ["simulate", "flat:2000", "-o", str(scene), "--width", "12",
                              "--height", "8", "--preset", "imx636", "--n-cycles", "2",
                              "--roi"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["reconstruct", str(scene), "-o", str(tmp_path / "img"),
                              "--method", "ml", "--calibration", str(cal), "--formats", "exr"])
    assert res.exit_code == 0, res.output
    assert "no --calibration" not in res.output
    assert "0 dead pixels in the calibration; 0 of them filled" in " ".join(res.output.split())
    img = read_image(tmp_path / "img" / "scene_ml_0001.exr")
    assert abs(float(np.nanmedian(img)) / 2000.0 - 1.0) < 0.03
    # without it, ml says what it did and what calibration would add
    res = runner.invoke(app, ["reconstruct", str(scene), "-o", str(tmp_path / "img0"),
                              "--method", "ml", "--formats", "exr"])
    assert res.exit_code == 0, res.output
    assert "no --calibration" in res.output and "mismatch 0.05" in res.output
    # a calibration of another sensor, or for another method, is refused before any work
    small = tmp_path / "small.h5"
    res = runner.invoke(app, ["simulate", "flat:2000", "-o", str(small), "--width", "6",
                              "--height", "4", "--preset", "imx636", "--n-cycles", "1"])
    assert res.exit_code == 0, res.output
    for args, word in ((["--method", "ml", "--calibration", str(cal)], "cal.npz: thresholds "
                        "of a 12x8 sensor"),
                       (["--method", "exp", "--calibration", str(cal)], "--calibration"),
                       (["--method", "ml", "--cmap", str(cal)], "--cmap")):
        out = tmp_path / "refused"
        res = runner.invoke(app, ["reconstruct", str(small), "-o", str(out), *args])
        assert res.exit_code == 2 and word in " ".join(res.output.split()), res.output
        assert not out.exists()


def test_design_prediction_counts_the_readout_queue() -> None:
    # the IMX636's round trip at 20 cycles/s (L_const 1196.6, a 0.15): without a readout
    # limit the queue biases nothing; at the array's readout the levels spread evenly keep
    # most of the range; with a quarter of the array at one radiance (its pixels fire in
    # the same instant) the queue biases levels past 5 % and the range shrinks by 30 dB or
    # more
    from asynhdr.design import MAX_BIAS, round_trip_rig

    rig = round_trip_rig(period_us=50_000, l_const=1196.6450696489756, a=0.15, b=0.45)
    imx = get_preset("imx636")
    levels = np.geomspace(0.1, 10 ** 5.5, 14)
    free = predict(rig, imx.with_(max_event_rate_hz=0.0), levels=levels)
    assert np.all(free.bias == 0.0) and free.max_delay_us == 0.0
    even = predict(rig, imx, levels=levels, uniform_share=0.0)
    lumped = predict(rig, imx, levels=levels)
    assert 0.3 < even.readout_load < 0.6  # the mean load, the same in both scenes
    assert lumped.max_delay_us > even.max_delay_us > 0.0
    assert np.nanmax(np.abs(lumped.bias)) > MAX_BIAS
    assert even.run(20.0)[0] >= lumped.run(20.0)[0] + 30.0
    # the queue delays each pixel's events by its own amounts: the spread of ml's error
    # over a level's pixels adds to the bound in quadrature (the same events before the
    # readout, so the same bound)
    assert free.queue_sd is not None and lumped.queue_sd is not None
    assert np.all(free.queue_sd == 0.0) and np.nanmax(lumped.queue_sd) > 0.01
    ok = np.isfinite(free.snr_db) & np.isfinite(lumped.snr_db)
    bound = 10.0 ** (-free.snr_db[ok] / 20.0)
    np.testing.assert_allclose(lumped.snr_db[ok],
                               -20.0 * np.log10(np.hypot(bound, lumped.queue_sd[ok])),
                               rtol=1e-9)
    with pytest.raises(ValueError, match="uniform_share"):
        predict(rig, imx, levels=levels, uniform_share=1.0)


def test_a_rig_of_another_period_is_refused(tmp_path: Path) -> None:
    # a recording made at 20 cycles/s (its trigger edges 50 ms apart) and a rig file of a
    # 40 ms rig: every radiometric method would read the events through the wrong
    # waveforms, so the reconstruction refuses it and writes nothing; the right rig works
    from typer.testing import CliRunner

    from asynhdr.cli import _register, app
    from asynhdr.io import open_source, write_recording
    from asynhdr.reconstruct import windows_for

    made = Rig(period_us=50_000)
    rec = simulate(np.full((6, 8), 100.0), rig=made, sensor="ideal", n_cycles=3, rng=0)
    raw = tmp_path / "rec.raw"
    write_recording(raw, rec)
    other = Rig(period_us=40_000)
    with pytest.raises(ValueError, match=r"50000 µs long \(from the rig it was made with\), "
                                         r"but the rig's period is 40000 µs"):
        windows_for(open_source(raw), rig=other)
    # without the recording's own rig, its trigger edges say the same
    bare = dataclasses.replace(rec, metadata={})
    with pytest.raises(ValueError, match="from its trigger edges"):
        windows_for(bare, rig=other)
    assert windows_for(open_source(raw), rig=made).n_cycles == 3
    # a period given beside the right rig: the cycles it makes are refused
    with pytest.raises(ValueError, match="40000 µs long"):
        windows_for(bare, rig=made, period_us=40_000)
    rig_p = tmp_path / "other.toml"
    write_rig(rig_p, other, sensor=get_preset("ideal"))
    _register()
    out = tmp_path / "img"
    res = CliRunner().invoke(app, ["reconstruct", str(raw), "--rig", str(rig_p), "--method",
                                   "ttfe", "--out", str(out)])
    assert res.exit_code == 2 and "the rig does not describe this recording" in " ".join(
        res.output.split())
    assert not out.exists()
