"""A frame camera beside the event sensor: same optics, same pixel count.

The paper's reference (Wu et al. 2024, Fig. 7) is a frame camera in the same optical
system whose 10 exposures are fused by Debevec and Malik's method. This module simulates
such a camera with the linear model of EMVA 1288 (release 4.0, the photon transfer
model), pixel by pixel:

    photons  n_p = Phi * E * t                 Phi = 4.09e15 * a_px photons / (lux s)
    electrons n_e ~ Poisson(eta * n_p + I_d * t), clipped at mu_sat + 5 sigma_d
    signal   v = n_e + N(0, sigma_d^2)         (read noise, electrons)
    digital  DN = clip(round(v / K), 0, 2^bits - 1),   K = mu_sat / (2^bits - 1) e-/DN

with ``E = k_lens * L`` the illuminance on the sensor (the scene's radiance in lux, as the
event sensor sees it with its panel fully open), ``a_px`` the pixel area (m^2), ``eta`` the
quantum efficiency, ``I_d`` the dark current (e-/s). EMVA 1288 measures the saturation
capacity ``mu_sat`` where the digital output saturates; the well itself holds a little more
(here ``5 sigma_d``), so a full pixel reads the top code whatever its read noise.
``4.09e15`` photons per lux second per m^2 is monochromatic light at 555 nm (1 lux =
1/683 W/m^2, photon energy h c / 555 nm); a white source gives more photons per lux, so
this is the conservative choice.

Below saturation the digital mean and variance have the closed forms

    mu_DN = (eta n_p + I_d t) / K,   sigma_DN^2 = (eta n_p + I_d t + sigma_d^2) / K^2 + 1/12

(shot noise is Poisson, so its variance equals its mean; ``1/12`` is the quantisation
noise of EMVA 1288). Presets carry their sources.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = [
    "FRAME_CAMERAS",
    "PHOTONS_PER_LUX_S_M2",
    "FrameCamera",
    "budget_bracket",
    "capture",
    "exposure_bracket",
    "get_frame_camera",
]

PHOTONS_PER_LUX_S_M2 = 1.0 / 683.0 / (6.62607015e-34 * 299792458.0 / 555e-9)
"""Photons per m^2 in one lux second of 555 nm light: ``(1/683 W/m^2) / (h c / 555 nm)``
(about 4.09e15)."""


@dataclass(frozen=True)
class FrameCamera:
    """A linear frame camera (EMVA 1288 model; see the module's text).

    Attributes
    ----------
    name : preset name or ``"custom"``.
    bit_depth : ADC bits.
    full_well_e : saturation capacity ``mu_sat`` (electrons).
    read_noise_e : temporal dark noise ``sigma_d`` (electrons, RMS).
    dark_current_e_per_s : ``I_d`` (electrons per second).
    quantum_efficiency : ``eta`` (0..1).
    pixel_pitch_um : pixel pitch (µm); the pixel area is its square.
    max_frame_rate_hz : frame rate at full resolution: a frame occupies at least
        ``1 / max_frame_rate_hz`` of a capture's time (0: no limit).
    source : where the figures come from.
    """

    name: str = "custom"
    bit_depth: int = 12
    full_well_e: float = 10_000.0
    read_noise_e: float = 2.0
    dark_current_e_per_s: float = 0.0
    quantum_efficiency: float = 0.7
    pixel_pitch_um: float = 3.45
    max_frame_rate_hz: float = 0.0
    source: str = ""

    def __post_init__(self) -> None:
        def bad(f: str, expected: str) -> ValueError:
            return ValueError(f"frame camera {self.name!r}: {f} must be {expected}, got "
                              f"{getattr(self, f)!r}")

        if int(self.bit_depth) != self.bit_depth or not 1 <= self.bit_depth <= 16:
            raise bad("bit_depth", "a whole number from 1 to 16")
        for f in ("full_well_e", "pixel_pitch_um"):
            v = getattr(self, f)
            if not (math.isfinite(v) and v > 0):
                raise bad(f, "a positive number")
        for f in ("read_noise_e", "dark_current_e_per_s", "max_frame_rate_hz"):
            v = getattr(self, f)
            if not (math.isfinite(v) and v >= 0):
                raise bad(f, "a finite number >= 0")
        if not 0 < self.quantum_efficiency <= 1:
            raise bad("quantum_efficiency", "in (0, 1]")

    @property
    def max_dn(self) -> int:
        """Largest digital value, ``2^bits - 1``."""
        return (1 << int(self.bit_depth)) - 1

    @property
    def gain_e_per_dn(self) -> float:
        """``K = mu_sat / (2^bits - 1)``: electrons per digital number."""
        return self.full_well_e / self.max_dn

    @property
    def electrons_per_lux_s(self) -> float:
        """Photo-electrons per pixel per lux second: ``eta Phi a_px``."""
        return self.quantum_efficiency * PHOTONS_PER_LUX_S_M2 * (self.pixel_pitch_um * 1e-6) ** 2

    @property
    def frame_time_s(self) -> float:
        """Shortest time a frame occupies (``1 / max_frame_rate_hz``; 0 without limit)."""
        return 1.0 / self.max_frame_rate_hz if self.max_frame_rate_hz > 0 else 0.0

    def expected_dn(self, illuminance_lux: npt.ArrayLike, exposure_s: float) -> np.ndarray:
        """Closed-form mean digital value below saturation, ``(eta n_p + I_d t) / K``."""
        e = (self.electrons_per_lux_s * np.asarray(illuminance_lux, dtype=np.float64)
             + self.dark_current_e_per_s) * exposure_s
        return e / self.gain_e_per_dn

    def expected_var_dn(self, illuminance_lux: npt.ArrayLike, exposure_s: float) -> np.ndarray:
        """Closed-form variance below saturation,
        ``(eta n_p + I_d t + sigma_d^2) / K^2 + 1/12``."""
        e = (self.electrons_per_lux_s * np.asarray(illuminance_lux, dtype=np.float64)
             + self.dark_current_e_per_s) * exposure_s
        return (e + self.read_noise_e**2) / self.gain_e_per_dn**2 + 1.0 / 12.0

    def to_metadata(self) -> dict[str, Any]:
        d = asdict(self)
        d["gain_e_per_dn"] = self.gain_e_per_dn
        d["electrons_per_lux_s"] = self.electrons_per_lux_s
        return d


FRAME_CAMERAS: dict[str, FrameCamera] = {
    # Sony IMX174 (Pregius, 5.86 µm global shutter, 1920x1200), EMVA 1288 figures of
    # Point Grey's measurement (white paper "Sony Pregius Global Shutter CMOS Imaging
    # Performance", Grasshopper3 GS3-U3-23S6M): QE 77 % at 525 nm, temporal dark noise
    # 6.83 e-, saturation capacity 32,691 e-; 12-bit ADC. Frame rate 155 fps at full
    # resolution (Basler acA1920-155um, same sensor). Dark current: not in those
    # figures; 10 e-/s is an order-of-magnitude value for the sensor class at room
    # temperature (0.5 e- in a 50 ms exposure, below the read noise).
    "imx174": FrameCamera(
        name="imx174", bit_depth=12, full_well_e=32_691.0, read_noise_e=6.83,
        dark_current_e_per_s=10.0, quantum_efficiency=0.77, pixel_pitch_um=5.86,
        max_frame_rate_hz=155.0,
        source="Sony IMX174, EMVA 1288 (Point Grey GS3-U3-23S6M): QE 0.77, 6.83 e-, "
               "32,691 e-, 12 bit; 155 fps (Basler acA1920-155um); dark current assumed"),
    # A noise-free 16-bit camera with a large well: what fusion does with perfect frames.
    "ideal": FrameCamera(
        name="ideal", bit_depth=16, full_well_e=1e6, read_noise_e=0.0,
        dark_current_e_per_s=0.0, quantum_efficiency=1.0, pixel_pitch_um=5.86,
        max_frame_rate_hz=0.0, source="no noise but shot noise; 16 bit; 1e6 e- well"),
}
"""Frame-camera presets by name."""


def get_frame_camera(name: str) -> FrameCamera:
    """The preset ``name``; ``ValueError`` listing the known ones otherwise."""
    try:
        return FRAME_CAMERAS[name]
    except KeyError:
        raise ValueError(f"unknown frame camera {name!r}; known: "
                         f"{', '.join(sorted(FRAME_CAMERAS))}") from None


def capture(
    camera: FrameCamera,
    illuminance_lux: npt.ArrayLike,
    *,
    exposure_s: float,
    rng: np.random.Generator | int | None = None,
) -> np.ndarray:
    """One frame: digital numbers (uint16, ``(height, width)``) of an exposure of
    ``exposure_s`` seconds of the sensor illuminance ``illuminance_lux`` (see the
    module's model). Same ``rng``, same frame."""
    if not (math.isfinite(exposure_s) and exposure_s > 0):
        raise ValueError(f"capture: exposure_s must be > 0, got {exposure_s}")
    e = np.asarray(illuminance_lux, dtype=np.float64)
    if e.ndim != 2:
        raise ValueError(f"capture: expected a 2-D (height, width) illuminance, got {e.shape}")
    if np.any(~np.isfinite(e)) or np.any(e < 0):
        raise ValueError("capture: illuminance must be finite and >= 0")
    gen = np.random.default_rng(rng)
    lam = (camera.electrons_per_lux_s * e + camera.dark_current_e_per_s) * exposure_s
    # Poisson draws above the full well are clipped anyway: cap the rate first so
    # huge rates do not overflow.
    well = camera.full_well_e + 5.0 * camera.read_noise_e
    n_e = gen.poisson(np.minimum(lam, 4.0 * well)).astype(np.float64)
    np.minimum(n_e, well, out=n_e)
    if camera.read_noise_e > 0:
        n_e += gen.normal(0.0, camera.read_noise_e, n_e.shape)
    dn = np.floor(n_e / camera.gain_e_per_dn + 0.5)
    return np.clip(dn, 0, camera.max_dn).astype(np.uint16)


def exposure_bracket(
    camera: FrameCamera,
    *,
    l_min_lux: float,
    l_max_lux: float,
    n: int = 10,
    top_fraction: float = 0.9,
    dark_electrons: float = 100.0,
) -> np.ndarray:
    """``n`` exposure times (s, increasing) spaced geometrically to cover a scene.

    The shortest puts ``l_max_lux`` at ``top_fraction`` of the full well; the longest
    gives ``l_min_lux`` ``dark_electrons`` photo-electrons (shot-noise SNR 10 at the
    default 100). ``t_i = t_1 r^(i-1)``, ``r = (t_n / t_1)^(1/(n-1))`` (the paper took 10
    exposures, its Fig. 7). When one exposure covers both ends, all are equal.
    """
    if n < 1:
        raise ValueError(f"exposure_bracket: n must be >= 1, got {n}")
    if not (l_max_lux > 0 and l_min_lux > 0):
        raise ValueError("exposure_bracket: l_min_lux and l_max_lux must be > 0")
    rate = camera.electrons_per_lux_s
    t1 = top_fraction * camera.full_well_e / (rate * l_max_lux)
    tn = max(t1, dark_electrons / (rate * l_min_lux))
    if n == 1:
        return np.array([t1])
    return t1 * (tn / t1) ** (np.arange(n) / (n - 1))


def budget_bracket(camera: FrameCamera, times_s: npt.ArrayLike, *,
                   budget_s: float) -> np.ndarray:
    """The exposures of ``times_s`` (shortest first) that fit in ``budget_s`` seconds of
    capture, each frame taking ``max(t, frame_time_s)``. When the next exposure does not
    fit, one more exposure fills what is left of the budget if that is longer than the
    last one taken. At least the shortest exposure is kept (cut to the budget)."""
    ts = np.sort(np.asarray(times_s, dtype=np.float64))
    if ts.size == 0 or not budget_s > 0:
        raise ValueError("budget_bracket: need exposures and a positive budget")
    ft = camera.frame_time_s
    out: list[float] = []
    used = 0.0
    for t in ts:
        cost = max(t, ft)
        if used + cost <= budget_s:
            out.append(float(t))
            used += cost
            continue
        left = budget_s - used
        if out and left >= ft and left > out[-1]:
            out.append(left)
        break
    if not out:
        out = [min(float(ts[0]), budget_s)]
    return np.array(out)
