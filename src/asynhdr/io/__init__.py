"""Event recordings in and out: one entry point for every file format.

- :func:`open_recording` reads a whole file into a :class:`~asynhdr.events.Recording`;
- :func:`iter_chunks` streams ``(events, triggers)`` by event count or time window,
  with memory flat in file size for ``.raw``, ``.h5``, ``.aedat4``, ``.dat`` and text;
- :func:`write_recording` writes ``.npz``, ``.h5``/``.hdf5``, ``.raw`` (EVT 3.0),
  ``.txt``/``.csv``;
- :func:`recording_info` / :func:`scan_recording` describe a file in one streaming
  pass (geometry, counts, times, event rate, trigger edges).

The reader is chosen by the file's extension; the first bytes are checked against
the format's signature, so a file that is something else fails with a
``ValueError`` that lists :data:`SUPPORTED_FORMATS`. A missing file raises
``FileNotFoundError`` naming it.

Format modules: :mod:`asynhdr.io.prophesee` (``.raw``), :mod:`asynhdr.io.dat`,
:mod:`asynhdr.io.aedat`, :mod:`asynhdr.io.hdf5`, :mod:`asynhdr.io.npz`,
:mod:`asynhdr.io.text`. They are imported when first needed.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr.events import Recording, empty_events, empty_triggers

__all__ = [
    "SUPPORTED_FORMATS",
    "WRITABLE_FORMATS",
    "RecordingScan",
    "format_of",
    "iter_chunks",
    "open_recording",
    "recording_info",
    "scan_recording",
    "write_recording",
]

logger = logging.getLogger(__name__)

SUPPORTED_FORMATS: dict[str, str] = {
    ".raw": "Prophesee RAW, EVT 2.0 / 2.1 / 3.0 (Metavision, OpenEB), with triggers",
    ".dat": "Prophesee DAT, CD events (legacy Metavision)",
    ".aedat4": "iniVation AEDAT 4.0 (DV), uncompressed, LZ4 or Zstd, with triggers",
    ".h5": "HDF5, asynhdr layout (events/x,y,t,p; triggers/t,rising,id)",
    ".hdf5": "HDF5, asynhdr layout (same as .h5)",
    ".npz": "NumPy archive, asynhdr layout (events_x, ..., metadata)",
    ".txt": "text, one event a line: t x y p",
    ".csv": "text, one event a line: t,x,y,p",
}
"""File extension -> description of every format :func:`open_recording` reads."""

WRITABLE_FORMATS: tuple[str, ...] = (".npz", ".h5", ".hdf5", ".raw", ".txt", ".csv")
"""Extensions :func:`write_recording` writes (``.raw`` as EVT 3.0)."""

_KIND_BY_EXT = {
    ".raw": "raw", ".dat": "dat", ".aedat4": "aedat4", ".h5": "hdf5", ".hdf5": "hdf5",
    ".npz": "npz", ".txt": "text", ".csv": "text",
}

_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_AEDAT4_MAGIC = b"#!AER-DAT4.0"
_ZIP_MAGIC = b"PK\x03\x04"

DEFAULT_CHUNK_EVENTS = 1_000_000
"""Events per chunk of :func:`iter_chunks` when neither a count nor a window is given."""


# --------------------------------------------------------------------------- helpers


def _supported_text() -> str:
    return "supported formats: " + "; ".join(f"{k} ({v})" for k, v in SUPPORTED_FORMATS.items())


def _require_file(path: str | os.PathLike[str]) -> Path:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    if p.is_dir():
        raise ValueError(f"{p}: is a folder, not a recording file")
    return p


def _sniff(p: Path) -> str | None:
    """The format a file's first bytes reveal, or None."""
    try:
        with open(p, "rb") as f:
            head = f.read(1024)
    except OSError:
        return None
    if head.startswith(_AEDAT4_MAGIC):
        return "aedat4"
    if head.startswith(_HDF5_MAGIC):
        return "hdf5"
    if head.startswith(_ZIP_MAGIC):
        return "npz"
    if head.startswith((b"% evt", b"% format", b"% Date", b"% camera", b"% integrator")):
        return "raw"
    return None


