"""How many events the readout's missing acknowledge lets through.

The simulator's readout (docs/sensor.md, item 6) queues events after the pixels fired them:
a waiting event moves its timestamp, but its pixel resets and fires again as if it had
been read at once. A real pixel holds its request until the readout acknowledges it. This
script simulates the step chart through each preset's default rig with the readout off,
passes the events through the readout afterwards, and counts the events whose pixel's
previous event was still waiting, or whose dead time after that read was not over: events
a pixel that waits for its acknowledge would not have fired then.

Then the same chart with ``arbiter="hold"``, where a waiting pixel is held until it is
read: its events, the longest wait, the closest two reads of one pixel (at least the
refractory period when every pixel waited for its acknowledge) and the time it took
beside the preset's readout.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr.design import default_rig
from asynhdr.scene import step_chart
from asynhdr.sensor.noise import apply_arbiter
from asynhdr.sensor.params import get_preset
from asynhdr.simulate import simulate

SIZES = {"davis346": (346, 260), "imx636": (1280, 720)}


def measure(preset: str, *, n_cycles: int) -> dict[str, Any]:
    w, h = SIZES[preset]
    sensor = get_preset(preset)
    rec = simulate(step_chart(width=w, height=h), rig=default_rig(preset),
                   sensor=sensor.with_(max_event_rate_hz=0.0), n_cycles=n_cycles, rng=0,
                   sensor_seed=1)
    ev = rec.events
    fired = ev["t"].copy()
    read, _ = apply_arbiter(ev.copy(), sensor, n_pixels=w * h)
    wait = read["t"] - fired
    pix = ev["y"].astype(np.int64) * w + ev["x"]
    order = np.lexsort((fired, pix))
    p, t, d = pix[order], fired[order], wait[order]
    dead = sensor.latency_us + sensor.refractory_us
    early = (p[1:] == p[:-1]) & (d[:-1] > 0) & (t[1:] - t[:-1] < d[:-1] + dead)
    out = {"preset": preset, "width": w, "height": h, "cycles": n_cycles,
           "events": int(ev.size), "waited": int(np.count_nonzero(wait > 0)),
           "longest_wait_us": int(wait.max(initial=0)),
           "fired_while_waiting": int(np.count_nonzero(early))}
    for arbiter in ("delay", "hold"):
        t0 = time.perf_counter()
        rec = simulate(step_chart(width=w, height=h), rig=default_rig(preset),
                       sensor=sensor.with_(name=preset, arbiter=arbiter), n_cycles=n_cycles,
                       rng=0, sensor_seed=1)
        seconds = time.perf_counter() - t0
        ev = rec.events
        pix = ev["y"].astype(np.int64) * w + ev["x"]
        order = np.lexsort((ev["t"], pix))
        same = pix[order][1:] == pix[order][:-1]
        gaps = np.diff(ev["t"][order])[same]
        out[arbiter] = {"events": int(ev.size), "seconds": seconds,
                        "longest_wait_us": rec.metadata["readout"]["max_delay_us"],
                        "held_cycles": rec.metadata["readout"]["held_cycles"],
                        "closest_reads_us": int(gaps.min(initial=10**9))}
    return out


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--presets", nargs="+", default=sorted(SIZES), choices=sorted(SIZES))
    ap.add_argument("--n-cycles", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    rows = []
    for preset in args.presets:
        r = measure(preset, n_cycles=args.n_cycles)
        rows.append(r)
        print(f"{preset} ({r['width']}x{r['height']}, {r['cycles']} cycles): "
              f"{r['events']:,} events, {r['waited']:,} waited (longest "
              f"{r['longest_wait_us']:,} µs), {r['fired_while_waiting']:,} "
              f"({r['fired_while_waiting'] / max(r['events'], 1):.1%}) fired while the "
              "previous one waited or its dead time after the read ran", flush=True)
        for arbiter in ("delay", "hold"):
            a = r[arbiter]
            print(f"  arbiter={arbiter}: {a['events']:,} events in {a['seconds']:.1f} s, "
                  f"longest wait {a['longest_wait_us']:,.0f} µs, {a['held_cycles']} cycles "
                  f"held, closest reads of one pixel {a['closest_reads_us']:,} µs "
                  f"(refractory {get_preset(preset).refractory_us:g})", flush=True)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "readout_ack.json").write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
