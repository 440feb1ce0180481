"""iniVation AEDAT 4.0 recordings (``.aedat4``) through dv-processing.

dv-processing (iniVation's library) decodes the container (LZ4 or Zstd packets).
Events become ``EVENT_DTYPE`` (AEDAT polarity 1 -> +1 ON, 0 -> -1 OFF; times in
µs as recorded, often Unix time).

Triggers: an AEDAT trigger record has a type. Only the external-input types mark
modulation cycles, and become ``TRIGGER_DTYPE`` edges:

==================================  ===========  ==
dv.TriggerType                      rising       id
==================================  ===========  ==
EXTERNAL_SIGNAL_RISING_EDGE         True         0
EXTERNAL_SIGNAL_FALLING_EDGE        False        0
EXTERNAL_SIGNAL_PULSE               True         0
EXTERNAL_GENERATOR_RISING_EDGE      True         1
EXTERNAL_GENERATOR_FALLING_EDGE     False        1
==================================  ===========  ==

Every record, external or not (APS frame and exposure markers, timestamp resets),
is counted by type in ``metadata["trigger_records"]``.

Before dv-processing opens a file, :func:`asynhdr.io._aedat_check.check_aedat4` walks
its container and checks the LZ4 data of the event and trigger packets: dv-processing
never returns from some damaged LZ4 packets (one flipped byte can do it) and holds the
GIL meanwhile, so such a file is refused first, with the packet and byte named. The
check reads the file once more and costs about half of dv-processing's own read.

Each event packet is copied out of dv-processing and converted at once (still in
cache), in one compiled pass that also checks every pixel against the event stream's
resolution: an event outside it raises a ``ValueError`` naming the file, the event's
index and the bound. That pass is the whole check: the ``Recording`` is built with
:meth:`~asynhdr.events.Recording.from_checked` and does not scan the events again.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numba
import numpy as np

from asynhdr.events import EVENT_DTYPE, TRIGGER_DTYPE, Recording, empty_triggers
from asynhdr.io import _pair_triggers, _require_file
from asynhdr.io._aedat_check import check_aedat4

__all__ = ["EXTERNAL_TRIGGER_TYPES", "aedat_info", "iter_aedat", "read_aedat"]

logger = logging.getLogger(__name__)

EXTERNAL_TRIGGER_TYPES: dict[str, tuple[bool, int]] = {
    "EXTERNAL_SIGNAL_RISING_EDGE": (True, 0),
    "EXTERNAL_SIGNAL_FALLING_EDGE": (False, 0),
    "EXTERNAL_SIGNAL_PULSE": (True, 0),
    "EXTERNAL_GENERATOR_RISING_EDGE": (True, 1),
    "EXTERNAL_GENERATOR_FALLING_EDGE": (False, 1),
}
"""AEDAT trigger type name -> (rising, id) of the edge it becomes."""


def _dv() -> Any:
    try:
        import dv_processing as dv
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise ImportError("reading .aedat4 needs dv-processing (pip install dv-processing)") \
            from exc
    return dv


def _short(exc: BaseException) -> str:
    """dv-processing's error text without its stack trace."""
    text = str(exc)
    if "Error info:" in text:
        text = text.split("Error info:", 1)[1]
    text = text.split("Stacktrace:", 1)[0]
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    return " ".join(lines[:2]) or type(exc).__name__


def _open(p: Path) -> tuple[Any, dict[str, Any]]:
    """dv-processing's reader, once the container is checked (dv-processing hangs on
    some damaged LZ4 packets, see :mod:`asynhdr.io._aedat_check`), and the header's
    camera and stream names."""
    dv = _dv()
    try:
        check_aedat4(p, types=("EVTS", "TRIG"))
    except OSError:
        _require_file(p)  # a missing file or a folder gets its own message
        raise
    try:
        reader = dv.io.MonoCameraRecording(str(p))
    except Exception as exc:  # dv-processing raises RuntimeError for damaged files
        raise ValueError(f"{p}: not a readable AEDAT 4.0 file ({_short(exc)})") from exc
    try:  # a damaged header can hold names that are not text
        facts = {"camera": str(reader.getCameraName()),
                 "streams": [str(s) for s in reader.getStreamNames()]}
        has_events = bool(reader.isEventStreamAvailable())
    except Exception as exc:
        raise ValueError(f"{p}: damaged AEDAT 4.0 header ({_short(exc)})") from exc
    if not has_events:
        raise ValueError(f"{p}: no event stream; streams found: {facts['streams']}")
    return reader, facts


