"""The optics of the rig: two light paths through LCD panels, modulated every cycle.

Sensor irradiance (Wu et al. 2024, Eqs. 8-9)::

    I(x, y, t) = k_lens * (T1(t) * L(x, y) + T2(t) * L_const)

``T1`` (scene path) rises from its panel's leakage floor to fully open during the
ramp part of each cycle; ``T2`` (reference path, a weak uniform source ``L_const``)
falls. After the ramp both panels return to their start values, ready for the next
cycle. Transmittances are *actual* transmittances (leakage included), in [0, 1].

Waveforms are piecewise linear between knots over one cycle, phase ``u`` in [0, 1]
(fraction of ``period_us``). The exact sensor engine uses that: irradiance is then
exactly piecewise linear in time for every pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from asynhdr.events import make_triggers

__all__ = [
    "DEFAULT_KNOTS",
    "Rig",
    "Waveform",
    "cycle_waveform",
]

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


@dataclass(frozen=True)
class Rig:
    """The modulation optics: two panels, the reference source, the lens.

    Attributes
    ----------
    period_us : cycle length in µs (the paper runs 20 cycles/s: 50,000 µs).
    ramp_fraction : the part of the cycle over which ``T1`` rises and ``T2`` falls;
        the rest is the return to the start values (then a hold). Reconstruction
        integrates the ramp.
    t1_shape, t2_shape : ``"linear"`` or ``"exponential"`` ramps of the scene and
        reference panels (ignored where ``t1``/``t2`` give sampled curves). Default
        linear for both.
    contrast_ratio_1, contrast_ratio_2 : open/closed transmittance of each panel;
        the leakage floor is ``1 / contrast_ratio`` (TN panels: about 1000:1).
    t2_stop : how far the reference panel closes during the ramp, as a fraction of its
        range (1.0 closes it to its floor). The default 0.5 makes ``T2`` fall at half
        the rate ``T1`` rises, meeting the paper's design rule ``|dT2/dt| < |dT1/dt|``
        (section 2.2): pixels brighter than ``L_const`` then only ever brighten.
    l_const : radiance of the reference source, in the scene's unit. Default 10 lux:
        near the geometric centre of the paper's chart (160,000 lux x 10^-4.11).
    k_lens : lens attenuation (dimensionless); it scales both paths.
    t1, t2 : optional sampled waveforms replacing the generated ones.
    """

    period_us: int = 50_000
    ramp_fraction: float = 0.9
    t1_shape: Shape = "linear"
    t2_shape: Shape = "linear"
    contrast_ratio_1: float = 1000.0
    contrast_ratio_2: float = 1000.0
    t2_stop: float = 0.5
    l_const: float = 10.0
    k_lens: float = 1.0
    n_knots: int = DEFAULT_KNOTS
    t1: Waveform | None = field(default=None, compare=False)
    t2: Waveform | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if int(self.period_us) != self.period_us or self.period_us <= 0:
            raise ValueError(f"period_us must be a positive whole number of µs, got "
                             f"{self.period_us}")
        if not 0.0 < self.ramp_fraction <= 1.0:
            raise ValueError(f"ramp_fraction must be in (0, 1], got {self.ramp_fraction}")
        for name in ("contrast_ratio_1", "contrast_ratio_2"):
            v = getattr(self, name)
            if not (v >= 1.0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a finite number >= 1, got {v}")
        if not (self.l_const > 0 and math.isfinite(self.l_const)):
            raise ValueError(f"l_const must be positive and finite, got {self.l_const}")
        if not (self.k_lens > 0 and math.isfinite(self.k_lens)):
            raise ValueError(f"k_lens must be positive and finite, got {self.k_lens}")
        if not 0.0 <= self.t2_stop <= 1.0:
            raise ValueError(f"t2_stop must be in [0, 1], got {self.t2_stop}")
        for shape in (self.t1_shape, self.t2_shape):
            if shape not in ("linear", "exponential"):
                raise ValueError(f"unknown waveform shape {shape!r}; "
                                 "expected 'linear' or 'exponential'")

    @property
    def ramp_us(self) -> float:
        """Length of the ramp in µs."""
        return self.period_us * self.ramp_fraction

    def waveforms(self) -> tuple[Waveform, Waveform]:
        """``(T1, T2)`` over one cycle, leakage floors included."""
        floor1 = 1.0 / self.contrast_ratio_1
        floor2 = 1.0 / self.contrast_ratio_2
        t1 = self.t1 or cycle_waveform(self.t1_shape, start=floor1, stop=1.0,
                                       ramp_fraction=self.ramp_fraction, n_knots=self.n_knots)
        stop2 = floor2 + (1.0 - floor2) * (1.0 - self.t2_stop)
        t2 = self.t2 or cycle_waveform(self.t2_shape, start=1.0, stop=stop2,
                                       ramp_fraction=self.ramp_fraction, n_knots=self.n_knots)
        return t1, t2

    def irradiance(self, radiance: npt.ArrayLike, phase: npt.ArrayLike) -> np.ndarray:
        """``k_lens (T1(u) L + T2(u) L_const)`` (Eq. 9), broadcasting ``radiance`` and ``phase``."""
        t1, t2 = self.waveforms()
        u = np.asarray(phase, dtype=np.float64)
        return self.k_lens * (t1(u) * np.asarray(radiance, dtype=np.float64)
                              + t2(u) * self.l_const)

    def cycle_starts_us(self, n_cycles: int, *, t0_us: int = 0) -> np.ndarray:
        """Start time of each cycle in µs (int64)."""
        return t0_us + np.arange(n_cycles, dtype=np.int64) * np.int64(self.period_us)

    def triggers(self, n_cycles: int, *, t0_us: int = 0, channel: int = 0) -> np.ndarray:
        """One rising trigger edge at each cycle start (the generator's sync output)."""
        return make_triggers(self.cycle_starts_us(n_cycles, t0_us=t0_us), True, channel)

    def to_metadata(self) -> dict[str, Any]:
        """JSON-serialisable description (sampled waveforms are summarised by name)."""
        d: dict[str, Any] = {
            "period_us": int(self.period_us),
            "ramp_fraction": self.ramp_fraction,
            "t1_shape": self.t1_shape,
            "t2_shape": self.t2_shape,
            "contrast_ratio_1": self.contrast_ratio_1,
            "contrast_ratio_2": self.contrast_ratio_2,
            "t2_stop": self.t2_stop,
            "l_const": self.l_const,
            "k_lens": self.k_lens,
            "n_knots": self.n_knots,
        }
        if self.t1 is not None:
            d["t1"] = {"name": self.t1.name, "phase": self.t1.phase.tolist(),
                       "values": self.t1.values.tolist()}
        if self.t2 is not None:
            d["t2"] = {"name": self.t2.name, "phase": self.t2.phase.tolist(),
                       "values": self.t2.values.tolist()}
        return d

    @classmethod
    def from_metadata(cls, d: dict[str, Any]) -> Rig:
        """Inverse of ``to_metadata``."""
        names = ("period_us", "ramp_fraction", "t1_shape", "t2_shape", "contrast_ratio_1",
                 "contrast_ratio_2", "t2_stop", "l_const", "k_lens", "n_knots")
        kw: dict[str, Any] = {k: d[k] for k in names if k in d}
        for name in ("t1", "t2"):
            if name in d:
                w = d[name]
                kw[name] = Waveform(np.asarray(w["phase"]), np.asarray(w["values"]),
                                    name=w.get("name", "sampled"))
        return cls(**kw)
