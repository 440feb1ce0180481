"""Event I/O speed: AEDAT 4.0 decoding against dv-processing's bare read, and HDF5 /
NPZ / text write and read, each next to a reference measured in the same run.

Usage::

    python benchmarks/bench_io.py [--data DIR] [--out DIR] [--events N] [--repeat 5]

Figures are events per second, the median of ``--repeat`` samples; a sample repeats
its operation until it has run for at least 0.2 s (small files decode in ms).
- aedat4: ``asynhdr.io.aedat.read_aedat`` (the project's own container decoder: events
  as ``EVENT_DTYPE``, external trigger edges, a ``Recording``) against dv-processing
  (iniVation's library, a dev dependency here) reading the same file with
  ``MonoCameraRecording.getNextEventBatch`` + ``.numpy()`` ("dv bare": packets dropped
  as read), the same plus its trigger stream read through ("dv +trig": everything
  ``read_aedat`` decodes), and packets kept and joined into one array ("dv 1 arr",
  what a caller of dv needs); ratio = time asynhdr / time dv (target 1.2).
- hdf5 / npz / text: a synthetic recording of ``--events`` events written and read
  back; reference: ``numpy.save`` / ``numpy.load`` of the same four arrays,
  uncompressed (the memory and disk speed floor of this machine).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr._atomic import atomic_path
from asynhdr.events import Recording, make_events, make_triggers

MIN_SAMPLE_S = 0.2


def _default_data() -> Path:
    env = os.environ.get("ASYNHDR_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parent.parent.parent / "shared" / "data"


def timed(fn: Callable[[], Any], repeat: int) -> float:
    """Median seconds per call of ``fn`` over ``repeat`` samples."""
    return timed_together({"fn": fn}, repeat)["fn"]


def timed_together(fns: dict[str, Callable[[], Any]], repeat: int) -> dict[str, float]:
    """Median seconds per call of each function; samples interleaved (one sample of
    each in turn) so that a busy machine slows all of them alike."""
    for fn in fns.values():
        fn()  # warm up (imports, JIT, page cache)
    samples: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeat):
        for key, fn in fns.items():
            n = 0
            t0 = time.perf_counter()
            while True:
                fn()
                n += 1
                dt = time.perf_counter() - t0
                if dt >= MIN_SAMPLE_S:
                    break
            samples[key].append(dt / n)
    return {k: statistics.median(v) for k, v in samples.items()}


def bench_aedat(data: Path, repeat: int) -> list[dict[str, Any]]:
    import dv_processing as dv

    from asynhdr.io.aedat import read_aedat

    rows = []
    for path in sorted((data / "events").glob("*.aedat4")):
        rec = read_aedat(path)
        n = rec.events.size

        def ours(path: Path = path) -> None:
            read_aedat(path)

        def bare(path: Path = path, triggers: bool = False) -> None:
            r = dv.io.MonoCameraRecording(str(path))
            while True:
                b = r.getNextEventBatch()
                if b is None:
                    break
                b.numpy()
            if triggers and r.isTriggerStreamAvailable():
                while r.getNextTriggerBatch() is not None:
                    pass

        def bare_triggers(path: Path = path) -> None:
            bare(path, triggers=True)

        def bare_one_array(path: Path = path) -> None:
            r = dv.io.MonoCameraRecording(str(path))
            parts = []
            while True:
                b = r.getNextEventBatch()
                if b is None:
                    break
                parts.append(b.numpy())
            np.concatenate(parts)

        t = timed_together({"ours": ours, "bare": bare, "bare_tr": bare_triggers,
                            "one": bare_one_array}, repeat)
        rows.append({
            "file": path.name, "events": n, "trigger_records": sum(
                rec.metadata["trigger_records"].values()),
            "asynhdr_events_per_s": n / t["ours"], "dv_bare_events_per_s": n / t["bare"],
            "dv_bare_with_triggers_events_per_s": n / t["bare_tr"],
            "dv_one_array_events_per_s": n / t["one"],
            "ratio_time_asynhdr_over_dv": t["ours"] / t["bare"],
            "ratio_time_asynhdr_over_dv_with_triggers": t["ours"] / t["bare_tr"],
            "ratio_time_asynhdr_over_dv_one_array": t["ours"] / t["one"],
        })
    return rows


def synthetic(n: int, seed: int = 0) -> Recording:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, max(1, n // 10), size=n))  # 10 events per µs: 10 Mev/s
    ev = make_events(rng.integers(0, 1280, n), rng.integers(0, 720, n),
                     rng.choice(np.array([-1, 1], np.int8), n), t)
    tr = make_triggers(np.arange(0, int(t[-1]), 50_000), True, 0)
    return Recording(events=ev, width=1280, height=720, triggers=tr,
                     metadata={"bench": "synthetic"})


def bench_formats(n: int, repeat: int, tmp: Path, text_events: int) -> list[dict[str, Any]]:
    from asynhdr.io.hdf5 import load_hdf5, save_hdf5
    from asynhdr.io.npz import load_npz, save_npz
    from asynhdr.io.text import read_text, save_text

    rec = synthetic(n)
    rows = []

    def ref_write() -> None:
        for k in ("x", "y", "t", "p"):
            np.save(tmp / f"ref_{k}.npy", np.ascontiguousarray(rec.events[k]))

    def ref_read() -> None:
        for k in ("x", "y", "t", "p"):
            np.load(tmp / f"ref_{k}.npy")

    t_w, t_r = timed(ref_write, repeat), timed(ref_read, repeat)
    size = sum((tmp / f"ref_{k}.npy").stat().st_size for k in ("x", "y", "t", "p"))
    rows.append({"format": "numpy .npy x4 (reference, uncompressed)", "events": n,
                 "write_events_per_s": n / t_w, "read_events_per_s": n / t_r,
                 "bytes_per_event": size / n})
    small = synthetic(text_events)
    for name, ext, save, load, r in (
        ("hdf5 (Blosc zstd + bitshuffle)", ".h5", save_hdf5, load_hdf5, rec),
        ("npz (deflate level 1)", ".npz", save_npz, load_npz, rec),
        ("text (t x y p)", ".txt", save_text, read_text, small),
    ):
        path = tmp / f"bench{ext}"

        def w(path: Path = path, save: Any = save, r: Recording = r) -> None:
            save(path, r)

        def rd(path: Path = path, load: Any = load) -> None:
            load(path)

        t_w, t_r = timed(w, repeat), timed(rd, repeat)
        if not load(path).equals(r):
            raise RuntimeError(f"{name}: round trip differs")
        rows.append({"format": name, "events": r.events.size,
                     "write_events_per_s": r.events.size / t_w,
                     "read_events_per_s": r.events.size / t_r,
                     "bytes_per_event": path.stat().st_size / r.events.size})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=_default_data(),
                    help="real-data folder holding events/*.aedat4 (default ../shared/data)")
    ap.add_argument("--out", type=Path, default=None, help="write bench_io.json here")
    ap.add_argument("--events", type=int, default=4_000_000,
                    help="events of the synthetic recording (hdf5, npz)")
    ap.add_argument("--text-events", type=int, default=500_000,
                    help="events of the synthetic recording for text")
    ap.add_argument("--repeat", type=int, default=5, help="samples per figure (median)")
    ap.add_argument("--aedat-repeat", type=int, default=21,
                    help="samples per AEDAT 4.0 figure (median; small files, noisy timings)")
    args = ap.parse_args(argv)

    results: dict[str, Any] = {"repeat": args.repeat, "aedat_repeat": args.aedat_repeat,
                               "min_sample_s": MIN_SAMPLE_S}
    if (args.data / "events").is_dir():
        results["aedat4"] = bench_aedat(args.data, args.aedat_repeat)
        print(f"AEDAT 4.0 decode (events/s, median of {args.aedat_repeat}); ratios are time "
              "asynhdr / time dv")
        print(f"{'file':28s} {'events':>8s} {'asynhdr':>9s} {'dv bare':>9s} {'dv +trig':>9s} "
              f"{'dv 1 arr':>9s} {'/bare':>6s} {'/+trig':>6s} {'/1 arr':>6s}")
        for r in results["aedat4"]:
            print(f"{r['file']:28s} {r['events']:8d} {r['asynhdr_events_per_s'] / 1e6:7.1f} M "
                  f"{r['dv_bare_events_per_s'] / 1e6:7.1f} M "
                  f"{r['dv_bare_with_triggers_events_per_s'] / 1e6:7.1f} M "
                  f"{r['dv_one_array_events_per_s'] / 1e6:7.1f} M "
                  f"{r['ratio_time_asynhdr_over_dv']:6.2f} "
                  f"{r['ratio_time_asynhdr_over_dv_with_triggers']:6.2f} "
                  f"{r['ratio_time_asynhdr_over_dv_one_array']:6.2f}")
    else:
        print(f"no real data at {args.data}; skipping AEDAT 4.0", file=sys.stderr)
    with tempfile.TemporaryDirectory(prefix="asynhdr-bench-io-") as d:
        results["formats"] = bench_formats(args.events, args.repeat, Path(d), args.text_events)
    print()
    print(f"write / read (events/s, median of {args.repeat})")
    print(f"{'format':42s} {'events':>9s} {'write':>10s} {'read':>10s} {'B/event':>8s}")
    for r in results["formats"]:
        print(f"{r['format']:42s} {r['events']:9d} {r['write_events_per_s'] / 1e6:8.1f} M "
              f"{r['read_events_per_s'] / 1e6:8.1f} M {r['bytes_per_event']:8.2f}")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        with atomic_path(args.out / "bench_io.json") as tmp:
            tmp.write_text(json.dumps(results, indent=2))
        print(f"\nwrote {args.out / 'bench_io.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
