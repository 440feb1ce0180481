"""Scenes: the paper's step chart, flat fields, real radiance maps resized to a sensor."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from asynhdr.scene import (
    PAPER_DENSITIES,
    PAPER_ILLUMINANCE_LUX,
    Scene,
    flat_field,
    from_radiance_map,
    luminance,
    step_chart,
)

# Typed from the paper (Wu et al. 2024), level 1 to 36, independently of the module.
PAPER_TEXT = (
    "0.00 0.10 0.20 0.30 0.40 0.50 1.20 1.30 1.50 0.60 0.70 0.80 0.90 1.00 1.10 "
    "1.70 1.90 2.10 2.30 2.50 2.70 2.90 3.43 3.73 4.02 4.32 4.63 4.92 5.23 5.52 5.82 6.27 "
    "6.72 7.17 7.63 8.22"
)
SENSORS = [(346, 260), (640, 480), (1280, 720), (37, 17)]


def test_paper_constants() -> None:
    assert list(PAPER_DENSITIES) == [float(s) for s in PAPER_TEXT.split()]
    assert len(PAPER_DENSITIES) == 36
    assert PAPER_ILLUMINANCE_LUX == 160_000.0


@pytest.mark.parametrize(("width", "height"), SENSORS)
def test_step_chart_patches(width: int, height: int) -> None:
    s = step_chart(width=width, height=height)
    assert s.radiance.shape == (height, width)
    assert s.radiance.dtype == np.float32
    assert s.unit == "lux"
    assert s.rois is not None and s.truth is not None and s.densities is not None
    assert sorted(s.rois) == list(range(36))
    densities = [float(v) for v in PAPER_TEXT.split()]
    expected = [160_000.0 * 10.0 ** (-d) for d in densities]
    assert s.truth.tolist() == expected  # exact, float64
    assert s.densities.tolist() == densities
    background = np.float32(160_000.0 * 10.0 ** (-(8.22 + 1.0)))
    covered = np.zeros((height, width), dtype=np.int32)
    for i, (y0, y1, x0, x1) in s.rois.items():
        assert 0 <= y0 < y1 <= height and 0 <= x0 < x1 <= width
        # the ROI holds exactly level i+1's radiance (level order = the paper's)
        assert np.all(s.radiance[y0:y1, x0:x1] == np.float32(expected[i]))
        # strictly inside its patch: one pixel more on every side is still the patch
        assert np.all(s.radiance[y0 - 1 : y1 + 1, x0 - 1 : x1 + 1] == np.float32(expected[i]))
        covered[y0:y1, x0:x1] += 1
    assert covered.max() == 1  # no two ROIs overlap
    # row-major, 9 columns: level i+1 is right of level i in a row, rows go down
    for i in range(35):
        a, b = s.rois[i], s.rois[i + 1]
        if (i + 1) % 9:
            assert b[0] == a[0] and b[2] >= a[3]
            # a guard band of background lies between neighbouring patches
            assert np.any(s.radiance[a[0], a[3] : b[2]] == background)
        else:
            assert b[0] >= a[1]
    # the border is background
    assert s.radiance[0, 0] == background and s.radiance[-1, -1] == background


def test_step_chart_options() -> None:
    s = step_chart(
        width=100, height=60, densities=[0.0, 1.0, 2.0, 3.0], illuminance_lux=1000.0,
        columns=2, guard_px=4, roi_margin=0.0, background_density=math.inf,
    )
    assert s.rois is not None and s.truth is not None
    assert s.truth.tolist() == [1000.0, 100.0, 10.0, 1.0]
    # 2x2 grid, guard 4: patch width (100 - 3*4)//2 = 44, height (60 - 3*4)//2 = 24
    assert s.rois[0] == (4, 28, 4, 48)
    assert s.rois[3] == (32, 56, 52, 96)
    assert float(s.radiance.sum()) == pytest.approx(44 * 24 * 1111.0)
    assert s.radiance[0, 0] == 0.0  # background of infinite density is black
    # a 20 % margin: ceil(0.2*44) = 9 px and ceil(0.2*24) = 5 px on each side
    r = step_chart(width=100, height=60, densities=[0.0, 1.0, 2.0, 3.0], columns=2, guard_px=4)
    assert r.rois is not None
    assert r.rois[0] == (4 + 5, 28 - 5, 4 + 9, 48 - 9)


def test_step_chart_too_small() -> None:
    with pytest.raises(ValueError, match="37x17"):
        step_chart(width=36, height=17)
    with pytest.raises(ValueError, match="37x17"):
        step_chart(width=37, height=16)
    step_chart(width=37, height=17)  # the stated minimum works
    with pytest.raises(ValueError, match="roi_margin"):
        step_chart(width=346, height=260, roi_margin=0.5)
    with pytest.raises(ValueError, match="densities"):
        step_chart(width=346, height=260, densities=[0.1, -0.2])


def test_scene_is_frozen_and_read_only() -> None:
    s = step_chart(width=346, height=260)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.unit = "relative"  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        s.radiance[0, 0] = 1.0
    assert s.width == 346 and s.height == 260
    with pytest.raises(ValueError, match="negative"):
        Scene(radiance=np.full((2, 2), -1.0, dtype=np.float32))
    with pytest.raises(ValueError, match="outside"):
        Scene(radiance=np.ones((4, 4), dtype=np.float32), rois={0: (0, 5, 0, 4)})


def test_flat_field_uniform() -> None:
    s = flat_field(width=30, height=20, radiance=2.5, unit="lux")
    assert s.radiance.shape == (20, 30) and s.radiance.dtype == np.float32
    assert np.all(s.radiance == np.float32(2.5))
    assert s.unit == "lux"
    assert s.truth is not None and s.truth.tolist() == [2.5]
    with pytest.raises(ValueError, match="radiance"):
        flat_field(width=3, height=2, radiance=float("nan"))


def _smooth_map(h: int, w: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return (100.0 * np.exp(-((x - w / 3) ** 2 + (y - h / 2) ** 2) / (2 * (w / 5) ** 2))
            + 1.0 + 0.01 * x).astype(np.float32)


@pytest.mark.parametrize(("width", "height"), [(346, 260), (173, 97), (1280, 720)])
def test_from_radiance_map_preserves_mean(width: int, height: int) -> None:
    src = _smooth_map(480, 640)
    s = from_radiance_map(src, width=width, height=height, scale=3.0, unit="lux", name="blob",
                          fit="stretch")
    assert s.radiance.shape == (height, width) and s.radiance.dtype == np.float32
    assert s.unit == "lux" and s.name == "blob"
    mean_in = 3.0 * float(src.astype(np.float64).mean())
    assert float(s.radiance.astype(np.float64).mean()) == pytest.approx(mean_in, rel=0.01)
    assert float(s.radiance.min()) >= 0.0


def test_from_radiance_map_same_size_and_crop() -> None:
    src = _smooth_map(40, 60)
    s = from_radiance_map(src, width=60, height=40)
    assert np.array_equal(s.radiance, src) and s.rois == {0: (0, 40, 0, 60)}
    # crop to the sensor's aspect: 60x40 -> centre 40x40 -> 20x20
    c = from_radiance_map(src, width=20, height=20, fit="crop")
    assert c.radiance.shape == (20, 20)
    block = src[:, 10:50].astype(np.float64).reshape(20, 2, 20, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(c.radiance, block, rtol=1e-5)


def test_from_radiance_map_rejects_bad_values() -> None:
    src = _smooth_map(20, 30)
    bad = src.copy()
    bad[0, :3] = np.nan
    bad[1, 0] = np.inf
    with pytest.raises(ValueError, match="4 non-finite values"):
        from_radiance_map(bad, width=10, height=10)
    neg = src.copy()
    neg[2, :5] = -0.1
    with pytest.raises(ValueError, match="5 negative"):
        from_radiance_map(neg, width=10, height=10)
    with pytest.raises(ValueError, match="2-D"):
        from_radiance_map(np.ones((4, 4, 3)), width=2, height=2)
    with pytest.raises(ValueError, match="scale"):
        from_radiance_map(src, width=10, height=10, scale=0.0)


def test_luminance_rec709() -> None:
    rgb = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [2.0, 2.0, 2.0]])
    np.testing.assert_allclose(luminance(rgb), [0.2126, 0.7152, 0.0722, 2.0], rtol=1e-6)
    assert luminance(rgb).dtype == np.float32
    with pytest.raises(ValueError, match="alpha"):
        luminance(np.ones((2, 2, 4)))
