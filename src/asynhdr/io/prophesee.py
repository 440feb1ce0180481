"""Prophesee ``.raw`` files: EVT 2.0, EVT 2.1 and EVT 3.0 read, EVT 2.0 and 3.0 written,
with triggers.

A ``.raw`` file is a text header (lines starting with ``%``, closed by ``% end``
when present) followed by the event stream:

- EVT 2.0: 32-bit words; CD_OFF / CD_ON carry x, y and the 6 low bits of the
  time, EVT_TIME_HIGH the 28 bits above them, EXT_TRIGGER an input edge.
- EVT 2.1: 64-bit words; each CD word is a vector of 32 columns starting at x
  (one validity bit per column), all of the same polarity and time.
- EVT 3.0: 16-bit words that update a decoder state (row, vector base column,
  time low and high 12-bit halves of a 24-bit time) and emit single events
  (EVT_ADDR_X) or vectors (VECT_12, VECT_8), and EXT_TRIGGER edges.

Decoding follows the published format specifications and OpenEB's decoders:
words before the first time-high word are dropped (they cannot be timed), time
wraps are counted as OpenEB counts them, and an EVT 3.0 TIME_LOW that steps back
sets the time back, so that decoded times stay in file order and may be
non-monotone (:func:`asynhdr.events.sort_events` sorts them where needed).

An EVT 3.0 payload (:func:`read_raw`) or block (:func:`iter_raw`) of 256 KiB or
more is decoded in parts on several threads (``NUMBA_NUM_THREADS``, by default
one per CPU); the result, the chunks and the errors are exactly those of the
decoder running on one thread.

Events come out in the project's dtype (``x, y`` uint16, ``p`` int8 +1 ON / -1
OFF, ``t`` int64 µs); trigger edges in ``TRIGGER_DTYPE`` (``t`` µs, ``rising`` the
edge's value bit, ``id`` the input channel). An event outside the sensor
geometry, an unknown format or a missing geometry raises ``ValueError`` naming
the file (and the byte offset and pixel where there is one).

The sensor geometry comes from the header (``% geometry WxH``, or ``width`` and
``height`` in ``% format``), else from ``width=``/``height=`` arguments, else from
the sensor the header names (``% sensor_generation``, ``% generation``,
``% sensor_name``, a Prophesee ``% system_ID``, ``% plugin_name``).

:class:`RawWriter` writes EVT 3.0 or EVT 2.0 (events and triggers interleaved in
time), atomically, with the recording's metadata (the rig and sensor of a simulated
recording) as JSON on a ``% asynhdr_metadata`` header line, which :func:`read_raw` reads
back. A payload that is not sensor data (a long run of one word, EVT 2.0 words under an
EVT 2.1 header) raises ``ValueError``; a stream cut mid-word or inside a vector group is
read up to the cut, with a warning.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from asynhdr import _pool
from asynhdr.events import (
    EVENT_DTYPE,
    TRIGGER_DTYPE,
    Recording,
    empty_triggers,
    validate_events,
    validate_triggers,
)
from asynhdr.io import _evt_kernels as _k
from asynhdr.io._common import (
    FileWriter,
    Format,
    Header,
    ReadOptions,
    json_metadata,
    require_file,
)
from asynhdr.memory import Recycler

__all__ = [
    "FORMAT",
    "METADATA_KEY",
    "SUPPORTED_RAW_FORMATS",
    "Evt3Writer",
    "RawWriter",
    "iter_raw",
    "raw_info",
    "read_raw",
    "write_raw_evt3",
]

logger = logging.getLogger(__name__)

SUPPORTED_RAW_FORMATS: tuple[str, ...] = ("evt2", "evt21", "evt3")
"""Event formats this module decodes (EVT 2.0, EVT 2.1, EVT 3.0); it writes ``evt3``."""

_FORMAT_TITLES = {"evt2": "EVT 2.0", "evt21": "EVT 2.1", "evt3": "EVT 3.0"}
_SUPPORTED_TEXT = (
    "supported formats: EVT 2.0 ('% evt 2.0' or '% format EVT2;...'), "
    "EVT 2.1 ('% evt 2.1' or '% format EVT21;...'), "
    "EVT 3.0 ('% evt 3.0' or '% format EVT3;...')"
)
# Bytes per payload word.
_WORD_BYTES = {"evt2": 4, "evt21": 8, "evt3": 2}
# Spare event records a kernel keeps free in its buffer (at least the most events
# one payload word can produce).
_SPARE_EVENTS = {"evt2": 1, "evt21": 32, "evt3": 32}
# Format names in '% format NAME;...' and values of '% evt ...'.
_FORMAT_NAMES = {"EVT2": "evt2", "EVT21": "evt21", "EVT3": "evt3"}
_LEGACY_EVT_VALUES = {"2.0": "evt2", "2.1": "evt21", "3.0": "evt3"}

METADATA_KEY = "asynhdr_metadata"
"""Header key of the line in which asynhdr's writers store the recording's metadata as
JSON (OpenEB and other readers ignore header keys they do not know)."""

_MAX_HEADER_BYTES = 16 << 20
_MAX_COORDINATE = 2048  # 11-bit addresses in every EVT format
_DEFAULT_BLOCK_BYTES = 1 << 22

# EVT 3.0 payloads (read_raw) and blocks (iter_raw) of at least this many words are
# decoded in parallel, in parts of at least _PARALLEL_MIN_PART_WORDS words each. A
# part costs about 20 µs besides its words, and a thread that has been idle for a few
# ms is slow to wake: on a sparse 380,000-word file read just after another decoder
# ran, two parts took 1.31-1.38 ms and one part 1.18 ms.
_PARALLEL_MIN_WORDS = 1 << 19
_PARALLEL_MIN_PART_WORDS = 1 << 15
# Parts per thread: the threads take parts in turn, so that a thread slowed down by
# other work on the machine holds back only a small part.
_PARTS_PER_THREAD = 4
# Part 0 is decoded by the calling thread, which starts at once and needs no state scan:
# it gets 5/4 of the others' share of the words.
_FIRST_PART_QUARTERS = 5
# Copies of decoded events (read_raw joining parts) are spread over threads in shares of
# at least this many events.
_PARALLEL_MIN_COPY_EVENTS = 1 << 15
# How far back (words) a part looks for the last VECT_BASE_X before it leaves the
# vector base to be found when a vector word needs it (streams without vectors):
# scanning 4,096 words took 34 µs a part on a stream without vectors.
_BASE_SCAN_WORDS = 1 << 8

# Sensor geometry (width, height) by what a header names.
_VGA = (640, 480)
_HD = (1280, 720)
_GENX320 = (320, 320)
_GEOMETRY_BY_GENERATION = {"3": _VGA, "4": _HD, "320": _GENX320}
_GEOMETRY_BY_SENSOR_NAME = (  # substring of the lower-case name -> geometry
    ("genx320", _GENX320),
    ("imx8", _GENX320),
    ("imx636", _HD),
    ("gen4", _HD),
    ("gen3", _VGA),
)
_GEOMETRY_BY_PLUGIN = (  # substring of the lower-case plugin / camera name -> geometry
    ("genx320", _GENX320),
    ("imx8", _GENX320),
    ("imx636", _HD),
    ("evk4", _HD),
    ("gen4", _HD),  # gen4 and gen41
    ("gen3", _VGA),  # gen3 and gen31
)
# Prophesee system IDs (decimal in headers) of the sensors whose geometry is known.
_GEOMETRY_BY_SYSTEM_ID = {
    **dict.fromkeys(
        (0x15, 0x17, 0x97, 0x19, 0x99, 0x1D, 0x21, 0xA1, 0x1C, 0x23, 0x22, 0xA2, 0x29, 0x28), _VGA
    ),
    **dict.fromkeys((0x1A, 0x9A, 0x1E, 0x2E, 0x20, 0x1F, 0x27, 0x30), _HD),
    **dict.fromkeys((0x31, 0x32, 0x3A, 0x42), _HD),
    **dict.fromkeys((0x3B, 0x40), _GENX320),
}
# EVT 2.1 from Prophesee systems older than this ID stores its 32-bit halves swapped.
_EVT21_LEGACY_BEFORE_SYSTEM_ID = 0x37


# --------------------------------------------------------------------------------------
# Header
# --------------------------------------------------------------------------------------


def _read_header(f: BinaryIO, name: str) -> tuple[list[str], int]:
    """Return the '%' lines at the start of ``f`` (a file just opened, at byte 0; without
    '%') and the payload offset."""
    lines: list[str] = []
    buf = f.read(4096)  # a header is usually a few hundred bytes
    at = 0  # offset in the file of the line being read (and of buf[at])
    while True:
        if at >= len(buf):
            more = f.read(1 << 16)
            if not more:
                if lines:
                    logger.warning("%s: the file ends after %d header lines without '%% end' "
                                   "and without events: cut short?", name, len(lines))
                return lines, at
            buf += more
        if buf[at : at + 1] != b"%":
            return lines, at
        nl = buf.find(b"\n", at)
        while nl < 0:
            if len(buf) > _MAX_HEADER_BYTES:
                raise ValueError(
                    f"{name}: header line at byte {at} runs past {_MAX_HEADER_BYTES} bytes "
                    "without a newline; not a Prophesee .raw file"
                )
            more = f.read(max(1 << 16, len(buf)))
            if not more:
                raise ValueError(
                    f"{name}: the file ends inside its header (the line at byte {at} has no "
                    "end): cut short, nothing to read"
                )
            start = len(buf)
            buf += more
            nl = buf.find(b"\n", start)
        end = len(buf) if nl < 0 else nl + 1
        raw_line = buf[at:end]
        at = end
        if at > _MAX_HEADER_BYTES:
            raise ValueError(
                f"{name}: header is longer than {_MAX_HEADER_BYTES} bytes; "
                "not a Prophesee .raw file"
            )
        text = raw_line.decode("utf-8", errors="replace").rstrip("\r\n")
        body = text[1:].strip()
        if body == "end":
            return lines, at
        lines.append(body)


def _parse_fields(lines: list[str]) -> dict[str, str]:
    """Header lines 'key value' -> dict (a later line with the same key wins)."""
    fields: dict[str, str] = {}
    for line in lines:
        if not line:
            continue
        parts = line.split(None, 1)
        fields[parts[0]] = parts[1].strip() if len(parts) > 1 else ""
    return fields


def _field(fields: dict[str, str], key: str) -> str | None:
    """Case-insensitive header lookup."""
    if key in fields:
        return fields[key]
    low = key.lower()
    for k, v in fields.items():
        if k.lower() == low:
            return v
    return None


def _parse_int(text: str, name: str, what: str) -> int:
    try:
        return int(text.strip(), 0)
    except ValueError:
        try:
            return int(text.strip(), 10)
        except ValueError:
            raise ValueError(f"{name}: header {what} {text!r} is not an integer") from None


def _check_geometry(width: int, height: int, name: str, source: str) -> tuple[int, int]:
    if not (1 <= width <= _MAX_COORDINATE and 1 <= height <= _MAX_COORDINATE):
        raise ValueError(
            f"{name}: geometry {width}x{height} from {source} is outside 1..{_MAX_COORDINATE} "
            "pixels per side (the EVT formats address at most 2048x2048)"
        )
    return width, height


def _format_from_header(fields: dict[str, str], name: str) -> tuple[str, dict[str, str]]:
    """Return the format key ('evt2', 'evt21', 'evt3') and the '% format' options."""
    fmt_line = _field(fields, "format")
    options: dict[str, str] = {}
    if fmt_line:
        parts = [s.strip() for s in fmt_line.split(";")]
        fmt_name = parts[0].upper()
        for opt in parts[1:]:
            if "=" in opt:
                k, v = opt.split("=", 1)
                options[k.strip().lower()] = v.strip()
        if fmt_name not in _FORMAT_NAMES:
            raise ValueError(
                f"{name}: header '% format {fmt_line}' names an event format this reader "
                f"does not decode; {_SUPPORTED_TEXT}"
            )
        return _FORMAT_NAMES[fmt_name], options
    evt = _field(fields, "evt")
    if evt is not None:
        key = _LEGACY_EVT_VALUES.get(evt.strip())
        if key is None:
            raise ValueError(
                f"{name}: header '% evt {evt}' names an event format this reader does not "
                f"decode; {_SUPPORTED_TEXT}"
            )
        return key, options
    if not fields:
        raise ValueError(
            f"{name}: no Prophesee header ('% ...' lines) at the start of the file; "
            f"{_SUPPORTED_TEXT}"
        )
    raise ValueError(
        f"{name}: header has neither a '% format' nor a '% evt' line, so the event format "
        f"is unknown; {_SUPPORTED_TEXT}"
    )


def _integrator_is_prophesee(fields: dict[str, str]) -> bool:
    names = [
        _field(fields, k)
        for k in ("camera_integrator_name", "plugin_integrator_name", "integrator_name")
    ]
    given = [n for n in names if n]
    return all(n.strip().lower() == "prophesee" for n in given)


def _geometry_from_sensor(fields: dict[str, str]) -> tuple[tuple[int, int], str] | None:
    """Sensor geometry from what the header says about the camera, or None."""
    for key in ("sensor_generation", "generation"):
        gen = _field(fields, key)
        if gen:
            major = gen.strip().split(".")[0]
            if major in _GEOMETRY_BY_GENERATION:
                return _GEOMETRY_BY_GENERATION[major], f"'% {key} {gen}'"
    sensor_name = _field(fields, "sensor_name")
    if sensor_name:
        low = sensor_name.lower()
        for sub, geom in _GEOMETRY_BY_SENSOR_NAME:
            if sub in low:
                return geom, f"'% sensor_name {sensor_name}'"
    system_id = _field(fields, "system_ID")
    if system_id and _integrator_is_prophesee(fields):
        try:
            sid = int(system_id.strip(), 10)
        except ValueError:
            sid = -1
        if sid in _GEOMETRY_BY_SYSTEM_ID:
            return _GEOMETRY_BY_SYSTEM_ID[sid], f"'% system_ID {system_id}'"
    for key in ("plugin_name", "camera_integrator_name", "integrator_name"):
        value = _field(fields, key)
        if value:
            low = value.lower()
            for sub, geom in _GEOMETRY_BY_PLUGIN:
                if sub in low:
                    return geom, f"'% {key} {value}'"
    return None


def _resolve_geometry(
    fields: dict[str, str],
    options: dict[str, str],
    name: str,
    width: int | None,
    height: int | None,
) -> tuple[int, int, str]:
    """Geometry from the header, else the arguments, else the sensor table."""
    if (width is None) != (height is None):
        raise ValueError(f"{name}: give both width and height, or neither")
    if width is not None and height is not None:
        width, height = int(width), int(height)
        _check_geometry(width, height, name, "the arguments")
    header_geom: tuple[int, int] | None = None
    source = ""
    if "width" in options and "height" in options:
        header_geom = (
            _parse_int(options["width"], name, "format width"),
            _parse_int(options["height"], name, "format height"),
        )
        source = "'% format' line"
    geometry = _field(fields, "geometry")
    if geometry:
        parts = geometry.lower().split("x")
        if len(parts) != 2:
            raise ValueError(
                f"{name}: header '% geometry {geometry}' is not of the form WIDTHxHEIGHT"
            )
        geom = (
            _parse_int(parts[0], name, "geometry width"),
            _parse_int(parts[1], name, "geometry height"),
        )
        if header_geom is not None and header_geom != geom:
            raise ValueError(
                f"{name}: header geometry {geom[0]}x{geom[1]} ('% geometry') disagrees with "
                f"{header_geom[0]}x{header_geom[1]} ('% format' line)"
            )
        header_geom, source = geom, "'% geometry' line"
    if header_geom is not None:
        _check_geometry(header_geom[0], header_geom[1], name, f"the header {source}")
        if width is not None and (width, height) != header_geom:
            raise ValueError(
                f"{name}: header says {header_geom[0]}x{header_geom[1]} ({source}) but the "
                f"arguments say width={width}, height={height}"
            )
        return header_geom[0], header_geom[1], f"header {source}"
    if width is not None and height is not None:
        return width, height, "arguments"
    found = _geometry_from_sensor(fields)
    if found is not None:
        (w, h), why = found
        return w, h, f"sensor table ({why})"
    raise ValueError(
        f"{name}: the header gives no sensor geometry (no '% geometry' line, no width/height "
        "in '% format') and names no sensor this reader knows; pass width=... and height=... "
        "(pixels)"
    )


def _evt21_legacy(fields: dict[str, str], options: dict[str, str]) -> bool:
    """Whether EVT 2.1 words are stored with their 32-bit halves swapped (OpenEB's rule)."""
    endianness = options.get("endianness") or _field(fields, "endianness")
    if endianness:
        return endianness.strip().lower() == "legacy"
    system_id = _field(fields, "system_ID")
    if system_id and _integrator_is_prophesee(fields):
        try:
            sid = int(system_id.strip(), 10)
        except ValueError:
            return False
        return 0 < sid < _EVT21_LEGACY_BEFORE_SYSTEM_ID
    return False


def _stored_metadata(fields: dict[str, str], name: str) -> dict[str, Any] | None:
    """The recording's metadata from a ``% asynhdr_metadata {json}`` header line (what
    asynhdr's writers store: the rig and sensor of a simulated recording), or None."""
    text = _field(fields, METADATA_KEY)
    if text is None:
        return None
    try:
        meta = json.loads(text)
    except ValueError as exc:
        raise ValueError(f"{name}: header '% {METADATA_KEY}' is not valid JSON: {exc}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{name}: header '% {METADATA_KEY}' must hold a JSON object")
    return meta


class _RawInfo:
    """Everything the header says that decoding needs."""

    def __init__(self, path: str | os.PathLike[str], width: int | None, height: int | None):
        self.path = require_file(path)
        self.name = str(path)
        try:
            f = open(path, "rb", buffering=0)
        except OSError as exc:
            raise ValueError(f"{self.name}: cannot open: {exc.strerror or exc}") from exc
        with f:
            lines, self.header_bytes = _read_header(f, self.name)
            self.file_bytes = os.fstat(f.fileno()).st_size
        self.fields = _parse_fields(lines)
        self.format, options = _format_from_header(self.fields, self.name)
        self.width, self.height, self.geometry_source = _resolve_geometry(
            self.fields, options, self.name, width, height
        )
        self.legacy = self.format == "evt21" and _evt21_legacy(self.fields, options)
        self.word_bytes = _WORD_BYTES[self.format]
        payload = self.file_bytes - self.header_bytes
        self.n_words = payload // self.word_bytes
        self.trailing_bytes = payload - self.n_words * self.word_bytes
        stored = _stored_metadata(self.fields, self.name)
        self.metadata: dict[str, Any] = stored if stored is not None else {
            "format": self.format, "source": self.name, "header": dict(self.fields)}
        camera = _sensor_text(self.fields)
        if camera is not None:  # kept by a conversion into a format without these fields
            self.metadata.setdefault("camera", camera)

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "format": self.format,
            "width": self.width,
            "height": self.height,
            "header": dict(self.fields),
            "geometry_source": self.geometry_source,
            "header_bytes": self.header_bytes,
            "payload_bytes": self.file_bytes - self.header_bytes,
            "words": self.n_words,
        }
        if self.format == "evt21":
            out["evt21_layout"] = "legacy" if self.legacy else "standard"
        return out


