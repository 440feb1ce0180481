"""Event recordings in and out: a registry of formats and the file :class:`Source`.

Every format is one record (:class:`~asynhdr.io._common.Format`: how to recognise it,
read its header, stream its events, read it whole, write it) in :data:`FORMATS`:

- :func:`open_source` opens a file once as an :class:`asynhdr.source.Source` (geometry,
  triggers, metadata; chunks, time windows, event rate), the type every algorithm takes;
- :func:`open_recording` reads a whole file into a :class:`~asynhdr.events.Recording`;
- :func:`write_recording` writes a recording or any source, streaming, in the format the
  extension names (or ``format=``); :func:`convert` copies between any two formats;
- :func:`recording_info` describes a file in one streaming pass.

The format is chosen by the file's extension and checked against its first bytes (HDF5
files by their layout: asynhdr's or Metavision's); a file that is something else fails
with a ``ValueError`` that lists :data:`SUPPORTED_FORMATS`. A missing file raises
``FileNotFoundError`` naming it; a folder, a FIFO or a device is refused before it is
opened. Every geometry is capped (:data:`~asynhdr.io._common.MAX_SIDE_PX`) and every
time checked (:data:`~asynhdr.io._common.MAX_ABS_TIME_US`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr.events import Recording
from asynhdr.io import aedat, dat, hdf5, metavision, npz, prophesee, text
from asynhdr.io._common import (
    MAX_SIDE_PX,
    Format,
    Header,
    ReadOptions,
    check_geometry,
    check_times,
    require_file,
    resolve_geometry,
)
from asynhdr.source import Progress, Source, as_source

__all__ = [
    "FORMATS",
    "MAX_SIDE_PX",
    "SUPPORTED_FORMATS",
    "WRITABLE_FORMATS",
    "FileSource",
    "Format",
    "convert",
    "format_for",
    "iter_chunks",
    "open_recording",
    "open_source",
    "recording_info",
    "write_recording",
]

logger = logging.getLogger(__name__)

FORMATS: tuple[Format, ...] = (
    prophesee.FORMAT, dat.FORMAT, aedat.FORMAT, hdf5.FORMAT, metavision.FORMAT, npz.FORMAT,
    text.FORMAT,
)
"""Every format asynhdr reads (and most it writes), one record each."""

SUPPORTED_FORMATS: dict[str, str] = {
    ext: " / ".join(f.description for f in FORMATS if ext in f.extensions)
    for ext in dict.fromkeys(e for f in FORMATS for e in f.extensions)
}
"""File extension -> description of the formats read from it."""

WRITABLE_FORMATS: tuple[str, ...] = tuple(
    ext for ext in SUPPORTED_FORMATS
    if any(f.writer is not None and ext in f.extensions for f in FORMATS))
"""Extensions :func:`write_recording` writes."""


def _supported_text() -> str:
    return "supported formats: " + "; ".join(f"{k} ({v})" for k, v in SUPPORTED_FORMATS.items())


def _head(p: Path) -> bytes:
    with open(p, "rb") as f:
        return f.read(1024)


def format_for(path: str | os.PathLike[str], *, writing: bool = False) -> Format:
    """The format record for ``path``: by extension (case-insensitive) and, for a file
    being read, by its content (``.h5`` and ``.hdf5`` by their layout); for writing, the
    record whose first extension it is (``.h5``: asynhdr's HDF5, ``.hdf5``: Metavision's).
    ``ValueError`` listing :data:`SUPPORTED_FORMATS` when none fits."""
    p = Path(path)
    ext = p.suffix.lower()
    candidates = [f for f in FORMATS if ext in f.extensions]
    if writing:  # the record whose first extension it is, else any that writes it
        for f in sorted(candidates, key=lambda f: f.extensions[0] != ext):
            if f.writer is not None:
                return f
        raise ValueError(f"{p}: cannot write {ext or 'files without extension'!r}; writable: "
                         + ", ".join(WRITABLE_FORMATS))
    require_file(p)
    head = _head(p)
    for f in candidates:
        if f.sniff(p, head):
            return f
    seen = next((f for f in FORMATS if f.name != "text" and f.sniff(p, head)
                 and f.name not in ("raw", "dat")), None)
    what = f"looks like {seen.name}" if seen else f"starts with {head[:16]!r}"
    if not candidates:
        raise ValueError(f"{p}: unknown extension {ext or '(none)'!r}"
                         + (f"; its content {what}" if seen else "") + f"; {_supported_text()}")
    raise ValueError(f"{p}: not a {SUPPORTED_FORMATS[ext]} file ({what}); {_supported_text()}")


class FileSource(Source):
    """A recording file opened once (see :func:`open_source`)."""

    def __init__(self, path: Path, fmt: Format, header: Header, options: ReadOptions) -> None:
        self.path = path
        self.name = str(path)
        self.format = fmt
        self.header = header
        self.options = options

    @property
    def width(self) -> int:
        return self._geometry()[0]

    @property
    def height(self) -> int:
        return self._geometry()[1]

    @property
    def geometry_source(self) -> str:
        """Where the geometry came from (header, arguments, inferred from the events)."""
        return self._geometry()[2]

    def _geometry(self) -> tuple[int, int, str]:
        h = self.header
        if h.width is not None and h.height is not None:
            return int(h.width), int(h.height), str(h.geometry_source)
        sc = self.scan()
        if sc.events == 0:
            raise ValueError(f"{self.name}: no events and no geometry; pass width and height "
                             "(pixels)")
        w, hh = check_geometry(self.name, sc.x_max + 1, sc.y_max + 1, "the largest x and y")
        h.width, h.height, h.geometry_source = w, hh, "inferred from the largest x and y"
        h.metadata["geometry_inferred"] = True
        logger.warning("%s: no geometry in the file; using %dx%d from the largest x and y",
                       self.name, w, hh)
        return w, hh, str(h.geometry_source)

    @property
    def metadata(self) -> dict[str, Any]:
        return self.header.metadata

    def _header_triggers(self) -> np.ndarray | None:
        return self.header.triggers

    def _known_count(self) -> int | None:
        return self.header.events

    def _stream(self, read_chunk: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        chunks = self.format.chunks(self.path, self.header, read_chunk, self.options)
        if self.format.name == "raw":  # the decoder bounds its times
            return chunks
        return self._checked(chunks)

    def _checked(self, chunks: Iterator[tuple[np.ndarray, np.ndarray]]
                 ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        for ev, tr in chunks:
            check_times(self.name, ev["t"])
            check_times(self.name, tr["t"], "triggers")
            yield ev, tr

    def read(self) -> Recording:
        h = self.header
        if self.format.read is None:
            return super().read()
        opts = self.options
        if h.width is not None and opts.width is None:  # known (maybe inferred before)
            opts = replace(opts, width=h.width, height=h.height)
        rec = self.format.read(self.path, h, opts)
        if h.width is None:  # the reader inferred it (and said so)
            h.width, h.height = rec.width, rec.height
            h.geometry_source = "inferred from the largest x and y"
        check_times(self.name, rec.events["t"])
        check_times(self.name, rec.triggers["t"], "triggers")
        return rec

    def describe(self, *, progress: Progress | None = None) -> dict[str, Any]:
        """What the file holds, JSON-serialisable (see :func:`recording_info`)."""
        sc = self.scan(progress=progress)
        h = self.header
        tr = self.triggers
        edges: dict[str, int] = {}
        for ch in np.unique(tr["id"]):
            sel = tr["id"] == ch
            edges[f"channel {int(ch)} rising"] = int(np.count_nonzero(tr["rising"][sel]))
            edges[f"channel {int(ch)} falling"] = int(np.count_nonzero(~tr["rising"][sel]))
        duration = sc.duration_us
        if sc.rate_counts.size:
            i = int(np.argmax(sc.rate_counts))
            peak_at: int | None = sc.rate_t0_us + i * sc.rate_bin_us
        else:
            peak_at = None
        return {
            "path": self.name,
            "format": h.format,
            "format_description": self.format.description,
            # the file's own camera, else the one its metadata names (a converted file)
            "sensor": h.sensor if h.sensor not in (None, "asynhdr") else (
                (self.metadata or {}).get("camera") or h.sensor),
            "width": self.width if sc.events or h.width is not None else None,
            "height": self.height if sc.events or h.height is not None else None,
            "geometry_source": h.geometry_source,
            "events": sc.events,
            "on_events": sc.on_events,
            "off_events": sc.events - sc.on_events,
            "first_t_us": sc.first_t_us,
            "last_t_us": sc.last_t_us,
            "min_t_us": sc.min_t_us,
            "max_t_us": sc.max_t_us,
            "duration_us": duration,
            "time_sorted": sc.backward_steps == 0,
            "backward_steps": sc.backward_steps,
            "mean_rate_hz": (sc.events / (duration * 1e-6)) if duration > 0 else None,
            "peak_rate_hz": sc.peak_rate_hz,
            "peak_rate_bin_us": sc.rate_bin_us,
            "peak_rate_at_us": peak_at,
            "triggers": int(tr.size),
            "trigger_edges": edges,
            "trigger_records": h.facts.get("trigger_records"),
            "header": h.facts,
        }


def open_source(
    path: str | os.PathLike[str],
    *,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
) -> FileSource:
    """Open an event file, whatever its format, as a :class:`~asynhdr.source.Source`.

    Only the header is read now; the events are decoded when asked for, one chunk at a
    time. ``width``, ``height``: the sensor geometry (pixels) for files that carry none
    (a ``.raw`` header without geometry, text, a ``.dat`` without header); when the file
    has a geometry, they must agree with it. ``time_unit``: text and HDF5 only, ``"us"``,
    ``"ms"``, ``"s"`` (or ``"auto"`` for text) when the file's times are not integer µs.

    Raises ``FileNotFoundError`` (no such file) or ``ValueError`` (unknown extension,
    content that is not the format the extension names, a header the reader does not
    understand, a geometry beyond the cap; the message names the file and the field).
    """
    p = require_file(path)
    fmt = format_for(p)
    if time_unit is not None and not fmt.time_unit:
        raise ValueError(f"{p}: time_unit applies to text and HDF5 files only; {fmt.name} "
                         "files carry their own time base")
    opts = ReadOptions(width=width, height=height, time_unit=time_unit)
    try:
        header = fmt.header(p, opts)
    except ValueError as exc:
        text = str(exc)
        # a file that may be another format under a .raw name: say what asynhdr reads
        if fmt.name == "raw" and ("event format" in text or "not a Prophesee" in text
                                  or "no Prophesee header" in text):
            raise ValueError(f"{exc}. Files asynhdr reads: {_supported_text()}") from exc
        raise
    if header.width is None:
        geo = resolve_geometry(str(p), None, width, height)
        if geo is not None:
            header.width, header.height, header.geometry_source = geo
    return FileSource(p, fmt, header, opts)


def open_recording(
    path: str | os.PathLike[str],
    *,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
) -> Recording:
    """Read a whole event file into a :class:`Recording` (arguments and errors as in
    :func:`open_source`)."""
    return open_source(path, width=width, height=height, time_unit=time_unit).read()


def iter_chunks(
    path: str | os.PathLike[str],
    *,
    chunk_events: int | None = None,
    window_us: int | None = None,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Stream a file as ``(events, triggers)`` chunks: :meth:`Source.chunks` of
    :func:`open_source` (the header is read now, the events when the iterator is
    advanced)."""
    if chunk_events is not None and window_us is not None:
        raise ValueError("iter_chunks: give chunk_events or window_us, not both")
    src = open_source(path, width=width, height=height, time_unit=time_unit)
    return src.chunks(chunk_events=chunk_events, window_us=window_us)


