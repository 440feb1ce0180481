"""Recordings as compressed NumPy archives (``.npz``).

Layout (every field a separate array, so any NumPy program reads it without
asynhdr)::

    events_x   uint16 (N,)   pixel column
    events_y   uint16 (N,)   pixel row
    events_t   int64  (N,)   time, µs
    events_p   int8   (N,)   polarity, +1 ON / -1 OFF
    triggers_t       int64 (M,)  time, µs
    triggers_rising  bool  (M,)  edge direction
    triggers_id      uint8 (M,)  input channel
    width, height    int64 ()    sensor geometry, pixels
    metadata         str ()      JSON object
    format_version   int64 ()    1

The archive is a standard ``numpy.savez_compressed``-style zip (deflate); a round
trip keeps everything exactly (metadata as far as JSON does: tuples come
back as lists). No pickled objects are written or read.
"""

from __future__ import annotations

import json
import logging
import os
import zipfile
from typing import Any

import numpy as np

from asynhdr._atomic import atomic_path
from asynhdr.events import Recording, make_events, make_triggers
from asynhdr.io import _int_field, _recording, _require_file

__all__ = ["NPZ_FORMAT_VERSION", "load_npz", "npz_info", "save_npz"]

logger = logging.getLogger(__name__)

NPZ_FORMAT_VERSION = 1
"""Version of the ``.npz`` layout written by :func:`save_npz`."""

COMPRESS_LEVEL = 1
"""zlib level of the archive's members: level 1 writes about 5x faster than
``numpy.savez_compressed`` (level 6) for 3 % more bytes on event data."""

_EVENT_FIELDS = (("events_x", np.uint16), ("events_y", np.uint16), ("events_p", np.int8),
                 ("events_t", np.int64))
_TRIGGER_FIELDS = (("triggers_t", np.int64), ("triggers_rising", np.bool_),
                   ("triggers_id", np.uint8))
_REQUIRED = (*(k for k, _ in _EVENT_FIELDS + _TRIGGER_FIELDS), "width", "height", "metadata")


