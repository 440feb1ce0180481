"""Recordings in HDF5 (h5py + hdf5plugin): compressed chunks, read in slices.

Layout::

    /events/x        uint16 (N,)   pixel column
    /events/y        uint16 (N,)   pixel row
    /events/t        int64  (N,)   time, µs
    /events/p        int8   (N,)   polarity, +1 ON / -1 OFF
    /triggers/t      int64  (M,)   time, µs
    /triggers/rising uint8  (M,)   1 rising edge, 0 falling
    /triggers/id     uint8  (M,)   input channel
    attributes of /: width, height (pixels), time_unit = "us", metadata (JSON),
                     format_version = 1

Datasets are resizable, chunked (2^18 elements) and compressed with Blosc (Zstd,
bit-shuffle) from hdf5plugin; gzip when that filter is not available. Files from
other programs with the same dataset names are read too: ``time_unit`` ``"ms"`` or
``"s"`` (attribute or argument; float or integer times) is converted to integer µs
and the conversion is recorded in ``metadata["time_unit_source"]``; a missing
``/triggers`` group reads as no triggers.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import Any

import h5py
import numpy as np

from asynhdr.events import (
    Recording,
    empty_triggers,
    make_events,
    make_triggers,
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
    recording,
    require_file,
    resolve_geometry,
)
from asynhdr.source import pair_triggers

__all__ = [
    "FORMAT",
    "HDF5_FORMAT_VERSION",
    "Hdf5Writer",
    "hdf5_info",
    "iter_hdf5",
    "load_hdf5",
    "save_hdf5",
]

logger = logging.getLogger(__name__)

HDF5_FORMAT_VERSION = 1
"""Version of the layout written here."""

CHUNK_ELEMENTS = 1 << 18
"""Elements per HDF5 chunk of every dataset."""

TIME_UNITS_US = {"us": 1, "ms": 1_000, "s": 1_000_000}
"""Accepted time units and their size in µs."""

_EVENT_FIELDS = (("x", np.uint16), ("y", np.uint16), ("t", np.int64), ("p", np.int8))
_TRIGGER_FIELDS = (("t", np.int64), ("rising", np.uint8), ("id", np.uint8))
_ALIASES = {"ts": "t", "timestamp": "t", "timestamps": "t", "time": "t", "times": "t",
            "pol": "p", "polarity": "p", "polarities": "p", "xs": "x", "ys": "y", "ps": "p"}


def _compression(codec: str) -> dict[str, Any]:
    """h5py dataset options for a codec: "blosc" (Zstd + bit-shuffle), "lz4", "gzip", "none"."""
    if codec == "none":
        return {}
    if codec in ("blosc", "lz4"):
        try:
            import hdf5plugin

            if codec == "blosc" and h5py.h5z.filter_avail(hdf5plugin.BLOSC_ID):
                return dict(hdf5plugin.Blosc(cname="zstd", clevel=3,
                                             shuffle=hdf5plugin.Blosc.BITSHUFFLE))
            if codec == "lz4" and h5py.h5z.filter_avail(hdf5plugin.BLOSC_ID):
                return dict(hdf5plugin.Blosc(cname="lz4", clevel=5,
                                             shuffle=hdf5plugin.Blosc.SHUFFLE))
        except ImportError:
            pass
        logger.info("hdf5plugin Blosc is not available; using gzip")
        codec = "gzip"
    if codec == "gzip":
        return {"compression": "gzip", "compression_opts": 4, "shuffle": True}
    raise ValueError(f"hdf5: unknown codec {codec!r}; use 'blosc', 'lz4', 'gzip' or 'none'")


def _ensure_plugins() -> None:
    """Register hdf5plugin's filters so compressed files from anywhere can be read."""
    with contextlib.suppress(ImportError):
        import hdf5plugin  # noqa: F401


