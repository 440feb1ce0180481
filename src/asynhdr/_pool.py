"""The process's worker threads for compiled (``nogil``) kernels, and the order in which
numba's parallel loops take blocks of pixels.

One pool a process, with one thread fewer than numba's thread count
(``NUMBA_NUM_THREADS``): the calling thread does a share of the work itself.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

__all__ = ["block_order", "executor", "worker_threads"]

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_pool_pid = -1


def worker_threads() -> int:
    """Threads that may work at once, the caller's included (``NUMBA_NUM_THREADS``)."""
    return max(1, int(getattr(numba.config, "NUMBA_NUM_THREADS", 1)))


def _forget() -> None:
    """In a forked child: the parent's threads are gone; start afresh on first use."""
    global _pool, _lock
    _pool = None
    _lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget)


def executor() -> ThreadPoolExecutor:
    """The process's pool (``worker_threads() - 1`` threads, at least one)."""
    global _pool, _pool_pid
    with _lock:
        if _pool is None or _pool_pid != os.getpid():
            _pool = ThreadPoolExecutor(
                max_workers=max(1, worker_threads() - 1), thread_name_prefix="asynhdr"
            )
            _pool_pid = os.getpid()
        return _pool


def block_order(n: int, block: int) -> np.ndarray:
    """Indices of the ``ceil(n / block)`` blocks of ``n`` pixels in an order that gives
    every thread a share of each part of the image: numba's parallel loop hands each thread
    one contiguous range of its iterations, and an image's cost is seldom even (a bright
    sky above a dark ground). Iteration ``i`` of such a loop takes block ``order[i]``."""
    nblk = max(1, (n + block - 1) // block)
    threads = max(1, numba.get_num_threads())
    return np.argsort(np.arange(nblk) % threads, kind="stable").astype(np.int64)
