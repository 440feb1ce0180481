"""The paper's chart experiment: dynamic range, the SNR table and the k sweep, in simulation.

Simulate the 36-level step chart (Wu et al. 2024, section 3.2; 160,000 lux light box),
calibrate a c-map from flat-field captures of the same sensor, reconstruct with every
method with and without the c-map, and measure each patch with :mod:`asynhdr.metrics`
(a central 16 x 16 region per patch, input-referred SNR, both dynamic-range criteria).
Optionally: the k sweep of the exponential weighting (the paper's Fig. 5b), and a frame
camera of the same pixel count fusing its exposures (:mod:`asynhdr.framecam`,
:mod:`asynhdr.mef`) measured the same way.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from asynhdr.calib import flat_capture_sensor
from asynhdr.calibrate import CMap, cmap_from_levels, cmap_key, warn_nominal
from asynhdr.events import Recording
from asynhdr.framecam import (
    FrameCamera,
    budget_bracket,
    capture,
    exposure_bracket,
    get_frame_camera,
)
from asynhdr.mef import fuse_frames
from asynhdr.metrics import (
    MIN_EVENT_FRACTION,
    SNR_REGION_SHAPE,
    DynamicRange,
    PatchStats,
    SnrSummary,
    central_rois,
    distinct_grey_levels,
    dynamic_range,
    dynamic_range_steps,
    mean_snr_db,
    patch_event_fraction,
    patch_stats,
    radiometric_error,
)
from asynhdr.reconstruct import DEFAULT_K, WEIGHTINGS, reconstruct, weighted_sums, windows_for
from asynhdr.rig import Rig
from asynhdr.scene import PAPER_ILLUMINANCE_LUX, Scene, flat_field, step_chart
from asynhdr.sensor.params import SensorParams, get_preset
from asynhdr.simulate import simulate

__all__ = [
    "PAPER_DR_DB",
    "PAPER_SNR_DB",
    "ChartResult",
    "MethodResult",
    "event_counts",
    "finite_image",
    "measure_chart",
    "run_chart_experiment",
    "run_frame_chart",
]

logger = logging.getLogger(__name__)

PAPER_SNR_DB: dict[str, tuple[float, float]] = {
    "raw": (14.98, 21.74),
    "linear": (15.99, 24.99),
    "quadratic": (16.32, 26.43),
    "poly5": (16.56, 27.52),
    "exp": (16.61, 27.67),
}
"""The paper's mean patch SNR (dB), (without, with) c-map, by weighting (Table 1)."""

PAPER_DR_DB = 102.6
"""The paper's dynamic range (levels 2 to 29, densities 0.10 to 5.23)."""

DEFAULT_FLAT_DENSITY = 2.0
"""Flat-field captures for the c-map are taken at the light box behind this density
(1,600 lux for the 160,000 lux box): the middle of the chart's resolved range."""

