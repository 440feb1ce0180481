"""Simulation and reconstruction speed on a 1280x720 step chart.

Prints events/s (median of ``--repeats`` runs, after one warm-up run that compiles the
kernels) for the exact engine with several presets and for the time-stepped engine,
and the reconstruction time beside ``numpy.bincount`` over the same events, measured in
the same run.
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


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--stepped-width", type=int, default=320,
                    help="sensor width for the time-stepped engine (it costs pixels x steps)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)

    scene = step_chart(width=args.width, height=args.height)
    rig = Rig()
    results: dict[str, Any] = {"width": args.width, "height": args.height,
                               "repeats": args.repeats, "simulate": {}}
    print(f"simulation, exact engine, {args.width}x{args.height} step chart, 1 cycle "
          f"(median of {args.repeats})")
    rec = None
    for preset in ("ideal", "v2e", "imx636", "davis346"):
        def run(preset: str = preset) -> Any:
            return simulate(scene, rig=rig, sensor=preset, n_cycles=1, rng=0)
        dt, r = _median_time(run, args.repeats)
        n = int(r.events.size)
        results["simulate"][preset] = {"events": n, "seconds": dt, "events_per_s": n / dt}
        print(f"  {preset:9s} {n:>11,d} events  {dt:7.3f} s  {n / dt / 1e6:7.1f} M events/s")
        if preset == "ideal":
            rec = r

    try:
        from asynhdr.sensor.stepped import simulate_stepped  # noqa: F401
        has_stepped = True
    except ImportError:
        has_stepped = False
    if has_stepped:
        sw = args.stepped_width
        sh = sw * args.height // args.width
        small = step_chart(width=sw, height=sh)

        def run_stepped() -> Any:
            return simulate(small, rig=rig, sensor="ideal", n_cycles=1, rng=0,
                            engine="stepped", dt_us=5.0)

        dt, r = _median_time(run_stepped, args.repeats)
        n = int(r.events.size)
        steps = rig.period_us / 5.0 * sw * sh
        results["stepped"] = {"width": sw, "height": sh, "events": n, "seconds": dt,
                              "events_per_s": n / dt, "pixel_steps_per_s": steps / dt}
        print(f"  stepped   {n:>11,d} events  {dt:7.3f} s  {n / dt / 1e6:7.1f} M events/s "
              f"({sw}x{sh}, dt 5 µs: {steps / dt / 1e6:.0f} M pixel-steps/s)")

    assert rec is not None
    ev = rec.events
    windows = windows_for(rec)
    pix = ev["y"].astype(np.int64) * rec.width + ev["x"]
    pol = ev["p"].astype(np.float64)
    npx = rec.width * rec.height

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
