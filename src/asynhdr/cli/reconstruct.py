"""``asynhdr reconstruct`` and ``asynhdr calibrate``: files in, images or a c-map out."""

from __future__ import annotations

import contextlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import typer

from asynhdr.cli._app import app
from asynhdr.cli.core import (
    IMAGE_FORMATS,
    TIME_UNIT_HELP,
    _parse_formats,
    check_outputs,
    check_period,
    console,
    fail,
    progress_bar,
)
from asynhdr.reconstruct import DEFAULT_K, DEFAULT_METHOD, METHODS
from asynhdr.sensor.params import SensorParams

__all__ = ["calibrate", "reconstruct"]


def _open(path: Path, **source_options: Any) -> Any:
    from asynhdr.io import open_source

    try:
        return open_source(path, **source_options)
    except (ValueError, OSError) as exc:
        fail(str(exc))


@app.command()
def reconstruct(
    recording: Path = typer.Argument(..., help="Event recording (any supported format)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
    method: str = typer.Option(DEFAULT_METHOD, help=" | ".join(METHODS) + "."),
    k: float = typer.Option(DEFAULT_K, help="k of the exponential weighting."),
    cmap: Path | None = typer.Option(None, help="c-map from 'asynhdr calibrate'."),
    threshold_on: float | None = typer.Option(
        None, help="ON contrast threshold (default: the recording's sensor, else "
        f"{SensorParams.threshold_on:g})."),
    threshold_off: float | None = typer.Option(
        None, help="OFF contrast threshold (default: the recording's sensor, else "
        f"{SensorParams.threshold_off:g})."),
    window_us: float | None = typer.Option(None, help="Integration window after each cycle "
                                           "start (default: the ramp, else the period)."),
    period_us: float | None = typer.Option(None, help="Modulation period in µs, when known "
                                           "(needed with fewer than two trigger edges)."),
    single: bool = typer.Option(False, "--single", help="Treat the whole recording as one "
                                "cycle (a single ramp, e.g. a temporal-mapping capture), "
                                "from the rising trigger edge that opens it, else from its "
                                "first event."),
    skip_warmup: bool = typer.Option(False, "--skip-warmup", help="Leave out a warm-up "
                                     "cycle (the first, when the modulation starts with the "
                                     "recording)."),
    width: int | None = typer.Option(None, help="Sensor width, for files without geometry."),
    height: int | None = typer.Option(None, help="Sensor height, for files without geometry."),
    time_unit: str | None = typer.Option(None, "--time-unit", help=TIME_UNIT_HELP),
    formats: str = typer.Option("exr,png", help=f"Comma-separated, from {IMAGE_FORMATS}."),
    tonemap: str = typer.Option("log", help="PNG tone mapping: log | reinhard | linear."),
    demosaic: str = typer.Option("malvar", help="Colour recordings (a CFA in the metadata): "
                                 "malvar | bilinear | none (write the raw mosaic)."),
    scheduler: str | None = typer.Option(None, help="Spread the cycles over dask workers: "
                                         "'local' (a cluster on this machine) or a "
                                         "scheduler's address; same images as without, "
                                         "except that ml without --calibration learns "
                                         "the thresholds within each worker's cycles."),
    workers: int | None = typer.Option(None, help="With --scheduler local: worker "
                                       "processes (default: one per core)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing images."),
    rig: Path | None = typer.Option(None, "--rig", help="Rig file (TOML, from 'asynhdr "
                                    "design' or 'simulate --rig-out'): the rig and sensor "
                                    "of a real recording, for ml, invert and ttfe."),
    calibration: Path | None = typer.Option(None, "--calibration", help="Calibration file "
                                            "(.npz, asynhdr.calib) with per-pixel ON and OFF "
                                            "thresholds, for ml."),
    fast: bool = typer.Option(False, "--fast", help="ml's fast fit: ln L alone, each "
                              "pixel's thresholds held at the calibration's, or (without "
                              "--calibration) once learned from the cycles before; 5x to 9x "
                              "faster on the bench (docs/ml.md)."),
) -> None:
    """Reconstruct one HDR image per modulation cycle.

    Cycles come from the trigger edges, else (simulated recordings) the rig, else the
    event-rate envelope; when none are found nothing is written. The file is read one
    cycle at a time (memory flat in file size) after the passes that find its cycles.
    """
    from asynhdr.cli._colour import DEMOSAIC_CHOICES, write_colour
    from asynhdr.io.cmap import load_cmap
    from asynhdr.io.images import write_image
    from asynhdr.reconstruct import reconstruct_cycles
    from asynhdr.segment import NoCyclesError

    fmts = _parse_formats(formats)
    if demosaic not in DEMOSAIC_CHOICES:
        fail(f"--demosaic: expected one of {DEMOSAIC_CHOICES}, got {demosaic!r}")
    if method not in METHODS:
        fail(f"--method: unknown method {method!r}; choose from {list(METHODS)}")
    from asynhdr.tonemap import TONEMAP_METHODS

    if tonemap not in TONEMAP_METHODS:
        fail(f"--tonemap: expected one of {list(TONEMAP_METHODS)}, got {tonemap!r}")
    check_period(period_us)
    if method == "ml" and "hdr" in fmts:
        fail("--formats hdr: Radiance .hdr holds no NaN, and ml marks the pixels without "
             "information NaN; use exr, tif or npy")
    if out.exists() and not out.is_dir():
        fail(f"{out}: exists and is not a folder; --out names the folder for the images")
    stem = f"{recording.stem}_{method}_"
    existing = sorted(out.glob(f"{stem}[0-9][0-9][0-9][0-9].*")) if out.is_dir() else []
    check_outputs([*existing, out / f"{stem}0000.{fmts[0]}"], overwrite=overwrite)
    source_options: dict[str, Any] = dict(width=width, height=height, time_unit=time_unit)
    src = _open(recording, **source_options)
    m = METHODS[method]
    meta: dict[str, Any] = {"source": str(recording), "method": method, "k": k,
                            "cmap": str(cmap) if cmap else None, "radiometric": m.radiometric}
    from asynhdr.cli.ml_support import MlOutputs

    if calibration is not None and method != "ml":
        fail(f"--calibration: per-pixel thresholds are for --method ml, not {method} (the "
             "paper's weightings take a c-map: --cmap)")
    if cmap is not None and method == "ml":
        fail("--cmap: ml takes per-pixel thresholds from --calibration, not a c-map")
    if fast and method != "ml":
        fail(f"--fast: the fast fit is ml's, not {method}'s")
    mlo = MlOutputs.open(rig, calibration, method=method, formats=fmts, fail=fail)
    if mlo.thresholds is not None and src.width is not None and \
            mlo.thresholds[0].shape != (src.height, src.width):
        hc, wc = mlo.thresholds[0].shape
        fail(f"{calibration}: thresholds of a {wc}x{hc} sensor; {recording} is "
             f"{src.width}x{src.height}")
    if rig is not None:
        meta["rig"] = str(rig)
    opts = mlo.options
    if opts is not None and single:  # one ramp from rest: the pixels start on their reference
        opts["settled_start"] = True
    if opts is not None and fast:
        from asynhdr.ml import FAST_HOLD_SD

        opts["fast"] = True
        meta["ml_fit"] = ("fast: ln L alone, the calibration's thresholds held"
                          if calibration is not None else
                          "fast: ln L alone, the thresholds held once learned from the "
                          f"cycles before (to {FAST_HOLD_SD:g}); the rest fitted in full")
    try:
        cm = load_cmap(cmap) if cmap is not None else None
        with contextlib.ExitStack() as stack, progress_bar() as update:
            # one set of options for the serial and the distributed run
            common: dict[str, Any] = dict(method=method, k=k, threshold_on=threshold_on,
                                          threshold_off=threshold_off, rig=mlo.rig,
                                          ml_options=opts)
            serial = dict(common)
            if opts is not None and scheduler is None:
                # the fits' progress within each cycle (a callback stays on this machine)
                serial["ml_options"] = dict(opts, progress=update)
            plan = reconstruct_cycles(src, cmap=cm, window_us=window_us, period_us=period_us,
                                      single=single, progress=update, **serial)
            unit = mlo.unit or plan.metadata.get("radiance_unit", "relative")
            warm = plan.windows.warmup
            colour = bool(plan.metadata.get("cfa")) and demosaic != "none"
            images: Iterable[tuple[int, int, np.ndarray]] = plan
            if scheduler is not None:
                from asynhdr.distributed import reconstruct_distributed, scheduler_client

                client = stack.enter_context(scheduler_client(scheduler, workers=workers))
                images = reconstruct_distributed(
                    client, recording, plan.windows, cmap=cmap, progress=update,
                    source_options=source_options, **common)
            written = 0
            for i, _, img in images:
                if skip_warmup and i < warm:
                    continue
                info = dict(meta, cycle=i, unit=unit, warmup=i < warm)
                if mlo.active:
                    mlo.write(out / f"{stem}{i:04d}", img, info, tonemap=tonemap)
                elif colour:
                    write_colour(out / f"{stem}{i:04d}", img, plan.metadata, fmts,
                                 method=demosaic, tonemap=tonemap, extra=info)
                else:
                    for f in fmts:
                        write_image(out / f"{stem}{i:04d}.{f}", img,
                                    metadata=info if f in ("exr", "tif") else None,
                                    tonemap=tonemap)
                written += 1
    except NoCyclesError as exc:
        hint = "--single" if period_us is not None else "--period-us or --single"
        fail(f"{recording}: no cycles found ({exc.reason}); pass {hint}; nothing written")
    except (ValueError, OSError) as exc:
        fail(str(exc))
    note = ""
    if warm and not skip_warmup:
        note = (" (cycle 0 is a warm-up cycle: the modulation starts with the recording, so "
                "its pixels start from another state and its image differs; --skip-warmup "
                "leaves it out)")
    if colour and mlo.active:
        note += (f"; colour recording (CFA {plan.metadata['cfa']}): ml's images are the "
                 "mosaic, one radiance per pixel, not demosaiced")
    elif colour:
        note += (f"; colour recording (CFA {plan.metadata['cfa']}): demosaiced ({demosaic}) "
                 "to RGB")
    console.print(f"{written} image{'s' if written != 1 else ''} ({method}) from "
                  f"{plan.n_events:,} events, one cycle at a time -> {out}/{note}")
    if mlo.active and mlo.pixels:
        console.print(f"ml: {mlo.valid:,} of {mlo.pixels:,} pixels estimated in the last "
                      f"image ({100.0 * mlo.valid / mlo.pixels:.2f} %), {mlo.few:,} of them "
                      "from fewer than two events (128 in _valid.png); the rest are NaN or "
                      "hold a bound of the model's range (0)")
    if mlo.active and mlo.pixels and mlo.full_fits is not None:
        console.print(f"ml --fast: {mlo.pixels - mlo.full_fits:,} of {mlo.pixels:,} pixels "
                      f"fitted fast in the last image, {mlo.full_fits:,} in full (thresholds "
                      "not yet learned, or a failed check; docs/ml.md)")
    if mlo.active and mlo.defects is not None:
        console.print(f"ml: {int(mlo.defects.sum()):,} dead pixels in the calibration; "
                      f"{mlo.filled:,} of them filled from their neighbours in the last image "
                      "(0 in _valid.png)")
    elif mlo.active and mlo.filled:
        console.print(f"ml: {mlo.filled:,} silent pixels taken for dead (their neighbours say "
                      "they would have fired), filled from their neighbours in the last image "
                      "(0 in _valid.png)")
    if method == "ml" and calibration is None:
        from asynhdr.ml import sensor_of

        sensor = mlo.sensor or sensor_of(plan.metadata)
        if sensor.threshold_sigma > 0:
            learned = ""
            if len(plan) > 1:
                learned = (" and learned from cycle to cycle ("
                           + ("" if fast else "the first cycle fitted again with what the "
                              "second taught; ")
                           + "later cycles are the better for it)")
            console.print(f"ml: no --calibration, so every pixel's thresholds were fitted "
                          f"from its own events, starting from the nominal "
                          f"{sensor.threshold_on:.3g} / {sensor.threshold_off:.3g} (mismatch "
                          f"{sensor.threshold_sigma:g}){learned}; thresholds calibrated from "
                          "flat fields (asynhdr calibrate-thresholds) widen the range "
                          "(docs/ml.md)"
                          + ("; --fast fitted in full the pixels whose thresholds were not "
                             "yet learned (all of them in the first cycle)" if fast else ""))


@app.command()
def calibrate(
    flats: list[Path] = typer.Argument(..., help="Flat-field recordings of one sensor."),
    out: Path = typer.Option(..., "--out", "-o", help="c-map to write (.npz)."),
    k: float = typer.Option(DEFAULT_K, help="k of the exponential weighting."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing c-map."),
) -> None:
    """Estimate the c-map (per-pixel threshold correction) from flat-field recordings."""
    from asynhdr.calibrate import cmap_key, estimate_cmap
    from asynhdr.io.cmap import save_cmap
    from asynhdr.segment import NoCyclesError

    if out.suffix.lower() != ".npz":
        fail(f"{out}: a c-map is written as .npz")
    check_outputs([out], overwrite=overwrite)
    sources = [_open(f) for f in flats]
    try:
        with progress_bar() as update:
            cmap = estimate_cmap(sources, k=k, progress=update)
        cmap.metadata["sources"] = [str(f) for f in flats]
        save_cmap(out, cmap, overwrite=overwrite)
    except NoCyclesError as exc:
        fail(f"no cycles found ({exc.reason}); flat fields must be modulated recordings")
    except (ValueError, OSError) as exc:
        fail(str(exc))
    ex = cmap.maps[cmap_key("exp", k=k)]
    console.print(f"c-map from {len(flats)} captures ({cmap.metadata['n_cycles']} cycles): "
                  f"{', '.join(cmap.maps)}; exp map spread (std) {float(np.std(ex)):.4f} -> {out}")
