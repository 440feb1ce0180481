"""LCD panel physics: the static voltage-to-transmittance curve and the LC dynamics.

A panel of the rig is a twisted-nematic (TN) liquid-crystal cell between crossed
polarisers, driven by an AC voltage of RMS amplitude ``|V|`` (the liquid crystal
responds to ``V^2``, so the sign of the drive does not matter). Two parts:

- the static curve ``T_s(V)`` (:class:`PanelCurve`): the transmittance the panel
  settles to under a constant drive ``|V|``. S-shaped; a normally-white panel is open
  at ``V = 0`` and closes as ``|V|`` rises, down to its leakage floor
  ``t_min = t_max / contrast_ratio``;
- the dynamics (:class:`PanelResponse`): the actual transmittance ``T(t)`` follows the
  static value ``x(t) = T_s(V(t))`` of the commanded voltage as an asymmetric
  first-order system::

      dT/dt = (x(t) - T(t)) / tau,   tau = rise_us if x(t) > T(t) else fall_us

  (the transmittance rises with time constant ``rise_us`` and falls with ``fall_us``).
  The field drives the director fast; when the field is removed the director relaxes
  elastically, slowly: ``tau_off = gamma_1 d^2 / (K pi^2)`` against
  ``tau_on = tau_off / ((V / V_c)^2 - 1)`` (Jakeman and Raynes 1972). For a
  normally-white panel *opening* (transmittance rising, field removed) is the slow
  relaxation, so ``rise_us > fall_us``; for a normally-black panel it is the reverse.

Transmittances are relative to the panel's open state unless a curve says otherwise
(``t_max = 1``), as the rig's waveforms are. Sources and default values: docs/panels.md.
"""

from __future__ import annotations

import math
import numbers
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from scipy.interpolate import PchipInterpolator
from scipy.optimize import OptimizeWarning, curve_fit
from scipy.special import expit

__all__ = [
    "FAST_FALL_US",
    "FAST_RISE_US",
    "PRESETS",
    "TN_CONTRAST_RATIO",
    "TN_DRIVEN_US",
    "TN_FALL_US",
    "TN_RELAX_US",
    "TN_RISE_US",
    "TN_V_MAX_V",
    "TN_V_SATURATION_V",
    "TN_V_THRESHOLD_V",
    "Hold",
    "Panel",
    "PanelCurve",
    "PanelResponse",
    "calibrate_curve",
    "get_panel",
    "tn_panel",
]

# Defaults of the generic TN panel: each value and its source is in docs/panels.md.
TN_V_THRESHOLD_V = 1.5
"""Optical threshold (10 % of the transmittance swing), RMS volts."""
TN_V_SATURATION_V = 3.0
"""Optical saturation (90 % of the swing), RMS volts."""
TN_V_MAX_V = 5.0
"""Largest drive amplitude, RMS volts (the closed state)."""
TN_CONTRAST_RATIO = 1000.0
"""Open / closed transmittance; the leakage floor is ``1 / TN_CONTRAST_RATIO``."""
TN_RELAX_US = 3000.0
"""Time constant of the field-off elastic relaxation, µs (10-90 % in 6.6 ms)."""
TN_DRIVEN_US = 1500.0
"""Time constant of the field-driven switching, µs (10-90 % in 3.3 ms)."""
TN_RISE_US = TN_RELAX_US
"""Normally-white TN: rising transmittance (opening) is the relaxation, µs."""
TN_FALL_US = TN_DRIVEN_US
"""Normally-white TN: falling transmittance (closing) is field driven, µs."""
FAST_RISE_US = 400.0
"""Fast shutter: rising time constant, µs (10-90 % in 0.88 ms)."""
FAST_FALL_US = 200.0
"""Fast shutter: falling time constant, µs (10-90 % in 0.44 ms)."""

Hold = Literal["zoh", "linear"]
"""How a sampled command is held between samples: constant (sample-and-hold) or
linear interpolation to the next sample."""

