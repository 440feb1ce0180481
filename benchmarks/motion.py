"""Motion artefacts of the modulated event camera against a frame camera at the same rate.

Pans a vertical edge (30 | 3,000 lux, 60 rows; 40 px from the left, the image wide
enough that the edge stays in view over the run: 120 px plus the motion) at several
velocities
(:func:`asynhdr.motion.run_motion_experiment`) and prints, per method, the median over
cycles of the log-radiance RMSE (stops, after one global scale) against the scene at the
middle of the time each frame looked at, and the edge's 10-90 % width in pixels.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from asynhdr.design import default_rig
from asynhdr.motion import edge_scene, run_motion_experiment
from asynhdr.rig import Rig


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--preset", default="imx636")
    ap.add_argument("--velocities", default="0,50,200,400", help="px/s, comma-separated")
    ap.add_argument("--methods", default="invert,exp", help="event methods, comma-separated")
    ap.add_argument("--designed", action="store_true",
                    help="the preset's designed rig (asynhdr design) instead of the paper's")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    rows = []
    rig = default_rig(args.preset) if args.designed else Rig()
    n_cycles = 4
    duration_s = n_cycles * rig.period_us * 1e-6
    methods = tuple(args.methods.split(","))
    print(f"{args.preset} ({'designed' if args.designed else 'paper'} rig): edge 30 | 3000 "
          f"lux, 60 rows, {n_cycles} cycles of {rig.period_us / 1e3:g} ms (first left out)")
    print("| v (px/s) | motion in the ramp (px) | method | log RMSE (stops) | edge width (px) |")
    print("| --- | --- | --- | --- | --- |")
    for v in (float(x) for x in args.velocities.split(",")):
        scene = edge_scene(width=120 + math.ceil(abs(v) * duration_s), height=60, dark=30.0,
                           bright=3000.0, edge_x=40.0)
        res = run_motion_experiment(scene, velocity_px_per_s=(v, 0.0), sensor=args.preset,
                                    n_cycles=n_cycles, rig=rig, methods=methods)
        for m, s in res.summary().items():
            row = {"velocity_px_per_s": v, "method": m, **s,
                   "motion_during_ramp_px": res.settings["motion_during_ramp_px"]}
            rows.append(row)
            print(f"| {v:g} | {row['motion_during_ramp_px']:.1f} | {m} | "
                  f"{s['log_rmse_stops']:.3f} | {s['edge_width_px']:.1f} |", flush=True)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        name = f"motion_{args.preset}{'_designed' if args.designed else ''}.json"
        (args.out / name).write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
