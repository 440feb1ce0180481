"""Stream a recording time window by time window (one modulation cycle at a time).

:func:`iter_windows` reads a file of any supported format in chunks and yields, for
each window ``[start_us[i], stop_us[i])``, the events whose time falls in it (in file
order) and the triggers in it, holding only the events of the windows not yet
complete: memory stays flat in file size.

Real streams step back in time by a few µs (DESIGN, section 4), so a window is
yielded only once the stream has gone ``holdback_us`` past its end. An event that
arrives later than that, for a window already yielded, is left out and counted; the
count is logged as a warning when the stream ends.

:func:`rate_histogram` is the event-rate histogram of a file in one streaming pass.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Iterator
from typing import NamedTuple

import numpy as np

from asynhdr.events import EVENT_DTYPE, TRIGGER_DTYPE

__all__ = ["DEFAULT_HOLDBACK_US", "Window", "iter_windows", "rate_histogram",
           "windows_from_chunks"]

logger = logging.getLogger(__name__)

DEFAULT_HOLDBACK_US = 1000
"""How far (µs) the stream must have gone past a window's end before it is yielded."""

_READ_CHUNK_EVENTS = 1 << 18


class Window(NamedTuple):
    """The events of one time window of a recording."""

    i: int
    """The window's position in the ``start_us`` given."""
    start_us: int
    stop_us: int
    """The window is ``[start_us, stop_us)``."""
    events: np.ndarray
    """``EVENT_DTYPE``, every event with ``start_us <= t < stop_us``, in file order."""
    triggers: np.ndarray
    """``TRIGGER_DTYPE``, the triggers in the window, sorted by time."""


def _check_windows(start_us: np.ndarray, stop_us: np.ndarray) -> None:
    if start_us.ndim != 1 or start_us.shape != stop_us.shape:
        raise ValueError(f"windows: start_us and stop_us must be 1-D and of one length, got "
                         f"shapes {start_us.shape} and {stop_us.shape}")
    if start_us.size > 1 and not (np.diff(start_us) > 0).all():
        i = int(np.argmax(np.diff(start_us) <= 0)) + 1
        raise ValueError(f"windows: start_us must increase strictly; window {i} starts at "
                         f"{int(start_us[i])} µs, after {int(start_us[i - 1])} µs")
    if (stop_us <= start_us).any():
        i = int(np.argmax(stop_us <= start_us))
        raise ValueError(f"windows: window {i} ends ({int(stop_us[i])} µs) before it starts "
                         f"({int(start_us[i])} µs)")


