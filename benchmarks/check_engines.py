"""Check two simulated recordings of the same scene, one per engine, with h5py alone.

    asynhdr simulate chart --width 160 --height 120 --preset imx636 --n-cycles 3 \\
        --engine exact -o out/exact.h5
    asynhdr simulate chart --width 160 --height 120 --preset imx636 --n-cycles 3 \\
        --engine stepped -o out/stepped.h5
    python benchmarks/check_engines.py out/exact.h5 out/stepped.h5

Reads the ``events`` and ``triggers`` groups and the ``metadata`` attribute directly
(none of asynhdr's readers), and prints for each file the smallest gap between two
events of one pixel against the refractory period less the timestamp jitter (three
standard deviations, plus the 1 µs timestamp quantum) and less the longest wait in the
readout's queue (the metadata's ``readout.max_delay_us``: the queue stamps a pixel's
events late by different amounts), and, across the two files, the
share of pixels whose event counts agree within one per cycle in every cycle (cycles
cut at the rising trigger edges). Exits 1 when either check fails.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import h5py
import hdf5plugin  # noqa: F401  (the Blosc filter the events are stored with)
import numpy as np


def _load(path: Path) -> tuple[dict[str, np.ndarray], np.ndarray, dict, int, int]:
    with h5py.File(path, "r") as f:
        ev = {k: f["events"][k][()] for k in ("x", "y", "p", "t")}
        trig_t = f["triggers"]["t"][()]
        rising = f["triggers"]["rising"][()].astype(bool)
        meta = json.loads(f.attrs["metadata"])
        width = int(f.attrs["width"])
        height = int(f.attrs["height"])
    return ev, trig_t[rising], meta, width, height


def min_gap(ev: dict[str, np.ndarray], width: int) -> tuple[int, np.ndarray]:
    """Smallest gap between consecutive events of one pixel, and every such gap."""
    pix = ev["y"].astype(np.int64) * width + ev["x"]
    order = np.lexsort((ev["t"], pix))
    ps, ts = pix[order], ev["t"][order]
    same = ps[1:] == ps[:-1]
    gaps = np.diff(ts)[same]
    return (int(gaps.min()) if gaps.size else -1), gaps


def counts_per_cycle(ev: dict[str, np.ndarray], starts: np.ndarray, width: int,
                     height: int) -> np.ndarray:
    """Events per pixel and cycle, shape (cycles, pixels)."""
    npx = width * height
    pix = ev["y"].astype(np.int64) * width + ev["x"]
    cyc = np.searchsorted(starts, ev["t"], side="right") - 1
    keep = cyc >= 0
    flat = cyc[keep] * npx + pix[keep]
    return np.bincount(flat, minlength=starts.size * npx).reshape(starts.size, npx)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("a", type=Path)
    ap.add_argument("b", type=Path)
    ap.add_argument("--agree", type=float, default=0.95,
                    help="share of pixels that must agree within 1 per cycle")
    args = ap.parse_args(argv)
    ok = True
    loaded = []
    for path in (args.a, args.b):
        ev, starts, meta, width, height = _load(path)
        sensor = meta["sensor"]
        pixel = sensor["refractory_us"] - 3.0 * sensor["jitter_sigma_us"] - 1.0
        # the readout's queue stamps a pixel's events late by different amounts: two of
        # them can come closer by as much as the longest wait
        queue = float((meta.get("readout") or {}).get("max_delay_us", 0.0))
        allowed = pixel - queue
        gmin, gaps = min_gap(ev, width)
        below = int(np.count_nonzero(gaps < allowed))
        below_pixel = int(np.count_nonzero(gaps < pixel))
        same_t = float(np.mean(gaps == 0)) if gaps.size else 0.0
        print(f"{path}: engine {meta.get('engine')}, {ev['t'].size:,} events, "
              f"{starts.size} cycles; smallest gap between a pixel's events {gmin} µs "
              f"(refractory {sensor['refractory_us']:g} µs less jitter: {pixel:g} µs, "
              f"{below_pixel} gaps below it; less the readout's longest wait, {queue:g} µs: "
              f"{allowed:g} µs, {below} below); same timestamp as the pixel's previous "
              f"event: {100 * same_t:.2f} %")
        ok &= below == 0
        loaded.append((ev, starts, width, height))
    (ea, sa, w, h), (eb, sb, wb, hb) = loaded
    if (w, h) != (wb, hb) or sa.size != sb.size:
        print("the two recordings differ in size or number of cycles")
        return 1
    ca = counts_per_cycle(ea, sa, w, h)
    cb = counts_per_cycle(eb, sb, w, h)
    diff = np.abs(ca - cb)
    within = np.all(diff <= 1, axis=0)
    identical = np.all(diff == 0, axis=0)
    share = float(within.mean())
    print(f"per-pixel counts within 1 per cycle: {100 * share:.2f} % of {w * h:,} pixels "
          f"(identical in every cycle: {100 * identical.mean():.2f} %, largest difference "
          f"{int(diff.max())}); totals {int(ca.sum()):,} / {int(cb.sum()):,}")
    ok &= share >= args.agree
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
