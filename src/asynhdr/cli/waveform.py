"""``asynhdr waveform``: design the panel voltages for the rig's modulation."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.markup import escape

from asynhdr._atomic import atomic_path
from asynhdr.cli._app import app
from asynhdr.panel import PRESETS, Panel, PanelResponse, get_panel, tn_panel
from asynhdr.rig import Rig
from asynhdr.waveform import DEFAULT_CARRIER_HZ, DEFAULT_SAMPLE_RATE_HZ, Design, design
from asynhdr.waveform_io import SIDECAR_NAME

__all__ = ["build_design", "waveform"]

_RIG = Rig()
PNG_NAME = "waveform.png"


def _panel(preset: str, *, contrast_ratio: float | None, rise_us: float | None,
           fall_us: float | None) -> Panel:
    base = get_panel(preset)
    if contrast_ratio is not None:
        params = base.curve.params
        base = dataclasses.replace(base, curve=tn_panel(
            normally_white=base.curve.normally_white, contrast_ratio=contrast_ratio,
            v_threshold_v=params["v_threshold_v"], v_saturation_v=params["v_saturation_v"],
            v_max_v=params["v_max_v"], t_max=params["t_max"]).curve)
    if rise_us is not None or fall_us is not None:
        resp = PanelResponse(rise_us=base.response.rise_us if rise_us is None else rise_us,
                             fall_us=base.response.fall_us if fall_us is None else fall_us)
        base = dataclasses.replace(base, response=resp)
    return base


def build_design(*, period_us: int = _RIG.period_us,
                 sample_rate_hz: float = DEFAULT_SAMPLE_RATE_HZ,
                 ramp_fraction: float = _RIG.ramp_fraction, t1_shape: str = _RIG.t1_shape,
                 t2_shape: str = _RIG.t2_shape, t2_stop: float = _RIG.t2_stop,
                 panel1: str = "tn_generic", panel2: str = "tn_generic_nb",
                 contrast_ratio: float | None = None, rise_us: float | None = None,
                 fall_us: float | None = None, carrier_hz: float | None = DEFAULT_CARRIER_HZ,
                 pre_emphasis: bool = True) -> Design:
    """The design ``asynhdr waveform`` makes from its options (defaults: its defaults)."""
    p1 = _panel(panel1, contrast_ratio=contrast_ratio, rise_us=rise_us, fall_us=fall_us)
    p2 = _panel(panel2, contrast_ratio=contrast_ratio, rise_us=rise_us, fall_us=fall_us)
    rig = Rig(period_us=period_us, ramp_fraction=ramp_fraction,
              t1_shape=t1_shape,  # type: ignore[arg-type]
              t2_shape=t2_shape,  # type: ignore[arg-type]
              t2_stop=t2_stop,
              contrast_ratio_1=p1.contrast_ratio, contrast_ratio_2=p2.contrast_ratio)
    t1, t2 = rig.waveforms()
    return design(t1, t2, panel1=p1, panel2=p2, period_us=period_us,
                  sample_rate_hz=sample_rate_hz, pre_emphasis=pre_emphasis,
                  ramp_fraction=ramp_fraction, carrier_hz=carrier_hz)


def _plot(d: Design, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 7), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 2, sharex=True)
    t_ms = d.time_s * 1e3
    for k, ch in enumerate(d.channels):
        ax = axes[k, 0]
        ax.plot(t_ms, ch.target, color="k", lw=2.0, label="target")
        if d.pre_emphasis:
            ax.plot(t_ms, ch.command, color="tab:orange", lw=0.8, label="commanded (static)")
            ax.plot(t_ms, ch.result, color="tab:blue", lw=1.2, ls="--",
                    label=f"result ({ch.rms_error_pct:.2f} % RMS)")
        ax.plot(t_ms, ch.naive_result, color="tab:red", lw=1.0, ls=":",
                label=f"without pre-emphasis ({ch.naive_rms_error_pct:.2f} % RMS)")
        if d.ramp_fraction is not None:
            ax.axvline(d.period_us * d.ramp_fraction / 1e3, color="0.6", lw=0.8)
        ax.set_ylabel(f"T{k + 1} ({ch.panel.name})")
        ax.legend(fontsize=8, loc="best")
        axv = axes[k, 1]
        axv.plot(t_ms, ch.voltage_v, color="tab:blue", lw=0.8, label="pre-emphasis"
                 if d.pre_emphasis else "direct")
        if d.pre_emphasis:
            axv.plot(t_ms, ch.naive_voltage_v, color="tab:red", lw=0.8, ls=":",
                     label="without pre-emphasis")
        axv.set_ylabel(f"V{k + 1} (V)")
        axv.legend(fontsize=8, loc="best")
    for ax in axes[1]:
        ax.set_xlabel("time in cycle (ms)")
    fig.suptitle(f"panel waveforms: period {d.period_us} µs, {d.sample_rate_hz:g} samples/s")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)


@app.command("waveform")
def waveform(
    period_us: int = typer.Option(_RIG.period_us, help="Cycle length, µs."),
    sample_rate_hz: float = typer.Option(DEFAULT_SAMPLE_RATE_HZ,
                                         help="Generator sample rate, Hz."),
    ramp_fraction: float = typer.Option(_RIG.ramp_fraction,
                                        help="Part of the cycle taken by the ramp."),
    t1_shape: str = typer.Option(_RIG.t1_shape, help="Scene panel ramp: linear|exponential."),
    t2_shape: str = typer.Option(_RIG.t2_shape,
                                 help="Reference panel ramp: linear|exponential."),
    t2_stop: float = typer.Option(_RIG.t2_stop,
                                  help="How far the reference panel closes (fraction of range)."),
    panel1: str = typer.Option("tn_generic", help=f"Scene panel preset: {sorted(PRESETS)}."),
    panel2: str = typer.Option("tn_generic_nb",
                               help=f"Reference panel preset: {sorted(PRESETS)}."),
    contrast_ratio: float | None = typer.Option(
        None, help="Contrast ratio of both panels and of the targets (default: preset's)."),
    rise_us: float | None = typer.Option(
        None, help="Time constant of rising transmittance, µs, both panels "
                   "(default: preset's)."),
    fall_us: float | None = typer.Option(
        None, help="Time constant of falling transmittance, µs, both panels "
                   "(default: preset's)."),
    carrier_hz: float = typer.Option(
        DEFAULT_CARRIER_HZ, help="AC carrier: the drive polarity reverses as a square wave at "
        "this frequency, DC-free, as liquid crystals need."),
    dc: bool = typer.Option(False, "--dc", help="Drive DC (no carrier). A DC voltage "
                            "degrades a liquid-crystal cell: only for other modulators."),
    pre_emphasis: bool = typer.Option(True, "--pre-emphasis/--no-pre-emphasis",
                                      help="Invert the panels' dynamics."),
    out: Path = typer.Option(Path("waveform"), "--out", help="Output folder."),
) -> None:
    """Design both panels' voltages for the rig's target waveforms; write one file per
    panel in the generators' formats (plain column .csv, Keysight .arb, Siglent .csv),
    a JSON sidecar and a plot."""
    console = Console()
    try:
        d = build_design(period_us=period_us, sample_rate_hz=sample_rate_hz,
                         ramp_fraction=ramp_fraction, t1_shape=t1_shape, t2_shape=t2_shape,
                         t2_stop=t2_stop, panel1=panel1, panel2=panel2,
                         contrast_ratio=contrast_ratio, rise_us=rise_us, fall_us=fall_us,
                         carrier_hz=None if dc else carrier_hz, pre_emphasis=pre_emphasis)
    except ValueError as exc:
        console.print(f"[red]error:[/red] {escape(str(exc))}")
        raise typer.Exit(code=2) from None
    files = d.write_files(out)
    png_path = out / PNG_NAME
    _plot(d, png_path)

    console.print(f"RMS error in % of full scale, {d.n_samples} samples per cycle "
                  f"(ramp: first {ramp_fraction:g} of the cycle)")
    for k, ch in enumerate(d.channels, start=1):
        r = ch.panel.response
        head = f"[bold]T{k}[/bold] {escape(ch.panel.name)} (rise {r.rise_us:g} µs, " \
               f"fall {r.fall_us:g} µs): "
        if d.pre_emphasis:
            console.print(
                head + f"with pre-emphasis [bold]{ch.rms_error_pct:.3f} %[/bold] over the "
                f"cycle, {ch.rms_error_ramp_pct:.3f} % over the ramp; without "
                f"[bold]{ch.naive_rms_error_pct:.3f} %[/bold] and "
                f"{ch.naive_rms_error_ramp_pct:.3f} %")
        else:
            console.print(
                head + f"without pre-emphasis [bold]{ch.naive_rms_error_pct:.3f} %[/bold] over "
                f"the cycle, {ch.naive_rms_error_ramp_pct:.3f} % over the ramp")
    for k, ch in enumerate(d.channels, start=1):
        if not np.isclose(ch.result[0], ch.target[0], rtol=0.1):
            console.print(f"[yellow]note:[/yellow] panel {k} starts the cycle at "
                          f"{ch.result[0]:.4g} instead of {ch.target[0]:.4g}: the return is too "
                          "fast for it; a smaller ramp_fraction leaves it more time")
    drive = "DC (no carrier)" if d.carrier_hz is None else f"AC carrier {d.carrier_hz:g} Hz"
    if d.carrier_hz is None:
        console.print("[yellow]warning:[/yellow] DC drive: a DC voltage across a "
                      "liquid-crystal cell degrades it")
    console.print(f"drive: {drive}; wrote {len(files) - 1} channel files and "
                  f"{escape(str(out / SIDECAR_NAME))}, plot {escape(str(png_path))}")
