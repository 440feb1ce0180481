"""Memory reused instead of fresh: recycled arrays (reused only once nothing refers to them)
and the process's freed memory kept for its next allocations."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from asynhdr.events import EVENT_DTYPE, Recording, make_events
from asynhdr.io import prophesee as pr
from asynhdr.memory import Recycler, retain_freed_memory


def test_an_idle_array_is_reused_and_a_held_one_is_not() -> None:
    r = Recycler(keep=4, max_bytes=1 << 20)
    a = r.get(100, EVENT_DTYPE)
    address = a.ctypes.data
    b = r.get(100, EVENT_DTYPE)  # `a` is held: a new array
    assert b.ctypes.data != address
    del a
    c = r.get(100, EVENT_DTYPE)  # `a` was let go: its memory comes back
    assert c.ctypes.data == address


def test_a_view_keeps_its_array_out_of_reuse() -> None:
    r = Recycler(keep=4, max_bytes=1 << 20)
    a = r.get(100, EVENT_DTYPE)
    address = a.ctypes.data
    t = a["t"][10:20]  # a field view of a slice: its base is `a`
    del a
    assert r.get(100, EVENT_DTYPE).ctypes.data != address
    del t
    assert r.get(100, EVENT_DTYPE).ctypes.data == address


def test_other_lengths_dtypes_and_large_arrays_are_not_mixed_up() -> None:
    r = Recycler(keep=4, max_bytes=1000)
    a = r.get(10, EVENT_DTYPE)
    address = a.ctypes.data
    del a
    assert r.get(11, EVENT_DTYPE).ctypes.data != address
    assert r.get(10, np.dtype(np.uint8)).shape == (10,)
    big = r.get(1000, EVENT_DTYPE)  # 13 kB > max_bytes: never kept
    big_address = big.ctypes.data
    del big
    assert all(x.ctypes.data != big_address for x in r._pool)


def test_at_most_keep_arrays_are_kept() -> None:
    r = Recycler(keep=2, max_bytes=1 << 20)
    held = [r.get(50, EVENT_DTYPE) for _ in range(5)]
    assert len(r._pool) == 2
    assert held[-1] is r._pool[-1]


def test_chunks_a_caller_keeps_are_never_overwritten(tmp_path: Path) -> None:
    """Hold some chunks (whole, or as views) while iterating on: they keep their
    values; the chunks let go are reused and the stream still reads right."""
    rng = np.random.default_rng(3)
    n = 50_000
    ev = make_events(rng.integers(0, 64, n), rng.integers(0, 48, n),
                     rng.choice(np.array([-1, 1], np.int8), n),
                     np.sort(rng.integers(0, 2_000_000, n)))
    path = tmp_path / "rec.raw"
    pr.write_raw_evt3(path, Recording(ev, 64, 48))
    for _ in range(2):  # the second pass starts with the first pass's arrays kept
        kept: list[tuple[np.ndarray, np.ndarray]] = []
        parts = []
        for i, (chunk, _) in enumerate(pr.iter_raw(path, chunk_events=3_000)):
            parts.append(chunk.copy())
            if i % 3 == 0:
                kept.append((chunk, chunk.copy()))
            elif i % 3 == 1:
                kept.append((chunk["x"], chunk["x"].copy()))
        for held, at_yield in kept:
            np.testing.assert_array_equal(held, at_yield)
        np.testing.assert_array_equal(np.concatenate(parts), pr.read_raw(path).events)


_RSS_AFTER_FREE = """
import sys
import numpy as np
from asynhdr.memory import retain_freed_memory
took = retain_freed_memory(keep=sys.argv[1] == "keep")
a = np.ones(300 * 2**20 // 8)  # 300 MiB, every page written
del a
rss = [int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmRSS")]
print(int(took), rss[0] // 1024)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
                    reason="retain_freed_memory sets glibc's malloc")
@pytest.mark.parametrize("keep", [True, False])
def test_retained_memory_stays_with_the_process_and_returned_memory_leaves(keep: bool) -> None:
    """A freed 300 MiB array: kept in the process's resident memory with the setting,
    handed back to the system without it (glibc's default, which unmaps it)."""
    out = subprocess.run([sys.executable, "-c", _RSS_AFTER_FREE, "keep" if keep else "return"],
                         capture_output=True, text=True, check=True,
                         env={**os.environ, "ASYNHDR_RETAIN_MEMORY": "1"}).stdout.split()
    took, rss_mib = int(out[0]), int(out[1])
    assert took == 1
    if keep:
        assert rss_mib >= 300
    else:
        assert rss_mib < 250


def test_retaining_memory_can_be_refused_from_the_environment(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ASYNHDR_RETAIN_MEMORY", "0")
    assert retain_freed_memory() is False
