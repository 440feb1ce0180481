"""Motion artefacts of the modulated event camera against a frame camera at the same rate.

Pans a vertical edge (30 | 3,000 lux, 120x60) at several velocities
(:func:`asynhdr.motion.run_motion_experiment`) and prints, per method, the median over
cycles of the log-radiance RMSE (stops, after one global scale) against the scene at the
middle of the time each frame looked at, and the edge's 10-90 % width in pixels.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from asynhdr.design import default_rig
from asynhdr.motion import edge_scene, run_motion_experiment


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--preset", default="imx636")
    ap.add_argument("--velocities", default="0,50,200,400", help="px/s, comma-separated")
    ap.add_argument("--methods", default="invert,exp", help="event methods, comma-separated")
    ap.add_argument("--designed", action="store_true",
                    help="the preset's designed rig (asynhdr design) instead of the paper's")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    scene = edge_scene(width=120, height=60, dark=30.0, bright=3000.0)
    rows = []
    rig = default_rig(args.preset) if args.designed else None
    methods = tuple(args.methods.split(","))
    print(f"{args.preset} ({'designed' if args.designed else 'paper'} rig): edge 30 | 3000 "
          f"lux, 120x60, 4 cycles of 50 ms (first left out)")
    print("| v (px/s) | motion in the ramp (px) | method | log RMSE (stops) | edge width (px) |")
    print("| --- | --- | --- | --- | --- |")
    for v in (float(x) for x in args.velocities.split(",")):
        res = run_motion_experiment(scene, velocity_px_per_s=(v, 0.0), sensor=args.preset,
                                    n_cycles=4, rig=rig, methods=methods)
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
