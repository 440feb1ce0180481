"""What each non-ideality of a realistic pixel does to the chart experiment.

Runs the paper's chart experiment (:func:`asynhdr.experiments.run_chart_experiment`: the
36-level step chart, a c-map from flat fields of the same sensor, every method) for a
realistic preset, then again with one part of the pixel model switched off at a time,
with the readout holding a waiting pixel until it is read (``arbiter="hold"``, where the
preset's queue only moves timestamps), and for the ideal pixel. Prints one row per
variant: events, the exp weighting's mean
patch SNR without and with the c-map (over the patches that respond, counted), both
dynamic ranges of exp with the c-map, and the dynamic range of ``invert``.
docs/sensor.md quotes the table.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

from asynhdr.experiments import run_chart_experiment
from asynhdr.sensor.params import SensorParams, get_preset

OFF: dict[str, dict[str, Any]] = {
    "threshold mismatch": {"threshold_sigma": 0.0},
    "reset noise": {"reset_noise_sigma": 0.0},
    "refractory period": {"refractory_us": 0.0},
    "photoreceptor low-pass": {"cutoff_hz": 0.0},
    "jitter": {"jitter_sigma_us": 0.0},
    "background events": {"leak_rate_hz": 0.0, "shot_noise_rate_hz": 0.0,
                          "hot_pixel_fraction": 0.0},
    "dead pixels": {"dead_pixel_fraction": 0.0},
    "readout limit": {"max_event_rate_hz": 0.0},
}


def _fmt(v: float) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.2f}"


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--preset", default="imx636")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--only", nargs="+", default=None, metavar="WORD",
                    help="run only the variants whose name holds one of these words "
                         "(e.g. 'all' 'holding')")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    base = get_preset(args.preset)
    variants: list[tuple[str, SensorParams]] = [(f"{args.preset} (all parts)", base)]
    for part, change in OFF.items():
        if any(getattr(base, k) != v for k, v in change.items()):
            variants.append((f"without {part}", base.with_(**change)))
    if base.max_event_rate_hz > 0 and base.arbiter == "delay":
        variants.append(("with the readout holding its pixels",
                         base.with_(name=base.name, arbiter="hold")))
    variants.append(("ideal pixel", get_preset("ideal")))
    if args.only:
        variants = [(n, v) for n, v in variants if any(w in n for w in args.only)]
    rows = []
    print(f"chart experiment, {args.width}x{args.height}, 3 cycles, c-map from 4 flat fields")
    print("| variant | events | exp SNR (dB) no c-map / c-map [patches] | DR exp+c-map EMVA / "
          "steps (dB) | DR invert EMVA (dB) |")
    print("| --- | --- | --- | --- | --- |")
    for name, sensor in variants:
        t0 = time.perf_counter()
        res = run_chart_experiment(width=args.width, height=args.height, sensor=sensor,
                                   methods=("exp", "invert"))
        e0, e1 = res.get("exp", False), res.get("exp", True)
        inv = res.get("invert", True)
        row = {"variant": name, "events": res.metadata["n_events"],
               "snr_exp_db": e0.snr.mean_db, "snr_exp_patches": e0.snr.n_patches,
               "snr_exp_cmap_db": e1.snr.mean_db, "snr_exp_cmap_patches": e1.snr.n_patches,
               "dr_exp_cmap_db": e1.dr.dr_db, "dr_steps_exp_cmap_db": e1.dr_steps.dr_db,
               "dr_invert_cmap_db": inv.dr.dr_db, "seconds": time.perf_counter() - t0}
        rows.append(row)
        print(f"| {name} | {row['events']:,} | {_fmt(e0.snr.mean_db)} / "
              f"{_fmt(e1.snr.mean_db)} [{e0.snr.n_patches}/{e1.snr.n_patches}] | "
              f"{e1.dr.dr_db:.1f} / {e1.dr_steps.dr_db:.1f} | {inv.dr.dr_db:.1f} |", flush=True)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"nonidealities_{args.preset}.json").write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
