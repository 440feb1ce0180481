"""Parameters of the DVS pixel model, and named presets.

Every value is written once, here, with its source; docs/sensor.md tabulates them.
Thresholds are in natural-log units of irradiance (a pixel fires when
``|log I - log I_ref| >= c``). Irradiance is in the scene's unit (lux for the chart)
times ``k_lens``.

Each non-ideality has a switch: a zero rate, time or fraction turns it off.
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
        units).
    threshold_sigma : standard deviation of the frozen per-pixel threshold mismatch
        (log units, Gaussian).
    threshold_min : thresholds drawn below this are raised to it (v2e clips at 0.01).
    reset_noise_sigma : per-event noise on the new reference level after each event
        (log units, Gaussian); 0 disables.
    refractory_us : after an event the pixel ignores its input for this long; the new
        reference is the level at the end of the refractory period. 0 disables.
    cutoff_hz : photoreceptor 3 dB bandwidth at ``cutoff_irradiance``; the time
        constant ``tau = 1 / (2 pi cutoff_hz) * (cutoff_irradiance + dark_irradiance) /
        (I + dark_irradiance)``, capped at ``tau_max_us``: dark pixels respond late.
        0 disables the low-pass.
    cutoff_irradiance : irradiance at which the bandwidth is ``cutoff_hz``.
    dark_irradiance : the dark current, as an equivalent irradiance.
    tau_max_us : the longest photoreceptor time constant.
    latency_us : fixed delay from threshold crossing to timestamp.
    jitter_sigma_us : Gaussian timestamp jitter (standard deviation).
    leak_rate_hz : ON leak events per pixel per second (junction leakage in the reset
        switch), independent of light.
    shot_noise_rate_hz : ON+OFF shot-noise events per pixel per second in the dark.
    shot_noise_bright_factor : shot-noise rate at ``shot_noise_full_irradiance`` and above,
        relative to the dark rate (v2e's intensity factor); linear in between.
    shot_noise_full_irradiance : irradiance regarded as full scale for shot noise.
    hot_pixel_fraction, hot_pixel_rate_hz : fraction of pixels that fire ON and OFF
        events at random, and their rate.
    dead_pixel_fraction : fraction of pixels that never fire.
    max_event_rate_hz : the readout's event-rate limit (events per second for the
        whole array); 0 is unlimited.
    array_pixels : the pixels of the real array that share the readout. A simulation of
        ``n`` pixels stands for the whole array: its readout serves ``n / array_pixels``
        of ``max_event_rate_hz`` (and of ``arbiter_buffer_events``), so each pixel
        carries the real sensor's load at any simulated size. 0: the rate holds as given
        for any size (a region of interest read alone).
    arbiter : ``"delay"`` (events queue and their timestamps move later; their pixels fire
        on as if read at once), ``"hold"`` (as ``"delay"``, and a pixel whose event waits
        is held until it is read: its dead time runs from the read; the exact engine
        simulating the whole sensor, :class:`asynhdr.simulate.HeldReadout`) or ``"drop"``
        (events that find the queue full are lost).
    arbiter_buffer_events : queue length for ``"drop"``.
    timestamp_resolution_us : event time quantum; timestamps are floored to it.
    """

    name: str = "custom"
    threshold_on: float = 0.2
    threshold_off: float = 0.2
    threshold_sigma: float = 0.03
    threshold_min: float = 0.01
    reset_noise_sigma: float = 0.0
    refractory_us: float = 0.0
    cutoff_hz: float = 0.0
    cutoff_irradiance: float = 1000.0
    dark_irradiance: float = 0.1
    tau_max_us: float = 50_000.0
    latency_us: float = 0.0
    jitter_sigma_us: float = 0.0
    leak_rate_hz: float = 0.0
    shot_noise_rate_hz: float = 0.0
    shot_noise_bright_factor: float = 0.25
    shot_noise_full_irradiance: float = 1000.0
    hot_pixel_fraction: float = 0.0
    hot_pixel_rate_hz: float = 0.0
    dead_pixel_fraction: float = 0.0
    max_event_rate_hz: float = 0.0
    arbiter: str = "delay"
    arbiter_buffer_events: int = 1024
    timestamp_resolution_us: int = 1
    array_pixels: int = 0

    def __post_init__(self) -> None:
        def bad(field: str, expected: str) -> ValueError:
            return ValueError(f"sensor {self.name!r}: {field} must be {expected}, got "
                              f"{getattr(self, field)!r}")

        for nm in ("threshold_on", "threshold_off", "threshold_min", "cutoff_irradiance",
                   "tau_max_us", "shot_noise_full_irradiance"):
            v = getattr(self, nm)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise bad(nm, "a positive number")
        for nm in ("threshold_sigma", "reset_noise_sigma", "refractory_us", "cutoff_hz",
                   "dark_irradiance", "latency_us", "jitter_sigma_us", "leak_rate_hz",
                   "shot_noise_rate_hz", "shot_noise_bright_factor", "hot_pixel_rate_hz",
                   "max_event_rate_hz"):
            v = getattr(self, nm)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise bad(nm, "a finite number >= 0")
        for nm in ("hot_pixel_fraction", "dead_pixel_fraction"):
            v = getattr(self, nm)
            if not (isinstance(v, int | float) and 0.0 <= v <= 1.0):
                raise bad(nm, "a fraction in [0, 1]")
        if self.hot_pixel_fraction + self.dead_pixel_fraction > 1.0:
            raise ValueError(f"sensor {self.name!r}: hot_pixel_fraction + dead_pixel_fraction "
                             "must not exceed 1")
        if self.arbiter not in ("delay", "hold", "drop"):
            raise bad("arbiter", "'delay', 'hold' or 'drop'")
        if int(self.arbiter_buffer_events) != self.arbiter_buffer_events or \
                self.arbiter_buffer_events < 1:
            raise bad("arbiter_buffer_events", "a whole number >= 1")
        if int(self.timestamp_resolution_us) != self.timestamp_resolution_us or \
                self.timestamp_resolution_us < 1:
            raise bad("timestamp_resolution_us", "a whole number >= 1")
        if int(self.array_pixels) != self.array_pixels or self.array_pixels < 0:
            raise bad("array_pixels", "a whole number >= 0")

    def readout(self, n_pixels: int) -> tuple[float, float]:
        """The readout that ``n_pixels`` simulated pixels get: ``(events per second,
        queue length in events)``, the array's share by ``array_pixels`` (0 rate: no
        limit)."""
        share = n_pixels / self.array_pixels if self.array_pixels > 0 else 1.0
        return (self.max_event_rate_hz * share,
                max(1.0, self.arbiter_buffer_events * share))

    def region_of_interest(self, pixels: int | None = None) -> SensorParams:
        """The sensor read through regions of interest, each with the whole readout:
        regions of ``pixels`` pixels (a simulation of more pixels stands for several
        regions read one after the other), or, with None, the simulated pixels read
        alone. Unchanged without a shared readout (``array_pixels`` 0)."""
        if not self.array_pixels:
            return self
        return replace(self, array_pixels=0 if pixels is None else max(1, int(pixels)))

    @property
    def tau_ref_us(self) -> float:
        """Photoreceptor time constant at ``cutoff_irradiance`` (µs); 0 when disabled."""
        return 1e6 / (2.0 * math.pi * self.cutoff_hz) if self.cutoff_hz > 0 else 0.0

    def tau_us(self, irradiance: Any) -> Any:
        """``tau(I) = tau_ref (I_ref + I_dark) / (I + I_dark)``, capped at ``tau_max_us``."""
        import numpy as np

        if self.cutoff_hz <= 0:
            return np.zeros_like(np.asarray(irradiance, dtype=np.float64))
        i = np.asarray(irradiance, dtype=np.float64)
        tau = self.tau_ref_us * (self.cutoff_irradiance + self.dark_irradiance) / (
            i + self.dark_irradiance)
        return np.minimum(tau, self.tau_max_us)

    @property
    def has_noise_events(self) -> bool:
        """Whether any event source other than the signal is on."""
        return (self.leak_rate_hz > 0 or self.shot_noise_rate_hz > 0
                or (self.hot_pixel_fraction > 0 and self.hot_pixel_rate_hz > 0))

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


