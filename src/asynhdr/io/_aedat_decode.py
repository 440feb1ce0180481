"""Decode the event and trigger packets of an AEDAT 4.0 file.

The container, as the AEDAT 4.0 layout describes it:

- ``#!AER-DAT4.0\\r\\n``, an int32 size and the ``IOHeader`` flatbuffer (compression,
  position of the file data table, and the streams as XML);
- packets: int32 stream id, int32 size, the (compressed) packet;
- the file data table (an index, not needed to read the packets in order);

is walked window by window, so memory stays flat in file size. Each packet of a wanted
stream is decoded (LZ4 and Zstd by cramjam, or stored as is) into reused memory (no
allocation per packet), after its frame layout gives a bound on its decoded size; the
packets of a window are decoded in batches spread over the process's decoding threads
(cramjam releases the GIL) and yielded in file order. Each is parsed as the
size-prefixed flatbuffer dv writes:

- ``EVTS``: a table whose first field is a vector of 16-byte ``Event`` structs
  (int64 timestamp, int16 x, int16 y, bool polarity, 3 bytes of padding), returned as a
  view of the decoded bytes;
- ``TRIG``: a table whose first field is a vector of ``Trigger`` tables (int64
  timestamp, int8 type), read in one compiled pass.

Every offset of the flatbuffer is checked against the packet's decoded size. Any
problem (a packet cut short, data that do not decompress, a flatbuffer that does not
parse) is a ``ValueError`` naming the file, the packet's byte offset and its stream.
Nothing here can loop on damaged data: a frame that does not decode raises, and the
packets are read in file order, so a damaged file data table is never read.
"""

from __future__ import annotations

import html
import logging
import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numba
import numpy as np

from asynhdr import _pool
from asynhdr.memory import Recycler

logger = logging.getLogger(__name__)

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
def _grown(a, n):  # pragma: no cover - compiled
    """``a[:n]`` in an array twice as long as ``a``."""
    b = np.empty(2 * a.shape[0], dtype=a.dtype)
    b[:n] = a[:n]
    return b


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
        if k == at.shape[0]:
            at, size, stream = _grown(at, k), _grown(size, k), _grown(stream, k)
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
    metadata: str | None = None  # asynhdr's metadata (JSON), when asynhdr wrote the file


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


_STREAM_NODE = re.compile(rb'<node name="(\d+)" path="[^"]*/outInfo/\1/">')
_ATTR = re.compile(rb'<attr key="([^"]+)" type="[^"]*">([^<]*)</attr>')


def _streams(name: str, header: bytes) -> dict[int, Stream]:
    """The output streams of the header's XML: each ``outInfo/ID/`` node's attributes
    and those of its ``info`` node (their keys do not overlap), up to the next stream's
    node. A regular expression, not an XML parser: a third of the time, and a damaged
    header still gives what it can (a stream it does not describe is not read)."""
    nodes = list(_STREAM_NODE.finditer(header))
    out: dict[int, Stream] = {}
    for k, m in enumerate(nodes):
        nxt = nodes[k + 1] if k + 1 < len(nodes) else None
        segment = header[m.end() : nxt.start() if nxt is not None else len(header)]
        try:
            attrs = {k.decode("utf-8"): html.unescape(v.decode("utf-8")).strip()
                     for k, v in _ATTR.findall(segment)}
        except UnicodeDecodeError:
            raise ValueError(f"{name}: damaged AEDAT 4.0 header: the description of stream "
                             f"{int(m.group(1))} is not text") from None

        def dim(key: str, attrs: dict[str, str] = attrs) -> int | None:
            try:
                return int(attrs[key]) if key in attrs else None
            except ValueError:
                return None

        sid = int(m.group(1))
        out.setdefault(sid, Stream(id=sid, type=attrs.get("typeIdentifier", ""),
                                   name=attrs.get("originalOutputName", str(sid)),
                                   width=dim("sizeX"), height=dim("sizeY"),
                                   source=attrs.get("source"),
                                   metadata=attrs.get("asynhdr_metadata")))
    if not out:
        raise ValueError(f"{name}: AEDAT 4.0 header describes no stream (no outInfo nodes "
                         "in its XML)")
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


