"""Image files (real HDR maps in, HDR images out) and tone mapping."""

from __future__ import annotations

import json
import logging
import math
import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import OpenEXR
import pytest
import tifffile

from asynhdr.io import images
from asynhdr.io.images import read_image, read_metadata, read_radiance, write_image
from asynhdr.tonemap import tonemap

SCENES = ["Desk.exr", "StillLife.exr", "MtTamWest.exr", "nancy_church.hdr"]


# --------------------------------------------------------------------------- real files


@pytest.fixture(scope="module")
def real_scenes(data_dir: Path) -> dict[str, tuple[np.ndarray, dict[str, Any]]]:
    """Each real scene read once for the whole module."""
    return {name: read_radiance(data_dir / "hdr" / "scenes" / name) for name in SCENES}


def _manifest_entry(manifest: dict[str, Any], name: str) -> dict[str, Any]:
    return manifest["hdr"][f"hdr/scenes/{name}"]


@pytest.mark.parametrize("name", SCENES)
def test_real_scene_geometry(name: str, real_scenes: dict, manifest: dict[str, Any]) -> None:
    entry = _manifest_entry(manifest, name)
    assert "width x height" in entry["what"]  # the manifest states the order
    m = re.search(r"(\d+)x(\d+)", entry["what"])
    assert m is not None
    width, height = int(m.group(1)), int(m.group(2))
    y, info = real_scenes[name]
    assert y.shape == (height, width)
    assert y.dtype == np.float32
    assert (info["width"], info["height"]) == (width, height)
    assert info["format"] == name.rsplit(".", 1)[1]
    assert float(y.min()) >= 0.0 and bool(np.all(np.isfinite(y)))


@pytest.mark.parametrize("name", ["Desk.exr", "StillLife.exr"])
def test_real_scene_non_positive_counts(
    name: str, real_scenes: dict, manifest: dict[str, Any], data_dir: Path
) -> None:
    entry = _manifest_entry(manifest, name)
    m = re.search(r"([\d,]+) pixels have non-positive luminance", entry["note"])
    assert m is not None
    expected_non_positive = int(m.group(1).replace(",", ""))
    y, info = real_scenes[name]
    # the manifest counts luminance <= 0 before clipping
    assert info["non_positive"] == expected_non_positive
    # independent count of strictly negative luminance: the RGBA array OpenEXR
    # returns by default, weighted in float64
    with OpenEXR.File(str(data_dir / "hdr" / "scenes" / name)) as f:
        rgba = np.asarray(f.channels()["RGBA"].pixels, dtype=np.float64)
    lum = 0.2126 * rgba[..., 0] + 0.7152 * rgba[..., 1] + 0.0722 * rgba[..., 2]
    assert info["clipped_negative"] == int(np.count_nonzero(lum < 0))
    assert int(np.count_nonzero(lum <= 0)) == expected_non_positive
    # the loader's map is that luminance with negatives set to 0
    np.testing.assert_allclose(y, np.maximum(lum, 0.0), rtol=1e-6, atol=0.0)
    assert int(np.count_nonzero(y == 0)) == expected_non_positive


def test_real_hdr_dynamic_range(real_scenes: dict, manifest: dict[str, Any]) -> None:
    entry = _manifest_entry(manifest, "nancy_church.hdr")
    m = re.search(r"spans ([\d.]+) stops max/min", entry["what"])
    assert m is not None
    y, _ = real_scenes["nancy_church.hdr"]
    assert round(math.log2(float(y.max()) / float(y.min())), 1) == float(m.group(1))


# --------------------------------------------------------------------------- synthetic reads


def _write_exr(path: Path, channels: dict[str, np.ndarray]) -> None:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def test_exr_channel_order_and_alpha(tmp_path: Path) -> None:
    h, w = 3, 4
    r = np.full((h, w), 1.0, np.float16)
    g = np.full((h, w), 2.0, np.float16)
    b = np.full((h, w), 4.0, np.float16)
    a = np.full((h, w), 100.0, np.float16)
    _write_exr(tmp_path / "rgba.exr", {"R": r, "G": g, "B": b, "A": a})
    y, info = read_radiance(tmp_path / "rgba.exr")
    np.testing.assert_allclose(y, 0.2126 * 1 + 0.7152 * 2 + 0.0722 * 4, rtol=1e-6)
    assert info["channels"] == ["R", "G", "B"]
    _write_exr(tmp_path / "y.exr", {"Y": np.full((h, w), 7.5, np.float32)})
    y, _ = read_radiance(tmp_path / "y.exr")
    assert np.all(y == np.float32(7.5))