class Hdf5Writer(FileWriter):
    """Write events (and triggers) to an HDF5 file in pieces, atomically.

    The file is written under a temporary name beside ``path`` and renamed when the
    ``with`` block ends without an exception (otherwise removed)::

        with Hdf5Writer("out.h5", width=346, height=260) as w:
            for events, triggers in chunks:
                w.write(events, triggers)

    Parameters
    ----------
    path : target file.
    width, height : sensor geometry, pixels.
    metadata : JSON-serialisable dict stored as the ``metadata`` attribute.
    codec : "blosc" (default), "lz4", "gzip" or "none". Blosc is an HDF5 filter that
        h5py reads only once ``hdf5plugin`` is imported; gzip is read everywhere.
    overwrite : replace an existing file (else ``FileExistsError``).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        width: int,
        height: int,
        metadata: dict[str, Any] | None = None,
        codec: str = "blosc",
        overwrite: bool = True,
    ) -> None:
        super().__init__(path, overwrite=overwrite)
        self.width, self.height = check_geometry(str(path), width, height,
                                                 "the writer's arguments")
        self._meta = json_metadata(str(path), metadata)
        self._opts = _compression(codec)
        self.n_events = 0
        self.n_triggers = 0
        self._last_trigger_t: int | None = None

    def _open(self, tmp: Path) -> h5py.File:
        return h5py.File(tmp, "w")

    def _start(self, f: h5py.File) -> None:
        f.attrs["width"] = np.int64(self.width)
        f.attrs["height"] = np.int64(self.height)
        f.attrs["time_unit"] = "us"
        f.attrs["metadata"] = self._meta
        f.attrs["format_version"] = np.int64(HDF5_FORMAT_VERSION)
        for group, fields in (("events", _EVENT_FIELDS), ("triggers", _TRIGGER_FIELDS)):
            g = f.create_group(group)
            for key, dt in fields:
                g.create_dataset(key, shape=(0,), maxshape=(None,), dtype=dt,
                                 chunks=(CHUNK_ELEMENTS,), **self._opts)

    def write(self, events: np.ndarray, triggers: np.ndarray | None = None) -> None:
        """Append events (``EVENT_DTYPE``, file order kept) and triggers (sorted, after
        the ones already written)."""
        f = self._file()
        validate_events(events, width=self.width, height=self.height, require_sorted=False)
        if events.size:
            n0, n1 = self.n_events, self.n_events + events.size
            g = f["events"]
            for key, _ in _EVENT_FIELDS:
                g[key].resize((n1,))
                g[key][n0:n1] = events[key]
            self.n_events = n1
        if triggers is not None and triggers.size:
            validate_triggers(triggers)
            if self._last_trigger_t is not None and int(triggers["t"][0]) < self._last_trigger_t:
                raise ValueError(
                    f"{self.path}: trigger at t={int(triggers['t'][0])} µs comes before the "
                    f"last one written ({self._last_trigger_t} µs); triggers must be sorted"
                )
            m0, m1 = self.n_triggers, self.n_triggers + triggers.size
            g = f["triggers"]
            for key, _ in _TRIGGER_FIELDS:
                g[key].resize((m1,))
                g[key][m0:m1] = triggers[key]
            self.n_triggers = m1
            self._last_trigger_t = int(triggers["t"][-1])

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        super().__exit__(exc_type, exc, tb)
        if exc_type is None:
            logger.info("%s: wrote %d events, %d triggers", self.path, self.n_events,
                        self.n_triggers)


def save_hdf5(path: str | os.PathLike[str], recording: Recording, *, codec: str = "blosc",
              overwrite: bool = True) -> None:
    """Write a whole recording to HDF5 (atomically); see the module's layout."""
    with Hdf5Writer(path, width=recording.width, height=recording.height,
                    metadata=recording.metadata, codec=codec, overwrite=overwrite) as w:
        w.write(recording.events, recording.triggers)


# --------------------------------------------------------------------------- reading


