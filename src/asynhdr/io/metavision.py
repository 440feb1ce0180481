"""Metavision's HDF5 event files (OpenEB, Metavision SDK; ``.hdf5``), read and written.

Layout (OpenEB's ``HDF5EventFileWriter``)::

    /CD/events            compound: x uint16, y uint16, p int16 (1 ON, 0 OFF), t int64 µs
    /CD/indexes           compound: id uint64, ts int64; entry 0 is (0, -1), entry k >= 1
                          the first event at or after t0 + (k - 1) 2 ms and its time - t0
                          (attribute ``offset`` = -t0); Metavision seeks with it
    /EXT_TRIGGER/events   compound: p int16 (edge value), t int64 µs, id int16 (channel)
    /EXT_TRIGGER/indexes  as /CD/indexes
    attributes of /      version "1.0", geometry "WxH", format, and the camera's facts

Metavision compresses the event datasets with its ECF codec, an HDF5 filter (id 36559)
that HDF5 loads from ``HDF5_PLUGIN_PATH`` once installed from
https://github.com/prophesee-ai/hdf5_ecf (it is not part of ``hdf5plugin``). A file that
needs a filter HDF5 does not have raises ``ValueError`` naming the filter. The writer uses
ECF when HDF5 has it and gzip otherwise (``codec="auto"``; HDF5's built-in deflate, which
Metavision and plain h5py read); ``codec="ecf"`` insists on ECF. asynhdr stores the
recording's metadata (the rig and sensor of a simulated recording) as JSON in the root
attribute ``asynhdr_metadata``, which other readers ignore.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from asynhdr.events import (
    EVENT_DTYPE,
    TRIGGER_DTYPE,
    validate_events,
    validate_triggers,
)
from asynhdr.io._common import (
    FileWriter,
    Format,
    Header,
    ReadOptions,
    check_geometry,
    int_field,
    json_metadata,
    require_file,
    resolve_geometry,
)
from asynhdr.io.hdf5 import HDF5_MAGIC, _attr_str, _ensure_plugins, _guard, _is_metavision
from asynhdr.source import pair_triggers

__all__ = ["CD_DTYPE", "ECF_FILTER_ID", "FORMAT", "TRIGGER_RECORD_DTYPE", "MetavisionWriter"]

logger = logging.getLogger(__name__)

ECF_FILTER_ID = 0x8ECF
"""HDF5 filter id of Prophesee's ECF codec (36559)."""

CD_DTYPE = np.dtype({"names": ["x", "y", "p", "t"], "formats": ["<u2", "<u2", "<i2", "<i8"],
                     "offsets": [0, 2, 4, 8], "itemsize": 16})
"""Record of ``/CD/events``."""

TRIGGER_RECORD_DTYPE = np.dtype({"names": ["p", "t", "id"], "formats": ["<i2", "<i8", "<i2"],
                                 "offsets": [0, 8, 16], "itemsize": 24})
"""Record of ``/EXT_TRIGGER/events``."""

INDEX_DTYPE = np.dtype([("id", "<u8"), ("ts", "<i8")])
INDEX_PERIOD_US = 2000
CHUNK_RECORDS = 16384
METADATA_ATTR = "asynhdr_metadata"
_FILTER_NAMES = {ECF_FILTER_ID: "Prophesee ECF"}


# --------------------------------------------------------------------------- reading


def _check_filters(name: str, d: h5py.Dataset, what: str) -> None:
    """``ValueError`` naming the filter when ``d`` needs one that HDF5 does not have."""
    plist = d.id.get_create_plist()
    for i in range(plist.get_nfilters()):
        fid, _, _, fname = plist.get_filter(i)
        if not h5py.h5z.filter_avail(fid):
            label = _FILTER_NAMES.get(fid) or (fname.decode("ascii", "replace")
                                               if isinstance(fname, bytes) else str(fname))
            hint = (" (install it from https://github.com/prophesee-ai/hdf5_ecf and set "
                    "HDF5_PLUGIN_PATH to its folder)" if fid == ECF_FILTER_ID else "")
            raise ValueError(f"{name}: dataset {what!r} is compressed with the {label} HDF5 "
                             f"filter (id {fid}), which is not installed{hint}")


