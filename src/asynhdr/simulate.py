"""Simulate the rig: scene radiance -> two modulated light paths -> DVS pixels -> recording."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from asynhdr import __version__
from asynhdr.events import EVENT_DTYPE, Recording
from asynhdr.rig import Rig
from asynhdr.sensor._rng import seed_from
from asynhdr.sensor.exact import ExactState, cycle_pieces, simulate_cycle_exact
from asynhdr.sensor.noise import apply_arbiter, background_events, draw_defects, merge_sorted
from asynhdr.sensor.params import SensorParams, get_preset

__all__ = ["ENGINES", "draw_thresholds", "simulate"]

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


def _as_radiance(scene: Any, *, frames: bool = False) -> tuple[np.ndarray, dict[str, Any]]:
    radiance = getattr(scene, "radiance", scene)
    radiance = np.asarray(radiance)
    info: dict[str, Any] = {}
    for attr in ("name", "unit"):
        if hasattr(scene, attr):
            info[attr] = getattr(scene, attr)
    if frames and radiance.ndim != 3:
        raise ValueError(f"a moving scene must be a 3-D (n_frames, height, width) array, got "
                         f"shape {radiance.shape}")
    if not frames and radiance.ndim != 2:
        raise ValueError(f"scene radiance must be a 2-D (height, width) array, got shape "
                         f"{radiance.shape}; a moving scene needs frame_times_us")
    if not np.issubdtype(radiance.dtype, np.floating) and \
            not np.issubdtype(radiance.dtype, np.integer):
        raise ValueError(f"scene radiance must be numeric, got dtype {radiance.dtype}")
    bad = ~np.isfinite(radiance)
    if bad.any():
        raise ValueError(f"scene radiance has {int(bad.sum())} NaN or infinite values")
    if (radiance < 0).any():
        raise ValueError(f"scene radiance has {int((radiance < 0).sum())} negative values")
    return radiance, info


def _concat_sorted(chunks: list[np.ndarray]) -> np.ndarray:
    """Concatenate per-cycle chunks, each sorted; where late events of one cycle reach
    into the next (lag, latency, jitter), merge the overlap stably."""
    if not chunks:
        return np.zeros(0, EVENT_DTYPE)
    out: list[np.ndarray] = [chunks[0]]
    for c in chunks[1:]:
        if c.size == 0:
            continue
        prev = out[-1]
        if prev.size and prev["t"][-1] > c["t"][0]:
            cut = int(np.searchsorted(prev["t"], c["t"][0], side="right"))
            tail = prev[cut:]
            out[-1] = prev[:cut]
            out.append(merge_sorted(tail, c))
        else:
            out.append(c)
    return out[0] if len(out) == 1 else np.concatenate(out)


ENGINES = ("exact", "stepped")


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
    engine: str = "exact",
    dt_us: float = 5.0,
    frame_times_us: np.ndarray | None = None,
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
    rng : seed or generator for everything random in this capture (reset noise,
        jitter, background activity; and the frozen sensor maps when ``sensor_seed``
        is not given). Same seed, same events, bit for bit.
    t0_us : start time of the first cycle.
    thresholds : optional ``(c_on, c_off)`` maps to use instead of drawing them.
    sensor_seed : when given, the sensor's frozen maps (threshold mismatch, hot and
        dead pixels) are drawn from this seed rather than from ``rng``: the same seed
        is the same physical sensor across captures.
    engine : ``"exact"`` (crossing times computed; the photoreceptor low-pass as the lag
        of a slowly varying input) or ``"stepped"`` (time-stepped integration of the
        pixel state with step ``dt_us``: exact low-pass, any waveform).
    frame_times_us : for a moving scene, ``scene`` is ``(n_frames, height, width)`` and
        these are the frames' times (µs from ``t0_us``; radiance is interpolated linearly
        between them and held outside). Needs ``engine="stepped"``.
    progress : called as ``progress(done_cycles, n_cycles)``.

    Returns
    -------
    A ``Recording`` whose metadata holds the rig, the sensor, the seeds and what the
    readout did (``"readout"``: emitted, delivered, delayed, dropped events).
    """
    rig = rig or Rig()
    if isinstance(sensor, str):
        sensor = get_preset(sensor)
    if int(n_cycles) != n_cycles or n_cycles < 1:
        raise ValueError(f"n_cycles must be a whole number >= 1, got {n_cycles}")
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; expected one of {ENGINES}")
    if sensor.refractory_us >= rig.period_us:
        raise ValueError(f"refractory_us ({sensor.refractory_us}) must be shorter than the "
                         f"cycle (period_us={rig.period_us})")
    moving = frame_times_us is not None
    radiance, info = _as_radiance(scene, frames=moving)
    if moving and engine != "stepped":
        raise ValueError("a moving scene (frame_times_us) needs engine='stepped'")
    height, width = radiance.shape[-2:]
    if width > 65535 or height > 65535:
        raise ValueError(f"sensor too large for uint16 coordinates: {width}x{height}")
    gen = np.random.default_rng(rng)
    sensor_gen = gen if sensor_seed is None else np.random.default_rng(sensor_seed)

    if thresholds is None:
        c_on, c_off = draw_thresholds(sensor, width=width, height=height, rng=sensor_gen)
    else:
        c_on, c_off = (np.asarray(a, dtype=np.float64) for a in thresholds)
        if c_on.shape != (height, width) or c_off.shape != (height, width):
            raise ValueError(
                f"thresholds must have the sensor's shape {(height, width)}, got {c_on.shape} "
                f"and {c_off.shape}"
            )
        if (c_on <= 0).any() or (c_off <= 0).any():
            raise ValueError("thresholds must be positive")
    defects = draw_defects(sensor, n_pixels=width * height, rng=sensor_gen)
    hash_seed = seed_from(gen)

    w1, w2 = rig.waveforms()
    if not np.array_equal(w1.phase, w2.phase):
        knots = np.union1d(w1.phase, w2.phase)
        t1v, t2v = w1(knots), w2(knots)
    else:
        knots, t1v, t2v = w1.phase, w1.values, w2.values
    still = radiance.mean(axis=0) if moving else radiance
    rho = (still.astype(np.float64) / rig.l_const).ravel()
    e_min = float(np.min(float(radiance.min()) / rig.l_const * t1v + t2v))
    if not e_min > 0:
        raise ValueError(
            "the sensor irradiance reaches zero during the cycle (T2 closes fully while some "
            "pixels have zero radiance); give the panels a leakage floor (contrast ratio)"
        )
    c_on_f = np.ascontiguousarray(c_on.ravel())
    c_off_f = np.ascontiguousarray(c_off.ravel())
    starts = rig.cycle_starts_us(n_cycles, t0_us=t0_us)
    scale = rig.k_lens * rig.l_const
    rad_f = still.astype(np.float64).ravel()  # a moving scene's mean, for noise rates

    def irradiance_at(pix: np.ndarray, t_off_us: np.ndarray) -> np.ndarray:
        u = np.asarray(t_off_us) / rig.period_us
        return rig.k_lens * (w1(u) * rad_f[pix] + w2(u) * rig.l_const)

    signal: list[np.ndarray] = []
    alive = np.ones(width * height, dtype=np.int8)
    alive[defects.dead] = 0
    if engine == "exact":
        pieces = cycle_pieces(t1v, t2v)
        state = ExactState(np.log(rho * t1v[0] + t2v[0]))
        for k in range(n_cycles):
            signal.append(simulate_cycle_exact(
                rho, c_on_f, c_off_f, state, knots, t1v, t2v, width=width,
                period_us=rig.period_us, t_start_us=int(starts[k]), pieces=pieces, cycle=k,
                seed=hash_seed, reset_noise_sigma=sensor.reset_noise_sigma,
                refractory_us=sensor.refractory_us, irradiance_scale=scale,
                tau_ref_us=sensor.tau_ref_us, cutoff_irradiance=sensor.cutoff_irradiance,
                dark_irradiance=sensor.dark_irradiance, tau_max_us=sensor.tau_max_us,
                latency_us=sensor.latency_us, jitter_sigma_us=sensor.jitter_sigma_us,
                alive=alive))
            if progress is not None:
                progress(k + 1, n_cycles)
    else:
        from asynhdr.sensor.stepped import simulate_stepped

        stepped = simulate_stepped(
            radiance.astype(np.float64), rig=rig, sensor=sensor, n_cycles=n_cycles,
            c_on=c_on, c_off=c_off, seed=hash_seed, dt_us=dt_us, t0_us=t0_us,
            frame_times_us=frame_times_us, progress=progress)
        stepped = _shift_times(stepped, sensor, hash_seed)
        signal.append(stepped)

    n_signal = sum(int(c.size) for c in signal)
    chunks = list(signal)
    n_noise = 0
    if sensor.has_noise_events:
        noise = [background_events(sensor, irradiance_at=irradiance_at, n_pixels=width * height,
                                   width=width, t_start_us=int(starts[k]),
                                   duration_us=float(rig.period_us), defects=defects, rng=gen)
                 for k in range(n_cycles)]
        n_noise = sum(int(c.size) for c in noise)
        if engine == "exact":
            chunks = [merge_sorted(a, b) for a, b in zip(signal, noise, strict=True)]
        else:
            chunks = [merge_sorted(signal[0], _concat_sorted(noise))]
    events = _concat_sorted(chunks)
    if defects.dead.size and engine != "exact":
        # the exact engine and the background skip dead pixels themselves
        keep = alive[events["y"].astype(np.int64) * width + events["x"]].astype(bool)
        if not keep.all():
            events = events[keep]
    step = sensor.timestamp_resolution_us
    if step > 1:
        events["t"] = (events["t"] // step) * step
    events, stats = apply_arbiter(events, sensor)
    n = events.size
    metadata: dict[str, Any] = {
        "simulated": True,
        "asynhdr_version": __version__,
        "engine": engine,
        "rig": rig.to_metadata(),
        "sensor": sensor.to_metadata(),
        "n_cycles": int(n_cycles),
        "t0_us": int(t0_us),
        "seed": rng if isinstance(rng, int) else None,
        "sensor_seed": sensor_seed,
        "radiance_unit": info.get("unit", "relative"),
        "scene": info.get("name", ""),
        "counts": {"signal": n_signal, "background": n_noise,
                   "hot_pixels": int(defects.hot.size), "dead_pixels": int(defects.dead.size)},
        "readout": {"emitted": stats.emitted, "delivered": stats.delivered,
                    "delayed": stats.delayed, "dropped": stats.dropped,
                    "max_delay_us": stats.max_delay_us},
    }
    logger.info("simulated %d events over %d cycles on %dx%d", n, n_cycles, width, height)
    return Recording(events=events, width=width, height=height,
                     triggers=rig.triggers(n_cycles, t0_us=t0_us), metadata=metadata)


def _shift_times(events: np.ndarray, sensor: SensorParams, seed: int) -> np.ndarray:
    """Latency and jitter for engines that do not apply them (then re-sorted stably)."""
    if sensor.latency_us <= 0 and sensor.jitter_sigma_us <= 0:
        return events
    g = np.random.default_rng(seed)
    t = events["t"].astype(np.float64) + sensor.latency_us
    if sensor.jitter_sigma_us > 0:
        t += g.normal(0.0, sensor.jitter_sigma_us, t.size)
    out = events.copy()
    out["t"] = np.floor(t).astype(np.int64)
    order = np.argsort(out["t"], kind="stable")
    return out[order]