def _datasets(f: h5py.File) -> list[str]:
    names: list[str] = []

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset):
            names.append(name)

    f.visititems(visit)
    return sorted(names)


def _attr_str(v: Any) -> str:
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.ndarray) and v.shape == ():
        return _attr_str(v[()])
    return str(v)


def _geometry_attrs(name: str, attrs: Any) -> tuple[int, int] | None:
    """``(width, height)`` from the root attributes, None when both are absent;
    ``ValueError`` naming the file when only one is there or one is not a whole number."""
    if "width" not in attrs and "height" not in attrs:
        return None
    if "width" not in attrs or "height" not in attrs:
        raise ValueError(f"{name}: attribute {'height' if 'width' in attrs else 'width'!r} "
                         "missing; expected both width and height (pixels)")
    out = []
    for key in ("width", "height"):
        v = attrs[key]
        try:
            if isinstance(v, (bytes, str, np.bytes_, np.str_)) or float(v) != int(v):
                raise ValueError
            out.append(int(v))
        except (TypeError, ValueError):
            raise ValueError(f"{name}: attribute {key}={_attr_str(v)!r} is not a whole number "
                             "of pixels; expected e.g. width=346, height=260") from None
    return check_geometry(name, out[0], out[1], "the file attributes")


def _version(name: str, attrs: Any) -> int | None:
    if "format_version" not in attrs:
        return None
    try:
        return int(attrs["format_version"])
    except (TypeError, ValueError):
        raise ValueError(f"{name}: attribute format_version="
                         f"{_attr_str(attrs['format_version'])!r} is not an integer") from None


def _missing_dataset(name: str, f: h5py.File, want: str) -> ValueError:
    found = _datasets(f)
    group, key = want.split("/")
    near = [d for d in found if d.startswith(group + "/")
            and _ALIASES.get(d.split("/", 1)[1].lower()) == key]
    hint = ""
    if near:
        hint = f"; {near[0]!r} looks like it, under another name"
        if key == "t":
            hint += " (seconds? then pass time_unit='s')"
    shown = ", ".join(repr(d) for d in found[:12]) + (" ..." if len(found) > 12 else "")
    return ValueError(
        f"{name}: dataset {want!r} missing; found {shown or 'no datasets'}{hint} — expected "
        "events/x, events/y, events/t, events/p (and triggers/t, triggers/rising, triggers/id)"
    )


