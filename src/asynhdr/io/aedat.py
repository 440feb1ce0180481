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
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numba
import numpy as np

from asynhdr.events import EVENT_DTYPE, Recording, empty_triggers, make_triggers
from asynhdr.io import _pair_triggers, _recording, _require_file

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


def _open(p: Path) -> Any:
    dv = _dv()
    try:
        reader = dv.io.MonoCameraRecording(str(p))
    except Exception as exc:  # dv-processing raises RuntimeError for damaged files
        raise ValueError(f"{p}: not a readable AEDAT 4.0 file ({_short(exc)})") from exc
    if not reader.isEventStreamAvailable():
        raise ValueError(
            f"{p}: no event stream; streams found: {list(reader.getStreamNames())}"
        )
    return reader


_POLARITY = np.array([-1, 1], dtype=np.int8)  # AEDAT polarity 0 (OFF), 1 (ON) -> -1, +1
_DV_LAYOUT = (0, 8, 10, 12, 16)  # byte offsets of timestamp, x, y, polarity; itemsize
_OUT_LAYOUT = (0, 2, 4, 5, 13)  # byte offsets of x, y, p, t in EVENT_DTYPE; itemsize


@numba.njit(cache=True, nogil=True)
def _convert_dv(src: np.ndarray, dst: np.ndarray) -> None:  # pragma: no cover - compiled
    """One pass over dv's records (rows of 16 bytes: int64 time, int16 x, int16 y,
    polarity byte) into EVENT_DTYPE rows (13 bytes: x, y, p, t), byte by byte;
    polarity 0 -> -1 (0xFF), else +1."""
    for i in range(src.shape[0]):
        for j in range(8):
            dst[i, 5 + j] = src[i, j]
        dst[i, 0] = src[i, 8]
        dst[i, 1] = src[i, 9]
        dst[i, 2] = src[i, 10]
        dst[i, 3] = src[i, 11]
        dst[i, 4] = 1 if src[i, 12] != 0 else 255


_LAYOUT_CHECKED: dict[np.dtype, bool] = {}


def _is_dv_layout(dt: np.dtype) -> bool:
    """Whether dv's event dtype is the one :func:`_convert_dv` assumes (cached)."""
    ok = _LAYOUT_CHECKED.get(dt)
    if ok is None:
        ok = _LAYOUT_CHECKED[dt] = _check_dv_layout(dt)
    return ok


def _check_dv_layout(dt: np.dtype) -> bool:
    f = dt.fields
    if f is None or dt.itemsize != _DV_LAYOUT[4] or sys.byteorder != "little":
        return False
    want = {"timestamp": ("<i8", 0), "x": ("<i2", 8), "y": ("<i2", 10)}
    for key, (code, off) in want.items():
        if key not in f or f[key][0] != np.dtype(code) or f[key][1] != off:
            return False
    return "polarity" in f and f["polarity"][0].itemsize == 1 and f["polarity"][1] == 12


def _out_layout_ok() -> bool:
    f = EVENT_DTYPE.fields
    if f is None:
        return False
    return (EVENT_DTYPE.itemsize, f["x"][1], f["y"][1], f["p"][1], f["t"][1]) == (
        _OUT_LAYOUT[4], *_OUT_LAYOUT[:4])


_FAST_OUT = _out_layout_ok()


def _convert_into(a: np.ndarray, out: np.ndarray) -> None:
    """dv's event array (timestamp, x, y, polarity) -> EVENT_DTYPE, written into ``out``
    (a contiguous slice): one compiled pass for dv's usual layout, else field by field."""
    m = a.shape[0]
    if (_FAST_OUT and m and _is_dv_layout(a.dtype) and a.flags.c_contiguous
            and out.flags.c_contiguous):
        _convert_dv(a.view(np.uint8).reshape(m, _DV_LAYOUT[4]),
                    out.view(np.uint8).reshape(m, _OUT_LAYOUT[4]))
        return
    out["t"] = a["timestamp"]
    out["x"] = a["x"]
    out["y"] = a["y"]
    out["p"] = _POLARITY.take((a["polarity"] != 0).view(np.uint8))


def _events(batch: Any) -> np.ndarray:
    """dv EventStore -> EVENT_DTYPE array."""
    a = batch.numpy()
    out = np.empty(a.shape[0], dtype=EVENT_DTYPE)
    _convert_into(a, out)
    return out


