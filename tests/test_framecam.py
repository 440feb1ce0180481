"""The frame camera against its closed form; Debevec fusion against OpenCV and against an
independent implementation, on simulated frames and on the real memorial bracket."""

from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from asynhdr.framecam import (
    PHOTONS_PER_LUX_S_M2,
    FrameCamera,
    budget_bracket,
    capture,
    exposure_bracket,
    get_frame_camera,
)
from asynhdr.mef import calibrate_debevec, fuse_frames, merge_debevec


def test_photon_constant_by_hand() -> None:
    # 1 lux of 555 nm light is 1/683 W/m^2; a photon carries h c / 555 nm
    e_photon = 6.62607015e-34 * 299792458.0 / 555e-9
    assert PHOTONS_PER_LUX_S_M2 == pytest.approx(1 / 683 / e_photon, rel=1e-12)
    assert PHOTONS_PER_LUX_S_M2 == pytest.approx(4.09e15, rel=0.001)


@pytest.mark.parametrize(("lux", "exposure_s"), [(100.0, 1e-3), (100.0, 1e-5), (0.5, 0.02)])
def test_noise_matches_the_closed_form(lux: float, exposure_s: float) -> None:
    cam = get_frame_camera("imx174")
    img = capture(cam, np.full((400, 500), lux), exposure_s=exposure_s, rng=7)
    # computed here from the preset's figures, not from the camera's own helpers
    k = 32_691.0 / 4095.0
    e = (0.77 * PHOTONS_PER_LUX_S_M2 * (5.86e-6) ** 2 * lux + 10.0) * exposure_s
    mu = e / k
    var = (e + 6.83**2) / k**2 + 1 / 12
    n = img.size
    assert abs(img.mean() - mu) < 5 * math.sqrt(var / n)
    assert img.var() == pytest.approx(var, rel=5 * math.sqrt(2 / n) + 0.01)
    assert cam.expected_dn(lux, exposure_s) == pytest.approx(mu)
    assert cam.expected_var_dn(lux, exposure_s) == pytest.approx(var)


def test_capture_saturates_and_repeats() -> None:
    cam = get_frame_camera("imx174")
    bright = capture(cam, np.full((50, 50), 1e6), exposure_s=1.0, rng=1)
    assert bright.dtype == np.uint16 and np.all(bright == 4095)
    a = capture(cam, np.full((8, 8), 3.0), exposure_s=0.01, rng=5)
    b = capture(cam, np.full((8, 8), 3.0), exposure_s=0.01, rng=5)
    assert np.array_equal(a, b)
    with pytest.raises(ValueError, match="exposure_s"):
        capture(cam, np.ones((2, 2)), exposure_s=0.0)
    with pytest.raises(ValueError, match="bit_depth"):
        FrameCamera(bit_depth=20)


def test_brackets() -> None:
    cam = get_frame_camera("imx174")
    ts = exposure_bracket(cam, l_min_lux=0.01, l_max_lux=1e4, n=10)
    assert ts.size == 10
    assert cam.expected_dn(1e4, ts[0]) == pytest.approx(0.9 * 4095)
    assert cam.electrons_per_lux_s * 0.01 * ts[-1] == pytest.approx(100.0)
    assert np.allclose(ts[1:] / ts[:-1], ts[1] / ts[0])
    # frames take at least 1/155 s: 2 ms and 4 ms cost 6.45 ms each
    ladder = [0.002, 0.004, 0.008, 0.016, 0.032]
    ft = 1 / 155
    used = 2 * ft + 0.008 + 0.016  # 36.9 ms
    short = budget_bracket(cam, ladder, budget_s=0.05)
    assert short.tolist() == [0.002, 0.004, 0.008, 0.016]  # 13.1 ms left: not > 16 ms
    longer = budget_bracket(cam, ladder, budget_s=0.06)
    assert longer.tolist()[:4] == [0.002, 0.004, 0.008, 0.016]
    assert longer[4] == pytest.approx(0.06 - used)  # 23.1 ms left fill one more frame
    assert sum(max(t, ft) for t in longer) == pytest.approx(0.06)


