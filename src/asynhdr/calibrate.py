"""Calibration: the per-pixel threshold correction map (c-map) from flat-field captures.

On a uniformly lit field every pixel sees the same log-irradiance swing, so a pixel
whose threshold is ``c_p = c * g_p`` fires ``1/g_p`` times as many (weighted) events
as a nominal one. Averaging the weighted sums ``S_p`` of ``N`` captures (and of all
their cycles) and taking::

    cmap_p = median_q(S_q) / S_p

gives the factor that turns the nominal ``c`` into the pixel's own ``c * cmap_p`` in
``img = L_const exp(c cmap S)`` (Wu et al. 2024, section 2.3: "iterative acquisition of
images from a uniformly illuminated light box, followed by the averaging of the
obtained results"). Because each weighting sums the events differently, one map is
estimated per weighting.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from asynhdr.events import Recording
from asynhdr.reconstruct import DEFAULT_K, WEIGHTINGS, CycleWindows, weighted_sums, windows_for

__all__ = ["CMap", "cmap_key", "estimate_cmap"]

logger = logging.getLogger(__name__)


def cmap_key(method: str, *, k: float = DEFAULT_K) -> str:
    """Name of the map for a weighting (``"exp"`` maps carry their ``k``)."""
    return f"exp:k={k:g}" if method == "exp" else method


@dataclass(frozen=True, eq=False)
class CMap:
    """Per-pixel threshold corrections, one ``(height, width)`` float32 map per weighting.

    Attributes
    ----------
    maps : key (see ``cmap_key``) -> map. Multiply the nominal threshold by it.
    metadata : how it was made (flat-field radiance, number of captures and cycles).
    """

    maps: dict[str, np.ndarray]
    metadata: dict[str, Any] = field(default_factory=dict)

    def for_method(self, method: str, *, k: float = DEFAULT_K) -> np.ndarray | None:
        """The map for ``method``; ``None`` (with a warning) for methods without one."""
        key = cmap_key(method, k=k)
        if key in self.maps:
            return self.maps[key]
        if method in ("ttfe", "count", "invert", "ml") and "raw" in self.maps:
            # the raw map is the per-pixel threshold ratio itself (event counts)
            return self.maps["raw"]
        raise ValueError(
            f"the c-map has no map for {key!r}; it has {sorted(self.maps)}. "
            "Calibrate with this method (and k) too."
        )

    @property
    def shape(self) -> tuple[int, int]:
        first = next(iter(self.maps.values()))
        return (int(first.shape[0]), int(first.shape[1]))


def estimate_cmap(
    captures: Sequence[Recording] | Iterable[Recording],
    *,
    methods: Sequence[str] = tuple(WEIGHTINGS),
    k: float = DEFAULT_K,
    windows: CycleWindows | None = None,
    min_abs_sum: float = 1e-6,
) -> CMap:
    """Estimate the c-map from flat-field captures.

    Parameters
    ----------
    captures : recordings of a uniform field (each may hold several cycles).
    methods : weightings to calibrate (one map each).
    k : the exponential weighting's ``k``.
    windows : integration windows (default: each capture's own, see ``windows_for``).
    min_abs_sum : pixels whose mean weighted sum is smaller than this (no events) get 1.

    Raises ``ValueError`` when there are no captures or their geometries differ.
    """
    caps = list(captures)
    if not caps:
        raise ValueError("estimate_cmap: no flat-field captures given")
    shape = (caps[0].height, caps[0].width)
    for i, c in enumerate(caps):
        if (c.height, c.width) != shape:
            raise ValueError(f"estimate_cmap: capture {i} is {c.width}x{c.height}, "
                             f"expected {shape[1]}x{shape[0]}")
    for m in methods:
        if m not in WEIGHTINGS:
            raise ValueError(f"estimate_cmap: unknown weighting {m!r}; "
                             f"expected some of {list(WEIGHTINGS)}")
    maps: dict[str, np.ndarray] = {}
    n_cycles = 0
    sums: dict[str, np.ndarray] = {m: np.zeros(shape, np.float64) for m in methods}
    for cap in caps:
        win = windows or windows_for(cap)
        n_cycles += win.n_cycles
        for m in methods:
            sums[m] += weighted_sums(cap, win, method=m, k=k).sum(axis=0)
    for m in methods:
        mean = sums[m] / n_cycles
        valid = np.abs(mean) > min_abs_sum
        ref = float(np.median(mean[valid])) if valid.any() else 0.0
        cm = np.ones(shape, np.float64)
        if ref != 0.0:
            cm[valid] = ref / mean[valid]
            bad = cm <= 0
            cm[bad] = 1.0
            if bad.any():
                logger.warning("c-map %s: %d pixels of opposite sign set to 1", m, int(bad.sum()))
        maps[cmap_key(m, k=k)] = cm.astype(np.float32)
    meta: dict[str, Any] = {
        "n_captures": len(caps),
        "n_cycles": n_cycles,
        "methods": list(methods),
        "k": float(k),
    }
    return CMap(maps=maps, metadata=meta)