Window = tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


_CUTS_REPORTED: set[tuple[str, int]] = set()  # (file, size): warned once per process


def _warn_cut(c: Container, at: int) -> None:
    key = (c.name, c.size)
    if key not in _CUTS_REPORTED:
        _CUTS_REPORTED.add(key)
        logger.warning("%s: the file ends at byte %d inside the packet at byte %d: it was "
                       "cut; the packets before it are read", c.name, c.size, at)


def _windows(c: Container) -> Iterator[Window]:
    """The file read window by window from the first packet on (memory flat in file
    size): ``(file offset of the window, its bytes, and the positions in it, sizes and
    stream ids of the packets lying wholly in it)``. The window's bytes are valid until
    the next window is asked for; a packet larger than the window makes it grow. A
    packet that runs past the data table, or past the end of a file whose table lies within
    it, raises ``ValueError`` once the packets before it are yielded; past the end of a file
    cut short (its table beyond the end, or none) it ends the windows with a warning."""
    name, size, end = c.name, c.size, c.end
    # the file ends before the data table its header names (or it names none): a packet
    # that runs past the end was cut, and the packets before it are the recording
    cut = not 0 < c.table <= size
    pos = c.first
    buf = _BUFFERS.get(max(1, min(_WINDOW_BYTES, size)), _BYTE)
    with open(c.path, "rb", buffering=0) as f:
        while pos < end:
            f.seek(pos)
            want = min(buf.size, size - pos)
            got = f.readinto(buf.data[:want])
            if got < want:  # the file is shorter than when it was opened
                raise ValueError(f"{name}: file ended at byte {pos + got} while reading, "
                                 f"{size} bytes expected (was it cut while being read?)")
            at, n, stream, status, nxt = _packets(buf, got, end - pos)
            if at.shape[0]:
                yield pos, buf, at, n, stream
            if status == 2:
                a = pos + int(nxt)
                sid, m = struct.unpack("<ii", bytes(buf[int(nxt) : int(nxt) + 8]))
                if cut and m > 0:
                    _warn_cut(c, a)
                    return
                raise ValueError(f"{name}: packet at byte {a} (stream {sid}) claims {m} bytes; "
                                 f"the data end at byte {end}")
            if status == 1:
                if pos + got >= size:  # the window reached the end of the file
                    if cut:
                        _warn_cut(c, pos + int(nxt))
                        return
                    raise ValueError(f"{name}: packet at byte {pos + int(nxt)} cut short: the "
                                     f"file ends at byte {size}")
                if int(nxt) == 0:  # one packet larger than the window
                    (m,) = struct.unpack("<i", bytes(buf[4:8]))
                    buf = np.empty(max(2 * buf.size, m + 8), dtype=np.uint8)
            pos += int(nxt)
            if status == 0:
                break


def walk(c: Container, wanted: set[int]) -> Iterator[tuple[int, int, memoryview]]:
    """``(byte offset, stream id, packet data)`` of each packet of the ``wanted``
    streams, in file order. The data are a view of the read window, valid until the
    next packet is asked for."""
    for pos, buf, at, n, stream in _windows(c):
        mv = buf.data
        for a, m, s in zip(at.tolist(), n.tolist(), stream.tolist(), strict=True):
            if s in wanted:
                yield pos + a, s, mv[a + 8 : a + 8 + m]


# Decoding memory, reused from one packet and one read to the next (memory written
# before costs no page faults to write again).
_ARENA_BYTES = 16 << 20
_ARENAS = Recycler(keep=2, max_bytes=_ARENA_BYTES)


