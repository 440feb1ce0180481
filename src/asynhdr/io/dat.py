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
Only CD files are read: a trigger ``.dat`` raises ``ValueError``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr.events import EVENT_DTYPE, Recording, empty_events, empty_triggers, validate_events
from asynhdr.io import _recording, _require_file, _resolve_geometry, _supported_text

__all__ = ["dat_info", "iter_dat", "read_dat"]

logger = logging.getLogger(__name__)

_FALLBACK_SIDE = 1 << 14  # DAT 2 addresses 14 bits per coordinate
_EVENT_TYPES = {12: "cd", 14: "trigger", 0: "2d"}


def dat_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Header facts of a ``.dat`` file: ``version`` (1, 2 or None), ``dimensions``
    (``(width, height)`` or None), ``event_type`` ("cd", "trigger", ...), ``event_size``
    (bytes), ``header`` (every ``% key value`` line) and ``events`` (record count)."""
    p = _require_file(path)
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
        raise ValueError(f"{p}: no event type and size after the header; not a DAT file; "
                         f"{_supported_text()}")
    etype, esize = type_size[0], type_size[1]
    if esize != 8:
        raise ValueError(
            f"{p}: event size {esize} bytes; a DAT file has 8-byte events (not a DAT file?); "
            f"{_supported_text()}"
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
    geo = _resolve_geometry(str(p), info["dimensions"], width, height, source="header")
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
    p = _require_file(path)
    return _iter(p, int(chunk_events), width, height)


def _iter(p: Path, chunk: int, width: int | None, height: int | None
          ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    from asynhdr.io import _rechunk

    dec, _, geo = _decoder(p, width, height)

    def checked() -> Iterator[tuple[np.ndarray, np.ndarray]]:
        for ev in _packets(p, dec):
            if geo is not None:
                try:
                    validate_events(ev, width=geo[0], height=geo[1], require_sorted=False)
                except ValueError as exc:
                    raise ValueError(f"{p}: {exc}") from exc
            yield ev, empty_triggers()

    yield from _rechunk(checked(), chunk_events=chunk)


def read_dat(
    path: str | os.PathLike[str], *, width: int | None = None, height: int | None = None
) -> Recording:
    """Read a whole CD ``.dat`` file into a :class:`Recording` (metadata: format,
    source, DAT version, header lines)."""
    p = _require_file(path)
    dec, info, geo = _decoder(p, width, height)
    parts = list(_packets(p, dec))
    events = np.concatenate(parts) if len(parts) > 1 else (parts[0] if parts else empty_events())
    meta: dict[str, Any] = {"format": "dat", "source": str(p),
                            "dat_version": info["version"], "header": info["header"]}
    if geo is None:
        if events.size == 0:
            raise ValueError(f"{p}: no events and no geometry; pass width=... and height=...")
        w, h = int(events["x"].max()) + 1, int(events["y"].max()) + 1
        meta["geometry_inferred"] = True
        logger.warning("%s: no geometry in the header; using %dx%d from the largest x and y",
                       p, w, h)
    else:
        w, h = geo[0], geo[1]
    return _recording(str(p), events=events, width=w, height=h, triggers=empty_triggers(),
                      metadata=meta)
