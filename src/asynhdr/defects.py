"""Dead pixels: found in flat fields, filled from their neighbours.

Under the rig's modulation every working pixel fires in every cycle: its irradiance sweeps
far more than a threshold each way. A pixel that fired no event in any cycle of a set of
flat-field captures, while the typical pixel fired several in each, is dead (stuck; real
arrays have a few in ten thousand). :func:`dead_pixels` makes the map from the events the
flat fields gave each pixel; the calibration file keeps it
(:class:`asynhdr.calib.Calibration`, ``defects``).

A reconstruction has nothing to say about a dead pixel (``ml``: NaN and
:data:`asynhdr.ml.FLAG_NO_EVENTS`). :func:`fill_defects` gives it the median of its
measured 8-neighbours, as a frame camera's defect correction does; only pixels of the map
that have no value are filled, never a measurement, and ``ml`` flags the filled ones
(:data:`asynhdr.ml.FLAG_FILLED`) so they stay apart from estimates (not valid, no
deviation).
"""

from __future__ import annotations

import numpy as np

__all__ = ["MIN_TYPICAL_EVENTS", "dead_pixels", "fill_defects"]

MIN_TYPICAL_EVENTS = 4
"""A pixel is called dead only when the median pixel fired at least this many events in the
same captures (else silence is no evidence)."""


def dead_pixels(counts: np.ndarray, *, min_typical: int = MIN_TYPICAL_EVENTS) -> np.ndarray:
    """Boolean map of the pixels with no event in ``counts`` (events per pixel over a set
    of flat-field cycles, ``(height, width)``); all False when the median pixel fired
    fewer than ``min_typical``."""
    c = np.asarray(counts)
    if c.ndim != 2:
        raise ValueError(f"dead_pixels: counts must be (height, width), got {c.shape}")
    if c.size == 0 or float(np.median(c)) < min_typical:
        return np.zeros(c.shape, dtype=bool)
    return c == 0


def fill_defects(image: np.ndarray, defects: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``image`` (2-D) with each pixel of ``defects`` that has no finite value set to the
    median of the finite values of its 8-neighbours that are not defects themselves.

    Returns ``(filled copy, mask of the pixels filled)``; a defect with no such neighbour
    stays as it was.
    """
    img = np.array(image, copy=True)
    d = np.asarray(defects, dtype=bool)
    if img.ndim != 2 or d.shape != img.shape:
        raise ValueError(f"fill_defects: image {img.shape} and defect map {d.shape} must be "
                         "the same (height, width)")
    done = np.zeros(d.shape, dtype=bool)
    h, w = img.shape
    for y, x in zip(*np.nonzero(d & ~np.isfinite(image)), strict=True):
        y0, y1, x0, x1 = max(y - 1, 0), min(y + 2, h), max(x - 1, 0), min(x + 2, w)
        patch = np.asarray(image[y0:y1, x0:x1], dtype=np.float64)
        use = np.isfinite(patch) & ~d[y0:y1, x0:x1]
        if use.any():
            img[y, x] = np.median(patch[use])
            done[y, x] = True
    return img, done
