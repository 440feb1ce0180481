"""Check the container of an AEDAT 4.0 file before dv-processing reads it.

dv-processing (2.0) never returns from ``getNextEventBatch`` on some damaged LZ4
packets (one flipped byte in a compressed packet is enough), holding the GIL, so no
thread and no timeout can stop it. Such a file must be refused before dv-processing
sees it. This module walks the file as the AEDAT 4.0 layout describes it:

- ``#!AER-DAT4.0\\r\\n``, an int32 size and the ``IOHeader`` flatbuffer (compression,
  position of the file data table);
- packets: int32 stream id, int32 size, the (compressed) packet;
- the file data table, one compressed block from its position to the end;

and, for LZ4 files, checks every LZ4 frame (magic, descriptor, header checksum,
block sizes) and every compressed block's sequences (lengths within the block,
match offsets within the data decoded so far, output within the block's maximum)
without writing the decoded data: a linear pass over the compressed bytes. Zstd
damage makes dv-processing raise, which the reader turns into a ``ValueError``.

:func:`check_aedat4` raises ``ValueError`` naming the file, what is wrong and the
byte offset. Memory stays flat: one packet is read at a time.
"""

from __future__ import annotations

import os
import re
import struct
from pathlib import Path
from typing import BinaryIO

import numba
import numpy as np

from asynhdr._recycle import Recycler

__all__ = ["check_aedat4"]

_MAGIC = b"#!AER-DAT4.0\r\n"
_LZ4 = (1, 2)  # dv CompressionType LZ4, LZ4_HIGH
_LZ4_MAGIC = 0x184D2204

_PROBLEMS = {
    1: "not an LZ4 frame (bad magic number)",
    2: "bad LZ4 frame descriptor",
    3: "LZ4 frame header checksum does not match",
    4: "LZ4 frame cut short",
    5: "LZ4 block size beyond the frame's maximum or the packet",
    6: "LZ4 block data that does not decode",
    7: "bytes after the end of the LZ4 frame",
    8: "LZ4 content size does not match the data",
}


@numba.njit(cache=True, nogil=True)
def _u32(buf, i):  # pragma: no cover - compiled
    return (np.int64(buf[i]) | (np.int64(buf[i + 1]) << 8) | (np.int64(buf[i + 2]) << 16)
            | (np.int64(buf[i + 3]) << 24))


@numba.njit(cache=True, nogil=True)
def _xxh32_short(buf, start, n):  # pragma: no cover - compiled
    """xxHash32 (seed 0) of ``buf[start:start + n]`` for ``n < 16``."""
    mask = np.int64(0xFFFFFFFF)
    p1, p2, p3 = np.int64(2654435761), np.int64(2246822519), np.int64(3266489917)
    p4, p5 = np.int64(668265263), np.int64(374761393)
    h = (p5 + n) & mask
    i = start
    end = start + n
    while i + 4 <= end:
        h = (h + _u32(buf, i) * p3) & mask
        h = (((h << 17) | (h >> 15)) & mask) * p4 & mask
        i += 4
    while i < end:
        h = (h + np.int64(buf[i]) * p5) & mask
        h = (((h << 11) | (h >> 21)) & mask) * p1 & mask
        i += 1
    h ^= h >> 15
    h = (h * p2) & mask
    h ^= h >> 13
    h = (h * p3) & mask
    h ^= h >> 16
    return h


@numba.njit(cache=True, nogil=True)
def _length_bytes(buf, ip, end, n):  # pragma: no cover - compiled
    """An LZ4 length's extra bytes from ``ip`` on (each adds its value; 255 means one
    more follows): (length, position after them), the position ``end + 1`` when the
    block ends first."""
    while True:
        if ip >= end:
            return n, end + np.uint64(1)
        s = np.int64(buf[ip])
        ip += np.uint64(1)
        n += s
        if s != 255:
            return n, ip