class Arena:
    """Packets decoded one after another into reused memory. :meth:`release` says that
    nothing decoded so far is needed any more: the next packet starts again at the
    beginning. A packet that does not fit gets fresh memory (what was decoded before
    stays valid: its views keep their memory)."""

    def __init__(self) -> None:
        self.buf = _ARENAS.get(_ARENA_BYTES, _BYTE)
        self.at = 0

    def release(self) -> None:
        self.at = 0

    def take(self, need: int) -> int:
        """Where in :attr:`buf` to decode a packet of at most ``need`` bytes."""
        if self.at + need > self.buf.shape[0]:
            if need <= _ARENA_BYTES:
                self.buf = _ARENAS.get(_ARENA_BYTES, _BYTE)
            else:
                self.buf = np.empty(need, dtype=np.uint8)
            self.at = 0
        return self.at

    def keep(self, start: int, n: int) -> None:
        """Keep the ``n`` bytes decoded at ``start``: the next packet goes after them
        (16-byte aligned)."""
        self.at = start + ((n + 15) & ~15)


# Packets of one window decoded together (on several threads) before they are yielded:
# at most this many bytes of decoded bounds.
_BATCH_BYTES = 4 << 20
# Below this many compressed bytes a batch is decoded on the calling thread alone.
_PARALLEL_MIN_BYTES = 128 << 10


def decoded(c: Container, wanted: set[int], arena: Arena
            ) -> Iterator[tuple[int, int, np.ndarray]]:
    """``(byte offset, stream id, decoded bytes)`` of each packet of the ``wanted``
    streams, in file order. The bytes are a view of ``arena``, valid until the arena is
    released (a release while packets are being yielded frees only those yielded).

    A packet that does not decode raises ``ValueError`` naming the file, the packet's
    byte offset and its stream (a panic of the decoder included), once the packets
    before it are yielded. LZ4 frames are checked first (layout, block sizes, content
    size), a window at a time, by :func:`_lz4_plan`. Each frame then goes to cramjam
    straight into the arena: block by block to the block decoder when its blocks need
    no earlier data (the frame decoder's set-up costs more than a small frame's
    decoding), whole to the frame decoder when its blocks are linked (each may refer to
    the one before). The packets of a window are decoded in batches, each spread over
    the process's decoding threads (cramjam releases the GIL)."""
    comp = c.compression
    for pos, buf, at_a, n_a, stream_a in _windows(c):
        at, n, stream = at_a.tolist(), n_a.tolist(), stream_a.tolist()
        keep = [k for k, s in enumerate(stream) if s in wanted]
        if not keep:
            continue
        plan: list[list[int]] | None = None
        if comp in (1, 2):
            mask = np.zeros(len(at), dtype=np.bool_)
            mask[keep] = True
            plan = [a.tolist() for a in _lz4_plan(buf, at_a, n_a, mask)]
        mv = buf.data
        i = 0
        while i < len(keep):
            # A batch: consecutive packets, each given its own place in the arena.
            jobs: list[_Job] = []
            total = 0
            while i < len(keep) and (not jobs or total < _BATCH_BYTES):
                k = keep[i]
                i += 1
                job = _Job(pos + at[k], stream[k], at[k] + 8, n[k], k)
                try:
                    need = _need(comp, mv[job.a : job.a + job.m], k, plan)
                except ValueError as exc:
                    job.error = _decode_error(c, job.off, job.sid, exc)
                    need = 0
                start = arena.take(need)
                job.out = arena.buf[start : start + need]
                arena.keep(start, need)
                total += need
                jobs.append(job)
            _run(c, comp, mv, plan, jobs)
            tail = arena.at
            for job in jobs:
                if job.error is not None:
                    raise job.error
                yield job.off, job.sid, job.out[: job.got]
                arena.at = max(arena.at, tail)  # a release frees only what was yielded


class _Job:
    """One packet to decode: where it is, where it goes, what came of it."""

    __slots__ = ("a", "error", "got", "k", "m", "off", "out", "sid")

    def __init__(self, off: int, sid: int, a: int, m: int, k: int) -> None:
        self.off, self.sid, self.a, self.m, self.k = off, sid, a, m, k
        self.out: np.ndarray = _EMPTY
        self.got = 0
        self.error: ValueError | None = None


_EMPTY = np.empty(0, dtype=np.uint8)


