"""Simulate the rig: scene radiance -> two modulated light paths -> DVS pixels -> recording."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from asynhdr import __version__
from asynhdr.events import Recording
from asynhdr.rig import Rig
from asynhdr.sensor.exact import cycle_pieces, simulate_cycle_exact
from asynhdr.sensor.params import SensorParams, get_preset

__all__ = ["draw_thresholds", "simulate"]

logger = logging.getLogger(__name__)

Progress = Callable[[int, int], None]
"""``progress(done, total)``, called after each cycle."""


class _HasRadiance(Protocol):
    @property
    def radiance(self) -> np.ndarray: ...


def draw_thresholds(
    sensor: SensorParams, *, width: int, height: int, rng: np.random.Generator | int | None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ON and OFF thresholds ``(height, width)``, frozen mismatch.

    ``c = N(c_nominal, threshold_sigma)``, raised to ``threshold_min`` (as v2e does).
    The ON map is drawn first, then the OFF map, from ``rng``.
    """
    gen = np.random.default_rng(rng)
    shape = (height, width)
    c_on = np.full(shape, sensor.threshold_on, dtype=np.float64)
    c_off = np.full(shape, sensor.threshold_off, dtype=np.float64)
    if sensor.threshold_sigma > 0:
        c_on += gen.normal(0.0, sensor.threshold_sigma, shape)
        c_off += gen.normal(0.0, sensor.threshold_sigma, shape)
        np.maximum(c_on, sensor.threshold_min, out=c_on)
        np.maximum(c_off, sensor.threshold_min, out=c_off)
    return c_on, c_off


def _as_radiance(scene: Any) -> tuple[np.ndarray, dict[str, Any]]:
    radiance = getattr(scene, "radiance", scene)
    radiance = np.asarray(radiance)
    info: dict[str, Any] = {}
    for attr in ("name", "unit"):
        if hasattr(scene, attr):
            info[attr] = getattr(scene, attr)
    if radiance.ndim != 2:
        raise ValueError(f"scene radiance must be a 2-D (height, width) array, got shape "
                         f"{radiance.shape}")
    if not np.issubdtype(radiance.dtype, np.floating) and \
            not np.issubdtype(radiance.dtype, np.integer):
        raise ValueError(f"scene radiance must be numeric, got dtype {radiance.dtype}")
    bad = ~np.isfinite(radiance)
    if bad.any():
        raise ValueError(f"scene radiance has {int(bad.sum())} NaN or infinite values")
    if (radiance < 0).any():
        raise ValueError(f"scene radiance has {int((radiance < 0).sum())} negative values")
    return radiance, info


def simulate(
    scene: _HasRadiance | np.ndarray,
    *,
    rig: Rig | None = None,
    sensor: SensorParams | str = "v2e",
    n_cycles: int = 1,
    rng: np.random.Generator | int | None = 0,
    t0_us: int = 0,
    thresholds: tuple[np.ndarray, np.ndarray] | None = None,
    sensor_seed: int | None = None,
    progress: Progress | None = None,
) -> Recording:
    """Simulate ``n_cycles`` modulation cycles of a static scene.

    Parameters
    ----------
    scene : a ``Scene`` (anything with a ``radiance`` attribute) or a ``(height, width)``
        radiance array, in the same unit as ``rig.l_const``.
    rig : the optics (default ``Rig()``).
    sensor : pixel parameters or a preset name.
    n_cycles : number of cycles; one rising trigger at each cycle start.
    rng : seed or generator for everything random (the frozen threshold mismatch).
        Same seed, same events, bit for bit.
    t0_us : start time of the first cycle.
    thresholds : optional ``(c_on, c_off)`` maps to use instead of drawing them
        (a calibration capture reuses the sensor's frozen mismatch this way).
    sensor_seed : when given (and ``thresholds`` is not), the frozen mismatch is drawn
        from this seed rather than from ``rng``: the same seed is the same physical
        sensor across captures.
    progress : called as ``progress(done_cycles, n_cycles)``.

    Returns
    -------
    A ``Recording`` whose metadata holds the rig, the sensor and the seed.
    """
    rig = rig or Rig()
    if isinstance(sensor, str):
        sensor = get_preset(sensor)
    if int(n_cycles) != n_cycles or n_cycles < 1:
        raise ValueError(f"n_cycles must be a whole number >= 1, got {n_cycles}")
    radiance, info = _as_radiance(scene)
    height, width = radiance.shape
    if width > 65535 or height > 65535:
        raise ValueError(f"sensor too large for uint16 coordinates: {width}x{height}")

    if thresholds is None:
        c_on, c_off = draw_thresholds(
            sensor, width=width, height=height,
            rng=rng if sensor_seed is None else sensor_seed)
    else:
        c_on, c_off = (np.asarray(a, dtype=np.float64) for a in thresholds)
        if c_on.shape != radiance.shape or c_off.shape != radiance.shape:
            raise ValueError(
                f"thresholds must have the scene's shape {radiance.shape}, got {c_on.shape} "
                f"and {c_off.shape}"
            )
        if (c_on <= 0).any() or (c_off <= 0).any():
            raise ValueError("thresholds must be positive")

    w1, w2 = rig.waveforms()
    if not np.array_equal(w1.phase, w2.phase):
        knots = np.union1d(w1.phase, w2.phase)
        t1v, t2v = w1(knots), w2(knots)
    else:
        knots, t1v, t2v = w1.phase, w1.values, w2.values
    rho = (radiance.astype(np.float64) / rig.l_const).ravel()
    e_min = float(np.min(rho.min() * t1v + t2v))
    if not e_min > 0:
        raise ValueError(
            "the sensor irradiance reaches zero during the cycle (T2 closes fully while some "
            "pixels have zero radiance); give the panels a leakage floor (contrast ratio)"
        )
    pieces = cycle_pieces(t1v, t2v)
    ref = np.log(rho * t1v[0] + t2v[0])
    c_on_f = np.ascontiguousarray(c_on.ravel())
    c_off_f = np.ascontiguousarray(c_off.ravel())
    starts = rig.cycle_starts_us(n_cycles, t0_us=t0_us)

    chunks = []
    for k in range(n_cycles):
        chunks.append(simulate_cycle_exact(
            rho, c_on_f, c_off_f, ref, knots, t1v, t2v, width=width,
            period_us=rig.period_us, t_start_us=int(starts[k]), pieces=pieces))
        if progress is not None:
            progress(k + 1, n_cycles)
    events = chunks[0] if len(chunks) == 1 else np.concatenate(chunks)
    n = events.size
    step = sensor.timestamp_resolution_us
    if step > 1:
        events["t"] = (events["t"] // step) * step
    metadata: dict[str, Any] = {
        "simulated": True,
        "asynhdr_version": __version__,
        "engine": "exact",
        "rig": rig.to_metadata(),
        "sensor": sensor.to_metadata(),
        "n_cycles": int(n_cycles),
        "t0_us": int(t0_us),
        "seed": rng if isinstance(rng, int) else None,
        "sensor_seed": sensor_seed,
        "radiance_unit": info.get("unit", "relative"),
        "scene": info.get("name", ""),
    }
    logger.info("simulated %d events over %d cycles on %dx%d", n, n_cycles, width, height)
    return Recording(events=events, width=width, height=height,
                     triggers=rig.triggers(n_cycles, t0_us=t0_us), metadata=metadata)