_DV_FIELDS = ("timestamp", "x", "y", "polarity")
_MAX_INITIAL_EVENTS = 1 << 24  # 218 MB of EVENT_DTYPE reserved at most before it grows
_COPY_TRIM_BYTES = 32 << 20  # glibc's largest heap-served block (DEFAULT_MMAP_THRESHOLD_MAX)
_GROUP_EVENTS = 1 << 22  # events of the dv packets held before converting (64 MB)


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


def _check_dv_dtype(p: Path, dt: np.dtype) -> None:
    names = dt.names
    if names is None or any(f not in names for f in _DV_FIELDS):
        raise ValueError(
            f"{p}: dv-processing gave event records with fields {names}; "
            f"expected {', '.join(_DV_FIELDS)}"
        )


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


def _next_batch(p: Path, reader: Any) -> Any:
    try:
        return reader.getNextEventBatch()
    except Exception as exc:  # dv-processing raises RuntimeError for damaged packets
        raise ValueError(f"{p}: damaged event packet ({_short(exc)})") from exc


_TRIGGER_CODES: dict[str, dict[int, Any]] = {}


def _trigger_codes() -> tuple[dict[int, str], dict[int, tuple[bool, int]]]:
    """dv.TriggerType value -> name, and external value -> (rising, id); built once
    (``int(record.type)`` and a look-up by int cost far less than ``.type.name``)."""
    if not _TRIGGER_CODES:
        members = _dv().TriggerType.__members__
        _TRIGGER_CODES["names"] = {int(m): name for name, m in members.items()}
        _TRIGGER_CODES["edges"] = {int(members[name]): edge
                                   for name, edge in EXTERNAL_TRIGGER_TYPES.items()
                                   if name in members}
    return _TRIGGER_CODES["names"], _TRIGGER_CODES["edges"]


def _read_triggers(p: Path, reader: Any) -> tuple[np.ndarray, dict[str, int]]:
    """External edges as TRIGGER_DTYPE, and counts of every record by type name."""
    counts: dict[str, int] = {}
    if not reader.isTriggerStreamAvailable():
        return empty_triggers(), counts
    names, edges = _trigger_codes()
    records: list[tuple[int, int]] = []  # (type code, timestamp)
    try:
        while True:
            batch = reader.getNextTriggerBatch()
            if batch is None:
                break
            # indexing: pybind's iterator costs µs per batch
            records.extend((int(r.type), r.timestamp) for r in map(batch.__getitem__,
                                                                    range(len(batch))))
    except ValueError:
        raise
    except Exception as exc:
        raise ValueError(f"{p}: damaged trigger stream ({_short(exc)})") from exc
    for code in {c for c, _ in records}:
        name = names.get(code, f"TRIGGER_TYPE_{code}")
        counts[name] = counts.get(name, 0) + sum(1 for c, _ in records if c == code)
    kept = [(t, edges[c]) for c, t in records if c in edges]
    if not kept:
        return empty_triggers(), counts
    tr = np.empty(len(kept), dtype=TRIGGER_DTYPE)
    tr["t"] = [t for t, _ in kept]
    tr["rising"] = [e[0] for _, e in kept]
    tr["id"] = [e[1] for _, e in kept]
    t = tr["t"]
    if (t[1:] < t[:-1]).any():
        tr = tr[np.argsort(t, kind="stable")]
    return tr, counts


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
    p = _require_file(path)
    reader, facts = _open(p)
    width, height = _geometry(p, reader)
    tr, counts = _read_triggers(p, reader)
    info = _metadata(p, facts, counts)
    info.update(width=width, height=height, triggers=int(tr.size))
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
    p = _require_file(path)
    return _iter(p, chunk_events)