@numba.njit(cache=True, nogil=True)
def _lz4_block(buf, start, size, block_max, history):  # pragma: no cover - compiled
    """Walk one compressed LZ4 block: (bytes it decodes to, offset of the first bad
    byte or -1).

    The walk follows the sequences (token, literals, 2-byte match offset, match length)
    and checks what a decoder needs: input within the block, every match offset inside
    the data decoded so far (``history`` bytes of earlier blocks included), the block
    ending right after a run of literals, and its decoded size within ``block_max``
    (checked once at the end: the walk writes nothing). Unsigned indices keep numba's
    wraparound checks out of the loop.
    """
    ip = np.uint64(start)
    end = np.uint64(start + size)
    op = np.int64(0)
    while True:
        if ip >= end:
            return op, np.int64(ip)  # a block ends with literals, not a match
        token = np.int64(buf[ip])
        ip += np.uint64(1)
        lit = token >> 4
        if lit == 15:
            lit, ip = _length_bytes(buf, ip, end, lit)
            if ip > end:
                return op, np.int64(end)
        ip += np.uint64(lit)
        op += lit
        if ip + np.uint64(2) > end:
            if ip == end and op <= block_max:
                return op, np.int64(-1)
            return op, np.int64(min(ip, end))
        off = np.int64(buf[ip]) | (np.int64(buf[ip + np.uint64(1)]) << 8)
        if off == 0 or off > op + history:
            return op, np.int64(ip)
        ip += np.uint64(2)
        ml = token & 15
        if ml == 15:
            ml, ip = _length_bytes(buf, ip, end, ml)
            if ip > end:
                return op, np.int64(end)
        op += ml + 4


@numba.njit(cache=True, nogil=True)
def _lz4_frame(buf, n):  # pragma: no cover - compiled
    """Check the LZ4 frame ``buf[:n]``: (problem code, byte offset); code 0 when fine."""
    if n < 7:
        return 4, np.int64(0)
    if _u32(buf, 0) != _LZ4_MAGIC:
        return 1, np.int64(0)
    flg = np.int64(buf[4])
    bd = np.int64(buf[5])
    if (flg >> 6) != 1 or (flg & 2) != 0 or (bd & 0x8F) != 0 or ((bd >> 4) & 7) < 4:
        return 2, np.int64(4)
    pos = np.int64(6)
    if flg & 8:
        pos += 8
    if flg & 1:
        pos += 4
    if pos + 1 > n:
        return 4, pos
    if ((_xxh32_short(buf, 4, pos - 4) >> 8) & 0xFF) != np.int64(buf[pos]):
        return 3, pos
    pos += 1
    block_max = np.int64(1) << (8 + 2 * ((bd >> 4) & 7))
    linked = (flg & 32) == 0
    produced = np.int64(0)
    while True:
        if pos + 4 > n:
            return 4, pos
        bs = _u32(buf, pos)
        if bs == 0:
            pos += 4
            break
        size = bs & 0x7FFFFFFF
        if size > block_max or pos + 4 + size > n:
            return 5, pos
        pos += 4
        if bs & 0x80000000:
            out = size
        else:
            history = min(produced, np.int64(65536)) if linked else np.int64(0)
            out, bad = _lz4_block(buf, pos, size, block_max, history)
            if bad >= 0:
                return 6, bad
        produced += out
        pos += size
        if flg & 16:
            pos += 4
    if flg & 4:
        pos += 4
    if pos > n:
        return 4, n
    if flg & 8:
        content = _u32(buf, 6) | (_u32(buf, 10) << 32)
        if content != produced:
            return 8, np.int64(6)
    if pos != n:
        return 7, pos
    return 0, np.int64(0)


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


@numba.njit(cache=True, nogil=True)
def _frames(buf, at, size):  # pragma: no cover - compiled
    """Check the LZ4 frame of each packet: (code, offset) per packet.

    On one thread: numba's parallel threads keep spinning for a while after their
    work, which slows dv-processing's decoding right after on a two-core machine."""
    k = at.shape[0]
    code = np.zeros(k, dtype=np.int64)
    off = np.zeros(k, dtype=np.int64)
    for i in range(k):
        a = at[i] + 8
        c, o = _lz4_frame(buf[a: a + size[i]], size[i])
        code[i] = c
        off[i] = o
    return code, off


_WINDOW_BYTES = 16 << 20
# Read buffers, reused from one check to the next (no page faults on refill).
_BUFFERS = Recycler(keep=2, max_bytes=_WINDOW_BYTES)
_BYTE = np.dtype(np.uint8)


