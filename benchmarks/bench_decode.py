"""Decoding speed of the Prophesee .raw codec, beside faery measured in the same run.

1. Every real ``.raw`` file of the data folder, each figure the median of
   ``--runs`` rounds after one warm-up (in a round, each reader runs once, in
   turn): ``read_raw`` events/s (one Recording) and ``iter_raw`` events/s
   (65,536-event chunks, counted), beside faery's EVT decoder on the same file,
   its packets counted (like ``iter_raw``) and joined into one array (like
   ``read_raw``), with the like-for-like ratios, per file and for all the files
   of a format together (total events over total time).
2. A synthetic EVT 3.0 file of ``--big-gb`` GB written by ``Evt3Writer`` in
   chunks into a temporary folder, read back with ``iter_raw``: write and read
   events/s and the peak resident memory while streaming (sampled every 5 ms);
   then reconstructed cycle by cycle (``reconstruct_cycles``, exp weighting, one
   image per 50 ms cycle, discarded) with its time and peak resident memory; then
   deleted.

Prints a compact table and writes ``bench_decode.json`` to ``--out``.

    python benchmarks/bench_decode.py --data ../shared/data --big-gb 1.0 --out out/bench
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr.events import EVENT_DTYPE, TRIGGER_DTYPE
from asynhdr.io import prophesee as pr

_HERE = Path(__file__).resolve().parent


def _default_data() -> Path:
    env = os.environ.get("ASYNHDR_DATA")
    return Path(env) if env else _HERE.parent.parent / "shared" / "data"


def _rss_bytes() -> int:
    import psutil

    return int(psutil.Process().memory_info().rss)


def _max_rss_bytes() -> int:
    """Peak resident memory of this process so far (Linux reports kB)."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


class _RssSampler:
    """Sample this process's resident memory in a thread; keep the peak."""

    def __init__(self, period_s: float = 0.005) -> None:
        self.period_s = period_s
        self.peak = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, _rss_bytes())
            self._stop.wait(self.period_s)

    def __enter__(self) -> _RssSampler:
        self.peak = _rss_bytes()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss_bytes())


def _faery_decode(path: Path, dims: tuple[int, int], concatenate: bool) -> int:
    """Decode with faery's EVT decoder; count the events, or join them into one array."""
    import faery

    chunks = []
    n = 0
    with faery.evt.Decoder(path, dimensions_fallback=dims, version_fallback=None) as decoder:
        for packet in decoder:
            if "events" in packet:
                n += packet["events"].shape[0]
                if concatenate:
                    chunks.append(packet["events"])
    if concatenate and chunks:
        n = int(np.concatenate(chunks).shape[0])
    return n


def _stream_count(path: Path) -> int:
    """Decode with ``iter_raw`` in 65,536-event chunks, counting the events."""
    n = 0
    for events, _ in pr.iter_raw(path, chunk_events=65_536):
        n += events.shape[0]
    return n


def _median_times(fns: dict[str, Any], runs: int) -> tuple[dict[str, float], dict[str, Any]]:
    """Median seconds of each function over ``runs`` rounds, one call of each per round
    in turn (a machine that slows down slows all of them alike), after one warm-up
    call each (JIT cache load, file cache); also each function's last result."""
    results = {k: fn() for k, fn in fns.items()}
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(runs):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            results[k] = fn()
            times[k].append(time.perf_counter() - t0)
    return {k: float(np.median(v)) for k, v in times.items()}, results


