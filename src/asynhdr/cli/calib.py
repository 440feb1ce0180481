"""``asynhdr calibrate-thresholds``: per-pixel ON and OFF thresholds (and the panels'
curves from a voltage sweep) into one calibration file for ``reconstruct --calibration``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from asynhdr.cli._app import app
from asynhdr.cli.core import check_outputs, console, fail, progress_bar

__all__ = ["calibrate_thresholds"]


@app.command("calibrate-thresholds")
def calibrate_thresholds(
    flats: list[Path] = typer.Argument(..., help="Flat-field recordings of one sensor "
                                       "behind the rig (brighter and darker than L_const)."),
    radiance: list[float] = typer.Option(..., "--radiance", help="Each flat field's radiance "
                                         "in the rig's unit: once for all, or once per "
                                         "recording, in order (--radiance 506 --radiance "
                                         "0.56)."),
    rig: Path = typer.Option(..., "--rig", help="Rig file (TOML) of the captures; its "
                             "\\[sensor] table is the pixel model (else --preset)."),
    out: Path = typer.Option(..., "--out", "-o", help="Calibration file to write (.npz)."),
    preset: str | None = typer.Option(None, help="Sensor preset when the rig file has no "
                                      "\\[sensor] table."),
    sweep: Path | None = typer.Option(None, help="Voltage sweep CSV (voltage_v, "
                                      "transmittance_1, transmittance_2) to fit the panels' "
                                      "curves into the same file."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing file."),
) -> None:
    """Fit every pixel's ON and OFF thresholds to flat fields of known radiance (ml with the
    radiance held; docs/ml.md), with their stated errors, find the dead pixels (no event in
    any cycle), and write them with a record of how they were made."""
    import dataclasses

    from asynhdr.calib import fit_panel_curves, read_sweep_csv, thresholds_from_flats
    from asynhdr.io import open_recording
    from asynhdr.io.calibration import write_calibration
    from asynhdr.io.rigfile import read_rig
    from asynhdr.sensor.params import get_preset

    if out.suffix.lower() != ".npz":
        fail(f"{out}: a calibration file is written as .npz")
    check_outputs([out], overwrite=overwrite)
    for f in flats:
        if f.exists():
            continue
        try:
            float(str(f))
        except ValueError:
            continue
        fail(f"{f}: no such recording; a radiance? Give --radiance once per value "
             f"(--radiance {radiance[0]:g} --radiance {f})")
    if len(radiance) not in (1, len(flats)):
        fail(f"--radiance: give one value, or one per recording ({len(flats)}); got "
             f"{len(radiance)}")
    try:
        rf = read_rig(rig)
        sensor = rf.sensor
        if sensor is None:
            if preset is None:
                fail(f"{rig}: no [sensor] table; give --preset")
            sensor = get_preset(str(preset))
        with progress_bar() as update:
            caps = []
            for i, f in enumerate(flats):
                caps.append(open_recording(f))
                update("read flat fields", i + 1, len(flats))
        rads = radiance * len(flats) if len(radiance) == 1 else list(radiance)
        cal = thresholds_from_flats(caps, radiance=rads, rig=rf.rig, sensor=sensor)
        cal.how["sources"] = [str(f) for f in flats]
        cal.how["rig_file"] = str(rig)
        if sweep is not None:
            cal = dataclasses.replace(cal, panel_curves=fit_panel_curves(read_sweep_csv(sweep)))
            cal.how["sweep"] = str(sweep)
        write_calibration(out, cal)
    except (ValueError, OSError) as exc:
        fail(str(exc))
    assert cal.c_on is not None and cal.c_off is not None
    console.print(
        f"thresholds of {cal.c_on.size:,} pixels from {len(flats)} flat fields "
        f"({cal.how['cycles']} cycles): ON {float(np.mean(cal.c_on)):.4f} +- "
        f"{float(np.std(cal.c_on)):.4f}, OFF {float(np.mean(cal.c_off)):.4f} +- "
        f"{float(np.std(cal.c_off)):.4f} (mismatch); median stated error ON "
        f"{cal.how['median_error_on']:.4f}, OFF {cal.how['median_error_off']:.4f}; "
        f"{cal.how['dead_pixels']:,} dead pixels (no event in any cycle)"
        + (f"; panel curves {sorted(cal.panel_curves)}" if cal.panel_curves else "")
        + f" -> {out}")