def write_recording(
    path: str | os.PathLike[str],
    recording: Recording | Source,
    *,
    format: str | None = None,
    overwrite: bool = True,
    progress: Progress | None = None,
    time_shift_us: int = 0,
    **options: Any,
) -> None:
    """Write a recording, or any source streamed chunk by chunk, atomically, in the
    format ``path``'s extension names (``format=`` picks a record by name instead).

    Every writer stores the geometry, the triggers (where the format holds them) and
    the metadata (the rig and sensor of a simulated recording). ``.raw`` is EVT 3.0
    (``evt="2.0"``: EVT 2.0), ``.h5`` asynhdr's HDF5, ``.hdf5`` Metavision's HDF5,
    ``.npz``, ``.txt``/``.csv`` text, ``.dat`` Prophesee DAT. ``options`` go to the
    format's writer. ``overwrite`` False refuses an existing file. ``progress("write",
    events_written, total)`` is called after each chunk. ``time_shift_us`` is subtracted
    from every event and trigger time (a camera's clock since 1970 does not fit the
    formats that count from the recording's start); the metadata's ``time_shift_us``
    adds it up, so that ``t + time_shift_us`` is the time as recorded.
    """
    p = Path(path)
    if format is None:
        fmt = format_for(p, writing=True)
    else:
        fmt = next((f for f in FORMATS if f.name == format), None)  # type: ignore[assignment]
        if fmt is None or fmt.writer is None:
            raise ValueError(f"{p}: no writer for format {format!r}; writable: "
                             + ", ".join(f.name for f in FORMATS if f.writer))
    assert fmt.writer is not None
    src = as_source(recording)
    shift = int(time_shift_us)
    metadata = src.metadata
    if shift:
        metadata = dict(metadata or {})
        metadata["time_shift_us"] = int(metadata.get("time_shift_us", 0)) + shift
    writer = fmt.writer(p, width=src.width, height=src.height, metadata=metadata,
                        overwrite=overwrite, **options)
    total = src._known_count()
    done = 0
    with writer as w:
        for ev, tr in src.chunks():
            if shift:
                ev = ev.copy()
                ev["t"] -= shift
                tr = tr.copy()
                tr["t"] -= shift
            w.write(ev, tr)
            done += int(ev.size)
            if progress is not None:
                progress("write", done, total)