class _Reader:
    """An open asynhdr-layout HDF5 file, checked."""

    def __init__(self, path: Path, *, width: int | None, height: int | None,
                 time_unit: str | None) -> None:
        _ensure_plugins()
        self.name = str(path)
        try:
            self.f = h5py.File(path, "r")
        except Exception as exc:  # h5py raises OSError and others for non-HDF5 content
            raise ValueError(f"{self.name}: not a readable HDF5 file ({exc})") from exc
        try:
            self._check(width, height, time_unit)
        except BaseException:
            self.f.close()
            raise

    def _check(self, width: int | None, height: int | None, time_unit: str | None) -> None:
        f, name = self.f, self.name
        self.ev: dict[str, h5py.Dataset] = {}
        for key, _ in _EVENT_FIELDS:
            d = f.get(f"events/{key}")
            if not isinstance(d, h5py.Dataset):
                raise _missing_dataset(name, f, f"events/{key}")
            if d.ndim != 1:
                raise ValueError(f"{name}: dataset 'events/{key}' must be 1-D, got shape {d.shape}")
            self.ev[key] = d
        lengths = {k: d.shape[0] for k, d in self.ev.items()}
        if len(set(lengths.values())) > 1:
            raise ValueError(f"{name}: event datasets have different lengths {lengths}")
        self.n = next(iter(lengths.values()))
        self.tr: dict[str, h5py.Dataset] | None = None
        if "triggers" in f:
            self.tr = {}
            for key, _ in _TRIGGER_FIELDS:
                d = f.get(f"triggers/{key}")
                if not isinstance(d, h5py.Dataset):
                    raise _missing_dataset(name, f, f"triggers/{key}")
                if d.ndim != 1:
                    raise ValueError(
                        f"{name}: dataset 'triggers/{key}' must be 1-D, got shape {d.shape}")
                self.tr[key] = d
            tl = {k: d.shape[0] for k, d in self.tr.items()}
            if len(set(tl.values())) > 1:
                raise ValueError(f"{name}: trigger datasets have different lengths {tl}")
        attrs = f.attrs
        file_unit = _attr_str(attrs["time_unit"]) if "time_unit" in attrs else None
        if file_unit is not None and time_unit is not None and file_unit != time_unit:
            raise ValueError(
                f"{name}: attribute time_unit={file_unit!r} but time_unit={time_unit!r} was "
                "passed; pass none to use the file's"
            )
        unit = time_unit or file_unit or "us"
        if unit not in TIME_UNITS_US:
            raise ValueError(
                f"{name}: time unit {unit!r} not understood; expected one of "
                f"{sorted(TIME_UNITS_US)}"
            )
        self.unit = unit
        tdt = self.ev["t"].dtype
        if tdt.kind not in "iuf":
            raise ValueError(f"{name}: dataset 'events/t' has dtype {tdt}; expected int64 µs")
        geo = resolve_geometry(name, _geometry_attrs(name, attrs), width, height,
                               source="file attributes")
        if geo is None:
            raise ValueError(
                f"{name}: attributes 'width' and 'height' missing; pass width=... and "
                "height=... (pixels)"
            )
        self.width, self.height = int(geo[0]), int(geo[1])
        meta: Any = {}
        if "metadata" in attrs:
            try:
                meta = json.loads(_attr_str(attrs["metadata"]))
            except ValueError as exc:
                raise ValueError(f"{name}: attribute 'metadata' is not valid JSON: {exc}") from exc
            if not isinstance(meta, dict):
                raise ValueError(f"{name}: attribute 'metadata' must be a JSON object, "
                                 f"got {type(meta).__name__}")
        if unit != "us":
            meta = dict(meta)
            meta["time_unit_source"] = unit
            meta["time_conversion"] = f"{unit} -> integer µs (rounded to nearest)"
        self.metadata: dict[str, Any] = meta
        v = _version(name, attrs)
        if v is not None:
            if v > HDF5_FORMAT_VERSION:
                raise ValueError(f"{name}: format_version {v} is newer than this reader "
                                 f"({HDF5_FORMAT_VERSION}); update asynhdr")

    def _time(self, raw: np.ndarray, field: str) -> np.ndarray:
        scale = TIME_UNITS_US[self.unit]
        if raw.dtype.kind == "f":
            if not np.isfinite(raw).all():
                i = int(np.argmax(~np.isfinite(raw)))
                raise ValueError(f"{self.name}: dataset {field!r} holds {raw[i]} at index {i}")
            us = raw.astype(np.float64) * scale
            if self.unit == "us" and (us != np.rint(us)).any():
                i = int(np.argmax(us != np.rint(us)))
                raise ValueError(
                    f"{self.name}: dataset {field!r} holds {raw[i]} at index {i}, not a whole "
                    "number of µs; if the times are in seconds or ms, pass time_unit='s' "
                    "or 'ms'"
                )
            if us.size and (np.abs(us) > 9.2e18).any():
                raise ValueError(f"{self.name}: dataset {field!r} holds times beyond int64 µs")
            return np.rint(us).astype(np.int64)
        t = int_field(self.name, field, raw, np.int64)
        if scale != 1:
            if t.size and (np.abs(t) > np.iinfo(np.int64).max // scale).any():
                raise ValueError(f"{self.name}: dataset {field!r} holds times beyond int64 µs")
            t = t * scale
        return t

    def events(self, a: int, b: int) -> np.ndarray:
        cols = {}
        for key, dt in _EVENT_FIELDS:
            raw = self.ev[key][a:b]
            if key == "t":
                cols[key] = self._time(raw, "events/t")
            else:
                cols[key] = int_field(self.name, f"events/{key}", raw, dt)
        return make_events(cols["x"], cols["y"], cols["p"], cols["t"])

    def triggers(self) -> np.ndarray:
        if self.tr is None:
            return empty_triggers()
        t = self._time(self.tr["t"][:], "triggers/t")
        rising = int_field(self.name, "triggers/rising", self.tr["rising"][:], np.bool_)
        ids = int_field(self.name, "triggers/id", self.tr["id"][:], np.uint8)
        tr = make_triggers(t, rising, ids)
        try:
            validate_triggers(tr)
        except ValueError as exc:
            raise ValueError(f"{self.name}: {exc}") from exc
        return tr

    def close(self) -> None:
        self.f.close()


def _guard(name: str) -> contextlib.AbstractContextManager[None]:
    """Turn low-level failures of a damaged file into ValueError naming it."""

    @contextlib.contextmanager
    def cm() -> Iterator[None]:
        try:
            yield
        except (ValueError, FileNotFoundError):
            raise
        except Exception as exc:  # h5py / filter errors on damaged data
            raise ValueError(
                f"{name}: damaged or unreadable HDF5 data ({type(exc).__name__}: {exc})"
            ) from exc

    return cm()


def load_hdf5(
    path: str | os.PathLike[str],
    *,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
) -> Recording:
    """Read a whole HDF5 recording.

    ``width``/``height`` serve when the file has no geometry attributes (and must
    agree when it has). ``time_unit`` ("us", "ms", "s") serves when the file has no
    ``time_unit`` attribute. Raises ``FileNotFoundError`` for a missing file and
    ``ValueError`` naming the file, dataset or attribute and what was expected.
    """
    p = require_file(path)
    with _guard(str(p)):
        r = _Reader(p, width=width, height=height, time_unit=time_unit)
        try:
            events = r.events(0, r.n)
            triggers = r.triggers()
        finally:
            r.close()
    return recording(str(p), events=events, width=r.width, height=r.height,
                      triggers=triggers, metadata=r.metadata)


def iter_hdf5(
    path: str | os.PathLike[str],
    *,
    chunk_events: int = 1_000_000,
    width: int | None = None,
    height: int | None = None,
    time_unit: str | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Read an HDF5 recording in slices of ``chunk_events`` events: yield
    ``(events, triggers)``; triggers come with the chunk whose events reach their
    time (the last chunk takes the rest). Errors as in :func:`load_hdf5`, raised on
    the first ``next``."""
    if int(chunk_events) < 1:
        raise ValueError(f"iter_hdf5: chunk_events must be >= 1, got {chunk_events}")
    p = require_file(path)
    return _iter(p, int(chunk_events), width, height, time_unit)


def _iter(p: Path, chunk: int, width: int | None, height: int | None,
          time_unit: str | None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    name = str(p)
    with _guard(name):
        r = _Reader(p, width=width, height=height, time_unit=time_unit)
    try:
        with _guard(name):
            triggers = r.triggers()

        def chunks() -> Iterator[np.ndarray]:
            for a in range(0, r.n, chunk):
                with _guard(name):
                    ev = r.events(a, min(a + chunk, r.n))
                try:
                    validate_events(ev, width=r.width, height=r.height, require_sorted=False)
                except ValueError as exc:
                    raise ValueError(f"{name}: events {a}..: {exc}") from exc
                yield ev

        yield from pair_triggers(chunks(), triggers)
    finally:
        r.close()


def _filters(d: h5py.Dataset) -> list[str]:
    """Names of the filters of a dataset's pipeline (e.g. ['blosc'], ['shuffle', 'deflate'])."""
    plist = d.id.get_create_plist()
    out = []
    for i in range(plist.get_nfilters()):
        f = plist.get_filter(i)
        nm = f[3]
        out.append(nm.decode("ascii", "replace") if isinstance(nm, bytes) else str(nm))
    return out


def hdf5_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Header facts of an HDF5 recording without reading its events: ``width``,
    ``height`` (None when absent), ``time_unit``, ``format_version``, ``events``,
    ``triggers`` (counts), ``datasets``, ``compression`` and ``metadata``."""
    p = require_file(path)
    name = str(p)
    _ensure_plugins()
    with _guard(name):
        try:
            f = h5py.File(p, "r")
        except Exception as exc:
            raise ValueError(f"{name}: not a readable HDF5 file ({exc})") from exc
        with f:
            a = f.attrs
            t = f.get("events/t")
            tt = f.get("triggers/t")
            meta: Any = {}
            if "metadata" in a:
                try:
                    meta = json.loads(_attr_str(a["metadata"]))
                except ValueError as exc:
                    raise ValueError(
                        f"{name}: attribute 'metadata' is not valid JSON: {exc}") from exc
            geo = _geometry_attrs(name, a)
            if not isinstance(meta, dict):
                raise ValueError(f"{name}: attribute 'metadata' must be a JSON object")
            info = {
                "width": geo[0] if geo else None,
                "height": geo[1] if geo else None,
                "time_unit": _attr_str(a["time_unit"]) if "time_unit" in a else None,
                "format_version": _version(name, a),
                "events": int(t.shape[0]) if isinstance(t, h5py.Dataset) else None,
                "triggers": int(tt.shape[0]) if isinstance(tt, h5py.Dataset) else 0,
                "datasets": _datasets(f),
                "compression": _filters(t) if isinstance(t, h5py.Dataset) else None,
                "metadata": meta,
            }
    if info["events"] is None:
        with _guard(name), h5py.File(p, "r") as f:
            raise _missing_dataset(name, f, "events/t")
    return info


HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
"""The first bytes of every HDF5 file."""


def _is_metavision(path: Path) -> bool:
    """Whether an HDF5 file has Metavision's event layout (a ``CD`` group)."""
    _ensure_plugins()
    try:
        with h5py.File(path, "r") as f:
            return isinstance(f.get("CD"), h5py.Group)
    except Exception:  # not readable: the reader says why
        return False


def _header(path: Path, opts: ReadOptions) -> Header:
    info = hdf5_info(path)
    geo = resolve_geometry(str(path), (info["width"], info["height"])
                           if info["width"] is not None else None,
                           opts.width, opts.height, source="file attributes")
    with _guard(str(path)):
        r = _Reader(path, width=opts.width, height=opts.height, time_unit=opts.time_unit)
        try:
            triggers = r.triggers()
        finally:
            r.close()
    return Header(format="hdf5", width=geo[0] if geo else None, height=geo[1] if geo else None,
                  geometry_source=geo[2] if geo else None, metadata=r.metadata, facts=info,
                  triggers=triggers, events=info["events"])


FORMAT = Format(
    name="hdf5",
    extensions=(".h5", ".hdf5"),
    description="HDF5, asynhdr layout (events/x,y,t,p; triggers/t,rising,id; Blosc: "
                "h5py needs hdf5plugin)",
    sniff=lambda path, head: head.startswith(HDF5_MAGIC) and not _is_metavision(path),
    header=_header,
    chunks=lambda path, header, n, opts: iter_hdf5(path, chunk_events=n, width=opts.width,
                                                   height=opts.height,
                                                   time_unit=opts.time_unit),
    read=lambda path, header, opts: load_hdf5(path, width=opts.width, height=opts.height,
                                              time_unit=opts.time_unit),
    writer=Hdf5Writer,
    time_unit=True,
)
"""The asynhdr HDF5 record of the format registry (:mod:`asynhdr.io`)."""
