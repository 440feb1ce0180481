"""The optics of the rig: two light paths through LCD panels, modulated every cycle.

Sensor irradiance (Wu et al. 2024, Eqs. 8-9)::

    I(x, y, t) = k_lens * (T1(t) * L(x, y) + T2(t) * L_const)

``T1`` (scene path) rises from its panel's leakage floor to fully open during the
ramp part of each cycle; ``T2`` (reference path, a weak uniform source ``L_const``)
falls. After the ramp both panels return to their start values, ready for the next
cycle. Transmittances are *actual* transmittances (leakage included), in [0, 1].

The rig *commands* transmittances (:meth:`Rig.target_waveforms`); real liquid-crystal
panels produce them through their voltage curve and their slow, asymmetric response
(:mod:`asynhdr.panel`). With a panel named (``panel="tn"`` or ``"fast_shutter"``) the
drive voltages are designed for those panels (:func:`asynhdr.waveform.design`, with
pre-emphasis unless ``pre_emphasis=False``) and :meth:`Rig.waveforms` returns what the
panels then really transmit, one knot per generator sample: the transmittance the
sensor sees. ``panel="ideal"`` follows the command instantly.

Waveforms are piecewise linear between knots over one cycle, phase ``u`` in [0, 1]
(fraction of ``period_us``). The exact sensor engine uses that: irradiance is then
exactly piecewise linear in time for every pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import numpy.typing as npt

from asynhdr.events import make_triggers
from asynhdr.panel import FAST_FALL_US, FAST_RISE_US, Panel, tn_panel
from asynhdr.transmittance import DEFAULT_KNOTS, Shape, Waveform, cycle_waveform
from asynhdr.waveform import DEFAULT_SAMPLE_RATE_HZ, design

__all__ = [
    "DEFAULT_KNOTS",
    "PANELS",
    "Rig",
    "Waveform",
    "cycle_waveform",
]

PANELS = ("ideal", "tn", "fast_shutter")
"""Panel models the rig can name: ``ideal`` follows the command at once; ``tn`` is a
twisted-nematic pair (normally-white scene panel, normally-black reference panel, whose
field-driven directions serve the fast parts of the cycle); ``fast_shutter`` is a
sub-millisecond nematic shutter on both paths. Constants and sources: docs/panels.md."""


def rig_panels(name: str, *, contrast_ratio_1: float, contrast_ratio_2: float
               ) -> tuple[Panel, Panel] | None:
    """The scene and reference panels of the preset ``name`` (None for ``ideal``), with
    the rig's contrast ratios as their leakage floors."""
    if name == "ideal":
        return None
    if name == "tn":
        return (tn_panel(normally_white=True, contrast_ratio=contrast_ratio_1, name="tn"),
                tn_panel(normally_white=False, contrast_ratio=contrast_ratio_2,
                         name="tn_nb"))
    if name == "fast_shutter":
        return tuple(tn_panel(rise_us=FAST_RISE_US, fall_us=FAST_FALL_US, contrast_ratio=cr,
                              name="fast_shutter")
                     for cr in (contrast_ratio_1, contrast_ratio_2))  # type: ignore[return-value]
    raise ValueError(f"unknown panel {name!r}; expected one of {', '.join(PANELS)}")

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
    t1, t2 : optional sampled target waveforms replacing the generated ones.
    panel : the panels the waveforms drive (:data:`PANELS`): ``"ideal"`` transmits the
        target at once; ``"tn"`` and ``"fast_shutter"`` transmit what real panels of
        that kind make of the designed drive (module docstring).
    pre_emphasis : design the drive to invert the panels' response (else the static
        inverse of the target is commanded). Ignored for ``panel="ideal"``.
    sample_rate_hz : the signal generator's sample rate for the drive.
    design_range : the scene radiances ``(lowest, highest)`` the rig was designed for
        (:func:`asynhdr.design.design`), in the unit of ``l_const``; None if unknown.
        :meth:`mid_radiance` is their geometric middle.
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
    panel: str = "ideal"
    pre_emphasis: bool = True
    sample_rate_hz: float = DEFAULT_SAMPLE_RATE_HZ
    design_range: tuple[float, float] | None = None

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
        if self.panel not in PANELS:
            raise ValueError(f"unknown panel {self.panel!r}; expected one of "
                             f"{', '.join(PANELS)}")
        if not (self.sample_rate_hz > 0 and math.isfinite(self.sample_rate_hz)):
            raise ValueError(f"sample_rate_hz must be positive and finite, got "
                             f"{self.sample_rate_hz}")
        if self.design_range is not None:
            try:
                lo, hi = (float(v) for v in self.design_range)
            except (TypeError, ValueError):
                raise ValueError(f"design_range must be (lowest, highest), got "
                                 f"{self.design_range!r}") from None
            if not (0 < lo < hi and math.isfinite(hi)):
                raise ValueError(f"design_range must have 0 < lowest < highest, got "
                                 f"{self.design_range!r}")
            object.__setattr__(self, "design_range", (lo, hi))

    def working_range(self) -> tuple[float, float]:
        """The radiances ``(lowest, highest)`` the rig works for: :attr:`design_range` for a
        designed rig; else, for the paper's rig, ``L_const`` (below which pixels only see
        the reference fall) to ``L_const CR_1`` (above which the scene dominates from the
        start), and for a rig with its own waveforms ``L_const T2 / T1`` over the ramp's
        extremes."""
        if self.design_range is not None:
            return self.design_range
        if self.t1 is None:
            return self.l_const, self.l_const * self.contrast_ratio_1
        w1, w2 = self.waveforms()
        return (self.l_const * float(w2.values.min()) / float(w1.values.max()),
                self.l_const * float(w2.values.max()) / float(w1.values.min()))

    def mid_radiance(self) -> float:
        """The radiance at the middle of the rig's working range, where automatic exposure
        puts a scene's log-average (:func:`asynhdr.scene.exposure_scale`): the geometric
        middle of :meth:`working_range` (``L_const sqrt(CR_1)`` for the paper's rig)."""
        lo, hi = self.working_range()
        return math.sqrt(lo * hi)

    @property
    def ramp_us(self) -> float:
        """Length of the ramp in µs."""
        return self.period_us * self.ramp_fraction

    def target_waveforms(self) -> tuple[Waveform, Waveform]:
        """The commanded ``(T1, T2)`` over one cycle, leakage floors included."""
        floor1 = 1.0 / self.contrast_ratio_1
        floor2 = 1.0 / self.contrast_ratio_2
        t1 = self.t1 or cycle_waveform(self.t1_shape, start=floor1, stop=1.0,
                                       ramp_fraction=self.ramp_fraction, n_knots=self.n_knots)
        stop2 = floor2 + (1.0 - floor2) * (1.0 - self.t2_stop)
        t2 = self.t2 or cycle_waveform(self.t2_shape, start=1.0, stop=stop2,
                                       ramp_fraction=self.ramp_fraction, n_knots=self.n_knots)
        return t1, t2

    @cached_property
    def _actual(self) -> tuple[Waveform, Waveform]:
        targets = self.target_waveforms()
        panels = rig_panels(self.panel, contrast_ratio_1=self.contrast_ratio_1,
                            contrast_ratio_2=self.contrast_ratio_2)
        if panels is None:
            return targets
        try:
            d = design(targets[0], targets[1], panel1=panels[0], panel2=panels[1],
                       period_us=int(self.period_us), sample_rate_hz=self.sample_rate_hz,
                       pre_emphasis=self.pre_emphasis, ramp_fraction=self.ramp_fraction)
        except ValueError as exc:
            raise ValueError(f"rig with panel {self.panel!r}: {exc}") from exc
        return d.to_waveforms()

    def waveforms(self) -> tuple[Waveform, Waveform]:
        """The transmitted ``(T1, T2)`` over one cycle: the targets through the panels
        (one knot per generator sample), or the targets themselves for ``panel="ideal"``."""
        return self._actual

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
            "panel": self.panel,
            "pre_emphasis": bool(self.pre_emphasis),
            "sample_rate_hz": float(self.sample_rate_hz),
        }
        if self.design_range is not None:
            d["design_range"] = [float(v) for v in self.design_range]
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
                 "contrast_ratio_2", "t2_stop", "l_const", "k_lens", "n_knots", "panel",
                 "pre_emphasis", "sample_rate_hz")
        kw: dict[str, Any] = {k: d[k] for k in names if k in d}
        if d.get("design_range") is not None:
            kw["design_range"] = tuple(float(v) for v in d["design_range"])
        for name in ("t1", "t2"):
            if name in d:
                w = d[name]
                kw[name] = Waveform(np.asarray(w["phase"]), np.asarray(w["values"]),
                                    name=w.get("name", "sampled"))
        return cls(**kw)