def _read_triggers(p: Path, reader: Any) -> tuple[np.ndarray, dict[str, int]]:
    """External edges as TRIGGER_DTYPE, and counts of every record by type name."""
    counts: dict[str, int] = {}
    if not reader.isTriggerStreamAvailable():
        return empty_triggers(), counts
    ts: list[int] = []
    rising: list[bool] = []
    ids: list[int] = []
    try:
        while True:
            batch = reader.getNextTriggerBatch()
            if batch is None:
                break
            for rec in batch:
                tname = rec.type.name
                counts[tname] = counts.get(tname, 0) + 1
                edge = EXTERNAL_TRIGGER_TYPES.get(tname)
                if edge is not None:
                    ts.append(int(rec.timestamp))
                    rising.append(edge[0])
                    ids.append(edge[1])
    except Exception as exc:
        raise ValueError(f"{p}: damaged trigger stream ({_short(exc)})") from exc
    if not ts:
        return empty_triggers(), counts
    tr = make_triggers(np.array(ts, dtype=np.int64), np.array(rising),
                       np.array(ids, dtype=np.uint8))
    order = np.argsort(tr["t"], kind="stable")
    return tr[order], counts


def _metadata(p: Path, reader: Any, counts: dict[str, int]) -> dict[str, Any]:
    return {
        "format": "aedat4",
        "source": str(p),
        "camera": str(reader.getCameraName()),
        "streams": [str(s) for s in reader.getStreamNames()],
        "trigger_records": dict(sorted(counts.items())),
        "trigger_channels": {"0": "EXTERNAL_SIGNAL", "1": "EXTERNAL_GENERATOR"},
    }


def aedat_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Header facts of an AEDAT 4.0 file: ``camera``, ``width``, ``height``, ``streams``,
    ``trigger_records`` (every trigger record by type) and the external ``triggers``
    count, without decoding the events."""
    p = _require_file(path)
    reader = _open(p)
    res = reader.getEventResolution()
    tr, counts = _read_triggers(p, reader)
    info = _metadata(p, reader, counts)
    info.update(width=int(res[0]), height=int(res[1]), triggers=int(tr.size))
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


def _packets(p: Path, reader: Any) -> Iterator[np.ndarray]:
    while True:
        try:
            batch = reader.getNextEventBatch()
        except Exception as exc:
            raise ValueError(f"{p}: damaged event packet ({_short(exc)})") from exc
        if batch is None:
            return
        if len(batch):
            yield _events(batch)


def _iter(p: Path, chunk_events: int | None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    reader = _open(p)
    triggers, _ = _read_triggers(p, reader)
    paired = _pair_triggers(_packets(p, reader), triggers)
    if chunk_events is not None:
        from asynhdr.io import _rechunk

        yield from _rechunk(paired, chunk_events=int(chunk_events))
        return
    yield from paired


def _read_all_events(p: Path, reader: Any) -> np.ndarray:
    """Every event: dv's packets are gathered, then converted straight into one array
    of the exact size (no concatenation, no second copy)."""
    arrays = []
    n = 0
    while True:
        try:
            batch = reader.getNextEventBatch()
        except Exception as exc:
            raise ValueError(f"{p}: damaged event packet ({_short(exc)})") from exc
        if batch is None:
            break
        a = batch.numpy()
        if a.shape[0]:
            arrays.append(a)
            n += a.shape[0]
    out = np.empty(n, dtype=EVENT_DTYPE)
    i = 0
    for a in arrays:
        m = a.shape[0]
        _convert_into(a, out[i : i + m])
        i += m
    return out


def read_aedat(path: str | os.PathLike[str]) -> Recording:
    """Read a whole AEDAT 4.0 file: events, external trigger edges, geometry from the
    event stream's resolution, and metadata (camera, streams, ``trigger_records``)."""
    p = _require_file(path)
    reader = _open(p)
    res = reader.getEventResolution()
    if res is None:
        raise ValueError(f"{p}: the event stream gives no resolution")
    triggers, counts = _read_triggers(p, reader)
    events = _read_all_events(p, reader)
    meta = _metadata(p, reader, counts)
    logger.info("%s: AEDAT 4.0 from %s, %dx%d, %d events, %d external trigger edges "
                "(%d trigger records)", p, meta["camera"], res[0], res[1], events.size,
                triggers.size, sum(counts.values()))
    return _recording(str(p), events=events, width=int(res[0]), height=int(res[1]),
                      triggers=triggers, metadata=meta)