def raw_info(
    path: str | os.PathLike[str], *, width: int | None = None, height: int | None = None
) -> dict[str, Any]:
    """Describe a ``.raw`` file from its header, without decoding the payload.

    Returns a dict with ``format`` (one of :data:`SUPPORTED_RAW_FORMATS`), ``width``
    and ``height`` (pixels), ``header`` (every ``% key value`` field), and
    ``geometry_source``, ``header_bytes``, ``payload_bytes``, ``words`` (payload
    words of 2, 4 or 8 bytes) and, for EVT 2.1, ``evt21_layout``.

    Geometry comes from the header (``% geometry WxH`` or ``width``/``height`` in
    ``% format``), else from ``width``/``height``, else from the sensor the header
    names (generation, sensor name, Prophesee system ID, plugin name); otherwise
    ``ValueError`` asks for ``width`` and ``height``.
    """
    return _RawInfo(path, width, height).as_dict()


# --------------------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------------------


_STATE_SIZES = {"evt2": _k.EVT2_STATE_SIZE, "evt21": _k.EVT21_STATE_SIZE,
                "evt3": _k.EVT3_STATE_SIZE}


def _new_state(fmt: str) -> np.ndarray:
    return np.zeros(_STATE_SIZES[fmt], dtype=np.int64)