_LN9 = math.log(9.0)
_RANGE_TOL = 1e-9


def _as_1d(name: str, values: npt.ArrayLike) -> np.ndarray:
    arr = np.array(values, dtype=np.float64)
    if arr.ndim != 1 or arr.size < 2:
        raise ValueError(f"{name} must be a 1-D array of at least 2 values, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has {int((~np.isfinite(arr)).sum())} NaN or infinite values")
    return arr


def _logistic(v: np.ndarray, v_mid: float, width: float, t_zero: float,
              t_inf: float) -> np.ndarray:
    """``t_inf + (t_zero - t_inf) / (1 + exp((V - v_mid) / width))``."""
    return t_inf + (t_zero - t_inf) * expit(-(v - v_mid) / width)


@dataclass(frozen=True, eq=False)
class PanelCurve:
    """Static transmittance ``T_s(|V|)`` of a panel, from a strictly monotone table.

    Between table points the curve is the monotone cubic (PCHIP) interpolant of the
    table; :meth:`voltage` inverts that same interpolant (bisection inside the
    bracketing table interval), so ``voltage(transmittance(V)) == V`` to rounding.

    Attributes
    ----------
    voltages_v : RMS drive amplitudes ``|V|`` in volts, >= 0, strictly increasing.
    transmittances : static transmittance at each voltage, in (0, 1], strictly
        decreasing (normally white) or strictly increasing (normally black).
    name : a short description.
    params : the parameters of the form the table was made from (e.g. the logistic's
        ``v_threshold_v``), for the record; empty for a measured table.
    """

    voltages_v: np.ndarray
    transmittances: np.ndarray
    name: str = "table"
    params: Mapping[str, float] = field(default_factory=dict)
    _interp: Any = field(init=False, repr=False, default=None)

    def __post_init__(self) -> None:
        v = _as_1d("voltages_v", self.voltages_v)
        t = _as_1d("transmittances", self.transmittances)
        if t.shape != v.shape:
            raise ValueError(f"transmittances must match voltages_v in length, got {t.size} "
                             f"and {v.size}")
        if v.min() < 0:
            raise ValueError("voltages_v must be RMS amplitudes >= 0 (the panel responds to "
                             f"|V|), got minimum {v.min():g} V; pass abs(voltages_v)")
        dv = np.diff(v)
        if np.any(dv <= 0):
            i = int(np.argmax(dv <= 0))
            raise ValueError(f"voltages_v must increase strictly; index {i + 1} "
                             f"({v[i + 1]:g} V) does not exceed index {i} ({v[i]:g} V)")
        if t.min() <= 0 or t.max() > 1:
            raise ValueError(f"transmittances must lie in (0, 1], got range "
                             f"[{t.min():.6g}, {t.max():.6g}]")
        dt = np.diff(t)
        if not (np.all(dt < 0) or np.all(dt > 0)):
            sign = np.sign(dt[0]) if dt[0] != 0 else 1.0
            i = int(np.argmax(np.sign(dt) != sign))
            raise ValueError(
                f"transmittances must be strictly monotone in voltage to be inverted; the "
                f"table turns at index {i + 1} ({v[i + 1]:g} V, T = {t[i + 1]:.6g} after "
                f"{t[i]:.6g}); smooth a noisy sweep with calibrate_curve(..., "
                f"method='logistic')")
        v.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "voltages_v", v)
        object.__setattr__(self, "transmittances", t)
        object.__setattr__(self, "params", dict(self.params))
        object.__setattr__(self, "_interp", PchipInterpolator(v, t, extrapolate=False))

    # --- range -------------------------------------------------------------------
    @property
    def v_min_v(self) -> float:
        """Smallest tabulated drive amplitude, V."""
        return float(self.voltages_v[0])

    @property
    def v_max_v(self) -> float:
        """Largest tabulated drive amplitude, V."""
        return float(self.voltages_v[-1])

    @property
    def t_min(self) -> float:
        """Leakage floor: the smallest achievable transmittance."""
        return float(self.transmittances.min())

    @property
    def t_max(self) -> float:
        """The largest achievable transmittance."""
        return float(self.transmittances.max())

    @property
    def contrast_ratio(self) -> float:
        """``t_max / t_min``."""
        return self.t_max / self.t_min

    @property
    def normally_white(self) -> bool:
        """True when transmittance falls as ``|V|`` rises."""
        return bool(self.transmittances[-1] < self.transmittances[0])

    # --- evaluation --------------------------------------------------------------
    def transmittance(self, voltage_v: npt.ArrayLike) -> np.ndarray:
        """Static transmittance ``T_s(|V|)`` (same shape as ``voltage_v``).

        Raises ``ValueError`` when ``|V|`` leaves the tabulated range.
        """
        v = np.abs(np.asarray(voltage_v, dtype=np.float64))
        if v.size:
            if not np.all(np.isfinite(v)):
                raise ValueError("voltage_v has NaN or infinite values")
            lo, hi = float(v.min()), float(v.max())
            if lo < self.v_min_v - _RANGE_TOL or hi > self.v_max_v + _RANGE_TOL:
                raise ValueError(
                    f"voltage_v: |V| spans [{lo:.6g}, {hi:.6g}] V, outside the curve "
                    f"{self.name!r}'s range [{self.v_min_v:.6g}, {self.v_max_v:.6g}] V")
        v = np.clip(v, self.v_min_v, self.v_max_v)
        return np.asarray(self._interp(v), dtype=np.float64)

    def voltage(self, transmittance: npt.ArrayLike) -> np.ndarray:
        """RMS drive amplitude ``|V|`` (volts) whose static transmittance is ``transmittance``.

        The inverse of :meth:`transmittance` (exact to ~1e-15 V). Raises ``ValueError``
        when a value lies outside ``[t_min, t_max]``.
        """
        t = np.asarray(transmittance, dtype=np.float64)
        if t.size:
            if not np.all(np.isfinite(t)):
                raise ValueError("transmittance has NaN or infinite values")
            lo, hi = float(t.min()), float(t.max())
            if lo < self.t_min - _RANGE_TOL or hi > self.t_max + _RANGE_TOL:
                bad = int(np.argmax((t < self.t_min - _RANGE_TOL) | (t > self.t_max + _RANGE_TOL)))
                raise ValueError(
                    f"transmittance: value {t.flat[bad]:.6g} (flat index {bad}) is outside "
                    f"the curve {self.name!r}'s achievable range [{self.t_min:.6g}, "
                    f"{self.t_max:.6g}]")
        flat = np.clip(t.ravel(), self.t_min, self.t_max)
        vt, tt = self.voltages_v, self.transmittances
        sign = 1.0 if tt[-1] > tt[0] else -1.0  # make the table increasing in s = sign * T
        s_tab = sign * tt
        s = sign * flat
        j = np.clip(np.searchsorted(s_tab, s, side="right") - 1, 0, vt.size - 2)
        lo_v = vt[j].copy()
        hi_v = vt[j + 1].copy()
        for _ in range(60):
            mid = 0.5 * (lo_v + hi_v)
            below = sign * self._interp(mid) < s
            lo_v = np.where(below, mid, lo_v)
            hi_v = np.where(below, hi_v, mid)
        out = 0.5 * (lo_v + hi_v)
        return out.reshape(t.shape)

    # --- construction ------------------------------------------------------------
    @classmethod
    def logistic(
        cls,
        v_threshold_v: float = TN_V_THRESHOLD_V,
        v_saturation_v: float = TN_V_SATURATION_V,
        *,
        contrast_ratio: float = TN_CONTRAST_RATIO,
        t_max: float = 1.0,
        v_max_v: float = TN_V_MAX_V,
        normally_white: bool = True,
        n_points: int = 1025,
    ) -> PanelCurve:
        """The S-shaped curve of a TN cell, as a logistic in ``|V|``.

        ``T_s(V) = t_inf + (t_zero - t_inf) / (1 + exp((V - v_mid) / w))`` with
        ``v_mid = (v_threshold_v + v_saturation_v) / 2`` and
        ``w = (v_saturation_v - v_threshold_v) / (2 ln 9)``: the transmittance has moved
        10 % of its asymptotic swing at ``v_threshold_v`` and 90 % at ``v_saturation_v``.
        The asymptotes ``t_zero``, ``t_inf`` are set so that the curve spans exactly
        ``[t_max / contrast_ratio, t_max]`` over ``[0, v_max_v]``. Tabulated at
        ``n_points`` evenly spaced voltages.
        """
        for name, val in (("v_threshold_v", v_threshold_v), ("v_saturation_v", v_saturation_v),
                          ("v_max_v", v_max_v)):
            if not (math.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be positive and finite, got {val}")
        if not v_threshold_v < v_saturation_v:
            raise ValueError(f"v_threshold_v ({v_threshold_v}) must be below v_saturation_v "
                             f"({v_saturation_v})")
        if not (math.isfinite(contrast_ratio) and contrast_ratio > 1):
            raise ValueError(f"contrast_ratio must be a finite number > 1, got {contrast_ratio}")
        if not 0 < t_max <= 1:
            raise ValueError(f"t_max must be in (0, 1], got {t_max}")
        if int(n_points) != n_points or n_points < 8:
            raise ValueError(f"n_points must be a whole number >= 8, got {n_points}")
        v_mid = 0.5 * (v_threshold_v + v_saturation_v)
        width = (v_saturation_v - v_threshold_v) / (2.0 * _LN9)
        v = np.linspace(0.0, v_max_v, int(n_points))
        sig = expit(-(v - v_mid) / width)  # 1 at V << v_mid, 0 at V >> v_mid
        t_min = t_max / contrast_ratio
        t_open, t_closed = (t_max, t_min) if normally_white else (t_min, t_max)
        # Rescale so that T(0) = t_open and T(v_max) = t_closed exactly.
        frac = (sig - sig[-1]) / (sig[0] - sig[-1])
        t = t_closed + (t_open - t_closed) * frac
        t[0], t[-1] = t_open, t_closed
        if np.any(np.diff(t) == 0):
            raise ValueError(
                f"the logistic curve is flat to rounding over [0, {v_max_v}] V "
                f"(v_threshold_v={v_threshold_v}, v_saturation_v={v_saturation_v}); move "
                "the thresholds inside the drive range or use fewer n_points")
        params = {"v_threshold_v": float(v_threshold_v), "v_saturation_v": float(v_saturation_v),
                  "v_max_v": float(v_max_v), "contrast_ratio": float(contrast_ratio),
                  "t_max": float(t_max), "normally_white": float(normally_white)}
        kind = "normally-white" if normally_white else "normally-black"
        return cls(v, t, name=f"logistic {kind}", params=params)

    @classmethod
    def fit(
        cls,
        voltages_v: npt.ArrayLike,
        transmittance: npt.ArrayLike,
        *,
        n_points: int = 1025,
    ) -> tuple[PanelCurve, float]:
        """Fit the logistic form to a measured sweep; returns ``(curve, rms_residual)``.

        Model: ``T(V) = t_inf + (t_zero - t_inf) / (1 + exp((V - v_mid) / w))``
        (``t_zero > t_inf``: normally white), least squares (``scipy.optimize.curve_fit``).
        The returned curve tabulates the fitted model over the swept range of ``|V|``;
        its ``params`` give ``v_threshold_v = v_mid - w ln 9``,
        ``v_saturation_v = v_mid + w ln 9`` and the asymptotes. ``rms_residual`` is the
        RMS of (model - measurement), in transmittance units.
        """
        v, t = _sweep(voltages_v, transmittance)
        if v.size < 4:
            raise ValueError(f"a logistic fit needs at least 4 distinct voltages, got {v.size}")
        t0_guess, tinf_guess = float(t[0]), float(t[-1])
        half = 0.5 * (t0_guess + tinf_guess)
        order = np.argsort(t)
        v_mid_guess = float(np.interp(half, t[order], v[order]))
        span_v = float(v[-1] - v[0])
        p0 = [v_mid_guess, span_v / 10.0, t0_guess, tinf_guess]
        lo = [float(v[0]) - span_v, span_v * 1e-4, 0.0, 0.0]
        hi = [float(v[-1]) + span_v, span_v * 10.0, 1.5, 1.5]
        p0 = [min(max(p, a + 1e-12), b - 1e-12) for p, a, b in zip(p0, lo, hi, strict=True)]
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", OptimizeWarning)
                popt, _ = curve_fit(_logistic, v, t, p0=p0, bounds=(lo, hi), maxfev=20000)
        except (RuntimeError, ValueError) as exc:
            raise ValueError(f"logistic fit to the voltage sweep failed: {exc}") from exc
        v_mid, width, t_zero, t_inf = (float(p) for p in popt)
        residual = float(np.sqrt(np.mean((_logistic(v, *popt) - t) ** 2)))
        grid = np.linspace(float(v[0]), float(v[-1]), int(n_points))
        tab = _logistic(grid, *popt)
        if tab.min() <= 0 or tab.max() > 1:
            raise ValueError(
                f"the fitted curve leaves (0, 1] over the sweep (range [{tab.min():.4g}, "
                f"{tab.max():.4g}]); normalise the measured transmittance to the open state")
        params = {"v_threshold_v": v_mid - width * _LN9, "v_saturation_v": v_mid + width * _LN9,
                  "v_mid_v": v_mid, "width_v": width, "t_zero": t_zero, "t_inf": t_inf,
                  "rms_residual": residual}
        try:
            curve = cls(grid, tab, name="logistic fit", params=params)
        except ValueError as exc:
            raise ValueError(f"the fitted curve cannot be inverted: {exc}") from exc
        return curve, residual

    def to_metadata(self) -> dict[str, Any]:
        """JSON-serialisable summary (name, range, parameters)."""
        return {"name": self.name, "v_min_v": self.v_min_v, "v_max_v": self.v_max_v,
                "t_min": self.t_min, "t_max": self.t_max,
                "contrast_ratio": self.contrast_ratio, "normally_white": self.normally_white,
                "params": dict(self.params)}


def _sweep(voltages_v: npt.ArrayLike, transmittance: npt.ArrayLike) -> tuple[np.ndarray,
                                                                           np.ndarray]:
    """``|V|`` sorted, repeated voltages averaged; checks shapes and values."""
    v = np.abs(_as_1d("voltages_v", voltages_v))
    t = _as_1d("measured_transmittance", transmittance)
    if t.shape != v.shape:
        raise ValueError(f"measured_transmittance must match voltages_v in length, got "
                         f"{t.size} and {v.size}")
    uv, inv = np.unique(v, return_inverse=True)
    tm = np.bincount(inv, weights=t) / np.bincount(inv)
    return uv, tm


def calibrate_curve(
    voltages_v: npt.ArrayLike,
    measured_transmittance: npt.ArrayLike,
    *,
    method: Literal["logistic", "table"] = "logistic",
    n_points: int = 1025,
) -> PanelCurve:
    """A panel curve from a voltage sweep (a photodiode behind the panel, DC drive levels).

    ``voltages_v`` are drive amplitudes (their sign is ignored; repeated voltages are
    averaged); ``measured_transmittance`` is normalised to the open state (divide the
    photodiode signal by its value at the open drive, after subtracting its dark level).

    ``method="logistic"`` fits the S-shaped form (:meth:`PanelCurve.fit`; robust to
    noise); ``method="table"`` uses the averaged measurements as the table, which must
    then be strictly monotone.
    """
    if method == "logistic":
        curve, _ = PanelCurve.fit(voltages_v, measured_transmittance, n_points=n_points)
        return curve
    if method == "table":
        v, t = _sweep(voltages_v, measured_transmittance)
        return PanelCurve(v, t, name="measured table")
    raise ValueError(f"unknown method {method!r}; expected 'logistic' or 'table'")


def _zoh_step(y: float, x: float, a_rise: float, a_fall: float) -> tuple[float, float]:
    """Exact first-order update over one sample with the drive held at ``x``."""
    a = a_rise if x > y else a_fall
    return x + (y - x) * a, a


def _linear_step(y: float, x0: float, x1: float, dt_us: float, rise_us: float,
                 fall_us: float) -> tuple[float, float]:
    """Exact update over one sample with the drive linear from ``x0`` to ``x1``.

    With ``x = x0 + s t`` and a fixed ``tau``, ``e = x - T`` obeys ``de/dt = s - e / tau``:
    ``e(t) = s tau + (e0 - s tau) exp(-t / tau)``. ``e`` changes sign at most once
    within the sample (at ``t* = tau ln((e0 - s tau) / (-s tau))``), where ``tau``
    switches. Returns the new state and ``dT(dt)/dT(0)``.
    """
    s = (x1 - x0) / dt_us
    e = x0 - y
    if e > 0 or (e == 0 and s > 0):
        tau, other = rise_us, fall_us
    elif e < 0 or (e == 0 and s < 0):
        tau, other = fall_us, rise_us
    else:
        return y, math.exp(-dt_us / max(rise_us, fall_us))
    t_used = 0.0
    decay = 0.0
    c = s * tau
    if (tau == rise_us and s < 0) or (tau == fall_us and s > 0):
        t_star = tau * math.log((e - c) / (-c))
        if t_star < dt_us:
            t_used = t_star
            decay = t_star / tau
            e = 0.0
            tau = other
            c = s * tau
    rem = dt_us - t_used
    e_end = c + (e - c) * math.exp(-rem / tau)
    return x1 - e_end, math.exp(-(decay + rem / tau))


def _periodic_state(one_pass: Callable[[float], tuple[float, float]], lo: float, hi: float,
                    guess: float) -> float:
    """Start state ``y0`` with ``one_pass(y0)[0] == y0`` (periodic steady state).

    ``one_pass(y0)`` returns the state after one cycle and its derivative in ``y0``.
    The map is increasing with slope in [0, 1), so ``g(y) = F(y) - y`` is decreasing and
    has one root in ``[lo, hi]``: Newton steps, kept inside a shrinking bracket.
    """
    y = min(max(guess, lo), hi)
    for _ in range(200):
        end, slope = one_pass(y)
        g = end - y
        if abs(g) <= 1e-14 * max(1.0, abs(y)):
            return end
        if g > 0:
            lo = y
        else:
            hi = y
        nxt = y + g / (1.0 - slope) if slope < 1.0 else 0.5 * (lo + hi)
        if not lo < nxt < hi:
            nxt = 0.5 * (lo + hi)
        if hi - lo <= 1e-15 * max(1.0, abs(hi)):
            return nxt
        y = nxt
    return y


@dataclass(frozen=True)
class PanelResponse:
    """Asymmetric first-order dynamics of the liquid crystal.

    ``dT/dt = (x - T) / tau`` with ``tau = rise_us`` while ``x > T`` (transmittance
    rising) and ``fall_us`` while ``x < T`` (falling), ``x`` the static transmittance of
    the command. A step from ``T0`` to ``x`` gives ``T(t) = x + (T0 - x) exp(-t / tau)``:
    ``1 - 1/e`` of the way after ``tau``, 10 % to 90 % in ``tau ln 9``.

    Attributes
    ----------
    rise_us : time constant of rising transmittance, µs (> 0).
    fall_us : time constant of falling transmittance, µs (> 0).
    """

    rise_us: float = TN_RISE_US
    fall_us: float = TN_FALL_US

    def __post_init__(self) -> None:
        for name in ("rise_us", "fall_us"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, numbers.Real)
                                           and math.isfinite(float(v)) and float(v) > 0):
                raise ValueError(f"{name} must be a positive finite time in µs, got {v!r}")

    def step_factors(self, sample_rate_hz: float) -> tuple[float, float]:
        """``(exp(-dt / rise_us), exp(-dt / fall_us))`` for one sample ``dt = 1e6 / fs`` µs."""
        dt_us = _dt_us(sample_rate_hz)
        return math.exp(-dt_us / self.rise_us), math.exp(-dt_us / self.fall_us)

    def simulate(
        self,
        drive: npt.ArrayLike,
        *,
        sample_rate_hz: float,
        initial: float | None = None,
        periodic: bool = True,
        hold: Hold = "zoh",
    ) -> np.ndarray:
        """Actual transmittance at each sample instant for a sampled drive.

        ``drive[n]`` is the static transmittance commanded at ``t_n = n / fs``; with
        ``hold="zoh"`` it holds over ``[t_n, t_{n+1})``, with ``hold="linear"`` it moves
        linearly to ``drive[n + 1]`` (to ``drive[0]`` after the last sample when
        ``periodic``, else it stays). The update is exact for either (no Euler steps).
        Returns ``T(t_n)``, same length as ``drive``. ``periodic=True`` returns the
        periodic steady state (``T(t_N) = T(t_0)`` with the drive repeated every ``N``
        samples), solved exactly; ``initial`` is then only a starting guess. Otherwise the
        panel starts at ``initial`` (default ``drive[0]``: settled at the first command).
        """
        x = _as_1d("drive", drive)
        if hold not in ("zoh", "linear"):
            raise ValueError(f"hold must be 'zoh' or 'linear', got {hold!r}")
        dt_us = _dt_us(sample_rate_hz)
        xs = x.tolist()
        n = len(xs)
        nxt = [*xs[1:], xs[0] if periodic else xs[-1]]
        a_rise, a_fall = math.exp(-dt_us / self.rise_us), math.exp(-dt_us / self.fall_us)
        rise_us, fall_us = float(self.rise_us), float(self.fall_us)

        def run(y0: float, out: list[float] | None) -> tuple[float, float]:
            y, slope = y0, 1.0
            for k in range(n):
                if out is not None:
                    out.append(y)
                if hold == "zoh":
                    y, d = _zoh_step(y, xs[k], a_rise, a_fall)
                else:
                    y, d = _linear_step(y, xs[k], nxt[k], dt_us, rise_us, fall_us)
                slope *= d
            return y, slope

        if periodic:
            lo, hi = float(x.min()), float(x.max())
            y0 = _periodic_state(lambda y: run(y, None), lo, hi,
                                 xs[-1] if initial is None else float(initial))
        else:
            y0 = xs[0] if initial is None else float(initial)
            if not math.isfinite(y0):
                raise ValueError(f"initial must be finite, got {initial}")
        out: list[float] = []
        run(y0, out)
        return np.asarray(out, dtype=np.float64)

    def to_metadata(self) -> dict[str, float]:
        """``{"rise_us": ..., "fall_us": ...}``."""
        return {"rise_us": float(self.rise_us), "fall_us": float(self.fall_us)}


