"""``asynhdr bench`` (the paper's experiments, one JSON, plots and an HTML report) and
``asynhdr evaluate`` (real HDR scenes against ground truth)."""

from __future__ import annotations

import contextlib
import json
import math
import os
import shlex
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import typer
from rich.markup import escape
from rich.table import Table

from asynhdr.cli._app import app
from asynhdr.cli.core import console, err_console, fail, progress_bar
from asynhdr.report import range_note, scene_table

PRESET_SIZES: dict[str, tuple[int, int]] = {
    "ideal": (640, 480),
    "v2e": (640, 480),
    "davis346": (346, 260),
    "imx636": (1280, 720),
}
"""Sensor size (width, height) of each preset in the full bench: the sensor's own where it
has one (DAVIS346 346x260, IMX636 1280x720), else 640x480."""

QUICK_SIZE = (320, 240)


def _scene_files(paths: list[Path] | None) -> list[Path]:
    if paths:
        return paths
    env = os.environ.get("ASYNHDR_DATA")
    for base in ([Path(env)] if env else []) + [Path.cwd().parent / "shared" / "data",
                                                Path("../shared/data")]:
        d = base / "hdr" / "scenes"
        if d.is_dir():
            return sorted(p for p in d.iterdir() if p.suffix.lower() in (".exr", ".hdr"))
    return []


def _client(stack: contextlib.ExitStack, scheduler: str | None, workers: int | None) -> Any:
    """A dask client entered on ``stack`` for ``--scheduler``, or None."""
    if scheduler is None:
        return None
    from asynhdr.distributed import scheduler_client

    client = stack.enter_context(scheduler_client(scheduler, workers=workers))
    err_console.print(f"on {len(client.scheduler_info()['workers'])} dask workers "
                      f"({scheduler})")
    return client


def _chart_for(preset: str, *, sizes: dict[str, tuple[int, int]], **kwargs: Any) -> Any:
    """The chart experiment of one preset (a task a dask worker can run)."""
    from asynhdr.experiments import run_chart_experiment

    w, h = sizes[preset]
    return run_chart_experiment(width=w, height=h, sensor=preset, **kwargs)


def _evaluate_file(f: Path, **kwargs: Any) -> Any:
    """Read one scene and evaluate it (a task a dask worker can run)."""
    from asynhdr.evaluate import evaluate_scene
    from asynhdr.io.images import read_radiance

    radiance, info = read_radiance(f)
    if info.get("clipped_negative"):
        err_console.print(f"{f}: {info['clipped_negative']} negative pixels clipped to 0")
    return evaluate_scene(radiance, name=f.stem, **kwargs)


def _run_scenes(files: list[Path], out: Path, *, width: int, height: int, preset: str,
                scale: float | None, n_cycles: int, frame_camera: str, seed: int,
                sensor_seed: int, update: Any, rig: Any = None,
                methods: tuple[str, ...] | None = None, client: Any = None,
                ) -> tuple[list[dict[str, Any]], dict[str, str]]:
    from asynhdr.distributed import map_ordered
    from asynhdr.evaluate import calibrate_for_scenes
    from asynhdr.io.images import write_image
    from asynhdr.plots import plot_error_maps, plot_mosaic

    cmap = calibrate_for_scenes(width=width, height=height, sensor=preset,
                                sensor_seed=sensor_seed, rig=rig)
    more: dict[str, Any] = {"rig": rig}
    if methods:
        more["methods"] = methods
    from asynhdr.evaluate import ML_FAST, calibrate_thresholds_for_scenes

    if rig is not None and {"ml", ML_FAST} & set(methods or ("ml",)):

        more["ml_calibration"] = calibrate_thresholds_for_scenes(
            width=width, height=height, sensor=preset, rig=rig, sensor_seed=sensor_seed)
    summaries: list[dict[str, Any]] = []
    figures: dict[str, str] = {}
    kw: dict[str, Any] = dict(width=width, height=height, sensor=preset, scale=scale,
                              cmap=cmap,
              n_cycles=n_cycles, frame_camera=frame_camera, seed=seed,
              sensor_seed=sensor_seed, **more)
    evaluations: Iterator[Any]
    if client is None:
        evaluations = (_evaluate_file(f, progress=update, **kw) for f in files)
    else:  # the scenes on the workers, results in order
        evaluations = iter(map_ordered(client, _evaluate_file, files, **kw))
    for i, (f, ev) in enumerate(zip(files, evaluations, strict=True)):
        summaries.append(ev.summary())
        y0, y1, x0, x1 = ev.metadata["region"]
        truth = ev.scene.radiance[y0:y1, x0:x1]
        picks = [("truth (scene)", truth)] + [
            (f"{m}: {ev.metrics[m].pu21_psnr_db:.1f} dB, {1000 * ev.capture_s[m]:.0f} ms",
             img[y0:y1, x0:x1]) for m, img in ev.images.items()]
        fig = out / "scenes" / f"{f.stem}.png"
        plot_mosaic([p[1] for p in picks], [p[0] for p in picks], fig, columns=5,
                    reference=truth)
        figures[f"scene/{f.stem}"] = os.path.relpath(fig, out)
        err_fig = out / "scenes" / f"{f.stem}_error.png"
        plot_error_maps([img[y0:y1, x0:x1] for img in ev.images.values()],
                        [f"{m}: {ev.metrics[m].log_rmse_stops:.3f} stops"
                         for m in ev.images], truth, err_fig, columns=5,
                        outside=None if ev.beyond_range is None
                        else ev.beyond_range[y0:y1, x0:x1])
        figures[f"scene/{f.stem}/error"] = os.path.relpath(err_fig, out)
        write_image(out / "scenes" / f"{f.stem}_truth.exr", ev.scene.radiance,
                    metadata={"unit": "lux", "scale": ev.metadata["scale"]})
        for m, img in ev.images.items():
            write_image(out / "scenes" / f"{f.stem}_{m}.exr", img,
                        metadata={"unit": "lux", "method": m, "scaled_to_truth": True})
        update("scenes", i + 1, len(files))
    return summaries, figures


