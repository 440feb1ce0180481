"""Colour: Bayer mosaic, demosaicing, colour error, and a colour scene through the rig."""

from __future__ import annotations

import numpy as np
import pytest

from asynhdr import colour
from asynhdr.colour import (
    CFA_PATTERNS,
    cfa_channels,
    colour_errors,
    colour_scene,
    demosaic,
    mosaic,
    reconstruct_colour,
    tonemap_rgb,
)


def _smooth_rgb(h=20, w=24):
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    # linear in x and y: both methods reproduce it exactly away from the border
    return np.stack([10 + 0.5 * x, 20 + 0.25 * y, 5 + 0.1 * x + 0.2 * y], axis=-1)


def test_cfa_layouts_by_hand():
    np.testing.assert_array_equal(cfa_channels("rggb", height=3, width=3),
                                  [[0, 1, 0], [1, 2, 1], [0, 1, 0]])
    np.testing.assert_array_equal(cfa_channels("gbrg", height=2, width=2), [[1, 2], [0, 1]])
    for p in CFA_PATTERNS:  # one R, two G, one B in every 2x2 block
        assert sorted(cfa_channels(p, height=2, width=2).ravel().tolist()) == [0, 1, 1, 2]
    with pytest.raises(ValueError, match="unknown CFA pattern"):
        cfa_channels("rgbw", height=2, width=2)


def test_mosaic_picks_each_pixels_channel():
    rgb = np.zeros((2, 2, 3))
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 1.0, 2.0, 3.0
    np.testing.assert_array_equal(mosaic(rgb, "rggb"), [[1, 2], [2, 3]])
    np.testing.assert_array_equal(mosaic(rgb, "bggr", transmittance=(0.5, 1.0, 2.0)),
                                  [[6, 2], [2, 0.5]])
    with pytest.raises(ValueError, match="3 positive numbers"):
        mosaic(rgb, transmittance=(1.0, 0.0, 1.0))


def test_malvar_filters_have_unit_gain():
    for k in (colour._M_G_AT_RB, colour._M_ROWWISE, colour._M_COLWISE, colour._M_RB_AT_BR):
        assert k.sum() == pytest.approx(1.0)
    # the paper's centre taps: 4/8, 5/8, 6/8
    assert colour._M_G_AT_RB[2, 2] * 8 == 4 and colour._M_ROWWISE[2, 2] * 8 == 5
    assert colour._M_RB_AT_BR[2, 2] * 8 == 6


@pytest.mark.parametrize("method", ["bilinear", "malvar"])
@pytest.mark.parametrize("pattern", sorted(CFA_PATTERNS))
def test_demosaic_exact_on_linear_colour(method, pattern):
    rgb = _smooth_rgb()
    out = demosaic(mosaic(rgb, pattern), pattern, method=method, domain="linear")
    np.testing.assert_allclose(out[2:-2, 2:-2], rgb[2:-2, 2:-2], rtol=1e-6)
    # a uniform colour comes back everywhere, borders included (mirror keeps the phase)
    flat = np.broadcast_to([0.2, 3.0, 40.0], (9, 11, 3))
    np.testing.assert_allclose(demosaic(mosaic(flat, pattern), pattern, method=method,
                                        domain="linear"), flat, rtol=1e-6)
    np.testing.assert_allclose(demosaic(mosaic(flat, pattern), pattern, method=method),
                               flat, rtol=1e-5)


def test_log_domain_stays_positive_at_hdr_edges():
    rgb = np.full((16, 16, 3), 1.0)
    rgb[:, 8:] = [5e4, 3e4, 1e4]  # a 1e4:1 edge
    raw = mosaic(rgb)
    lin = demosaic(raw, method="malvar", domain="linear")
    assert lin.min() == 0.0  # the linear filter overshoots below zero (clipped)
    log = demosaic(raw, method="malvar", domain="log")
    assert log.min() > 0  # ratios are interpolated: positive, whatever the contrast
    assert np.allclose(log[:, :5], 1.0) and np.allclose(log[:, 11:], rgb[:, 11:])
    bil = demosaic(raw, method="bilinear", domain="log")  # no negative lobes: no overshoot
    assert bil.min() >= 1.0 - 1e-5 and bil.max() <= 5e4 * (1 + 1e-5)


def test_demosaic_fills_missing_pixels():
    rgb = _smooth_rgb()
    raw = mosaic(rgb).astype(np.float64)
    raw[10, 10] = np.nan
    out = demosaic(raw, domain="linear", method="bilinear")
    assert np.all(np.isfinite(out))
    assert out[10, 10, 0] == pytest.approx(rgb[10, 10, 0], rel=1e-6)  # R from R 2 px away