def test_fusion_of_simulated_frames_recovers_radiance() -> None:
    cam = get_frame_camera("imx174")
    lux = np.logspace(-1, 4, 200)[None, :].repeat(50, axis=0)
    ts = exposure_bracket(cam, l_min_lux=0.1, l_max_lux=1e4, n=10)
    frames = [capture(cam, lux, exposure_s=t, rng=i) for i, t in enumerate(ts)]
    out = fuse_frames(cam, frames, ts)
    rel = np.median(out, axis=0) / lux[0]
    # where the longest exposure collects 1,000 e- or more (lux >= 1), within 3 %; below,
    # hat-weighted log averaging of frames near the noise floor reads high (honestly)
    lit = lux[0] >= 1.0
    assert np.all(np.abs(rel[lit] - 1) < 0.03), rel[lit]
    assert np.all(np.abs(rel[~lit] - 1) < 0.3), rel[~lit]


def _debevec_numpy(images: list[np.ndarray], times: list[float], response: np.ndarray,
                   ) -> np.ndarray:
    """Debevec and Malik 1997, Eq. 6, written out independently of OpenCV: hat weights
    w(z) = min(z, 255 - z) with 1e-6 at 0 and 255, averaged over channels."""
    g = np.log(response.astype(np.float64)[:, 0, :])  # (256, channels)
    w = np.array([1e-6] + [float(min(z, 255 - z)) for z in range(1, 255)] + [1e-6])
    num = np.zeros(images[0].shape)
    den = np.zeros(images[0].shape[:2])
    for im, t in zip(images, times, strict=True):
        ww = w[im].mean(axis=2)
        gz = np.stack([g[im[..., c], c] for c in range(im.shape[2])], axis=-1)
        num += ww[..., None] * (gz - math.log(t))
        den += ww
    return np.exp(num / den[..., None])


def _memorial(data_dir: Path) -> tuple[list[np.ndarray], list[float]]:
    d = data_dir / "hdr" / "memorial"
    files = sorted(d.glob("memorial*.png"))
    times = [float(Fraction(s.strip())) for s in
             (d / "shutter_times.txt").read_text().splitlines() if s.strip()]
    return [cv2.imread(str(f)) for f in files], times


def test_memorial_bracket_through_the_fusion_path(data_dir: Path,
                                                  manifest: dict[str, Any]) -> None:
    facts = manifest["hdr"]["hdr/memorial/"]["what"]
    assert "16 LDR PNG exposures" in facts
    images, times = _memorial(data_dir)
    assert len(images) == len(times) == 16 and images[0].shape == (768, 512, 3)
    resp = calibrate_debevec(images, times)
    ours = merge_debevec(images, times, response=resp)
    # OpenCV's own result, called directly
    cal = cv2.createCalibrateDebevec().process(images, np.array(times, np.float32))
    own = cv2.createMergeDebevec().process(images, np.array(times, np.float32), cal)
    assert np.max(np.abs(ours / own - 1)) < 1e-6
    # and Eq. 6 computed here independently: float32 against float64, within 1e-5
    ref = _debevec_numpy(images, times, resp)
    assert np.max(np.abs(ours / ref - 1)) < 1e-5
    # manifest: about 17.8 stops max/min, 14.5 between the 0.1 and 99.9 percentiles
    y = 0.0722 * ours[..., 0] + 0.7152 * ours[..., 1] + 0.2126 * ours[..., 2]
    assert math.log2(y.max() / y.min()) == pytest.approx(17.8, abs=0.2)
    p = np.percentile(y, [0.1, 99.9])
    assert math.log2(p[1] / p[0]) == pytest.approx(14.5, abs=0.2)
