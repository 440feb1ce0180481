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
    evt: str = typer.Option("3.0", "--evt", help="EVT version of a .raw target: 3.0 | 2.0."),
    width: int | None = typer.Option(None, help="Sensor width, for files without geometry."),
    height: int | None = typer.Option(None, help="Sensor height, for files without geometry."),
    time_unit: str | None = typer.Option(None, "--time-unit", help=TIME_UNIT_HELP),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing target."),
) -> None:
    """Copy an event recording into another format, chunk by chunk (memory flat in file
    size), with its geometry, triggers and metadata (the rig and sensor of a simulated
    recording)."""
    from asynhdr.io import open_source, write_recording

    check_outputs([target], overwrite=overwrite)
    options = {"evt": evt} if target.suffix.lower() == ".raw" else {}
    try:
        src = open_source(source, width=width, height=height, time_unit=time_unit)
        with progress_bar() as update:
            write_recording(target, src, overwrite=overwrite, progress=update, **options)
    except (ValueError, OSError) as exc:
        fail(str(exc))
    console.print(f"{source} ({src.header.format}, {src.width}x{src.height}) -> {target}")
