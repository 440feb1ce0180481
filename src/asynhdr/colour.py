"""Colour: a Bayer colour filter array over the event sensor, demosaicing, colour error.

A colour event sensor (e.g. the colour DAVIS346) has a Bayer colour filter array (CFA)
over its pixels: each pixel sees one channel of the scene. In the rig the modulation is
the same for every pixel, so the colour sensor is the grey one with a per-pixel radiance

    L_cfa(y, x) = t_c * L_c(y, x),    c = CFA(y mod 2, x mod 2) in {R, G, B}      (1)

(``t_c``: the filter's relative transmittance of channel ``c``, default 1). The
simulator needs no change: :func:`mosaic` gives it that radiance map. Every
reconstruction method works per pixel, so the reconstructed image is itself a mosaic:
pixel ``(y, x)`` estimates ``t_c L_c``. :func:`reconstruct_colour` divides by ``t_c``
and demosaics it into an RGB image ``(height, width, 3)``.

Demosaicing (:data:`DEMOSAIC_METHODS`), on float data (OpenCV's ``cvtColor`` Bayer
conversions take 8- and 16-bit images only):

- ``"bilinear"``: each missing sample is the mean of its nearest neighbours of that
  channel (the kernels ``[[0,1,0],[1,4,1],[0,1,0]]/4`` for G and
  ``[[1,2,1],[2,4,2],[1,2,1]]/4`` for R and B on the channel's sparse plane);
- ``"malvar"``: H. S. Malvar, L.-W. He and R. Cutler, "High-quality linear
  interpolation for demosaicing of Bayer-patterned color images", IEEE ICASSP 2004,
  vol. 3, pp. 485-488: bilinear plus a gradient correction from the known channel, as
  four 5x5 filters (coefficients in eighths, Figure 2 of the paper).

Both are linear filters. HDR radiance spans decades, where a linear filter's negative
lobes overshoot at every edge (negative radiance next to a bright edge), so
``domain="log"`` (the default) interpolates ``ln L`` and exponentiates: ratios, not
differences, are interpolated, and the result is positive.

Borders: the image is extended by mirror reflection without repeating the edge pixel
(``d c b | a b c d | c b a``), which keeps the Bayer phase.

Colour error (:func:`colour_errors`) against a reference RGB image, after one global
scale (median of the luminance log ratio): per-channel RMS of ``ln(rec / ref)``, and
CIEDE2000 (Sharma, Wu, Dalal 2005; scikit-image's ``deltaE_ciede2000``) in CIE L*a*b*
from linear Rec. 709 RGB through XYZ (D65), with the reference white at the
reference's 99th-percentile luminance.

Pure functions: no files (reading and writing RGB images is in
:mod:`asynhdr.io.colour_images`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import ndimage

from asynhdr.scene import REC709_LUMA, from_radiance_map

__all__ = [
    "CFA_PATTERNS",
    "DEFAULT_CFA",
    "DEMOSAIC_METHODS",
    "REC709_TO_XYZ",
    "ColourScene",
    "cfa_channels",
    "colour_errors",
    "colour_scene",
    "demosaic",
    "mosaic",
    "reconstruct_colour",
    "tonemap_rgb",
]

logger = logging.getLogger(__name__)

CFA_PATTERNS: dict[str, tuple[tuple[int, int], tuple[int, int]]] = {
    "rggb": ((0, 1), (1, 2)),
    "bggr": ((2, 1), (1, 0)),
    "grbg": ((1, 0), (2, 1)),
    "gbrg": ((1, 2), (0, 1)),
}
"""Bayer layouts: channel index (0 R, 1 G, 2 B) at ``(y mod 2, x mod 2)``; the name
reads the top-left 2x2 block row by row."""

DEFAULT_CFA = "rggb"
"""The Bayer layout of the colour DAVIS346 and most colour sensors' datasheets."""

REC709_TO_XYZ = np.array([[0.4124564, 0.3575761, 0.1804375],
                          [0.2126729, 0.7151522, 0.0721750],
                          [0.0193339, 0.1191920, 0.9503041]])
