"""One stream type between event files and algorithms: the :class:`Source`.

A source is opened once and knows its sensor geometry (``width``, ``height``), its
trigger edges and its metadata (the rig and sensor when simulated); it hands out the
events in chunks (:meth:`Source.chunks`, by event count or time window), in arbitrary
time windows (:meth:`Source.windows`, one modulation cycle at a time), as an event-rate
histogram (:meth:`Source.event_rate`) and as one pass of facts (:meth:`Source.scan`).
Memory stays flat in the recording's size for every one of these.

An in-memory :class:`~asynhdr.events.Recording` is a source too
(:class:`RecordingSource`, or :func:`as_source`); files are opened by
:func:`asynhdr.io.open_source`, which implements the same type. Algorithms
(segmentation, reconstruction, calibration) take a source, never a path.

Events keep file order (times may step back by a few µs in real streams, see the
design notes); triggers are sorted by time.
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from asynhdr.events import (
    EVENT_DTYPE,
    TRIGGER_DTYPE,
    Recording,
    empty_events,
    empty_triggers,
)

__all__ = [
    "DEFAULT_CHUNK_EVENTS",
    "DEFAULT_HOLDBACK_US",
    "Progress",
    "RecordingSource",
    "Scan",
    "Source",
    "Window",
    "as_source",
    "pair_triggers",
    "rechunk",
    "windows_from_chunks",
]

logger = logging.getLogger(__name__)

DEFAULT_CHUNK_EVENTS = 1_000_000
"""Events per chunk of :meth:`Source.chunks` when neither a count nor a window is given."""

DEFAULT_HOLDBACK_US = 1000
"""How far (µs) the stream must have gone past a window's end before it is yielded."""

SCAN_RATE_BIN_US = 1000
"""Bin width (µs) of the event-rate histogram of :meth:`Source.scan` (the peak rate is
the densest bin x 1000)."""

_READ_CHUNK_EVENTS = 1 << 18


Progress = Callable[[str, int, "int | None"], None]
"""The progress protocol of the whole library: ``progress(stage, done, total)``.

``stage`` names the step ("scan", "reconstruct", ...), ``done`` counts what is done
(events, cycles) and ``total`` is the count when known, else None. Only the command line
draws bars from it."""


# --------------------------------------------------------------------------- chunks