def check_aedat4(path: str | os.PathLike[str], types: tuple[str, ...] | None = None) -> None:
    """Refuse a damaged AEDAT 4.0 container (see the module docstring): ``ValueError``
    naming the file, the problem and its byte offset; return quietly otherwise.

    ``types``: check the compressed data of the streams of these type identifiers only
    (``EVTS`` events, ``TRIG`` triggers, ...: the packets dv-processing will be asked
    to decode); every packet header and the file data table are checked in any case.
    """
    p = Path(path)
    name = str(p)
    size = p.stat().st_size
    with open(p, "rb") as f:
        comp, table, pos = _header(name, f, size)
        end = table if 0 < table <= size else size
        lz4 = comp in _LZ4
        wanted: np.ndarray | None = None
        if lz4 and types is not None:
            f.seek(18)
            ids = _stream_types(name, f.read(pos - 18))
            if "EVTS" in ids:  # else every packet is checked
                wanted = np.array([ids[t] for t in types if t in ids], dtype=np.int64)
        buf = _BUFFERS.get(max(1, min(_WINDOW_BYTES, size)), _BYTE)
        while pos < end:
            # one window of the file at a time, from the next packet on
            f.seek(pos)
            got = f.readinto(buf.data[: min(buf.size, size - pos)])
            at, n, stream, status, nxt = _packets(buf, got, end - pos)
            if lz4 and at.size:
                sel = np.ones(at.size, dtype=bool) if wanted is None else np.isin(stream,
                                                                                  wanted)
                code = np.zeros(at.size, dtype=np.int64)
                off = np.zeros(at.size, dtype=np.int64)
                code[sel], off[sel] = _frames(buf, at[sel], n[sel])
                bad = np.flatnonzero(code)
                if bad.size:
                    i = int(bad[0])
                    a = pos + int(at[i])
                    raise ValueError(f"{name}: packet of stream {int(stream[i])} at byte {a}: "
                                     f"{_PROBLEMS[int(code[i])]} (byte {a + 8 + int(off[i])}); "
                                     "the file is damaged")
            if status == 2:
                a = pos + int(nxt)
                sid, m = struct.unpack("<ii", bytes(buf[int(nxt): int(nxt) + 8]))
                raise ValueError(f"{name}: packet at byte {a} (stream {sid}) claims {m} bytes; "
                                 f"the data end at byte {end}")
            if status == 1:
                if pos + got >= size:  # the window reached the end of the file
                    raise ValueError(f"{name}: packet at byte {pos + int(nxt)} cut short: the "
                                     f"file ends at byte {size}")
                if int(nxt) == 0:  # one packet larger than the window (its header is in it)
                    (m,) = struct.unpack("<i", bytes(buf[4:8]))
                    buf = np.empty(max(2 * buf.size, m + 8), dtype=np.uint8)
            pos += int(nxt)
            if status == 0:
                break
        if lz4 and 0 < table < size:
            m = size - table
            if m > buf.size:
                buf = np.empty(m, dtype=np.uint8)
            f.seek(table)
            got = f.readinto(buf.data[:m])
            code_t, off_t = _lz4_frame(buf[:got], got)
            if code_t:
                raise ValueError(f"{name}: file data table at byte {table}: "
                                 f"{_PROBLEMS[int(code_t)]} (byte {table + int(off_t)}); the "
                                 "file is damaged")


_OUTPUT_NODE = re.compile(rb'<node name="(\d+)"')
_TYPE_ATTR = re.compile(rb'key="typeIdentifier" type="string">([^<]+)<')


def _stream_types(name: str, header: bytes) -> dict[str, int]:
    """Stream id of each type identifier (``EVTS``, ``TRIG``, ...) from the header's XML
    (each output's ``<node name="ID">`` holds its ``typeIdentifier``)."""
    nodes = list(_OUTPUT_NODE.finditer(header))
    out: dict[str, int] = {}
    for m, nxt in zip(nodes, [*nodes[1:], None], strict=True):
        segment = header[m.end(): nxt.start() if nxt is not None else len(header)]
        t = _TYPE_ATTR.search(segment)
        if t is not None:
            out.setdefault(t.group(1).decode("ascii", "replace").strip(), int(m.group(1)))
    return out
