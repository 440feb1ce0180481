"""HDR video: the steady tone curve, the MP4 writer, the ``video`` command, moving scenes."""

from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from asynhdr.cli import _register, app
from asynhdr.io.images import read_image, read_metadata
from asynhdr.io.video import read_video, video_info, write_video
from asynhdr.motion import edge_scene, edge_width_px, run_motion_experiment
from asynhdr.reconstruct import reconstruct
from asynhdr.rig import Rig
from asynhdr.scene import moving_scene
from asynhdr.simulate import simulate
from asynhdr.tonemap import StableLogToneCurve, tonemap

_register()
runner = CliRunner()


# ------------------------------------------------------------------ tone curve


def test_stable_curve_without_memory_is_the_log_curve() -> None:
    rng = np.random.default_rng(0)
    img = np.exp(rng.normal(3.0, 2.0, (40, 60)))
    curve = StableLogToneCurve(tau_frames=0.0)
    np.testing.assert_array_equal(curve(img), tonemap(img, method="log"))


def test_stable_curve_does_not_flicker_with_noisy_percentiles() -> None:
    """A static scene whose frames differ by noise: with the per-frame curve every
    frame's mean grey moves with its percentiles; the moving average keeps it steadier."""
    rng = np.random.default_rng(1)
    base = np.exp(np.linspace(0.0, 8.0, 80))[None, :] * np.ones((30, 1))
    frames = [base * np.exp(rng.normal(0.0, 0.4, base.shape)) for _ in range(40)]
    per_frame = StableLogToneCurve(tau_frames=0.0)
    steady = StableLogToneCurve(tau_frames=10.0)
    a = [per_frame(f) for f in frames]
    b = [steady(f) for f in frames]

    def flicker(seq: list[np.ndarray]) -> float:
        # the change of each frame's tone mapping of the same (noise-free) scene
        return float(np.std([np.mean(s.astype(float)) for s in seq[10:]]))

    # anchors of the steady curve move less than the per-frame ones
    lo_a = np.diff([x[0] for x in per_frame.anchors])
    lo_b = np.diff([x[0] for x in steady.anchors[10:]])
    assert np.std(lo_b) < 0.3 * np.std(lo_a)
    assert flicker(b) <= flicker(a)
    # a frame with nothing positive keeps the previous anchors
    steady(np.zeros((30, 80)))
    assert steady.anchors[-1] == steady.anchors[-2]


# ------------------------------------------------------------------ video files


def test_video_round_trip_rate_count_and_grey_levels(tmp_path: Path) -> None:
    ramp = np.tile(np.linspace(0, 255, 81).astype(np.uint8), (41, 1))  # odd sizes
    frames = [np.clip(ramp.astype(int) + 5 * i, 0, 255).astype(np.uint8) for i in range(12)]
    out = tmp_path / "v.mp4"
    assert write_video(out, frames, fps=Fraction(20)) == 12
    info = video_info(out)
    assert info["frames"] == 12 and info["fps"] == 20
    assert (info["width"], info["height"]) == (82, 42)  # padded to even
    back = read_video(out)[:, :41, :81].astype(int)
    err = np.abs(back - np.stack(frames))
    assert err.max() <= 4 and err.mean() < 1.0


def test_video_writer_refuses_bad_frames_and_leaves_nothing(tmp_path: Path) -> None:
    out = tmp_path / "bad.mp4"
    good = np.zeros((10, 10), np.uint8)
    with pytest.raises(ValueError, match="frame 1"):
        write_video(out, [good, np.zeros((12, 10), np.uint8)], fps=20)
    with pytest.raises(ValueError, match="uint8"):
        write_video(out, [good.astype(float)], fps=20)
    with pytest.raises(ValueError, match="no frames"):
        write_video(out, [], fps=20)
    assert not out.exists() and list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ moving scenes


def test_moving_scene_shifts_by_velocity_times_time() -> None:
    r = edge_scene(width=40, height=6, dark=1.0, bright=100.0, edge_x=10)
    m = moving_scene(r, velocity_px_per_s=(2000.0, 0.0), duration_us=5000, frame_step_us=500)
    assert m.frames.shape == (11, 6, 40)
    for i, t in enumerate(m.times_us):
        shift = 2000.0 * t * 1e-6  # 0 .. 10 px
        row = m.frames[i, 3]
        # the edge (half way up the step) sits at 9.5 + shift
        x_half = float(np.interp(50.5, row, np.arange(40)))
        assert x_half == pytest.approx(9.5 + shift, abs=1e-6)
    # between frames the scene is linear in time
    np.testing.assert_allclose(m.at(750.0), 0.5 * (m.frames[1] + m.frames[2]))
    assert m.metadata["motion"]["velocity_px_per_s"] == [2000.0, 0.0]