def _need(comp: int, data: memoryview, k: int, plan: list[list[int]] | None) -> int:
    """Bytes the packet decodes to at most (``ValueError`` when its frame says none)."""
    if plan is not None:
        problem, bound, _, content = plan[0], plan[1], plan[2], plan[3]
        if problem[k]:
            raise ValueError(_lz4_problem(problem[k], len(data), content[k]))
        return bound[k]
    if comp == 0:
        return len(data)
    size = _zstd_content_size(data)
    if size < 0:
        raise ValueError("the Zstd frame gives no content size")
    return size


def _run(c: Container, comp: int, mv: memoryview, plan: list[list[int]] | None,
         jobs: list[_Job]) -> None:
    """Decode the jobs: on the calling thread, or spread over the decoding threads
    (cut where the compressed bytes are shared evenly)."""
    threads = _pool.worker_threads()
    todo = [j for j in jobs if j.error is None]
    size = sum(j.m for j in todo)
    if threads < 2 or len(todo) < 2 or size < _PARALLEL_MIN_BYTES:
        _decode_jobs(c, comp, mv, plan, todo)
        return
    parts: list[list[_Job]] = [[] for _ in range(min(threads, len(todo)))]
    acc = 0
    for j in todo:
        parts[min(len(parts) - 1, acc * len(parts) // size)].append(j)
        acc += j.m
    futures = [_pool.executor().submit(_decode_jobs, c, comp, mv, plan, part)
               for part in parts[1:]]
    _decode_jobs(c, comp, mv, plan, parts[0])
    for f in futures:
        f.result()


def _decode_jobs(c: Container, comp: int, mv: memoryview, plan: list[list[int]] | None,
                 jobs: list[_Job]) -> None:
    """Decode each job's packet into its place; a failure is kept in the job."""
    import cramjam

    for job in jobs:
        a, m = job.a, job.m
        out = job.out.data
        try:
            if plan is not None:
                job.got = _lz4_into(mv, plan, job)
            elif comp == 0:
                out[:m] = mv[a : a + m]
                job.got = m
            else:
                job.got = int(cramjam.zstd.decompress_into(mv[a : a + m], out))
        except Exception as exc:  # ValueError, cramjam.DecompressionError
            job.error = _decode_error(c, job.off, job.sid, exc)
        except BaseException as exc:  # a Rust panic (pyo3's PanicException)
            if type(exc).__name__ != "PanicException":
                raise
            job.error = _decode_error(c, job.off, job.sid, exc)


def _lz4_into(mv: memoryview, plan: list[list[int]], job: _Job) -> int:
    """Decode the job's LZ4 frame (checked by :func:`_lz4_plan`) into its place: the
    decoded size."""
    import cramjam

    k_first, bmax, bstart, bsize = plan[4], plan[5], plan[6], plan[7]
    k = job.k
    out = job.out.data
    if plan[2][k]:  # linked blocks
        return int(cramjam.lz4.decompress_into(mv[job.a : job.a + job.m], out))
    need = len(out)
    got, top = 0, bmax[k]
    block = cramjam.lz4.decompress_block_into
    for j in range(k_first[k], k_first[k + 1]):
        s, z = bstart[j], bsize[j]
        if z < 0:  # stored as is
            out[got : got - z] = mv[s : s - z]
            got -= z
        else:
            got += block(mv[s : s + z], out[got : min(got + top, need)])
    content = plan[3][k]
    if content >= 0 and content != got:
        raise ValueError(f"LZ4 content size {content} does not match the {got} bytes decoded")
    return got


def _decode_error(c: Container, offset: int, sid: int, exc: BaseException) -> ValueError:
    return ValueError(f"{c.name}: packet at byte {offset} (stream {sid}): its "
                      f"{_COMPRESSION[c.compression]} data do not decode ({exc}); the file "
                      "is damaged")


_LZ4_MAGIC = 0x184D2204


def _lz4_problem(code: int, size: int, content: int) -> str:
    return {
        1: f"an LZ4 frame needs 7 bytes or more, the packet has {size}",
        2: "not an LZ4 frame (bad magic number)",
        3: "bad LZ4 frame descriptor",
        4: "LZ4 frame cut short",
        5: "LZ4 block size beyond the frame's maximum or the packet",
        6: "the LZ4 frame does not end where the packet ends",
        7: f"LZ4 content size {content} exceeds its blocks",
    }[code]


@numba.njit(cache=True, nogil=True)
def _lz4_plan(buf, at, size, keep):  # pragma: no cover - compiled
    """Walk the LZ4 frame (the format's version 1) of each kept packet (``size[k]``
    bytes from ``at[k] + 8``). Per packet: problem code (0: none, else see
    :func:`_lz4_problem`), bound on the decoded size (the content size when the frame
    gives it, else its blocks times their maximum size), whether its blocks are linked
    (more than one, and not independent), the content size or -1, its first block's
    index, and its blocks' maximum size; per block: position in ``buf`` and size
    (negative: stored as is)."""
    k_n = at.shape[0]
    problem = np.zeros(k_n, dtype=np.int64)
    bound = np.zeros(k_n, dtype=np.int64)
    linked = np.zeros(k_n, dtype=np.bool_)
    content = np.full(k_n, -1, dtype=np.int64)
    first = np.zeros(k_n + 1, dtype=np.int64)
    bmax = np.zeros(k_n, dtype=np.int64)
    cap = 64
    bstart = np.empty(cap, dtype=np.int64)
    bsize = np.empty(cap, dtype=np.int64)
    nb = 0
    for k in range(k_n):
        first[k] = nb
        if not keep[k]:
            continue
        base = at[k] + 8
        n = size[k]
        if n < 7:
            problem[k] = 1
            continue
        if _u32(buf, base) != _LZ4_MAGIC:
            problem[k] = 2
            continue
        flg = np.int64(buf[base + 4])
        bd = np.int64(buf[base + 5])
        if (flg >> 6) != 1 or (flg & 2) or (bd & 0x8F) or ((bd >> 4) & 7) < 4:
            problem[k] = 3
            continue
        pos = 6 + (8 if flg & 8 else 0) + (4 if flg & 1 else 0) + 1
        top = np.int64(1) << (8 + 2 * ((bd >> 4) & 7))
        bmax[k] = top
        skip = 4 if flg & 16 else 0
        blocks = 0
        bad = 0
        while True:
            if pos + 4 > n:
                bad = 4
                break
            bs = _u32(buf, base + pos)
            pos += 4
            if bs == 0:
                break
            z = bs & 0x7FFFFFFF
            if z > top or pos + z > n:
                bad = 5
                break
            if nb == bstart.shape[0]:
                bstart, bsize = _grown(bstart, nb), _grown(bsize, nb)
            bstart[nb] = base + pos
            bsize[nb] = -z if bs & 0x80000000 else z
            nb += 1
            blocks += 1
            pos += z + skip
        if bad == 0 and (pos + 4 if flg & 4 else pos) != n:
            bad = 6
        if bad == 0 and flg & 8:
            c = np.int64(0)
            for b in range(8):
                c |= np.int64(buf[base + 6 + b]) << (8 * b)
            content[k] = c
            if c < 0 or c > blocks * top:
                bad = 7
        if bad:
            problem[k] = bad
            nb = first[k]
            continue
        bound[k] = content[k] if content[k] >= 0 else blocks * top
        linked[k] = blocks > 1 and not flg & 32
    first[k_n] = nb
    return problem, bound, linked, content, first, bmax, bstart[:nb], bsize[:nb]


def _zstd_content_size(data: memoryview) -> int:
    """A Zstd frame's content size from its header, or -1 when it is not given."""
    n = len(data)
    if n < 6 or struct.unpack_from("<I", data, 0)[0] != 0xFD2FB528:
        raise ValueError("not a Zstd frame (bad magic number)")
    fhd = data[4]
    fcs_flag, single, did_flag = fhd >> 6, (fhd >> 5) & 1, fhd & 3
    pos = 5 + (0 if single else 1) + (0, 1, 2, 4)[did_flag]
    fcs_bytes = (1 if single else 0, 2, 4, 8)[fcs_flag]
    if fcs_bytes == 0:
        return -1
    if pos + fcs_bytes > n:
        raise ValueError("Zstd frame header cut short")
    raw = int.from_bytes(data[pos : pos + fcs_bytes], "little")
    return raw + 256 if fcs_bytes == 2 else raw


_FB_PROBLEMS = {
    1: "too few decoded bytes for a packet",
    2: "its size prefix does not match its decoded size",
    3: "its type identifier is not the stream's",
    4: "its root table lies outside the packet",
    5: "its table layout (vtable) lies outside the packet",
    6: "its element vector lies outside the packet",
}


@numba.njit(cache=True, nogil=True)
def _fb_vector(raw, ident):  # pragma: no cover - compiled
    """(problem code or 0, position, length) of the vector in the first field of a
    size-prefixed flatbuffer's root table whose identifier is ``ident``."""
    n = raw.shape[0]
    if n < 12:
        return 1, 0, 0
    if _u32(raw, 0) != n - 4:
        return 2, 0, 0
    if _u32(raw, 8) != ident:
        return 3, 0, 0
    root = 4 + _u32(raw, 4)
    if root + 4 > n:
        return 4, 0, 0
    back = _u32(raw, root)
    if back >= 1 << 31:
        back -= np.int64(1) << 32
    vt = root - back
    if vt < 4 or vt + 4 > n:
        return 5, 0, 0
    vsize = np.int64(raw[vt]) | (np.int64(raw[vt + 1]) << 8)
    if vt + vsize > n:
        return 5, 0, 0
    f0 = np.int64(0)
    if vsize >= 6:
        f0 = np.int64(raw[vt + 4]) | (np.int64(raw[vt + 5]) << 8)
    if f0 == 0:
        return 0, 0, 0  # no elements
    at = root + f0
    if at + 4 > n:
        return 6, 0, 0
    vec = at + _u32(raw, at)
    if vec + 4 > n:
        return 6, 0, 0
    return 0, vec + 4, _u32(raw, vec)


_IDENT = {b"EVTS": struct.unpack("<I", b"EVTS")[0], b"TRIG": struct.unpack("<I", b"TRIG")[0]}


def _vector(c: Container, offset: int, sid: int, raw: np.ndarray, ident: bytes
            ) -> tuple[int, int]:
    """(position, length) of the vector in the first field of the packet's root table."""
    code, start, count = _fb_vector(raw, _IDENT[ident])
    if code:
        raise ValueError(f"{c.name}: packet at byte {offset} (stream {sid}, "
                         f"{ident.decode()}): {_FB_PROBLEMS[code]}; the file is damaged")
    return int(start), int(count)


def event_records(c: Container, offset: int, sid: int, raw: np.ndarray) -> np.ndarray:
    """The packet's events (``raw``: its decoded bytes, uint8) as a ``DV_EVENT_DTYPE``
    view of ``raw``."""
    start, count = _vector(c, offset, sid, raw, b"EVTS")
    end = start + count * DV_EVENT_DTYPE.itemsize
    if end > raw.shape[0]:
        raise ValueError(f"{c.name}: packet at byte {offset} (stream {sid}, EVTS): "
                         f"{count} events do not fit its {raw.shape[0]} decoded bytes; the "
                         "file is damaged")
    return raw[start:end].view(DV_EVENT_DTYPE)


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
        tab = at + _u32(raw, at)
        if tab + 4 > n:
            return ts, kind, at
        back = _u32(raw, tab)
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


def trigger_records(c: Container, offset: int, sid: int, raw: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The packet's trigger records (``raw``: its decoded bytes, uint8): (timestamps,
    type codes), both int64 arrays of their own."""
    start, count = _vector(c, offset, sid, raw, b"TRIG")
    if start + 4 * count > raw.shape[0]:
        raise ValueError(f"{c.name}: packet at byte {offset} (stream {sid}, TRIG): "
                         f"{count} triggers do not fit its {raw.shape[0]} decoded bytes; the "
                         "file is damaged")
    ts, kind, bad = _trigger_tables(raw, start, count)
    if bad >= 0:
        raise ValueError(f"{c.name}: packet at byte {offset} (stream {sid}, TRIG): a "
                         f"trigger's data at decoded byte {int(bad)} lie outside the packet; "
                         "the file is damaged")
    return ts, kind
