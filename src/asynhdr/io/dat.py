"""Prophesee DAT recordings (``.dat``, CD events), read through faery.

Layout (Prophesee's legacy format): ASCII header lines starting with ``%``
(``% Version 2``, ``% Width W``, ``% Height H``, ``% Date ...``), then two bytes
(event type: 12 = CD, 14 = external trigger; event size: 8), then one 8-byte
little-endian record per event: ``uint32 t`` (µs) and ``uint32 data`` with
``x = data & 0x3FFF``, ``y = (data >> 14) & 0x3FFF``, ``p = data >> 28`` (DAT 2;
DAT 1 packs ``x`` in 9 bits, ``y`` in 8 and ``p`` in 1).

faery's decoder unwraps the 32-bit timestamp overflow and holds time monotone.
A file without geometry in its header takes ``width``/``height`` from the
arguments, else the largest x and y + 1 (``metadata["geometry_inferred"]``).
Only CD files are read: a trigger ``.dat`` raises ``ValueError``. A file cut inside a
record is read up to the cut, with a warning. :class:`DatWriter` writes DAT 2 CD files
with the recording's metadata on a ``% asynhdr_metadata`` header line.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

import numpy as np

from asynhdr.events import (
    EVENT_DTYPE,
    Recording,
    empty_events,
    empty_triggers,
    validate_events,
    validate_triggers,
)
from asynhdr.io._common import (
    FileWriter,
    Format,
    Header,
    ReadOptions,
    check_geometry,
    json_metadata,
    recording,
    require_file,
    resolve_geometry,
)
from asynhdr.source import rechunk

__all__ = ["FORMAT", "DatWriter", "dat_info", "iter_dat", "read_dat"]

logger = logging.getLogger(__name__)

_FALLBACK_SIDE = 1 << 14  # DAT 2 addresses 14 bits per coordinate
_EVENT_TYPES = {12: "cd", 14: "trigger", 0: "2d"}


def dat_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Header facts of a ``.dat`` file: ``version`` (1, 2 or None), ``dimensions``
    (``(width, height)`` or None), ``event_type`` ("cd", "trigger", ...), ``event_size``
    (bytes), ``header`` (every ``% key value`` line) and ``events`` (record count)."""
    p = require_file(path)
    header: dict[str, str] = {}
    with open(p, "rb") as f:
        while True:
            pos = f.tell()
            first = f.read(1)
            if first != b"%":
                f.seek(pos)
                break
            line = f.readline().decode("latin-1").strip()
            key, _, value = line.partition(" ")
            if key:
                header[key.lower()] = value.strip()
        type_size = f.read(2)
        body_start = f.tell()
        f.seek(0, os.SEEK_END)
        body = f.tell() - body_start
    if len(type_size) < 2:
        raise ValueError(f"{p}: no event type and size after the header; not a DAT file")
    etype, esize = type_size[0], type_size[1]
    if esize != 8:
        raise ValueError(
            f"{p}: event size {esize} bytes; a DAT file has 8-byte events (not a DAT file?)"
        )
    version: int | None = None
    if "version" in header:
        try:
            version = int(header["version"])
        except ValueError:
            raise ValueError(f"{p}: header '% Version {header['version']}' is not a number") \
                from None
    dims: tuple[int, int] | None = None
    if "width" in header and "height" in header:
        try:
            dims = (int(header["width"]), int(header["height"]))
        except ValueError:
            raise ValueError(f"{p}: header Width/Height are not whole numbers") from None
    return {
        "format": "dat",
        "version": version,
        "dimensions": dims,
        "event_type": _EVENT_TYPES.get(etype, f"unknown ({etype})"),
        "event_size": esize,
        "header": header,
        "events": body // 8,
        "trailing_bytes": body % 8,
    }