def _c(contrast_percent: float) -> float:
    """Log threshold for a Weber contrast in percent: ``ln(1 + C/100)``."""
    return math.log1p(contrast_percent / 100.0)


_NOISY = SensorParams(
    name="noisy",
    # v2e's 'noisy' model: sigma_thres 0.05, leak 0.1 Hz, shot noise 5 Hz.
    threshold_sigma=0.05,
    leak_rate_hz=0.1,
    shot_noise_rate_hz=5.0,
    # not from a datasheet (see docs/sensor.md): reset noise, jitter, defects.
    reset_noise_sigma=0.01,
    jitter_sigma_us=2.0,
    hot_pixel_fraction=1e-4,
    hot_pixel_rate_hz=10.0,
    dead_pixel_fraction=1e-4,
    cutoff_irradiance=1000.0,
    dark_irradiance=0.1,
    arbiter="delay",
)
"""What the realistic presets share: v2e's noise model and our defect choices."""


def _tau_to_cutoff_hz(tau_us: float) -> float:
    """3 dB cut-off of a first-order low-pass with time constant ``tau_us``."""
    return 1e6 / (2 * math.pi * tau_us)


PRESETS: dict[str, SensorParams] = {
    # Noise-free pixel, no mismatch: every pixel with the same radiance fires at the
    # same instants. Thresholds are v2e's nominal 0.2.
    "ideal": SensorParams(name="ideal", threshold_sigma=0.0),
    # v2e's EventEmulator constructor defaults: pos_thres = neg_thres = 0.2,
    # sigma_thres = 0.03, leak_rate_hz = 0.1, cutoff_hz = 0, shot_noise_rate_hz = 0,
    # refractory_period_s = 0.
    "v2e": SensorParams(name="v2e", leak_rate_hz=0.1),
    # iniVation DAVIS346 (datasheet: contrast sensitivity 14.3 % ON / 22.5 % OFF,
    # event bandwidth 12 Mev/s, minimum latency about 20 µs, used as the time constant
    # at 1000); refractory 1 ms (v2e's --refractory_period default).
    "davis346": _NOISY.with_(
        name="davis346",
        threshold_on=_c(14.3),
        threshold_off=_c(22.5),
        refractory_us=1000.0,
        cutoff_hz=_tau_to_cutoff_hz(20.0),
        max_event_rate_hz=12e6,
        array_pixels=346 * 260,
    ),
    # Sony IMX636 / Prophesee Gen4.1 (Finateu et al., ISSCC 2020: 1280x720, pixel latency
    # about 100 µs at 1 klux, readout up to 1.066 Gev/s). Thresholds at the default
    # biases about 25 % (Prophesee's bias documentation); refractory 100 µs (order of
    # the bias_refr default).
    "imx636": _NOISY.with_(
        name="imx636",
        threshold_on=_c(25.0),
        threshold_off=_c(25.0),
        refractory_us=100.0,
        cutoff_hz=_tau_to_cutoff_hz(100.0),
        max_event_rate_hz=1.066e9,
        array_pixels=1280 * 720,
    ),
}


def get_preset(name: str) -> SensorParams:
    """The preset called ``name``; ``ValueError`` listing the known ones otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(
            f"unknown sensor preset {name!r}; known presets: {', '.join(sorted(PRESETS))}"
        ) from None
