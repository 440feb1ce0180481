"""What every format module shares: the format record, the header record, and the checks
at the boundary (regular files only, geometry caps, time range, integer fields)."""

from __future__ import annotations

import contextlib
import json
import os
import stat
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol

import numpy as np

from asynhdr._atomic import atomic_path
from asynhdr.events import Recording

__all__ = [
    "KNOWN_SENSORS",
    "MAX_ABS_TIME_US",
    "MAX_SIDE_PX",
    "FileWriter",
    "Format",
    "Header",
    "ReadOptions",
    "Writer",
    "check_geometry",
    "check_times",
    "int_field",
    "json_metadata",
    "recording",
    "require_file",
    "resolve_geometry",
]

KNOWN_SENSORS: dict[str, tuple[int, int]] = {
    "Prophesee Gen3 (VGA)": (640, 480),
    "Prophesee Gen4 / Sony IMX636": (1280, 720),
    "Prophesee GenX320": (320, 320),
    "Samsung DVS Gen4": (1280, 960),
    "CelePixel CeleX-V": (1280, 800),
    "iniVation DAVIS346": (346, 260),
    "iniVation DVXplorer": (640, 480),
    "iniVation DAVIS240": (240, 180),
}
"""Sensor geometries (width, height) in pixels of the event cameras in use."""

MAX_SIDE_PX = 4096
"""Largest width or height accepted from any file or argument: the largest sensor in
:data:`KNOWN_SENSORS` is 1280 pixels a side; the cap leaves a margin of more than three
times that (simulated sensors up to 4K). A damaged header asking for more would make
every per-pixel array (one float64 per pixel and cycle) too large to allocate."""

MAX_ABS_TIME_US = (1 << 53) - 1
"""Largest ``|t|`` accepted (µs, 285 years): every time is then exact in float64, which
rate histograms and phases use. Unix time in µs (AEDAT files) is 1.7e15, well inside."""


@dataclass(frozen=True)
class ReadOptions:
    """What a caller may tell a reader: geometry for files without one, time unit for
    text and HDF5 files whose times are not integer µs."""

    width: int | None = None
    height: int | None = None
    time_unit: str | None = None


@dataclass
class Header:
    """What a format's header says, read without decoding the events.

    ``metadata`` is the recording's metadata (the rig and sensor a simulated recording
    was made with, stored by asynhdr's writers; format facts otherwise); ``facts`` are
    the format's own header fields, for ``asynhdr info``. ``triggers`` and ``events``
    are None when only a pass over the events can tell. ``private`` is the format
    module's own state (an open file's description)."""

    format: str
    width: int | None
    height: int | None
    geometry_source: str | None
    metadata: dict[str, Any] = field(default_factory=dict)
    facts: dict[str, Any] = field(default_factory=dict)
    sensor: str | None = None
    triggers: np.ndarray | None = None
    events: int | None = None
    private: Any = None


class FileWriter:
    """Base of the streaming writers: a context manager that writes ``path`` under a
    temporary name (:func:`asynhdr._atomic.atomic_path`) and renames it when the ``with``
    block ends without an exception. Subclasses open the file (:meth:`_open`, binary by
    default), write its head (:meth:`_start`) and implement ``write(events, triggers)``,
    which :meth:`_file` guards."""

    def __init__(self, path: str | os.PathLike[str], *, overwrite: bool = True) -> None:
        self.path = Path(path)
        self._overwrite = overwrite
        self._stack: contextlib.ExitStack | None = None
        self._f: Any = None

    def _open(self, tmp: Path) -> Any:
        return open(tmp, "wb")

    def _start(self, f: Any) -> None:
        """Write what comes before the first batch."""

    def __enter__(self) -> Any:
        stack = contextlib.ExitStack()
        try:
            tmp = stack.enter_context(atomic_path(self.path, overwrite=self._overwrite))
            self._f = stack.enter_context(self._open(tmp))
            self._start(self._f)
        except BaseException:
            stack.close()
            self._f = None
            raise
        self._stack = stack
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        stack, self._stack, self._f = self._stack, None, None
        if stack is not None:
            stack.__exit__(exc_type, exc, tb)

    def _file(self) -> Any:
        """The open file; ``ValueError`` outside the ``with`` block."""
        if self._f is None:
            raise ValueError(f"{self.path}: the writer is not open (use it in a with block)")
        return self._f


class Writer(Protocol):
    """A streaming writer: a context manager taking batches of events and triggers."""

    def __enter__(self) -> Any: ...

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None, /) -> None: ...

    def write(self, events: np.ndarray, triggers: np.ndarray | None = None, /) -> None: ...