DEFAULT_METHODS: tuple[str, ...] = (*WEIGHTINGS, "ttfe", "count", "invert")

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``."""


@dataclass(frozen=True, eq=False)
class MethodResult:
    """One image of the chart and its measurements (see :func:`measure_chart`)."""

    method: str
    with_cmap: bool
    image: np.ndarray
    stats: PatchStats
    snr: SnrSummary
    snr_in: np.ndarray
    responding: np.ndarray
    dr: DynamicRange
    dr_steps: DynamicRange
    rel_error: np.ndarray
    rel_error_median: float
    grey_levels: int
    n_nonfinite: int = 0

    def to_dict(self) -> dict[str, Any]:
        def fl(v: float) -> float | str | None:
            return float(v) if math.isfinite(v) else (None if math.isnan(v) else
                                                       ("inf" if v > 0 else "-inf"))

        return {
            "method": self.method, "with_cmap": self.with_cmap,
            "mean_snr_db": fl(self.snr.mean_db), "snr_patches": self.snr.n_patches,
            "snr_noiseless_patches": self.snr.n_noiseless,
            "dr_db": self.dr.dr_db, "dr_l_min": self.dr.l_min, "dr_l_max": self.dr.l_max,
            "dr_patches": self.dr.n_patches,
            "dr_steps_db": self.dr_steps.dr_db, "dr_steps_d": [self.dr_steps.d_brightest,
                                                              self.dr_steps.d_darkest],
            "median_rel_error": fl(self.rel_error_median),
            "grey_levels": self.grey_levels, "n_nonfinite": self.n_nonfinite,
            "patch_mean": self.stats.mean.tolist(),
            "patch_std": self.stats.std.tolist(),
            "patch_snr_db": [fl(v) for v in self.stats.snr_db],
            "patch_snr_in": [fl(v) for v in self.snr_in],
            "patch_responding": self.responding.tolist(),
            "patch_rel_error": [fl(v) for v in self.rel_error],
        }


def finite_image(image: np.ndarray, *, name: str = "image",
                 region: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """The image with its non-finite pixels made finite, and how many there were: NaN (a
    pixel without an estimate) becomes 0, a hole that the metrics charge in full;
    infinity (an overflowing ``exp``) becomes the image's largest finite value.

    ``region``: the pixels that are measured (a boolean mask of the image's shape); the
    warning then counts the holes in it apart from the others (a padded scene's border,
    pixels of no light)."""
    img = np.asarray(image)
    bad = ~np.isfinite(img)
    n = int(bad.sum())
    if not n:
        return img, 0
    ok = img[~bad]
    top = float(ok.max()) if ok.size else 0.0
    nan = np.isnan(img)
    out = np.where(nan, 0.0, np.where(bad, top, img)).astype(img.dtype)
    n_nan = int(nan.sum())
    n_inf = n - n_nan
    if region is None:
        logger.warning("%s: %d pixels without an estimate (NaN) set to 0, %d infinite ones "
                       "to the image's largest finite value", name, n_nan, n_inf)
    else:
        inside = np.asarray(region, bool)
        if inside.shape != img.shape:
            raise ValueError(f"finite_image: region's shape {inside.shape} is not the "
                             f"image's {img.shape}")
        n_in = int(np.count_nonzero(nan & inside))
        logger.warning("%s: %d of the %d pixels measured without an estimate (NaN) set to "
                       "0 (and %d not measured), %d infinite ones to the image's largest "
                       "finite value", name, n_in, int(inside.sum()), n_nan - n_in, n_inf)
    return out, n


def measure_chart(image: np.ndarray, scene: Scene, *, method: str, with_cmap: bool = False,
                  has_events: np.ndarray | None = None,
                  region_shape: tuple[int, int] = SNR_REGION_SHAPE) -> MethodResult:
    """Measure one chart image: stats over the central ``region_shape`` of each patch,
    both dynamic ranges, the SNR over the patches that respond (events and
    ``SNR_in >= 1``), the radiometric error after one global scale, grey levels."""
    if scene.rois is None or scene.truth is None or scene.densities is None:
        raise ValueError("measure_chart: the scene has no patches (use step_chart)")
    image, n_bad = finite_image(image, name=method)
    rois = central_rois(scene.rois, shape=region_shape)
    st = patch_stats(image, rois)
    dr = dynamic_range(st, scene.truth, has_events=has_events)
    snr_in = dr.snr_in if dr.snr_in is not None else np.zeros(st.mean.size)
    ev = np.ones(st.mean.size, bool) if has_events is None else np.asarray(has_events, bool)
    responding = ev & (snr_in >= 1.0)
    illum = float(scene.truth[int(np.argmin(scene.densities))] *
                  10.0 ** float(np.min(scene.densities)))
    steps = dynamic_range_steps(st, scene.densities, has_events=has_events,
                                illuminance=illum)
    err, _ = radiometric_error(st, scene.truth, mask=responding)
    med = float(np.median(err[responding])) if responding.any() else float("nan")
    return MethodResult(
        method=method, with_cmap=with_cmap, image=image, stats=st,
        snr=mean_snr_db(st, responding=responding), snr_in=snr_in, responding=responding,
        dr=dr, dr_steps=steps, rel_error=err, rel_error_median=med,
        grey_levels=distinct_grey_levels(image), n_nonfinite=n_bad)


def event_counts(rec: Recording, cycle: int = -1) -> np.ndarray:
    """Events per pixel ``(height, width)`` in one cycle's integration window."""
    win = windows_for(rec)
    start = int(win.start_us[cycle])
    ev = rec.events
    sel = (ev["t"] >= start) & (ev["t"] < start + win.window_us)
    idx = ev["y"][sel].astype(np.int64) * rec.width + ev["x"][sel]
    return np.bincount(idx, minlength=rec.width * rec.height).reshape(rec.height, rec.width)


def _cmaps_from_flats(captures: Iterator[Recording], ks: Sequence[float]) -> CMap:
    """The c-map of :func:`asynhdr.calibrate.estimate_cmap` (``median(S) / S`` per
    weighting, ``S`` the mean weighted sum per cycle), for the exponential weighting at
    every ``k`` at once, holding one flat-field capture at a time."""
    keys: list[tuple[str, float]] = [(m, DEFAULT_K) for m in WEIGHTINGS if m != "exp"]
    keys += [("exp", float(k)) for k in dict.fromkeys([*ks, DEFAULT_K])]
    sums: dict[tuple[str, float], np.ndarray] = {}
    n_cycles = 0
    n_caps = 0
    for cap in captures:
        win = windows_for(cap)
        n_cycles += win.n_cycles
        n_caps += 1
        for m, k in keys:
            s = weighted_sums(cap, win, method=m, k=k).sum(axis=0)
            sums[(m, k)] = sums[(m, k)] + s if (m, k) in sums else s
    if n_caps == 0:
        raise ValueError("no flat-field captures")
    maps: dict[str, np.ndarray] = {}
    kept: dict[str, int] = {}
    for (m, k), s in sums.items():
        key = cmap_key(m, k=k)
        maps[key], kept[key] = cmap_from_levels(s, n_cycles)
    warn_nominal(kept, next(iter(sums.values())).size)
    return CMap(maps=maps, metadata={"n_captures": n_caps, "n_cycles": n_cycles,
                                     "methods": list(WEIGHTINGS), "k": DEFAULT_K,
                                     "k_sweep": [float(k) for k in ks],
                                     "nominal_pixels": kept})


@dataclass(frozen=True, eq=False)
class ChartResult:
    """Everything the chart experiment measured."""

    scene: Scene
    cmap: CMap
    results: list[MethodResult] = field(default_factory=list)
    k_sweep: list[dict[str, Any]] = field(default_factory=list)
    frame: list[MethodResult] = field(default_factory=list)
    has_events: np.ndarray | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    recording: Recording | None = None

    def get(self, method: str, with_cmap: bool) -> MethodResult:
        for r in (*self.results, *self.frame):
            if r.method == method and r.with_cmap == with_cmap:
                return r
        raise KeyError((method, with_cmap))

    def snr_table(self) -> dict[str, tuple[float, float]]:
        """Mean SNR (dB) over responding patches, (without, with) c-map, per weighting."""
        return {m: (self.get(m, False).snr.mean_db, self.get(m, True).snr.mean_db)
                for m in WEIGHTINGS}

    def summary(self) -> dict[str, Any]:
        """JSON-serialisable figures."""
        out: dict[str, Any] = {
            "metadata": self.metadata,
            "methods": [r.to_dict() for r in self.results],
            "frame_camera": [r.to_dict() for r in self.frame],
            "k_sweep": self.k_sweep,
            "patch_has_events": None if self.has_events is None else self.has_events.tolist(),
            "truth": None if self.scene.truth is None else self.scene.truth.tolist(),
            "densities": None if self.scene.densities is None else
            self.scene.densities.tolist(),
            "paper": {"snr_db": PAPER_SNR_DB, "dr_db": PAPER_DR_DB},
        }
        return out


def run_frame_chart(scene: Scene, camera: FrameCamera | str, *, budget_s: float,
                    n_exposures: int = 10, rng: np.random.Generator | int | None = 0,
                    ) -> tuple[list[MethodResult], dict[str, Any]]:
    """The frame camera on the chart: Debevec fusion of ``n_exposures`` exposures
    (:func:`asynhdr.framecam.exposure_bracket` over the chart's patch radiances) and of
    the exposures that fit in ``budget_s`` (:func:`~asynhdr.framecam.budget_bracket`),
    each measured by :func:`measure_chart`. Method names ``mef-N`` and ``mef-budget``."""
    cam = get_frame_camera(camera) if isinstance(camera, str) else camera
    if scene.truth is None:
        raise ValueError("run_frame_chart: the scene has no patches")
    gen = np.random.default_rng(rng)
    full = exposure_bracket(cam, l_min_lux=float(np.min(scene.truth)),
                            l_max_lux=float(np.max(scene.truth)), n=n_exposures)
    short = budget_bracket(cam, full, budget_s=budget_s)
    frames = {float(t): capture(cam, scene.radiance, exposure_s=float(t), rng=gen)
              for t in np.union1d(full, short)}
    out = []
    for name, ts in ((f"mef-{n_exposures}", full), ("mef-budget", short)):
        img = fuse_frames(cam, [frames[float(t)] for t in ts], ts)
        out.append(measure_chart(img, scene, method=name))
    meta = {"camera": cam.to_metadata(), "exposures_s": full.tolist(),
            "budget_exposures_s": short.tolist(), "budget_s": budget_s,
            "capture_s": float(sum(max(t, cam.frame_time_s) for t in full)),
            "budget_capture_s": float(sum(max(t, cam.frame_time_s) for t in short))}
    return out, meta


def run_chart_experiment(
    *,
    width: int = 640,
    height: int = 480,
    sensor: SensorParams | str = "v2e",
    rig: Rig | None = None,
    n_cycles: int = 3,
    n_flat: int = 4,
    flat_cycles: int = 2,
    methods: Sequence[str] = DEFAULT_METHODS,
    k: float = DEFAULT_K,
    k_sweep: Sequence[float] = (),
    frame_camera: FrameCamera | str | None = None,
    illuminance_lux: float = PAPER_ILLUMINANCE_LUX,
    flat_density: float = DEFAULT_FLAT_DENSITY,
    seed: int = 0,
    sensor_seed: int = 1,
    engine: str = "exact",
    keep_recording: bool = False,
    progress: Progress | None = None,
) -> ChartResult:
    """Run the chart experiment.

    The sensor's frozen threshold mismatch is drawn once from ``sensor_seed`` and shared
    by the chart and the flat-field captures (one physical sensor); each capture draws
    its own randomness from ``seed``. Images are measured on the last cycle; a patch
    "has events" when at least half its region's pixels fired in that cycle.
    ``k_sweep``: values of ``k`` for the exponential weighting (each with its own
    c-map). ``frame_camera``: also image the chart with that camera
    (:func:`run_frame_chart`, capture budget one modulation period).
    """
    rig = rig or Rig()
    sensor = get_preset(sensor) if isinstance(sensor, str) else sensor
    scene = step_chart(width=width, height=height, illuminance_lux=illuminance_lux)
    if scene.rois is None or scene.densities is None or scene.truth is None:
        raise RuntimeError("step_chart returned a scene without patches")
    central_rois(scene.rois)  # fail early, before simulating, when patches are too small
    seeds = np.random.SeedSequence(seed).spawn(2 + n_flat)

    def cb(stage: str) -> Callable[[str, int, int], None] | None:
        if progress is None:
            return None
        return lambda _s, d, t: progress(stage, d, t)

    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=n_cycles,
                   rng=np.random.default_rng(seeds[0]), sensor_seed=sensor_seed, engine=engine,
                   progress=cb("simulate chart"))
    flat = flat_field(width=width, height=height,
                      radiance=illuminance_lux * 10.0 ** (-flat_density), unit="lux")

    roi = flat_capture_sensor(sensor, width * height)

    def flats() -> Iterator[Recording]:
        for i in range(n_flat):
            yield simulate(flat, rig=rig, sensor=roi, n_cycles=flat_cycles,
                           rng=np.random.default_rng(seeds[2 + i]),
                           sensor_seed=sensor_seed, engine=engine)
            if progress is not None:
                progress("flat-field captures", i + 1, n_flat)

    cmap = _cmaps_from_flats(flats(), [*k_sweep, k])
    cmap.metadata.update({"flat_radiance": float(flat.radiance.flat[0]), "unit": "lux"})

    counts = event_counts(rec)
    frac = patch_event_fraction(counts, central_rois(scene.rois))
    has_events = frac >= MIN_EVENT_FRACTION

    results = []
    total = 2 * len(methods) + 2 * len(k_sweep)
    done = 0
    for m in methods:
        for use in (False, True):
            img = reconstruct(rec, method=m, k=k, cmap=cmap if use else None)[-1]
            results.append(measure_chart(img, scene, method=m, with_cmap=use,
                                         has_events=has_events))
            done += 1
            if progress is not None:
                progress("reconstruct", done, total)
    sweep = []
    for kk in k_sweep:
        row: dict[str, Any] = {"k": float(kk)}
        for use in (False, True):
            img = reconstruct(rec, method="exp", k=kk, cmap=cmap if use else None)[-1]
            r = measure_chart(img, scene, method="exp", with_cmap=use, has_events=has_events)
            tag = "cmap" if use else "raw"
            row[f"snr_db_{tag}"] = r.snr.mean_db if math.isfinite(r.snr.mean_db) else None
            row[f"snr_patches_{tag}"] = r.snr.n_patches
            row[f"dr_db_{tag}"] = r.dr.dr_db
            row[f"dr_steps_db_{tag}"] = r.dr_steps.dr_db
            done += 1
            if progress is not None:
                progress("reconstruct", done, total)
        sweep.append(row)
    frame: list[MethodResult] = []
    frame_meta: dict[str, Any] | None = None
    if frame_camera is not None:
        frame, frame_meta = run_frame_chart(scene, frame_camera,
                                            budget_s=rig.period_us * 1e-6,
                                            rng=np.random.default_rng(seeds[1]))
        if progress is not None:
            progress("frame camera", 1, 1)
    meta = {
        "width": width, "height": height, "n_cycles": n_cycles, "n_flat": n_flat,
        "flat_cycles": flat_cycles, "k": k, "seed": seed, "sensor_seed": sensor_seed,
        "illuminance_lux": illuminance_lux, "flat_density": flat_density,
        "rig": rig.to_metadata(), "sensor": sensor.to_metadata(), "engine": engine,
        "n_events": int(rec.events.size), "readout": rec.metadata.get("readout"),
        "region_shape": list(SNR_REGION_SHAPE), "min_event_fraction": MIN_EVENT_FRACTION,
        "patches_with_events": int(has_events.sum()), "frame_camera": frame_meta,
    }
    return ChartResult(scene=scene, cmap=cmap, results=results, k_sweep=sweep, frame=frame,
                       has_events=has_events, metadata=meta,
                       recording=rec if keep_recording else None)