def _dt_us(sample_rate_hz: float) -> float:
    if isinstance(sample_rate_hz, bool) or not (isinstance(sample_rate_hz, numbers.Real)
                                                and math.isfinite(sample_rate_hz)
                                                and sample_rate_hz > 0):
        raise ValueError(f"sample_rate_hz must be positive and finite, got {sample_rate_hz!r}")
    return 1e6 / float(sample_rate_hz)


@dataclass(frozen=True)
class Panel:
    """One LCD panel: static curve + dynamics (the leakage floor is the curve's ``t_min``).

    Attributes
    ----------
    curve : the static voltage-to-transmittance curve.
    response : the first-order rise and fall.
    name : a short name.
    """

    curve: PanelCurve
    response: PanelResponse = field(default_factory=PanelResponse)
    name: str = "panel"

    @property
    def contrast_ratio(self) -> float:
        """Open / closed transmittance, ``t_max / t_min``."""
        return self.curve.contrast_ratio

    @property
    def t_min(self) -> float:
        """Leakage floor."""
        return self.curve.t_min

    @property
    def t_max(self) -> float:
        """Fully open transmittance."""
        return self.curve.t_max

    def simulate(
        self,
        voltage_samples: npt.ArrayLike,
        *,
        sample_rate_hz: float,
        initial: float | None = None,
        periodic: bool = True,
        hold: Hold = "zoh",
    ) -> np.ndarray:
        """Actual transmittance at each sample for commanded voltages (V, any sign).

        The drive is ``x[n] = T_s(|V[n]|)``; see :meth:`PanelResponse.simulate` for the
        timing, ``hold``, ``periodic`` and ``initial``.
        """
        v = _as_1d("voltage_samples", voltage_samples)
        x = self.curve.transmittance(v)
        return self.response.simulate(x, sample_rate_hz=sample_rate_hz, initial=initial,
                                      periodic=periodic, hold=hold)

    def to_metadata(self) -> dict[str, Any]:
        """JSON-serialisable description."""
        return {"name": self.name, "curve": self.curve.to_metadata(),
                "response": self.response.to_metadata()}