def _decoder(p: Path, width: int | None, height: int | None) -> tuple[Any, dict[str, Any],
                                                                      tuple[int, int, str] | None]:
    from faery.extension import dat as faery_dat

    info = dat_info(p)
    if info["event_type"] != "cd":
        raise ValueError(
            f"{p}: holds {info['event_type']} events, not CD events; asynhdr reads CD .dat "
            "files only"
        )
    geo = resolve_geometry(str(p), info["dimensions"], width, height, source="header")
    fallback = (geo[0], geo[1]) if geo is not None else (_FALLBACK_SIDE, _FALLBACK_SIDE)
    try:
        dec = faery_dat.Decoder(str(p), fallback, "dat2")
    except Exception as exc:  # faery raises RuntimeError for malformed files
        raise ValueError(f"{p}: not a readable DAT file ({exc})") from exc
    return dec, info, geo


def _convert(packet: np.ndarray) -> np.ndarray:
    out = np.empty(packet.shape[0], dtype=EVENT_DTYPE)
    out["t"] = packet["t"].astype(np.int64)
    out["x"] = packet["x"]
    out["y"] = packet["y"]
    out["p"] = np.where(packet["payload"] > 0, 1, -1).astype(np.int8)
    return out


def _packets(p: Path, dec: Any) -> Iterator[np.ndarray]:
    try:
        with dec:
            for packet in dec:
                if packet.shape[0]:
                    yield _convert(packet)
    except ValueError:
        raise
    except Exception as exc:
        raise ValueError(f"{p}: damaged DAT data ({exc})") from exc


