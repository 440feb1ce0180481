"""Image quality that cannot flatter: chart metrics (SNR, dynamic range, radiometric
error) and full-image metrics against a ground-truth radiance map.

Chart metrics work on per-patch statistics taken over a central region of a FIXED pixel
count in every patch (:data:`SNR_REGION_SHAPE`, 16 x 16 = 256 pixels): the SNR of an
image with heavy-tailed noise depends on how many pixels it is taken over, so a fixed
count makes figures comparable across sensor sizes.

- Patch SNR, the paper's (Wu et al. 2024, section 3.2): ``SNR = 10 log10(mu^2 / sigma^2)``
  dB over the region's pixels.
- Input-referred noise, as EMVA 1288 (release 4.0: noise and dynamic range referred to
  the input through the responsivity) does for a camera: with ``img = R(L)``
  the fitted monotone response,
  ``sigma_L = sigma_img / |dR/dL|`` and ``SNR_in = mu_L / sigma_L = L |dR/dL| / sigma_img
  = |dR / d ln L| / sigma_img``. It does not depend on the output's scale or curve: a
  compressive (log-like) image has a small slope where it is flat, and its noise counts
  for more there.
- Dynamic range (EMVA 1288 definition, ``DR = 20 log10(L_max / L_min)`` dB, over the
  range where ``SNR_in >= 1``): over the longest run of patches, in order of radiance,
  where every patch has events, ``SNR_in >= 1`` and each step to the next patch raises
  the measured mean strictly. A flat response has ``dR/dL = 0`` and no range.
- The paper's step criterion beside it: neighbouring patches (by density) are told
  apart when their means differ by more than the sum of their pixel spreads,
  ``|mu_i - mu_j| > sigma_i + sigma_j``; ``DR = 20 (D_darkest - D_brightest)``.

Full-image metrics (:func:`compare_images`): each test image is first given one global
scale (:func:`fit_scale`), then log-radiance RMSE, median relative error, PU21-PSNR
(Mantiuk and Azimi 2021) and SSIM on a tone-mapped pair (scikit-image).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = [
    "PU21_PARAMS",
    "SNR_REGION_SHAPE",
    "DynamicRange",
    "ImageComparison",
    "LinearRun",
    "PatchStats",
    "ResponseFit",
    "SnrSummary",
    "central_rois",
    "compare_images",
    "distinct_grey_levels",
    "dynamic_range",
    "dynamic_range_steps",
    "fit_response",
    "fit_scale",
    "input_referred_snr",
    "linear_run",
    "log_rmse",
    "mean_snr_db",
    "patch_event_fraction",
    "patch_stats",
    "pu21_decode",
    "pu21_encode",
    "pu21_psnr",
    "radiometric_error",
    "relative_error",
    "ssim_tonemapped",
]

Roi = tuple[int, int, int, int]

SNR_REGION_SHAPE: tuple[int, int] = (16, 16)
"""(height, width) of the central region over which every patch is measured: 256 pixels,
which fits inside the patches of the paper's 36-level chart on sensors from 346 x 260
(DAVIS346) up."""

MIN_EVENT_FRACTION = 0.5
"""A patch 'has events' when at least this fraction of its region's pixels fired at least
one event in the measured cycle."""


# --------------------------------------------------------------------------- patches


@dataclass(frozen=True)
class PatchStats:
    """Per-patch mean, standard deviation (population, ``ddof=0``) and pixel count."""

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
        """The paper's ``10 log10(mu^2 / sigma^2)`` dB per patch; ``inf`` where
        ``sigma == 0 < |mu|``, NaN where both are 0."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return 10.0 * np.log10(self.mean**2 / self.std**2)


def central_rois(rois: Mapping[int, Roi], *,
                 shape: tuple[int, int] = SNR_REGION_SHAPE) -> dict[int, Roi]:
    """The central ``shape`` (height, width) region of each ROI ``(y0, y1, x0, x1)``.

    Raises ``ValueError`` naming the first ROI smaller than ``shape``: a smaller region
    would change the statistics this module promises to keep fixed.
    """
    h, w = shape
    out: dict[int, Roi] = {}
    for k, (y0, y1, x0, x1) in rois.items():
        if y1 - y0 < h or x1 - x0 < w:
            raise ValueError(
                f"central_rois: patch {k} region is {x1 - x0}x{y1 - y0} (width x height), "
                f"smaller than the fixed {w}x{h} measuring region; use a larger sensor or "
                "a smaller region")
        cy = y0 + (y1 - y0 - h) // 2
        cx = x0 + (x1 - x0 - w) // 2
        out[int(k)] = (cy, cy + h, cx, cx + w)
    return out


