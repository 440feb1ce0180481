"""Motion artefacts: the modulated event camera against a frame camera at the same rate.

The rig assumes a static scene within a cycle (Wu et al. 2024, section 5: "static scenes
only"). This experiment measures what motion does. An image pans across the sensor at a
constant velocity (:func:`asynhdr.scene.moving_scene`); the event camera is simulated by
the stepped engine (each pixel's own signal, radiance linear in time between the scene's
frames) and reconstructed once per cycle; a frame camera with the same pixel count makes
one HDR frame per cycle period by fusing (Debevec) the exposures that fit in it, each
exposure integrating the moving scene over its own time (motion blur) at its own moment
(ghosting between exposures).

Each output frame is compared with the scene at the middle of the time it looked at (the
ramp of the cycle for the event camera, the exposures' span for the frame camera), with
:func:`asynhdr.metrics.log_rmse` after one global scale, and, for a scene with one
vertical edge, by the edge's width: the distance over which the log radiance of the
central rows goes from 10 % to 90 % of its step.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from asynhdr.framecam import (
    FrameCamera,
    budget_bracket,
    capture,
    exposure_bracket,
    get_frame_camera,
)
from asynhdr.mef import fuse_frames
from asynhdr.metrics import fit_scale, log_rmse
from asynhdr.reconstruct import reconstruct
from asynhdr.rig import Rig
from asynhdr.scene import MovingScene, moving_scene
from asynhdr.sensor.params import SensorParams
from asynhdr.simulate import simulate

__all__ = ["MotionResult", "edge_scene", "edge_width_px", "frame_camera_video",
           "run_motion_experiment"]

Progress = Callable[[str, int, int], None]


def edge_scene(*, width: int, height: int, dark: float, bright: float,
               edge_x: float | None = None) -> np.ndarray:
    """A vertical step edge: ``dark`` left of ``edge_x`` (default a third of the width),
    ``bright`` right of it."""
    x0 = width / 3.0 if edge_x is None else edge_x
    r = np.full((height, width), float(dark))
    r[:, round(x0):] = float(bright)
    return r


def edge_width_px(image: npt.ArrayLike, *, rows: slice | None = None) -> float:
    """10-90 % width (pixels) of the largest step along x of the central rows' median log
    profile (pixels without a value, holes or NaN, left out: they are counted by the log
    error, not here); NaN when the image has no positive step."""
    a = np.asarray(image, dtype=np.float64)
    h = a.shape[0]
    sel = a[rows if rows is not None else slice(h // 3, 2 * h // 3)]
    ok = np.isfinite(sel) & (sel > 0)
    if not ok.any(axis=0).all():
        return float("nan")
    prof = np.nanmedian(np.log(np.where(ok, sel, np.nan)), axis=0)
    lo, hi = float(np.percentile(prof, 5)), float(np.percentile(prof, 95))
    if not hi > lo:
        return float("nan")
    v = (prof - lo) / (hi - lo)
    # the first crossing of 0.1 and of 0.9 going right, interpolated
    def cross(level: float) -> float:
        i = int(np.argmax(v >= level))
        if i == 0:
            return 0.0
        return i - 1 + (level - v[i - 1]) / (v[i] - v[i - 1])
    return float(cross(0.9) - cross(0.1))


def _window_mean(scene: MovingScene, t0_us: float, t1_us: float, n: int = 16) -> np.ndarray:
    """Time-average of the moving scene over ``[t0, t1]`` (midpoint rule, ``n`` samples)."""
    ts = t0_us + (np.arange(n) + 0.5) * (t1_us - t0_us) / n
    return np.mean([scene.at(float(t)) for t in ts], axis=0)


def frame_camera_video(scene: MovingScene, camera: FrameCamera | str, *, frame_period_us: int,
                       n_frames: int, l_min_lux: float, l_max_lux: float,
                       n_exposures: int = 10, t0_us: float = 0.0,
                       rng: np.random.Generator | int | None = 0,
                       ) -> list[tuple[np.ndarray, float]]:
    """HDR frames of a frame camera at one frame per ``frame_period_us``: each fuses the
    exposures of a bracket over ``[l_min, l_max]`` that fit in the period
    (:func:`asynhdr.framecam.budget_bracket`), taken one after the other from the
    period's start, each integrating the moving scene over its own exposure. Returns
    ``(radiance, mid_time_us)`` per frame (the middle of the exposures' span)."""
    cam = get_frame_camera(camera) if isinstance(camera, str) else camera
    gen = np.random.default_rng(rng)
    full = exposure_bracket(cam, l_min_lux=l_min_lux, l_max_lux=l_max_lux, n=n_exposures)
    ts = budget_bracket(cam, full, budget_s=frame_period_us * 1e-6)
    out = []
    for k in range(n_frames):
        start = t0_us + k * frame_period_us
        t = start
        frames = []
        for exp_s in ts:
            span = exp_s * 1e6
            frames.append(capture(cam, _window_mean(scene, t, t + span), exposure_s=exp_s,
                                  rng=gen))
            t += max(exp_s, cam.frame_time_s) * 1e6
        out.append((fuse_frames(cam, frames, ts).astype(np.float64), 0.5 * (start + t)))
    return out


@dataclass
class MotionResult:
    """Per output frame and method: log RMSE (stops) against the scene at the frame's
    middle time, and the edge width (px); plus the settings."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, dict[str, float]]:
        """Median over frames of each figure, per method."""
        out: dict[str, dict[str, float]] = {}
        for m in sorted({r["method"] for r in self.rows}):
            rs = [r for r in self.rows if r["method"] == m]
            out[m] = {key: float(np.nanmedian([r[key] for r in rs]))
                      for key in ("log_rmse_stops", "edge_width_px")}
        return out


def run_motion_experiment(
    radiance: npt.ArrayLike,
    *,
    velocity_px_per_s: tuple[float, float],
    sensor: SensorParams | str = "v2e",
    rig: Rig | None = None,
    n_cycles: int = 4,
    methods: Sequence[str] = ("invert", "exp"),
    frame_camera: FrameCamera | str = "imx174",
    frame_step_us: float = 500.0,
    seed: int = 0,
    sensor_seed: int = 1,
    progress: Progress | None = None,
) -> MotionResult:
    """Pan ``radiance`` (lux) at ``velocity_px_per_s`` and image it with the event camera
    (every method in ``methods``) and the frame camera at one HDR frame per cycle period.
    The first cycle is left out (the pixels start adapted to a static view)."""
    rig = rig or Rig()
    r = np.asarray(radiance, dtype=np.float64)
    h, w = r.shape
    duration = n_cycles * rig.period_us
    scene = moving_scene(r, velocity_px_per_s=velocity_px_per_s, duration_us=duration,
                         frame_step_us=frame_step_us, unit="lux")
    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=n_cycles, rng=seed,
                   sensor_seed=sensor_seed, engine="stepped", progress=progress)
    margin = max(2, math.ceil(abs(velocity_px_per_s[1]) * duration * 1e-6))
    mask = np.zeros((h, w), dtype=bool)
    mask[margin:h - margin, 2:w - 2] = True
    rows: list[dict[str, Any]] = []
    mid_ramp = 0.5 * rig.ramp_us
    for m in methods:
        imgs = reconstruct(rec, method=m)
        for k in range(1, n_cycles):
            t_mid = k * rig.period_us + mid_ramp
            truth = scene.at(t_mid)
            img = np.asarray(imgs[k], dtype=np.float64)
            img = np.where(np.isfinite(img), img, 0.0)
            s = fit_scale(img, truth, mask=mask)
            rows.append({"method": m, "cycle": k, "t_mid_us": t_mid,
                         "log_rmse_stops": log_rmse(s * img, truth, mask=mask),
                         "edge_width_px": edge_width_px(img)})
        if progress is not None:
            progress("reconstruct", methods.index(m) + 1, len(methods))
    lo, hi = float(r[r > 0].min()), float(r.max())
    frames = frame_camera_video(scene, frame_camera, frame_period_us=rig.period_us,
                                n_frames=n_cycles, l_min_lux=lo, l_max_lux=hi,
                                rng=seed + 1)
    for k in range(1, n_cycles):
        img, t_mid = frames[k]
        truth = scene.at(t_mid)
        s = fit_scale(img, truth, mask=mask)
        rows.append({"method": "frame camera (fusion in one period)", "cycle": k,
                     "t_mid_us": t_mid, "log_rmse_stops": log_rmse(s * img, truth, mask=mask),
                     "edge_width_px": edge_width_px(img)})
    cam = get_frame_camera(frame_camera) if isinstance(frame_camera, str) else frame_camera
    static = [float(np.hypot(*velocity_px_per_s)) * rig.ramp_us * 1e-6]
    settings = {"velocity_px_per_s": list(velocity_px_per_s), "width": w, "height": h,
                "n_cycles": n_cycles, "period_us": rig.period_us, "ramp_us": rig.ramp_us,
                "frame_step_us": frame_step_us, "sensor": rec.metadata["sensor"]["name"],
                "frame_camera": cam.to_metadata(),
                "motion_during_ramp_px": static[0]}
    return MotionResult(rows=rows, settings=settings)