class _Reader:
    """An open Metavision HDF5 file, checked."""

    def __init__(self, path: Path) -> None:
        _ensure_plugins()
        self.name = str(path)
        try:
            self.f = h5py.File(path, "r")
        except Exception as exc:
            raise ValueError(f"{self.name}: not a readable HDF5 file ({exc})") from exc
        try:
            self.cd = self._dataset("CD/events", CD_DTYPE)
            tr = self.f.get("EXT_TRIGGER/events")
            self.tr = None if tr is None else self._dataset("EXT_TRIGGER/events",
                                                            TRIGGER_RECORD_DTYPE)
        except BaseException:
            self.f.close()
            raise

    def _dataset(self, key: str, dtype: np.dtype) -> h5py.Dataset:
        d = self.f.get(key)
        if not isinstance(d, h5py.Dataset) or d.ndim != 1:
            raise ValueError(f"{self.name}: dataset {key!r} missing or not 1-D; expected "
                             "Metavision's layout (CD/events, EXT_TRIGGER/events)")
        names = d.dtype.names or ()
        need = [n for n in dtype.names or () if n not in names]
        if need:
            raise ValueError(f"{self.name}: dataset {key!r} has fields {list(names)}; "
                             f"missing {need}")
        _check_filters(self.name, d, key)
        return d

    def attrs(self) -> dict[str, Any]:
        return {k: _attr_str(v) for k, v in self.f.attrs.items()}

    def events(self, a: int, b: int) -> np.ndarray:
        raw = self.cd[a:b]
        p = int_field(self.name, "CD/events p", raw["p"], np.int16)
        bad = (p != 0) & (p != 1)
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"{self.name}: CD/events record {a + i} has p={int(p[i])}; "
                             "expected 0 (OFF) or 1 (ON)")
        out = np.empty(raw.shape[0], dtype=EVENT_DTYPE)
        out["x"] = int_field(self.name, "CD/events x", raw["x"], np.uint16)
        out["y"] = int_field(self.name, "CD/events y", raw["y"], np.uint16)
        out["p"] = 2 * p - 1
        out["t"] = int_field(self.name, "CD/events t", raw["t"], np.int64)
        return out

    def triggers(self) -> np.ndarray:
        if self.tr is None:
            return np.zeros(0, TRIGGER_DTYPE)
        raw = self.tr[:]
        out = np.empty(raw.shape[0], dtype=TRIGGER_DTYPE)
        out["t"] = int_field(self.name, "EXT_TRIGGER/events t", raw["t"], np.int64)
        out["rising"] = raw["p"] > 0
        out["id"] = int_field(self.name, "EXT_TRIGGER/events id", raw["id"], np.uint8)
        return out[np.argsort(out["t"], kind="stable")]


def _geometry(name: str, attrs: dict[str, Any]) -> tuple[int, int] | None:
    g = attrs.get("geometry")
    if g is None:
        return None
    parts = str(g).lower().split("x")
    try:
        w, h = (int(v) for v in parts)
    except ValueError:
        raise ValueError(f"{name}: attribute geometry={g!r} is not WIDTHxHEIGHT") from None
    return check_geometry(name, w, h, "the 'geometry' attribute")