def test_hdr_channel_order(tmp_path: Path) -> None:
    bgr = np.zeros((2, 3, 3), np.float32)
    bgr[..., 0], bgr[..., 1], bgr[..., 2] = 4.0, 2.0, 1.0  # B, G, R as OpenCV stores them
    assert cv2.imwrite(str(tmp_path / "c.hdr"), bgr)
    y, info = read_radiance(tmp_path / "c.hdr")
    np.testing.assert_allclose(y, 0.2126 * 1 + 0.7152 * 2 + 0.0722 * 4, rtol=1e-6)
    assert info["format"] == "hdr"


def test_npy_rgba_and_negative_clip(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rgba = np.ones((4, 5, 4), np.float32)
    rgba[0, :3, :3] = -0.5  # three pixels of negative luminance
    rgba[1, 0, :3] = 0.0  # one of zero luminance
    np.save(tmp_path / "m.npy", rgba)
    with caplog.at_level(logging.INFO, logger="asynhdr.io.images"):
        y, info = read_radiance(tmp_path / "m.npy")
    assert info["clipped_negative"] == 3 and info["non_positive"] == 4
    assert "clipped 3 negative" in caplog.text
    assert y.shape == (4, 5) and float(y.min()) == 0.0
    assert np.count_nonzero(y == 0) == 4


def test_float_tiff_read(tmp_path: Path) -> None:
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    tifffile.imwrite(tmp_path / "a.tif", a)
    y, info = read_radiance(tmp_path / "a.tif")
    assert np.array_equal(y, a) and info["format"] == "tiff"
    tifffile.imwrite(tmp_path / "i.tif", a.astype(np.uint16))
    with pytest.raises(ValueError, match="floating-point"):
        read_radiance(tmp_path / "i.tif")


# --------------------------------------------------------------------------- errors


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nowhere\.exr"):
        read_radiance(tmp_path / "nowhere.exr")


@pytest.mark.parametrize(
    ("ext", "expected"),
    [(".exr", "OpenEXR"), (".hdr", "Radiance"), (".npy", "NumPy"), (".tif", "TIFF")],
)
def test_not_an_image(tmp_path: Path, ext: str, expected: str) -> None:
    p = tmp_path / f"notes{ext}"
    p.write_text("these are notes, not pixels\n")
    with pytest.raises(ValueError, match=f"notes{re.escape(ext)}.*not .*{expected}"):
        read_radiance(p)


def test_nan_values_rejected(tmp_path: Path) -> None:
    a = np.ones((4, 4), np.float32)
    a[0, :2] = np.nan
    np.save(tmp_path / "nan.npy", a)
    with pytest.raises(ValueError, match=r"nan\.npy: 2 pixels have NaN"):
        read_radiance(tmp_path / "nan.npy")
    a[3, 3] = np.inf
    _write_exr(tmp_path / "nan.exr", {"R": a, "G": a, "B": a})
    with pytest.raises(ValueError, match=r"nan\.exr: 3 pixels have NaN"):
        read_radiance(tmp_path / "nan.exr")


def test_unknown_extension(tmp_path: Path) -> None:
    p = tmp_path / "photo.jpg"
    p.write_bytes(b"\xff\xd8")
    with pytest.raises(ValueError, match=r"photo\.jpg.*\.exr, \.hdr, \.npy, \.tif, \.tiff"):
        read_radiance(p)
    with pytest.raises(ValueError, match=r"\.png"):
        write_image(tmp_path / "out.jpg", np.ones((2, 2)))


# --------------------------------------------------------------------------- writing


def _test_image(rng: np.random.Generator) -> np.ndarray:
    a = (10.0 ** rng.uniform(-6, 6, size=(37, 53))).astype(np.float32)
    a[0, 0], a[0, 1], a[0, 2] = 0.0, np.finfo(np.float32).tiny, np.finfo(np.float32).max
    return a


@pytest.mark.parametrize("ext", [".exr", ".npy", ".tiff", ".tif"])
def test_round_trip_exact(tmp_path: Path, ext: str) -> None:
    a = _test_image(np.random.default_rng(1))
    a[1, 0] = -3.25  # negative values survive the float formats
    out = write_image(tmp_path / f"img{ext}", a)
    assert out == tmp_path / f"img{ext}"
    b = read_image(out)
    assert b.dtype == np.float32 and b.shape == a.shape
    assert np.array_equal(b.view(np.uint32), a.view(np.uint32))  # bit equal
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"img{ext}"]  # no temporaries


