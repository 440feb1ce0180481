"""Calibration: the per-pixel threshold correction map (c-map) from flat-field captures.

On a uniformly lit field every pixel sees the same log-irradiance swing ``D``. A pixel
whose thresholds are ``g_p`` times the nominal ones reaches it with weighted sums
``S_on``, ``S_off`` such that ``g_p (c_on S_on,p - c_off S_off,p) = D``. Averaging the
level ``l_p = c_on S_on,p - c_off S_off,p`` of ``N`` captures (and of all their cycles)
and taking::

    cmap_p = median_q(l_q) / l_p

gives the factor that turns the nominal thresholds into the pixel's own in
``img = L_const exp(cmap (c_on S_on - c_off S_off))`` (Wu et al. 2024, section 2.3:
"iterative acquisition of images from a uniformly illuminated light box, followed by
the averaging of the obtained results"). Because each weighting sums the events
differently, one map is estimated per weighting; the ``raw`` map (events counted) is the
per-pixel threshold ratio itself, which the methods that use thresholds directly take
(their record's ``cmap`` kind is ``"threshold"``).

A pixel keeps the nominal thresholds (map 1, counted in the metadata and a warning) when
its flat-field level does not measure a threshold: no events, a level of the wrong sign,
or a correction beyond :data:`CMAP_MAX_GAIN` either way. Without the last guard a pixel
whose weighted events happen to cancel on the flat field (the exponential weighting
gives late events weights near zero) gets a gain of thousands, and its reconstruction
of a scene leaves float32's range.

Captures are :class:`~asynhdr.source.Source` objects or recordings, read one at a time.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from asynhdr.events import Recording
from asynhdr.reconstruct import (
    DEFAULT_K,
    METHODS,
    WEIGHTINGS,
    CycleWindows,
    thresholds_of,
    weighted_sums,
    windows_for,
)
from asynhdr.source import Progress, Source, as_source

__all__ = [
    "CMAP_MAX_GAIN",
    "CMAP_MIN_LEVEL",
    "CMap",
    "cmap_from_levels",
    "cmap_key",
    "estimate_cmap",
    "warn_nominal",
]

logger = logging.getLogger(__name__)


CMAP_MAX_GAIN = 10.0
"""The largest correction a c-map applies, either way. Thresholds of one sensor differ by
a few percent to tens of percent between pixels; a factor of ten is not a threshold but
a pixel that is hot, dead or whose flat-field level is noise."""



CMAP_MIN_LEVEL = 1e-6
"""A pixel whose mean flat-field level is smaller than this fired nothing: it keeps 1."""


def cmap_from_levels(total: np.ndarray, n_cycles: int, *,
                     min_abs_level: float = CMAP_MIN_LEVEL) -> tuple[np.ndarray, int]:
    """One weighting's c-map, ``median(l) / l_p``, from the per-pixel sums of the level
    ``l`` over ``n_cycles`` flat-field cycles. Pixels whose level measures no threshold
    (module docstring) get 1; returns the map (float32) and their number
    (:func:`warn_nominal` reports them)."""
    mean = total / n_cycles
    valid = np.abs(mean) > min_abs_level
    cm = np.ones(mean.shape, np.float64)
    if valid.any():
        ref = float(np.median(mean[valid]))
        if ref != 0.0:
            cm[valid] = ref / mean[valid]
    bad = ~valid | (cm <= 0) | (cm > CMAP_MAX_GAIN) | (cm < 1.0 / CMAP_MAX_GAIN)
    cm[bad] = 1.0
    return cm.astype(np.float32), int(bad.sum())


def warn_nominal(kept: dict[str, int], n_pixels: int) -> None:
    """One warning for the pixels each map left at the nominal thresholds (if any)."""
    if any(kept.values()):
        logger.warning("c-map: pixels of %d that keep the nominal thresholds (no events, a "
                       "level of the wrong sign, or a correction beyond %gx): %s", n_pixels,
                       CMAP_MAX_GAIN, ", ".join(f"{k} {v}" for k, v in kept.items()))


def cmap_key(method: str, *, k: float = DEFAULT_K) -> str:
    """Name of the map for a weighting (``"exp"`` maps carry their ``k``)."""
    return f"exp:k={k:g}" if method == "exp" else method


@dataclass(frozen=True, eq=False)
class CMap:
    """Per-pixel threshold corrections, one ``(height, width)`` float32 map per weighting.

    Attributes
    ----------
    maps : key (see ``cmap_key``) -> map. Multiply the nominal thresholds by it.
    metadata : how it was made (flat-field radiance, number of captures and cycles).
    """

    maps: dict[str, np.ndarray]
    metadata: dict[str, Any] = field(default_factory=dict)

    def for_method(self, method: str, *, k: float = DEFAULT_K) -> np.ndarray | None:
        """The map ``method`` takes (its record's ``cmap`` kind: its own weighting's, or
        the threshold ratio ``raw``); None for a method that takes none."""
        m = METHODS.get(method)
        if m is None:
            raise ValueError(f"unknown method {method!r}; expected one of {list(METHODS)}")
        if m.cmap is None:
            return None
        key = cmap_key(method, k=k) if m.cmap == "weighting" else "raw"
        if key in self.maps:
            return self.maps[key]
        raise ValueError(
            f"the c-map has no map for {key!r} (method {method!r}); it has "
            f"{sorted(self.maps)}. Calibrate with this method (and k) too."
        )

    @property
    def shape(self) -> tuple[int, int]:
        first = next(iter(self.maps.values()))
        return (int(first.shape[0]), int(first.shape[1]))


def estimate_cmap(
    captures: Sequence[Source | Recording] | Iterable[Source | Recording],
    *,
    methods: Sequence[str] = tuple(WEIGHTINGS),
    k: float = DEFAULT_K,
    windows: CycleWindows | None = None,
    threshold_on: float | None = None,
    threshold_off: float | None = None,
    min_abs_level: float = CMAP_MIN_LEVEL,
    progress: Progress | None = None,
) -> CMap:
    """Estimate the c-map from flat-field captures.

    Parameters
    ----------
    captures : sources or recordings of a uniform field (each may hold several cycles),
        read one at a time.
    methods : weightings to calibrate (one map each).
    k : the exponential weighting's ``k``.
    windows : integration windows (default: each capture's own, see ``windows_for``).
    threshold_on, threshold_off : nominal thresholds (default: the first capture's
        sensor, see :func:`asynhdr.reconstruct.thresholds_of`).
    min_abs_level : pixels whose mean level is smaller than this (no events) get 1.
    progress : ``progress("calibrate", captures_done, n_captures or None)``.

    Raises ``ValueError`` when there are no captures or their geometries differ.
    """
    for m in methods:
        if m not in WEIGHTINGS:
            raise ValueError(f"estimate_cmap: unknown weighting {m!r}; "
                             f"expected some of {list(WEIGHTINGS)}")
    total = len(captures) if isinstance(captures, Sequence) else None
    shape: tuple[int, int] | None = None
    c: tuple[float, float] | None = None
    sums: dict[str, np.ndarray] = {}
    n_cycles = n_caps = 0
    for i, cap in enumerate(captures):
        src = as_source(cap, name=f"capture {i}")
        if shape is None:
            shape = (src.height, src.width)
            c0 = thresholds_of(src)
            c = (c0[0] if threshold_on is None else float(threshold_on),
                 c0[1] if threshold_off is None else float(threshold_off))
            sums = {m: np.zeros(shape, np.float64) for m in methods}
        elif (src.height, src.width) != shape:
            raise ValueError(f"estimate_cmap: {src.name} is {src.width}x{src.height}, "
                             f"expected {shape[1]}x{shape[0]}")
        assert c is not None
        win = windows or windows_for(src)
        rec = src.read()
        n_cycles += win.n_cycles
        n_caps += 1
        for m in methods:
            sums[m] += weighted_sums(rec, win, method=m, k=k, c_on=c[0], c_off=c[1]).sum(axis=0)
        if progress is not None:
            progress("calibrate", n_caps, total)
    if shape is None or c is None:
        raise ValueError("estimate_cmap: no flat-field captures given")
    maps: dict[str, np.ndarray] = {}
    kept: dict[str, int] = {}
    for m in methods:
        key = cmap_key(m, k=k)
        maps[key], kept[key] = cmap_from_levels(sums[m], n_cycles, min_abs_level=min_abs_level)
    warn_nominal(kept, shape[0] * shape[1])
    meta: dict[str, Any] = {
        "n_captures": n_caps,
        "n_cycles": n_cycles,
        "methods": list(methods),
        "k": float(k),
        "threshold_on": c[0],
        "threshold_off": c[1],
        "nominal_pixels": kept,
    }
    return CMap(maps=maps, metadata=meta)