def _print_scenes(summaries: list[dict[str, Any]]) -> None:
    for sc in summaries:
        md = sc["metadata"]
        note = range_note(md)
        t = Table(title=f"{sc['name']}: against the scene (one global scale per image); "
                  f"span {md['span_stops']:.1f} stops, scale {md['scale']:.4g}",
                  caption=note)
        head, rows = scene_table(sc)
        for h in head:
            t.add_column(h, justify="right" if h != "method" else "left")
        for r in rows:
            t.add_row(escape(r[0]), *r[1:])
        console.print(t)


@app.command()
def evaluate(
    scenes: list[Path] = typer.Argument(..., help="HDR radiance maps (.exr .hdr .npy .tif)."),
    out: Path = typer.Option(Path("out/evaluate"), help="Output folder."),
    width: int = typer.Option(640, help="Sensor width (pixels)."),
    height: int = typer.Option(480, help="Sensor height (pixels)."),
    preset: str = typer.Option("v2e", help="Event sensor preset."),
    frame_camera: str = typer.Option("imx174", help="Frame camera preset: imx174 | ideal."),
    scale: float | None = typer.Option(None, help="Multiply the file's values by this to get "
                                       "lux (default: automatic exposure, the scene's "
                                       "log-average at the middle of the rig's range)."),
    n_cycles: int = typer.Option(2, help="Cycles to simulate (the last is measured)."),
    seed: int = typer.Option(0, help="Seed of the captures' randomness."),
    sensor_seed: int = typer.Option(1, help="Seed of the sensor's frozen mismatch."),
    rig_file: Path | None = typer.Option(None, "--rig", help="Rig file (TOML), e.g. from "
                                         "'asynhdr design' (default: the paper's rig)."),
    designed: bool = typer.Option(False, "--designed", help="Use the preset's designed rig "
                                  "(asynhdr.design.DESIGNED) instead of the paper's."),
    methods: str | None = typer.Option(None, help="Comma-separated event methods (default: "
                                       "raw,linear,exp,ttfe,invert,ml; also "
                                       "ml-uncalibrated: ml as 'asynhdr reconstruct' runs "
                                       "it without a calibration; ml-fast: its fast fit "
                                       "with the calibration, needs --designed or --rig)."),
    scheduler: str | None = typer.Option(None, help="Evaluate the scenes on dask workers: "
                                         "'local' or a scheduler's address."),
    workers: int | None = typer.Option(None, help="With --scheduler local: worker "
                                       "processes (default: one per core)."),
) -> None:
    """Simulate and reconstruct real HDR scenes with every method, image them with a frame
    camera (single exposure, Debevec fusion of 10 exposures and of one cycle's worth), and
    measure all against the scene: log RMSE, relative error, PU21-PSNR, SSIM."""
    from asynhdr._atomic import atomic_path
    from asynhdr.framecam import get_frame_camera
    from asynhdr.sensor.params import get_preset

    t0 = time.perf_counter()
    try:
        get_preset(preset)
        get_frame_camera(frame_camera)
        if scale is not None and not (scale > 0 and math.isfinite(scale)):
            fail(f"--scale must be a positive number, got {scale}")
        rig = None
        if rig_file is not None:
            from asynhdr.io.rigfile import read_rig

            rig = read_rig(rig_file).rig
        elif designed:
            from asynhdr.design import default_rig

            rig = default_rig(preset)
        meths = tuple(m.strip() for m in methods.split(",") if m.strip()) if methods else None
        if meths:
            from asynhdr.evaluate import ML_FAST, ML_UNCALIBRATED
            from asynhdr.reconstruct import METHODS

            known = (*METHODS, ML_UNCALIBRATED, ML_FAST)
            bad = [m for m in meths if m not in known]
            if bad:
                fail(f"--methods: unknown {', '.join(bad)}; known: {', '.join(known)}")
            if ML_FAST in meths and rig is None:
                fail(f"--methods {ML_FAST}: the fast fit holds the calibration's thresholds, "
                     "and the scenes are calibrated for a rig: add --designed or --rig")
        with contextlib.ExitStack() as stack, progress_bar() as update:
            client = _client(stack, scheduler, workers)
            summaries, _ = _run_scenes(scenes, out, width=width, height=height, preset=preset,
                                       scale=scale, n_cycles=n_cycles,
                                       frame_camera=frame_camera, seed=seed,
                                       sensor_seed=sensor_seed, update=update, rig=rig,
                                       methods=meths, client=client)
    except (ValueError, FileNotFoundError) as exc:
        fail(str(exc))
    _print_scenes(summaries)
    with atomic_path(out / "evaluate.json") as tmp:
        tmp.write_text(json.dumps({"scenes": summaries,
                                   "wall_s": time.perf_counter() - t0}, indent=1))
    console.print(f"{len(summaries)} scene(s); figures and images in {out}/scenes, figures "
                  f"in {out}/evaluate.json ({time.perf_counter() - t0:.1f} s)")