Chunks = Iterator[tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Format:
    """One event-file format: how to recognise it, read its header, stream its events,
    read it whole (where faster than streaming), and write it.

    ``sniff(path, head)`` says whether a file (``head``: its first 1 KiB) is in this
    format; ``chunks(path, header, read_chunk, options)`` yields ``(events, triggers)``
    in file order; ``writer(path, width=, height=, metadata=, **options)`` is a
    :class:`Writer` (None: not writable). ``time_unit``: the reader accepts a time unit.
    """

    name: str
    extensions: tuple[str, ...]
    description: str
    sniff: Callable[[Path, bytes], bool]
    header: Callable[[Path, ReadOptions], Header]
    chunks: Callable[[Path, Header, int, ReadOptions], Chunks]
    read: Callable[[Path, Header, ReadOptions], Recording] | None = None
    writer: Callable[..., Writer] | None = None
    time_unit: bool = False


# --------------------------------------------------------------------------- checks


def require_file(path: str | os.PathLike[str]) -> Path:
    """``path`` as a Path when it names a regular file; ``FileNotFoundError`` when it does
    not exist, ``ValueError`` for a folder or anything else (a FIFO or a device would
    block the reader or never end)."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: no such file") from None
    except OSError as exc:
        raise ValueError(f"{p}: cannot read: {exc.strerror or exc}") from None
    if stat.S_ISDIR(st.st_mode):
        raise ValueError(f"{p}: is a folder, not a recording file")
    if not stat.S_ISREG(st.st_mode):
        kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode) else
                "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else
                "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
        raise ValueError(f"{p}: is {kind}; recordings are read from regular files only")
    return p


def check_geometry(name: str, width: int, height: int, source: str) -> tuple[int, int]:
    """``(width, height)`` when both are whole numbers in ``1..MAX_SIDE_PX``, else
    ``ValueError`` naming the file and where the geometry came from."""
    try:
        w, h = int(width), int(height)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: geometry {width!r}x{height!r} from {source} is not a pair "
                         "of whole numbers of pixels") from None
    if not (1 <= w <= MAX_SIDE_PX and 1 <= h <= MAX_SIDE_PX):
        big = max(s for wh in KNOWN_SENSORS.values() for s in wh)
        raise ValueError(
            f"{name}: geometry {w}x{h} from {source} is outside 1..{MAX_SIDE_PX} pixels a "
            f"side (the largest known sensor has {big}); the file is damaged or the "
            "geometry wrong")
    return w, h


def resolve_geometry(
    name: str,
    file_geometry: tuple[int, int] | None,
    width: int | None,
    height: int | None,
    *,
    source: str = "file",
) -> tuple[int, int, str] | None:
    """Geometry from the file, else from the arguments; the two must agree, and both are
    capped (:func:`check_geometry`). Returns ``(width, height, where)`` or None when
    neither gives one."""
    if (width is None) != (height is None):
        raise ValueError(f"{name}: give both width and height, or neither")
    if width is not None:
        width, height = check_geometry(name, width, height, "the arguments")  # type: ignore[arg-type]
    if file_geometry is not None:
        fw, fh = check_geometry(name, file_geometry[0], file_geometry[1], f"the {source}")
        if width is not None and (width, height) != (fw, fh):
            raise ValueError(
                f"{name}: the {source} says {fw}x{fh} but the arguments say "
                f"width={width}, height={height}"
            )
        return fw, fh, source
    if width is not None and height is not None:
        return width, height, "arguments"
    return None


def check_times(name: str, t: np.ndarray, what: str = "events") -> None:
    """``ValueError`` naming the file when a time is beyond ``±MAX_ABS_TIME_US``."""
    if t.size == 0:
        return
    lo, hi = int(t.min()), int(t.max())
    if lo < -MAX_ABS_TIME_US or hi > MAX_ABS_TIME_US:
        bad = hi if hi > MAX_ABS_TIME_US else lo
        i = int(np.argmax(t == bad))
        raise ValueError(f"{name}: {what}: time {bad} µs at index {i} is beyond "
                         f"±{MAX_ABS_TIME_US} µs (285 years); the file is damaged")


def int_field(name: str, field: str, values: Any, dtype: Any) -> np.ndarray:
    """``values`` as a 1-D array of integer ``dtype``; ``ValueError`` naming the file and
    field when it is not 1-D, not integer (bool is accepted for bool targets) or out of
    the dtype's range."""
    a = np.asarray(values)
    dt = np.dtype(dtype)
    if a.ndim != 1:
        raise ValueError(f"{name}: field {field!r} must be 1-D, got shape {a.shape}")
    if dt.kind == "b":
        if a.dtype.kind == "b":
            return a
        if a.dtype.kind not in "iu":
            raise ValueError(f"{name}: field {field!r} has dtype {a.dtype}; expected bool or 0/1")
        if a.size and ((a != 0) & (a != 1)).any():
            i = int(np.argmax((a != 0) & (a != 1)))
            raise ValueError(f"{name}: field {field!r} holds {a[i]} at index {i}; expected 0 or 1")
        return a.astype(bool)
    if a.dtype.kind == "b" or a.dtype.kind not in "iu":
        raise ValueError(
            f"{name}: field {field!r} has dtype {a.dtype}; expected integers ({dt})"
        )
    if a.size and a.dtype != dt:
        info = np.iinfo(dt)
        lo, hi = a.min(), a.max()
        if int(lo) < info.min or int(hi) > info.max:
            bad = int(np.argmax((a < info.min) | (a > info.max)))
            raise ValueError(
                f"{name}: field {field!r} holds {a[bad]} at index {bad}, outside the range "
                f"of {dt} ({info.min}..{info.max})"
            )
    return a.astype(dt, copy=False)


def json_metadata(name: str, metadata: dict[str, Any] | None, *, allow_nan: bool = True
                  ) -> str:
    """``metadata`` as one line of JSON (``{}`` for None); ``ValueError`` naming the file
    when it is not JSON-serialisable."""
    try:
        return json.dumps(metadata or {}, allow_nan=allow_nan)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: metadata is not JSON-serialisable: {exc}") from exc


def recording(name: str, **kwargs: Any) -> Recording:
    """Build a Recording; a validation error names the file."""
    try:
        return Recording(**kwargs)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from exc