def bench_real_files(data: Path, runs: int) -> list[dict[str, Any]]:
    rows = []
    for path in sorted((data / "events").glob("*.raw")):
        info = pr.raw_info(path)
        fns: dict[str, Any] = {
            "ours": lambda p=path: pr.read_raw(p).events.shape[0],
            "stream": lambda p=path: _stream_count(p),
        }
        if info["format"] in ("evt2", "evt3"):
            dims = (info["width"], info["height"])
            fns["faery"] = lambda p=path, d=dims: _faery_decode(p, d, False)
            fns["joined"] = lambda p=path, d=dims: _faery_decode(p, d, True)
        t, res = _median_times(fns, runs)
        n = int(res["ours"])
        row: dict[str, Any] = {
            "file": path.name,
            "format": info["format"],
            "events": n,
            "ours_s": t["ours"],
            "ours_mev_s": n / t["ours"] / 1e6,
            "ours_stream_s": t["stream"],
            "ours_stream_mev_s": res["stream"] / t["stream"] / 1e6,
        }
        if "faery" in t:
            row.update(
                faery_s=t["faery"],
                faery_events=res["faery"],
                faery_mev_s=res["faery"] / t["faery"] / 1e6,
                ratio_stream_vs_faery=(res["stream"] / t["stream"])
                / (res["faery"] / t["faery"]),
                faery_joined_s=t["joined"],
                faery_joined_mev_s=res["joined"] / t["joined"] / 1e6,
                ratio_vs_faery_joined=(n / t["ours"]) / (res["joined"] / t["joined"]),
            )
        rows.append(row)
    return rows


def _totals(rows: list[dict[str, Any]], fmt: str) -> dict[str, float] | None:
    """Every file of one format together: total events over total time."""
    sel = [r for r in rows if r["format"] == fmt and "faery_s" in r]
    if not sel:
        return None
    n = sum(r["events"] for r in sel)
    return {
        "files": len(sel),
        "events": n,
        "stream_mev_s": n / sum(r["ours_stream_s"] for r in sel) / 1e6,
        "faery_mev_s": n / sum(r["faery_s"] for r in sel) / 1e6,
        "ratio_stream_vs_faery": sum(r["faery_s"] for r in sel)
        / sum(r["ours_stream_s"] for r in sel),
        "read_raw_mev_s": n / sum(r["ours_s"] for r in sel) / 1e6,
        "ratio_vs_faery_joined": sum(r["faery_joined_s"] for r in sel)
        / sum(r["ours_s"] for r in sel),
    }