@app.command()
def bench(
    out: Path = typer.Option(Path("out/bench"), help="Output folder."),
    quick: bool = typer.Option(False, "--quick", help="Small run: 320x240 for every preset, "
                               "2 cycles, 2 flat fields, k in 1,2,5,10,20; scenes at 320x240."),
    presets: str = typer.Option("ideal,v2e,davis346,imx636", help="Comma-separated presets."),
    scenes: list[Path] | None = typer.Option(None, "--scene", help="HDR scenes to evaluate "
                                             "(default: $ASYNHDR_DATA/hdr/scenes or "
                                             "../shared/data/hdr/scenes when present)."),
    no_scenes: bool = typer.Option(False, "--no-scenes", help="Skip the HDR scenes."),
    scene_preset: str = typer.Option("v2e", help="Event sensor preset for the scenes."),
    frame_camera: str = typer.Option("imx174", help="Frame camera preset."),
    seed: int = typer.Option(0, help="Seed of the captures' randomness."),
    sensor_seed: int = typer.Option(1, help="Seed of the sensors' frozen mismatch."),
    scheduler: str | None = typer.Option(None, help="Run the presets and scenes on dask "
                                         "workers: 'local' or a scheduler's address."),
    workers: int | None = typer.Option(None, help="With --scheduler local: worker "
                                       "processes (default: one per core)."),
) -> None:
    """The paper's experiments in simulation: the 36-level chart for every preset and
    every method with and without c-map (SNR table, both dynamic ranges, response,
    radiometric error, grey levels), the k sweep, a frame camera with multi-exposure
    fusion, and real HDR scenes against ground truth. Writes bench.json, plots, images
    and report.html."""
    from asynhdr._atomic import atomic_path
    from asynhdr.experiments import PAPER_DR_DB, PAPER_SNR_DB, run_chart_experiment
    from asynhdr.plots import (
        plot_chart_response,
        plot_input_snr,
        plot_k_sweep,
        plot_mosaic,
        plot_snr_per_level,
    )
    from asynhdr.report import render_report, write_report
    from asynhdr.sensor.params import get_preset

    t0 = time.perf_counter()
    names = [p.strip() for p in presets.split(",") if p.strip()]
    try:
        for p in names:
            get_preset(p)
    except ValueError as exc:
        fail(str(exc))
    ks = [1.0, 2.0, 5.0, 10.0, 20.0] if quick else [float(k) for k in range(1, 21)]
    n_cycles, n_flat = (2, 2) if quick else (3, 4)
    files = [] if no_scenes else _scene_files(scenes)
    settings: dict[str, Any] = {
        "command": "asynhdr " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
        "quick": quick, "presets": names, "k_sweep": ks, "n_cycles": n_cycles,
        "n_flat": n_flat, "frame_camera": frame_camera, "seed": seed,
        "sensor_seed": sensor_seed, "scene_preset": scene_preset,
        "scenes": [str(f) for f in files],
        "sizes": {p: (QUICK_SIZE if quick else PRESET_SIZES.get(p, (640, 480)))
                  for p in names},
    }
    out.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {"settings": settings, "presets": {},
                               "paper": {"snr_db": PAPER_SNR_DB, "dr_db": PAPER_DR_DB},
                               "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    figures: dict[str, str] = {}
    sweeps: dict[str, list[dict[str, Any]]] = {}
    try:
        with contextlib.ExitStack() as stack, progress_bar() as update:
            client = _client(stack, scheduler, workers)
            common: dict[str, Any] = dict(n_cycles=n_cycles, n_flat=n_flat, k_sweep=ks,
                          frame_camera=frame_camera, seed=seed, sensor_seed=sensor_seed)
            spread = None
            if client is not None:  # every preset on a worker, results in order
                from asynhdr.distributed import map_ordered

                spread = iter(map_ordered(client, _chart_for, names, sizes=settings["sizes"],
                                          **common))
            for p in names:
                w, h = settings["sizes"][p]
                def stage(st: str, d: int, t: int, p: str = p) -> None:
                    update(f"{p}: {st}", d, t)

                res = next(spread) if spread is not None else run_chart_experiment(
                    width=w, height=h, sensor=p, progress=stage, **common)
                summary["presets"][p] = res.summary()
                sweeps[p] = res.k_sweep
                d = out / p
                for key, fn in (("response", plot_chart_response), ("snr", plot_snr_per_level),
                                ("input_snr", plot_input_snr)):
                    figures[f"{p}/{key}"] = os.path.relpath(fn(res, d / f"{key}.png"), out)
                picks = [("truth", res.scene.radiance)] + [
                    (f"{r.method}{' + c-map' if r.with_cmap else ''}", r.image)
                    for r in (*res.results, *res.frame)
                    if r.with_cmap or r.method in ("raw", "exp") or r.method.startswith("mef")]
                figures[f"{p}/mosaic"] = os.path.relpath(plot_mosaic(
                    [q[1] for q in picks], [q[0] for q in picks], d / "mosaic.png",
                    columns=5), out)
                del res
            figures["k_sweep"] = os.path.relpath(plot_k_sweep(sweeps, out / "k_sweep.png"), out)
            if files:
                sw, sh = QUICK_SIZE if quick else (640, 480)
                summary["scenes"], scene_figs = _run_scenes(
                    files, out, width=sw, height=sh, preset=scene_preset, scale=None,
                    n_cycles=2, frame_camera=frame_camera, seed=seed,
                    sensor_seed=sensor_seed, update=update, client=client)
                figures.update(scene_figs)
    except ValueError as exc:
        fail(str(exc))
    summary["wall_s"] = time.perf_counter() - t0
    summary["figures"] = figures
    with atomic_path(out / "bench.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=1, default=str))
    report = write_report(out / "report.html", render_report(summary, figures))

    t = Table(title=escape("Mean patch SNR (dB), no c-map / with c-map [responding patches "
                           "with noise (+ without)], and DR with c-map: EMVA / paper's steps "
                           "(dB)"))
    t.add_column("method")
    for p in names:
        t.add_column(f"{p} SNR", justify="right")
        t.add_column(f"{p} DR", justify="right")
    t.add_column("paper", justify="right")

    def get(p: str, m: str, cm: bool) -> dict[str, Any] | None:
        ch = summary["presets"][p]
        for r in ch["methods"]:
            if r["method"] == m and r["with_cmap"] == cm:
                return dict(r)
        for r in ch["frame_camera"]:
            if r["method"] == m:
                return dict(r)
        return None

    def snr(r: dict[str, Any] | None) -> str:
        if r is None:
            return "-"
        v = r["mean_snr_db"]
        n = f"{r['snr_patches']}" + (f"+{r['snr_noiseless_patches']}"
                                     if r.get("snr_noiseless_patches") else "")
        return (f"{v:.2f}" if isinstance(v, float) else str(v or "-")) + escape(f"[{n}]")

    for m in ("raw", "linear", "quadratic", "poly5", "exp", "ttfe", "count", "invert",
              "mef-10", "mef-budget"):
        row = [m]
        for p in names:
            a, b = get(p, m, False), get(p, m, True)
            row.append(snr(a) if m.startswith("mef") else f"{snr(a)} / {snr(b)}")
            row.append("-" if b is None else f"{b['dr_db']:.1f} / {b['dr_steps_db']:.1f}")
        pv = PAPER_SNR_DB.get(m)
        row.append((f"{pv[0]:.2f} / {pv[1]:.2f}" if pv else "-") +
                   (f"; DR {PAPER_DR_DB}" if m == "exp" else ""))
        t.add_row(*row)
    console.print(t)
    if files:
        _print_scenes(summary.get("scenes", []))
    console.print(f"bench: {time.perf_counter() - t0:.0f} s; report {report}, figures "
                  f"{out / 'bench.json'}")