def _header(path: Path, opts: ReadOptions) -> Header:
    name = str(require_file(path))
    with _guard(name):
        r = _Reader(path)
        try:
            attrs = r.attrs()
            triggers = r.triggers()
            n = int(r.cd.shape[0])
        finally:
            r.f.close()
    geo = resolve_geometry(name, _geometry(name, attrs), opts.width, opts.height,
                           source="'geometry' attribute")
    meta: Any = {}
    if METADATA_ATTR in attrs:
        try:
            meta = json.loads(attrs[METADATA_ATTR])
        except ValueError as exc:
            raise ValueError(f"{name}: attribute {METADATA_ATTR!r} is not valid JSON: "
                             f"{exc}") from None
        if not isinstance(meta, dict):
            raise ValueError(f"{name}: attribute {METADATA_ATTR!r} must hold a JSON object")
    else:
        meta = {"format": "metavision-hdf5", "source": name, "header": attrs}
    facts = {k: v for k, v in attrs.items() if k != METADATA_ATTR}
    facts.update(events=n, triggers=int(triggers.size))
    sensor = ", ".join(f"{k}={attrs[k]}" for k in ("generation", "serial_number", "system_ID")
                       if attrs.get(k)) or None
    return Header(format="metavision-hdf5", width=geo[0] if geo else None,
                  height=geo[1] if geo else None, geometry_source=geo[2] if geo else None,
                  metadata=meta, facts=facts, sensor=sensor, triggers=triggers, events=n)


def _chunks(path: Path, header: Header, read_chunk: int,
            opts: ReadOptions) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    name = str(path)
    with _guard(name):
        r = _Reader(path)
    try:
        def parts() -> Iterator[np.ndarray]:
            n = int(r.cd.shape[0])
            for a in range(0, n, read_chunk):
                with _guard(name):
                    yield r.events(a, min(a + read_chunk, n))

        assert header.triggers is not None
        yield from pair_triggers(parts(), header.triggers)
    finally:
        r.f.close()


# --------------------------------------------------------------------------- writing


def _codec(name: str, codec: str) -> dict[str, Any]:
    if codec not in ("auto", "ecf", "gzip", "none"):
        raise ValueError(f"{name}: codec must be 'auto', 'ecf', 'gzip' or 'none', got "
                         f"{codec!r}")
    ecf = bool(h5py.h5z.filter_avail(ECF_FILTER_ID))
    if codec == "ecf" and not ecf:
        raise ValueError(f"{name}: the Prophesee ECF HDF5 filter (id {ECF_FILTER_ID}) is not "
                         "installed (https://github.com/prophesee-ai/hdf5_ecf, loaded through "
                         "HDF5_PLUGIN_PATH); write with codec='gzip' instead")
    if codec == "ecf" or (codec == "auto" and ecf):
        return {"compression": ECF_FILTER_ID}
    if codec == "none":
        return {}
    return {"compression": "gzip", "compression_opts": 4, "shuffle": True}


class _Indexed:
    """One ``events`` dataset and its ``indexes``, appended to batch by batch."""

    def __init__(self, group: h5py.Group, dtype: np.dtype, opts: dict[str, Any]) -> None:
        self.ev = group.create_dataset("events", shape=(0,), maxshape=(None,), dtype=dtype,
                                       chunks=(CHUNK_RECORDS,), **opts)
        self.ix = group.create_dataset("indexes", shape=(0,), maxshape=(None,),
                                       dtype=INDEX_DTYPE, chunks=(CHUNK_RECORDS,))
        self.n = 0
        self.t0: int | None = None
        self.next_k = 0  # next 2 ms boundary to index

    def append(self, records: np.ndarray) -> None:
        if records.size == 0:
            return
        t = records["t"]
        if self.t0 is None:
            self.t0 = int(t[0])
            self.ix.attrs["offset"] = str(-self.t0)
            self._index(np.array([(0, -1)], dtype=INDEX_DTYPE))
        bounds = []
        last = int(t[-1])
        while self.t0 + self.next_k * INDEX_PERIOD_US <= last:
            bounds.append(self.t0 + self.next_k * INDEX_PERIOD_US)
            self.next_k += 1
        if bounds:
            pos = np.searchsorted(t, np.array(bounds, dtype=np.int64), side="left")
            idx = np.empty(pos.size, dtype=INDEX_DTYPE)
            idx["id"] = pos + self.n
            idx["ts"] = t[pos] - self.t0
            self._index(idx)
        self.ev.resize((self.n + records.size,))
        self.ev[self.n:] = records
        self.n += records.size

    def _index(self, idx: np.ndarray) -> None:
        m = self.ix.shape[0]
        self.ix.resize((m + idx.size,))
        self.ix[m:] = idx