def test_exr_is_single_y_channel(tmp_path: Path) -> None:
    write_image(tmp_path / "y.exr", np.ones((2, 3)))
    with OpenEXR.File(str(tmp_path / "y.exr"), separate_channels=True) as f:
        chans = f.channels()
        assert list(chans) == ["Y"]
        assert chans["Y"].pixels.dtype == np.float32


def test_hdr_round_trip_within_rgbe_precision(tmp_path: Path) -> None:
    a = (10.0 ** np.random.default_rng(2).uniform(-3, 5, size=(20, 30))).astype(np.float32)
    write_image(tmp_path / "img.hdr", a)
    y, info = read_radiance(tmp_path / "img.hdr")
    assert y.shape == a.shape and info["format"] == "hdr"
    np.testing.assert_allclose(y, a, rtol=0.01)
    with pytest.raises(ValueError, match="negative"):
        write_image(tmp_path / "neg.hdr", -a)
    assert not (tmp_path / "neg.hdr").exists()


def test_png_is_uint8(tmp_path: Path) -> None:
    a = _test_image(np.random.default_rng(3))
    write_image(tmp_path / "img.png", a, tonemap="reinhard", tonemap_options={"gamma": 1.8})
    u = cv2.imread(str(tmp_path / "img.png"), cv2.IMREAD_UNCHANGED)
    assert u is not None
    assert u.dtype == np.uint8 and u.shape == a.shape
    assert np.array_equal(u, tonemap(a, method="reinhard", gamma=1.8))


@pytest.mark.parametrize("ext", [".exr", ".tiff"])
def test_metadata_round_trip(tmp_path: Path, ext: str) -> None:
    meta = {"unit": "relative", "method": "exp", "k": 10, "c": np.float64(0.25),
            "shape": np.array([2, 3])}
    write_image(tmp_path / f"m{ext}", np.ones((2, 3)), metadata=meta)
    assert read_metadata(tmp_path / f"m{ext}") == {
        "unit": "relative", "method": "exp", "k": 10, "c": 0.25, "shape": [2, 3],
    }
    write_image(tmp_path / f"none{ext}", np.ones((2, 3)))
    assert read_metadata(tmp_path / f"none{ext}") == {}
    if ext == ".exr":
        with OpenEXR.File(str(tmp_path / "m.exr"), header_only=True) as f:
            assert json.loads(f.header()["asynhdr_metadata"])["unit"] == "relative"


@pytest.mark.parametrize(
    ("image", "match"),
    [
        (np.array([[1.0, np.nan], [np.inf, 2.0]]), "2 NaN or infinite"),
        (np.ones((2, 2, 3)), "2-D"),
        (np.ones(5), "2-D"),
        (np.array([[1e39]]), "1 NaN or infinite"),  # overflows float32
    ],
)
@pytest.mark.parametrize("ext", [".exr", ".png", ".npy"])
def test_write_rejects_bad_images(tmp_path: Path, image: np.ndarray, match: str, ext: str) -> None:
    with pytest.raises(ValueError, match=match):
        write_image(tmp_path / f"bad{ext}", image)
    assert list(tmp_path.iterdir()) == []


def test_write_rejects_unserialisable_metadata(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="JSON"):
        write_image(tmp_path / "m.exr", np.ones((2, 2)), metadata={"f": object()})
    assert list(tmp_path.iterdir()) == []


