"""``asynhdr convert IN OUT``: an event file into another format, streaming."""

from __future__ import annotations

from pathlib import Path

import typer

from asynhdr.cli._app import app
from asynhdr.cli.core import TIME_UNIT_HELP, check_outputs, console, fail, progress_bar

__all__ = ["convert"]


@app.command()
def convert(
    source: Path = typer.Argument(..., help="Event recording to read (any supported format)."),
    target: Path = typer.Argument(..., help="File to write: .raw (EVT 3.0), .h5 (asynhdr "
                                  "HDF5), .hdf5 (Metavision HDF5), .npz, .txt/.csv, .dat."),
    evt: str | None = typer.Option(None, "--evt", help="EVT version of a .raw target: 3.0 "
                                   "(default) | 2.0."),
    width: int | None = typer.Option(None, help="Sensor width, for files without geometry."),
    height: int | None = typer.Option(None, help="Sensor height, for files without geometry."),
    time_unit: str | None = typer.Option(None, "--time-unit", help=TIME_UNIT_HELP),
    start_at_zero: bool = typer.Option(False, "--start-at-zero", help="Subtract the first "
                                       "time (events and triggers) from every time, for "
                                       "targets that count from the recording's start "
                                       "(.raw, .dat: a camera clock since 1970 does not "
                                       "fit); the metadata keeps it (time_shift_us)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing target."),
) -> None:
    """Copy an event recording into another format, chunk by chunk (memory flat in file
    size), with its geometry, triggers and metadata (the rig and sensor of a simulated
    recording)."""
    from asynhdr.io import open_source, write_recording

    check_outputs([target], overwrite=overwrite)
    raw_target = target.suffix.lower() == ".raw"
    if evt is not None and not raw_target:
        fail(f"--evt {evt}: applies to a .raw target only, not {target.name}")
    options = {"evt": evt or "3.0"} if raw_target else {}
    try:
        src = open_source(source, width=width, height=height, time_unit=time_unit)
        with progress_bar() as update:
            shift = 0
            if start_at_zero:
                scan = src.scan(progress=update)
                firsts = [t for t in (scan.min_t_us,
                                      int(scan.triggers["t"][0]) if scan.triggers.size
                                      else None) if t is not None]
                shift = min(firsts) if firsts else 0
            write_recording(target, src, overwrite=overwrite, progress=update,
                            time_shift_us=shift, **options)
    except (ValueError, OSError) as exc:
        fail(str(exc))
    console.print(f"{source} ({src.header.format}, {src.width}x{src.height}) -> {target}")
