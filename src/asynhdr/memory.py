"""Memory written again instead of fresh: the page faults of new memory.

Writing to newly allocated memory costs a page fault per page the first time (the
kernel maps and zeroes it; in a virtual machine whose freed pages go back to the host,
the host faults too). Two remedies, one per scale:

- :class:`Recycler` keeps the arrays it has handed out and hands one out again only
  when its reference count shows that the caller has let go of it and of every view
  of it (a numpy view keeps its base array alive, so a view held anywhere keeps the
  array out of reuse). Arrays it keeps are bounded in number and in bytes. The
  decoders use it for their small chunks.
- :func:`retain_freed_memory` tells the C allocator to keep what the process frees
  for its next allocations instead of handing it back to the system. A simulated
  cycle of a 1280x720 sensor allocates and frees hundreds of MB (slots, sort keys,
  events); with this every cycle after the first writes into memory already mapped.
  The ``asynhdr`` command and the benchmarks call it; a program that simulates or
  reconstructs in its own process can too. The price: the process keeps its peak
  memory until it exits.
"""

from __future__ import annotations

import ctypes
import os
import sys
import threading

import numpy as np

__all__ = ["Recycler", "retain_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_KEEP_ENV = "ASYNHDR_RETAIN_MEMORY"


def retain_freed_memory(keep: bool = True) -> bool:
    """Keep freed memory in the process for reuse (glibc's ``malloc``: no allocation
    served by its own ``mmap``, which ``free`` would unmap, and no trimming of the heap
    below 2 GiB of free space); ``keep=False`` goes back to glibc's settings (allocations
    from 128 KiB by ``mmap``, the heap trimmed above 128 KiB free). Returns whether the
    allocator took the settings: False where the C library is not glibc, and, for
    ``keep``, when the environment variable ``ASYNHDR_RETAIN_MEMORY`` is ``0``.
    Allocations made before keep their ``mmap``."""
    if keep and os.environ.get(_KEEP_ENV, "1").strip() == "0":
        return False
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library the process runs on
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    mmap_max, trim = (0, 2**31 - 1) if keep else (65536, 128 * 1024)
    return bool(mallopt(_M_MMAP_MAX, mmap_max)) and bool(mallopt(_M_TRIM_THRESHOLD, trim))


def _refs(pool: list[np.ndarray], i: int) -> int:
    """References to ``pool[i]``, counted the same way for the baseline and the checks."""
    return sys.getrefcount(pool[i])


def _idle_refs() -> int:
    """References an array held only by a recycler's list shows in :func:`_refs`."""
    probe = [np.empty(1)]
    return _refs(probe, 0)


_IDLE_REFS = _idle_refs()


class Recycler:
    """Hand out 1-D arrays of a given length and dtype, reusing idle ones.

    ``keep``: most arrays kept; ``max_bytes``: larger arrays are never kept.
    Thread-safe. :meth:`get` returns uninitialised memory, like ``np.empty``.
    """

    def __init__(self, keep: int, max_bytes: int) -> None:
        self.keep = int(keep)
        self.max_bytes = int(max_bytes)
        self._pool: list[np.ndarray] = []
        self._lock = threading.Lock()

    def get(self, n: int, dtype: np.dtype) -> np.ndarray:
        """An array of ``n`` elements of ``dtype``: an idle kept one, or a new one."""
        with self._lock:
            pool = self._pool
            for i in range(len(pool)):
                a = pool[i]
                if a.shape[0] == n and a.dtype == dtype:
                    del a
                    if _refs(pool, i) == _IDLE_REFS:
                        pool.append(pool.pop(i))  # most recently used last
                        return pool[-1]
        out = np.empty(n, dtype=dtype)
        if out.nbytes <= self.max_bytes and self.keep > 0:
            with self._lock:
                self._pool.append(out)
                if len(self._pool) > self.keep:
                    del self._pool[0]  # the least recently used
        return out

    def clear(self) -> None:
        """Forget every kept array (each is freed once nothing else refers to it)."""
        with self._lock:
            self._pool.clear()