def _synthetic_chunk(
    rng: np.random.Generator, n: int, t0: int, width: int, height: int
) -> np.ndarray:
    """Random events, about two per µs, with a 32-column burst now and then."""
    ev = np.empty(n, dtype=EVENT_DTYPE)
    ev["t"] = t0 + np.cumsum(rng.integers(0, 2, n, dtype=np.int64))
    ev["x"] = rng.integers(0, width, n, dtype=np.uint16)
    ev["y"] = rng.integers(0, height, n, dtype=np.uint16)
    ev["p"] = rng.integers(0, 2, n, dtype=np.int8) * 2 - 1
    # bursts: 32 same-time events along a row, as a modulated panel makes them
    starts = np.flatnonzero(rng.random(n // 64 - 1) < 0.2) * 64
    idx = starts[:, None] + np.arange(32)[None, :]
    ev["t"][idx] = ev["t"][starts][:, None]
    ev["y"][idx] = ev["y"][starts][:, None]
    ev["p"][idx] = ev["p"][starts][:, None]
    ev["x"][idx] = (ev["x"][starts] // 32 * 32)[:, None] + np.arange(32, dtype=np.uint16)[None, :]
    return ev


def bench_big_file(
    big_gb: float, tmp_root: str | None, chunk_events: int, seed: int,
    reconstruct: bool = True,
) -> dict[str, Any]:
    width, height = 1280, 720
    target = int(big_gb * 1e9)
    rng = np.random.default_rng(seed)
    gen_chunk = 2_000_000
    with tempfile.TemporaryDirectory(dir=tmp_root, prefix="bench_decode_") as tmp:
        path = Path(tmp) / "synthetic_evt3.raw"
        t_next = 0
        n_written = 0
        n_trig = 0
        t_write = 0.0
        t_all = time.perf_counter()
        with pr.Evt3Writer(path, width=width, height=height) as writer:
            while writer.bytes_written < target:
                ev = _synthetic_chunk(rng, gen_chunk, t_next, width, height)
                t_end = int(ev["t"][-1])
                # a trigger edge every 25 ms (20 Hz modulation cycles, rising and falling)
                first = (t_next + 24_999) // 25_000
                tt = np.arange(first, t_end // 25_000 + 1, dtype=np.int64) * 25_000
                tr = np.empty(tt.shape[0], dtype=TRIGGER_DTYPE)
                tr["t"] = tt
                tr["rising"] = (tt // 25_000) % 2 == 0
                tr["id"] = 0
                t0 = time.perf_counter()
                writer.write(ev, tr)
                t_write += time.perf_counter() - t0
                n_written += ev.shape[0]
                n_trig += tr.shape[0]
                t_next = t_end + 1
        t_all = time.perf_counter() - t_all
        size = path.stat().st_size
        rss_before = _rss_bytes()
        n_read = 0
        n_trig_read = 0
        t0 = time.perf_counter()
        with _RssSampler() as sampler:
            for events, triggers in pr.iter_raw(path, chunk_events=chunk_events):
                n_read += events.shape[0]
                n_trig_read += triggers.shape[0]
        t_read = time.perf_counter() - t0
        rec: dict[str, Any] = {}
        if reconstruct:
            rec = _bench_reconstruct_file(path)
    if n_read != n_written or n_trig_read != n_trig:
        raise RuntimeError(
            f"read back {n_read} events / {n_trig_read} triggers, wrote {n_written} / {n_trig}"
        )
    return {
        "file_bytes": size,
        "events": n_written,
        "triggers": n_trig,
        "write_encode_s": t_write,
        "write_total_s": t_all,
        "write_mev_s": n_written / t_write / 1e6,
        "read_s": t_read,
        "read_mev_s": n_read / t_read / 1e6,
        "read_mb_s": size / t_read / 1e6,
        "chunk_events": chunk_events,
        "rss_before_read_mb": rss_before / 1e6,
        "peak_rss_during_read_mb": sampler.peak / 1e6,
        "process_max_rss_mb": _max_rss_bytes() / 1e6,
        **rec,
    }


def _bench_reconstruct_file(path: Path) -> dict[str, Any]:
    """``reconstruct_cycles`` (exp weighting) over every cycle of the file: one image per
    cycle, discarded; time and peak resident memory while it runs."""
    from asynhdr.io import open_source
    from asynhdr.reconstruct import reconstruct_cycles

    rss_before = _rss_bytes()
    t0 = time.perf_counter()
    with _RssSampler() as sampler:
        plan = reconstruct_cycles(open_source(path), method="exp")
        t_plan = time.perf_counter() - t0
        n_img = sum(1 for _ in plan)
    t_all = time.perf_counter() - t0
    return {
        "reconstruct_cycles": n_img,
        "reconstruct_plan_s": t_plan,
        "reconstruct_total_s": t_all,
        "reconstruct_cycles_per_s": n_img / (t_all - t_plan),
        "reconstruct_mev_s": plan.n_events / t_all / 1e6,
        "rss_before_reconstruct_mb": rss_before / 1e6,
        "peak_rss_during_reconstruct_mb": sampler.peak / 1e6,
    }


def _print_table(rows: list[dict[str, Any]], big: dict[str, Any] | None) -> None:
    print("Mev/s. read_raw: one Recording; stream: iter_raw, 65,536-event chunks counted;")
    print("faery: its EVT decoder's packets counted; joined: its packets joined into one array")
    print(f"{'file':<26} {'fmt':<5} {'events':>8} {'read_raw':>8} {'stream':>7} {'faery':>7} "
          f"{'stream/faery':>12} {'joined':>7} {'read_raw/joined':>15}")
    for r in rows:
        if "faery_mev_s" in r:
            f = (f"{r['faery_mev_s']:7.1f} {r['ratio_stream_vs_faery']:12.2f} "
                 f"{r['faery_joined_mev_s']:7.1f} {r['ratio_vs_faery_joined']:15.2f}")
        else:
            f = f"{'-':>7} {'-':>12} {'-':>7} {'-':>15}"
        print(f"{r['file']:<26} {r['format']:<5} {r['events']:>8} {r['ours_mev_s']:8.1f} "
              f"{r['ours_stream_mev_s']:7.1f} {f}")
    for fmt in ("evt2", "evt3"):
        tot = _totals(rows, fmt)
        if tot is not None:
            print(f"{'all ' + fmt + ' files':<26} {fmt:<5} {tot['events']:>8} "
                  f"{tot['read_raw_mev_s']:8.1f} {tot['stream_mev_s']:7.1f} "
                  f"{tot['faery_mev_s']:7.1f} {tot['ratio_stream_vs_faery']:12.2f} "
                  f"{'':>7} {tot['ratio_vs_faery_joined']:15.2f}")
    if big is not None:
        print(
            f"synthetic EVT3 {big['file_bytes'] / 1e9:.2f} GB, {big['events']:,} events, "
            f"{big['triggers']:,} triggers: write {big['write_mev_s']:.1f} Mev/s "
            f"(encode), {big['write_total_s']:.1f} s in all; iter_raw read "
            f"{big['read_mev_s']:.1f} Mev/s ({big['read_mb_s']:.0f} MB/s, {big['read_s']:.2f} s)"
        )
        print(
            f"resident memory: {big['rss_before_read_mb']:.0f} MB before reading, peak "
            f"{big['peak_rss_during_read_mb']:.0f} MB while streaming "
            f"(chunk_events={big['chunk_events']:,}); peak of the whole process so far "
            f"{big['process_max_rss_mb']:.0f} MB (earlier benchmarks in the run included)"
        )
        if "reconstruct_cycles" in big:
            print(
                f"reconstruct_cycles (exp), cycle by cycle: {big['reconstruct_cycles']:,} "
                f"images of 1280x720 in {big['reconstruct_total_s']:.1f} s (plan "
                f"{big['reconstruct_plan_s']:.1f} s, then "
                f"{big['reconstruct_cycles_per_s']:.1f} cycles/s; "
                f"{big['reconstruct_mev_s']:.1f} M events/s overall); resident memory "
                f"{big['rss_before_reconstruct_mb']:.0f} MB before, peak "
                f"{big['peak_rss_during_reconstruct_mb']:.0f} MB"
            )


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=_default_data(),
                        help="data folder holding events/*.raw (default ../shared/data)")
    parser.add_argument("--big-gb", type=float, default=1.0,
                        help="size of the synthetic EVT 3.0 file in GB (0 to skip)")
    parser.add_argument("--out", type=Path, default=Path("out") / "bench",
                        help="folder for bench_decode.json")
    parser.add_argument("--runs", type=int, default=31,
                        help="timed rounds per file (single calls: ms-scale, so many rounds)")
    parser.add_argument("--chunk-events", type=int, default=1_000_000,
                        help="iter_raw chunk size for the synthetic file")
    parser.add_argument("--tmp", default=None, help="folder for the synthetic file")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-reconstruct", action="store_true",
                        help="skip reconstructing the synthetic file cycle by cycle")
    args = parser.parse_args(argv)

    rows = bench_real_files(args.data, args.runs) if (args.data / "events").is_dir() else []
    if not rows:
        print(f"no .raw files under {args.data / 'events'}; real-file figures skipped",
              file=sys.stderr)
    big = (
        bench_big_file(args.big_gb, args.tmp, args.chunk_events, args.seed,
                       reconstruct=not args.no_reconstruct)
        if args.big_gb > 0
        else None
    )
    _print_table(rows, big)
    result = {
        "runs": args.runs,
        "cpu_count": os.cpu_count(),
        "files": rows,
        "totals": {fmt: _totals(rows, fmt) for fmt in ("evt2", "evt3")},
        "synthetic": big,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    out_path = args.out / "bench_decode.json"
    out_path.write_text(json.dumps(result, indent=2), encoding="utf-8")
    print(f"figures written to {out_path}")
    return result


if __name__ == "__main__":
    main()
