"""Decode the event and trigger packets of an AEDAT 4.0 file.

The container, as the AEDAT 4.0 layout describes it:

- ``#!AER-DAT4.0\\r\\n``, an int32 size and the ``IOHeader`` flatbuffer (compression,
  position of the file data table, and the streams as XML);
- packets: int32 stream id, int32 size, the (compressed) packet;
- the file data table (an index, not needed to read the packets in order);

is walked window by window, so memory stays flat in file size. Each packet of a wanted
stream is decompressed whole (LZ4 frame by python-lz4, Zstd frame by zstandard, or
stored as is) and parsed as the size-prefixed flatbuffer dv writes:

- ``EVTS``: a table whose first field is a vector of 16-byte ``Event`` structs
  (int64 timestamp, int16 x, int16 y, bool polarity, 3 bytes of padding), returned as a
  read-only view of the decompressed bytes;
- ``TRIG``: a table whose first field is a vector of ``Trigger`` tables (int64
  timestamp, int8 type), read in one compiled pass.

Every offset of the flatbuffer is checked against the packet's decoded size. Any
problem (a packet cut short, data that do not decompress, a flatbuffer that does not
parse) is a ``ValueError`` naming the file, the packet's byte offset and its stream.
Nothing here can loop on damaged data: a frame that does not decode raises, and the
packets are read in file order, so a damaged file data table is never read.
"""

from __future__ import annotations

import re
import struct
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numba
import numpy as np

from asynhdr._recycle import Recycler

__all__ = ["DV_EVENT_DTYPE", "TRIGGER_TYPE_NAMES", "Container", "open_container"]

DV_EVENT_DTYPE = np.dtype(
    {
        "names": ["timestamp", "x", "y", "polarity"],
        "formats": ["<i8", "<i2", "<i2", "u1"],
        "offsets": [0, 8, 10, 12],
        "itemsize": 16,
    }
)
"""One ``Event`` struct of dv's event packet (flatbuffers pads it to 16 bytes)."""

TRIGGER_TYPE_NAMES = {
    0: "TIMESTAMP_RESET",
    1: "EXTERNAL_SIGNAL_RISING_EDGE",
    2: "EXTERNAL_SIGNAL_FALLING_EDGE",
    3: "EXTERNAL_SIGNAL_PULSE",
    4: "EXTERNAL_GENERATOR_RISING_EDGE",
    5: "EXTERNAL_GENERATOR_FALLING_EDGE",
    6: "APS_FRAME_START",
    7: "APS_FRAME_END",
    8: "APS_EXPOSURE_START",
    9: "APS_EXPOSURE_END",
}
"""AEDAT 4.0 ``TriggerType`` values (dv's ``dv.TriggerType``)."""

_MAGIC = b"#!AER-DAT4.0\r\n"
_COMPRESSION = {0: "none", 1: "LZ4", 2: "LZ4_HIGH", 3: "ZSTD", 4: "ZSTD_HIGH"}
_WINDOW_BYTES = 16 << 20
_BUFFERS = Recycler(keep=2, max_bytes=_WINDOW_BYTES)
_BYTE = np.dtype(np.uint8)


@numba.njit(cache=True, nogil=True)
def _u32(buf, i):  # pragma: no cover - compiled
    return (np.int64(buf[i]) | (np.int64(buf[i + 1]) << 8) | (np.int64(buf[i + 2]) << 16)
            | (np.int64(buf[i + 3]) << 24))