def format_of(path: str | os.PathLike[str]) -> str:
    """The reader a path needs: ``raw``, ``dat``, ``aedat4``, ``hdf5``, ``npz`` or ``text``.

    Chosen from the extension (case-insensitive). When the file exists, its first
    bytes must show the signature of the formats that have one (AEDAT 4.0, HDF5,
    NPZ), and a ``.raw`` or ``.dat`` must not show another format's signature.
    Raises ``ValueError`` listing :data:`SUPPORTED_FORMATS` otherwise.
    """
    p = Path(path)
    ext = p.suffix.lower()
    kind = _KIND_BY_EXT.get(ext)
    if kind is None:
        seen = _sniff(p) if p.is_file() else None
        hint = f"; its content looks like {seen}" if seen else ""
        raise ValueError(f"{p}: unknown extension {ext or '(none)'!r}{hint}; {_supported_text()}")
    if p.is_file() and kind in ("aedat4", "hdf5", "npz", "raw", "dat"):
        seen = _sniff(p)
        # Formats with a signature must show it; the others must not show another's.
        mismatch = seen != kind if kind in ("aedat4", "hdf5", "npz") else (
            seen is not None and seen != "raw")
        if mismatch:
            with open(p, "rb") as f:
                head = f.read(16)
            what = f"looks like {seen}" if seen else f"starts with {head!r}"
            raise ValueError(
                f"{p}: not a {SUPPORTED_FORMATS[ext]} file ({what}); {_supported_text()}"
            )
    return kind


def _resolve_geometry(
    name: str,
    file_geometry: tuple[int, int] | None,
    width: int | None,
    height: int | None,
    *,
    source: str = "file",
) -> tuple[int, int, str] | None:
    """Geometry from the file, else from the arguments; the two must agree.

    Returns ``(width, height, where)`` or None when neither gives one.
    """
    if (width is None) != (height is None):
        raise ValueError(f"{name}: give both width and height, or neither")
    if file_geometry is not None:
        fw, fh = int(file_geometry[0]), int(file_geometry[1])
        if width is not None and (int(width), int(height)) != (fw, fh):  # type: ignore[arg-type]
            raise ValueError(
                f"{name}: the {source} says {fw}x{fh} but the arguments say "
                f"width={width}, height={height}"
            )
        return fw, fh, source
    if width is not None and height is not None:
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"{name}: width and height must be positive, got {width}x{height}")
        return int(width), int(height), "arguments"
    return None


def _int_field(name: str, field: str, values: Any, dtype: Any) -> np.ndarray:
    """``values`` as a 1-D array of integer ``dtype``; ``ValueError`` naming the file and
    field when it is not 1-D, not integer (bool is accepted for bool targets) or out of
    the dtype's range."""
    a = np.asarray(values)
    dt = np.dtype(dtype)
    if a.ndim != 1:
        raise ValueError(f"{name}: field {field!r} must be 1-D, got shape {a.shape}")
    if dt.kind == "b":
        if a.dtype.kind == "b":
            return a
        if a.dtype.kind not in "iu":
            raise ValueError(f"{name}: field {field!r} has dtype {a.dtype}; expected bool or 0/1")
        if a.size and ((a != 0) & (a != 1)).any():
            i = int(np.argmax((a != 0) & (a != 1)))
            raise ValueError(f"{name}: field {field!r} holds {a[i]} at index {i}; expected 0 or 1")
        return a.astype(bool)
    if a.dtype.kind == "b" or a.dtype.kind not in "iu":
        raise ValueError(
            f"{name}: field {field!r} has dtype {a.dtype}; expected integers ({dt})"
        )
    if a.size and a.dtype != dt:
        info = np.iinfo(dt)
        lo, hi = a.min(), a.max()
        if int(lo) < info.min or int(hi) > info.max:
            bad = int(np.argmax((a < info.min) | (a > info.max)))
            raise ValueError(
                f"{name}: field {field!r} holds {a[bad]} at index {bad}, outside the range "
                f"of {dt} ({info.min}..{info.max})"
            )
    return a.astype(dt, copy=False)


def _recording(name: str, **kwargs: Any) -> Recording:
    """Build a Recording; a validation error names the file."""
    try:
        return Recording(**kwargs)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from exc


