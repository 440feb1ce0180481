"""Dask: a sensor split into pixel ranges and a recording split by cycles give the serial
results bit for bit, on a real dask.distributed LocalCluster of worker processes."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from asynhdr.cli import _register, app
from asynhdr.io import open_source, write_recording
from asynhdr.io.images import read_image
from asynhdr.reconstruct import reconstruct_cycles
from asynhdr.scene import moving_scene, step_chart
from asynhdr.simulate import finish_recording, simulate, simulate_cycles

_register()
runner = CliRunner()


@pytest.mark.parametrize(("preset", "engine"), [("ideal", "exact"), ("imx636", "exact"),
                                                ("davis346", "exact"), ("imx636", "stepped")])
def test_pixel_ranges_join_into_the_serial_recording(preset: str, engine: str) -> None:
    chart = step_chart(width=64, height=40)
    whole = simulate(chart, sensor=preset, n_cycles=3, rng=4, sensor_seed=2, engine=engine)
    cuts = [0, 700, 1201, 2000, 64 * 40]
    parts = [simulate_cycles(chart, sensor=preset, n_cycles=3, rng=4, sensor_seed=2,
                             engine=engine, pixels=(a, b))
             for a, b in itertools.pairwise(cuts)]
    joined = finish_recording(parts[::-1])  # any order: joined by pixel range
    assert whole.events.size > 10_000
    assert joined.events.tobytes() == whole.events.tobytes()
    assert joined.metadata == whole.metadata
    with pytest.raises(ValueError, match="do not cover"):
        finish_recording(parts[1:])


def test_a_moving_scene_splits_too() -> None:
    m = moving_scene(step_chart(width=40, height=24).radiance, velocity_px_per_s=(300.0, 0),
                     duration_us=100_000)
    whole = simulate(m, sensor="imx636", n_cycles=2, rng=1)
    parts = [simulate_cycles(m, sensor="imx636", n_cycles=2, rng=1, pixels=r)
             for r in ((0, 333), (333, 960))]
    assert finish_recording(parts).events.tobytes() == whole.events.tobytes()


@pytest.fixture(scope="module")
def client():
    pytest.importorskip("distributed")
    from asynhdr.distributed import scheduler_client

    with scheduler_client("local", workers=2) as c:
        yield c


def test_simulate_on_a_local_cluster_equals_serial(client) -> None:
    from asynhdr.distributed import simulate_distributed

    chart = step_chart(width=80, height=48)
    kw = dict(sensor="imx636", n_cycles=2, rng=7, sensor_seed=3)
    serial = simulate(chart, **kw)
    spread = simulate_distributed(client, chart, n_parts=3, **kw)
    assert serial.events.size > 10_000
    assert spread.events.tobytes() == serial.events.tobytes()
    assert spread.metadata == serial.metadata


def test_a_held_readout_is_simulated_whole_on_the_cluster(client) -> None:
    from asynhdr.distributed import simulate_distributed
    from asynhdr.sensor.params import get_preset

    chart = step_chart(width=48, height=32)
    held = get_preset("davis346").with_(name="davis346", arbiter="hold")
    kw = dict(sensor=held, n_cycles=2, rng=3, sensor_seed=1)
    serial = simulate(chart, **kw)
    spread = simulate_distributed(client, chart, n_parts=3, **kw)
    assert serial.metadata["readout"]["pixels_held"]
    assert serial.metadata["readout"]["held_cycles"] == 2
    assert spread.events.tobytes() == serial.events.tobytes()
    assert spread.metadata == serial.metadata


def test_reconstruct_on_a_local_cluster_equals_serial(client, tmp_path: Path) -> None:
    from asynhdr.distributed import reconstruct_distributed

    rec = simulate(step_chart(width=80, height=48), sensor="v2e", n_cycles=5, rng=2)
    path = tmp_path / "rec.raw"
    write_recording(path, rec)
    src = open_source(path)
    # invert treats the warm-up cycle apart: the part that holds it must know it
    for method in ("exp", "invert"):
        plan = reconstruct_cycles(src, method=method)
        assert plan.windows.warmup == 1
        serial = list(plan)
        spread = list(reconstruct_distributed(client, path, plan.windows, method=method,
                                              n_parts=3))
        assert [(i, s) for i, s, _ in spread] == [(i, s) for i, s, _ in serial]
        for (_, _, a), (_, _, b) in zip(serial, spread, strict=True):
            assert a.tobytes() == b.tobytes()


def test_cli_scheduler_local_writes_the_serial_images(client, tmp_path: Path) -> None:
    rec = tmp_path / "rec.h5"
    common = ["--width", "48", "--height", "32", "--preset", "v2e", "--n-cycles", "4"]
    r = runner.invoke(app, ["simulate", "chart", "-o", str(rec), *common])
    assert r.exit_code == 0, r.output
    rec2 = tmp_path / "rec2.h5"
    r = runner.invoke(app, ["simulate", "chart", "-o", str(rec2), *common,
                            "--scheduler", "local", "--workers", "2"])
    assert r.exit_code == 0, r.output
    from asynhdr.io import open_recording

    assert open_recording(rec).events.tobytes() == open_recording(rec2).events.tobytes()
    a, b = tmp_path / "serial", tmp_path / "spread"
    assert runner.invoke(app, ["reconstruct", str(rec), "-o", str(a),
                               "--formats", "exr"]).exit_code == 0
    r = runner.invoke(app, ["reconstruct", str(rec), "-o", str(b), "--formats", "exr",
                            "--scheduler", client.scheduler.address])
    assert r.exit_code == 0, r.output
    fa, fb = sorted(a.glob("*.exr")), sorted(b.glob("*.exr"))
    assert [p.name for p in fa] == [p.name for p in fb] and len(fa) == 4
    for x, y in zip(fa, fb, strict=True):
        np.testing.assert_array_equal(read_image(x), read_image(y))
    r = runner.invoke(app, ["reconstruct", str(rec), "-o", str(tmp_path / "c"),
                            "--scheduler", "tcp://127.0.0.1:1"])
    assert r.exit_code == 2 and "scheduler" in r.output


def test_cli_scheduler_passes_the_rig_and_ml_writes_every_cycle(client, tmp_path: Path
                                                                ) -> None:
    # a .raw file carries no rig: ml needs --rig, and the workers must get it too; the
    # recording's name has a dot, which must not eat the cycle number of the images
    rec = tmp_path / "scene.v1.raw"
    rig = tmp_path / "rig.toml"
    r = runner.invoke(app, ["simulate", "chart", "-o", str(rec), "--width", "40",
                            "--height", "24", "--preset", "ideal", "--n-cycles", "3",
                            "--rig-out", str(rig)])
    assert r.exit_code == 0, r.output
    a, b = tmp_path / "serial", tmp_path / "spread"
    args = ["--method", "ml", "--rig", str(rig), "--formats", "exr,png"]
    r = runner.invoke(app, ["reconstruct", str(rec), "-o", str(a), *args])
    assert r.exit_code == 0, r.output
    # the module's cluster, by its address: the CLI's way to a running scheduler
    r = runner.invoke(app, ["reconstruct", str(rec), "-o", str(b), *args,
                            "--scheduler", client.scheduler.address])
    assert r.exit_code == 0, r.output
    names = sorted(p.name for p in a.iterdir())
    assert names == sorted(p.name for p in b.iterdir())
    for i in range(3):
        for suffix in (".exr", ".png", "_sigma.exr", "_valid.png"):
            assert f"scene.v1_ml_{i:04d}{suffix}" in names
    for name in names:
        if name.endswith(".exr"):
            np.testing.assert_array_equal(read_image(a / name), read_image(b / name))
        else:
            assert (a / name).read_bytes() == (b / name).read_bytes(), name
    first = read_image(a / "scene.v1_ml_0000.exr")
    assert np.isfinite(first).mean() > 0.9


def test_cli_evaluate_on_workers_gives_the_serial_figures(tmp_path: Path) -> None:
    import json

    scene = tmp_path / "grad.npy"
    np.save(scene, np.geomspace(1.0, 1e4, 96 * 64).reshape(64, 96).astype(np.float32))
    common = ["--width", "96", "--height", "64", "--methods", "raw,exp,invert",
              "--n-cycles", "2"]
    a, b = tmp_path / "a", tmp_path / "b"
    r = runner.invoke(app, ["evaluate", str(scene), str(scene), "--out", str(a), *common])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["evaluate", str(scene), str(scene), "--out", str(b), *common,
                            "--scheduler", "local", "--workers", "2"])
    assert r.exit_code == 0, r.output
    sa = json.loads((a / "evaluate.json").read_text())["scenes"]
    sb = json.loads((b / "evaluate.json").read_text())["scenes"]
    assert [s["methods"] for s in sa] == [s["methods"] for s in sb]