def _evt3_kernel(words: np.ndarray, pos: int) -> Any:
    """The EVT 3.0 decoder variant for the words from ``pos`` (sparse or dense stream),
    picked once a block: the pick samples 1,024 words."""
    return _k.decode_evt3_sparse if _k.evt3_sparse(words, pos) else _k.decode_evt3


def _block_kernel(info: _RawInfo, words: np.ndarray) -> Any:
    """What :func:`_run_kernel` decodes a block of ``info``'s format with: the EVT 3.0
    variant for these words, or None for the EVT 2.x formats."""
    return _evt3_kernel(words, 0) if info.format == "evt3" else None


def _run_kernel(
    info: _RawInfo,
    kernel: Any,
    words: np.ndarray,
    pos: int,
    state: np.ndarray,
    events: np.ndarray,
    n_ev: int,
    limit: int,
    triggers: np.ndarray,
    n_tr: int,
) -> tuple[int, int, int, int]:
    if info.format == "evt3":
        res = kernel(
            words, pos, state, info.width, info.height, events, n_ev, limit, triggers, n_tr,
            _NO_TRIGGER_INDEX,
        )
    elif info.format == "evt2":
        res = _k.decode_evt2(
            words, pos, state, info.width, info.height, events, n_ev, limit, triggers, n_tr
        )
    else:
        res = _k.decode_evt21(
            words,
            1 if info.legacy else 0,
            pos,
            state,
            info.width,
            info.height,
            events,
            n_ev,
            limit,
            triggers,
            n_tr,
        )
    return int(res[0]), int(res[1]), int(res[2]), int(res[3])


def _raise_decode_error(
    info: _RawInfo, status: int, word_index: int, state: np.ndarray
) -> None:
    offset = info.header_bytes + word_index * info.word_bytes
    x, y = int(state[_k.S_ERR_X]), int(state[_k.S_ERR_Y])
    title = _FORMAT_TITLES[info.format]
    if status == _k.STATUS_BAD_X:
        what = f"x={x} is outside the sensor (width={info.width})"
    elif status == _k.STATUS_BAD_Y:
        what = f"y={y} is outside the sensor (height={info.height})"
    else:
        what = f"decoder status {status}"
    raise ValueError(
        f"{info.name}: {title} word at byte offset {offset} gives an event at (x={x}, y={y}): "
        f"{what}; the file is corrupt or its geometry {info.width}x{info.height} "
        f"(from {info.geometry_source}) is wrong"
    )


def _grow(arr: np.ndarray, n_used: int, min_size: int) -> np.ndarray:
    new = np.empty(max(min_size, 2 * arr.shape[0]), dtype=arr.dtype)
    new[:n_used] = arr[:n_used]
    return new


_KERNEL_DTYPES: dict[str, np.dtype[Any]] = {
    "evt3": np.dtype("<u2"), "evt2": np.dtype("<u4"), "evt21": np.dtype("<u4")}


def _kernel_view(info: _RawInfo, raw: np.ndarray) -> np.ndarray:
    """Payload bytes -> the array a kernel takes (uint16, uint32, or uint32 pairs)."""
    return raw.view(_KERNEL_DTYPES[info.format])