def windows_from_chunks(
    chunks: Iterable[tuple[np.ndarray, np.ndarray]],
    start_us: np.ndarray,
    stop_us: np.ndarray,
    *,
    holdback_us: int = DEFAULT_HOLDBACK_US,
    name: str = "recording",
) -> Iterator[Window]:
    """Cut a stream of ``(events, triggers)`` chunks (file order) into time windows.

    ``start_us`` increases strictly; windows may overlap (an event then goes to each
    window it falls in). Every window is yielded, in order, empty if nothing falls in
    it. See the module docstring for ``holdback_us``.
    """
    starts = np.asarray(start_us, dtype=np.int64)
    stops = np.asarray(stop_us, dtype=np.int64)
    _check_windows(starts, stops)
    if int(holdback_us) < 0:
        raise ValueError(f"windows: holdback_us must be >= 0, got {holdback_us}")
    n = starts.size
    # The latest stop among windows 0..i: an event at t can belong to a yielded window
    # only if t < that (checked exactly below).
    stop_so_far = np.maximum.accumulate(stops) if n else stops
    pending = np.empty(0, dtype=EVENT_DTYPE)  # events of windows i.., file order
    order = np.empty(0, dtype=np.int64)  # pending sorted stably by time
    t_sorted = np.empty(0, dtype=np.int64)
    pending_tr = np.empty(0, dtype=TRIGGER_DTYPE)
    i = 0
    t_seen: int | None = None
    late = 0

    def cut(k: int) -> Window:
        lo, hi = np.searchsorted(t_sorted, [starts[k], stops[k]], side="left")
        ev = pending[np.sort(order[lo:hi])]  # back to file order
        tt = pending_tr["t"]
        trs = pending_tr[(tt >= starts[k]) & (tt < stops[k])]
        return Window(k, int(starts[k]), int(stops[k]), ev,
                      trs[np.argsort(trs["t"], kind="stable")])

    def late_count(te: np.ndarray) -> int:
        """How many of the times ``te`` fall in one of the windows 0..i-1."""
        j = np.searchsorted(starts[:i], te, side="right") - 1
        maybe = (j >= 0) & (te < stop_so_far[np.maximum(j, 0)])
        hits = 0
        for tv, jv in zip(te[maybe], j[maybe], strict=True):  # rare: step-backs only
            hits += bool(((tv >= starts[: jv + 1]) & (tv < stops[: jv + 1])).any())
        return hits

    def drain(final: bool) -> Iterator[Window]:
        nonlocal i, pending, order, t_sorted, pending_tr
        while i < n and (final or (t_seen is not None
                                   and t_seen >= int(stops[i]) + int(holdback_us))):
            yield cut(i)
            i += 1
        if i < n:  # keep what windows i.. may still need
            lo = int(np.searchsorted(t_sorted, starts[i], side="left"))
            if lo:
                keep = np.sort(order[lo:])
                pending = pending[keep]
                order = np.argsort(pending["t"], kind="stable")
                t_sorted = pending["t"][order]
            pending_tr = pending_tr[pending_tr["t"] >= starts[i]]

    for ev, tr in chunks:
        if n == 0:
            continue
        if i >= n:  # every window yielded: what falls in one now is late
            if ev.size:
                late += late_count(ev["t"])
            continue
        if ev.size:
            t = ev["t"]
            hi = int(t.max())
            t_seen = hi if t_seen is None else max(t_seen, hi)
            early = t < starts[i]
            if early.any():  # in a gap between windows, or late for a yielded one
                if i > 0:
                    late += late_count(t[early])
                ev = ev[~early]
            if ev.size:
                pending = np.concatenate([pending, ev]) if pending.size else ev
                order = np.argsort(pending["t"], kind="stable")
                t_sorted = pending["t"][order]
        if tr.size:
            pending_tr = np.concatenate([pending_tr, tr]) if pending_tr.size else tr
        yield from drain(final=False)
    yield from drain(final=True)
    if late:
        logger.warning("%s: %d events stepped back more than %d µs behind the stream and "
                       "arrived after their window was yielded; they were left out",
                       name, late, int(holdback_us))


def iter_windows(
    path: str | os.PathLike[str],
    start_us: np.ndarray,
    stop_us: np.ndarray,
    *,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
    holdback_us: int = DEFAULT_HOLDBACK_US,
) -> Iterator[Window]:
    """Stream a recording window by window: a :class:`Window` for each
    ``[start_us[i], stop_us[i])`` (``start_us`` increasing strictly), with memory flat in
    file size. ``width``, ``height``, ``time_unit`` as in
    :func:`asynhdr.io.open_recording`. Errors are raised when the iterator is first
    advanced at the latest.
    """
    from asynhdr.io import iter_chunks

    chunks = iter_chunks(path, chunk_events=_READ_CHUNK_EVENTS, width=width, height=height,
                         time_unit=time_unit)
    return windows_from_chunks(chunks, np.asarray(start_us), np.asarray(stop_us),
                               holdback_us=holdback_us, name=str(path))


def rate_histogram(
    path: str | os.PathLike[str],
    *,
    bin_us: float,
    t0_us: int,
    n_bins: int,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """Events per bin ``[t0 + i bin, t0 + (i + 1) bin)``, ``i < n_bins``, in one
    streaming pass: :func:`asynhdr.segment.event_rate` chunk by chunk, summed; events
    outside the bins are not counted."""
    from asynhdr.io import iter_chunks
    from asynhdr.segment import event_rate

    if not bin_us > 0:
        raise ValueError(f"rate_histogram: bin_us must be positive, got {bin_us}")
    counts = np.zeros(max(int(n_bins), 0), dtype=np.int64)
    seen = 0
    for ev, _ in iter_chunks(path, chunk_events=_READ_CHUNK_EVENTS, width=width,
                             height=height, time_unit=time_unit):
        if ev.size == 0:
            continue
        part = event_rate(ev["t"], bin_us=bin_us, t0_us=t0_us)[: counts.size]
        counts[: part.size] += part
        seen += ev.size
        if progress is not None:
            progress(seen)
    return counts
