"""Colour (RGB) HDR images: read a scene's linear RGB, write a demosaiced RGB image.

Reading (:func:`read_rgb_radiance`): ``.exr`` (R, G, B channels; alpha ignored),
``.hdr`` (Radiance RGBE through OpenCV), ``.npy`` and ``.tif`` holding
``(height, width, 3|4)``; negative values (filter undershoot) are clipped to 0 and
counted, NaN or infinite values are an error.

Writing (:func:`write_rgb_image`), atomic, by extension: ``.exr`` (FLOAT channels R, G,
B, ZIP, with the metadata as the JSON string attribute ``asynhdr_metadata`` like
:func:`asynhdr.io.images.write_image`), ``.hdr`` (RGBE), ``.npy``, ``.tif`` (float32
RGB, metadata as JSON in the description) and ``.png`` (8-bit, tone-mapped by
:func:`asynhdr.colour.tonemap_rgb`).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import OpenEXR
import tifffile

from asynhdr._atomic import atomic_path
from asynhdr.io.images import METADATA_ATTRIBUTE, read_image

__all__ = ["RGB_WRITE_FORMATS", "read_rgb_radiance", "write_rgb_image"]

logger = logging.getLogger(__name__)

RGB_WRITE_FORMATS = (".exr", ".hdr", ".npy", ".tif", ".tiff", ".png")
"""Extensions :func:`write_rgb_image` accepts."""


def read_rgb_radiance(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict[str, Any]]:
    """Linear RGB float32 ``(height, width, 3)`` of an HDR image, and an info dict
    (``source``, ``width``, ``height``, ``clipped_negative``)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such file")
    if p.suffix.lower() == ".hdr":
        bgr = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if bgr is None or bgr.ndim != 3 or bgr.shape[2] != 3:
            raise ValueError(f"{p}: not a Radiance RGBE (.hdr) image (OpenCV cannot decode it)")
        rgb = np.ascontiguousarray(bgr[..., ::-1], dtype=np.float32)
    else:
        rgb = read_image(p)
    if rgb.ndim != 3 or rgb.shape[2] not in (3, 4):
        raise ValueError(f"{p}: holds shape {rgb.shape}; a colour image is (height, width, 3), "
                         "this one is grey")
    rgb = np.ascontiguousarray(rgb[..., :3], dtype=np.float32)
    bad = int(np.count_nonzero(~np.isfinite(rgb)))
    if bad:
        raise ValueError(f"{p}: {bad} NaN or infinite values; radiance must be finite")
    neg = rgb < 0
    n_neg = int(np.count_nonzero(neg))
    if n_neg:
        logger.warning("%s: clipped %d negative RGB values to 0", p, n_neg)
        rgb = np.where(neg, np.float32(0.0), rgb)
    return rgb, {"source": str(p), "width": int(rgb.shape[1]), "height": int(rgb.shape[0]),
                 "clipped_negative": n_neg}


def write_rgb_image(path: str | os.PathLike[str], rgb: np.ndarray, *,
                    metadata: dict[str, Any] | None = None, tonemap: str = "log") -> Path:
    """Write linear RGB ``(height, width, 3)``, format by extension (module docstring)."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in RGB_WRITE_FORMATS:
        raise ValueError(f"{p}: unsupported extension for an RGB image; expected one of "
                         f"{RGB_WRITE_FORMATS}")
    a = np.ascontiguousarray(rgb, dtype=np.float32)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"{p}: expected (height, width, 3) RGB, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{p}: {int((~np.isfinite(a)).sum())} NaN or infinite values")
    meta = None if metadata is None else json.dumps(metadata, default=str)
    with atomic_path(p) as tmp:
        if ext == ".exr":
            header: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION,
                                      "type": OpenEXR.scanlineimage}
            if meta is not None:
                header[METADATA_ATTRIBUTE] = meta
            chans = {c: np.ascontiguousarray(a[..., i]) for i, c in enumerate("RGB")}
            with OpenEXR.File(header, chans) as f:
                f.write(str(tmp))
        elif ext == ".hdr":
            if not cv2.imwrite(str(tmp), np.ascontiguousarray(a[..., ::-1])):
                raise ValueError(f"{p}: OpenCV could not write the RGBE image")
        elif ext == ".npy":
            with open(tmp, "wb") as fh:
                np.save(fh, a)
        elif ext in (".tif", ".tiff"):
            tifffile.imwrite(tmp, a, photometric="rgb", description=meta)
        else:
            from asynhdr.colour import tonemap_rgb

            png = tonemap_rgb(a, method=tonemap)
            if not cv2.imwrite(str(tmp), np.ascontiguousarray(png[..., ::-1]),
                               [cv2.IMWRITE_PNG_COMPRESSION, 6]):
                raise ValueError(f"{p}: OpenCV could not write the PNG")
    return p
