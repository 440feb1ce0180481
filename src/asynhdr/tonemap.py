"""Tone mapping: linear HDR images to 8-bit display images.

Pure functions, one per method, chosen by name from :data:`TONEMAP_METHODS`:

- ``"log"``: ``v = (log L - log lo) / (log hi - log lo)`` with ``lo``, ``hi`` the low
  and high percentiles of the positive pixels; zeros (and negatives) sit at ``lo``.
  Already perceptually spaced: no gamma.
- ``"reinhard"``: the global operator of Reinhard, Stark, Shirley and Ferwerda,
  "Photographic tone reproduction for digital images", SIGGRAPH 2002, eq. 1, 2, 4:
  ``Lbar = exp(mean(log L))``, ``Lm = a / Lbar * L`` with key ``a = 0.18``,
  ``Ld = Lm (1 + Lm / Lwhite**2) / (1 + Lm)`` with ``Lwhite`` the scaled high
  percentile (that pixel maps to display white); the log-average floors pixels at
  the low percentile of the positive ones, the mapping itself sends 0 to 0; then
  gamma.
- ``"linear"``: ``v = clip((L - lo) / (hi - lo), 0, 1)`` with percentiles over all
  pixels; then gamma.

Output: ``floor(255 * v ** (1 / gamma) + 0.5)`` as uint8 (``gamma`` applies to
``"reinhard"`` and ``"linear"``, whose ``v`` is linear in display luminance). Every
method is non-decreasing in ``L``. A constant image (no range between the
percentiles) maps to mid-grey 128, or to 0 where it is not positive.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

__all__ = ["REINHARD_KEY", "TONEMAP_METHODS", "StableLogToneCurve", "tonemap"]

REINHARD_KEY = 0.18
"""Key value ``a`` of Reinhard et al. 2002 (middle grey of the scaled image)."""

_MID_GREY = 128


def _positive_floor(image: np.ndarray, low_percentile: float) -> tuple[np.ndarray, float] | None:
    pos = image[image > 0]
    if pos.size == 0:
        return None
    return pos, float(np.percentile(pos, low_percentile))


def _display_log(image: np.ndarray, low: float, high: float, gamma: float) -> np.ndarray:
    got = _positive_floor(image, low)
    if got is None:
        return np.zeros(image.shape, dtype=np.float64)
    pos, lo = got
    hi = float(np.percentile(pos, high))
    if not hi > lo:
        return np.where(image > 0, _MID_GREY / 255.0, 0.0)
    log_lo, log_hi = math.log(lo), math.log(hi)
    v = (np.log(np.clip(image, lo, hi)) - log_lo) / (log_hi - log_lo)
    return np.clip(v, 0.0, 1.0)


def _display_reinhard(image: np.ndarray, low: float, high: float, gamma: float) -> np.ndarray:
    got = _positive_floor(image, low)
    if got is None:
        return np.zeros(image.shape, dtype=np.float64)
    pos, floor = got
    log_avg = math.exp(float(np.mean(np.log(np.maximum(image, floor)))))
    scaled = (REINHARD_KEY / log_avg) * np.maximum(image, 0.0)
    white = (REINHARD_KEY / log_avg) * float(np.percentile(pos, high))
    if not white > (REINHARD_KEY / log_avg) * floor:
        return np.where(image > 0, _MID_GREY / 255.0, 0.0)
    ld = scaled * (1.0 + scaled / white**2) / (1.0 + scaled)
    return np.clip(ld, 0.0, 1.0) ** (1.0 / gamma)


def _display_linear(image: np.ndarray, low: float, high: float, gamma: float) -> np.ndarray:
    lo, hi = (float(v) for v in np.percentile(image, [low, high]))
    if not hi > lo:
        return np.where(image > 0, _MID_GREY / 255.0, 0.0)
    v = np.clip((image - lo) / (hi - lo), 0.0, 1.0)
    return v ** (1.0 / gamma)


TONEMAP_METHODS: dict[str, Callable[[np.ndarray, float, float, float], np.ndarray]] = {
    "log": _display_log,
    "reinhard": _display_reinhard,
    "linear": _display_linear,
}
"""Tone-mapping methods by name: ``f(image, low_percentile, high_percentile, gamma)``
returning display values in [0, 1]."""


def tonemap(
    image: npt.ArrayLike,
    *,
    method: str = "log",
    low_percentile: float = 0.5,
    high_percentile: float = 99.5,
    gamma: float = 2.2,
) -> np.ndarray:
    """Map a linear HDR image to an 8-bit display image.

    Parameters
    ----------
    image:
        2-D ``(height, width)`` linear image (radiance), finite.
    method:
        ``"log"``, ``"reinhard"`` or ``"linear"`` (see the module docstring).
    low_percentile, high_percentile:
        Percentiles (0..100) that set black and white; for ``"log"`` and
        ``"reinhard"`` they are taken over the positive pixels.
    gamma:
        Display gamma, ``> 0``, for ``"reinhard"`` and ``"linear"``.

    Returns
    -------
    numpy.ndarray
        uint8 ``(height, width)``, 0..255, non-decreasing in the input.
    """
    try:
        fn = TONEMAP_METHODS[method]
    except KeyError:
        raise ValueError(
            f"tonemap: unknown method {method!r}; expected one of {sorted(TONEMAP_METHODS)}"
        ) from None
    a = np.asarray(image)
    if a.ndim != 2:
        raise ValueError(f"tonemap: expected a 2-D (height, width) image, got shape {a.shape}")
    if a.size == 0:
        raise ValueError(f"tonemap: empty image of shape {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"tonemap: expected a real numeric image, got dtype {a.dtype}")
    a = a.astype(np.float64, copy=False)
    n_bad = int(np.count_nonzero(~np.isfinite(a)))
    if n_bad:
        raise ValueError(f"tonemap: image has {n_bad} NaN or infinite values")
    if not (0.0 <= low_percentile < high_percentile <= 100.0):
        raise ValueError(
            "tonemap: expected 0 <= low_percentile < high_percentile <= 100, got "
            f"{low_percentile}, {high_percentile}"
        )
    if not (math.isfinite(gamma) and gamma > 0):
        raise ValueError(f"tonemap: gamma must be finite and > 0, got {gamma}")
    v = fn(a, float(low_percentile), float(high_percentile), float(gamma))
    return np.floor(np.clip(v, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


@dataclass
class StableLogToneCurve:
    """The ``"log"`` tone curve for a sequence, with black and white points that move
    slowly: no flicker from frame to frame.

    Per frame the anchors are ``log`` of the low and high percentiles of its positive
    pixels, as in :func:`tonemap`; the curve maps with their exponential moving average
    over frames, ``A_n = a A_(n-1) + (1 - a) anchors_n`` with ``a = exp(-1 / tau_frames)``
    (the first frame starts the average). ``tau_frames = 0`` follows every frame (the
    per-frame curve, which flickers when the percentiles do); ``inf`` keeps the first
    frame's curve. A frame with fewer than two distinct positive values keeps the
    previous anchors. Call it on frames in order; ``anchors`` holds ``(log lo, log hi)``
    of each frame mapped.

    Why a moving average: the sequence is reconstructed one cycle at a time, so the
    curve is known without reading the recording twice, and a scene that brightens over
    seconds is followed while cycle-to-cycle noise of the percentiles is averaged out.
    """

    low_percentile: float = 0.5
    high_percentile: float = 99.5
    tau_frames: float = 10.0
    anchors: list[tuple[float, float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not (0.0 <= self.low_percentile < self.high_percentile <= 100.0):
            raise ValueError("StableLogToneCurve: expected 0 <= low_percentile < "
                             f"high_percentile <= 100, got {self.low_percentile}, "
                             f"{self.high_percentile}")
        if not self.tau_frames >= 0:
            raise ValueError(f"StableLogToneCurve: tau_frames must be >= 0, got "
                             f"{self.tau_frames}")

    def __call__(self, image: npt.ArrayLike) -> np.ndarray:
        """The next frame as uint8 ``(height, width)``."""
        a = np.asarray(image, dtype=np.float64)
        if a.ndim != 2:
            raise ValueError(f"StableLogToneCurve: expected a 2-D image, got shape {a.shape}")
        finite = np.isfinite(a)
        pos = a[finite & (a > 0)]
        cur: tuple[float, float] | None = None
        if pos.size:
            lo, hi = (float(v) for v in np.percentile(pos, [self.low_percentile,
                                                           self.high_percentile]))
            if hi > lo:
                cur = (math.log(lo), math.log(hi))
        if self.anchors:
            prev = self.anchors[-1]
            if cur is None:
                cur = prev
            else:
                w = math.exp(-1.0 / self.tau_frames) if self.tau_frames > 0 else 0.0
                cur = (w * prev[0] + (1 - w) * cur[0], w * prev[1] + (1 - w) * cur[1])
        if cur is None:
            return np.where(finite & (a > 0), _MID_GREY, 0).astype(np.uint8)
        self.anchors.append(cur)
        log_lo, log_hi = cur
        with np.errstate(divide="ignore", invalid="ignore"):
            la = np.log(np.where(finite & (a > 0), a, math.exp(log_lo)))
        v = np.clip((la - log_lo) / (log_hi - log_lo), 0.0, 1.0)
        return np.floor(v * 255.0 + 0.5).astype(np.uint8)