def _warn_trailing(info: _RawInfo) -> None:
    if info.trailing_bytes:
        logger.warning(
            "%s: %d trailing byte(s) after the last whole %d-byte word ignored "
            "(the file was cut mid-word)",
            info.name,
            info.trailing_bytes,
            info.word_bytes,
        )


# A run of this many identical payload words is not sensor data (padding, or a damaged
# file): real streams repeat at most a TIME_HIGH word a few times (11 in the shared
# recordings), which is left out of the check. Runs are looked for among every 64th word
# and checked word by word where the samples agree.
_RUN_LIMIT_WORDS = 4096
_RUN_STRIDE = 64


def _constant_run(w: np.ndarray, high_type: int) -> tuple[int, int, int] | None:
    """``(first word, length, value)`` of a run of at least ``_RUN_LIMIT_WORDS`` identical
    words other than time-high words (type ``high_type`` in the top 4 bits), or None."""
    s = w[::_RUN_STRIDE]
    need = _RUN_LIMIT_WORDS // _RUN_STRIDE - 1
    if s.size <= need:
        return None
    bounds = np.concatenate(([0], np.flatnonzero(s[1:] != s[:-1]) + 1, [s.size]))
    top = 8 * w.dtype.itemsize - 4
    for k in np.flatnonzero(np.diff(bounds) >= need):
        v = s[bounds[k]]
        if int(v) >> top == high_type:
            continue
        lo = max(0, (int(bounds[k]) - 1) * _RUN_STRIDE + 1)
        hi = min(w.size, int(bounds[k + 1]) * _RUN_STRIDE)
        same = np.concatenate(([0], (w[lo:hi] == v).view(np.int8), [0]))
        d = np.diff(same)
        a, b = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
        j = int(np.argmax(b - a))
        if b[j] - a[j] >= _RUN_LIMIT_WORDS:
            return lo + int(a[j]), int(b[j] - a[j]), int(v)
    return None


def _check_payload(info: _RawInfo, words: np.ndarray, words_before: int) -> None:
    """``ValueError`` naming the byte offset when a block of the payload (``words``, the
    kernel's view, ``words_before`` words into the payload) is not sensor data: a long run
    of one word, or, in the first block of an EVT 2.1 file, 32-bit EVT 2.0 words."""
    w = words.view("<u8") if info.format == "evt21" else words
    run = _constant_run(w, 0x8)
    if run is not None:
        at, n, v = run
        offset = info.header_bytes + (words_before + at) * info.word_bytes
        word = f"0x{v:0{2 * info.word_bytes}X}"
        raise ValueError(
            f"{info.name}: {n} identical {info.word_bytes}-byte words {word} from byte "
            f"offset {offset}: not {_FORMAT_TITLES[info.format]} sensor data (padding or a "
            "damaged file)")
    if info.format == "evt21" and words_before == 0:
        _check_evt21_framing(info, words[: 1 << 17])


