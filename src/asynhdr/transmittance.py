"""Transmittance over one modulation cycle: a piecewise-linear waveform.

Both panels' transmittances are described by :class:`Waveform` (knots in phase ``u``,
the fraction of the period, and the transmittance at them); :func:`cycle_waveform`
builds the rig's standard cycle (a ramp, a return, a hold).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

__all__ = ["DEFAULT_KNOTS", "Shape", "Waveform", "cycle_waveform"]

DEFAULT_KNOTS = 4096
"""Knots over the ramp of a generated waveform. A log-linear (exponential) ramp over a
1000:1 range sampled this finely is within 4e-7 (relative) of the true curve: a timing
error under 0.003 µs on a 45 ms ramp, well below the 1 µs timestamp quantum."""

Shape = Literal["linear", "exponential"]


@dataclass(frozen=True, eq=False)
class Waveform:
    """Actual transmittance over one cycle, piecewise linear between knots.

    Attributes
    ----------
    phase : float64 knots, strictly increasing, first 0 and last 1 (fraction of the
        period).
    values : float64 transmittance at the knots, each in [0, 1].
    name : a short description ("exponential 0.001->1", "sampled", ...).
    """

    phase: np.ndarray
    values: np.ndarray
    name: str = "sampled"

    def __post_init__(self) -> None:
        ph = np.ascontiguousarray(self.phase, dtype=np.float64)
        va = np.ascontiguousarray(self.values, dtype=np.float64)
        object.__setattr__(self, "phase", ph)
        object.__setattr__(self, "values", va)
        if ph.ndim != 1 or va.shape != ph.shape or ph.size < 2:
            raise ValueError(
                f"waveform {self.name!r}: phase and values must be 1-D of equal length >= 2, "
                f"got {ph.shape} and {va.shape}"
            )
        if ph[0] != 0.0 or ph[-1] != 1.0 or np.any(np.diff(ph) <= 0):
            raise ValueError(
                f"waveform {self.name!r}: phase knots must increase strictly from 0 to 1"
            )
        if not np.all(np.isfinite(va)) or va.min() < 0.0 or va.max() > 1.0:
            raise ValueError(
                f"waveform {self.name!r}: transmittance must be finite and within [0, 1], "
                f"got range [{va.min():.4g}, {va.max():.4g}]"
            )

    def __call__(self, phase: npt.ArrayLike) -> np.ndarray:
        """Transmittance at ``phase`` (fraction of the period, in [0, 1])."""
        return np.interp(np.asarray(phase, dtype=np.float64), self.phase, self.values)

    @classmethod
    def from_samples(cls, values: npt.ArrayLike, *, name: str = "sampled") -> Waveform:
        """A waveform from samples evenly spaced over the cycle, first at phase 0, last at 1."""
        va = np.asarray(values, dtype=np.float64)
        return cls(np.linspace(0.0, 1.0, va.size), va, name=name)


def _ramp_values(shape: str, start: float, stop: float, s: np.ndarray) -> np.ndarray:
    """Transmittance along a ramp, ``s`` in [0, 1] from ``start`` to ``stop``."""
    if shape == "linear":
        return start + (stop - start) * s
    if shape == "exponential":
        if start <= 0.0 or stop <= 0.0:
            raise ValueError(
                "exponential ramp: start and stop transmittance must be > 0 "
                f"(got {start}, {stop}); the panel's leakage floor sets the start"
            )
        return start * (stop / start) ** s
    raise ValueError(f"unknown waveform shape {shape!r}; expected 'linear' or 'exponential'")


def cycle_waveform(
    shape: str,
    *,
    start: float,
    stop: float,
    ramp_fraction: float,
    n_knots: int = DEFAULT_KNOTS,
) -> Waveform:
    """One modulation cycle: a ramp from ``start`` to ``stop``, then a linear return.

    Over phase ``[0, ramp_fraction]`` the transmittance follows ``shape`` (sampled on
    ``n_knots`` intervals; a linear ramp needs only its two ends):
    ``linear``: ``T = start + (stop - start) s``; ``exponential`` (log-linear):
    ``T = start (stop / start)^s``, with ``s = u / ramp_fraction``. Over the first half
    of ``[ramp_fraction, 1]`` it returns linearly to ``start`` and holds there for the
    second half, so every pixel has settled (and fired its return events) before the
    next cycle starts.
    """
    if not 0.0 < ramp_fraction <= 1.0:
        raise ValueError(f"ramp_fraction must be in (0, 1], got {ramp_fraction}")
    if n_knots < 2:
        raise ValueError(f"n_knots must be >= 2, got {n_knots}")
    # a straight ramp is exact with its two end knots; curved ones need the table
    s = np.linspace(0.0, 1.0, (1 if shape == "linear" else n_knots) + 1)
    vals = _ramp_values(shape, start, stop, s)
    phase = s * ramp_fraction
    if ramp_fraction < 1.0:
        settle = ramp_fraction + 0.5 * (1.0 - ramp_fraction)
        phase = np.append(phase, [settle, 1.0])
        vals = np.append(vals, [start, start])
    return Waveform(phase, vals, name=f"{shape} {start:g}->{stop:g}")
