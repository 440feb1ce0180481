"""``asynhdr design``: the rig that gives ``ml`` the widest dynamic range for a sensor."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.table import Table

from asynhdr.cli._app import app
from asynhdr.cli.core import console, fail, progress_bar
from asynhdr.design import (
    DEFAULT_FRAME_RATE_HZ,
    DEFAULT_MARGIN_DB,
    DEFAULT_MEAN_SNR_DB,
    DEFAULT_MIN_SNR_DB,
    DEFAULT_SCENE_RANGE,
    FAMILIES,
    MAX_BIAS,
)

__all__ = ["design"]


@app.command()
def design(
    preset: str = typer.Option("imx636", help="Sensor preset: ideal | v2e | davis346 | "
                               "imx636."),
    l_min: float = typer.Option(DEFAULT_SCENE_RANGE[0], help="Darkest scene radiance (lux)."),
    l_max: float = typer.Option(DEFAULT_SCENE_RANGE[1], help="Brightest scene radiance "
                                "(lux)."),
    frame_rate_hz: float | None = typer.Option(None, help="Cycles per second (default: the "
                                               "preset's default rig's, asynhdr.design."
                                               f"DESIGNED; else {DEFAULT_FRAME_RATE_HZ:g})."),
    contrast_ratio: float = typer.Option(1000.0, help="Panels' open/closed ratio."),
    min_snr_db: float = typer.Option(DEFAULT_MIN_SNR_DB, help="Per-pixel SNR a level needs "
                                     "to count in the range."),
    mean_snr_db: float = typer.Option(DEFAULT_MEAN_SNR_DB, help="Mean per-pixel SNR over "
                                      "the range that settles a tie of ranges: the rig with "
                                      "the fewest events that reaches it wins."),
    margin_db: float = typer.Option(DEFAULT_MARGIN_DB, help="Rank rigs first by the range "
                                    "whose levels are predicted at least this far above "
                                    "--min-snr-db (a capture scatters about the "
                                    "prediction), then by the range itself."),
    family: list[str] = typer.Option(list(FAMILIES), "--family",
                                     help="Rig families to search (repeatable): "
                                     + " | ".join(FAMILIES) + "."),
    out: Path | None = typer.Option(None, "--out", "-o", help="Rig file to write (.toml)."),
    compare: bool = typer.Option(False, "--compare", help="Also predict the paper's rig "
                                 "(linear ramps, t2_stop 0.5, L_const 10 lux) and a "
                                 "cross-fade (both exponential, T2 to its floor)."),
    json_out: Path | None = typer.Option(None, "--json", help="Write every figure as JSON."),
) -> None:
    """Choose the rig family (sequential, or round trips: there and back, once or twice per
    cycle), L_const and the ramps' split that maximise the range over which ml's predicted
    per-pixel SNR (the model's Cramér-Rao bound) is at least --min-snr-db (first with
    --margin-db to spare) and the readout's queue (the whole array's, a quarter of it at
    one radiance) moves ml's estimate by at most 5 %; between equal ranges, the rig with
    the fewest events whose mean SNR reaches --mean-snr-db. Print it and write the rig
    file."""
    import numpy as np

    from asynhdr.design import DESIGNED, predict
    from asynhdr.design import design as run
    from asynhdr.rig import Rig
    from asynhdr.sensor.params import get_preset

    if frame_rate_hz is None:
        frame_rate_hz = float(DESIGNED.get(preset, {}).get("frame_rate_hz",
                                                           DEFAULT_FRAME_RATE_HZ))
    try:
        sensor = get_preset(preset)
        with progress_bar() as update:
            res = run(sensor, l_min=l_min, l_max=l_max, frame_rate_hz=frame_rate_hz,
                      contrast_ratio=contrast_ratio, min_snr_db=min_snr_db,
                      mean_snr_db=mean_snr_db, margin_db=margin_db,
                      families=tuple(family),
                      progress=lambda d, t: update("candidates", d, t))
    except ValueError as exc:
        fail(str(exc))
    p = res.params
    rows = {"designed": res.snr_db}
    others: dict[str, dict[str, float]] = {}
    if compare:
        period = round(1e6 / frame_rate_hz)
        alts = {
            "paper (linear, t2_stop 0.5)": Rig(period_us=period, l_const=10.0),
            "cross-fade (exp, T2 to floor)": Rig(period_us=period, l_const=p["l_const"],
                                                 t1_shape="exponential",
                                                 t2_shape="exponential", t2_stop=1.0),
        }
        for name, rig in alts.items():
            pred = predict(rig, sensor, levels=res.levels)
            db, lo, hi, _ = pred.run(min_snr_db)
            rows[name] = pred.snr_db
            others[name] = {"range_db": db, "l_lo": lo, "l_hi": hi,
                            "readout_load": pred.readout_load}
    table = Table(title=f"Predicted per-pixel SNR of ml (dB), sensor '{preset}', "
                  f"{frame_rate_hz:g} cycles/s")
    table.add_column("radiance (lux)", justify="right")
    for name in rows:
        table.add_column(name, justify="right")
    for i, lv in enumerate(res.levels):
        table.add_row(f"{lv:.3g}", *[f"{rows[n][i]:.1f}" for n in rows])
    console.print(table)
    back = ""
    if p["family"] in ("round_trip", "two_round_trips"):
        c = 2.0 * p["b"] - p["a"]
        back = (f", reopens over {p['b']:.3g}..{c:.3g}, scene panel closes over "
                f"{c:.3g}..{2.0 * p['b']:.3g}")
        if p["family"] == "two_round_trips":
            back += f"; again over {2.0 * p['b']:.3g}..{4.0 * p['b']:.3g}"
    console.print(f"design ({p['family']}): L_const {p['l_const']:.4g} lux; scene panel opens "
                  f"over phase 0..{p['a']:.3g}, reference closes over "
                  f"{p['a']:.3g}..{p['b']:.3g} to {p['floor_2']:g}{back}, hold to "
                  f"{res.rig.ramp_fraction:.3g}; cycle {int(p['period_us'])} µs")
    pr = res.prediction
    console.print(f"predicted range (per-pixel SNR >= {min_snr_db:g} dB, readout bias <= "
                  f"{MAX_BIAS:.0%}): [bold]{res.range_db:.1f} dB[/] ({res.l_lo:.3g} to "
                  f"{res.l_hi:.3g} lux); with {margin_db:g} dB to spare "
                  f"{res.margin_range_db:.1f} dB")
    if sensor.max_event_rate_hz > 0:
        n_bad = int(np.count_nonzero((pr.snr_db >= min_snr_db) & ~pr.counts(min_snr_db)))
        console.print(f"readout: {pr.events_per_cycle:.1f} events per pixel and cycle, "
                      f"{pr.readout_load:.0%} of the {sensor.max_event_rate_hz:.3g} ev/s "
                      f"readout on average; the queue holds events up to "
                      f"{pr.max_delay_us:.0f} µs"
                      + (f"; {n_bad} levels lose more than {MAX_BIAS:.0%} to it" if n_bad
                         else ""))
        if pr.readout_load > 0:
            console.print(f"  the readout carries this rig's events at up to "
                          f"{frame_rate_hz / pr.readout_load:.3g} cycles/s on average "
                          f"(bursts need more)")
    for name, o in others.items():
        console.print(f"  {name}: {o['range_db']:.1f} dB ({o['l_lo']:.3g} to {o['l_hi']:.3g})")
    if out is not None:
        from asynhdr import __version__
        from asynhdr.io.rigfile import write_rig

        try:
            write_rig(out, res.rig, sensor=sensor, radiance_unit="lux",
                      made={"by": "asynhdr design", "asynhdr_version": __version__,
                            "preset": preset, "l_min": l_min, "l_max": l_max,
                            "frame_rate_hz": frame_rate_hz, "contrast_ratio": contrast_ratio,
                            "min_snr_db": min_snr_db, "mean_snr_db": mean_snr_db,
                            "margin_db": margin_db, "predicted_range_db": res.range_db,
                            "margin_range_db": res.margin_range_db,
                            **{k: v for k, v in p.items()}})
        except (ValueError, OSError) as exc:
            fail(str(exc))
        console.print(f"rig file -> {out}")
    if json_out is not None:
        from asynhdr._atomic import atomic_path

        d = res.summary()
        d["compare"] = {k: dict(v, snr_db=np.asarray(rows[k]).tolist())
                        for k, v in others.items()}
        with atomic_path(json_out) as tmp:
            tmp.write_text(json.dumps(d, indent=1, default=float))