class MetavisionWriter(FileWriter):
    """Write events and triggers in Metavision's HDF5 layout (see the module), atomically.

    Batches must be sorted by time and follow each other in time (the indexes point at
    the first event of each 2 ms). ``codec``: ``"auto"`` (ECF when HDF5 has the filter,
    else gzip), ``"ecf"``, ``"gzip"`` or ``"none"``. ``metadata`` is stored as JSON in the
    ``asynhdr_metadata`` attribute; ``attributes`` (strings) are written as root
    attributes as well (a camera's serial number, ...)."""

    def __init__(self, path: str | os.PathLike[str], *, width: int, height: int,
                 metadata: dict[str, Any] | None = None, codec: str = "auto",
                 attributes: dict[str, str] | None = None, overwrite: bool = True) -> None:
        super().__init__(path, overwrite=overwrite)
        self.width, self.height = check_geometry(str(path), width, height,
                                                 "the writer's arguments")
        self._meta = json_metadata(str(path), metadata)
        self._opts = _codec(str(path), codec)
        self._attrs = dict(attributes or {})
        self._cd: _Indexed | None = None
        self._tr: _Indexed | None = None
        self._last_t: int | None = None

    def _open(self, tmp: Path) -> h5py.File:
        return h5py.File(tmp, "w")

    def _start(self, f: h5py.File) -> None:
        ecf = self._opts.get("compression") == ECF_FILTER_ID
        for k, v in {"version": "1.0", "geometry": f"{self.width}x{self.height}",
                     "format": "ECF" if ecf else "HDF5", **self._attrs}.items():
            f.attrs[k] = str(v)
        f.attrs[METADATA_ATTR] = self._meta
        self._cd = _Indexed(f.create_group("CD", track_order=True), CD_DTYPE, self._opts)
        self._tr = _Indexed(f.create_group("EXT_TRIGGER", track_order=True),
                            TRIGGER_RECORD_DTYPE, {})

    def write(self, events: np.ndarray, triggers: np.ndarray | None = None) -> None:
        """Append a time-sorted batch of events and triggers."""
        self._file()
        assert self._cd is not None and self._tr is not None
        name = str(self.path)
        validate_events(events, width=self.width, height=self.height, require_sorted=True,
                        name=f"{name}: events")
        if events.size:
            if self._last_t is not None and int(events["t"][0]) < self._last_t:
                raise ValueError(f"{name}: batch starts at t={int(events['t'][0])} µs, "
                                 f"before the last event written ({self._last_t} µs)")
            self._last_t = int(events["t"][-1])
            rec = np.empty(events.size, dtype=CD_DTYPE)
            rec["x"], rec["y"], rec["t"] = events["x"], events["y"], events["t"]
            rec["p"] = events["p"] > 0
            self._cd.append(rec)
        if triggers is not None and triggers.size:
            validate_triggers(triggers, name=f"{name}: triggers")
            tr = np.zeros(triggers.size, dtype=TRIGGER_RECORD_DTYPE)
            tr["p"], tr["t"], tr["id"] = triggers["rising"], triggers["t"], triggers["id"]
            self._tr.append(tr)


FORMAT = Format(
    name="metavision-hdf5",
    extensions=(".hdf5", ".h5"),
    description="HDF5, Metavision's layout (CD/events, EXT_TRIGGER/events; ECF filter or "
                "gzip)",
    sniff=lambda path, head: head.startswith(HDF5_MAGIC) and _is_metavision(path),
    header=_header,
    chunks=_chunks,
    writer=MetavisionWriter,
)
"""The Metavision HDF5 record of the format registry (:mod:`asynhdr.io`)."""