"""Linear Rec. 709 / sRGB RGB to CIE XYZ, D65 white (IEC 61966-2-1)."""

_EPS = 1e-30


def _pattern(pattern: str) -> tuple[tuple[int, int], tuple[int, int]]:
    try:
        return CFA_PATTERNS[pattern.lower()]
    except (KeyError, AttributeError):
        raise ValueError(f"unknown CFA pattern {pattern!r}; expected one of "
                         f"{sorted(CFA_PATTERNS)}") from None


def cfa_channels(pattern: str = DEFAULT_CFA, *, height: int, width: int) -> np.ndarray:
    """Channel index (0 R, 1 G, 2 B) of every pixel, int8 ``(height, width)``."""
    p = np.asarray(_pattern(pattern), dtype=np.int8)
    return np.tile(p, ((height + 1) // 2, (width + 1) // 2))[:height, :width]


def _transmittance(t: npt.ArrayLike) -> np.ndarray:
    a = np.asarray(t, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.any(a <= 0):
        raise ValueError(f"CFA transmittance: expected 3 positive numbers (R, G, B), got {t!r}")
    return a


def mosaic(rgb: npt.ArrayLike, pattern: str = DEFAULT_CFA, *,
           transmittance: npt.ArrayLike = (1.0, 1.0, 1.0)) -> np.ndarray:
    """Per-pixel radiance behind a Bayer CFA, equation (1): float32 ``(height, width)``."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"mosaic: expected (height, width, 3) linear RGB, got shape {a.shape}")
    t = _transmittance(transmittance)
    ch = cfa_channels(pattern, height=a.shape[0], width=a.shape[1])
    picked = np.take_along_axis(a.astype(np.float64), ch[..., None].astype(np.intp), axis=2)
    return (picked[..., 0] * t[ch]).astype(np.float32)


@dataclass(frozen=True, eq=False)
class ColourScene:
    """A colour scene seen through a Bayer CFA.

    Attributes
    ----------
    radiance : the per-pixel radiance behind the CFA, float32 ``(height, width)``: what
        the simulator takes (equation 1).
    rgb : the scene's linear RGB, float32 ``(height, width, 3)``, the colour truth.
    cfa : Bayer layout (:data:`CFA_PATTERNS`).
    transmittance : ``(t_R, t_G, t_B)``.
    unit, name : as :class:`asynhdr.scene.Scene`.
    """

    radiance: np.ndarray
    rgb: np.ndarray
    cfa: str = DEFAULT_CFA
    transmittance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    unit: str = "relative"
    name: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def metadata(self) -> dict[str, Any]:
        """What a recording of this scene should carry: ``{"cfa": ..., ...}``."""
        return {"cfa": self.cfa, "cfa_transmittance": list(self.transmittance),
                **dict(self.extra)}


def colour_scene(rgb: npt.ArrayLike, *, width: int, height: int,
                 pattern: str = DEFAULT_CFA, transmittance: npt.ArrayLike = (1.0, 1.0, 1.0),
                 scale: float = 1.0, unit: str = "relative", name: str = "",
                 fit: str = "stretch") -> ColourScene:
    """A colour scene from linear RGB ``(rows, cols, 3)``: each channel resized to the
    sensor like :func:`asynhdr.scene.from_radiance_map`, then put behind the CFA."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise ValueError(f"colour_scene: expected (height, width, 3) linear RGB, got shape "
                         f"{a.shape}")
    chans = [from_radiance_map(a[..., c], width=width, height=height, scale=scale, unit=unit,
                               name=name, fit=fit).radiance for c in range(3)]
    full = np.stack(chans, axis=-1).astype(np.float32)
    t = _transmittance(transmittance)
    return ColourScene(radiance=mosaic(full, pattern, transmittance=t), rgb=full,
                       cfa=pattern.lower(), transmittance=(float(t[0]), float(t[1]), float(t[2])),
                       unit=unit, name=name)


# --------------------------------------------------------------------------- demosaicing

_BILINEAR_G = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]], dtype=np.float64) / 4.0
_BILINEAR_RB = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], dtype=np.float64) / 4.0

