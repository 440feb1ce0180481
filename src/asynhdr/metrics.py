"""Image quality on a chart: patch statistics, SNR, dynamic range, radiometric error.

SNR of a patch (Wu et al. 2024, section 3.2): ``10 log10(mu^2 / sigma^2)`` over the
pixels of its region of interest, on the reconstructed image.

Dynamic range by the paper's criterion: ``DR = 20 (D_darkest - D_brightest)`` dB over
the resolved patches ("sensitivity to brightness variations across filter levels").
Here, taking the patches in order of density, a step between neighbours is *resolved*
when the brighter patch reconstructs brighter by more than three standard errors of
the difference of the two patch means, ``mu_i - mu_j > 3 sqrt(sigma_i^2/n_i +
sigma_j^2/n_j)`` (``n``: pixels in each region), and a patch counts only while its
signal is at least its noise, ``mu >= sigma`` (SNR >= 0 dB, the lower limit of the
dynamic range in EMVA 1288). The resolved levels are the longest run of consecutive
densities whose every patch and every adjacent step pass; ``D_brightest`` and
``D_darkest`` are its ends. A saturated end (neighbours reading the same) or a
response that turns back ends the run.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

__all__ = [
    "DynamicRange",
    "PatchStats",
    "dynamic_range",
    "mean_snr_db",
    "patch_stats",
    "relative_rmse",
]

Roi = tuple[int, int, int, int]


@dataclass(frozen=True)
class PatchStats:
    """Per-patch mean, standard deviation and pixel count of an image; SNR in dB.

    ``count`` is the number of pixels of each region (1 when not given).
    """

    mean: np.ndarray
    std: np.ndarray
    count: np.ndarray | None = None

    @property
    def n(self) -> np.ndarray:
        """Pixels per patch (ones when ``count`` is not given)."""
        return np.ones_like(self.mean) if self.count is None else \
            np.asarray(self.count, dtype=np.float64)

    @property
    def snr_db(self) -> np.ndarray:
        """``10 log10(mu^2 / sigma^2)``; ``inf`` where ``sigma == 0 < |mu|``, NaN where both
        are 0 (an empty patch)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return 10.0 * np.log10(self.mean**2 / self.std**2)


def patch_stats(image: np.ndarray, rois: Mapping[int, Roi]) -> PatchStats:
    """Mean and standard deviation of ``image`` over each ROI (``(y0, y1, x0, x1)``)."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"patch_stats: expected a 2-D image, got shape {img.shape}")
    n = len(rois)
    mean = np.empty(n)
    std = np.empty(n)
    count = np.empty(n)
    for i in range(n):
        y0, y1, x0, x1 = rois[i]
        region = img[y0:y1, x0:x1]
        mean[i] = region.mean()
        std[i] = region.std()
        count[i] = region.size
    return PatchStats(mean, std, count)


def mean_snr_db(stats: PatchStats) -> float:
    """Mean patch SNR in dB over the patches that have noise.

    Patches with zero noise (``sigma == 0``: infinite SNR, as every pixel of a patch of
    a noise-free, mismatch-free sensor reads the same) and empty patches (NaN) are left
    out; ``inf`` when no patch has noise.
    """
    snr = stats.snr_db
    finite = snr[np.isfinite(snr)]
    if finite.size:
        return float(np.mean(finite))
    return float("inf") if np.any(np.isposinf(snr)) else float("nan")


@dataclass(frozen=True)
class DynamicRange:
    """Dynamic range by the paper's criterion, and the resolved run of patches."""

    dr_db: float
    brightest_index: int
    darkest_index: int
    d_brightest: float
    d_darkest: float
    resolved: np.ndarray  # bool per patch


def dynamic_range(stats: PatchStats, densities: np.ndarray, *,
                  z: float = 3.0) -> DynamicRange:
    """``20 (D_darkest - D_brightest)`` dB over the longest run of resolved patches
    (see the module's text; ``z`` standard errors make a step)."""
    d = np.asarray(densities, dtype=np.float64)
    if d.size != stats.mean.size:
        raise ValueError(f"dynamic_range: {d.size} densities for {stats.mean.size} patches")
    order = np.argsort(d, kind="stable")
    mu = stats.mean[order]
    sd = stats.std[order]
    n = stats.n[order]
    se = np.sqrt(sd[:-1] ** 2 / n[:-1] + sd[1:] ** 2 / n[1:])
    signal = mu >= sd
    ok = ((mu[:-1] - mu[1:]) > z * se) & signal[:-1] & signal[1:]
    best = (0, 0)  # [start, end] in sorted positions
    i = 0
    while i < ok.size:
        if ok[i]:
            j = i
            while j < ok.size and ok[j]:
                j += 1
            if j - i > best[1] - best[0]:
                best = (i, j)
            i = j
        else:
            i += 1
    resolved = np.zeros(d.size, dtype=bool)
    lo, hi = best
    if hi > lo:
        resolved[order[lo:hi + 1]] = True
    bi, di = int(order[lo]), int(order[hi])
    return DynamicRange(
        dr_db=float(20.0 * (d[di] - d[bi])) if hi > lo else 0.0,
        brightest_index=bi,
        darkest_index=di,
        d_brightest=float(d[bi]),
        d_darkest=float(d[di]),
        resolved=resolved,
    )


def relative_rmse(stats: PatchStats, truth: np.ndarray, *, fit_scale: bool = True) -> np.ndarray:
    """Per-patch relative RMS error against true radiance.

    With ``fit_scale`` the image is first scaled by the single factor that best matches
    the truth in the log domain (median of ``log(truth / mean)``): the error of a
    linear-but-uncalibrated image is then its shape error, not its unit.
    """
    t = np.asarray(truth, dtype=np.float64)
    mu = stats.mean.astype(np.float64)
    scale = 1.0
    if fit_scale:
        ok = (mu > 0) & (t > 0)
        if ok.any():
            scale = float(np.exp(np.median(np.log(t[ok] / mu[ok]))))
    m = mu * scale
    s = stats.std * scale
    return np.sqrt((m - t) ** 2 + s**2) / t
