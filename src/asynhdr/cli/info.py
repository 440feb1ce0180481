"""``asynhdr info FILE``: what a recording holds, and its modulation cycles."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import typer
from rich.console import Console
from rich.progress import Progress, SpinnerColumn, TextColumn
from rich.table import Table

from asynhdr._atomic import atomic_path
from asynhdr.cli._app import app
from asynhdr.cli.core import TIME_UNIT_HELP, as_flags, check_outputs, check_period, fail
from asynhdr.segment import Cycles, NoCyclesError, find_cycles
from asynhdr.source import Scan

__all__ = ["info", "save_rate_plot"]

logger = logging.getLogger(__name__)


def save_rate_plot(path: Path, name: str, scan: Scan, cycles: Cycles | None) -> None:
    """Event rate over time (1 ms bins) with cycle starts and trigger edges, in the image
    format the extension names (.png, .pdf, .svg, ...; written atomically)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    counts = scan.rate_counts.astype(np.float64)
    bin_us = scan.rate_bin_us
    group = max(1, 1000 // bin_us) if bin_us < 1000 else 1
    if group > 1:
        pad = (-counts.size) % group
        counts = np.concatenate([counts, np.zeros(pad)]).reshape(-1, group).sum(axis=1)
    width_us = bin_us * group
    t0 = scan.rate_t0_us
    t_s = (np.arange(counts.size) * width_us) / 1e6
    fig = Figure(figsize=(10, 4), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(t_s, counts * (1e6 / width_us) / 1e6, lw=0.7, color="k", label="event rate")
    if cycles is not None and len(cycles) and len(cycles) <= 500:
        for s in cycles.start_us:
            ax.axvline((int(s) - t0) / 1e6, color="tab:blue", lw=0.5, alpha=0.6)
        ax.plot([], [], color="tab:blue", lw=0.5, label=f"cycle starts ({cycles.source})")
    tr = scan.triggers
    if tr.size and tr.size <= 2000:
        for t, r in zip(tr["t"], tr["rising"], strict=True):
            ax.axvline((int(t) - t0) / 1e6, color="tab:red" if r else "tab:orange", lw=0.8,
                       ls="--")
        ax.plot([], [], color="tab:red", ls="--", lw=0.8,
                label="trigger edges (red rising, orange falling)")
    ax.set_xlabel(f"time since {t0} µs [s]")
    ax.set_ylabel(f"event rate [Mev/s] ({width_us / 1000:g} ms bins)")
    ax.set_title(Path(name).name)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=_plot_format(path))


def _plot_format(path: Path) -> str:
    """The image format ``path``'s extension names (one matplotlib writes), else error."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fmt = path.suffix.lower().lstrip(".")
    known = FigureCanvasAgg.get_supported_filetypes()
    if fmt not in known:
        raise ValueError(f"{path}: --plot writes {', '.join('.' + k for k in sorted(known))};"
                         f" not {path.suffix or 'a file without an extension'}")
    return fmt


def _fmt_rate(hz: float | None) -> str:
    if hz is None:
        return "-"
    if hz >= 1e6:
        return f"{hz / 1e6:.3g} Mev/s"
    if hz >= 1e3:
        return f"{hz / 1e3:.3g} kev/s"
    return f"{hz:.3g} ev/s"


def _table(info: dict[str, Any], cycles: Cycles | None, how: str) -> Table:
    t = Table(show_header=False, box=None, pad_edge=False)
    t.add_column(style="bold cyan", no_wrap=True)
    t.add_column()
    t.add_row("file", info["path"])
    t.add_row("format", f"{info['format']} — {info['format_description']}")
    t.add_row("sensor", info["sensor"] or "-")
    if info["width"] is None:
        t.add_row("geometry", "unknown (the file gives none; --width and --height set it)")
    else:
        t.add_row("geometry", f"{info['width']} x {info['height']} (width x height, "
                              f"{info['geometry_source']})")
    t.add_row("events", f"{info['events']:,} ({info['on_events']:,} ON, "
                        f"{info['off_events']:,} OFF)")
    if info["events"]:
        order = "sorted" if info["time_sorted"] else (
            f"not sorted: {info['backward_steps']:,} backward steps")
        t.add_row("time", f"{info['first_t_us']} .. {info['last_t_us']} µs (file order; {order})")
        t.add_row("duration", f"{info['duration_us'] / 1e6:.6f} s")
    t.add_row("mean rate", _fmt_rate(info["mean_rate_hz"]))
    t.add_row("peak rate", f"{_fmt_rate(info['peak_rate_hz'])} "
                           f"({info['peak_rate_bin_us'] / 1000:g} ms bins)")
    edges = info["trigger_edges"]
    t.add_row("trigger edges", ", ".join(f"{k}: {v}" for k, v in edges.items()) or "none")
    records = info.get("trigger_records")
    if records is not None:
        t.add_row("trigger records",
                  ", ".join(f"{k}: {v}" for k, v in records.items()) or "none")
    if cycles is None:
        t.add_row("cycles", f"none: {how}")
    else:
        s = cycles.summary()
        t.add_row("cycles", f"{s['cycles']}, {how}")
        if s["warmup"]:
            t.add_row("warm-up", "cycle 0 (the modulation starts with the recording: its "
                      "pixels start from another state)")
        t.add_row("period", f"{s['period_us']:.3f} µs ({s['frequency_hz']:.4g} Hz)")
        t.add_row("first start", f"{s['first_start_us']} µs")
        low = " (low: the recording may not be modulated)" if s["confidence"] < 0.5 else ""
        t.add_row("confidence", f"{s['confidence']:.2f}{low}")
        if s["missing"] or s["extra"]:
            t.add_row("irregular", f"{s['missing']} missing, {s['extra']} extra edges/bursts")
    return t


_HOW = {"triggers": "from the rising trigger edges", "rig": "from the simulated rig",
        "event_rate": "from the event-rate envelope"}


@app.command("info")
def info(
    file: Path = typer.Argument(..., help="Recording: .raw, .dat, .aedat4, .h5, .hdf5, .npz, "
                                ".txt, .csv"),
    width: int | None = typer.Option(None, "--width", help="Sensor width (pixels), for files "
                                     "without geometry."),
    height: int | None = typer.Option(None, "--height", help="Sensor height (pixels)."),
    time_unit: str | None = typer.Option(None, "--time-unit", help=TIME_UNIT_HELP),
    period_us: float | None = typer.Option(None, "--period-us", help="Modulation period "
                                           "(µs), when known."),
    plot: Path | None = typer.Option(None, "--plot", help="Save an event-rate plot (.png, "
                                     ".pdf, .svg, ...)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing plot."),
) -> None:
    """Describe a recording: format, sensor, geometry, events, rates, triggers, and the
    cycles that every other command would use."""
    from asynhdr.io import open_source

    err = Console(stderr=True)
    check_period(period_us)
    if plot is not None:
        check_outputs([plot], overwrite=overwrite)
        try:
            _plot_format(plot)
        except ValueError as exc:
            fail(str(exc))
    try:
        src = open_source(file, width=width, height=height, time_unit=time_unit)
        with Progress(SpinnerColumn(), TextColumn("{task.description}"), console=err,
                      transient=True) as prog:
            task = prog.add_task(f"reading {file.name}", total=None)

            def progress(stage: str, n: int, total: int | None) -> None:
                prog.update(task, description=f"{stage} {file.name}: {n:,} events")

            description = src.describe(progress=progress)
            cycles: Cycles | None
            try:
                cycles = find_cycles(src, period_us=period_us, progress=progress)
                how = _HOW[cycles.source]
            except NoCyclesError as exc:
                cycles = None
                if not description["events"]:
                    how = "the file holds no events"
                else:
                    hint = "--single" if period_us is not None else "--period-us or --single"
                    how = as_flags(f"{exc.reason}; pass {hint}")
        if plot is not None:
            save_rate_plot(plot, str(file), src.scan(), cycles)
    except (ValueError, OSError) as exc:
        fail(str(exc))
    if as_json:
        out = dict(description)
        out["cycles"] = cycles.summary() if cycles is not None else None
        out["cycles_how"] = how
        typer.echo(json.dumps(out, indent=2, default=str))
    else:
        Console().print(_table(description, cycles, how))
    if plot is not None:
        Console(stderr=True).print(f"event-rate plot: {plot}")