# Malvar, He, Cutler 2004, Figure 2 (in eighths).
_M_G_AT_RB = np.array([[0, 0, -1, 0, 0],
                       [0, 0, 2, 0, 0],
                       [-1, 2, 4, 2, -1],
                       [0, 0, 2, 0, 0],
                       [0, 0, -1, 0, 0]], dtype=np.float64) / 8.0
_M_ROWWISE = np.array([[0, 0, 0.5, 0, 0],       # R at G in an R row (B at G in a B row)
                       [0, -1, 0, -1, 0],
                       [-1, 4, 5, 4, -1],
                       [0, -1, 0, -1, 0],
                       [0, 0, 0.5, 0, 0]], dtype=np.float64) / 8.0
_M_COLWISE = _M_ROWWISE.T                          # R at G in a B row (B at G in an R row)
_M_RB_AT_BR = np.array([[0, 0, -1.5, 0, 0],
                        [0, 2, 0, 2, 0],
                        [-1.5, 0, 6, 0, -1.5],
                        [0, 2, 0, 2, 0],
                        [0, 0, -1.5, 0, 0]], dtype=np.float64) / 8.0


def _conv(a: np.ndarray, k: np.ndarray) -> np.ndarray:
    return ndimage.correlate(a, k, mode="mirror")


def _bilinear(raw: np.ndarray, ch: np.ndarray) -> np.ndarray:
    out = np.empty((*raw.shape, 3), dtype=np.float64)
    for c in range(3):
        plane = np.where(ch == c, raw, 0.0)
        out[..., c] = _conv(plane, _BILINEAR_G if c == 1 else _BILINEAR_RB)
    return out


def _malvar(raw: np.ndarray, ch: np.ndarray) -> np.ndarray:
    h, w = raw.shape
    out = np.repeat(raw[..., None], 3, axis=2).astype(np.float64)
    g_at = _conv(raw, _M_G_AT_RB)
    row = _conv(raw, _M_ROWWISE)
    col = _conv(raw, _M_COLWISE)
    diag = _conv(raw, _M_RB_AT_BR)
    is_r, is_g, is_b = ch == 0, ch == 1, ch == 2
    r_row = int(np.nonzero(ch[:2, :2] == 0)[0][0])  # row parity of the R samples
    row_has_r = np.broadcast_to((np.arange(h) % 2 == r_row)[:, None], (h, w))
    out[..., 1] = np.where(is_g, raw, g_at)
    g_in_r_row = is_g & row_has_r
    g_in_b_row = is_g & ~row_has_r
    out[..., 0] = np.where(is_r, raw, np.where(g_in_r_row, row, np.where(g_in_b_row, col, diag)))
    out[..., 2] = np.where(is_b, raw, np.where(g_in_b_row, row, np.where(g_in_r_row, col, diag)))
    return out


DEMOSAIC_METHODS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "bilinear": _bilinear,
    "malvar": _malvar,
}
"""Demosaicing methods by name (module docstring)."""