def patch_stats(image: npt.ArrayLike, rois: Mapping[int, Roi]) -> PatchStats:
    """Mean and standard deviation of ``image`` over each ROI ``(y0, y1, x0, x1)``,
    patches indexed ``0..n-1``."""
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


def patch_event_fraction(event_count: npt.ArrayLike, rois: Mapping[int, Roi]) -> np.ndarray:
    """Fraction of each ROI's pixels with at least one event (``event_count``: events per
    pixel, ``(height, width)``)."""
    cnt = np.asarray(event_count)
    out = np.empty(len(rois))
    for i in range(len(rois)):
        y0, y1, x0, x1 = rois[i]
        out[i] = float(np.mean(cnt[y0:y1, x0:x1] > 0))
    return out


# --------------------------------------------------------------------------- response


@dataclass(frozen=True)
class ResponseFit:
    """A monotone response fitted to patch means, in the patches' own order.

    Attributes
    ----------
    fitted : the fitted response at each patch (same unit as the image).
    slope_ln : ``|dR / d ln L|`` at each patch (image unit per neperian unit of radiance).
    increasing : whether the response rises with radiance.
    """

    fitted: np.ndarray
    slope_ln: np.ndarray
    increasing: bool


def fit_response(radiance: npt.ArrayLike, mean: npt.ArrayLike) -> ResponseFit:
    """Fit a monotone response ``R(L)`` to patch means and take its slope.

    ``R`` is the isotonic (least-squares monotone) regression of the means on
    ``x = ln L`` (direction: the sign of the rank correlation). Its slope at a patch is
    the SMALLER of the two secant slopes of the fit to its neighbours in ``x``
    (one-sided at the ends):

        ``s_i = min( (R_{i+1} - R_i) / (x_{i+1} - x_i), (R_i - R_{i-1}) / (x_i - x_{i-1}) )``

    so a patch at the knee of a flat stretch gets slope 0 from its flat side.
    Patches of equal radiance are pooled by the fit.
    """
    from scipy.optimize import isotonic_regression
    from scipy.stats import spearmanr

    lum = np.asarray(radiance, dtype=np.float64)
    mu = np.asarray(mean, dtype=np.float64)
    if lum.shape != mu.shape or lum.ndim != 1:
        raise ValueError(f"fit_response: radiance {lum.shape} and mean {mu.shape} must be "
                         "1-D of the same length")
    if np.any(~(lum > 0)):
        raise ValueError("fit_response: radiance must be > 0 (log axis)")
    n = lum.size
    if n < 2:
        return ResponseFit(mu.copy(), np.zeros(n), True)
    order = np.argsort(lum, kind="stable")
    x = np.log(lum[order])
    y = mu[order]
    finite = np.isfinite(y)
    inc = True
    if finite.sum() >= 2 and np.ptp(y[finite]) > 0:
        rho = spearmanr(x[finite], y[finite]).statistic
        inc = not (np.isfinite(rho) and rho < 0)
    yy = np.where(finite, y, np.nanmin(y) if finite.any() else 0.0)
    fit = isotonic_regression(yy, increasing=inc).x
    dx = np.diff(x)
    with np.errstate(divide="ignore", invalid="ignore"):
        sec = np.where(dx > 0, np.abs(np.diff(fit)) / dx, 0.0)
    slope = np.empty(n)
    slope[0] = sec[0]
    slope[-1] = sec[-1]
    if n > 2:
        slope[1:-1] = np.minimum(sec[:-1], sec[1:])
    out_fit = np.empty(n)
    out_slope = np.empty(n)
    out_fit[order] = fit
    out_slope[order] = slope
    return ResponseFit(out_fit, out_slope, inc)


def input_referred_snr(stats: PatchStats, radiance: npt.ArrayLike,
                       fit: ResponseFit | None = None) -> np.ndarray:
    """EMVA 1288 input-referred SNR per patch (a ratio, not dB).

    ``sigma_L = sigma_img / |dR/dL|``, ``SNR_in = L / sigma_L = |dR / d ln L| / sigma_img``
    with ``R`` from :func:`fit_response`. ``inf`` where the response rises and the image
    has no noise (``sigma_img = 0``); 0 where the response is flat.
    """
    fit = fit or fit_response(radiance, stats.mean)
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = np.where(fit.slope_ln > 0, fit.slope_ln / stats.std, 0.0)
    return snr


