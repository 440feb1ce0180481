"""Arrays reused once nothing refers to them any more.

Writing to newly allocated memory costs a page fault per 4 KiB page the first time
(the kernel maps and zeroes it), a large share of decoding a small file. A
:class:`Recycler` keeps the arrays it has handed out and hands one out again only
when its reference count shows that the caller has let go of it and of every view
of it (a numpy view keeps its base array alive, so a view held anywhere keeps the
array out of reuse). Arrays it keeps are bounded in number and in bytes.
"""

from __future__ import annotations

import sys
import threading

import numpy as np

__all__ = ["Recycler"]


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