def demosaic(raw: npt.ArrayLike, pattern: str = DEFAULT_CFA, *, method: str = "malvar",
             domain: str = "log") -> np.ndarray:
    """RGB ``(height, width, 3)`` float32 from a Bayer mosaic ``(height, width)``.

    Parameters
    ----------
    raw : linear mosaic (e.g. a reconstructed image of a colour recording), finite,
        non-negative; NaN marks pixels without information and is filled from their
        neighbours' interpolation where possible.
    pattern : the Bayer layout.
    method : ``"malvar"`` (default) or ``"bilinear"``.
    domain : ``"log"`` (interpolate ``ln L``; positive output, for HDR) or ``"linear"``
        (the methods as published; negative results are clipped to 0 and counted in the
        log).
    """
    a = np.asarray(raw, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"demosaic: expected a 2-D (height, width) mosaic, got shape {a.shape}")
    if a.shape[0] < 2 or a.shape[1] < 2:
        raise ValueError(f"demosaic: a mosaic needs at least 2x2 pixels, got {a.shape}")
    try:
        fn = DEMOSAIC_METHODS[method]
    except KeyError:
        raise ValueError(f"demosaic: unknown method {method!r}; expected one of "
                         f"{sorted(DEMOSAIC_METHODS)}") from None
    if domain not in ("log", "linear"):
        raise ValueError(f"demosaic: domain must be 'log' or 'linear', got {domain!r}")
    ch = cfa_channels(pattern, height=a.shape[0], width=a.shape[1])
    if np.any(a[np.isfinite(a)] < 0):
        raise ValueError("demosaic: the mosaic has negative values; expected radiance >= 0")
    bad = ~np.isfinite(a)
    if domain == "log":
        pos = a[(~bad) & (a > 0)]
        floor = float(pos.min()) if pos.size else 1.0
        x = np.log(np.maximum(a, floor))
        if bad.any():
            x = _fill(x, bad, ch)
        return np.exp(fn(x, ch)).astype(np.float32)
    x = _fill(a, bad, ch) if bad.any() else a
    out = fn(x, ch)
    neg = out < 0
    if neg.any():
        logger.info("demosaic (%s, linear): %d negative samples clipped to 0", method,
                    int(neg.sum()))
        out = np.maximum(out, 0.0)
    return out.astype(np.float32)


def _fill(x: np.ndarray, bad: np.ndarray, ch: np.ndarray) -> np.ndarray:
    """Replace invalid samples by the mean of valid same-channel samples 2 px away."""
    out = x.copy()
    for c in range(3):
        sel = ch == c
        valid = sel & ~bad
        k = np.zeros((5, 5))
        k[0, 2] = k[4, 2] = k[2, 0] = k[2, 4] = k[0, 0] = k[0, 4] = k[4, 0] = k[4, 4] = 1
        num = _conv(np.where(valid, x, 0.0), k)
        den = _conv(valid.astype(np.float64), k)
        fix = sel & bad
        with np.errstate(invalid="ignore", divide="ignore"):
            out[fix] = np.where(den[fix] > 0, num[fix] / np.maximum(den[fix], _EPS),
                                np.nanmedian(np.where(valid, x, np.nan)))
    return out


def reconstruct_colour(image: npt.ArrayLike, pattern: str = DEFAULT_CFA, *,
                       transmittance: npt.ArrayLike = (1.0, 1.0, 1.0), method: str = "malvar",
                       domain: str = "log") -> np.ndarray:
    """RGB from a reconstructed image of a colour recording: divide each pixel by its
    filter's transmittance ``t_c`` (equation 1), then :func:`demosaic`. Pixels of value 0
    or NaN carry no information (a radiometric method found no event to invert) and are
    filled from the valid samples of their channel two pixels away."""
    a = np.asarray(image, dtype=np.float64)
    t = _transmittance(transmittance)
    ch = cfa_channels(pattern, height=a.shape[0], width=a.shape[1]) if a.ndim == 2 else None
    if ch is None:
        raise ValueError(f"reconstruct_colour: expected a 2-D mosaic, got shape {a.shape}")
    x = a / t[ch]
    missing = ~(x > 0)  # no information (0 or NaN): filled from the same channel around
    if missing.any():
        logger.info("reconstruct_colour: %d pixels without information filled from their "
                    "neighbours", int(missing.sum()))
        x = np.where(missing, np.nan, x)
    return demosaic(x, pattern, method=method, domain=domain)


# --------------------------------------------------------------------------- colour error

def _luma(rgb: np.ndarray) -> np.ndarray:
    r, g, b = REC709_LUMA
    return r * rgb[..., 0] + g * rgb[..., 1] + b * rgb[..., 2]