def iter_dat(
    path: str | os.PathLike[str],
    *,
    chunk_events: int = 1_000_000,
    width: int | None = None,
    height: int | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Decode a CD ``.dat`` file in chunks of ``chunk_events`` events: yield
    ``(events, triggers)`` (triggers always empty). Errors on ``next``."""
    if int(chunk_events) < 1:
        raise ValueError(f"iter_dat: chunk_events must be >= 1, got {chunk_events}")
    p = require_file(path)
    return _iter(p, int(chunk_events), width, height)


def _iter(p: Path, chunk: int, width: int | None, height: int | None
          ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    dec, _, geo = _decoder(p, width, height)

    def checked() -> Iterator[tuple[np.ndarray, np.ndarray]]:
        for ev in _packets(p, dec):
            if geo is not None:
                try:
                    validate_events(ev, width=geo[0], height=geo[1], require_sorted=False)
                except ValueError as exc:
                    raise ValueError(f"{p}: {exc}") from exc
            yield ev, empty_triggers()

    yield from rechunk(checked(), chunk_events=chunk)


def read_dat(
    path: str | os.PathLike[str], *, width: int | None = None, height: int | None = None
) -> Recording:
    """Read a whole CD ``.dat`` file into a :class:`Recording` (metadata: format,
    source, DAT version, header lines)."""
    p = require_file(path)
    dec, info, geo = _decoder(p, width, height)
    parts = list(_packets(p, dec))
    events = np.concatenate(parts) if len(parts) > 1 else (parts[0] if parts else empty_events())
    stored = _stored_metadata(p, info["header"])
    meta: dict[str, Any] = stored if stored is not None else {
        "format": "dat", "source": str(p), "dat_version": info["version"],
        "header": info["header"]}
    if geo is None:
        if events.size == 0:
            raise ValueError(f"{p}: no events and no geometry; pass width=... and height=...")
        w, h = check_geometry(str(p), int(events["x"].max()) + 1, int(events["y"].max()) + 1,
                              "the largest x and y")
        meta["geometry_inferred"] = True
        logger.warning("%s: no geometry in the header; using %dx%d from the largest x and y",
                       p, w, h)
    else:
        w, h = geo[0], geo[1]
    return recording(str(p), events=events, width=w, height=h, triggers=empty_triggers(),
                      metadata=meta)


METADATA_KEY = "asynhdr_metadata"
"""Header key of the line holding the recording's metadata as JSON."""

_MAX_DAT_TIME_US = (1 << 32) - 1


def _stored_metadata(p: Path, header: dict[str, str]) -> dict[str, Any] | None:
    text = header.get(METADATA_KEY)
    if text is None:
        return None
    try:
        meta = json.loads(text)
    except ValueError as exc:
        raise ValueError(f"{p}: header '% {METADATA_KEY}' is not valid JSON: {exc}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{p}: header '% {METADATA_KEY}' must hold a JSON object")
    return meta


class DatWriter(FileWriter):
    """CD events as a Prophesee DAT 2 file, atomically: ``%`` header lines (``Version 2``,
    ``Width``, ``Height``, the metadata as JSON on ``% asynhdr_metadata``), the event type
    (12, CD) and size (8), then per event ``uint32 t`` (µs) and ``uint32 x | y << 14 |
    p << 28`` (p 1 ON, 0 OFF). A DAT file holds no triggers: those given are left out
    and counted in a warning. Times must lie in ``[0, 2**32)`` µs, in order."""

    def __init__(self, path: str | os.PathLike[str], *, width: int, height: int,
                 metadata: dict[str, Any] | None = None, overwrite: bool = True) -> None:
        super().__init__(path, overwrite=overwrite)
        self.width, self.height = check_geometry(str(path), width, height,
                                                 "the writer's arguments")
        meta = json_metadata(str(path), metadata)
        self._head = (f"% Data file containing CD events.\n% Version 2\n"
                      f"% Width {self.width}\n% Height {self.height}\n"
                      f"% {METADATA_KEY} {meta}\n").encode("ascii") + bytes([12, 8])
        self._last_t = 0
        self.triggers_left_out = 0

    def _start(self, f: BinaryIO) -> None:
        f.write(self._head)

    def write(self, events: np.ndarray, triggers: np.ndarray | None = None) -> None:
        """Append time-sorted events (triggers are counted and left out)."""
        f = self._file()
        validate_events(events, width=self.width, height=self.height, require_sorted=True,
                        name=f"{self.path}: events")
        if triggers is not None and triggers.size:
            validate_triggers(triggers, name=f"{self.path}: triggers")
            self.triggers_left_out += int(triggers.size)
        if events.size == 0:
            return
        t = events["t"]
        if int(t[0]) < self._last_t or int(t[-1]) > _MAX_DAT_TIME_US:
            raise ValueError(f"{self.path}: times {int(t[0])}..{int(t[-1])} µs are outside "
                             f"what DAT holds in order (0..{_MAX_DAT_TIME_US} µs from the "
                             "previous batch)")
        self._last_t = int(t[-1])
        rec = np.empty((events.size, 2), dtype="<u4")
        rec[:, 0] = t
        rec[:, 1] = (events["x"].astype(np.uint32) | (events["y"].astype(np.uint32) << 14)
                     | ((events["p"] > 0).astype(np.uint32) << 28))
        f.write(rec.data)

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        super().__exit__(exc_type, exc, tb)
        if exc_type is None and self.triggers_left_out:
            logger.warning("%s: %d trigger edges left out: a CD .dat file holds no triggers",
                           self.path, self.triggers_left_out)


def _header(path: Path, opts: ReadOptions) -> Header:
    info = dat_info(path)
    if info["trailing_bytes"]:
        logger.warning("%s: the file ends %d bytes into an 8-byte record: it was cut; the "
                       "%d whole records before the cut are read", path,
                       info["trailing_bytes"], info["events"])
    if info["event_type"] != "cd":
        raise ValueError(f"{path}: holds {info['event_type']} events, not CD events; "
                         "asynhdr reads CD .dat files only")
    geo = resolve_geometry(str(path), info["dimensions"], opts.width, opts.height,
                           source="header")
    meta = _stored_metadata(path, info["header"])
    if meta is None:
        meta = {"format": "dat", "source": str(path), "dat_version": info["version"],
                "header": info["header"]}
    return Header(format="dat", width=geo[0] if geo else None, height=geo[1] if geo else None,
                  geometry_source=geo[2] if geo else None, metadata=meta, facts=info,
                  triggers=empty_triggers(), events=info["events"])


FORMAT = Format(
    name="dat",
    extensions=(".dat",),
    description="Prophesee DAT, CD events (legacy Metavision)",
    sniff=lambda path, head: head.startswith(b"%") or not head,
    header=_header,
    chunks=lambda path, header, n, opts: iter_dat(path, chunk_events=n, width=opts.width,
                                                  height=opts.height),
    read=lambda path, header, opts: read_dat(path, width=opts.width, height=opts.height),
    writer=DatWriter,
)
"""The ``.dat`` record of the format registry (:mod:`asynhdr.io`)."""