def _geometry(p: Path, reader: Any) -> tuple[int, int]:
    try:
        res = reader.getEventResolution()
    except Exception as exc:
        raise ValueError(f"{p}: damaged AEDAT 4.0 header ({_short(exc)})") from exc
    if res is None:
        raise ValueError(f"{p}: the event stream gives no resolution")
    if not (0 < int(res[0]) <= 65536 and 0 < int(res[1]) <= 65536):
        raise ValueError(f"{p}: the event stream's resolution {int(res[0])}x{int(res[1])} "
                         "is not a sensor's")
    return int(res[0]), int(res[1])


def _packets(p: Path, reader: Any) -> Iterator[np.ndarray]:
    """Each non-empty dv packet as its own EVENT_DTYPE array (pixels checked)."""
    width, height = _geometry(p, reader)
    seen = 0
    while True:
        batch = _next_batch(p, reader)
        if batch is None:
            return
        a = batch.numpy()
        m = a.shape[0]
        if m == 0:
            continue
        _check_dv_dtype(p, a.dtype)
        out = np.empty(m, dtype=EVENT_DTYPE)
        if not _convert_dv(a, out, 0, width, height):
            _raise_outside(p, a, seen, width, height)
        seen += m
        yield out


def _iter(p: Path, chunk_events: int | None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    reader, _ = _open(p)
    triggers, _ = _read_triggers(p, reader)
    paired = _pair_triggers(_packets(p, reader), triggers)
    if chunk_events is not None:
        from asynhdr.io import _rechunk

        yield from _rechunk(paired, chunk_events=int(chunk_events))
        return
    yield from paired


def _convert_group(p: Path, group: list[Any], buf: np.ndarray, n: int, width: int,
                   height: int) -> int:
    """Copy each of dv's packets ``group`` out (``numpy()``) and convert it into
    ``buf[n:]`` at once, while the copy is in cache; return the new event count.

    On the calling thread: ``numpy()`` holds the GIL, so a second thread mostly waits
    for it (sharing the packets between two threads measured slower).
    """
    for store in group:
        a = store.numpy()
        _check_dv_dtype(p, a.dtype)
        if not _convert_dv(a, buf, n, width, height):
            _raise_outside(p, a, n, width, height)
        n += a.shape[0]
    return n


def _read_all_events(p: Path, reader: Any, width: int, height: int) -> np.ndarray:
    """Every event, in one array.

    dv's packets are fetched in groups of about ``_GROUP_EVENTS`` events and kept as
    dv holds them; each packet is then copied out (``numpy()``) and converted at once,
    while the copy is still in cache. A file that fits in one group goes straight
    into an array of its exact size. Larger ones go into a buffer with room for
    ``file size / 2`` events (reserved memory that is never written costs nothing),
    doubled when full, then trimmed to the events read: below ``_COPY_TRIM_BYTES`` by a
    copy into an exact-size array (the allocator then reuses the same memory from one
    read to the next instead of mapping, and faulting in, fresh pages each time),
    above it in place (``realloc``: no second copy).
    """
    buf: np.ndarray | None = None
    cap = n = 0
    group: list[Any] = []
    pending = 0
    while True:
        batch = _next_batch(p, reader)
        if batch is not None:
            m = len(batch)
            if m == 0:
                continue
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
    reader, facts = _open(p)
    width, height = _geometry(p, reader)
    triggers, counts = _read_triggers(p, reader)
    events = _read_all_events(p, reader, width, height)
    meta = _metadata(p, facts, counts)
    logger.info("%s: AEDAT 4.0 from %s, %dx%d, %d events, %d external trigger edges "
                "(%d trigger records)", p, meta["camera"], width, height, events.size,
                triggers.size, sum(counts.values()))
    # _convert_dv checked every pixel and wrote every polarity as +-1.
    return Recording.from_checked(events=events, width=width, height=height,
                                  triggers=triggers, metadata=meta)
