"""``asynhdr demo`` and ``simulate``; the helpers every command shares (errors that name
flags, the progress bar, output checks)."""

from __future__ import annotations

import functools
import inspect
import json
import math
import re
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn
from rich.progress import Progress as RichProgress
from rich.table import Table

from asynhdr.cli._app import app
from asynhdr.reconstruct import DEFAULT_K
from asynhdr.rig import Rig
from asynhdr.simulate import simulate as _simulate
from asynhdr.source import Progress


def _default(func: Any, name: str) -> Any:
    """The default of ``func``'s parameter ``name``, where it is written once."""
    return inspect.signature(func).parameters[name].default

console = Console(width=None if sys.stdout.isatty() else 150)
err_console = Console(stderr=True, width=None if sys.stderr.isatty() else 110)

IMAGE_FORMATS = ("exr", "hdr", "npy", "png", "tif")


@functools.cache
def _option_flags() -> dict[str, str]:
    """Python name -> flag of every option of every command (``period_us`` ->
    ``--period-us``)."""
    group = typer.main.get_command(app)
    flags: dict[str, str] = {}
    for cmd in getattr(group, "commands", {}).values():
        for p in cmd.params:
            opts = [o for o in getattr(p, "opts", []) if o.startswith("--")]
            if p.name and opts and getattr(p, "param_type_name", "") == "option":
                flags.setdefault(p.name, max(opts, key=len))
    return flags


def as_flags(msg: str) -> str:
    """``msg`` with the library's parameter names turned into the command line's flags:
    ``period_us`` -> ``--period-us``, ``single=True`` -> ``--single``, ``width=...`` ->
    ``--width ...`` (names with an underscore, and ``name=True`` or ``name=...``, so that
    ordinary words stay as they are)."""
    for name, flag in _option_flags().items():
        msg = re.sub(rf"(?<![\w-]){re.escape(name)}=(True|False)(?![\w-])", flag, msg)
        msg = re.sub(rf"(?<![\w-]){re.escape(name)}=\.\.\.", f"{flag} ...", msg)
        if "_" in name:
            msg = re.sub(rf"(?<![\w-]){re.escape(name)}(?![\w-])", flag, msg)
    return msg


def fail(msg: str) -> NoReturn:
    """Print an error (library parameter names as this command's flags) and exit with
    status 2. The message is one line, never broken by the console (a file's path in it
    stays whole for whoever copies it or searches a log)."""
    err_console.print(f"[bold red]error:[/] {escape(as_flags(msg))}", highlight=False,
                      soft_wrap=True)  # the message as written: "[x]" in it is not markup
    raise typer.Exit(code=2)


@contextmanager
def progress_bar() -> Iterator[Progress]:
    """A rich progress bar driven by the library's progress protocol
    ``update(stage, done, total)`` (``total`` None: not known)."""
    with RichProgress(TextColumn("{task.description:<22}"), BarColumn(), MofNCompleteColumn(),
                      TimeElapsedColumn(),
                      console=err_console, transient=False) as prog:
        tasks: dict[str, Any] = {}

        def update(stage: str, done: int, total: int | None) -> None:
            if stage not in tasks:
                tasks[stage] = prog.add_task(stage, total=total)
            prog.update(tasks[stage], completed=done, total=total)

        yield update


def check_outputs(paths: list[Path], *, overwrite: bool) -> None:
    """Before any work: every output can be written; an existing one only with
    ``--overwrite`` (and never a read-only one). Exits with a message otherwise."""
    from asynhdr._atomic import check_output

    for p in paths:
        try:
            check_output(p, overwrite=overwrite)
        except FileExistsError:
            fail(f"{p}: exists; pass --overwrite to replace it")
        except ValueError as exc:
            fail(str(exc))


TIME_UNIT_HELP = "Text/HDF5 time unit: us, ms, s (text: also auto)."


def check_period(period_us: float | None) -> None:
    """``--period-us``, when given, is a positive number of µs (else the error)."""
    if period_us is not None and not (math.isfinite(period_us) and period_us > 0):
        fail(f"--period-us must be a positive number of µs, got {period_us}")


def _parse_formats(formats: str) -> list[str]:
    out = [f.strip().lower().lstrip(".") for f in formats.split(",") if f.strip()]
    bad = [f for f in out if f not in IMAGE_FORMATS]
    if bad:
        fail(f"--formats: unknown image format(s) {bad}; choose from {list(IMAGE_FORMATS)}")
    return out