def pair_triggers(
    chunks: Iterable[np.ndarray], triggers: np.ndarray
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Attach time-sorted ``triggers`` to a stream of event chunks.

    Each chunk gets the triggers up to the latest event time seen so far (file order),
    the last chunk everything left. At least one chunk (possibly empty) is yielded.
    """
    tt = triggers["t"]
    pos = 0
    cut: int | None = None
    prev: np.ndarray | None = None
    for ev in chunks:
        if prev is not None:
            if prev.size and pos < tt.shape[0]:  # no triggers left: no need to look
                c = int(prev["t"].max())
                cut = c if cut is None else max(cut, c)
            j = pos if cut is None else max(pos, int(np.searchsorted(tt, cut, side="right")))
            yield prev, triggers[pos:j]
            pos = j
        prev = ev
    yield (prev if prev is not None else empty_events()), triggers[pos:]


class _TriggerQueue:
    """Time-sorted triggers waiting to be attached to output chunks."""

    def __init__(self) -> None:
        self.pending = empty_triggers()

    def add(self, tr: np.ndarray) -> None:
        if tr.size:
            self.pending = tr.copy() if self.pending.size == 0 else np.concatenate(
                [self.pending, tr])

    def pop_upto(self, t_us: int, *, inclusive: bool) -> np.ndarray:
        j = int(np.searchsorted(self.pending["t"], t_us, side="right" if inclusive else "left"))
        out, self.pending = self.pending[:j], self.pending[j:]
        return out

    def pop_all(self) -> np.ndarray:
        out, self.pending = self.pending, empty_triggers()
        return out


def _concat(parts: list[np.ndarray]) -> np.ndarray:
    if not parts:
        return empty_events()
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _rechunk_count(
    source: Iterable[tuple[np.ndarray, np.ndarray]], chunk_events: int
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    buf: list[np.ndarray] = []
    nbuf = 0
    queue = _TriggerQueue()
    cut: int | None = None
    yielded = False
    for ev, tr in source:
        queue.add(tr)
        if ev.size:
            buf.append(ev)
            nbuf += ev.size
        while nbuf > chunk_events:
            allev = _concat(buf)
            out, rest = allev[:chunk_events], allev[chunk_events:]
            buf, nbuf = [rest], rest.size
            c = int(out["t"].max())
            cut = c if cut is None else max(cut, c)
            yield out, queue.pop_upto(cut, inclusive=True)
            yielded = True
    last = _concat(buf)
    trig = queue.pop_all()
    if last.size or trig.size or not yielded:
        yield last, trig


def _rechunk_window(
    source: Iterable[tuple[np.ndarray, np.ndarray]], window_us: int
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    buf: list[np.ndarray] = []
    queue = _TriggerQueue()
    end: int | None = None
    yielded = False
    for ev, tr in source:
        queue.add(tr)
        if ev.size == 0:
            continue
        if end is None:
            end = int(ev["t"][0]) + window_us
        runmax = np.maximum.accumulate(ev["t"])
        pos = 0
        while pos < ev.size:
            i = int(np.searchsorted(runmax, end, side="left"))
            if i >= ev.size:
                buf.append(ev[pos:])
                break
            buf.append(ev[pos:i])
            yield _concat(buf), queue.pop_upto(end, inclusive=False)
            yielded = True
            buf = []
            pos = i
            end += window_us
    last = _concat(buf)
    trig = queue.pop_all()
    if last.size or trig.size or not yielded:
        yield last, trig


def rechunk(
    source: Iterable[tuple[np.ndarray, np.ndarray]],
    *,
    chunk_events: int | None = None,
    window_us: int | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Cut a stream of ``(events, triggers)`` into chunks of ``chunk_events`` events, or
    into time windows ``[t_first + k w, t_first + (k + 1) w)`` of ``window_us`` (a window
    ends at the first event, in file order, at or past its end; empty windows are
    yielded). Triggers come with the chunk whose events reach their time; the last chunk
    takes the rest. See :meth:`Source.chunks`."""
    if chunk_events is not None and window_us is not None:
        raise ValueError("chunks: give chunk_events or window_us, not both")
    if chunk_events is not None and int(chunk_events) < 1:
        raise ValueError(f"chunks: chunk_events must be >= 1, got {chunk_events}")
    if window_us is not None and int(window_us) < 1:
        raise ValueError(f"chunks: window_us must be >= 1 µs, got {window_us}")
    if window_us is not None:
        return _rechunk_window(source, int(window_us))
    return _rechunk_count(source, int(chunk_events or DEFAULT_CHUNK_EVENTS))


# --------------------------------------------------------------------------- windows


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
    it, once the stream has gone ``holdback_us`` past its end (real streams step back
    by a few µs). An event that arrives later than that, for a window already yielded,
    is left out and counted; the count is logged as a warning when the stream ends.
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
    arrived: list[np.ndarray] = []  # chunks not yet in pending (joined when a window is cut)
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

    def join() -> None:
        """Move the arrived chunks into ``pending`` and sort it once (not per chunk: a
        window of millions of events arrives in hundreds of chunks)."""
        nonlocal pending, order, t_sorted
        if not arrived:
            return
        pending = np.concatenate([pending, *arrived]) if pending.size or len(arrived) > 1 \
            else arrived[0]
        arrived.clear()
        order = np.argsort(pending["t"], kind="stable")
        t_sorted = pending["t"][order]

    def drain(final: bool) -> Iterator[Window]:
        nonlocal i, pending, order, t_sorted, pending_tr
        if i < n and (final or (t_seen is not None
                                and t_seen >= int(stops[i]) + int(holdback_us))):
            join()
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
                arrived.append(ev)
        if tr.size:
            pending_tr = np.concatenate([pending_tr, tr]) if pending_tr.size else tr
        yield from drain(final=False)
    yield from drain(final=True)
    if late:
        logger.warning("%s: %d events stepped back more than %d µs behind the stream and "
                       "arrived after their window was yielded; they were left out",
                       name, late, int(holdback_us))


# --------------------------------------------------------------------------- scan


class _Histogram:
    """Events per bin over a growing time range (µs), coarsened when it gets too long.

    ``counts[k]`` holds the events of bin ``first + k``, bin ``j`` covering
    ``[j * bin_us, (j + 1) * bin_us)``. Bin numbers are Python ints and event times are
    divided before anything is subtracted, so no time in the int64 range overflows."""

    MAX_BINS = 1 << 26

    def __init__(self, bin_us: int) -> None:
        self.bin_us = int(bin_us)
        self.first: int | None = None
        self.counts = np.zeros(0, dtype=np.int64)

    def add(self, t: np.ndarray) -> None:
        if t.size == 0:
            return
        while True:
            b = t // self.bin_us
            lo_b, hi_b = int(b.min()), int(b.max())
            if self.first is None:
                self.first = lo_b - 64
                self.counts = np.zeros(1024, dtype=np.int64)
            lo, hi = lo_b - self.first, hi_b - self.first
            if hi - min(lo, 0) + 1 <= self.MAX_BINS:
                break
            self._coarsen()
        if lo < 0:
            pad = -lo + 64
            self.counts = np.concatenate([np.zeros(pad, dtype=np.int64), self.counts])
            self.first -= pad
            lo, hi = lo + pad, hi + pad
        if hi >= self.counts.size:
            grow = max(hi + 1, 2 * self.counts.size)
            self.counts = np.concatenate(
                [self.counts, np.zeros(min(grow, self.MAX_BINS) - self.counts.size,
                                       dtype=np.int64)])
        bc = np.bincount(b - lo_b)
        self.counts[lo : lo + bc.size] += bc

    def _coarsen(self) -> None:
        assert self.first is not None
        c = self.counts
        if self.first % 2:  # pairs of bins must start on an even bin
            c = np.concatenate([np.zeros(1, dtype=np.int64), c])
            self.first -= 1
        if c.size % 2:
            c = np.concatenate([c, np.zeros(1, dtype=np.int64)])
        self.counts = c.reshape(-1, 2).sum(axis=1)
        self.first //= 2
        self.bin_us *= 2

    def result(self) -> tuple[int, np.ndarray]:
        """``(t0_us, counts)`` trimmed to the first and last non-empty bins."""
        if self.first is None:
            return 0, np.zeros(0, dtype=np.int64)
        nz = np.flatnonzero(self.counts)
        a, b = int(nz[0]), int(nz[-1]) + 1
        return (self.first + a) * self.bin_us, self.counts[a:b].copy()


@dataclass(frozen=True, eq=False)
class Scan:
    """What one pass over a source's events found.

    Attributes
    ----------
    events, on_events : event counts (all, ON).
    first_t_us, last_t_us : first and last event time in file order (None: no events).
    min_t_us, max_t_us : earliest and latest event time (None: no events).
    backward_steps : how many times the time steps back in file order.
    x_max, y_max : largest column and row (-1: no events).
    triggers : every trigger edge (``TRIGGER_DTYPE``, sorted by time).
    rate_t0_us, rate_bin_us, rate_counts : events per bin ``[t0 + k bin, t0 + (k+1) bin)``
        (``SCAN_RATE_BIN_US``, coarser only for recordings longer than 2^26 bins).
    """

    events: int
    on_events: int
    first_t_us: int | None
    last_t_us: int | None
    min_t_us: int | None
    max_t_us: int | None
    backward_steps: int
    x_max: int
    y_max: int
    triggers: np.ndarray
    rate_t0_us: int
    rate_bin_us: int
    rate_counts: np.ndarray

    @property
    def duration_us(self) -> int:
        """``max_t_us - min_t_us`` (0 without events)."""
        return 0 if self.min_t_us is None else int(self.max_t_us) - self.min_t_us  # type: ignore[arg-type]

    @property
    def peak_rate_hz(self) -> float:
        """Events per second in the densest rate bin."""
        if self.rate_counts.size == 0:
            return 0.0
        return float(self.rate_counts.max()) * 1e6 / self.rate_bin_us


def _scan(chunks: Iterable[tuple[np.ndarray, np.ndarray]], progress: Progress | None,
          total: int | None) -> Scan:
    rate = _Histogram(SCAN_RATE_BIN_US)
    n = n_on = backward = 0
    first_t = last_t = t_min = t_max = None
    x_max = y_max = -1
    trig: list[np.ndarray] = []
    for ev, tr in chunks:
        if tr.size:
            trig.append(tr)
        if ev.size == 0:
            continue
        t = ev["t"]
        if first_t is None:
            first_t = int(t[0])
        elif int(t[0]) < last_t:  # type: ignore[operator]
            backward += 1
        backward += int(np.count_nonzero(t[1:] < t[:-1]))
        last_t = int(t[-1])
        lo, hi = int(t.min()), int(t.max())
        t_min = lo if t_min is None else min(t_min, lo)
        t_max = hi if t_max is None else max(t_max, hi)
        n += ev.size
        n_on += int(np.count_nonzero(ev["p"] > 0))
        x_max = max(x_max, int(ev["x"].max()))
        y_max = max(y_max, int(ev["y"].max()))
        rate.add(t)
        if progress is not None:
            progress("scan", n, total)
    triggers = np.concatenate(trig) if trig else empty_triggers()
    triggers = triggers[np.argsort(triggers["t"], kind="stable")]
    r_t0, r_counts = rate.result()
    return Scan(events=n, on_events=n_on, first_t_us=first_t, last_t_us=last_t,
                min_t_us=t_min, max_t_us=t_max, backward_steps=backward, x_max=x_max,
                y_max=y_max, triggers=triggers, rate_t0_us=r_t0, rate_bin_us=rate.bin_us,
                rate_counts=r_counts)


# --------------------------------------------------------------------------- sources


class Source(abc.ABC):
    """A recording opened once: geometry, triggers, metadata, and its events on demand.

    Subclasses implement :meth:`_stream` (the events in file order, in chunks of about
    ``read_chunk`` events, each with the triggers that belong to it) and set ``name``;
    the geometry, the metadata and, where they are known without reading the events,
    the triggers and the event count come from :meth:`_header_triggers`,
    :attr:`width`, :attr:`height`, :attr:`metadata`.
    """

    name: str = "recording"

    @property
    @abc.abstractmethod
    def width(self) -> int:
        """Sensor width, pixels."""

    @property
    @abc.abstractmethod
    def height(self) -> int:
        """Sensor height, pixels."""

    @property
    @abc.abstractmethod
    def metadata(self) -> dict[str, Any]:
        """JSON-serialisable facts: the rig and sensor of a simulated recording, the
        format and header of a file."""

    @abc.abstractmethod
    def _stream(self, read_chunk: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """``(events, triggers)`` in file order, about ``read_chunk`` events a chunk."""

    def _header_triggers(self) -> np.ndarray | None:
        """The trigger edges when known without reading the events, else None."""
        return None

    # ------------------------------------------------------------------ derived

    @property
    def triggers(self) -> np.ndarray:
        """Every trigger edge, sorted by time (one pass over the events when the
        format keeps them among the events)."""
        tr = self._header_triggers()
        return self.scan().triggers if tr is None else tr

    def chunks(
        self, *, chunk_events: int | None = None, window_us: int | None = None
    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Stream the recording as ``(events, triggers)`` chunks: ``chunk_events`` events
        each (the last may hold fewer), or time windows of ``window_us`` (see
        :func:`rechunk`); neither: :data:`DEFAULT_CHUNK_EVENTS`. The chunks concatenate
        to :meth:`read`; at least one (possibly empty) is yielded. Errors come when the
        iterator is first advanced at the latest."""
        read = max(int(chunk_events) if chunk_events else DEFAULT_CHUNK_EVENTS, 1 << 16)
        return rechunk(self._stream(read), chunk_events=chunk_events, window_us=window_us)

    def windows(
        self,
        start_us: np.ndarray,
        stop_us: np.ndarray,
        *,
        holdback_us: int = DEFAULT_HOLDBACK_US,
    ) -> Iterator[Window]:
        """A :class:`Window` for each ``[start_us[i], stop_us[i])`` (``start_us``
        increasing strictly), in one pass, with memory flat in the recording's size;
        see :func:`windows_from_chunks`."""
        return windows_from_chunks(self._stream(_READ_CHUNK_EVENTS), np.asarray(start_us),
                                   np.asarray(stop_us), holdback_us=holdback_us,
                                   name=self.name)

    def event_rate(
        self,
        *,
        bin_us: float,
        t0_us: int,
        n_bins: int,
        progress: Progress | None = None,
    ) -> np.ndarray:
        """Events per bin ``[t0 + i bin, t0 + (i + 1) bin)``, ``i < n_bins`` (int64), in
        one pass; events outside the bins are not counted."""
        if not bin_us > 0:
            raise ValueError(f"event_rate: bin_us must be positive, got {bin_us}")
        counts = np.zeros(max(int(n_bins), 0), dtype=np.int64)
        seen = 0
        for ev, _ in self._stream(_READ_CHUNK_EVENTS):
            if ev.size == 0:
                continue
            idx = np.floor((ev["t"] - int(t0_us)) / float(bin_us)).astype(np.int64)
            idx = idx[(idx >= 0) & (idx < counts.size)]
            counts += np.bincount(idx, minlength=counts.size)
            seen += ev.size
            if progress is not None:
                progress("event rate", seen, None)
        return counts

    def scan(self, *, progress: Progress | None = None) -> Scan:
        """Counts, time range, trigger edges and the event rate, from one pass over the
        events (done once; later calls return the same :class:`Scan`)."""
        cached = self.__dict__.get("_scan_result")
        if cached is None:
            cached = _scan(self._stream(_READ_CHUNK_EVENTS), progress, self._known_count())
            self.__dict__["_scan_result"] = cached
        return cached

    def _known_count(self) -> int | None:
        """The event count when known without reading the events."""
        return None

    def read(self) -> Recording:
        """The whole recording in memory."""
        ev: list[np.ndarray] = []
        tr: list[np.ndarray] = []
        for e, t in self._stream(DEFAULT_CHUNK_EVENTS):
            ev.append(e)
            tr.append(t)
        triggers = np.concatenate(tr) if tr else empty_triggers()
        return Recording(events=_concat(ev), width=self.width, height=self.height,
                         triggers=triggers[np.argsort(triggers["t"], kind="stable")],
                         metadata=self.metadata)

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}>"


class RecordingSource(Source):
    """An in-memory :class:`~asynhdr.events.Recording` as a :class:`Source`."""

    def __init__(self, recording: Recording, *, name: str = "recording") -> None:
        self.recording = recording
        self.name = name

    @property
    def width(self) -> int:
        return int(self.recording.width)

    @property
    def height(self) -> int:
        return int(self.recording.height)

    @property
    def metadata(self) -> dict[str, Any]:
        return self.recording.metadata

    def _header_triggers(self) -> np.ndarray:
        return self.recording.triggers

    def _known_count(self) -> int:
        return int(self.recording.events.size)

    def _stream(self, read_chunk: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        ev = self.recording.events
        parts = [ev[i : i + read_chunk] for i in range(0, ev.size, read_chunk)]
        return pair_triggers(parts, self.recording.triggers)

    def read(self) -> Recording:
        return self.recording


def as_source(obj: Source | Recording, *, name: str = "recording") -> Source:
    """``obj`` itself when it is a :class:`Source`, a :class:`RecordingSource` when it is
    a :class:`~asynhdr.events.Recording`; ``TypeError`` otherwise."""
    if isinstance(obj, Source):
        return obj
    if isinstance(obj, Recording):
        return RecordingSource(obj, name=name)
    raise TypeError(f"expected a Source or a Recording, got {type(obj).__name__}")