def tn_panel(
    *,
    normally_white: bool = True,
    contrast_ratio: float = TN_CONTRAST_RATIO,
    rise_us: float | None = None,
    fall_us: float | None = None,
    v_threshold_v: float = TN_V_THRESHOLD_V,
    v_saturation_v: float = TN_V_SATURATION_V,
    v_max_v: float = TN_V_MAX_V,
    t_max: float = 1.0,
    name: str | None = None,
) -> Panel:
    """A TN panel: logistic static curve and asymmetric response (docs/panels.md).

    The relaxation (field removed) is the slow direction: opening for a normally-white
    panel, closing for a normally-black one. ``rise_us``/``fall_us`` default to
    ``TN_RELAX_US``/``TN_DRIVEN_US`` accordingly; give them to override.
    """
    if rise_us is None:
        rise_us = TN_RELAX_US if normally_white else TN_DRIVEN_US
    if fall_us is None:
        fall_us = TN_DRIVEN_US if normally_white else TN_RELAX_US
    if name is None:
        name = "tn_generic" if normally_white else "tn_generic_nb"
    curve = PanelCurve.logistic(v_threshold_v, v_saturation_v, contrast_ratio=contrast_ratio,
                                t_max=t_max, v_max_v=v_max_v, normally_white=normally_white)
    return Panel(curve, PanelResponse(rise_us=rise_us, fall_us=fall_us), name=name)


def _tn_generic() -> Panel:
    return tn_panel()


def _tn_generic_nb() -> Panel:
    return tn_panel(normally_white=False)


def _fast_shutter() -> Panel:
    return tn_panel(rise_us=FAST_RISE_US, fall_us=FAST_FALL_US, name="fast_shutter")


PRESETS: dict[str, Callable[[], Panel]] = {
    "tn_generic": _tn_generic,
    "tn_generic_nb": _tn_generic_nb,
    "fast_shutter": _fast_shutter,
}
"""Named panels (factories; each call builds a fresh :class:`Panel`): ``tn_generic``
(normally white: the scene panel), ``tn_generic_nb`` (normally black: its quick return
to open is field driven, the reference panel's need) and ``fast_shutter`` (a
sub-millisecond shutter on the same curve). Values and sources: docs/panels.md."""


def get_panel(name: str) -> Panel:
    """The preset panel called ``name``."""
    try:
        factory = PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown panel preset {name!r}; expected one of "
                         f"{sorted(PRESETS)}") from None
    return factory()