def save_npz(path: str | os.PathLike[str], recording: Recording) -> None:
    """Write ``recording`` to a compressed ``.npz`` archive, atomically.

    Raises ``ValueError`` when the metadata is not JSON-serialisable.
    """
    try:
        meta = json.dumps(recording.metadata, allow_nan=True)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: metadata is not JSON-serialisable: {exc}") from exc
    ev, tr = recording.events, recording.triggers
    arrays: dict[str, Any] = {
        "events_x": np.ascontiguousarray(ev["x"]),
        "events_y": np.ascontiguousarray(ev["y"]),
        "events_t": np.ascontiguousarray(ev["t"]),
        "events_p": np.ascontiguousarray(ev["p"]),
        "triggers_t": np.ascontiguousarray(tr["t"]),
        "triggers_rising": np.ascontiguousarray(tr["rising"]),
        "triggers_id": np.ascontiguousarray(tr["id"]),
        "width": np.int64(recording.width),
        "height": np.int64(recording.height),
        "metadata": np.array(meta),
        "format_version": np.int64(NPZ_FORMAT_VERSION),
    }
    with atomic_path(path) as tmp, zipfile.ZipFile(
        tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=COMPRESS_LEVEL, allowZip64=True
    ) as zf:
        for key, value in arrays.items():
            with zf.open(f"{key}.npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(value), allow_pickle=False)
    logger.info("%s: wrote %d events, %d triggers", path, ev.size, tr.size)


def _scalar_int(name: str, field: str, a: np.ndarray) -> int:
    if a.shape != () or a.dtype.kind not in "iu":
        raise ValueError(
            f"{name}: field {field!r} must be a scalar integer, got dtype {a.dtype} "
            f"shape {a.shape}"
        )
    return int(a)


def load_npz(path: str | os.PathLike[str]) -> Recording:
    """Read a recording written by :func:`save_npz`.

    Raises ``FileNotFoundError`` for a missing file and ``ValueError`` naming the file
    for anything else: not an archive, a missing or malformed field (named, with what
    was expected), fields of different lengths, bad metadata JSON, polarity not ±1, a
    pixel outside the sensor.
    """
    p = _require_file(path)
    name = str(p)
    try:
        with open(p, "rb") as fh, np.load(fh, allow_pickle=False) as z:
            files = list(z.files)
            missing = [k for k in _REQUIRED if k not in files]
            if missing:
                raise ValueError(
                    f"{name}: field {missing[0]!r} missing"
                    + (f" (and {missing[1:]})" if len(missing) > 1 else "")
                    + f"; found {sorted(files)}; expected {list(_REQUIRED)} "
                    "(the layout written by asynhdr.io.npz.save_npz)"
                )
            raw = {k: z[k] for k in _REQUIRED}
            version = z["format_version"] if "format_version" in files else None
    except ValueError as exc:
        if str(exc).startswith(name):
            raise
        raise ValueError(f"{name}: not a readable .npz archive: {exc}") from exc
    except Exception as exc:  # any decoding failure of a damaged archive (zip, zlib, header)
        raise ValueError(
            f"{name}: not a readable .npz archive ({type(exc).__name__}: {exc})"
        ) from exc
    if version is not None:
        v = _scalar_int(name, "format_version", np.asarray(version))
        if v > NPZ_FORMAT_VERSION:
            raise ValueError(
                f"{name}: format_version {v} is newer than this reader "
                f"({NPZ_FORMAT_VERSION}); update asynhdr"
            )
    cols = {k: _int_field(name, k, raw[k], dt) for k, dt in _EVENT_FIELDS}
    tcols = {k: _int_field(name, k, raw[k], dt) for k, dt in _TRIGGER_FIELDS}
    n = {k: v.size for k, v in cols.items()}
    if len(set(n.values())) > 1:
        raise ValueError(f"{name}: event fields have different lengths {n}; expected one length")
    m = {k: v.size for k, v in tcols.items()}
    if len(set(m.values())) > 1:
        raise ValueError(
            f"{name}: trigger fields have different lengths {m}; expected one length"
        )
    width = _scalar_int(name, "width", raw["width"])
    height = _scalar_int(name, "height", raw["height"])
    meta_arr = raw["metadata"]
    if meta_arr.shape != () or meta_arr.dtype.kind != "U":
        raise ValueError(
            f"{name}: field 'metadata' must be a JSON string, got dtype {meta_arr.dtype} "
            f"shape {meta_arr.shape}"
        )
    try:
        metadata = json.loads(str(meta_arr))
    except ValueError as exc:
        raise ValueError(f"{name}: field 'metadata' is not valid JSON: {exc}") from exc
    if not isinstance(metadata, dict):
        raise ValueError(
            f"{name}: field 'metadata' must be a JSON object, got {type(metadata).__name__}"
        )
    events = make_events(cols["events_x"], cols["events_y"], cols["events_p"], cols["events_t"])
    triggers = make_triggers(tcols["triggers_t"], tcols["triggers_rising"], tcols["triggers_id"])
    return _recording(name, events=events, width=width, height=height, triggers=triggers,
                      metadata=metadata)


def npz_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Header facts of an asynhdr ``.npz`` without reading its events: ``width``,
    ``height``, ``events`` and ``triggers`` (counts, from the array headers),
    ``format_version`` and ``metadata``. Errors as in :func:`load_npz`."""
    p = _require_file(path)
    name = str(p)
    try:
        with zipfile.ZipFile(p) as zf:
            members = set(zf.namelist())

            def small(key: str) -> np.ndarray:
                with zf.open(f"{key}.npy") as fh:
                    return np.lib.format.read_array(fh, allow_pickle=False)

            def count(key: str) -> int:
                fmt = np.lib.format
                with zf.open(f"{key}.npy") as fh:
                    version = fmt.read_magic(fh)
                    if version == (1, 0):
                        shape = fmt.read_array_header_1_0(fh)[0]
                    elif version == (2, 0):
                        shape = fmt.read_array_header_2_0(fh)[0]
                    else:
                        shape = small(key).shape
                return int(shape[0]) if len(shape) else 0

            missing = [k for k in _REQUIRED if f"{k}.npy" not in members]
            if missing:
                raise ValueError(
                    f"{name}: field {missing[0]!r} missing; found "
                    f"{sorted(m[:-4] for m in members)}; expected {list(_REQUIRED)}"
                )
            width = _scalar_int(name, "width", small("width"))
            height = _scalar_int(name, "height", small("height"))
            meta_arr = small("metadata")
            version = (_scalar_int(name, "format_version", small("format_version"))
                       if "format_version.npy" in members else None)
            n_events = count("events_t")
            n_triggers = count("triggers_t")
    except ValueError as exc:
        if str(exc).startswith(name):
            raise
        raise ValueError(f"{name}: not a readable .npz archive: {exc}") from exc
    except Exception as exc:  # any decoding failure of a damaged archive
        raise ValueError(
            f"{name}: not a readable .npz archive ({type(exc).__name__}: {exc})"
        ) from exc
    try:
        metadata = json.loads(str(meta_arr))
    except ValueError as exc:
        raise ValueError(f"{name}: field 'metadata' is not valid JSON: {exc}") from exc
    return {"width": width, "height": height, "events": n_events, "triggers": n_triggers,
            "format_version": version, "metadata": metadata}