def convert(
    source: str | os.PathLike[str],
    target: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    progress: Progress | None = None,
    **options: Any,
) -> FileSource:
    """Copy an event file into another format, streaming (memory flat in its size);
    the target's format from its extension (see :func:`write_recording`). Returns the
    source (its :meth:`~asynhdr.source.Source.scan` is not needed and not done)."""
    src = open_source(source)
    write_recording(target, src, overwrite=overwrite, progress=progress, **options)
    return src


def recording_info(
    path: str | os.PathLike[str],
    *,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
) -> dict[str, Any]:
    """Describe a recording in one streaming pass; a JSON-serialisable dict.

    Keys: ``path``, ``format`` (``evt2``/``evt21``/``evt3``, ``dat``, ``aedat4``,
    ``hdf5``, ``metavision-hdf5``, ``npz``, ``text``), ``format_description``, ``sensor``
    (camera or sensor name when the file says), ``width``, ``height``,
    ``geometry_source``, ``events``, ``on_events``, ``off_events``, ``first_t_us`` /
    ``last_t_us`` (file order), ``min_t_us`` / ``max_t_us``, ``duration_us`` (max -
    min), ``time_sorted``, ``backward_steps``, ``mean_rate_hz`` (events / duration),
    ``peak_rate_hz`` (densest 1 ms bin x 1000) with ``peak_rate_bin_us`` and
    ``peak_rate_at_us``, ``triggers``, ``trigger_edges`` (``"channel N rising"`` ->
    count), ``trigger_records`` (AEDAT 4: every trigger record by type, external or
    not) and ``header`` (format-specific facts).
    """
    return open_source(path, width=width, height=height, time_unit=time_unit).describe()
