"""Ground truth on real HDR scenes: simulate the rig on a radiance map, reconstruct with
every method, image the same scene with a frame camera (single exposures and Debevec
fusion), and measure everything against the scene itself.

Absolute units (the stated rule): an HDR file's values are relative. They are multiplied
by :func:`asynhdr.scene.exposure_scale` so that the scene's log-average lands at the
middle of the rig's working range (:meth:`asynhdr.rig.Rig.mid_radiance`: the geometric
middle of the range a designed rig was designed for, 178 lux for the presets' defaults;
``L_const sqrt(CR_1)``, 316 lux, for the paper's rig), unless a scale is given. The map
keeps its aspect (padded
onto the sensor, never stretched); the padding is left out of every metric. A scene wider
than the rig's working range has pixels beyond it at any exposure; every figure counts
them, and the log RMSE and PU21-PSNR over the rest stand beside (``*_in_range``), with
the shares above and below the range in the metadata: what the range costs, apart from
what the method does within it.

The frame camera has the same pixel count and sees the same sensor illuminance (the
scene's radiance in lux, panel open). Its brackets: ``mef-10``, ten exposures from the
one that puts the scene's maximum at 90 % of the full well to the one that gives the
scene's 0.1st percentile 100 electrons (:func:`asynhdr.framecam.exposure_bracket`), and
``mef-budget``, the exposures of that ladder that fit in one modulation cycle
(:func:`asynhdr.framecam.budget_bracket`), the event camera's capture time; ``frame-auto``
is one exposure putting the log-average at 18 % of the full well.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from asynhdr.calib import Calibration, flat_capture_sensor
from asynhdr.calibrate import CMap
from asynhdr.events import Recording
from asynhdr.experiments import _cmaps_from_flats, finite_image
from asynhdr.framecam import (
    FrameCamera,
    budget_bracket,
    capture,
    exposure_bracket,
    get_frame_camera,
)
from asynhdr.mef import fuse_frames
from asynhdr.metrics import ImageComparison, compare_images
from asynhdr.ml import FLAG_FEW_EVENTS, FLAG_FILLED
from asynhdr.reconstruct import DEFAULT_K, reconstruct
from asynhdr.rig import Rig
from asynhdr.scene import Scene, exposure_scale, flat_field, from_radiance_map, log_average
from asynhdr.sensor.params import SensorParams, get_preset
from asynhdr.simulate import simulate

__all__ = [
    "DEFAULT_SCENE_METHODS",
    "ML_FAST",
    "ML_UNCALIBRATED",
    "SceneEvaluation",
    "calibrate_for_scenes",
    "calibrate_thresholds_for_scenes",
    "evaluate_scene",
    "rig_mid_radiance",
]

logger = logging.getLogger(__name__)

DEFAULT_SCENE_METHODS: tuple[str, ...] = ("raw", "linear", "exp", "ttfe", "invert", "ml")
"""Event methods evaluated on scenes (all with the c-map)."""

ML_UNCALIBRATED = "ml-uncalibrated"
"""A further method name for :func:`evaluate_scene`: ``ml`` as ``asynhdr reconstruct``
runs it without a calibration (the nominal thresholds, learned from cycle to cycle; the
pixels it takes for dead filled), beside ``ml`` with the scenes' calibration."""

ML_FAST = "ml-fast"
"""... and ``ml``'s fast fit with the scenes' calibration (``reconstruct --method ml
--fast``): ``ln L`` alone, the calibrated thresholds held."""

AUTO_EXPOSURE_FRACTION = 0.18
"""``frame-auto`` puts the scene's log-average at this fraction of the full well (the 18 %
middle grey of photographic metering)."""

Progress = Callable[[str, int, int], None]


def rig_mid_radiance(rig: Rig) -> float:
    """Middle of the rig's working range (lux), where the scenes' log-average is put:
    :meth:`asynhdr.rig.Rig.mid_radiance`."""
    return rig.mid_radiance()


@dataclass(frozen=True, eq=False)
class SceneEvaluation:
    """One scene: truth, every image (scaled to the truth), and the metrics."""

    name: str
    scene: Scene
    mask: np.ndarray
    images: dict[str, np.ndarray]
    metrics: dict[str, ImageComparison]
    capture_s: dict[str, float]
    metadata: dict[str, Any] = field(default_factory=dict)
    beyond_range: np.ndarray | None = None
    """The scene's pixels (in ``mask``) outside the rig's working range at this exposure."""

    def summary(self) -> dict[str, Any]:
        return {"name": self.name, "metadata": self.metadata,
                "methods": {k: dict(v.to_dict(), capture_s=self.capture_s.get(k))
                            for k, v in self.metrics.items()}}