def _write_images(img: np.ndarray, stem: Path, formats: list[str], meta: dict[str, Any]) -> None:
    from asynhdr.io.images import write_image

    for f in formats:
        write_image(Path(f"{stem}.{f}"), img, metadata=meta if f != "png" else None)


# --------------------------------------------------------------------------- demo


@app.command()
def demo(
    out: Path = typer.Option(Path("out/demo"), help="Output folder."),
    width: int = typer.Option(640, help="Sensor width (pixels)."),
    height: int = typer.Option(480, help="Sensor height (pixels)."),
    preset: str = typer.Option(_default(_simulate, "sensor"),
                               help="Sensor preset: ideal | v2e | imx636 | davis346."),
    compare: str | None = typer.Option(None, help="A second preset whose SNR columns are "
                                       "printed beside the first (e.g. ideal)."),
    engine: str = typer.Option(_default(_simulate, "engine"),
                               help="Simulator engine: auto (exact for a static scene, "
                               "stepped for a moving one) | exact | stepped."),
    n_cycles: int = typer.Option(3, help="Chart cycles to simulate."),
    n_flat: int = typer.Option(4, help="Flat-field captures for the c-map."),
    k: float = typer.Option(DEFAULT_K, help="k of the exponential weighting 2^(-k t)."),
    seed: int = typer.Option(0, help="Seed of each capture's randomness."),
    sensor_seed: int = typer.Option(1, help="Seed of the sensor's frozen mismatch."),
) -> None:
    """Simulate the paper's step chart, calibrate a c-map, reconstruct with every method,
    and print the SNR table and the dynamic range beside the paper's."""
    from asynhdr.experiments import PAPER_DR_DB, PAPER_SNR_DB, run_chart_experiment
    from asynhdr.io.cmap import save_cmap
    from asynhdr.io.images import write_image
    from asynhdr.plots import plot_chart_response, plot_mosaic, plot_snr_per_level
    from asynhdr.reconstruct import WEIGHTINGS
    from asynhdr.sensor.params import get_preset

    try:
        sensor = get_preset(preset)
        other = get_preset(compare) if compare else None
    except ValueError as exc:
        fail(str(exc))
    t0 = time.perf_counter()
    console.print(f"[bold]asynhdr demo[/]: step chart (36 levels, 160,000 lux), "
                  f"{width}x{height} sensor '{preset}', {n_cycles} cycles, "
                  f"c-map from {n_flat} flat fields")
    try:
        with progress_bar() as update:
            res = run_chart_experiment(width=width, height=height, sensor=sensor,
                                       n_cycles=n_cycles, n_flat=n_flat, k=k, seed=seed,
                                       sensor_seed=sensor_seed, engine=engine,
                                       progress=update)
            ref = None
            if other is not None:
                ref = run_chart_experiment(
                    width=width, height=height, sensor=other, n_cycles=n_cycles,
                    n_flat=n_flat, k=k, seed=seed, sensor_seed=sensor_seed, engine=engine,
                    progress=lambda st, d, t: update(f"{other.name}: {st}", d, t))
    except ValueError as exc:
        fail(str(exc))
    out.mkdir(parents=True, exist_ok=True)
    images_dir = out / "images"
    meta: dict[str, Any] = {"scene": "step_chart", "unit": "lux", "radiometric": False}
    for r in res.results:
        name = r.method + ("_cmap" if r.with_cmap else "")
        info = dict(meta, method=r.method, k=k, with_cmap=r.with_cmap,
                    radiometric=r.method in ("ttfe", "invert"))
        _write_images(r.image, images_dir / name, ["exr", "png"], info)
    write_image(out / "truth.exr", res.scene.radiance, metadata={"unit": "lux"})
    write_image(out / "truth.png", res.scene.radiance)
    save_cmap(out / "cmap.npz", res.cmap)
    plot_snr_per_level(res, out / "snr_per_level.png")
    plot_chart_response(res, out / "chart_response.png")
    picks = [("truth", res.scene.radiance)] + [
        (f"{r.method}{' + c-map' if r.with_cmap else ''}", r.image)
        for r in res.results if r.with_cmap or r.method == "raw"]
    plot_mosaic([p[1] for p in picks], [p[0] for p in picks], out / "mosaic.png")
    summary = res.summary()
    if ref is not None:
        summary["compare"] = ref.summary()
    summary["elapsed_s"] = time.perf_counter() - t0
    from asynhdr._atomic import atomic_path

    with atomic_path(out / "results.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=1))

    table = Table(title="Mean patch SNR (dB) on the 36-level chart, last cycle, central "
                  "16x16 px of each patch, over the patches that respond (no c-map / with "
                  "c-map \\[patches])")
    table.add_column("method")
    table.add_column(f"{preset}", justify="right")
    if ref is not None:
        table.add_column(f"{ref.metadata['sensor']['name']}", justify="right")
    table.add_column("paper", justify="right")
    table.add_column("DR EMVA (dB)", justify="right")
    table.add_column("DR steps (dB)", justify="right")
    table.add_column("rel. error", justify="right")
    table.add_column("grey levels", justify="right")
    if ref is not None:
        table.add_column(f"DR {ref.metadata['sensor']['name']}", justify="right")

    def pair(r: Any, m: str) -> str:
        a, b = r.get(m, False), r.get(m, True)
        def n(s: Any) -> str:
            return f"{s.n_patches}" + (f"+{s.n_noiseless}" if s.n_noiseless else "")

        return (f"{a.snr.mean_db:6.2f} / {b.snr.mean_db:6.2f} "
                f"\\[{n(a.snr)}/{n(b.snr)}]").replace("inf", "  inf")

    for m in (*WEIGHTINGS, "ttfe", "count", "invert"):
        try:
            b = res.get(m, True)
        except KeyError:
            continue
        label = {"ttfe": "ttfe (baseline)", "count": "count (baseline)",
                 "invert": "invert (radiometric)"}.get(m, m)
        row = [label, pair(res, m)]
        if ref is not None:
            row.append(pair(ref, m))
        pa = PAPER_SNR_DB.get(m)
        row.append(f"{pa[0]:6.2f} / {pa[1]:6.2f}" if pa else "-")
        row += [f"{b.dr.dr_db:.1f}", f"{b.dr_steps.dr_db:.1f}",
                f"{b.rel_error_median:.3f}", f"{b.grey_levels}"]
        if ref is not None:
            row.append(f"{ref.get(m, True).dr.dr_db:.1f}")
        table.add_row(*row)
    console.print(table)
    console.print(
        "\\[patches]: patches that respond (at least half the region fired; input-referred "
        f"SNR >= 1) and have noise, of {res.get('exp', True).stats.mean.size} (+N: "
        "responding patches without noise, infinite SNR, left out of the mean). DR EMVA: "
        "20 log10(Lmax/Lmin) over the longest run with input-referred SNR >= 1 and a "
        "strictly monotone response; DR steps: the paper's criterion (neighbouring means "
        "apart by more than both spreads). "
        "DR, rel. error (median relative RMS error against the true radiance after one "
        "global scale) and grey levels (occupied 8-bit log levels) are with the c-map.")
    ro = res.metadata.get("readout") or {}
    if ro.get("emitted"):
        console.print(f"readout ({preset}): {ro['emitted']:,} emitted, {ro['delivered']:,} "
                      f"delivered, {ro['delayed']:,} delayed, {ro['dropped']:,} dropped")
    best = res.get("exp", True)
    console.print(
        f"Dynamic range (exp, k={k:g}, with c-map): [bold]{best.dr.dr_db:.1f} dB[/] EMVA "
        f"({best.dr.l_min:.3g} to {best.dr.l_max:.3g} lux), {best.dr_steps.dr_db:.1f} dB by "
        f"the paper's steps; paper: {PAPER_DR_DB} dB (densities 0.10 to 5.23)")
    snr = res.snr_table()
    order_ok = all(snr[a][1] < snr[b][1] for a, b in
                   zip(list(WEIGHTINGS)[:-1], list(WEIGHTINGS)[1:], strict=True))
    gain_ok = all(v[1] > v[0] for v in snr.values())
    console.print(f"Ordering raw < linear < quadratic < poly5 < exp (with c-map): "
                  f"{'yes' if order_ok else 'no'}; c-map raises every row: "
                  f"{'yes' if gain_ok else 'no'}")
    console.print(f"{res.metadata['n_events']:,} chart events; outputs in {out}/ "
                  f"({time.perf_counter() - t0:.1f} s)")


# --------------------------------------------------------------------------- simulate


def _scene_from_spec(spec: str, width: int, height: int, scale: float | None,
                     target: float = 316.0, cfa: str | None = None) -> Any:
    from asynhdr.scene import exposure_scale, flat_field, from_radiance_map, step_chart

    if cfa is not None:
        if spec == "chart" or spec.startswith("flat:"):
            fail(f"--cfa {cfa}: a colour sensor needs an RGB image, not {spec!r}")
        from asynhdr.cli._colour import colour_scene_from_file

        return colour_scene_from_file(spec, width=width, height=height, scale=scale, cfa=cfa,
                                      target=target)
    if spec == "chart":
        return step_chart(width=width, height=height)
    if spec.startswith("flat:"):
        try:
            value = float(spec[5:])
        except ValueError:
            fail(f"scene {spec!r}: expected flat:RADIANCE with a number, e.g. flat:1600")
        if not (value >= 0 and math.isfinite(value)):
            fail(f"scene {spec!r}: radiance must be finite and >= 0")
        return flat_field(width=width, height=height, radiance=value * (scale or 1.0),
                          unit="lux")
    from asynhdr.io.images import read_radiance

    radiance, info = read_radiance(spec)
    if info.get("clipped_negative"):
        err_console.print(f"{spec}: {info['clipped_negative']} negative pixels clipped to 0")
    if info.get("colour_reduced"):
        err_console.print(f"note: {spec} is a colour image: reduced to luminance (grey "
                          "sensor); --cfa rggb simulates a colour sensor")
    if scale is None:  # automatic exposure: the scene's log-average at the rig's middle
        scale = exposure_scale(radiance, target=target)
        err_console.print(f"{spec}: automatic exposure, x{scale:.4g} to lux (log-average at "
                          f"{target:.4g} lux; --scale to set it)")
    return from_radiance_map(radiance, width=width, height=height, scale=scale,
                             name=Path(spec).stem, unit="lux", fit="pad")


def _moving(sc: Any, spec: str, *, duration_us: float, frame_step_us: float) -> Any:
    """The scene moved by ``--motion VX,VY`` (px/s) over the capture."""
    from asynhdr.scene import moving_scene

    try:
        vx, vy = (float(v) for v in spec.split(","))
    except ValueError:
        fail(f"--motion: expected VX,VY in pixels per second (e.g. 200,0), got {spec!r}")
    if getattr(sc, "cfa", None):
        fail("--motion: a moving colour scene is not supported; drop --cfa/--colour")
    return moving_scene(sc.radiance, velocity_px_per_s=(vx, vy), duration_us=duration_us,
                        frame_step_us=frame_step_us, unit=getattr(sc, "unit", "relative"),
                        name=getattr(sc, "name", ""))


@app.command()
def simulate(
    scene: str = typer.Argument(..., help="'chart' (the paper's step chart), "
                                "'flat:RADIANCE', or an HDR image (.exr .hdr .npy .tif)."),
    out: Path = typer.Option(..., "--out", "-o", help="Recording to write "
                             "(.h5, .npz, .raw EVT 3.0, .txt)."),
    width: int = typer.Option(640, help="Sensor width (pixels)."),
    height: int = typer.Option(480, help="Sensor height (pixels)."),
    preset: str | None = typer.Option(None, help="Sensor preset (default: the rig file's "
                                      f"sensor, else {_default(_simulate, 'sensor')})."),
    n_cycles: int = typer.Option(3, help="Modulation cycles."),
    period_us: int | None = typer.Option(None, help=f"Cycle period (µs); default "
                                         f"{Rig.period_us:,}."),
    ramp_fraction: float | None = typer.Option(None, help="Part of the cycle the ramp takes "
                                               f"(paper rig; default {Rig.ramp_fraction})."),
    t1_shape: str | None = typer.Option(None, help="Scene panel ramp: linear | exponential "
                                        f"(paper rig; default {Rig.t1_shape})."),
    t2_shape: str | None = typer.Option(None, help="Reference panel ramp: linear | "
                                        f"exponential (paper rig; default {Rig.t2_shape})."),
    panel: str = typer.Option(Rig.panel, help="Panels the drive goes through: ideal (the "
                              "target at once) | tn | fast_shutter (real LC panels)."),
    pre_emphasis: bool = typer.Option(Rig.pre_emphasis, help="Design the panels' drive to "
                                      "invert their response (with --panel tn or "
                                      "fast_shutter)."),
    l_const: float | None = typer.Option(None, help="Reference radiance, in the scene's unit "
                                         f"(paper rig; default {Rig.l_const:g})."),
    rig_file: Path | None = typer.Option(None, "--rig", help="Rig file (TOML) to simulate "
                                         "(from 'asynhdr design')."),
    rig_out: Path | None = typer.Option(None, "--rig-out", help="Write the rig (and sensor) "
                                        "as a rig file, for 'reconstruct --rig'."),
    scale: float | None = typer.Option(None, help="Multiply the scene radiance by this "
                                       "(default for HDR images: automatic exposure, the "
                                       "log-average at L_const sqrt(contrast ratio 1))."),
    seed: int = typer.Option(0, help="Seed of this capture's randomness."),
    sensor_seed: int = typer.Option(1, help="Seed of the sensor's frozen mismatch "
                                    "(same seed, same sensor)."),
    engine: str = typer.Option(_default(_simulate, "engine"),
                               help="Simulator engine: auto (exact for a static scene, "
                               "stepped for a moving one) | exact | stepped."),
    dt_us: float = typer.Option(_default(_simulate, "dt_us"),
                                help="Largest step of the time grid (µs)."),
    cfa: str | None = typer.Option(None, "--cfa", help="Colour sensor: a Bayer filter "
                                   "(rggb, bggr, grbg, gbrg) over the pixels; needs an RGB "
                                   "image. Default: grey."),
    colour: bool = typer.Option(False, "--colour", help="Same as --cfa rggb."),
    motion: str | None = typer.Option(None, help="Move the scene across the sensor: "
                                      "VX,VY in pixels per second (a pan); simulated by the "
                                      "stepped engine."),
    frame_step_us: float = typer.Option(1_000.0, help="With --motion: time between the "
                                        "moving scene's frames (µs)."),
    scheduler: str | None = typer.Option(None, help="Spread the sensor over dask workers: "
                                         "'local' (a cluster on this machine) or a "
                                         "scheduler's address; same events as without."),
    workers: int | None = typer.Option(None, help="With --scheduler local: worker "
                                       "processes (default: one per core)."),
    roi: bool = typer.Option(False, "--roi", help="The pixels are a region of interest read "
                             "alone: the readout serves them at its full rate (default: "
                             "they stand for the whole array and get their share of it)."),
    hold: bool = typer.Option(False, "--hold", help="A pixel whose event waits for the "
                              "readout is held until it is read (arbiter 'hold'; default: "
                              "the queue moves timestamps only). Exact engine, one process."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing file."),
) -> None:
    """Simulate a scene seen through the rig and write the recording."""
    from asynhdr.io import write_recording
    from asynhdr.sensor.params import get_preset
    from asynhdr.simulate import simulate as run

    if rig_out is not None and rig_out.resolve() == out.resolve():
        fail(f"--rig-out {rig_out}: the same file as --out; name another")
    check_outputs([out] + ([rig_out] if rig_out is not None else []), overwrite=overwrite)
    try:
        file_sensor = None
        if rig_file is not None:
            given = [f for f, v in (("--period-us", period_us), ("--ramp-fraction", ramp_fraction),
                                    ("--t1-shape", t1_shape), ("--t2-shape", t2_shape),
                                    ("--l-const", l_const)) if v is not None]
            if panel != Rig.panel:
                given.append("--panel")
            if given:
                fail(f"--rig {rig_file}: the rig file sets the rig; leave out "
                     f"{', '.join(given)}")
            from asynhdr.io.rigfile import read_rig

            file_sensor = read_rig(rig_file).sensor
        if file_sensor is not None and preset is not None and preset != file_sensor.name:
            fail(f"--preset {preset}: the rig file {rig_file} is for the {file_sensor.name} "
                 "sensor; leave out --preset (or use another rig file)")
        sensor = file_sensor if file_sensor is not None else get_preset(
            preset or _default(_simulate, "sensor"))
        preset = sensor.name
        rig = _simulate_rig(preset, rig_file, period_us=period_us, ramp_fraction=ramp_fraction,
                            t1_shape=t1_shape, t2_shape=t2_shape, l_const=l_const,
                            panel=panel, pre_emphasis=pre_emphasis)
        if rig_file is None and panel != Rig.panel and all(
                v is None for v in (ramp_fraction, t1_shape, t2_shape, l_const)):
            err_console.print(f"note: --panel {panel}: the paper's rig (L_const "
                              f"{rig.l_const:g}, {rig.t1_shape} ramps), not the "
                              f"{preset} preset's designed rig, which assumes ideal panels")
        seen = sensor.region_of_interest() if roi else sensor
        if hold:
            if engine == "stepped" or (engine == "auto" and motion is not None):
                fail("--hold needs the exact engine (a static scene); the stepped engine "
                     "fires its pixels chunk by chunk")
            seen = seen.with_(name=seen.name, arbiter="hold")
        if scale is not None and not (scale > 0 and math.isfinite(scale)):
            fail(f"--scale must be a positive number, got {scale}")
        sc = _scene_from_spec(scene, width, height, scale,
                              target=rig.mid_radiance(),
                              cfa=cfa or ("rggb" if colour else None))
        if motion is not None:
            sc = _moving(sc, motion, duration_us=n_cycles * rig.period_us,
                         frame_step_us=frame_step_us)
        kw: dict[str, Any] = dict(rig=rig, sensor=seen, n_cycles=n_cycles, rng=seed,
                                  sensor_seed=sensor_seed, engine=engine, dt_us=dt_us)
        if scheduler is not None:
            from asynhdr.distributed import scheduler_client, simulate_distributed

            with scheduler_client(scheduler, workers=workers) as client:
                err_console.print(f"simulating on {len(client.scheduler_info()['workers'])} "
                                  f"dask workers ({scheduler})")
                rec = simulate_distributed(client, sc, **kw)
        else:
            with progress_bar() as update:
                rec = run(sc, progress=update, **kw)
        write_recording(out, rec, overwrite=overwrite)
        if rig_out is not None:
            from asynhdr import __version__
            from asynhdr.io.rigfile import write_rig

            write_rig(rig_out, rig, sensor=sensor,
                      radiance_unit=str(rec.metadata.get("radiance_unit", "lux")),
                      made={"by": "asynhdr simulate", "asynhdr_version": __version__,
                            "recording": str(out), "scene": scene})
    except (ValueError, FileNotFoundError) as exc:
        fail(str(exc))
    console.print(f"{rec.events.size:,} events, {rec.triggers.size} triggers, "
                  f"{rec.width}x{rec.height} -> {out}" + (f" (rig -> {rig_out})" if rig_out
                                                           else ""))
    ro = rec.metadata.get("readout") or {}
    if ro.get("delayed"):
        share = "" if roi or not sensor.array_pixels else (
            f", these {rec.width * rec.height:,} pixels' share of the array's "
            f"{sensor.max_event_rate_hz:.3g} ev/s; --roi reads them alone")
        held = (f"; their pixels held until read in {ro['held_cycles']} of {n_cycles} cycles"
                if ro.get("pixels_held") else
                "; their pixels fired on as if read at once (--hold holds them)"
                if ro["max_delay_us"] > sensor.timestamp_resolution_us else "")
        console.print(f"readout: {ro['delayed']:,} of {ro['emitted']:,} events delayed, by up "
                      f"to {ro['max_delay_us']:.0f} µs ({ro['rate_hz']:.3g} ev/s{share}){held}")


def _simulate_rig(preset: str, rig_file: Path | None, *, period_us: int | None,
                  ramp_fraction: float | None, t1_shape: str | None, t2_shape: str | None,
                  l_const: float | None, panel: str, pre_emphasis: bool) -> Any:
    """The rig ``simulate`` uses: a rig file; else, when any of the paper rig's options is
    given, that rig (the others at their defaults); else the designed rig of the preset
    (:data:`asynhdr.design.DESIGNED`)."""
    if rig_file is not None:
        from asynhdr.io.rigfile import read_rig

        return read_rig(rig_file).rig
    paper = (ramp_fraction, t1_shape, t2_shape, l_const)
    if any(v is not None for v in paper) or panel != "ideal":
        return Rig(period_us=Rig.period_us if period_us is None else period_us,
                   ramp_fraction=Rig.ramp_fraction if ramp_fraction is None else ramp_fraction,
                   t1_shape=t1_shape or Rig.t1_shape, t2_shape=t2_shape or Rig.t2_shape,  # type: ignore[arg-type]
                   l_const=Rig.l_const if l_const is None else l_const, panel=panel,
                   pre_emphasis=pre_emphasis)
    from asynhdr.design import default_rig

    return default_rig(preset, period_us=period_us)
