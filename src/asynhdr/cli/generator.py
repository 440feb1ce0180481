"""``asynhdr generator upload``: load the panel drive into an arbitrary-waveform generator."""

from __future__ import annotations

import sys
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape

from asynhdr.cli._app import app
from asynhdr.generator import (
    DEFAULT_TIMEOUT_MS,
    DIALECTS,
    TRANSFERS,
    GeneratorError,
    Program,
    scpi_commands,
    upload,
)

__all__ = ["generator_app", "upload_command"]

generator_app = typer.Typer(help="Signal generator: load the designed panel drive over VISA.",
                            no_args_is_help=True)
app.add_typer(generator_app, name="generator")

console = Console(width=None if sys.stdout.isatty() else 160, highlight=False)
err_console = Console(stderr=True, width=None if sys.stderr.isatty() else 160)


def _fail(msg: str) -> None:
    err_console.print(f"[bold red]error:[/] {escape(msg)}", soft_wrap=True)
    raise typer.Exit(code=2)


def _program(design: Path | None, sync_channel: int) -> Program:
    if design is not None:
        from asynhdr.waveform_io import read_waveform_files

        return Program.from_files(read_waveform_files(design), sync_channel=sync_channel)
    from asynhdr.cli.waveform import build_design

    return Program.from_design(build_design(), sync_channel=sync_channel)


@generator_app.command("upload")
def upload_command(
    resource: str | None = typer.Option(None, "--resource", help="VISA address of the "
                                        "generator, e.g. USB0::0x0957::0x2C07::MY5...::INSTR "
                                        "or TCPIP0::192.168.1.5::INSTR."),
    design: Path | None = typer.Option(None, "--design", help="Folder written by 'asynhdr "
                                       "waveform' (default: the default design, AC drive)."),
    dialect: str | None = typer.Option(None, help=f"Force a dialect {sorted(DIALECTS)} "
                                       "(default: from *IDN?; with --dry-run: all)."),
    transfer: str = typer.Option("binary", help=f"Waveform data transfer: {TRANSFERS}."),
    dry_run: bool = typer.Option(False, "--dry-run", help="Print the SCPI, send nothing."),
    sync_channel: int = typer.Option(1, help="Channel whose Sync output marks the cycle "
                                     "start."),
    visa_library: str = typer.Option("", help="pyvisa backend ('' default, '@py' pyvisa-py, "
                                     "'devices.yaml@sim' pyvisa-sim)."),
    timeout_ms: int = typer.Option(DEFAULT_TIMEOUT_MS, help="VISA timeout, ms."),
) -> None:
    """Send both panels' drive as arbitrary waveforms (channel 1 scene panel, channel 2
    reference panel) with sample rate, amplitude, offset, high-impedance load, both
    channels in phase and a Sync output at each cycle start; check the instrument's
    error queue (or read the state back) and name any command it rejected."""
    if dialect is not None and dialect not in DIALECTS:
        _fail(f"--dialect: unknown {dialect!r}; expected one of {sorted(DIALECTS)}")
    if transfer not in TRANSFERS:
        _fail(f"--transfer: expected one of {TRANSFERS}, got {transfer!r}")
    try:
        program = _program(design, sync_channel)
    except (ValueError, FileNotFoundError) as exc:
        _fail(str(exc))
    drive = "DC" if program.carrier_hz is None else f"AC carrier {program.carrier_hz:g} Hz"
    console.print(f"program: {program.n_samples} samples per channel at "
                  f"{program.sample_rate_hz:g} Sa/s ({program.period_us} µs cycle), {drive}")
    for k in (1, 2):
        sc = program.scale(k)
        console.print(f"  channel {k} ({'scene' if k == 1 else 'reference'} panel): "
                      f"{sc.amplitude_vpp:.4f} Vpp, offset {sc.offset_v:+.4f} V")
    if program.carrier_hz is None:
        err_console.print("[yellow]warning:[/] DC drive: a DC voltage degrades a "
                          "liquid-crystal cell")
    if dry_run:
        names = [dialect] if dialect else list(DIALECTS)
        for name in names:
            d = DIALECTS[name]
            try:
                cmds = scpi_commands(program, d, transfer=transfer)
            except ValueError as exc:
                console.print(f"# {d.title} ({name}): {escape(str(exc))}")
                continue
            console.print(f"# {d.title} ({name}), {transfer} transfer, {len(cmds)} commands; "
                          f"errors: {d.error_query or 'read-back of the state'}")
            for c in cmds:
                console.print(escape(c.show()))
            if d.error_query:
                console.print(escape(f"{d.error_query}   (after every command)"))
            for query, _, _ in d.verify(program):
                console.print(escape(f"{query}   (read back)"))
        return
    if resource is None:
        _fail("--resource VISA_ADDRESS is needed (or --dry-run to print the SCPI)")
    try:
        report = upload(resource, program, dialect=dialect, transfer=transfer,
                        visa_library=visa_library, timeout_ms=timeout_ms)
    except (GeneratorError, ValueError) as exc:
        _fail(str(exc))
    console.print(f"{escape(report.idn)}: {len(report.commands)} commands ({report.dialect} "
                  f"dialect, {transfer}) accepted"
                  + (f"; read back {', '.join(report.verified)}" if report.verified else
                     "; error queue empty"))
