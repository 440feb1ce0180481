"""Colour error of a scene through a Bayer (RGGB) event sensor, per preset.

Runs the two commands of docs/colour.md for each preset (``asynhdr simulate SCENE --cfa
rggb ... && asynhdr reconstruct ... --method invert``), reads the RGB EXR back and prints
the CIEDE2000 median / mean / 95th percentile and the RMS natural-log error per channel
against the scene's RGB resized to the sensor (:func:`asynhdr.colour.colour_errors`, one
global scale; pixels where either image is not positive in every channel are left out and
counted).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from asynhdr.colour import colour_errors, colour_scene
from asynhdr.io.colour_images import read_rgb_radiance


def _data_dir() -> Path:
    env = os.environ.get("ASYNHDR_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", type=Path,
                    default=_data_dir() / "hdr" / "scenes" / "nancy_church.hdr")
    ap.add_argument("--presets", default="ideal,v2e")
    ap.add_argument("--width", type=int, default=240)
    ap.add_argument("--height", type=int, default=320)
    ap.add_argument("--l-const", default="0.3")
    args = ap.parse_args(argv)
    if not args.scene.is_file():
        print(f"{args.scene} not found (set ASYNHDR_DATA)")
        return 1
    exe = Path(sys.executable).with_name("asynhdr")
    truth = colour_scene(read_rgb_radiance(args.scene)[0], width=args.width, height=args.height).rgb
    print(f"{args.scene.name}, {args.width}x{args.height}, one cycle, --l-const "
          f"{args.l_const}, invert, malvar demosaicing")
    print("| preset | dE00 median | mean | p95 | RMS ln error R, G, B | pixels left out |")
    print("| --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for preset in args.presets.split(","):
            rec = Path(tmp) / f"{preset}.h5"
            out = Path(tmp) / preset
            subprocess.run([str(exe), "simulate", str(args.scene), "--cfa", "rggb",
                            "--width", str(args.width), "--height", str(args.height),
                            "--n-cycles", "1", "--preset", preset, "--l-const", args.l_const,
                            "-o", str(rec)], check=True, capture_output=True)
            subprocess.run([str(exe), "reconstruct", str(rec), "--method", "invert",
                            "-o", str(out), "--formats", "exr"], check=True,
                           capture_output=True)
            rgb = read_rgb_radiance(sorted(out.glob("*.exr"))[-1])[0]
            e = colour_errors(rgb, truth)
            left = float(np.mean(~(np.all(rgb > 0, axis=-1) & np.all(truth > 0, axis=-1))))
            rms = ", ".join(f"{v:.3f}" for v in e["rms_log_error"])
            print(f"| {preset} | {e['ciede2000_median']:.2f} | {e['ciede2000_mean']:.2f} | "
                  f"{e['ciede2000_p95']:.2f} | {rms} | {100 * left:.2f} % |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
