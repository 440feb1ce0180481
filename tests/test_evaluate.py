"""HDR scenes: aspect kept, automatic exposure, evaluation against ground truth; the bench."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from asynhdr.cli import _register, app
from asynhdr.design import default_rig
from asynhdr.evaluate import (
    ML_FAST,
    ML_UNCALIBRATED,
    calibrate_thresholds_for_scenes,
    evaluate_scene,
    rig_mid_radiance,
)
from asynhdr.experiments import finite_image
from asynhdr.report import render_report
from asynhdr.rig import Rig
from asynhdr.scene import exposure_scale, from_radiance_map, log_average

_register()
runner = CliRunner()


def test_portrait_map_is_padded_not_stretched() -> None:
    src = np.arange(874 * 644, dtype=np.float32).reshape(874, 644) % 97 + 1.0
    s = from_radiance_map(src, width=640, height=480, pad_radiance=0.0)
    y0, y1, x0, x1 = s.rois[0]
    cols = round(644 * 480 / 874)  # 354: the map's aspect at the sensor's full height
    assert (y0, y1) == (0, 480) and x1 - x0 == cols and x0 == (640 - cols) // 2
    assert abs((x1 - x0) / (y1 - y0) - 644 / 874) < 1 / 480
    assert np.all(s.radiance[:, :x0] == 0) and np.all(s.radiance[:, x1:] == 0)
    assert float(s.radiance[:, x0:x1].mean()) == pytest.approx(float(src.mean()), rel=0.01)
    wide = from_radiance_map(np.ones((100, 400)), width=64, height=48)
    assert wide.rois[0] == (16, 32, 0, 64)  # 64 x 16 keeps 4:1


def test_automatic_exposure_puts_the_log_average_at_the_target() -> None:
    a = np.array([[1.0, 100.0], [10.0, 0.0]])  # the zero is left out
    assert log_average(a) == pytest.approx(10.0)  # (1 * 100 * 10)^(1/3)
    s = exposure_scale(a, target=316.0)
    assert s == pytest.approx(31.6)
    assert log_average(a * s) == pytest.approx(316.0)
    assert rig_mid_radiance(Rig()) == pytest.approx(10.0 * math.sqrt(1000.0))


def test_evaluate_scene_small() -> None:
    y, x = np.mgrid[0:60, 0:80]
    scene = np.exp((x / 80.0) * 8.0) * (1.0 + 0.3 * np.sin(y / 5.0))  # 11.5 stops
    ev = evaluate_scene(scene, name="ramp", width=96, height=72, sensor="ideal", n_cycles=2)
    assert set(ev.metrics) >= {"raw", "exp", "invert", "mef-10", "mef-budget", "frame-auto"}
    assert ev.metadata["region"] == [0, 72, 0, 96]
    assert log_average(ev.scene.radiance) == pytest.approx(rig_mid_radiance(Rig()), rel=0.05)
    for m in ev.metrics.values():
        assert math.isfinite(m.log_rmse_stops) and 0 < m.ssim <= 1
    # ten well-placed exposures recover the scene to a small fraction of a stop
    assert ev.metrics["mef-10"].log_rmse_stops < 0.1
    assert ev.capture_s["mef-budget"] <= 0.05 + 1e-12
    assert ev.capture_s["raw"] == pytest.approx(0.05)
    # 11.5 stops about the middle of the paper's rig's 10 stops: some of the scene lies
    # beyond the range either side; the shares and the figures over the rest, by hand
    md = ev.metadata
    lo, hi = md["rig_range_lux"]
    assert (lo, hi) == pytest.approx(Rig().working_range())
    truth = ev.scene.radiance.astype(np.float64)
    t = truth[ev.mask]
    assert md["above_range_fraction"] == pytest.approx(np.mean(t > hi))
    assert md["below_range_fraction"] == pytest.approx(np.mean(t < lo))
    assert md["above_range_fraction"] > 0.02 and md["below_range_fraction"] > 0.02
    inside = ev.mask & (truth >= lo) & (truth <= hi)
    assert np.array_equal(ev.beyond_range, ev.mask & (truth > 0) & ~inside)
    for name in ("mef-10", "invert"):
        c = ev.metrics[name]
        err = np.log2(ev.images[name][inside].astype(np.float64) / truth[inside])
        assert c.log_rmse_in_range_stops == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-4)
        assert math.isfinite(c.pu21_psnr_in_range_db)
    # the saturated ends cost the paper's inversion, not the ten exposures
    assert ev.metrics["invert"].log_rmse_in_range_stops < ev.metrics["invert"].log_rmse_stops
    # and the report says so beside the figures
    page = render_report({"scenes": [ev.summary()]}, {})
    assert "lie above it" in page and "in range: PU21" in page


def test_evaluate_cli_on_a_real_portrait_scene(data_dir: Path, manifest: dict[str, Any],
                                               tmp_path: Path) -> None:
    facts = manifest["hdr"]["hdr/scenes/Desk.exr"]["what"]
    assert "644x874" in facts
    r = runner.invoke(app, ["evaluate", str(data_dir / "hdr" / "scenes" / "Desk.exr"),
                            "--out", str(tmp_path), "--width", "160", "--height", "120"])
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "evaluate.json").read_text())
    sc = res["scenes"][0]
    y0, y1, x0, x1 = sc["metadata"]["region"]
    assert (y1 - y0, x1 - x0) == (120, round(644 * 120 / 874))
    assert sc["metadata"]["auto_exposure"] and sc["metadata"]["scale"] > 100
    assert (tmp_path / "scenes" / "Desk.png").is_file()
    assert (tmp_path / "scenes" / "Desk_error.png").is_file()
    # the paper's rig spans 60 dB, Desk 31 stops: some of it lies beyond the range
    md = sc["metadata"]
    assert md["above_range_fraction"] + md["below_range_fraction"] > 0
    assert md["rig_range_lux"] == pytest.approx(list(Rig().working_range()))
    # --scale wins over the automatic exposure
    r = runner.invoke(app, ["evaluate", str(data_dir / "hdr" / "scenes" / "Desk.exr"),
                            "--out", str(tmp_path / "s"), "--width", "160", "--height", "120",
                            "--scale", "2000"])
    assert r.exit_code == 0, r.output
    sc2 = json.loads((tmp_path / "s" / "evaluate.json").read_text())["scenes"][0]
    assert sc2["metadata"]["scale"] == 2000 and not sc2["metadata"]["auto_exposure"]


@pytest.mark.slow
def test_bench_quick(tmp_path: Path) -> None:
    r = runner.invoke(app, ["bench", "--quick", "--out", str(tmp_path), "--presets",
                            "ideal,v2e", "--no-scenes"])
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "bench.json").read_text())
    assert set(res["presets"]) == {"ideal", "v2e"}
    v2e = res["presets"]["v2e"]
    assert [row["k"] for row in v2e["k_sweep"]] == [1.0, 2.0, 5.0, 10.0, 20.0]
    assert {m["method"] for m in v2e["frame_camera"]} == {"mef-10", "mef-budget"}
    page = (tmp_path / "report.html").read_text()
    assert "SNR table" in page and "k sweep" in page
    for rel in res["figures"].values():
        assert (tmp_path / rel).is_file(), rel


def test_evaluate_ml_with_and_without_calibration_side_by_side(tmp_path: Path) -> None:
    # ml-uncalibrated is ml as 'asynhdr reconstruct' runs it without a calibration: the
    # same image as reconstruct(rec, method="ml") of the same capture
    y, x = np.mgrid[0:24, 0:32]
    scene = np.exp((x / 32.0) * 6.0) * (1.0 + 0.3 * np.sin(y / 3.0))
    ev = evaluate_scene(scene, name="ramp", width=32, height=24, sensor="v2e", n_cycles=2,
                        methods=("ml", ML_UNCALIBRATED))
    assert {"ml", ML_UNCALIBRATED} <= set(ev.metrics)
    assert ev.capture_s[ML_UNCALIBRATED] == ev.capture_s["ml"]
    for m in ("ml", ML_UNCALIBRATED):
        assert math.isfinite(ev.metrics[m].log_rmse_stops)
    # without the c-map's thresholds the uncalibrated fit differs from the c-map's
    assert not np.array_equal(ev.images["ml"], ev.images[ML_UNCALIBRATED])
    r = runner.invoke(app, ["evaluate", "flat.npy", "--methods", "ml,mlx", "--out",
                            str(tmp_path)])
    assert r.exit_code != 0 and "unknown mlx" in r.output
    # the fast fit holds the calibration's thresholds: no rig, no calibration, no run
    r = runner.invoke(app, ["evaluate", "flat.npy", "--methods", "ml-fast", "--out",
                            str(tmp_path / "fast")])
    assert r.exit_code != 0 and "--designed or --rig" in r.output
    assert not (tmp_path / "fast").exists()


def test_evaluate_ml_fast_beside_ml_with_the_same_calibration() -> None:
    # ml-fast is ml's fast fit with the scenes' calibration: on the same capture, its log
    # error no more than a quarter above the full fit's (0.031 against 0.032 stops)
    y, x = np.mgrid[0:24, 0:32]
    scene = np.exp((x / 32.0) * 6.0) * (1.0 + 0.3 * np.sin(y / 3.0))
    rig = default_rig("imx636")
    cal = calibrate_thresholds_for_scenes(width=32, height=24, sensor="imx636", rig=rig,
                                          sensor_seed=1)
    ev = evaluate_scene(scene, name="ramp", width=32, height=24, sensor="imx636", n_cycles=2,
                        rig=rig, ml_calibration=cal, methods=("ml", ML_FAST))
    full, fast = ev.metrics["ml"].log_rmse_stops, ev.metrics[ML_FAST].log_rmse_stops
    assert math.isfinite(fast) and fast < 1.25 * full
    assert not np.array_equal(ev.images["ml"], ev.images[ML_FAST])
    with pytest.raises(ValueError, match="calibration"):
        evaluate_scene(scene, name="ramp", width=32, height=24, sensor="imx636", n_cycles=1,
                       rig=rig, methods=(ML_FAST,))


def test_finite_image_counts_the_measured_pixels_holes_apart(
        caplog: pytest.LogCaptureFixture) -> None:
    # a 2x4 image whose outer columns are padding: one NaN inside the scene, two outside,
    # one infinity; NaN -> 0, infinity -> the largest finite value (5)
    img = np.array([[np.nan, 1.0, np.nan, 5.0], [np.nan, 2.0, np.inf, 3.0]], np.float32)
    region = np.zeros(img.shape, bool)
    region[:, 1:3] = True
    with caplog.at_level("WARNING", logger="asynhdr.experiments"):
        out, n = finite_image(img, name="scene ml", region=region)
    assert n == 4
    np.testing.assert_array_equal(out, [[0, 1, 0, 5], [0, 2, 5, 3]])
    assert "scene ml: 1 of the 4 pixels measured without an estimate" in caplog.text
    assert "(and 2 not measured), 1 infinite" in caplog.text
    with pytest.raises(ValueError, match="region's shape"):
        finite_image(img, region=region[:, :2])