def calibrate_for_scenes(*, width: int, height: int, sensor: SensorParams | str,
                         rig: Rig | None = None, n_flat: int = 2, flat_cycles: int = 2,
                         flat_radiance: float | None = None, sensor_seed: int = 1,
                         seed: int = 100, engine: str = "exact") -> CMap:
    """A c-map for the sensor from ``n_flat`` flat fields at ``flat_radiance`` (default:
    :func:`rig_mid_radiance`)."""
    rig = rig or Rig()
    sensor = get_preset(sensor) if isinstance(sensor, str) else sensor
    lum = rig_mid_radiance(rig) if flat_radiance is None else flat_radiance
    flat = flat_field(width=width, height=height, radiance=lum, unit="lux")
    seeds = np.random.SeedSequence(seed).spawn(n_flat)
    roi = flat_capture_sensor(sensor, width * height)

    def caps() -> Iterator[Recording]:
        for s in seeds:
            yield simulate(flat, rig=rig, sensor=roi, n_cycles=flat_cycles,
                           rng=np.random.default_rng(s), sensor_seed=sensor_seed,
                           engine=engine)

    cmap = _cmaps_from_flats(caps(), [DEFAULT_K])
    cmap.metadata.update({"flat_radiance": lum, "unit": "lux"})
    return cmap


def calibrate_thresholds_for_scenes(*, width: int, height: int, sensor: SensorParams | str,
                                    rig: Rig | None = None, sensor_seed: int = 1,
                                    seed: int = 300, engine: str = "exact") -> Calibration:
    """Per-pixel ON and OFF thresholds and the dead pixels, for ``ml``
    (:func:`asynhdr.calib.thresholds_from_flats`), from flat fields 30x above and below
    ``L_const``, two of each, three cycles each."""
    from asynhdr.calib import thresholds_from_flats

    rig = rig or Rig()
    sensor = get_preset(sensor) if isinstance(sensor, str) else sensor
    rads = [rig.l_const * 30.0, rig.l_const / 30.0] * 2
    seeds = np.random.SeedSequence(seed).spawn(len(rads))
    roi = flat_capture_sensor(sensor, width * height)
    caps = [simulate(flat_field(width=width, height=height, radiance=r, unit="lux"), rig=rig,
                     sensor=roi, n_cycles=3, rng=np.random.default_rng(sq),
                     sensor_seed=sensor_seed, engine=engine) for r, sq in zip(rads, seeds,
                                                                              strict=True)]
    return thresholds_from_flats(caps, radiance=rads, rig=rig, sensor=sensor)