def _pair_triggers(
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
    if len(parts) == 1:
        return parts[0]
    return np.concatenate(parts)


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


def _rechunk(
    source: Iterable[tuple[np.ndarray, np.ndarray]],
    *,
    chunk_events: int | None = None,
    window_us: int | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    if window_us is not None:
        return _rechunk_window(source, int(window_us))
    return _rechunk_count(source, int(chunk_events or DEFAULT_CHUNK_EVENTS))


def _check_time_unit_arg(name: str, kind: str, time_unit: str | None) -> None:
    if time_unit is not None and kind not in ("text", "hdf5"):
        raise ValueError(
            f"{name}: time_unit applies to text and HDF5 files only; {kind} files carry "
            "their own time base"
        )


# --------------------------------------------------------------------------- reading


def _raw_errors(exc: ValueError) -> ValueError:
    msg = str(exc)
    if "format" in msg or "header" in msg:
        return ValueError(f"{msg}. Files asynhdr reads: {_supported_text()}")
    return exc


def open_recording(
    path: str | os.PathLike[str],
    *,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
) -> Recording:
    """Read a whole event file, whatever its format, into a :class:`Recording`.

    Parameters
    ----------
    path : the file; its extension picks the reader (see :data:`SUPPORTED_FORMATS`).
    width, height : sensor geometry (pixels) for files that carry none (a ``.raw``
        header without geometry, text, a ``.dat`` without header); when the file
        has a geometry, these must agree with it.
    time_unit : text and HDF5 only: ``"us"``, ``"ms"``, ``"s"`` (or ``"auto"`` for
        text) when the file's times are not integer µs.

    Raises
    ------
    FileNotFoundError : the file does not exist.
    ValueError : unknown extension, content that is not the format the extension
        names, or a header the reader does not understand (the message lists the
        supported formats); malformed content (the message names the file, the
        place and the field).
    """
    p = _require_file(path)
    kind = format_of(p)
    _check_time_unit_arg(str(p), kind, time_unit)
    if kind == "raw":
        from asynhdr.io import prophesee

        try:
            return prophesee.read_raw(p, width=width, height=height)
        except ValueError as exc:
            raise _raw_errors(exc) from exc
    if kind == "dat":
        from asynhdr.io.dat import read_dat

        return read_dat(p, width=width, height=height)
    if kind == "aedat4":
        from asynhdr.io.aedat import read_aedat

        rec = read_aedat(p)
        _resolve_geometry(str(p), (rec.width, rec.height), width, height)
        return rec
    if kind == "hdf5":
        from asynhdr.io.hdf5 import load_hdf5

        return load_hdf5(p, width=width, height=height, time_unit=time_unit)
    if kind == "npz":
        from asynhdr.io.npz import load_npz

        rec = load_npz(p)
        _resolve_geometry(str(p), (rec.width, rec.height), width, height)
        return rec
    from asynhdr.io.text import read_text

    return read_text(p, width=width, height=height, time_unit=time_unit or "auto")


def _source(
    p: Path,
    kind: str,
    read_chunk: int,
    width: int | None,
    height: int | None,
    time_unit: str | None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The format's own chunked reader."""
    if kind == "raw":
        from asynhdr.io import prophesee

        try:
            return prophesee.iter_raw(p, chunk_events=read_chunk, width=width, height=height)
        except ValueError as exc:
            raise _raw_errors(exc) from exc
    if kind == "dat":
        from asynhdr.io.dat import iter_dat

        return iter_dat(p, chunk_events=read_chunk, width=width, height=height)
    if kind == "aedat4":
        from asynhdr.io.aedat import iter_aedat

        return iter_aedat(p)
    if kind == "hdf5":
        from asynhdr.io.hdf5 import iter_hdf5

        return iter_hdf5(p, chunk_events=read_chunk, time_unit=time_unit)
    if kind == "npz":
        from asynhdr.io.npz import load_npz

        rec = load_npz(p)
        ev = rec.events
        chunks = [ev[i : i + read_chunk] for i in range(0, ev.size, read_chunk)]
        return _pair_triggers(chunks, rec.triggers)
    from asynhdr.io.text import iter_text

    return iter_text(p, chunk_lines=read_chunk, time_unit=time_unit or "auto")


def iter_chunks(
    path: str | os.PathLike[str],
    *,
    chunk_events: int | None = None,
    window_us: int | None = None,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Stream a recording as ``(events, triggers)`` chunks, whatever its format.

    Give ``chunk_events`` (events per chunk; the last chunk may hold fewer) or
    ``window_us`` (time windows ``[t_first + k w, t_first + (k+1) w)`` with ``t_first``
    the first event's time; a window ends at the first event, in file order, at or
    past its end, and windows with no events are yielded empty). Neither: chunks of
    :data:`DEFAULT_CHUNK_EVENTS` events.

    Events keep file order. Triggers (sorted by time) come with the chunk whose
    events reach their time (count mode: ``t <= `` the latest event time so far;
    window mode: ``t <`` the window's end); the last chunk takes the rest. The
    chunks concatenate to exactly what :func:`open_recording` returns; at least one
    chunk (possibly empty) is yielded.

    Memory stays flat in file size for ``.raw``, ``.dat``, ``.aedat4``, ``.h5`` and
    text; ``.npz`` (compressed, not sliceable) is read whole. Errors as in
    :func:`open_recording`, raised when the iterator is first advanced at the latest.
    """
    if chunk_events is not None and window_us is not None:
        raise ValueError("iter_chunks: give chunk_events or window_us, not both")
    if chunk_events is not None and int(chunk_events) < 1:
        raise ValueError(f"iter_chunks: chunk_events must be >= 1, got {chunk_events}")
    if window_us is not None and int(window_us) < 1:
        raise ValueError(f"iter_chunks: window_us must be >= 1 µs, got {window_us}")
    p = _require_file(path)
    kind = format_of(p)
    _check_time_unit_arg(str(p), kind, time_unit)
    read_chunk = int(chunk_events) if chunk_events is not None else DEFAULT_CHUNK_EVENTS
    read_chunk = max(read_chunk, 1 << 16)
    src = _source(p, kind, read_chunk, width, height, time_unit)
    return _rechunk(src, chunk_events=chunk_events, window_us=window_us)


# --------------------------------------------------------------------------- writing


def write_recording(path: str | os.PathLike[str], recording: Recording) -> None:
    """Write a recording in the format its extension names (atomically).

    ``.npz`` and ``.h5``/``.hdf5`` keep everything (events, triggers, geometry,
    metadata) exactly; ``.raw`` is EVT 3.0 (events and triggers; geometry and
    metadata in the header); ``.txt``/``.csv`` write ``t x y p`` lines (integer µs)
    with geometry, metadata and triggers in ``#`` comment lines.
    """
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".npz":
        from asynhdr.io.npz import save_npz

        save_npz(p, recording)
    elif ext in (".h5", ".hdf5"):
        from asynhdr.io.hdf5 import save_hdf5

        save_hdf5(p, recording)
    elif ext == ".raw":
        from asynhdr.io import prophesee

        prophesee.write_raw_evt3(p, recording)
    elif ext in (".txt", ".csv"):
        from asynhdr.io.text import save_text

        save_text(p, recording, delimiter="," if ext == ".csv" else " ")
    else:
        raise ValueError(
            f"{p}: cannot write {ext or 'files without extension'!r}; writable: "
            + ", ".join(WRITABLE_FORMATS)
        )


# --------------------------------------------------------------------------- info


class _Histogram:
    """Events per bin over a growing time range (µs), coarsened when it gets too long.

    ``counts[k]`` holds the events of bin ``first + k``, bin ``j`` covering
    ``[j * bin_us, (j + 1) * bin_us)``. Bin numbers are Python ints and event times are
    divided before anything is subtracted, so no time in the int64 range overflows
    (a damaged file can hold any)."""

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
class RecordingScan:
    """What one streaming pass over a recording found.

    Attributes
    ----------
    info : JSON-serialisable description (see :func:`recording_info`).
    rate_counts : events per bin of ``rate_bin_us`` starting at ``rate_t0_us``.
    rate_bin_us : bin width (µs) of ``rate_counts`` (can be coarser than asked for a
        very long recording).
    rate_t0_us : start of the first bin (µs).
    triggers : every trigger edge of the recording (``TRIGGER_DTYPE``).
    """

    info: dict[str, Any]
    rate_counts: np.ndarray
    rate_bin_us: int
    rate_t0_us: int
    triggers: np.ndarray


def _pair_or_none(name: str, width: Any, height: Any, where: str) -> tuple[int, int] | None:
    if width is None and height is None:
        return None
    if width is None or height is None:
        raise ValueError(f"{name}: the {where} give only one of width and height; "
                         "expected both (pixels)")
    return int(width), int(height)


def _header_info(
    p: Path, kind: str, width: int | None, height: int | None, time_unit: str | None
) -> dict[str, Any]:
    """Format, sensor, geometry and format-specific facts read from the header only."""
    out: dict[str, Any] = {"format": kind, "sensor": None, "width": None, "height": None,
                           "geometry_source": None, "metadata": {}}
    if kind == "raw":
        from asynhdr.io import prophesee

        try:
            ri = prophesee.raw_info(p, width=width, height=height)
        except ValueError as exc:
            raise _raw_errors(exc) from exc
        header = dict(ri.get("header", {}))
        sensor_keys = ("camera_integrator_name", "integrator", "plugin_name", "sensor_name",
                       "sensor_generation", "generation", "serial_number")
        parts = [f"{k}={header[k]}" for k in sensor_keys if header.get(k)]
        out.update(format=ri["format"], width=ri["width"], height=ri["height"],
                   geometry_source=ri.get("geometry_source"),
                   sensor=", ".join(parts) or None,
                   metadata={k: v for k, v in ri.items() if k not in ("width", "height")})
    elif kind == "aedat4":
        from asynhdr.io.aedat import aedat_info

        ai = aedat_info(p)
        _resolve_geometry(str(p), (ai["width"], ai["height"]), width, height)
        out.update(sensor=ai["camera"], width=ai["width"], height=ai["height"],
                   geometry_source="file", metadata=ai)
    elif kind == "dat":
        from asynhdr.io.dat import dat_info

        di = dat_info(p)
        geo = _resolve_geometry(str(p), di["dimensions"], width, height, source="header")
        if geo is not None:
            out.update(width=geo[0], height=geo[1], geometry_source=geo[2])
        out["metadata"] = di
    elif kind == "hdf5":
        from asynhdr.io.hdf5 import hdf5_info

        hi = hdf5_info(p)
        fg = _pair_or_none(str(p), hi.get("width"), hi.get("height"), "attributes")
        geo = _resolve_geometry(str(p), fg, width, height, source="file attributes")
        if geo is not None:
            out.update(width=geo[0], height=geo[1], geometry_source=geo[2])
        out["metadata"] = hi
    elif kind == "npz":
        from asynhdr.io.npz import npz_info

        ni = npz_info(p)
        _resolve_geometry(str(p), (ni["width"], ni["height"]), width, height)
        out.update(width=ni["width"], height=ni["height"], geometry_source="file",
                   metadata=ni)
    else:
        from asynhdr.io.text import text_info

        ti = text_info(p)
        fg = _pair_or_none(str(p), ti.get("width"), ti.get("height"), "comments")
        geo = _resolve_geometry(str(p), fg, width, height, source="header comments")
        if geo is not None:
            out.update(width=geo[0], height=geo[1], geometry_source=geo[2])
        out["metadata"] = ti
    return out


def scan_recording(
    path: str | os.PathLike[str],
    *,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
    rate_bin_us: int = 1000,
    chunk_events: int = DEFAULT_CHUNK_EVENTS,
    progress: Callable[[int], None] | None = None,
) -> RecordingScan:
    """One streaming pass over a recording: description, event-rate histogram, triggers.

    ``progress(n_events_so_far)`` is called after each chunk. The peak rate is taken
    over 1 ms bins (``peak_rate_bin_us``; coarser only for recordings longer than
    2^26 ms). See :func:`recording_info` for the keys of ``info``.
    """
    if int(rate_bin_us) < 1:
        raise ValueError(f"scan_recording: rate_bin_us must be >= 1, got {rate_bin_us}")
    p = _require_file(path)
    kind = format_of(p)
    _check_time_unit_arg(str(p), kind, time_unit)
    head = _header_info(p, kind, width, height, time_unit)
    w_arg = head["width"] if head["width"] is not None else width
    h_arg = head["height"] if head["height"] is not None else height
    rate = _Histogram(rate_bin_us)
    peak = rate if int(rate_bin_us) == 1000 else _Histogram(1000)
    n = n_on = 0
    first_t: int | None = None
    last_t: int | None = None
    t_min: int | None = None
    t_max: int | None = None
    backward = 0
    x_max = y_max = -1
    trig_parts: list[np.ndarray] = []
    src = _source(p, kind, int(chunk_events), w_arg if kind != "text" else None,
                  h_arg if kind != "text" else None, time_unit)
    for ev, tr in src:
        if tr.size:
            trig_parts.append(tr)
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
        if peak is not rate:
            peak.add(t)
        if progress is not None:
            progress(n)
    triggers = np.concatenate(trig_parts) if trig_parts else empty_triggers()
    if head["width"] is None:
        if width is not None and height is not None:
            head.update(width=int(width), height=int(height), geometry_source="arguments")
        elif n:
            head.update(width=x_max + 1, height=y_max + 1,
                        geometry_source="inferred from the largest x and y")
    duration = (t_max - t_min) if n else 0  # type: ignore[operator]
    pk_t0, pk_counts = peak.result()
    if pk_counts.size:
        i = int(np.argmax(pk_counts))
        peak_rate = float(pk_counts[i]) * 1e6 / peak.bin_us
        peak_at = pk_t0 + i * peak.bin_us
    else:
        peak_rate, peak_at = 0.0, None
    edges: dict[str, int] = {}
    for ch in np.unique(triggers["id"]):
        sel = triggers["id"] == ch
        edges[f"channel {int(ch)} rising"] = int(np.count_nonzero(triggers["rising"][sel]))
        edges[f"channel {int(ch)} falling"] = int(np.count_nonzero(~triggers["rising"][sel]))
    info: dict[str, Any] = {
        "path": str(p),
        "format": head["format"],
        "format_description": SUPPORTED_FORMATS[p.suffix.lower()],
        "sensor": head["sensor"],
        "width": head["width"],
        "height": head["height"],
        "geometry_source": head["geometry_source"],
        "events": n,
        "on_events": n_on,
        "off_events": n - n_on,
        "first_t_us": first_t,
        "last_t_us": last_t,
        "min_t_us": t_min,
        "max_t_us": t_max,
        "duration_us": duration,
        "time_sorted": backward == 0,
        "backward_steps": backward,
        "mean_rate_hz": (n / (duration * 1e-6)) if duration > 0 else None,
        "peak_rate_hz": peak_rate,
        "peak_rate_bin_us": peak.bin_us,
        "peak_rate_at_us": peak_at,
        "triggers": int(triggers.size),
        "trigger_edges": edges,
        "trigger_records": head["metadata"].get("trigger_records"),
        "header": head["metadata"],
    }
    r_t0, r_counts = rate.result()
    return RecordingScan(info=info, rate_counts=r_counts, rate_bin_us=rate.bin_us,
                         rate_t0_us=r_t0, triggers=triggers)


def recording_info(
    path: str | os.PathLike[str],
    *,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
) -> dict[str, Any]:
    """Describe a recording in one streaming pass; a JSON-serialisable dict.

    Keys: ``path``, ``format`` (``evt2``/``evt21``/``evt3``, ``dat``, ``aedat4``,
    ``hdf5``, ``npz``, ``text``), ``format_description``, ``sensor`` (camera or
    sensor name when the file says), ``width``, ``height``, ``geometry_source``,
    ``events``, ``on_events``, ``off_events``, ``first_t_us`` / ``last_t_us`` (file
    order), ``min_t_us`` / ``max_t_us``, ``duration_us`` (max - min),
    ``time_sorted``, ``backward_steps``, ``mean_rate_hz`` (events / duration),
    ``peak_rate_hz`` (densest 1 ms bin × 1000) with ``peak_rate_bin_us`` and
    ``peak_rate_at_us``, ``triggers``, ``trigger_edges`` (``"channel N rising"`` ->
    count), ``trigger_records`` (AEDAT 4: every trigger record by type, external or
    not) and ``header`` (format-specific facts).
    """
    return scan_recording(path, width=width, height=height, time_unit=time_unit).info