# --------------------------------------------------------------------------- dynamic range


@dataclass(frozen=True)
class DynamicRange:
    """A dynamic range and the run of patches it spans.

    ``counted`` marks the run's patches; ``l_min``/``l_max`` are the radiances at its
    ends (0 and 0 when no run); ``criterion`` names the rule.
    """

    dr_db: float
    l_min: float
    l_max: float
    counted: np.ndarray
    criterion: str
    n_patches: int = 0
    d_brightest: float | None = None
    d_darkest: float | None = None
    snr_in: np.ndarray | None = field(default=None, repr=False)


def _longest_run(ok_patch: np.ndarray, ok_step: np.ndarray) -> tuple[int, int]:
    """Longest ``[lo, hi]`` (inclusive, in sorted positions) with every patch ok and every
    step between neighbours ok; ``(0, -1)`` when no patch is ok."""
    best = (0, -1)
    i = 0
    n = ok_patch.size
    while i < n:
        if not ok_patch[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and ok_step[j] and ok_patch[j + 1]:
            j += 1
        if j - i > best[1] - best[0]:
            best = (i, j)
        i = j + 1
    return best


def dynamic_range(stats: PatchStats, radiance: npt.ArrayLike, *,
                  has_events: npt.ArrayLike | None = None,
                  min_snr: float = 1.0) -> DynamicRange:
    """EMVA 1288 dynamic range over chart patches: ``20 log10(L_max / L_min)`` dB.

    Patches sorted by radiance ``L``; a patch counts when it has events (``has_events``,
    default all), its input-referred SNR (:func:`input_referred_snr`) is at least
    ``min_snr`` (1, i.e. 0 dB: EMVA 1288's lower limit), and its mean is finite; a step
    between neighbours counts when the measured mean moves strictly in the response's
    direction. The range is the longest run of counted patches joined by counted steps;
    a single patch, or none, is 0 dB.
    """
    lum = np.asarray(radiance, dtype=np.float64)
    n = lum.size
    if stats.mean.size != n:
        raise ValueError(f"dynamic_range: {n} radiances for {stats.mean.size} patches")
    ev = np.ones(n, bool) if has_events is None else np.asarray(has_events, bool)
    fit = fit_response(lum, stats.mean)
    snr_in = input_referred_snr(stats, lum, fit)
    order = np.argsort(lum, kind="stable")
    mu = stats.mean[order]
    sign = 1.0 if fit.increasing else -1.0
    ok_patch = ev[order] & (snr_in[order] >= min_snr) & np.isfinite(mu)
    ok_step = sign * np.diff(mu) > 0
    lo, hi = _longest_run(ok_patch, ok_step)
    counted = np.zeros(n, bool)
    if hi < lo:
        return DynamicRange(0.0, 0.0, 0.0, counted, "EMVA 1288 (SNR_in >= 1, monotone)",
                            0, snr_in=snr_in)
    counted[order[lo:hi + 1]] = True
    l_min, l_max = float(lum[order[lo]]), float(lum[order[hi]])
    return DynamicRange(20.0 * math.log10(l_max / l_min), l_min, l_max, counted,
                        "EMVA 1288 (SNR_in >= 1, monotone)", hi - lo + 1, snr_in=snr_in)


def dynamic_range_steps(stats: PatchStats, densities: npt.ArrayLike, *,
                        has_events: npt.ArrayLike | None = None,
                        illuminance: float = 1.0) -> DynamicRange:
    """The paper's step criterion (Wu et al. 2024, section 3.2, Fig. 5b):
    ``DR = 20 (D_darkest - D_brightest)`` dB over the longest run of neighbouring
    densities told apart, ``mu_bright - mu_dark > sigma_bright + sigma_dark`` (means
    apart by more than the two pixel spreads), every patch with events.
    ``illuminance`` only sets ``l_min``/``l_max`` (``illuminance 10^-D``)."""
    d = np.asarray(densities, dtype=np.float64)
    n = d.size
    if stats.mean.size != n:
        raise ValueError(f"dynamic_range_steps: {n} densities for {stats.mean.size} patches")
    ev = np.ones(n, bool) if has_events is None else np.asarray(has_events, bool)
    order = np.argsort(d, kind="stable")
    mu = stats.mean[order]
    sd = stats.std[order]
    ok_patch = ev[order] & np.isfinite(mu)
    ok_step = (mu[:-1] - mu[1:]) > (sd[:-1] + sd[1:])
    lo, hi = _longest_run(ok_patch, ok_step)
    counted = np.zeros(n, bool)
    if hi <= lo:
        return DynamicRange(0.0, 0.0, 0.0, counted, "paper (means apart > both spreads)", 0)
    counted[order[lo:hi + 1]] = True
    db, dd = float(d[order[lo]]), float(d[order[hi]])
    return DynamicRange(20.0 * (dd - db), illuminance * 10.0 ** (-dd),
                        illuminance * 10.0 ** (-db), counted,
                        "paper (means apart > both spreads)", hi - lo + 1,
                        d_brightest=db, d_darkest=dd)


# --------------------------------------------------------------------------- SNR table


@dataclass(frozen=True)
class SnrSummary:
    """Mean patch SNR (dB) over the patches that respond and have noise (``n_patches``),
    the responding patches without noise (``n_noiseless``), and all patches."""

    mean_db: float
    n_patches: int
    n_total: int
    n_noiseless: int

    def to_dict(self) -> dict[str, Any]:
        return {"mean_db": self.mean_db if math.isfinite(self.mean_db) else
                (None if math.isnan(self.mean_db) else "inf"),
                "n_patches": self.n_patches, "n_total": self.n_total,
                "n_noiseless": self.n_noiseless}


def mean_snr_db(stats: PatchStats, *, responding: npt.ArrayLike | None = None) -> SnrSummary:
    """The paper's mean patch SNR, ``mean_i 10 log10(mu_i^2 / sigma_i^2)`` dB, over the
    patches that respond (``responding``, default all) and have noise.

    Averaged in dB as the paper's table is. Responding patches without noise
    (``sigma = 0``: every pixel reads the same, as on a noise-free sensor or a quantised
    image) have infinite SNR; they are counted apart (``n_noiseless``) and left out of the
    mean, which is ``inf`` only when every responding patch is noiseless, NaN when none
    responds.
    """
    snr = stats.snr_db
    mask = np.ones(snr.size, bool) if responding is None else np.asarray(responding, bool)
    sel = snr[mask & ~np.isnan(snr)]
    n_inf = int(np.sum(np.isposinf(sel)))
    finite = sel[np.isfinite(sel)]
    if finite.size:
        value = float(np.mean(finite))
    elif n_inf:
        value = float("inf")
    else:
        value = float("nan")
    return SnrSummary(value, int(finite.size), int(snr.size), n_inf)


def radiometric_error(stats: PatchStats, truth: npt.ArrayLike, *,
                      mask: npt.ArrayLike | None = None) -> tuple[np.ndarray, float]:
    """Per-patch relative RMS error against the true radiance after ONE global scale.

    ``s = exp(median_i ln(L_i / mu_i))`` over the patches in ``mask`` with ``mu > 0``;
    ``e_i = sqrt((s mu_i - L_i)^2 + (s sigma_i)^2) / L_i`` (bias and spread). Returns the
    errors and ``s``. A non-linear image (the paper's ``img``) keeps its curve's error.
    """
    t = np.asarray(truth, dtype=np.float64)
    mu = stats.mean.astype(np.float64)
    ok = (mu > 0) & (t > 0)
    if mask is not None:
        ok &= np.asarray(mask, bool)
    scale = float(np.exp(np.median(np.log(t[ok] / mu[ok])))) if ok.any() else 1.0
    err = np.sqrt((mu * scale - t) ** 2 + (stats.std * scale) ** 2) / t
    return err, scale


@dataclass(frozen=True)
class LinearRun:
    """The longest run of levels an image measures as radiance (:func:`linear_run`).

    ``span_db`` is ``20 log10(L_hi / L_lo)`` (0 for a single level or none), ``lo``,
    ``hi`` the indices of its ends (-1 when there is none), ``mean_snr_db`` the mean
    per-pixel SNR over it, ``scale`` the global scale and ``bias`` every level's bias
    under it."""

    span_db: float
    lo: int
    hi: int
    mean_snr_db: float
    scale: float
    bias: np.ndarray

    @property
    def n_levels(self) -> int:
        return self.hi - self.lo + 1 if self.lo >= 0 else 0


def linear_run(radiance: npt.ArrayLike, mean: npt.ArrayLike, snr_db: npt.ArrayLike, *,
               max_bias: float = 0.05, min_snr_db: float = 20.0) -> LinearRun:
    """The longest run of consecutive levels (``radiance`` ascending) whose mean, after ONE
    global scale, is within ``max_bias`` of the radiance and whose per-pixel SNR is at
    least ``min_snr_db``: the range an image measures radiance over, up to its unit.

    The scale is the one that gives the longest run (ties: the higher mean SNR), tried at
    every level's own ratio ``L / mean``: a scale fixed from all levels at once would let
    the levels outside the sensor's range, biased by orders of magnitude, set the unit of
    those inside it."""
    lv = np.asarray(radiance, dtype=np.float64)
    mu = np.asarray(mean, dtype=np.float64)
    snr = np.asarray(snr_db, dtype=np.float64)
    if not (lv.shape == mu.shape == snr.shape and lv.ndim == 1):
        raise ValueError("linear_run: radiance, mean and snr_db must be 1-D of one length")
    if np.any(np.diff(lv) <= 0):
        raise ValueError("linear_run: radiance must be strictly ascending")
    good = np.isfinite(mu) & (mu > 0)
    loud = good & (snr >= min_snr_db)
    cands = np.unique(lv[loud] / mu[loud]) if loud.any() else np.array([])
    best = LinearRun(0.0, -1, -1, float("nan"), float("nan"), np.full(lv.size, np.nan))
    key_best = (-1.0, -np.inf)
    for scale in cands:
        with np.errstate(invalid="ignore"):
            bias = mu * scale / lv - 1.0
            ok = loud & (np.abs(bias) <= max_bias)
        i = 0
        while i < ok.size:
            if not ok[i]:
                i += 1
                continue
            j = i
            while j + 1 < ok.size and ok[j + 1]:
                j += 1
            span = 20.0 * math.log10(lv[j] / lv[i])
            m_snr = float(np.mean(snr[i:j + 1]))
            if (span, m_snr) > key_best:
                key_best = (span, m_snr)
                best = LinearRun(span, i, j, m_snr, float(scale), bias)
            i = j + 1
    return best


def distinct_grey_levels(image: npt.ArrayLike, *, mask: npt.ArrayLike | None = None) -> int:
    """Occupied levels of the 8-bit log tone map (:func:`asynhdr.tonemap.tonemap`,
    ``method="log"``, 0.5-99.5 percentiles) of ``image``: the paper's histogram argument
    (section 3.3: more grey levels, better image) as one number."""
    from asynhdr.tonemap import tonemap

    tm = tonemap(np.asarray(image, dtype=np.float64), method="log")
    if mask is not None:
        tm = tm[np.asarray(mask, bool)]
    return int(np.unique(tm).size)


# --------------------------------------------------------------------------- PU21

PU21_PARAMS: dict[str, tuple[float, ...]] = {
    "banding": (1.070275272, 0.4088273932, 0.153224308, 0.2520326168, 1.063512885,
                1.14115047, 521.4527484),
    "banding_glare": (0.353487901, 0.3734658629, 8.277049286e-05, 0.9062562627,
                      0.09150303166, 0.9099517204, 596.3148142),
    "peaks": (1.043882782, 0.6459495343, 0.3194584211, 0.374025247, 1.114783422,
              1.095360363, 384.9217577),
    "peaks_glare": (816.885024, 1479.463946, 0.001253215609, 0.9329636822, 0.06746643971,
                    1.573435413, 419.6006374),
}
"""PU21 parameters ``p1..p7`` by variant (Mantiuk and Azimi, "PU21: A novel perceptually
uniform encoding for adapting existing quality metrics for HDR", Picture Coding Symposium
2021, as published with the paper's reference code; ``banding_glare`` is the
recommended default)."""

PU21_L_MIN = 0.005
"""Lowest luminance (cd/m^2) PU21 encodes; below is clamped."""
PU21_L_MAX = 10000.0
"""Highest luminance (cd/m^2) PU21 encodes; above is clamped."""
PU21_PEAK = 256.0
"""Peak value of PU21-PSNR: PU21 is scaled so that 0-100 cd/m^2 spans about 0-256, like
8-bit sRGB (the authors' metric code uses 256)."""
PU21_DISPLAY_PEAK_CDM2 = 4000.0
"""Display peak (cd/m^2) the reference's maximum is mapped to before PU21 (the authors'
HDR example maps the image peak to a 4,000 cd/m^2 display)."""


def pu21_encode(luminance: npt.ArrayLike, *, variant: str = "banding_glare") -> np.ndarray:
    """PU21 encoding of absolute luminance ``Y`` (cd/m^2) (Mantiuk and Azimi 2021, the
    encoding function fitted in the paper):

        ``V = p7 * ( ((p1 + p2 Y^p4) / (1 + p3 Y^p4))^p5 - p6 )``

    with ``Y`` clamped to [0.005, 10000] cd/m^2.
    """
    try:
        p1, p2, p3, p4, p5, p6, p7 = PU21_PARAMS[variant]
    except KeyError:
        raise ValueError(f"pu21_encode: unknown variant {variant!r}; expected one of "
                         f"{sorted(PU21_PARAMS)}") from None
    y = np.clip(np.asarray(luminance, dtype=np.float64), PU21_L_MIN, PU21_L_MAX)
    yp = y**p4
    return p7 * (((p1 + p2 * yp) / (1.0 + p3 * yp)) ** p5 - p6)


def pu21_decode(v: npt.ArrayLike, *, variant: str = "banding_glare") -> np.ndarray:
    """Inverse of :func:`pu21_encode` (within the clamped range)."""
    p1, p2, p3, p4, p5, p6, p7 = PU21_PARAMS[variant]
    vp = np.maximum(np.asarray(v, dtype=np.float64) / p7 + p6, 0.0) ** (1.0 / p5)
    return (np.maximum(vp - p1, 0.0) / (p2 - p3 * vp)) ** (1.0 / p4)


def pu21_psnr(test: npt.ArrayLike, reference: npt.ArrayLike, *,
              mask: npt.ArrayLike | None = None, variant: str = "banding_glare") -> float:
    """PSNR on PU21-encoded absolute luminance (cd/m^2):
    ``10 log10(256^2 / mean((V_test - V_ref)^2))`` dB; ``inf`` for identical images."""
    a = pu21_encode(test, variant=variant)
    b = pu21_encode(reference, variant=variant)
    d = (a - b) ** 2
    if mask is not None:
        d = d[np.asarray(mask, bool)]
    mse = float(np.mean(d))
    return float("inf") if mse == 0 else 10.0 * math.log10(PU21_PEAK**2 / mse)


# --------------------------------------------------------------------------- images


def _valid(truth: np.ndarray, mask: npt.ArrayLike | None) -> np.ndarray:
    ok = truth > 0
    if mask is not None:
        ok &= np.asarray(mask, bool)
    return ok


def fit_scale(image: npt.ArrayLike, truth: npt.ArrayLike, *,
              mask: npt.ArrayLike | None = None) -> float:
    """One global scale ``s = exp(median ln(truth / image))`` over valid pixels (both > 0,
    inside ``mask``): the unit of an uncalibrated image, and nothing more."""
    img = np.asarray(image, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    ok = _valid(t, mask) & (img > 0)
    if not ok.any():
        return 1.0
    return float(np.exp(np.median(np.log(t[ok] / img[ok]))))


def _floored(img: np.ndarray, ok: np.ndarray) -> np.ndarray:
    pos = img[ok & (img > 0)]
    floor = float(pos.min()) if pos.size else 1e-12
    return np.maximum(img, floor)


def log_rmse(image: npt.ArrayLike, truth: npt.ArrayLike, *,
             mask: npt.ArrayLike | None = None) -> float:
    """RMS of ``log2(image / truth)`` over valid pixels, in stops. Pixels the image leaves
    at 0 or below read as its smallest positive value (black on a display), so a hole
    costs its full error instead of being skipped."""
    img = np.asarray(image, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    ok = _valid(t, mask)
    e = np.log2(_floored(img, ok)[ok] / t[ok])
    return float(np.sqrt(np.mean(e**2)))


def relative_error(image: npt.ArrayLike, truth: npt.ArrayLike, *,
                   mask: npt.ArrayLike | None = None) -> float:
    """Median over valid pixels of ``|image - truth| / truth``."""
    img = np.asarray(image, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    ok = _valid(t, mask)
    return float(np.median(np.abs(img[ok] - t[ok]) / t[ok]))


def ssim_tonemapped(image: npt.ArrayLike, truth: npt.ArrayLike, *,
                    mask: npt.ArrayLike | None = None) -> float:
    """SSIM (Wang et al. 2004, scikit-image's ``structural_similarity``, 7x7 window,
    ``data_range=1``) between the two images after the SAME log tone map, set by the
    truth: ``v = (ln x - ln lo) / (ln hi - ln lo)`` clipped to [0, 1], ``lo``, ``hi`` the
    0.5 and 99.5 percentiles of the truth's positive pixels. With ``mask``, the mean of
    the SSIM map over the mask's pixels (borders of half a window left out, as
    scikit-image does for its mean)."""
    from skimage.metrics import structural_similarity

    img = np.asarray(image, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    ok = _valid(t, mask)
    lo, hi = (float(v) for v in np.percentile(t[ok], [0.5, 99.5]))
    if not hi > lo:
        hi = lo * 1.0001 + 1e-12

    def tm(x: np.ndarray) -> np.ndarray:
        x = np.clip(x, lo, hi)
        return (np.log(x) - math.log(lo)) / (math.log(hi) - math.log(lo))

    mssim, smap = structural_similarity(tm(img), tm(t), data_range=1.0, full=True)
    if mask is None:
        return float(mssim)
    pad = 3  # scikit-image leaves out the window's half-width at the borders
    inner = ok[pad:-pad, pad:-pad]
    return float(np.mean(smap[pad:-pad, pad:-pad][inner]))


@dataclass(frozen=True)
class ImageComparison:
    """An image against the true radiance (after one global scale). The ``*_in_range``
    figures are the same over the pixels a capture system can measure (NaN unless asked
    for: :func:`compare_images`'s ``in_range``)."""

    scale: float
    log_rmse_stops: float
    rel_error: float
    pu21_psnr_db: float
    ssim: float
    zero_fraction: float
    log_rmse_in_range_stops: float = math.nan
    pu21_psnr_in_range_db: float = math.nan

    def to_dict(self) -> dict[str, float | None]:
        return {k: (None if not math.isfinite(v) else float(v))
                for k, v in self.__dict__.items()}


def compare_images(image: npt.ArrayLike, truth: npt.ArrayLike, *,
                   mask: npt.ArrayLike | None = None,
                   display_peak_cdm2: float = PU21_DISPLAY_PEAK_CDM2,
                   in_range: npt.ArrayLike | None = None) -> ImageComparison:
    """Every full-image metric of ``image`` against ``truth`` (linear radiance).

    The image is first multiplied by :func:`fit_scale`. For PU21 both are put on an HDR
    display by the same factor: the truth's maximum (over ``mask``) to
    ``display_peak_cdm2``. ``zero_fraction``: valid pixels the image leaves at 0 or below.
    ``in_range``: the pixels the capture could measure (a rig's working range, say); the
    log RMSE and PU21-PSNR over those of the valid ones as well, with the same scale and
    display (beside the whole image's figures, which still count every pixel).
    """
    img = np.asarray(image, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if img.shape != t.shape:
        raise ValueError(f"compare_images: image {img.shape} and truth {t.shape} differ")
    ok = _valid(t, mask)
    if not ok.any():
        raise ValueError("compare_images: no valid pixel (truth > 0 inside the mask)")
    s = fit_scale(img, t, mask=mask)
    scaled = img * s
    k = display_peak_cdm2 / float(t[ok].max())
    rmse_in = pu21_in = math.nan
    if in_range is not None:
        inside = ok & np.asarray(in_range, bool)
        if inside.any():
            rmse_in = log_rmse(scaled, t, mask=inside)
            pu21_in = pu21_psnr(scaled * k, t * k, mask=inside)
    return ImageComparison(
        scale=s,
        log_rmse_stops=log_rmse(scaled, t, mask=ok),
        rel_error=relative_error(scaled, t, mask=ok),
        pu21_psnr_db=pu21_psnr(scaled * k, t * k, mask=ok),
        ssim=ssim_tonemapped(scaled, t, mask=ok),
        zero_fraction=float(np.mean(img[ok] <= 0)),
        log_rmse_in_range_stops=rmse_in,
        pu21_psnr_in_range_db=pu21_in,
    )