def evaluate_scene(
    radiance_map: npt.ArrayLike,
    *,
    name: str = "scene",
    width: int = 640,
    height: int = 480,
    sensor: SensorParams | str = "v2e",
    rig: Rig | None = None,
    scale: float | None = None,
    cmap: CMap | None = None,
    ml_calibration: Calibration | None = None,
    n_cycles: int = 2,
    methods: Sequence[str] = DEFAULT_SCENE_METHODS,
    k: float = DEFAULT_K,
    frame_camera: FrameCamera | str = "imx174",
    n_exposures: int = 10,
    seed: int = 0,
    sensor_seed: int = 1,
    engine: str = "exact",
    progress: Progress | None = None,
) -> SceneEvaluation:
    """Evaluate one scene (see the module's text). ``cmap``: from
    :func:`calibrate_for_scenes` for the same sensor (made here when not given).
    ``ml_calibration``: per-pixel thresholds and dead pixels for ``ml``
    (:func:`calibrate_thresholds_for_scenes`); without it ``ml`` uses the c-map.
    ``methods`` may name :data:`ML_UNCALIBRATED` and :data:`ML_FAST` (which needs
    ``ml_calibration``) too."""
    rig = rig or Rig()
    sensor = get_preset(sensor) if isinstance(sensor, str) else sensor
    cam = get_frame_camera(frame_camera) if isinstance(frame_camera, str) else frame_camera
    raw_map = np.asarray(radiance_map)
    target = rig_mid_radiance(rig)
    s = exposure_scale(raw_map, target=target) if scale is None else float(scale)
    scene = from_radiance_map(raw_map, width=width, height=height, scale=s, unit="lux",
                              name=name, fit="pad")
    if scene.rois is None:
        raise RuntimeError("from_radiance_map returned no region")
    y0, y1, x0, x1 = scene.rois[0]
    mask = np.zeros((height, width), bool)
    mask[y0:y1, x0:x1] = True
    truth = scene.radiance.astype(np.float64)
    valid = mask & (truth > 0)
    gen = np.random.SeedSequence(seed).spawn(2)

    def tick(stage: str, done: int, total: int) -> None:
        if progress is not None:
            progress(stage, done, total)

    if cmap is None:
        cmap = calibrate_for_scenes(width=width, height=height, sensor=sensor, rig=rig,
                                    sensor_seed=sensor_seed, engine=engine)
    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=n_cycles,
                   rng=np.random.default_rng(gen[0]), sensor_seed=sensor_seed, engine=engine,
                   progress=lambda _s, d, t: tick(f"{name}: simulate", d, t))
    images: dict[str, np.ndarray] = {}
    ml_out: dict[str, Any] = {}
    for i, m in enumerate(methods):
        if m in ("ml", ML_FAST) and ml_calibration is not None:
            # per-pixel thresholds, dead pixels
            opts: dict[str, Any] = {"thresholds": ml_calibration.threshold_maps(),
                                    "defects": ml_calibration.defects, "fast": m == ML_FAST}
            if m == "ml":
                opts["out"] = ml_out
            img = reconstruct(rec, method="ml", ml_options=opts)[-1]
        elif m == ML_FAST:
            raise ValueError(f"{ML_FAST} holds the calibration's thresholds: it needs a "
                             "calibration (a rig: --designed or --rig)")
        elif m == ML_UNCALIBRATED:
            # the last cycle, learned from the first: the first is not fitted again
            img = reconstruct(rec, method="ml", ml_options={"refit_first": False})[-1]
        else:
            img = reconstruct(rec, method=m, k=k, cmap=cmap,
                              ml_options={"out": ml_out} if m == "ml" else None)[-1]
        images[m] = finite_image(img, name=f"{name} {m}", region=valid)[0]
        tick(f"{name}: reconstruct", i + 1, len(methods))
    n_events = int(rec.events.size)
    filled = few = 0
    if "flags" in ml_out:
        filled = int(np.count_nonzero(valid & (ml_out["flags"][-1] & FLAG_FILLED != 0)))
        few = int(np.count_nonzero(valid & (ml_out["flags"][-1] == FLAG_FEW_EVENTS)))
    del rec

    inside = truth[valid]
    n_valid = inside.size
    l_max = float(inside.max())
    l_min = float(np.percentile(inside, 0.1))
    full = exposure_bracket(cam, l_min_lux=l_min, l_max_lux=l_max, n=n_exposures)
    period_s = rig.period_us * 1e-6
    short = budget_bracket(cam, full, budget_s=period_s)
    t_auto = AUTO_EXPOSURE_FRACTION * cam.full_well_e / (
        cam.electrons_per_lux_s * log_average(inside))
    fgen = np.random.default_rng(gen[1])
    frames = {float(t): capture(cam, truth, exposure_s=float(t), rng=fgen)
              for t in np.union1d(full, short)}
    images[f"mef-{n_exposures}"] = fuse_frames(cam, [frames[float(t)] for t in full], full)
    images["mef-budget"] = fuse_frames(cam, [frames[float(t)] for t in short], short)
    auto = capture(cam, truth, exposure_s=t_auto, rng=fgen)
    images["frame-auto"] = (auto.astype(np.float64) * cam.gain_e_per_dn /
                            (cam.electrons_per_lux_s * t_auto)).astype(np.float32)
    tick(f"{name}: frame camera", 1, 1)

    # what the rig can measure: its working range; the pixels beyond it hold a bound (or
    # nothing), as a camera's saturated pixels do, and every figure counts them; beside
    # them the log error and PU21 over the rest
    r_lo, r_hi = (float(v) for v in rig.working_range())
    above = valid & (truth > r_hi)
    below = valid & (truth < r_lo)
    outside = int(np.count_nonzero(above | below))
    in_range = (valid & ~above & ~below) if outside else None
    metrics: dict[str, ImageComparison] = {}
    scaled: dict[str, np.ndarray] = {}
    for m, img in images.items():
        c = compare_images(img, truth, mask=valid, in_range=in_range)
        metrics[m] = c
        # a saturated pixel (the largest float32) times a scale > 1 would overflow
        with np.errstate(over="ignore"):
            scaled[m] = np.minimum(np.asarray(img, np.float64) * c.scale,
                                   np.finfo(np.float32).max).astype(np.float32)
    fc = cam.frame_time_s
    capture_s = {m: period_s for m in methods}
    capture_s[f"mef-{n_exposures}"] = float(sum(max(t, fc) for t in full))
    capture_s["mef-budget"] = float(sum(max(t, fc) for t in short))
    capture_s["frame-auto"] = float(max(t_auto, fc))
    span = float(np.log2(l_max / max(float(inside.min()), 1e-30)))
    meta = {
        "width": width, "height": height, "region": [y0, y1, x0, x1], "scale": s,
        "auto_exposure": scale is None, "target_log_average_lux": target if scale is None
        else None, "log_average_lux": log_average(inside), "max_lux": l_max,
        "p0.1_lux": l_min, "span_stops": span, "rig_range_lux": [r_lo, r_hi],
        "above_range_fraction": float(np.count_nonzero(above)) / n_valid,
        "below_range_fraction": float(np.count_nonzero(below)) / n_valid,
        "max_over_range": l_max / r_hi,
        "sensor": sensor.name, "rig": rig.to_metadata(), "n_cycles": n_cycles, "k": k,
        "n_events": n_events, "ml_dead_pixels_filled": filled,
        "ml_few_event_pixels": few,
        "frame_camera": cam.to_metadata(),
        "exposures_s": full.tolist(), "budget_exposures_s": short.tolist(),
        "auto_exposure_s": t_auto, "seed": seed, "sensor_seed": sensor_seed,
    }
    return SceneEvaluation(name=name, scene=scene, mask=mask, images=scaled, metrics=metrics,
                           capture_s=capture_s, metadata=meta, beyond_range=above | below)