def test_colour_errors_by_hand():
    ref = _smooth_rgb()
    e = colour_errors(0.5 * ref, ref)  # a global scale is no error
    assert e["scale"] == pytest.approx(2.0)
    assert max(e["rms_log_error"]) < 1e-9 and e["ciede2000_mean"] < 1e-6
    tinted = ref * np.array([1.1, 1.0, 1.0])  # 10 % more red
    e = colour_errors(tinted, ref)
    assert e["rms_log_chroma"][0] > e["rms_log_chroma"][1] > 0
    assert 1.0 < e["ciede2000_median"] < 10.0
    with pytest.raises(ValueError, match="one shape"):
        colour_errors(ref[:, :3], ref)


def test_tonemap_rgb_keeps_hue_order():
    rgb = _smooth_rgb()
    png = tonemap_rgb(rgb)
    assert png.dtype == np.uint8 and png.shape == rgb.shape
    # the display keeps each pixel's channel order
    for i, j in ((1, 0), (0, 2), (1, 2)):
        brighter = rgb[..., i] > rgb[..., j]
        assert brighter.any() and np.all(png[..., i][brighter] >= png[..., j][brighter])


def test_colour_scene_through_the_rig():
    from asynhdr.reconstruct import reconstruct
    from asynhdr.rig import Rig
    from asynhdr.simulate import simulate

    h = w = 24
    rgb = np.ones((h, w, 3))
    rgb[:, :12] = [400.0, 100.0, 25.0]   # orange
    rgb[:, 12:] = [20.0, 60.0, 300.0]    # blue
    sc = colour_scene(rgb, width=w, height=h, name="two patches")
    assert sc.metadata["cfa"] == "rggb"
    rig = Rig()
    rec = simulate(sc, rig=rig, sensor="ideal", n_cycles=1, rng=0)
    rec.metadata.update(sc.metadata)
    img = reconstruct(rec, method="invert")[0]
    out = reconstruct_colour(img, rec.metadata["cfa"])
    inner = np.zeros((h, w), dtype=bool)
    inner[2:-2, 2:10] = inner[2:-2, 14:-2] = True  # away from the border and the edge
    e = colour_errors(out, sc.rgb, mask=inner)
    print("two-patch colour error:", e)
    assert e["ciede2000_median"] < 2.0 and max(e["rms_log_error"]) < 0.1
    # reduced to grey, the same scene has no colour left: a large error
    grey = np.repeat(colour._luma(out)[..., None], 3, axis=2)
    assert colour_errors(grey, sc.rgb, mask=inner)["ciede2000_median"] > 20


def test_cli_colour_simulate_and_reconstruct(tmp_path):
    from typer.testing import CliRunner

    from asynhdr.cli import _register, app
    from asynhdr.io import open_recording
    from asynhdr.io.images import read_image, read_metadata

    _register()
    rgb = np.ones((24, 24, 3), dtype=np.float32)
    rgb[:, :12] = [400.0, 100.0, 25.0]
    rgb[:, 12:] = [20.0, 60.0, 300.0]
    scene = tmp_path / "patches.npy"
    np.save(scene, rgb)
    runner = CliRunner()
    grey = runner.invoke(app, ["simulate", str(scene), "--width", "24", "--height", "24",
                               "--n-cycles", "1", "--preset", "ideal", "-o",
                               str(tmp_path / "grey.h5")])
    assert grey.exit_code == 0, grey.output
    assert "reduced to luminance" in " ".join(grey.output.split())
    assert "cfa" not in open_recording(tmp_path / "grey.h5").metadata
    res = runner.invoke(app, ["simulate", str(scene), "--colour", "--width", "24", "--height",
                              "24", "--n-cycles", "1", "--preset", "ideal", "-o",
                              str(tmp_path / "col.h5")])
    assert res.exit_code == 0, res.output
    assert open_recording(tmp_path / "col.h5").metadata["cfa"] == "rggb"
    out = tmp_path / "out"
    rec = runner.invoke(app, ["reconstruct", str(tmp_path / "col.h5"), "--method", "invert",
                              "-o", str(out), "--formats", "exr,png"])
    assert rec.exit_code == 0, rec.output
    assert "demosaiced (malvar) to RGB" in rec.output
    img = read_image(out / "col_invert_0000.exr")
    assert img.shape == (24, 24, 3)
    assert read_metadata(out / "col_invert_0000.exr")["cfa"] == "rggb"
    inner = np.zeros((24, 24), dtype=bool)
    inner[2:-2, 2:10] = inner[2:-2, 14:-2] = True
    assert colour_errors(img, rgb, mask=inner)["ciede2000_median"] < 2.0
    bad = runner.invoke(app, ["simulate", "chart", "--cfa", "rggb", "-o",
                              str(tmp_path / "x.h5")])
    assert bad.exit_code == 2 and "needs an RGB image" in " ".join(bad.output.split())
