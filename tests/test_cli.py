"""The command line end to end, on a small sensor: simulate -> calibrate -> reconstruct."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from asynhdr.cli import _register, app
from asynhdr.io import open_recording
from asynhdr.io.images import read_image

_register()
runner = CliRunner()


def run(*args: str):
    return runner.invoke(app, [str(a) for a in args])


def test_simulate_calibrate_reconstruct(tmp_path: Path) -> None:
    common = ["--width", "64", "--height", "48", "--n-cycles", "2", "--sensor-seed", "3"]
    r = run("simulate", "chart", "-o", tmp_path / "chart.h5", *common)
    assert r.exit_code == 0, r.output
    for i in range(2):
        r = run("simulate", "flat:1600", "-o", tmp_path / f"flat{i}.npz", *common,
                "--seed", str(10 + i))
        assert r.exit_code == 0, r.output
    r = run("calibrate", tmp_path / "flat0.npz", tmp_path / "flat1.npz",
            "-o", tmp_path / "cmap.npz")
    assert r.exit_code == 0, r.output
    r = run("reconstruct", tmp_path / "chart.h5", "-o", tmp_path / "img", "--method", "exp",
            "--cmap", tmp_path / "cmap.npz", "--formats", "exr,png,npy")
    assert r.exit_code == 0, r.output
    rec = open_recording(tmp_path / "chart.h5")
    assert rec.triggers.size == 2 and rec.metadata["sensor_seed"] == 3
    names = sorted(p.name for p in (tmp_path / "img").iterdir())
    assert names == [f"chart_exp_{i:04d}.{e}" for i in range(2) for e in ("exr", "npy", "png")]
    img = read_image(tmp_path / "img" / "chart_exp_0001.exr")
    assert img.shape == (48, 64) and np.all(np.isfinite(img)) and img.max() > img.min()


def test_demo_small(tmp_path: Path) -> None:
    r = run("demo", "--out", tmp_path, "--width", "282", "--height", "128", "--n-cycles", "2",
            "--n-flat", "2")
    assert r.exit_code == 0, r.output
    assert "paper" in r.output and "Dynamic range" in r.output
    res = json.loads((tmp_path / "results.json").read_text())
    assert {m["method"] for m in res["methods"]} >= {"raw", "linear", "quadratic", "poly5",
                                                      "exp", "ttfe", "count"}
    for name in ("mosaic.png", "snr_per_level.png", "chart_response.png", "cmap.npz",
                 "images/exp_cmap.exr", "images/raw.png"):
        assert (tmp_path / name).is_file(), name


@pytest.mark.parametrize(
    ("scene", "message"),
    [
        ("missing.exr", "no such file"),
        ("notimage.exr", "missing.exr"),
        ("nan.npy", "NaN"),
        ("flat:abc", "flat:RADIANCE"),
    ],
)
def test_bad_scene_writes_nothing(tmp_path: Path, scene: str, message: str) -> None:
    (tmp_path / "notimage.exr").write_text("this is not an image")
    np.save(tmp_path / "nan.npy", np.array([[1.0, np.nan], [2.0, 3.0]], np.float32))
    out = tmp_path / "rec.h5"
    arg = str(tmp_path / scene) if not scene.startswith("flat:") else scene
    r = run("simulate", arg, "-o", out, "--width", "40", "--height", "20")
    assert r.exit_code == 2
    if scene != "notimage.exr":
        assert message in " ".join(r.output.split())  # the console wraps long paths
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.parametrize(
    ("flag", "value", "message"),
    [("--period-us", "0", "--period-us must"), ("--period-us", "-10", "--period-us must"),
     ("--preset", "nope", "unknown sensor preset")],
)
def test_bad_parameters_are_named(tmp_path: Path, flag: str, value: str, message: str) -> None:
    out = tmp_path / "rec.h5"
    r = run("simulate", "chart", "-o", out, "--width", "40", "--height", "20", flag, value)
    assert r.exit_code == 2 and message in r.output
    assert not out.exists()


def test_simulate_takes_the_rig_files_sensor_and_refuses_what_contradicts_it(
        tmp_path: Path) -> None:
    rig = Path(__file__).parents[1] / "docs" / "rigs" / "imx636_5fps.toml"
    out = tmp_path / "r.h5"
    r = run("simulate", "flat:100", "--rig", rig, "-o", out, "--width", "8", "--height", "6",
            "--n-cycles", "1")
    assert r.exit_code == 0, r.output
    assert open_recording(out).metadata["sensor"]["name"] == "imx636"  # not the default v2e
    for extra, word in ((["--period-us", "10000"], "--period-us"),
                        (["--panel", "tn"], "--panel"),
                        (["--preset", "v2e"], "--preset v2e")):
        bad = tmp_path / "bad.h5"
        r = run("simulate", "flat:100", "--rig", rig, "-o", bad, *extra)
        assert r.exit_code == 2 and word in r.output and not bad.exists(), r.output
    # --rig-out: checked with the recording, never the recording itself
    same = tmp_path / "same.h5"
    r = run("simulate", "flat:100", "-o", same, "--rig-out", same, "--width", "4",
            "--height", "4")
    assert r.exit_code == 2 and "--rig-out" in r.output and not same.exists()
    (tmp_path / "old.toml").write_text("keep")
    r = run("simulate", "flat:100", "-o", tmp_path / "new.h5", "--rig-out",
            tmp_path / "old.toml", "--width", "4", "--height", "4")
    assert r.exit_code == 2 and (tmp_path / "old.toml").read_text() == "keep"
    assert not (tmp_path / "new.h5").exists()
    # a moving scene is stepped: it cannot hold, and says so instead of dropping --hold
    r = run("simulate", "flat:100", "--hold", "--motion", "50,0", "-o", tmp_path / "m.h5",
            "--width", "4", "--height", "4")
    assert r.exit_code == 2 and "--hold" in r.output


def test_reconstruct_checks_its_options_before_writing(tmp_path: Path) -> None:
    rec = tmp_path / "r.h5"
    assert run("simulate", "flat:100", "-o", rec, "--width", "8", "--height", "6",
               "--n-cycles", "2", "--preset", "ideal").exit_code == 0
    for extra, word in ((["--tonemap", "foo"], "--tonemap"),
                        (["--period-us", "-5"], "--period-us"),
                        (["--method", "ml", "--formats", "exr,hdr"], "--formats hdr")):
        out = tmp_path / "img"
        r = run("reconstruct", rec, "-o", out, *extra)
        assert r.exit_code == 2 and word in r.output, r.output
        assert not out.exists()


def test_an_error_is_printed_as_written(tmp_path: Path) -> None:
    r = run("info", tmp_path / "[x]" / "absent.raw")
    assert r.exit_code == 2 and "[x]/absent.raw" in r.output