def _header(name: str, f: BinaryIO, size: int) -> tuple[int, int, int]:
    """(compression, data table position, first packet's offset) from the IOHeader."""
    read = f.read
    head = read(18)
    if len(head) < 18 or head[:14] != _MAGIC:
        raise ValueError(f"{name}: not an AEDAT 4.0 file (no '#!AER-DAT4.0' at byte 0)")
    (hsize,) = struct.unpack("<i", head[14:18])
    if hsize <= 0 or 18 + hsize > size:
        raise ValueError(f"{name}: AEDAT 4.0 header size {hsize} at byte 14 does not fit the "
                         f"file ({size} bytes)")
    h = read(hsize)
    try:
        (root,) = struct.unpack_from("<I", h, 0)
        (back,) = struct.unpack_from("<i", h, root)
        vt = root - back
        vsize, _ = struct.unpack_from("<HH", h, vt)
        nf = max(0, (vsize - 4) // 2)
        offs = struct.unpack_from(f"<{nf}H", h, vt + 4)
        comp = struct.unpack_from("<i", h, root + offs[0])[0] if nf > 0 and offs[0] else 0
        table = struct.unpack_from("<q", h, root + offs[1])[0] if nf > 1 and offs[1] else -1
    except struct.error:
        raise ValueError(f"{name}: AEDAT 4.0 header (bytes 18 to {18 + hsize}) does not "
                         "parse") from None
    return int(comp), int(table), 18 + hsize


@numba.njit(cache=True, nogil=True)
def _packets(buf, n, end):  # pragma: no cover - compiled
    """The packets whose bytes lie wholly in ``buf[:n]`` (file bytes from the first
    packet on; the packets end at ``end``, relative to the same start): their
    positions, sizes and streams, then (status, position of the next packet) with
    status 0 all packets done, 1 the next packet goes past the buffer (read more), 2 the
    next packet's header claims a size that does not fit."""
    pos = np.int64(0)
    cap = 1024
    at = np.empty(cap, dtype=np.int64)
    size = np.empty(cap, dtype=np.int64)
    stream = np.empty(cap, dtype=np.int64)
    k = 0
    status = 0
    while pos < end:
        if pos + 8 > n:
            status = 1
            break
        sid = _u32(buf, pos)
        m = _u32(buf, pos + 4)
        if m >= 0x80000000:
            m -= np.int64(1) << 32
        if sid >= 0x80000000:
            sid -= np.int64(1) << 32
        if m <= 0 or pos + 8 + m > end:
            status = 2  # the packets before it are returned; it is at ``pos``
            break
        if pos + 8 + m > n:
            status = 1
            break
        if k == cap:
            cap *= 2
            at2 = np.empty(cap, dtype=np.int64)
            size2 = np.empty(cap, dtype=np.int64)
            stream2 = np.empty(cap, dtype=np.int64)
            at2[:k] = at[:k]
            size2[:k] = size[:k]
            stream2[:k] = stream[:k]
            at, size, stream = at2, size2, stream2
        at[k], size[k], stream[k] = pos, m, sid
        k += 1
        pos += 8 + m
    return at[:k], size[:k], stream[:k], status, pos


@dataclass
class Stream:
    """One output stream of the header's XML."""

    id: int
    type: str  # typeIdentifier: EVTS, TRIG, FRME, IMUS, ...
    name: str  # originalOutputName: events, triggers, frames, imu, ...
    width: int | None = None
    height: int | None = None
    source: str | None = None  # the camera


@dataclass
class Container:
    """What the IOHeader says: compression, where the packets are, the streams."""

    path: Path
    size: int
    compression: int
    table: int  # file data table position (-1: none)
    first: int  # first packet's offset
    streams: dict[int, Stream] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return str(self.path)

    @property
    def end(self) -> int:
        """Where the packets end (the file data table, else the end of the file)."""
        return self.table if 0 < self.table <= self.size else self.size

    def stream_of_type(self, type_id: str) -> Stream | None:
        for s in self.streams.values():
            if s.type == type_id:
                return s
        return None


_XML = re.compile(rb"<dv\b.*</dv>", re.DOTALL)


def _streams(name: str, header: bytes) -> dict[int, Stream]:
    """The output streams of the header's XML (``outInfo``: one node per stream id)."""
    m = _XML.search(header)
    if m is None:
        raise ValueError(f"{name}: AEDAT 4.0 header holds no stream description (<dv> XML)")
    try:
        root = ET.fromstring(m.group(0).decode("utf-8"))
    except (UnicodeDecodeError, ET.ParseError) as exc:
        raise ValueError(f"{name}: damaged AEDAT 4.0 header: its stream description does "
                         f"not parse ({exc})") from None
    out: dict[int, Stream] = {}
    for node in root.iter("node"):
        if not node.get("path", "").rstrip("/").endswith(f"outInfo/{node.get('name')}"):
            continue
        try:
            sid = int(node.get("name", ""))
        except ValueError:
            continue
        attrs = {a.get("key"): (a.text or "").strip() for a in node.findall("attr")}
        info = node.find("node[@name='info']")
        iattrs = {} if info is None else {a.get("key"): (a.text or "").strip()
                                          for a in info.findall("attr")}

        def dim(key: str, iattrs: dict[str | None, str] = iattrs) -> int | None:
            try:
                return int(iattrs[key]) if key in iattrs else None
            except ValueError:
                return None

        out[sid] = Stream(id=sid, type=attrs.get("typeIdentifier", ""),
                          name=attrs.get("originalOutputName", str(sid)),
                          width=dim("sizeX"), height=dim("sizeY"), source=iattrs.get("source"))
    return out


def open_container(path: str | Path) -> Container:
    """Read the IOHeader of an AEDAT 4.0 file (``ValueError`` naming the file when it is
    not one, or its header is damaged)."""
    p = Path(path)
    size = p.stat().st_size
    with open(p, "rb") as f:
        comp, table, first = _header(str(p), f, size)
        f.seek(18)
        header = f.read(first - 18)
    if comp not in _COMPRESSION:
        raise ValueError(f"{p}: AEDAT 4.0 header names compression {comp}; known: "
                         + ", ".join(f"{k} ({v})" for k, v in _COMPRESSION.items()))
    return Container(path=p, size=size, compression=comp, table=table, first=first,
                     streams=_streams(str(p), header))


def walk(c: Container, wanted: set[int]) -> Iterator[tuple[int, int, memoryview]]:
    """``(byte offset, stream id, packet data)`` of each packet of the ``wanted``
    streams, in file order, reading the file in windows (memory flat in file size).

    The data are a view of the read buffer, valid until the next packet is asked for:
    :func:`decompress` copies what it keeps."""
    name, size, end = c.name, c.size, c.end
    pos = c.first
    buf = _BUFFERS.get(max(1, min(_WINDOW_BYTES, size)), _BYTE)
    with open(c.path, "rb") as f:
        while pos < end:
            f.seek(pos)
            got = f.readinto(buf.data[: min(buf.size, size - pos)])
            at, n, stream, status, nxt = _packets(buf, got, end - pos)
            for a, m, s in zip(at.tolist(), n.tolist(), stream.tolist(), strict=True):
                if s in wanted:
                    yield pos + a, s, buf.data[a + 8 : a + 8 + m]
            if status == 2:
                a = pos + int(nxt)
                sid, m = struct.unpack("<ii", bytes(buf[int(nxt) : int(nxt) + 8]))
                raise ValueError(f"{name}: packet at byte {a} (stream {sid}) claims {m} bytes; "
                                 f"the data end at byte {end}")
            if status == 1:
                if pos + got >= size:  # the window reached the end of the file
                    raise ValueError(f"{name}: packet at byte {pos + int(nxt)} cut short: the "
                                     f"file ends at byte {size}")
                if int(nxt) == 0:  # one packet larger than the window
                    (m,) = struct.unpack("<i", bytes(buf[4:8]))
                    buf = np.empty(max(2 * buf.size, m + 8), dtype=np.uint8)
            pos += int(nxt)
            if status == 0:
                break


def decompress(c: Container, offset: int, sid: int, data: memoryview) -> bytes:
    """The decoded packet (a size-prefixed flatbuffer), in memory of its own."""
    comp = c.compression
    try:
        if comp in (1, 2):
            import lz4.frame

            return bytes(lz4.frame.decompress(data))
        if comp in (3, 4):
            import zstandard

            return bytes(zstandard.ZstdDecompressor().decompress(data))
    except Exception as exc:  # lz4: RuntimeError; zstandard: ZstdError
        raise ValueError(f"{c.name}: packet at byte {offset} (stream {sid}): its "
                         f"{_COMPRESSION[comp]} data do not decode ({exc}); the file is "
                         "damaged") from None
    return bytes(data)


def _vector(c: Container, offset: int, sid: int, raw: bytes, ident: bytes) -> tuple[int, int]:
    """(position, length) of the vector in the first field of the packet's root table."""
    n = len(raw)

    def bad(what: str) -> ValueError:
        return ValueError(f"{c.name}: packet at byte {offset} (stream {sid}, "
                          f"{ident.decode()}): {what}; the file is damaged")

    if n < 12:
        raise bad(f"{n} decoded bytes are too few for a packet")
    (prefix,) = struct.unpack_from("<I", raw, 0)
    if prefix != n - 4:
        raise bad(f"its size prefix says {prefix} bytes, {n - 4} follow")
    if raw[8:12] != ident:
        raise bad(f"its type is {raw[8:12]!r}, expected {ident!r}")
    (root,) = struct.unpack_from("<I", raw, 4)
    root += 4
    if root + 4 > n:
        raise bad("its root table lies outside the packet")
    (back,) = struct.unpack_from("<i", raw, root)
    vt = root - back
    if vt < 4 or vt + 4 > n:
        raise bad("its table layout (vtable) lies outside the packet")
    vsize, _ = struct.unpack_from("<HH", raw, vt)
    if vt + vsize > n:
        raise bad("its table layout (vtable) runs past the packet")
    f0 = struct.unpack_from("<H", raw, vt + 4)[0] if vsize >= 6 else 0
    if f0 == 0:
        return 0, 0  # no elements
    at = root + f0
    if at + 4 > n:
        raise bad("its element vector's offset lies outside the packet")
    vec = at + struct.unpack_from("<I", raw, at)[0]
    if vec + 4 > n:
        raise bad("its element vector lies outside the packet")
    (count,) = struct.unpack_from("<I", raw, vec)
    return vec + 4, count


def event_records(c: Container, offset: int, sid: int, raw: bytes) -> np.ndarray:
    """The packet's events as a read-only ``DV_EVENT_DTYPE`` view of ``raw``."""
    start, count = _vector(c, offset, sid, raw, b"EVTS")
    if start + count * DV_EVENT_DTYPE.itemsize > len(raw):
        raise ValueError(f"{c.name}: packet at byte {offset} (stream {sid}, EVTS): "
                         f"{count} events do not fit its {len(raw)} decoded bytes; the file "
                         "is damaged")
    return np.frombuffer(raw, dtype=DV_EVENT_DTYPE, count=count, offset=start)


@numba.njit(cache=True, nogil=True)
def _trigger_tables(raw, start, count):  # pragma: no cover - compiled
    """Timestamps and types of ``count`` Trigger tables whose offsets start at ``start``;
    then the position of the first bad offset, or -1."""
    n = raw.shape[0]
    ts = np.zeros(count, dtype=np.int64)
    kind = np.zeros(count, dtype=np.int64)
    for i in range(count):
        at = start + 4 * i
        if at + 4 > n:
            return ts, kind, at
        tab = at + (np.int64(raw[at]) | (np.int64(raw[at + 1]) << 8)
                    | (np.int64(raw[at + 2]) << 16) | (np.int64(raw[at + 3]) << 24))
        if tab + 4 > n:
            return ts, kind, at
        back = (np.int64(raw[tab]) | (np.int64(raw[tab + 1]) << 8)
                | (np.int64(raw[tab + 2]) << 16) | (np.int64(raw[tab + 3]) << 24))
        if back >= 1 << 31:
            back -= np.int64(1) << 32
        vt = tab - back
        if vt < 0 or vt + 4 > n:
            return ts, kind, tab
        vsize = np.int64(raw[vt]) | (np.int64(raw[vt + 1]) << 8)
        if vt + vsize > n:
            return ts, kind, vt
        for fld in range(2):
            if 4 + 2 * fld + 2 > vsize:
                continue
            fo = np.int64(raw[vt + 4 + 2 * fld]) | (np.int64(raw[vt + 5 + 2 * fld]) << 8)
            if fo == 0:
                continue
            p = tab + fo
            if fld == 0:
                if p + 8 > n:
                    return ts, kind, tab
                v = np.int64(0)
                for b in range(8):
                    v |= np.int64(raw[p + b]) << (8 * b)
                ts[i] = v
            else:
                if p + 1 > n:
                    return ts, kind, tab
                kind[i] = np.int64(raw[p])
    return ts, kind, np.int64(-1)


def trigger_records(c: Container, offset: int, sid: int, raw: bytes) -> tuple[np.ndarray,
                                                                             np.ndarray]:
    """The packet's trigger records: (timestamps, type codes), both int64."""
    start, count = _vector(c, offset, sid, raw, b"TRIG")
    if start + 4 * count > len(raw):
        raise ValueError(f"{c.name}: packet at byte {offset} (stream {sid}, TRIG): "
                         f"{count} triggers do not fit its {len(raw)} decoded bytes; the "
                         "file is damaged")
    ts, kind, bad = _trigger_tables(np.frombuffer(raw, dtype=np.uint8), start, count)
    if bad >= 0:
        raise ValueError(f"{c.name}: packet at byte {offset} (stream {sid}, TRIG): a "
                         f"trigger's data at decoded byte {int(bad)} lie outside the packet; "
                         "the file is damaged")
    return ts, kind