def test_failing_write_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(tmp: Path, a: np.ndarray, meta: str | None) -> None:
        tmp.write_bytes(b"half a file")
        raise OSError("disk full")

    monkeypatch.setitem(images._WRITERS, "npy", broken)
    with pytest.raises(OSError, match="disk full"):
        write_image(tmp_path / "img.npy", np.ones((2, 2)))
    assert list(tmp_path.iterdir()) == []
    # an existing file is left as it was
    np.save(tmp_path / "img.npy", np.zeros((1, 1), np.float32))
    before = (tmp_path / "img.npy").read_bytes()
    with pytest.raises(OSError, match="disk full"):
        write_image(tmp_path / "img.npy", np.ones((2, 2)))
    assert [p.name for p in tmp_path.iterdir()] == ["img.npy"]
    assert (tmp_path / "img.npy").read_bytes() == before


# --------------------------------------------------------------------------- tone mapping

METHODS = ["log", "reinhard", "linear"]


@pytest.mark.parametrize("method", METHODS)
def test_tonemap_monotone(method: str) -> None:
    ramp = np.logspace(-4, 4, 2000).reshape(20, 100)
    ramp[0, :5] = 0.0
    u = tonemap(ramp, method=method)
    assert u.dtype == np.uint8 and u.shape == ramp.shape
    assert np.all(np.diff(u.ravel().astype(int)) >= 0)
    assert u.min() == 0 and u.max() == 255  # clipped at the percentiles: full range
    # a shuffled image keeps the order of its values
    rng = np.random.default_rng(4)
    x = rng.lognormal(0.0, 3.0, size=(30, 40))
    v = tonemap(x, method=method).ravel()
    assert np.all(np.diff(v[np.argsort(x.ravel())].astype(int)) >= 0)


@pytest.mark.parametrize("method", METHODS)
def test_tonemap_constant_and_zero(method: str) -> None:
    assert np.all(tonemap(np.full((4, 5), 3.0), method=method) == 128)
    assert np.all(tonemap(np.zeros((4, 5)), method=method) == 0)


def test_tonemap_log_values() -> None:
    # decades 1, 10, 100 with percentiles 0 and 100: 0, 127.5 -> 128, 255; zero -> floor -> 0
    img = np.array([[1.0, 10.0, 100.0, 0.0]])
    u = tonemap(img, method="log", low_percentile=0.0, high_percentile=100.0)
    assert u.tolist() == [[0, 128, 255, 0]]


def test_tonemap_linear_values() -> None:
    # 0..255 between percentiles 0 and 100 with gamma 1 is the identity
    img = np.arange(256, dtype=np.float64).reshape(16, 16) * 0.5 + 3.0
    u = tonemap(img, method="linear", low_percentile=0.0, high_percentile=100.0, gamma=1.0)
    assert u.ravel().tolist() == list(range(256))
    # gamma 2: 255 * sqrt(k / 255)
    u = tonemap(img, method="linear", low_percentile=0.0, high_percentile=100.0, gamma=2.0)
    assert u.ravel().tolist() == [int(255 * math.sqrt(k / 255) + 0.5) for k in range(256)]


def test_tonemap_reinhard_values() -> None:
    # half the pixels at 1, half at 4: log-average 2, key 0.18 -> scaled 0.09 and 0.36;
    # Lwhite = scaled high percentile = 0.36 maps to 1.0 -> 255;
    # 0.09 (1 + 0.09 / 0.36^2) / 1.09 = 0.139908..., ^(1/2.2) = 0.40902 -> 104
    img = np.array([[1.0, 1.0, 4.0, 4.0]])
    u = tonemap(img, method="reinhard", gamma=2.2)
    assert u.tolist() == [[104, 104, 255, 255]]


def test_tonemap_errors() -> None:
    with pytest.raises(ValueError, match="'linear', 'log', 'reinhard'"):
        tonemap(np.ones((2, 2)), method="drago")
    with pytest.raises(ValueError, match="1 NaN"):
        tonemap(np.array([[1.0, np.nan]]))
    with pytest.raises(ValueError, match="percentile"):
        tonemap(np.ones((2, 2)), low_percentile=60, high_percentile=40)
