"""iniVation AEDAT 4.0 recordings (``.aedat4``).

The container is walked and its event and trigger packets decoded here
(:mod:`asynhdr.io._aedat_decode`: LZ4 and Zstd by cramjam into reused memory, dv's
flatbuffers parsed with every offset checked), window by window: memory stays flat in
file size, and damaged data raise a ``ValueError`` naming the file and the packet.
dv-processing, iniVation's library, reads the same files to the same result (the tests
compare the two on every compression), but it is not used here: it never returns from
some damaged files (an LZ4 packet whose decoding fails without consuming input, or a
damaged file data table, which a check of the LZ4 data cannot see), holding the GIL
meanwhile, and it copies every packet out once more.

Events become ``EVENT_DTYPE`` (AEDAT polarity 1 -> +1 ON, 0 -> -1 OFF; times in
µs as recorded, often Unix time).

Triggers: an AEDAT trigger record has a type. Only the external-input types mark
modulation cycles, and become ``TRIGGER_DTYPE`` edges:

==================================  ===========  ==
TriggerType                         rising       id
==================================  ===========  ==
EXTERNAL_SIGNAL_RISING_EDGE         True         0
EXTERNAL_SIGNAL_FALLING_EDGE        False        0
EXTERNAL_SIGNAL_PULSE               True         0
EXTERNAL_GENERATOR_RISING_EDGE      True         1
EXTERNAL_GENERATOR_FALLING_EDGE     False        1
==================================  ===========  ==

Every record, external or not (APS frame and exposure markers, timestamp resets),
is counted by type in ``metadata["trigger_records"]``.

Each event packet is converted in one compiled pass that also checks every pixel
against the event stream's resolution: an event outside it raises a ``ValueError``
naming the file, the event's index and the bound. That pass is the whole check: the
``Recording`` is built with :meth:`~asynhdr.events.Recording.from_checked` and does not
scan the events again.
"""

from __future__ import annotations

import html
import json
import logging
import os
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numba
import numpy as np

from asynhdr.events import (
    EVENT_DTYPE,
    TRIGGER_DTYPE,
    Recording,
    empty_triggers,
    validate_events,
    validate_triggers,
)
from asynhdr.io import _aedat_decode as _own
from asynhdr.io._common import (
    FileWriter,
    Format,
    Header,
    ReadOptions,
    check_geometry,
    json_metadata,
    require_file,
)
from asynhdr.source import pair_triggers, rechunk

__all__ = ["EXTERNAL_TRIGGER_TYPES", "FORMAT", "AedatWriter", "aedat_info", "iter_aedat",
           "read_aedat"]

METADATA_KEY = "asynhdr_metadata"
"""Attribute of the event stream's ``info`` node holding the recording's metadata (JSON)."""

logger = logging.getLogger(__name__)

EXTERNAL_TRIGGER_TYPES: dict[str, tuple[bool, int]] = {
    "EXTERNAL_SIGNAL_RISING_EDGE": (True, 0),
    "EXTERNAL_SIGNAL_FALLING_EDGE": (False, 0),
    "EXTERNAL_SIGNAL_PULSE": (True, 0),
    "EXTERNAL_GENERATOR_RISING_EDGE": (True, 1),
    "EXTERNAL_GENERATOR_FALLING_EDGE": (False, 1),
}
"""AEDAT trigger type name -> (rising, id) of the edge it becomes."""


_MAX_INITIAL_EVENTS = 1 << 24  # 218 MB of EVENT_DTYPE reserved at most before it grows
_COPY_TRIM_BYTES = 32 << 20  # glibc's largest heap-served block (DEFAULT_MMAP_THRESHOLD_MAX)
# Events of decoded packets held (in the arena) before converting: 8 MB.
_GROUP_EVENTS = 1 << 19


@numba.njit(cache=True, nogil=True)
def _convert_dv(src, dst, start, width, height):  # pragma: no cover - compiled
    """dv's event records -> ``EVENT_DTYPE`` rows ``dst[start : start + len(src)]``.

    One pass: ``t`` = timestamp (µs), ``x``, ``y`` as recorded, ``p`` = +1 where the
    AEDAT polarity is nonzero (ON), else -1 (OFF). Returns whether every event lies
    inside the sensor, ``0 <= x < width`` and ``0 <= y < height`` (the int16 ``x``, ``y``
    are read as uint16, so a negative one is out of range; no branch in the loop).
    """
    x_max = np.uint16(0)
    y_max = np.uint16(0)
    # Unsigned indices: numba leaves out negative-index wraparound (a fifth faster).
    m = np.uint64(src.shape[0])
    first = np.uint64(start)
    i = np.uint64(0)
    while i < m:
        s = src[i]
        d = dst[first + i]
        ux = np.uint16(s.x)
        uy = np.uint16(s.y)
        x_max = max(x_max, ux)
        y_max = max(y_max, uy)
        d.x = ux
        d.y = uy
        d.p = np.int8(2 * (s.polarity != 0) - 1)
        d.t = s.timestamp
        i += np.uint64(1)
    return x_max < width and y_max < height