def _check_evt21_framing(info: _RawInfo, halves: np.ndarray) -> None:
    """An EVT 2.1 word carries its type and time in one 32-bit half and a validity mask in
    the other. EVT 2.0 data read as EVT 2.1 shows time-high words (type 0x8, the 28 bits
    of a time that the other time-high words share) in both halves; a genuine mask with
    its top 4 bits 0x8 has no reason to hold such a time."""
    n = halves.size // 2 * 2
    head, mask = (halves[0:n:2], halves[1:n:2]) if info.legacy else (halves[1:n:2], halves[0:n:2])
    th_head = head[(head >> 28) == 0x8] & 0x0FFFFFFF
    th_mask = mask[(mask >> 28) == 0x8] & 0x0FFFFFFF
    if th_head.size < 2 or th_mask.size < 4:
        return
    near = (th_mask >= int(th_head.min()) - 2) & (th_mask <= int(th_head.max()) + 2)
    if int(near.sum()) >= max(4, th_mask.size // 2):
        raise ValueError(
            f"{info.name}: the header says EVT 2.1 but the payload holds 32-bit EVT 2.0 "
            f"words: {int(near.sum())} time-high words sit where EVT 2.1 keeps its validity "
            f"masks (and {th_head.size} where it keeps its time-high words); the header's "
            "format line is wrong (EVT 2.0 data is read with '% evt 2.0')")


def _check_end(info: _RawInfo, words: np.ndarray) -> None:
    """Warn when an EVT 3.0 stream ends inside a vector group: after a VECT_BASE_X word,
    sensors and asynhdr's writer send vector words for whole groups of 32 columns
    (VECT_12, VECT_12, VECT_8), so a stream whose last vector words cover another number
    of columns was cut."""
    if info.format != "evt3" or words.size == 0:
        return
    typ = words[-64:].astype(np.int64) >> 12
    k, cols = typ.size, 0
    while k > 0 and typ[k - 1] in (0x4, 0x5):
        cols += 12 if typ[k - 1] == 0x4 else 8
        k -= 1
    if k == 0 or typ[k - 1] != 0x3 or (cols and cols % 32 == 0):
        return
    offset = info.header_bytes + (info.n_words - typ.size + k - 1) * info.word_bytes
    logger.warning(
        "%s: the stream ends inside a vector group (%d of 32 columns after the VECT_BASE_X "
        "word at byte offset %d): the file was cut; the events before the cut are kept",
        info.name, cols % 32, offset)


def _trim(arr: np.ndarray, n: int) -> np.ndarray:
    """Shrink a freshly allocated buffer to ``n`` items without copying when possible."""
    if arr.shape[0] == n:
        return arr
    try:
        arr.resize(n, refcheck=False)
        return arr
    except ValueError:
        return arr[:n].copy()


# --------------------------------------------------------------------------------------
# Parallel EVT 3.0 decoding
# --------------------------------------------------------------------------------------
#
# A block of EVT 3.0 words is cut into parts at word boundaries, a few per thread;
# the threads take the parts in turn. Each part finds the decoder state at its first
# word by scanning backwards (_k.evt3_state_at: last row, vector base and time words)
# and decodes into a region of its own. Only the 24-bit wrap count cannot be found
# that way: a part starts with the block's count and is shifted by 2**24 µs per wrap
# of the parts before it once all are done. The events are then copied together in
# order: into the result (read_raw, where part 0 decodes into the result itself) or
# into the chunks (iter_raw). The result, the chunks, the end state and the error
# reported (the first in the stream) equal the sequential decoder's exactly.

_NO_TRIGGER_INDEX = np.empty(0, dtype=np.int64)


def _decode_threads() -> int:
    """Threads that decode in parallel: numba's thread count (``NUMBA_NUM_THREADS``)."""
    return _pool.worker_threads()


def _executor() -> ThreadPoolExecutor:
    return _pool.executor()


def _evt3_split(n_words: int) -> list[int] | None:
    """Word indices that cut a block into parallel parts, or None to decode it in one piece."""
    threads = _decode_threads()
    if threads < 2 or n_words < _PARALLEL_MIN_WORDS:
        return None
    n_parts = min(_PARTS_PER_THREAD * threads, n_words // max(1, _PARALLEL_MIN_PART_WORDS))
    if n_parts < 2:
        return None
    # Part 0 has _FIRST_PART_QUARTERS quarters of a share, every other part 4 quarters.
    first, total = _FIRST_PART_QUARTERS, _FIRST_PART_QUARTERS + 4 * (n_parts - 1)
    return [0, *(n_words * (first + 4 * (k - 1)) // total for k in range(1, n_parts)), n_words]


class _Part:
    """What one part of a parallel EVT 3.0 decode produced."""

    def __init__(self) -> None:
        self.segments: list[tuple[np.ndarray, int, int]] = []  # (buffer, first, count)
        self.n_events = 0
        self.triggers = np.empty(16, dtype=TRIGGER_DTYPE)
        self.tr_at = np.empty(16, dtype=np.int64)  # events of the part before each trigger
        self.n_tr = 0
        self.status = _k.STATUS_DONE
        self.pos = 0
        self.state = np.zeros(_k.EVT3_STATE_SIZE, dtype=np.int64)
        self.loop_start = 0  # wrap count the part started with
        self.offset = 0  # index of the part's first event in the joined buffer


def _evt3_decode_part(
    words: np.ndarray,
    start: int,
    stop: int,
    state0: np.ndarray,
    width: int,
    height: int,
    events: np.ndarray,
    region: int,
    region_words: int,
    at_block_start: bool,
) -> _Part:
    """Decode ``words[start:stop]`` of a block that starts in ``state0`` (not modified).

    Events go to ``events[region:]`` (room for ``region_words`` events plus the
    spare records), then, if the part makes more events than that, to buffers of
    its own.
    """
    part = _Part()
    state = part.state
    if at_block_start:
        state[:] = state0
    else:
        _k.evt3_state_at(words, start, state0, state, _BASE_SCAN_WORDS)
    part.loop_start = int(state[_k.S3_LOOP])
    view = words[:stop]
    buf, base, n_ev, limit = events, region, region, region + region_words
    done = 0  # events of the part in closed segments
    pos = start
    n_tr = 0
    kernel = _evt3_kernel(words, start)
    while True:
        first_tr = n_tr
        res = kernel(
            view, pos, state, width, height, buf, n_ev, limit, part.triggers, n_tr, part.tr_at
        )
        status, pos, n_ev, n_tr = int(res[0]), int(res[1]), int(res[2]), int(res[3])
        part.tr_at[first_tr:n_tr] += done - base
        if status == _k.STATUS_NEED_BASE:
            # A vector word before any VECT_BASE_X of this part: find the base it needs.
            full = np.empty_like(state)
            _k.evt3_state_at(words, pos, state0, full, -1)
            for slot in (_k.S3_BASE_X, _k.S3_BASE_P, _k.S3_HAS_BASE):
                state[slot] = full[slot]
            continue
        if status != _k.STATUS_FULL:
            break
        if n_tr >= part.triggers.shape[0]:
            part.triggers = _grow(part.triggers, n_tr, 64)
            part.tr_at = _grow(part.tr_at, n_tr, 64)
            continue
        # The part made more events than its region holds: go on in a buffer of its own.
        part.segments.append((buf, base, n_ev - base))
        done += n_ev - base
        spare = _SPARE_EVENTS["evt3"]
        buf = np.empty(max(stop - pos, 1 << 12) + spare, dtype=EVENT_DTYPE)
        base = n_ev = 0
        limit = buf.shape[0] - spare
    part.segments.append((buf, base, n_ev - base))
    part.n_events = done + n_ev - base
    part.n_tr = n_tr
    part.status = status
    part.pos = pos
    return part


def _copy_events(dst: np.ndarray, at: int, src: np.ndarray, first: int, n: int) -> None:
    """``dst[at:at + n] = src[first:first + n]`` as bytes (overlap allowed).

    Copying the packed records as bytes is a plain memory move, ten times faster
    than numpy's field-by-field copy of a structured dtype.
    """
    if n <= 0 or (dst is src and at == first):
        return
    size = EVENT_DTYPE.itemsize
    dst.view(np.uint8)[at * size : (at + n) * size] = src.view(np.uint8)[
        first * size : (first + n) * size
    ]


class _Decoded:
    """A block decoded in parallel: its events as pieces of buffers, in stream order."""

    def __init__(
        self,
        pieces: list[tuple[np.ndarray, int, int]],
        triggers: np.ndarray,
        tr_index: np.ndarray,
        status: int,
        pos: int,
    ) -> None:
        self.pieces = pieces  # (buffer, first, count)
        self.n_events = sum(count for _, _, count in pieces)
        self.triggers = triggers
        self.tr_index = tr_index  # events of the block before each trigger
        self.status = status  # as decode_evt3 reports it, at word pos
        self.pos = pos


def _evt3_scratch_size(starts: list[int], first: int = 0) -> int:
    """Events the scratch of :func:`_evt3_decode_parallel` holds for the parts from ``first``."""
    return starts[-1] - starts[first] + _SPARE_EVENTS["evt3"] * (len(starts) - 1 - first)


def _evt3_decode_parallel(
    words: np.ndarray,
    state: np.ndarray,
    width: int,
    height: int,
    starts: list[int],
    scratch: np.ndarray,
    first: np.ndarray | None = None,
) -> _Decoded:
    """Decode a block of EVT 3.0 words in the parts ``[starts[k], starts[k + 1])``, in parallel.

    ``state`` is the decoder state at the block start and is left as the sequential
    decoder leaves it (at the error, if there is one). Each part writes its events to
    its own region of ``scratch`` (the part's word count plus the spare records:
    ``_evt3_scratch_size(starts)`` events in all), part 0 to the start of ``first``
    instead when given (then ``_evt3_scratch_size(starts, 1)``), and a part that makes
    more events than its region holds goes on in buffers of its own. The result lists
    where the events are, in stream order, up to the first error.
    """
    n_parts = len(starts) - 1
    spare = _SPARE_EVENTS["evt3"]
    sizes = [starts[k + 1] - starts[k] for k in range(n_parts)]
    regions: list[tuple[np.ndarray, int]] = []
    at = 0
    for k in range(n_parts):
        if k == 0 and first is not None:
            regions.append((first, 0))
            if first.shape[0] < sizes[0] + spare:
                raise ValueError("_evt3_decode_parallel: first buffer too small")
        else:
            regions.append((scratch, at))
            at += sizes[k] + spare
    if scratch.shape[0] < at:
        raise ValueError("_evt3_decode_parallel: scratch buffer too small")
    state0 = state.copy()

    def run(k: int) -> _Part:
        buf, region = regions[k]
        return _evt3_decode_part(
            words, starts[k], starts[k + 1], state0, width, height, buf, region, sizes[k],
            k == 0,
        )

    done: list[_Part | None] = [None] * n_parts
    turn = itertools.count()  # next() on a count is atomic under the GIL

    def drain() -> None:
        for k in iter(turn.__next__, None):
            if k >= n_parts:
                return
            done[k] = run(k)

    threads = min(_decode_threads(), n_parts)
    futures = [_executor().submit(drain) for _ in range(threads - 1)]
    try:
        drain()  # this thread takes part 0 first, the one that needs no state scan
    finally:
        for f in futures:  # wait for the threads that started; the others have no part left
            if not f.cancel():
                f.result()
    parts = [part for part in done if part is not None]
    for k, part in enumerate(parts):
        if part.status != _k.STATUS_DONE:
            parts = parts[: k + 1]  # the first error in the stream ends it
            break
    # Wrap counts and the vector base each part could not know, from the part before.
    loop = int(parts[0].state[_k.S3_LOOP])
    offset = parts[0].n_events
    for prev, part in itertools.pairwise(parts):
        shift = loop - part.loop_start
        loop = int(part.state[_k.S3_LOOP]) + shift
        part.state[_k.S3_LOOP] = loop
        if part.state[_k.S3_HAS_BASE] < 0:  # no vector word and no VECT_BASE_X in the part
            for slot in (_k.S3_BASE_X, _k.S3_BASE_P, _k.S3_HAS_BASE):
                part.state[slot] = prev.state[slot]
        if shift:
            for buf, at, count in part.segments:
                buf["t"][at : at + count] += np.int64(shift) << 24
            part.triggers["t"][: part.n_tr] += np.int64(shift) << 24
        part.offset = offset
        offset += part.n_events
    last = parts[-1]
    state[:] = last.state
    return _Decoded(
        [seg for part in parts for seg in part.segments if seg[2]],
        np.concatenate([part.triggers[: part.n_tr] for part in parts]),
        np.concatenate([part.tr_at[: part.n_tr] + part.offset for part in parts]),
        last.status,
        last.pos,
    )


def _join_pieces(dec: _Decoded, out: np.ndarray) -> np.ndarray:
    """The events of ``dec`` in one array: ``out`` when it is large enough and the pieces
    that lie in it come first, else a new array.

    The pieces in ``out`` move left, in order; the others are copied on every thread
    (the copy writes new memory, whose page faults cost as much as the copy itself).
    """
    in_out = [buf is out for buf, _, _ in dec.pieces]
    if dec.n_events > out.shape[0] or in_out != sorted(in_out, reverse=True):
        out = np.empty(dec.n_events, dtype=EVENT_DTYPE)
        in_out = [False] * len(dec.pieces)
    copies: list[tuple[int, np.ndarray, int, int]] = []  # (at, buffer, first, count)
    dst = 0
    for (buf, first, count), inside in zip(dec.pieces, in_out, strict=True):
        if inside:
            _copy_events(out, dst, buf, first, count)
        else:
            copies.append((dst, buf, first, count))
        dst += count
    n_copy = sum(c[3] for c in copies)
    threads = min(_decode_threads(), max(1, n_copy // _PARALLEL_MIN_COPY_EVENTS))
    # Cut the copies into one share per thread, of about the same number of events.
    shares: list[list[tuple[int, np.ndarray, int, int]]] = [[] for _ in range(threads)]
    quota = -(-n_copy // threads)
    k = taken = 0
    for at, buf, first, count in copies:
        while count:
            m = min(count, quota - taken)
            shares[k].append((at, buf, first, m))
            at, first, count, taken = at + m, first + m, count - m, taken + m
            if taken == quota:
                k, taken = min(k + 1, threads - 1), 0

    def copy(share: list[tuple[int, np.ndarray, int, int]]) -> None:
        for at, buf, first, count in share:
            _copy_events(out, at, buf, first, count)

    futures = [_executor().submit(copy, share) for share in shares[1:]]
    try:
        copy(shares[0])
    finally:
        for f in futures:
            f.result()
    return out


# Scratch buffers of parallel decoding, kept for the next call while small enough.
_SCRATCH_KEEP_EVENTS = (64 << 20) // EVENT_DTYPE.itemsize
_scratch_lock = threading.Lock()
_scratch_kept: list[np.ndarray] = []


def _take_scratch(n: int) -> np.ndarray:
    """An event buffer of at least ``n`` records: one kept from an earlier call, or new.

    Memory already written to costs nothing to write again, while the first write to
    newly allocated memory costs a page fault per page.
    """
    with _scratch_lock:
        for i, buf in enumerate(_scratch_kept):
            if buf.shape[0] >= n:
                return _scratch_kept.pop(i)
    return np.empty(n, dtype=EVENT_DTYPE)


def _give_scratch(buf: np.ndarray) -> None:
    """Keep ``buf`` for a later :func:`_take_scratch` (at most two, each small enough)."""
    if buf.shape[0] > _SCRATCH_KEEP_EVENTS:
        return
    with _scratch_lock:
        _scratch_kept.append(buf)
        _scratch_kept.sort(key=lambda b: b.shape[0], reverse=True)
        del _scratch_kept[2:]


class _Gather:
    """Copy consecutive runs of events out of a list of pieces ``(buffer, first, count)``."""

    def __init__(self, pieces: list[tuple[np.ndarray, int, int]]) -> None:
        self.pieces = pieces
        self.k = 0  # current piece
        self.used = 0  # events taken from it

    def take(self, out: np.ndarray, n: int) -> None:
        """Copy the next ``n`` events into ``out[:n]``."""
        dst = 0
        while dst < n:
            buf, first, count = self.pieces[self.k]
            m = min(n - dst, count - self.used)
            _copy_events(out, dst, buf, first + self.used, m)
            dst += m
            self.used += m
            if self.used == count:
                self.k += 1
                self.used = 0


def read_raw(
    path: str | os.PathLike[str], *, width: int | None = None, height: int | None = None
) -> Recording:
    """Decode a whole ``.raw`` file (EVT 2.0, EVT 2.1 or EVT 3.0) into a :class:`Recording`.

    Events keep file order; their times (µs) are those the stream encodes and may
    step back where an EVT 3.0 stream does. Geometry as in :func:`raw_info`.
    Triggers are sorted stably by time (a :class:`Recording` holds them sorted; a
    stream whose trigger times step back is logged). ``metadata`` is
    ``{"format": "evt3" | "evt2" | "evt21", "source": str(path), "header": {...}}``.

    Raises ``ValueError`` naming the file for an unknown format, a missing
    geometry, or an event outside the sensor (with its byte offset and pixel);
    ``FileNotFoundError`` when there is no such file.
    """
    info = _RawInfo(path, width, height)
    _warn_trailing(info)
    with open(info.path, "rb", buffering=0) as f:
        f.seek(info.header_bytes)
        raw = np.fromfile(f, dtype=np.uint8, count=info.n_words * info.word_bytes)
    if raw.size != info.n_words * info.word_bytes:
        raise ValueError(
            f"{info.name}: file shrank while being read ({raw.size} of "
            f"{info.n_words * info.word_bytes} payload bytes)"
        )
    words = _kernel_view(info, raw)
    _check_payload(info, words, 0)
    _check_end(info, words)
    state = _new_state(info.format)
    starts = _evt3_split(words.shape[0]) if info.format == "evt3" else None
    if starts is not None:
        # Part 0 decodes into the result itself, the other parts into scratch kept from
        # call to call, copied after it: the new memory written is the events' own.
        # Too large to keep: all parts decode into the result, moved together after.
        events = np.empty(_evt3_scratch_size(starts), dtype=EVENT_DTYPE)
        if _evt3_scratch_size(starts, 1) <= _SCRATCH_KEEP_EVENTS:
            scratch = _take_scratch(_evt3_scratch_size(starts, 1))
            dec = _evt3_decode_parallel(
                words, state, info.width, info.height, starts, scratch, first=events
            )
            if dec.status == _k.STATUS_DONE:
                events = _join_pieces(dec, events)
            _give_scratch(scratch)
        else:
            dec = _evt3_decode_parallel(words, state, info.width, info.height, starts, events)
            if dec.status == _k.STATUS_DONE:
                events = _join_pieces(dec, events)
        if dec.status != _k.STATUS_DONE:
            _raise_decode_error(info, dec.status, dec.pos, state)
        n_ev, triggers = dec.n_events, dec.triggers
        del dec
    else:
        spare = _SPARE_EVENTS[info.format]
        capacity = (info.n_words if info.format != "evt21" else 2 * info.n_words) + spare + 1
        events = np.empty(capacity, dtype=EVENT_DTYPE)
        triggers = np.empty(64, dtype=TRIGGER_DTYPE)
        pos = n_ev = n_tr = 0
        kernel = _block_kernel(info, words)
        while True:
            status, pos, n_ev, n_tr = _run_kernel(
                info, kernel, words, pos, state, events, n_ev, events.shape[0], triggers, n_tr
            )
            if status == _k.STATUS_DONE:
                break
            if status != _k.STATUS_FULL:
                _raise_decode_error(info, status, pos, state)
            if n_tr >= triggers.shape[0]:
                triggers = _grow(triggers, n_tr, 64)
            else:
                events = _grow(events, n_ev, n_ev + 8 * spare)
        triggers = triggers[:n_tr].copy()
    events = _trim(events, n_ev)
    tt = triggers["t"]
    if tt.size > 1 and (tt[1:] < tt[:-1]).any():
        order = np.argsort(tt, kind="stable")
        moved = int(np.count_nonzero(order != np.arange(order.size)))
        triggers = triggers[order]
        logger.warning(
            "%s: trigger times step back in the stream; %d of %d triggers sorted into time order",
            info.name,
            moved,
            order.size,
        )
    logger.info(
        "%s: %s, %dx%d, %d events, %d triggers",
        info.name,
        _FORMAT_TITLES[info.format],
        info.width,
        info.height,
        n_ev,
        triggers.shape[0],
    )
    metadata = info.metadata
    # The kernels check every pixel against the geometry and write polarity as +-1.
    return Recording.from_checked(
        events=events,
        width=info.width,
        height=info.height,
        triggers=triggers,
        metadata=metadata,
    )


def iter_raw(
    path: str | os.PathLike[str],
    *,
    chunk_events: int = 1_000_000,
    width: int | None = None,
    height: int | None = None,
    block_bytes: int = _DEFAULT_BLOCK_BYTES,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Decode a ``.raw`` file in chunks: yield ``(events, triggers)`` with memory flat in file size.

    The payload is read in blocks of ``block_bytes`` bytes (a positive multiple of
    8) and the decoder state (time base, row, vector base, polarity) is carried
    from block to block, so the chunks concatenate to exactly what
    :func:`read_raw` returns (triggers here keep file order; :func:`read_raw` sorts
    them, which changes nothing unless their times step back). Every chunk but the
    last holds exactly ``chunk_events`` events; triggers come in the chunk whose
    words hold them. At least one chunk (possibly empty) is yielded. Errors as in
    :func:`read_raw`.
    """
    if int(chunk_events) < 1:
        raise ValueError(f"iter_raw: chunk_events must be >= 1, got {chunk_events}")
    if int(block_bytes) < 8 or int(block_bytes) % 8:
        raise ValueError(
            f"iter_raw: block_bytes must be a positive multiple of 8, got {block_bytes}"
        )
    chunk_events = int(chunk_events)
    info = _RawInfo(path, width, height)
    _warn_trailing(info)
    return _iter_chunks(info, chunk_events, int(block_bytes))


# Chunks iter_raw yields, and its read blocks: reused once the caller lets go of them
# (memory written before costs no page faults to write again).
_CHUNKS = Recycler(keep=4, max_bytes=16 << 20)
_BLOCKS = Recycler(keep=2, max_bytes=_DEFAULT_BLOCK_BYTES)
_BYTE = np.dtype(np.uint8)


def _iter_chunks(
    info: _RawInfo, chunk_events: int, block_bytes: int
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    ws = info.word_bytes
    state = _new_state(info.format)
    ev_cap = chunk_events + _SPARE_EVENTS[info.format]
    events = _CHUNKS.get(ev_cap, EVENT_DTYPE)
    triggers = np.empty(64, dtype=TRIGGER_DTYPE)
    n_ev = n_tr = 0
    yielded = False
    payload_left = info.n_words * ws
    # No larger than the payload, and not zero-filled: every byte is read before use.
    block_array = _BLOCKS.get(max(8, min(block_bytes, payload_left)), _BYTE)
    block_view = block_array.data
    words_before = 0  # words of the payload decoded before this block
    with open(info.path, "rb", buffering=0) as f:
        f.seek(info.header_bytes)
        while payload_left > 0:
            want = min(block_bytes, payload_left)
            filled = 0
            while filled < want:
                got = f.readinto(block_view[filled:want])
                if not got:
                    raise ValueError(
                        f"{info.name}: file ended at byte "
                        f"{info.header_bytes + words_before * ws + filled} while reading "
                        "(was it truncated while being read?)"
                    )
                filled += got
            payload_left -= want
            words = _kernel_view(info, block_array[:want])
            _check_payload(info, words, words_before)
            if payload_left == 0:
                _check_end(info, words)
            starts = _evt3_split(words.shape[0]) if info.format == "evt3" else None
            if starts is not None:
                # Decode the block in parallel into scratch (kept for the next block or
                # call), then copy the events, after those carried, into chunks exactly
                # as the loop below cuts them.
                scratch = _take_scratch(_evt3_scratch_size(starts))
                dec = _evt3_decode_parallel(
                    words, state, info.width, info.height, starts, scratch
                )
                n_all = n_ev + dec.n_events
                all_tr = np.concatenate([triggers[:n_tr], dec.triggers])
                # A trigger belongs to the chunk being filled when its word is decoded.
                chunk_of = np.concatenate([np.zeros(n_tr, np.int64), n_ev + dec.tr_index])
                chunk_of //= chunk_events
                n_full = n_all // chunk_events
                cuts = np.searchsorted(chunk_of, np.arange(n_full + 1), side="left")
                gather = _Gather([(events, 0, n_ev), *dec.pieces])
                try:
                    for c in range(n_full):
                        out = _CHUNKS.get(ev_cap, EVENT_DTYPE)
                        gather.take(out, chunk_events)
                        yield out[:chunk_events], all_tr[cuts[c] : cuts[c + 1]].copy()
                        yielded = True
                        del out
                    n_ev = n_all - n_full * chunk_events
                    events = _CHUNKS.get(ev_cap, EVENT_DTYPE)
                    gather.take(events, n_ev)
                finally:  # the chunks are copies: scratch is free again
                    _give_scratch(scratch)
                if dec.status != _k.STATUS_DONE:
                    _raise_decode_error(info, dec.status, words_before + dec.pos, state)
                left = all_tr[cuts[n_full] :]
                triggers = np.empty(max(64, left.shape[0]), dtype=TRIGGER_DTYPE)
                triggers[: left.shape[0]] = left
                n_tr = left.shape[0]
                words_before += want // ws
                continue
            pos = 0
            kernel = _block_kernel(info, words)
            while True:
                status, pos, n_ev, n_tr = _run_kernel(
                    info, kernel, words, pos, state, events, n_ev, chunk_events, triggers, n_tr
                )
                if status == _k.STATUS_DONE:
                    break
                if status != _k.STATUS_FULL:
                    _raise_decode_error(info, status, words_before + pos, state)
                if n_ev >= chunk_events:
                    out = events[:chunk_events]
                    nxt = _CHUNKS.get(ev_cap, EVENT_DTYPE)
                    rest = n_ev - chunk_events
                    nxt[:rest] = events[chunk_events:n_ev]
                    yield out, triggers[:n_tr].copy()
                    yielded = True
                    events, n_ev, n_tr = nxt, rest, 0
                else:
                    triggers = _grow(triggers, n_tr, 64)
            words_before += want // ws
    # A vector word near the end can leave more than chunk_events events (up to 31 more).
    while n_ev > chunk_events:
        yield events[:chunk_events], triggers[:n_tr].copy()
        yielded = True
        rest = n_ev - chunk_events
        nxt = _CHUNKS.get(ev_cap, EVENT_DTYPE)
        nxt[:rest] = events[chunk_events:n_ev]
        events, n_ev, n_tr = nxt, rest, 0
    if n_ev or n_tr or not yielded:
        yield events[:n_ev], triggers[:n_tr].copy()


# --------------------------------------------------------------------------------------
# Writing EVT 2.0 and EVT 3.0
# --------------------------------------------------------------------------------------

# Latest time the writers accept: EVT 2.0 holds 34-bit times; an EVT 3.0 stream that
# starts later than 0 begins at time-high 0 and steps up one word per 4096 µs (about
# 8 MB at this limit).
_MAX_TIME_US = (1 << 34) - 1
_RESERVED_HEADER_KEYS = {"evt", "format", "geometry", "end", METADATA_KEY}
_WRITERS = {"3.0": ("evt3", "EVT3", _k.encode_evt3, _k.ENCODER_STATE_SIZE, np.uint16, 15),
            "2.0": ("evt2", "EVT2", _k.encode_evt2, _k.ENCODER2_STATE_SIZE, np.uint32, 31)}


class RawWriter(FileWriter):
    """Stream events and triggers into an EVT 3.0 (default) or EVT 2.0 ``.raw`` file,
    atomically.

    Use as a context manager; each :meth:`write` takes a time-sorted batch that
    starts no earlier than the previous batch ended. Events and triggers are
    interleaved by time in the stream (a trigger before events of the same µs).
    The file appears under its name only when the ``with`` block ends without an
    exception. Like a sensor, an EVT 3.0 stream carries a time-high word for every
    4096 µs between items, each followed by a TIME_LOW word before the next item (so
    any EVT 3.0 decoder follows its 24-bit wraps and never keeps stale low bits).
    Times must lie in ``[0, 2**34)`` µs.

    The header holds ``% evt 3.0`` (or ``2.0``), ``% format EVT3;height=H;width=W``,
    ``% geometry WxH``, one ``% key value`` line per ``header_extra`` item, the
    recording's ``metadata`` as JSON on a ``% asynhdr_metadata`` line (readers that do
    not know the key, OpenEB's among them, skip it), and ``% end``.

    Parameters
    ----------
    path : destination ``.raw`` file.
    width, height : sensor geometry in pixels (1..2048).
    metadata : JSON-serialisable dict (the rig and sensor of a simulated recording).
    header_extra : more header fields; keys without whitespace, values on one line.
    evt : ``"3.0"`` or ``"2.0"``.
    overwrite : replace an existing file (else ``FileExistsError``).

    Attributes ``events_written``, ``triggers_written`` and ``bytes_written`` (file
    size so far, header included) count what has been written.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        width: int,
        height: int,
        metadata: dict[str, Any] | None = None,
        header_extra: dict[str, Any] | None = None,
        evt: str = "3.0",
        overwrite: bool = True,
    ) -> None:
        if evt not in _WRITERS:
            raise ValueError(f"{path}: evt must be one of {sorted(_WRITERS)}, got {evt!r}")
        super().__init__(path, overwrite=overwrite)
        self.width = int(width)
        self.height = int(height)
        self.evt = evt
        self._fmt, self._fmt_name, encode, state_size, word, self._max_id = _WRITERS[evt]
        self._encode: Any = encode
        _check_geometry(self.width, self.height, str(path), "the writer's arguments")
        extra = dict(header_extra or {})
        if metadata is not None:
            extra[METADATA_KEY] = json_metadata(str(path), metadata)
        self._header = self._make_header(extra, header_extra or {})
        self._state = np.zeros(state_size, dtype=np.int64)
        if evt == "3.0":
            self._state[_k.E_Y] = -1
        self._last_t: int | None = None
        self._buf = np.empty(1 << 20, dtype=word)
        self.events_written = 0
        self.triggers_written = 0
        self.bytes_written = 0

    def _make_header(self, lines_from: dict[str, Any], user: dict[str, Any]) -> bytes:
        lines = [
            f"% evt {self.evt}",
            f"% format {self._fmt_name};height={self.height};width={self.width}",
            f"% geometry {self.width}x{self.height}",
        ]
        for key, value in lines_from.items():
            k = str(key)
            v = str(value)
            if not k or any(c.isspace() for c in k) or k.startswith("%"):
                raise ValueError(
                    f"{self.path}: header_extra key {k!r} must be non-empty, without "
                    "whitespace or '%'"
                )
            if k in user and k.lower() in _RESERVED_HEADER_KEYS:
                raise ValueError(
                    f"{self.path}: header_extra key {k!r} is written by the writer itself"
                )
            if "\n" in v or "\r" in v:
                raise ValueError(f"{self.path}: header_extra value of {k!r} must be one line")
            lines.append(f"% {k} {v}" if v else f"% {k}")
        lines.append("% end")
        return ("\n".join(lines) + "\n").encode("utf-8")

    def _start(self, f: BinaryIO) -> None:
        f.write(self._header)
        self.bytes_written = len(self._header)

    def write(self, events: np.ndarray, triggers: np.ndarray | None = None) -> None:
        """Append a batch of events (``EVENT_DTYPE``) and triggers (``TRIGGER_DTYPE``).

        Both must be sorted by time, inside the geometry, with times in
        ``[0, 2**34)`` µs, trigger channels 0..15 (EVT 3.0) or 0..31 (EVT 2.0), and no
        earlier than the last time already written.
        """
        out = self._file()
        name = str(self.path)
        events = validate_events(
            events, width=self.width, height=self.height, require_sorted=True,
            name=f"{name}: events",
        )
        if triggers is None:
            triggers = empty_triggers()
        triggers = validate_triggers(triggers, name=f"{name}: triggers")
        title = _FORMAT_TITLES[self._fmt]
        if triggers.size and int(triggers["id"].max()) > self._max_id:
            raise ValueError(
                f"{name}: trigger channel {int(triggers['id'].max())} does not fit {title} "
                f"(channels 0..{self._max_id})"
            )
        firsts = [int(a["t"][0]) for a in (events, triggers) if a.size]
        if not firsts:
            return
        t_first = min(firsts)
        t_last = max(int(a["t"][-1]) for a in (events, triggers) if a.size)
        if t_first < 0 or t_last > _MAX_TIME_US:
            raise ValueError(
                f"{name}: times {t_first}..{t_last} µs are outside what {title} holds "
                f"(0..{_MAX_TIME_US} µs, 4.8 hours); subtract a start time before writing "
                "(write_recording's time_shift_us, asynhdr convert --start-at-zero)"
            )
        if self._last_t is not None and t_first < self._last_t:
            raise ValueError(
                f"{name}: batch starts at t={t_first} µs, before the last time already "
                f"written ({self._last_t} µs); batches must follow each other in time"
            )
        self._last_t = t_last
        events = np.ascontiguousarray(events)
        triggers = np.ascontiguousarray(triggers)
        i = j = 0
        while True:
            if self._fmt == "evt3":
                res = self._encode(events, triggers, i, j, self._state, self.width, self._buf)
            else:
                res = self._encode(events, triggers, i, j, self._state, self._buf)
            status, i, j, n = (int(v) for v in res)
            out.write(self._buf[:n].data)
            self.bytes_written += self._buf.itemsize * n
            if status == _k.STATUS_DONE:
                break
            if status != _k.STATUS_FULL:  # time stepped back: validated above
                raise ValueError(f"{name}: times step back at event {i}, trigger {j}")
        self.events_written += int(events.size)
        self.triggers_written += int(triggers.size)


Evt3Writer = RawWriter
"""The EVT 3.0 writer (:class:`RawWriter` with its default ``evt="3.0"``)."""


def write_raw_evt3(path: str | os.PathLike[str], recording: Recording) -> None:
    """Write a recording (events and triggers sorted by time) as an EVT 3.0 ``.raw`` file,
    with its metadata in the header.

    Atomic: the file appears under ``path`` only once complete. Events out of time
    order raise ``ValueError``; sort them first (:meth:`Recording.sorted`).
    """
    with RawWriter(path, width=recording.width, height=recording.height,
                   metadata=recording.metadata) as writer:
        writer.write(recording.events, recording.triggers)


# --------------------------------------------------------------------------------------
# The format record
# --------------------------------------------------------------------------------------


def _sensor_text(fields: dict[str, str]) -> str | None:
    keys = ("camera_integrator_name", "integrator", "plugin_name", "sensor_name",
            "sensor_generation", "generation", "serial_number")
    parts = [f"{k}={fields[k]}" for k in keys if fields.get(k)]
    return ", ".join(parts) or None


def _header(path: Path, opts: ReadOptions) -> Header:
    info = _RawInfo(path, opts.width, opts.height)
    _warn_trailing(info)
    return Header(format=info.format, width=info.width, height=info.height,
                  geometry_source=info.geometry_source, metadata=info.metadata,
                  facts=info.as_dict(), sensor=_sensor_text(info.fields), private=info)


def _chunks(path: Path, header: Header, read_chunk: int,
            opts: ReadOptions) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    return _iter_chunks(header.private, read_chunk, _DEFAULT_BLOCK_BYTES)


def _read(path: Path, header: Header, opts: ReadOptions) -> Recording:
    return read_raw(path, width=opts.width, height=opts.height)


def _sniff(path: Path, head: bytes) -> bool:
    return head.startswith(b"%") or not head


FORMAT = Format(
    name="raw",
    extensions=(".raw",),
    description="Prophesee RAW, EVT 2.0 / 2.1 / 3.0 (Metavision, OpenEB)",
    sniff=_sniff,
    header=_header,
    chunks=_chunks,
    read=_read,
    writer=RawWriter,
)
"""The ``.raw`` record of the format registry (:mod:`asynhdr.io`)."""
