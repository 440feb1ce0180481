"""Parameters of the DVS pixel model, and named presets.

Every value is written once, here, with its source. Thresholds are in natural-log
units of irradiance (a pixel fires when ``|log I - log I_ref| >= c``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

__all__ = ["PRESETS", "SensorParams", "get_preset"]


@dataclass(frozen=True)
class SensorParams:
    """The pixel model's parameters.

    Attributes
    ----------
    name : preset name, or ``"custom"``.
    threshold_on, threshold_off : nominal ON and OFF contrast thresholds ``c`` (log
        units). v2e's defaults are 0.2 for both (Hu, Liu, Delbruck 2021, v2e).
    threshold_sigma : standard deviation of the per-pixel threshold mismatch (log
        units), frozen per pixel, Gaussian. v2e's default is 0.03.
    threshold_min : thresholds drawn below this are raised to it (v2e clips at 0.01).
    timestamp_resolution_us : event time quantum; timestamps are floored to it.
    """

    name: str = "custom"
    threshold_on: float = 0.2
    threshold_off: float = 0.2
    threshold_sigma: float = 0.03
    threshold_min: float = 0.01
    timestamp_resolution_us: int = 1

    def __post_init__(self) -> None:
        for nm in ("threshold_on", "threshold_off", "threshold_min"):
            v = getattr(self, nm)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"sensor {self.name!r}: {nm} must be positive, got {v}")
        if not (math.isfinite(self.threshold_sigma) and self.threshold_sigma >= 0):
            raise ValueError(
                f"sensor {self.name!r}: threshold_sigma must be >= 0, got {self.threshold_sigma}"
            )
        if int(self.timestamp_resolution_us) != self.timestamp_resolution_us or \
                self.timestamp_resolution_us < 1:
            raise ValueError(
                f"sensor {self.name!r}: timestamp_resolution_us must be a whole number >= 1, "
                f"got {self.timestamp_resolution_us}"
            )

    def with_(self, **changes: Any) -> SensorParams:
        """A copy with some fields changed (named ``custom`` unless ``name`` is given)."""
        changes.setdefault("name", "custom")
        return replace(self, **changes)

    def to_metadata(self) -> dict[str, Any]:
        """All fields, JSON-serialisable."""
        return asdict(self)

    @classmethod
    def from_metadata(cls, d: dict[str, Any]) -> SensorParams:
        """Inverse of ``to_metadata`` (unknown keys are an error)."""
        return cls(**d)


PRESETS: dict[str, SensorParams] = {
    # Noise-free pixel, no mismatch: every pixel with the same radiance fires at the
    # same instants. Thresholds are v2e's nominal 0.2.
    "ideal": SensorParams(name="ideal", threshold_sigma=0.0),
    # v2e's default pixel (v2e README / emulator defaults: pos_thres = neg_thres = 0.2,
    # sigma_thres = 0.03), without its noise sources.
    "v2e": SensorParams(name="v2e"),
}


def get_preset(name: str) -> SensorParams:
    """The preset called ``name``; ``ValueError`` listing the known ones otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(
            f"unknown sensor preset {name!r}; known presets: {', '.join(sorted(PRESETS))}"
        ) from None