def colour_errors(rec: npt.ArrayLike, ref: npt.ArrayLike, *,
                  mask: npt.ArrayLike | None = None) -> dict[str, Any]:
    """Colour error of ``rec`` against ``ref`` (both linear RGB ``(height, width, 3)``).

    One global scale ``s = exp(median(ln Y_ref - ln Y_rec))`` is fitted first (the
    reconstruction is relative to ``L_const``); over the pixels where both images are
    positive in every channel (and ``mask``):

    - ``rms_log_error``: per channel (R, G, B), ``sqrt(mean(ln(s rec_c / ref_c)^2))``,
      natural-log units (``/ ln 2`` for stops); ``rms_log_chroma``: the same after
      removing each pixel's luminance ratio (colour only);
    - ``ciede2000_median``, ``ciede2000_mean``, ``ciede2000_p95``: CIEDE2000 between the
      two in CIE L*a*b* (D65), XYZ scaled so that the reference's 99th-percentile
      luminance is the white ``Y_n = 1``.
    """
    from skimage.color import deltaE_ciede2000, xyz2lab

    a = np.asarray(rec, dtype=np.float64)
    b = np.asarray(ref, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"colour_errors: expected two (height, width, 3) images of one shape, "
                         f"got {a.shape} and {b.shape}")
    ok = np.all(a > 0, axis=2) & np.all(b > 0, axis=2) & np.all(np.isfinite(a), axis=2) \
        & np.all(np.isfinite(b), axis=2)
    if mask is not None:
        ok &= np.asarray(mask, dtype=bool)
    if ok.sum() < 1:
        raise ValueError("colour_errors: no pixel where both images are positive")
    ya, yb = _luma(a), _luma(b)
    s = float(np.exp(np.median(np.log(yb[ok]) - np.log(ya[ok]))))
    la = np.log(a[ok] * s)
    lb = np.log(b[ok])
    d = la - lb
    rms = np.sqrt(np.mean(d * d, axis=0))
    dy = np.log(ya[ok] * s) - np.log(yb[ok])
    dc = d - dy[:, None]
    rms_c = np.sqrt(np.mean(dc * dc, axis=0))
    white = float(np.percentile(yb[ok], 99.0))
    xyz_a = (a[ok] * s) @ REC709_TO_XYZ.T / white
    xyz_b = b[ok] @ REC709_TO_XYZ.T / white
    lab_a = xyz2lab(xyz_a[None], illuminant="D65", observer="2")[0]
    lab_b = xyz2lab(xyz_b[None], illuminant="D65", observer="2")[0]
    de = deltaE_ciede2000(lab_b, lab_a)
    return {
        "n_pixels": int(ok.sum()),
        "scale": s,
        "rms_log_error": [float(v) for v in rms],
        "rms_log_chroma": [float(v) for v in rms_c],
        "ciede2000_median": float(np.median(de)),
        "ciede2000_mean": float(np.mean(de)),
        "ciede2000_p95": float(np.percentile(de, 95.0)),
        "white_luminance": white,
    }


def tonemap_rgb(rgb: npt.ArrayLike, *, method: str = "log", saturation: float = 0.6,
                **kw: Any) -> np.ndarray:
    """8-bit display RGB: tone-map the luminance with :func:`asynhdr.tonemap.tonemap`
    and keep each pixel's colour ratios, ``C_d = Y_d (C / Y)^saturation`` (Schlick 1994;
    ``saturation`` < 1 desaturates the brightest colours a little, as displays need)."""
    from asynhdr.tonemap import tonemap

    a = np.asarray(rgb, dtype=np.float64)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"tonemap_rgb: expected (height, width, 3), got shape {a.shape}")
    if not (math.isfinite(saturation) and saturation > 0):
        raise ValueError(f"tonemap_rgb: saturation must be > 0, got {saturation}")
    y = _luma(np.maximum(a, 0.0))
    yd = tonemap(y, method=method, **kw).astype(np.float64) / 255.0
    ratio = np.where(y[..., None] > 0, np.maximum(a, 0.0) / np.maximum(y[..., None], _EPS), 1.0)
    out = yd[..., None] * ratio ** saturation
    return np.floor(np.clip(out, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
