"""Run every benchmark: ``make bench``. Figures are printed and written as JSON to --out."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
BENCHES = ("bench_sim", "bench_decode", "bench_io", "bench_ml")


def _data_dir() -> Path | None:
    env = os.environ.get("ASYNHDR_DATA")
    for c in ([Path(env)] if env else []) + [HERE.parent.parent / "shared" / "data"]:
        if (c / "manifest.json").is_file():
            return c
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("out/bench"))
    ap.add_argument("--only", nargs="*", default=list(BENCHES), choices=BENCHES)
    ap.add_argument("--big-gb", type=float, default=1.0,
                    help="size of the synthetic EVT 3.0 file streamed by bench_decode")
    args = ap.parse_args(argv)
    from asynhdr.memory import retain_freed_memory

    retain_freed_memory()  # as the asynhdr command does
    sys.path.insert(0, str(HERE))
    data = _data_dir()
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.only:
        print(f"\n=== {name} ===", flush=True)
        t0 = time.perf_counter()
        mod = importlib.import_module(name)
        bargs = ["--out", str(args.out)]
        if name in ("bench_decode", "bench_io"):
            if data is None:
                print("  real data not found (set ASYNHDR_DATA): real-file figures skipped")
            else:
                bargs += ["--data", str(data)]
        if name == "bench_decode":
            bargs += ["--big-gb", str(args.big_gb)]
        mod.main(bargs)
        print(f"  ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
