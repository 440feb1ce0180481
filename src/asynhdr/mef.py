"""Multi-exposure fusion (Debevec and Malik 1997) through OpenCV.

Debevec and Malik, "Recovering High Dynamic Range Radiance Maps from Photographs",
SIGGRAPH 1997, Eq. 6: with ``g`` the camera's log response and ``w`` a hat weighting,

    ln E = sum_j w(Z_j) (g(Z_j) - ln dt_j) / sum_j w(Z_j)

OpenCV implements it (``cv2.createMergeDebevec``: response ``exp g`` given, or linear;
weights ``w(z) = z`` below half range, ``z_max - z`` above, 1e-6 at both ends, averaged
over channels) for 8-bit and 16-bit images, and recovers ``g`` from a bracket
(``cv2.createCalibrateDebevec``, Eq. 3 of the paper). :func:`merge_debevec` and
:func:`calibrate_debevec` call it; :func:`fuse_frames` takes a simulated frame camera's
frames (any bit depth), whose response is known and linear, to radiance in lux.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
import numpy.typing as npt

from asynhdr.framecam import FrameCamera

__all__ = ["calibrate_debevec", "fuse_frames", "merge_debevec"]


def _stack(images: Sequence[npt.ArrayLike], exposure_s: Sequence[float],
           what: str) -> tuple[list[np.ndarray], np.ndarray]:
    imgs = [np.ascontiguousarray(im) for im in images]
    times = np.asarray(exposure_s, dtype=np.float32)
    if not imgs:
        raise ValueError(f"{what}: no images")
    if times.shape != (len(imgs),):
        raise ValueError(f"{what}: {len(imgs)} images but {times.size} exposure times")
    if np.any(~(times > 0)):
        raise ValueError(f"{what}: exposure times must be > 0 s")
    first = imgs[0]
    if first.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{what}: images must be uint8 or uint16, got {first.dtype}")
    for i, im in enumerate(imgs):
        if im.shape != first.shape or im.dtype != first.dtype:
            raise ValueError(f"{what}: image {i} is {im.shape} {im.dtype}, expected "
                             f"{first.shape} {first.dtype}")
    return imgs, times


def calibrate_debevec(images: Sequence[npt.ArrayLike], exposure_s: Sequence[float], *,
                      samples: int = 70, smoothness: float = 10.0) -> np.ndarray:
    """The camera response ``exp g(z)`` recovered from a bracket of 8-bit images
    (``cv2.createCalibrateDebevec``, grid sampling, ``samples`` points, smoothness
    ``lambda``): float32 ``(256, 1, channels)``."""
    imgs, times = _stack(images, exposure_s, "calibrate_debevec")
    if imgs[0].dtype != np.uint8:
        raise ValueError("calibrate_debevec: OpenCV calibrates 8-bit brackets only")
    cal = cv2.createCalibrateDebevec(samples=samples, lambda_=smoothness, random=False)
    return np.asarray(cal.process(imgs, times))


def merge_debevec(images: Sequence[npt.ArrayLike], exposure_s: Sequence[float], *,
                  response: npt.ArrayLike | None = None) -> np.ndarray:
    """Fuse a bracket (uint8 or uint16, ``(height, width)`` or ``(height, width, 3)``,
    exposure times in seconds) into a radiance map, float32, in response units per
    second (``cv2.createMergeDebevec``; ``response`` from :func:`calibrate_debevec`, or
    linear when ``None``)."""
    imgs, times = _stack(images, exposure_s, "merge_debevec")
    merge = cv2.createMergeDebevec()
    if response is None:
        return np.asarray(merge.process(imgs, times))
    return np.asarray(merge.process(imgs, times, np.asarray(response, dtype=np.float32)))


def fuse_frames(camera: FrameCamera, frames: Sequence[npt.ArrayLike],
                exposure_s: npt.ArrayLike) -> np.ndarray:
    """Radiance (lux at the sensor, float32) from a frame camera's bracket.

    The frames' digital numbers are spread over the 16-bit range,
    ``Z = round(DN * 65535 / (2^bits - 1))``, so that saturation lands on OpenCV's top
    code (weight 1e-6), and merged with the known linear response. Debevec's estimate
    is then ``Z / t`` averaged; ``L = Z/t * (2^bits - 1) / 65535 * K / (eta Phi a_px)``.
    """
    dn = [np.asarray(f) for f in frames]
    scale16 = 65535.0 / camera.max_dn
    z = [np.clip(np.floor(f.astype(np.float64) * scale16 + 0.5), 0, 65535).astype(np.uint16)
         for f in dn]
    merged = merge_debevec(z, np.asarray(exposure_s, dtype=np.float64).tolist()
                           ).astype(np.float64)
    lux = merged / scale16 * camera.gain_e_per_dn / camera.electrons_per_lux_s
    return lux.astype(np.float32)
