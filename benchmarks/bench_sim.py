"""Simulation and reconstruction speed on a 1280x720 step chart, one cycle.

Every figure is a median of ``--repeats`` runs after one warm-up run (numba compiles
there), next to references measured in the same run over the same number of events:
``numpy.sort`` of that many int64 timestamps and ``numpy.bincount`` of that many pixel
indices with weights. The machine's speed drifts; compare the ratios.

- the exact engine for every preset (the ideal pixel: closed-form crossings; the
  realistic ones: the photoreceptor tabulated over radiance), with the rig's ideal panels
  and with TN panels in the loop;
- the stepped engine (each pixel's signal integrated) on a smaller sensor;
- reconstruction (exp weighting) beside ``numpy.bincount``.

The process keeps the memory it frees for reuse (:func:`asynhdr.memory.retain_freed_memory`,
as the ``asynhdr`` command does; ``ASYNHDR_RETAIN_MEMORY=0`` to measure without).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr.memory import retain_freed_memory
from asynhdr.reconstruct import weighted_sums, windows_for
from asynhdr.rig import Rig
from asynhdr.scene import step_chart
from asynhdr.simulate import simulate


def _median_time(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    fn()  # warm-up: numba compilation, page faults
    times = []
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def _references(n: int, npx: int, repeats: int) -> dict[str, float]:
    """Median seconds of numpy.sort and numpy.bincount over ``n`` items."""
    rng = np.random.default_rng(0)
    t = rng.integers(0, 50_000, n)
    pix = rng.integers(0, npx, n)
    w = rng.standard_normal(n)
    t_sort, _ = _median_time(lambda: np.sort(t), repeats)
    t_bin, _ = _median_time(lambda: np.bincount(pix, weights=w, minlength=npx), repeats)
    return {"sort_seconds": t_sort, "bincount_seconds": t_bin}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--stepped-width", type=int, default=160,
                    help="sensor width for the stepped engine (it costs pixels x steps)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)

    retained = retain_freed_memory()
    scene = step_chart(width=args.width, height=args.height)
    npx = args.width * args.height
    results: dict[str, Any] = {"width": args.width, "height": args.height,
                               "repeats": args.repeats, "memory_retained": retained,
                               "simulate": {}}
    print(f"simulation, {args.width}x{args.height} step chart, 1 cycle, median of "
          f"{args.repeats}; references over the same number of events in the same run; "
          f"freed memory kept for reuse: {'yes' if retained else 'no'}")
    print(f"  {'preset':9s} {'panel':6s} {'engine':7s} {'events':>11s} {'seconds':>8s} "
          f"{'M ev/s':>7s} {'x sort':>7s} {'x bincount':>10s} {'distinct t':>10s}")
    rec = None
    for panel in ("ideal", "tn"):
        rig = Rig(panel=panel)
        for preset in ("ideal", "v2e", "davis346", "imx636"):
            def run(preset: str = preset, rig: Rig = rig) -> Any:
                return simulate(scene, rig=rig, sensor=preset, n_cycles=1, rng=0)

            dt, r = _median_time(run, args.repeats)
            n = int(r.events.size)
            ref = _references(n, npx, args.repeats)
            ev = r.events
            within = ev["t"][(ev["t"] >= 0) & (ev["t"] < rig.period_us)]
            distinct = int(np.unique(within).size)
            row = {"events": n, "seconds": dt, "events_per_s": n / dt,
                   "ratio_to_sort": dt / ref["sort_seconds"],
                   "ratio_to_bincount": dt / ref["bincount_seconds"],
                   "distinct_timestamps_in_cycle": distinct, **ref}
            results["simulate"][f"{preset}/{panel}"] = row
            print(f"  {preset:9s} {panel:6s} {'exact':7s} {n:>11,d} {dt:8.3f} "
                  f"{n / dt / 1e6:7.1f} {row['ratio_to_sort']:7.2f} "
                  f"{row['ratio_to_bincount']:10.2f} {distinct:>10,d}")
            if preset == "ideal" and panel == "ideal":
                rec = r

    sw = args.stepped_width
    sh = sw * args.height // args.width
    small = step_chart(width=sw, height=sh)
    results["stepped"] = {}
    for preset in ("ideal", "imx636"):
        def run_stepped(preset: str = preset) -> Any:
            return simulate(small, sensor=preset, n_cycles=1, rng=0, engine="stepped")

        dt, r = _median_time(run_stepped, max(1, args.repeats // 2))
        n = int(r.events.size)
        results["stepped"][preset] = {"width": sw, "height": sh, "events": n, "seconds": dt,
                                      "events_per_s": n / dt, "pixels_per_s": sw * sh / dt}
        print(f"  {preset:9s} {'ideal':6s} {'stepped':7s} {n:>11,d} {dt:8.3f} "
              f"{n / dt / 1e6:7.1f}   ({sw}x{sh}: {sw * sh / dt / 1e3:.0f} k pixel-cycles/s)")

    assert rec is not None
    ev = rec.events
    windows = windows_for(rec)
    pix = ev["y"].astype(np.int64) * rec.width + ev["x"]
    pol = ev["p"].astype(np.float64)

    def floor() -> Any:
        return np.bincount(pix, weights=pol, minlength=npx)

    def recon() -> Any:
        return weighted_sums(rec, windows, method="exp", k=10.0)

    t_floor, _ = _median_time(floor, args.repeats)
    t_rec, _ = _median_time(recon, args.repeats)
    n = int(ev.size)
    results["reconstruct"] = {
        "events": n, "seconds": t_rec, "events_per_s": n / t_rec,
        "bincount_seconds": t_floor, "bincount_events_per_s": n / t_floor,
        "ratio_to_bincount": t_rec / t_floor,
    }
    print(f"reconstruction (exp weighting, {n:,} events): {t_rec:.3f} s "
          f"({n / t_rec / 1e6:.0f} M events/s); numpy.bincount on the same events "
          f"{t_floor:.3f} s ({n / t_floor / 1e6:.0f} M events/s); ratio {t_rec / t_floor:.2f}")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "bench_sim.json").write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