def _raise_outside(p: Path, a: np.ndarray, start: int, width: int, height: int) -> None:
    """``ValueError`` naming the file, the first event of dv's records ``a`` outside
    the sensor (its index in the file: ``start`` + index in ``a``) and the bound."""
    x, y = a["x"].astype(np.int64), a["y"].astype(np.int64)
    bad = int(np.argmax((x < 0) | (x >= width) | (y < 0) | (y >= height)))
    if not 0 <= x[bad] < width:
        what = f"x={int(x[bad])} is outside the sensor (width={width})"
    else:
        what = f"y={int(y[bad])} is outside the sensor (height={height})"
    raise ValueError(f"{p}: events: event {start + bad} at {what}; the geometry is the "
                     "event stream's resolution")


def _edges(codes: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
    """Trigger records (type codes 0-255, timestamps) -> external edges as
    TRIGGER_DTYPE (sorted by time, stably) and the count of every record by type name."""
    per_code = np.bincount(codes, minlength=256)
    counts = {_own.TRIGGER_TYPE_NAMES.get(code, f"TRIGGER_TYPE_{code}"): int(per_code[code])
              for code in np.flatnonzero(per_code).tolist()}
    keep = _EDGE_KEEP[codes]
    if not keep.any():
        return empty_triggers(), counts
    kept = codes[keep]
    tr = np.empty(kept.size, dtype=TRIGGER_DTYPE)
    tr["t"] = times[keep]
    tr["rising"] = _EDGE_RISING[kept]
    tr["id"] = _EDGE_ID[kept]
    t = tr["t"]
    if (t[1:] < t[:-1]).any():
        tr = tr[np.argsort(t, kind="stable")]
    return tr, counts


# Type code -> whether it is an external edge, and the edge's (rising, id).
_EDGE_KEEP = np.zeros(256, dtype=bool)
_EDGE_RISING = np.zeros(256, dtype=bool)
_EDGE_ID = np.zeros(256, dtype=np.uint8)
for _code, _name in _own.TRIGGER_TYPE_NAMES.items():
    if _name in EXTERNAL_TRIGGER_TYPES:
        _EDGE_KEEP[_code] = True
        _EDGE_RISING[_code], _EDGE_ID[_code] = EXTERNAL_TRIGGER_TYPES[_name]


def _own_triggers(c: _own.Container) -> tuple[np.ndarray, dict[str, int]]:
    """External edges and record counts of the trigger stream."""
    s = c.stream_of_type("TRIG")
    if s is None:
        return empty_triggers(), {}
    arena = _own.Arena()
    records = []
    for off, sid, raw in _own.decoded(c, {s.id}, arena):
        records.append(_own.trigger_records(c, off, sid, raw))
        arena.release()
    return _trigger_edges(records)


def _trigger_edges(records: list[tuple[np.ndarray, np.ndarray]]
                   ) -> tuple[np.ndarray, dict[str, int]]:
    """(timestamps, type codes) of each trigger packet -> edges and record counts."""
    if not records:
        return empty_triggers(), {}
    return _edges(np.concatenate([k for _, k in records]),
                  np.concatenate([t for t, _ in records]))


class _Source:
    """One file's facts, geometry, triggers and event packets."""

    def __init__(self, p: Path):
        require_file(p)  # a missing file, a folder, a FIFO: named, never opened
        c = _own.open_container(p)
        ev = c.stream_of_type("EVTS")
        self.facts = {"camera": "" if ev is None or ev.source is None else ev.source,
                      "streams": [s.name for s in c.streams.values()]}
        self.stored: dict[str, Any] | None = None
        if ev is not None and ev.metadata is not None:
            try:
                self.stored = json.loads(ev.metadata)
            except ValueError as exc:
                raise ValueError(f"{p}: the event stream's {METADATA_KEY} is not valid JSON: "
                                 f"{exc}") from None
            if not isinstance(self.stored, dict):
                raise ValueError(f"{p}: the event stream's {METADATA_KEY} must be a JSON "
                                 "object")
        if ev is None:
            raise ValueError(f"{p}: no event stream; streams found: {self.facts['streams']}")
        if ev.width is None or ev.height is None:
            raise ValueError(f"{p}: the event stream gives no resolution")
        self.p = p
        self.width, self.height = _check_resolution(p, ev.width, ev.height)
        self._c = c
        self._events = ev.id

    def triggers(self) -> tuple[np.ndarray, dict[str, int]]:
        return _own_triggers(self._c)

    def batches(self, arena: _own.Arena,
                triggers: list[tuple[np.ndarray, np.ndarray]] | None = None
                ) -> Iterator[np.ndarray]:
        """Each non-empty event packet, as an array of dv's records in ``arena`` (valid
        until the arena is released); with ``triggers``, the trigger packets' (timestamps,
        type codes) are appended to it on the way (one pass over the file)."""
        c = self._c
        ev = self._events
        wanted = {ev}
        trig = c.stream_of_type("TRIG")
        if triggers is not None and trig is not None:
            wanted.add(trig.id)
        for off, sid, raw in _own.decoded(c, wanted, arena):
            if sid != ev:
                assert triggers is not None
                triggers.append(_own.trigger_records(c, off, sid, raw))
                continue
            a = _own.event_records(c, off, sid, raw)
            if a.shape[0]:
                yield a


def _metadata(p: Path, facts: dict[str, Any], counts: dict[str, int]) -> dict[str, Any]:
    return {
        "format": "aedat4",
        "source": str(p),
        "camera": facts["camera"],
        "streams": facts["streams"],
        "trigger_records": dict(sorted(counts.items())),
        "trigger_channels": {"0": "EXTERNAL_SIGNAL", "1": "EXTERNAL_GENERATOR"},
    }


def aedat_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Header facts of an AEDAT 4.0 file: ``camera``, ``width``, ``height``, ``streams``,
    ``trigger_records`` (every trigger record by type) and the external ``triggers``
    count, without decoding the events."""
    p = require_file(path)
    src = _Source(p)
    tr, counts = src.triggers()
    info = _metadata(p, src.facts, counts)
    info.update(width=src.width, height=src.height, triggers=int(tr.size))
    return info


def iter_aedat(
    path: str | os.PathLike[str], *, chunk_events: int | None = None
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Decode an AEDAT 4.0 file packet by packet: yield ``(events, triggers)``.

    With ``chunk_events``, packets are gathered (and split) into chunks of that many
    events. External trigger edges (read first; they are few) come with the chunk
    whose events reach their time. Errors (``ValueError`` naming the file) on ``next``.
    """
    if chunk_events is not None and int(chunk_events) < 1:
        raise ValueError(f"iter_aedat: chunk_events must be >= 1, got {chunk_events}")
    p = require_file(path)
    return _iter(p, chunk_events)


def _check_resolution(p: Path, width: int, height: int) -> tuple[int, int]:
    return check_geometry(str(p), width, height, "the event stream's resolution")


def _packets(src: _Source) -> Iterator[np.ndarray]:
    """Each non-empty event packet as its own EVENT_DTYPE array (pixels checked)."""
    p, width, height = src.p, src.width, src.height
    seen = 0
    arena = _own.Arena()
    for a in src.batches(arena):
        m = a.shape[0]
        out = np.empty(m, dtype=EVENT_DTYPE)
        if not _convert_dv(a, out, 0, width, height):
            _raise_outside(p, a, seen, width, height)
        arena.release()
        seen += m
        yield out


def _iter(p: Path, chunk_events: int | None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    src = _Source(p)
    triggers, _ = src.triggers()
    paired = pair_triggers(_packets(src), triggers)
    if chunk_events is not None:
        yield from rechunk(paired, chunk_events=int(chunk_events))
        return
    yield from paired


def _convert_group(p: Path, group: list[np.ndarray], buf: np.ndarray, n: int, width: int,
                   height: int) -> int:
    """Convert each decoded packet of ``group`` into ``buf[n:]``; return the new event
    count."""
    for a in group:
        if not _convert_dv(a, buf, n, width, height):
            _raise_outside(p, a, n, width, height)
        n += a.shape[0]
    return n


def _read_all_events(src: _Source, triggers: list[tuple[np.ndarray, np.ndarray]] | None = None
                     ) -> np.ndarray:
    """Every event, in one array.

    Packets are decoded in groups of about ``_GROUP_EVENTS`` events, then converted.
    A file that fits in one group goes straight into an array of its exact size.
    Larger ones go into a buffer with room for
    ``file size / 2`` events (reserved memory that is never written costs nothing),
    doubled when full, then trimmed to the events read: below ``_COPY_TRIM_BYTES`` by a
    copy into an exact-size array (the allocator then reuses the same memory from one
    read to the next instead of mapping, and faulting in, fresh pages each time),
    above it in place (``realloc``: no second copy).
    """
    p, width, height = src.p, src.width, src.height
    arena = _own.Arena()
    batches = src.batches(arena, triggers)
    buf: np.ndarray | None = None
    cap = n = 0
    group: list[np.ndarray] = []
    pending = 0
    while True:
        batch = next(batches, None)
        if batch is not None:
            m = len(batch)
            group.append(batch)
            pending += m
            if pending < _GROUP_EVENTS:
                continue
        if group:
            if buf is None:
                cap = pending if batch is None else max(
                    min(p.stat().st_size // 2, _MAX_INITIAL_EVENTS), 2 * pending)
                buf = np.empty(cap, dtype=EVENT_DTYPE)
            elif n + pending > cap:
                cap = max(2 * cap, n + pending)
                buf.resize(cap, refcheck=False)  # the only reference is ours
            n = _convert_group(p, group, buf, n, width, height)
            group, pending = [], 0
            arena.release()
        if batch is None:
            break
    if buf is None:
        return np.empty(0, dtype=EVENT_DTYPE)
    if n == cap:
        return buf
    if n * EVENT_DTYPE.itemsize > _COPY_TRIM_BYTES:
        buf.resize(n, refcheck=False)
        return buf
    out = np.empty(n, dtype=EVENT_DTYPE)
    out.view(np.uint8)[:] = buf.view(np.uint8)[: out.nbytes]  # a memcpy
    return out


def read_aedat(path: str | os.PathLike[str]) -> Recording:
    """Read a whole AEDAT 4.0 file: events, external trigger edges, geometry from the
    event stream's resolution, and metadata (camera, streams, ``trigger_records``).

    An event outside the resolution raises ``ValueError`` naming the file, the event
    and the bound."""
    p = Path(path)
    src = _Source(p)
    records: list[tuple[np.ndarray, np.ndarray]] = []
    events = _read_all_events(src, records)
    triggers, counts = _trigger_edges(records)
    meta = _metadata(p, src.facts, counts)
    width, height = src.width, src.height
    if src.stored is not None:
        meta = src.stored
    logger.info("%s: AEDAT 4.0 from %s, %dx%d, %d events, %d external trigger edges "
                "(%d trigger records)", p, src.facts["camera"], width, height, events.size,
                triggers.size, sum(counts.values()))
    # _convert_dv checked every pixel and wrote every polarity as +-1.
    return Recording.from_checked(events=events, width=width, height=height,
                                  triggers=triggers, metadata=meta)


def _header(path: Path, opts: ReadOptions) -> Header:
    src = _Source(path)
    tr, counts = src.triggers()
    facts = dict(_metadata(path, src.facts, counts), width=src.width, height=src.height,
                 triggers=int(tr.size))
    meta = src.stored if src.stored is not None else _metadata(path, src.facts, counts)
    return Header(format="aedat4", width=src.width, height=src.height,
                  geometry_source="the event stream's resolution", metadata=meta,
                  facts=facts, sensor=str(src.facts["camera"]) or None, triggers=tr)


_AEDAT_TYPES = {(True, 0): 1, (False, 0): 2, (True, 1): 4, (False, 1): 5}
"""(rising, id) of an edge -> the AEDAT TriggerType it is written as."""
_PACKET_EVENTS = 1 << 15


def _xml(width: int, height: int, camera: str, metadata: str) -> bytes:
    """The IOHeader's stream description (the layout dv-processing writes)."""
    q = html.escape

    def stream(sid: int, name: str, ident: str, info: str) -> str:
        path = f"/outInfo/{sid}/"
        attrs = "".join(f'<attr key="{k}" type="string">{q(v)}</attr>' for k, v in (
            ("compression", "NONE"), ("originalModuleName", "asynhdr"),
            ("originalOutputName", name), ("typeDescription", "Custom data type output."),
            ("typeIdentifier", ident)))
        return (f'<node name="{sid}" path="{path}">{attrs}<node name="info" '
                f'path="{path}info/">{info}</node></node>')

    src = f'<attr key="source" type="string">{q(camera)}</attr>'
    ev_info = (f'<attr key="sizeX" type="int">{width}</attr><attr key="sizeY" type="int">'
               f'{height}</attr>{src}<attr key="{METADATA_KEY}" type="string">'
               f'{q(metadata)}</attr>')
    return (f'<dv version="2.0"><node name="outInfo" path="/outInfo/">'
            f'{stream(0, "events", "EVTS", ev_info)}{stream(1, "triggers", "TRIG", src)}'
            "</node></dv>").encode()


def _io_header(xml: bytes) -> bytes:
    """The IOHeader flatbuffer: no compression, no file data table, the XML."""
    head = struct.pack("<I4s4xHHHHH2x", 24, b"IOHE", 10, 20, 4, 8, 16)  # vtable at 12
    table = struct.pack("<iiqI", 12, 0, -1, 4)  # at 24: compression, table at -1, the XML
    body = struct.pack("<I", len(xml)) + xml + b"\0"
    return head + table + body + b"\0" * (-len(body) % 4)


def _packet(sid: int, ident: bytes, body: bytes) -> bytes:
    """Stream id, size and a size-prefixed flatbuffer whose root table has one field, a
    vector at byte 28 of the buffer (``body``: its length and elements)."""
    fb = struct.pack("<II4sHHHH", 0, 16, ident, 6, 8, 4, 0) + struct.pack("<iI", 8, 4) + body
    fb = struct.pack("<I", len(fb) - 4) + fb[4:]
    return struct.pack("<ii", sid, len(fb)) + fb


class AedatWriter(FileWriter):
    """An AEDAT 4.0 file (uncompressed packets, no file data table) with an event stream
    and a trigger stream, atomically; dv-processing and faery read it. Edges on channel 0
    become EXTERNAL_SIGNAL edges, on channel 1 EXTERNAL_GENERATOR edges (the two kinds
    the reader keeps); the recording's metadata is a JSON attribute of the event stream
    (``asynhdr_metadata``). Events are written in packets of up to 32,768."""

    def __init__(self, path: str | os.PathLike[str], *, width: int, height: int,
                 metadata: dict[str, Any] | None = None, camera: str | None = None,
                 overwrite: bool = True) -> None:
        super().__init__(path, overwrite=overwrite)
        if camera is None:  # the recording's camera (a converted file's), else asynhdr
            camera = str((metadata or {}).get("camera") or "asynhdr")
        self.width, self.height = check_geometry(str(path), width, height,
                                                 "the writer's arguments")
        head = _io_header(_xml(self.width, self.height, camera,
                               json_metadata(str(path), metadata)))
        self._head = b"#!AER-DAT4.0\r\n" + struct.pack("<i", len(head)) + head

    def _start(self, f: BinaryIO) -> None:
        f.write(self._head)

    def write(self, events: np.ndarray, triggers: np.ndarray | None = None) -> None:
        """Append events (``EVENT_DTYPE``, sorted by time) and triggers (channels 0, 1)."""
        f = self._file()
        validate_events(events, width=self.width, height=self.height, require_sorted=True,
                        name=f"{self.path}: events")
        for a in range(0, events.size, _PACKET_EVENTS):
            ev = events[a : a + _PACKET_EVENTS]
            rec = np.zeros(ev.size, dtype=_own.DV_EVENT_DTYPE)
            rec["timestamp"], rec["x"], rec["y"] = ev["t"], ev["x"], ev["y"]
            rec["polarity"] = ev["p"] > 0
            f.write(_packet(0, b"EVTS", struct.pack("<I", ev.size) + rec.tobytes()))
        if triggers is not None and triggers.size:
            validate_triggers(triggers, name=f"{self.path}: triggers")
            bad = triggers["id"] > 1
            if bad.any():
                raise ValueError(f"{self.path}: trigger channel {int(triggers['id'][bad][0])}: "
                                 "AEDAT 4.0 holds channels 0 (external signal) and 1 "
                                 "(external generator) only")
            m = triggers.size
            pad = 4 * (m % 2)  # each table's int64 at a multiple of 8
            offsets = [4 * m + pad + 24 * k + 8 - 4 * k for k in range(m)]
            tables = b"".join(
                struct.pack("<HHHHibxxxq", 8, 16, 8, 4, 8,
                            _AEDAT_TYPES[(bool(r), int(i))], int(t))
                for t, r, i in zip(triggers["t"], triggers["rising"], triggers["id"],
                                   strict=True))
            f.write(_packet(1, b"TRIG", struct.pack(f"<I{m}I", m, *offsets) + b"\0" * pad
                            + tables))


FORMAT = Format(
    name="aedat4",
    extensions=(".aedat4",),
    description="iniVation AEDAT 4.0 (DV): uncompressed, LZ4 or Zstd",
    sniff=lambda path, head: head.startswith(b"#!AER-DAT4.0"),
    header=_header,
    chunks=lambda path, header, n, opts: iter_aedat(path, chunk_events=n),
    read=lambda path, header, opts: read_aedat(path),
    writer=AedatWriter,
)
"""The ``.aedat4`` record of the format registry (:mod:`asynhdr.io`)."""