def test_a_moving_scene_is_simulated_by_the_stepped_engine() -> None:
    r = edge_scene(width=24, height=4, dark=5.0, bright=500.0)
    m = moving_scene(r, velocity_px_per_s=(300.0, 0.0), duration_us=100_000)
    rec = simulate(m, sensor="ideal", n_cycles=2)
    assert rec.metadata["engine"] == "stepped"
    assert rec.metadata["motion"]["velocity_px_per_s"] == [300.0, 0.0]
    with pytest.raises(ValueError, match="stepped"):
        simulate(m, sensor="ideal", n_cycles=2, engine="exact")


def test_motion_blurs_the_event_image_by_the_motion_during_the_ramp() -> None:
    """An edge panning at v px/s moves v x ramp during the ramp the events come from: the
    radiometric reconstruction's edge is that wide (the static one is about one pixel)."""
    rig = Rig()
    r = edge_scene(width=80, height=24, dark=30.0, bright=3000.0)
    v = 200.0
    res = run_motion_experiment(r, velocity_px_per_s=(v, 0.0), sensor="ideal", n_cycles=3,
                                methods=("invert",))
    s = res.summary()
    want = v * rig.ramp_us * 1e-6  # 9 px
    assert s["invert"]["edge_width_px"] == pytest.approx(want, abs=2.5)
    # the frame camera's fused frame is sharper: its exposures last far less than the ramp
    assert s["frame camera (fusion in one period)"]["edge_width_px"] < \
        s["invert"]["edge_width_px"]
    still = edge_width_px(reconstruct(simulate(r, sensor="ideal", n_cycles=2),
                                      method="invert")[-1])
    assert still < 1.5


# ------------------------------------------------------------------ the command


def test_video_command_frames_match_the_cycle_images(tmp_path: Path) -> None:
    rec_path = tmp_path / "pan.h5"
    r = runner.invoke(app, ["simulate", "chart", "--width", "64", "--height", "48",
                            "--preset", "ideal", "--n-cycles", "4", "--motion", "100,0",
                            "-o", str(rec_path)])
    assert r.exit_code == 0, r.output
    out = tmp_path / "pan.mp4"
    r = runner.invoke(app, ["video", str(rec_path), "-o", str(out), "--method", "exp",
                            "--exr-dir", str(tmp_path / "exr"), "--crf", "0"])
    assert r.exit_code == 0, r.output
    info = video_info(out)
    assert info["frames"] == 4
    assert info["fps"] == 20  # one frame per 50 ms cycle
    from asynhdr.io import open_recording

    images = reconstruct(open_recording(rec_path), method="exp")
    curve = StableLogToneCurve(tau_frames=10.0)
    want = np.stack([curve(im) for im in images]).astype(int)
    got = read_video(out)[:, :48, :64].astype(int)
    # lossless H.264 (crf 0): the grey plane comes back up to the rounding of the
    # full-to-video range conversion (one level)
    assert np.abs(got - want).max() <= 1 and np.mean(got != want) < 0.1
    # the default quality: within a few grey levels (sharp chart edges cost most)
    lossy = tmp_path / "lossy.mp4"
    assert runner.invoke(app, ["video", str(rec_path), "-o", str(lossy),
                               "--method", "exp"]).exit_code == 0
    err = read_video(lossy)[:, :48, :64].astype(float) - want
    psnr = 10 * np.log10(255.0**2 / np.mean(err**2))
    assert psnr > 35.0
    exrs = sorted((tmp_path / "exr").glob("*.exr"))
    assert [p.name for p in exrs] == [f"pan_{i:04d}_t{i * 50_000}us.exr" for i in range(4)]
    img, meta = read_image(exrs[2]), read_metadata(exrs[2])
    assert meta["start_us"] == 100_000 and meta["cycle"] == 2
    np.testing.assert_allclose(img, images[2], rtol=1e-6)
    # an existing video is refused unless --overwrite
    r = runner.invoke(app, ["video", str(rec_path), "-o", str(out)])
    assert r.exit_code == 2 and "--overwrite" in r.output
    assert math.isfinite(float(np.mean(got)))
