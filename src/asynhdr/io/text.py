"""Recordings as plain text: one event a line, ``t x y p``.

Reading
-------
- Fields separated by whitespace or by commas (decided on the first data line).
- ``#`` starts a comment (whole line or the end of a line); blank lines are skipped.
- An optional header line names the columns in any order (``t,x,y,p``,
  ``timestamp x y polarity`` ...); a time column named ``t_s``, ``t_ms`` or ``t_us``
  gives the time unit.
- Polarity: ``1`` ON, ``0`` or ``-1`` OFF.
- ``time_unit``: ``"us"``, ``"ms"``, ``"s"`` or ``"auto"``. Auto: seconds when the
  times of the first chunk of lines have a fractional part and span less than
  10^4; integer µs when they are whole numbers; otherwise ``ValueError`` asking for
  the unit. What was detected is logged and, when not µs, recorded in
  ``metadata["time_unit_source"]`` (with ``metadata["time_unit_detected"]``).
- Comment lines ``# width: W``, ``# height: H``, ``# metadata: {json}`` before the
  first event, and ``# trigger: t rising id`` anywhere, carry what :func:`save_text`
  writes, so a recording survives the round trip. Without geometry, width and
  height are the largest x and y + 1 (``metadata["geometry_inferred"] = True``).

Errors are ``ValueError`` naming the file, the line number and the field.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, TextIO

import numpy as np

from asynhdr.events import (
    EVENT_DTYPE,
    Recording,
    empty_events,
    empty_triggers,
    make_triggers,
    validate_events,
    validate_triggers,
)
from asynhdr.io._common import (
    MAX_SIDE_PX,
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

__all__ = [
    "DEFAULT_CHUNK_LINES",
    "FORMAT",
    "TEXT_TIME_UNITS",
    "TextWriter",
    "iter_text",
    "read_text",
    "save_text",
    "text_info",
]

logger = logging.getLogger(__name__)

TEXT_TIME_UNITS = ("us", "ms", "s", "auto")
"""Values of ``time_unit``."""

DEFAULT_CHUNK_LINES = 1 << 18
"""Lines read and parsed at a time."""

SECONDS_SPAN_LIMIT = 1e4
"""Auto detection: fractional times spanning less than this are seconds."""

_SCALE_US = {"us": 1, "ms": 1_000, "s": 1_000_000}
_COLUMN_NAMES = {
    "t": "t", "ts": "t", "time": "t", "timestamp": "t", "timestamps": "t",
    "x": "x", "y": "y",
    "p": "p", "pol": "p", "polarity": "p", "on": "p",
}
_UNIT_SUFFIXES = ("_us", "_ms", "_s")
_FIELDS = ("t", "x", "y", "p")
_MAX_EXACT_FLOAT = 2.0 ** 53


@dataclass
class _State:
    """What the lines read so far have established."""

    name: str
    time_unit: str
    delimiter: str | None = None
    columns: tuple[str, ...] | None = None  # field name of each column
    header_unit: str | None = None
    unit: str | None = None  # decided unit
    detected: bool = False
    width: int | None = None
    height: int | None = None
    metadata: dict[str, Any] | None = None
    in_preamble: bool = True
    last_trigger_t: int | None = None
    trigger_lines: list[tuple[int, str]] = field(default_factory=list)


def _fail(st: _State, lineno: int, msg: str) -> ValueError:
    return ValueError(f"{st.name}:{lineno}: {msg}")


def _directive(st: _State, lineno: int, text: str) -> None:
    """Handle a comment line (``text`` without the leading '#')."""
    body = text.strip()
    key, sep, value = body.partition(":")
    if not sep:
        return
    key = key.strip().lower()
    value = value.strip()
    if key == "trigger":
        st.trigger_lines.append((lineno, value))
        return
    if not st.in_preamble:
        return
    if key in ("width", "height"):
        try:
            v = int(value)
        except ValueError:
            raise _fail(st, lineno, f"comment '{key}: {value}' is not a whole number of "
                        "pixels") from None
        if not 1 <= v <= MAX_SIDE_PX:
            raise _fail(st, lineno, f"comment '{key}: {value}' is outside 1..{MAX_SIDE_PX} "
                        "pixels")
        setattr(st, key, v)
    elif key == "metadata":
        try:
            meta = json.loads(value)
        except ValueError as exc:
            raise _fail(st, lineno, f"comment 'metadata:' is not valid JSON ({exc})") from None
        if not isinstance(meta, dict):
            raise _fail(st, lineno, "comment 'metadata:' must hold a JSON object")
        st.metadata = meta


def _split(st: _State, s: str) -> list[str]:
    if st.delimiter is None:
        return s.split()
    return [tok.strip() for tok in s.split(st.delimiter)]


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _header(st: _State, lineno: int, tokens: list[str]) -> None:
    names: list[str] = []
    for tok in tokens:
        low = tok.strip().strip('"').strip("'").lower()
        unit = None
        for suf in _UNIT_SUFFIXES:
            if low.endswith(suf) and _COLUMN_NAMES.get(low[: -len(suf)]) == "t":
                unit, low = suf[1:], low[: -len(suf)]
                break
        canon = _COLUMN_NAMES.get(low)
        if canon is None:
            raise _fail(st, lineno, f"header names a column {tok!r} that is not t, x, y or p "
                        "(expected a header such as 't,x,y,p' or numbers)")
        if unit is not None:
            st.header_unit = unit
        names.append(canon)
    if sorted(names) != sorted(_FIELDS):
        raise _fail(st, lineno, f"header names columns {names}; expected t, x, y and p once "
                    "each, in any order")
    st.columns = tuple(names)


def _locate(st: _State, lines: list[str], linenos: list[int]) -> ValueError:
    """The first malformed line: wrong field count or a field that is not a number."""
    cols = st.columns or _FIELDS
    for s, ln in zip(lines, linenos, strict=True):
        toks = _split(st, s)
        if len(toks) != 4:
            return _fail(st, ln, f"expected 4 fields ({' '.join(cols)}), found {len(toks)}: "
                         f"{s[:80]!r}")
        for tok, nm in zip(toks, cols, strict=True):
            if not _is_number(tok):
                return _fail(st, ln, f"field {nm!r}: {tok[:40]!r} is not a number")
    return ValueError(f"{st.name}: lines {linenos[0]}..{linenos[-1]} could not be parsed")


def _decide_unit(st: _State, t: np.ndarray, linenos: list[int]) -> None:
    if st.unit is not None:
        return
    if st.time_unit != "auto":
        st.unit = st.time_unit
        return
    if st.header_unit is not None:
        st.unit, st.detected = st.header_unit, True
        logger.info("%s: time unit %r from the header", st.name, st.unit)
        return
    fractional = bool(np.any(t != np.floor(t)))
    span = float(t.max() - t.min()) if t.size else 0.0
    if not fractional:
        st.unit = "us"
        logger.info("%s: times are whole numbers; reading them as µs", st.name)
        return
    if span < SECONDS_SPAN_LIMIT:
        st.unit, st.detected = "s", True
        # a guess that is wrong by 1000x for milliseconds with fractions: said, not logged
        logger.warning("%s: times have fractions and span %.6g < %g; reading them as "
                       "seconds (a guess: pass the time unit, e.g. --time-unit ms, if they "
                       "are not)", st.name, span, SECONDS_SPAN_LIMIT)
        return
    raise ValueError(
        f"{st.name}: cannot tell the time unit: times from line {linenos[0]} have fractions "
        f"but span {span:.6g} (seconds would span less than {SECONDS_SPAN_LIMIT:g}); pass "
        "time_unit='us', 'ms' or 's'"
    )


def _bad_row(st: _State, lines: list[str], linenos: list[int], mask: np.ndarray, nm: str,
             expect: str) -> ValueError:
    """Error for the first row in ``mask``, quoting the field as written."""
    i = int(np.argmax(mask))
    cols = st.columns or _FIELDS
    toks = _split(st, lines[i])
    tok = toks[cols.index(nm)] if len(toks) == len(cols) else lines[i]
    return _fail(st, linenos[i], f"field {nm!r}: {tok[:40]!r} {expect}")


def _to_events(st: _State, arr: np.ndarray, lines: list[str], linenos: list[int]) -> np.ndarray:
    cols = st.columns or _FIELDS
    idx = {nm: cols.index(nm) for nm in _FIELDS}
    t = arr[:, idx["t"]]
    out = np.empty(arr.shape[0], dtype=EVENT_DTYPE)
    for nm in ("x", "y"):
        v = arr[:, idx[nm]]
        bad = ~np.isfinite(v) | (v != np.floor(v)) | (v < 0) | (v > 65535)
        if bad.any():
            raise _bad_row(st, lines, linenos, bad, nm,
                           "is not a pixel coordinate (a whole number 0..65535)")
        out[nm] = v.astype(np.uint16)
    p = arr[:, idx["p"]]
    bad = (p != 0) & (p != 1) & (p != -1)
    if bad.any():
        raise _bad_row(st, lines, linenos, bad, "p", "is not a polarity (1 ON; 0 or -1 OFF)")
    out["p"] = np.where(p > 0, 1, -1).astype(np.int8)
    bad = ~np.isfinite(t)
    if bad.any():
        raise _bad_row(st, lines, linenos, bad, "t", "is not a finite time")
    _decide_unit(st, t, linenos)
    unit = st.unit or "us"
    if unit == "us":
        if (np.abs(t) >= _MAX_EXACT_FLOAT).any():
            t_int = _exact_times(st, lines, linenos, idx["t"])
        else:
            frac = t != np.floor(t)
            if frac.any():
                raise _bad_row(st, lines, linenos, frac, "t",
                               "is not a whole number of µs; pass time_unit='s' or 'ms' "
                               "if the times are in seconds or milliseconds")
            t_int = t.astype(np.int64)
    else:
        us = t * _SCALE_US[unit]
        bad = np.abs(us) >= 9.2e18
        if bad.any():
            raise _bad_row(st, lines, linenos, bad, "t", f"({unit}) is beyond the int64 µs range")
        t_int = np.rint(us).astype(np.int64)
    out["t"] = t_int
    if st.width is not None and st.height is not None:
        for nm, lim in (("x", st.width), ("y", st.height)):
            over = out[nm] >= lim
            if over.any():
                raise _bad_row(st, lines, linenos, over, nm,
                               f"is outside the sensor ({st.width}x{st.height} from the "
                               "comments)")
    return out


def _exact_times(st: _State, lines: list[str], linenos: list[int], col: int) -> np.ndarray:
    """Integer µs parsed exactly (times beyond 2^53, where float64 is not exact)."""
    out = np.empty(len(lines), dtype=np.int64)
    for i, (s, ln) in enumerate(zip(lines, linenos, strict=True)):
        tok = _split(st, s)[col]
        try:
            v = int(tok)
        except ValueError:
            raise _fail(st, ln, f"field 't': {tok!r} is not a whole number of µs") from None
        if not -(2 ** 63) <= v < 2 ** 63:
            raise _fail(st, ln, f"field 't': {tok!r} is beyond the int64 µs range")
        out[i] = v
    return out


def _triggers(st: _State) -> np.ndarray:
    if not st.trigger_lines:
        return empty_triggers()
    ts, rs, ids = [], [], []
    for ln, value in st.trigger_lines:
        toks = value.replace(",", " ").split()
        try:
            if len(toks) != 3:
                raise ValueError
            t, r, i = int(toks[0]), int(toks[1]), int(toks[2])
            if r not in (0, 1) or not 0 <= i <= 255 or not -(2 ** 63) <= t < 2 ** 63:
                raise ValueError
        except ValueError:
            raise _fail(st, ln, f"comment 'trigger: {value[:60]}' must be 't rising id' "
                        "(integer µs, 0 or 1, 0..255)") from None
        if st.last_trigger_t is not None and t < st.last_trigger_t:
            raise _fail(st, ln, f"trigger at t={t} µs comes before the previous one "
                        f"({st.last_trigger_t} µs); triggers must be sorted")
        st.last_trigger_t = t
        ts.append(t)
        rs.append(bool(r))
        ids.append(i)
    st.trigger_lines = []
    return make_triggers(np.array(ts, dtype=np.int64), np.array(rs), np.array(ids, dtype=np.uint8))


def _parse_chunk(st: _State, raw_lines: list[str], first_lineno: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    lines: list[str] = []
    linenos: list[int] = []
    for i, raw in enumerate(raw_lines):
        s = raw.strip()
        if not s:
            continue
        if s[0] == "#":
            _directive(st, first_lineno + i, s[1:])
            continue
        if "#" in s:
            s = s.split("#", 1)[0].strip()
            if not s:
                continue
        if st.columns is None:
            st.delimiter = "," if "," in s else None
            toks = _split(st, s)
            st.in_preamble = False
            if not all(_is_number(tok) for tok in toks):
                _header(st, first_lineno + i, toks)
                continue
            st.columns = _FIELDS
        st.in_preamble = False
        lines.append(s)
        linenos.append(first_lineno + i)
    triggers = _triggers(st)
    if not lines:
        return empty_events(), triggers
    try:
        arr = np.loadtxt(lines, delimiter=st.delimiter, dtype=np.float64, ndmin=2,
                         comments=None)
    except ValueError:
        raise _locate(st, lines, linenos) from None
    if arr.shape[1] != 4:
        raise _locate(st, lines, linenos)
    return _to_events(st, arr, lines, linenos), triggers


def _open(p: Path) -> TextIO:
    return open(p, encoding="utf-8", newline=None)


def _read_lines(st: _State, f: TextIO, n: int, lineno: int) -> list[str]:
    try:
        return list(itertools.islice(f, n))
    except UnicodeDecodeError as exc:
        raise ValueError(
            f"{st.name}: not UTF-8 text near line {lineno} ({exc.reason} at byte "
            f"{exc.start} of a block); expected text lines 't x y p'"
        ) from None


def iter_text(
    path: str | os.PathLike[str],
    *,
    chunk_lines: int = DEFAULT_CHUNK_LINES,
    time_unit: str = "auto",
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Read a text recording ``chunk_lines`` lines at a time: yield ``(events,
    triggers)`` (triggers from ``# trigger:`` comments in those lines). Events keep
    file order. Errors (``ValueError`` with file, line and field) come on ``next``."""
    if time_unit not in TEXT_TIME_UNITS:
        raise ValueError(f"time_unit must be one of {TEXT_TIME_UNITS}, got {time_unit!r}")
    if int(chunk_lines) < 1:
        raise ValueError(f"iter_text: chunk_lines must be >= 1, got {chunk_lines}")
    p = require_file(path)
    st = _State(name=str(p), time_unit=time_unit)
    return _iter(p, st, int(chunk_lines))


def _iter(p: Path, st: _State, chunk_lines: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    lineno = 1
    yielded = False
    with _open(p) as f:
        while True:
            raw = _read_lines(st, f, chunk_lines, lineno)
            if not raw:
                break
            ev, tr = _parse_chunk(st, raw, lineno)
            lineno += len(raw)
            if ev.size or tr.size:
                yield ev, tr
                yielded = True
    if not yielded:
        yield empty_events(), empty_triggers()


def _preamble(p: Path, time_unit: str = "auto") -> _State:
    """Read the comment lines and header before the first event."""
    st = _State(name=str(p), time_unit=time_unit)
    with _open(p) as f:
        lineno = 0
        while True:
            try:
                line = f.readline()
            except UnicodeDecodeError as exc:
                raise ValueError(f"{st.name}: not UTF-8 text near line {lineno + 1} "
                                 f"({exc.reason})") from None
            lineno += 1
            if not line:
                break
            s = line.strip()
            if not s:
                continue
            if s[0] == "#":
                _directive(st, lineno, s[1:])
                continue
            toks = [t.strip() for t in s.split(",")] if "," in s else s.split()
            if not all(_is_number(t) for t in toks):
                st.delimiter = "," if "," in s else None
                _header(st, lineno, toks)
            break
    st.trigger_lines = []
    return st


def text_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Header facts of a text recording (no event is parsed): ``width``, ``height``
    (None when the comments give none), ``columns`` (from a header line, else None),
    ``time_unit`` (from the header, else None) and ``metadata``."""
    p = require_file(path)
    st = _preamble(p)
    return {"width": st.width, "height": st.height,
            "columns": list(st.columns) if st.columns else None,
            "time_unit": st.header_unit, "metadata": st.metadata or {}}


def read_text(
    path: str | os.PathLike[str],
    *,
    width: int | None = None,
    height: int | None = None,
    time_unit: str = "auto",
) -> Recording:
    """Read a whole text recording (see the module's description of the format).

    ``width``/``height`` serve when the comments give no geometry (they must agree
    when they do); with neither, the geometry is inferred from the largest x and y.
    """
    if time_unit not in TEXT_TIME_UNITS:
        raise ValueError(f"time_unit must be one of {TEXT_TIME_UNITS}, got {time_unit!r}")
    p = require_file(path)
    st = _State(name=str(p), time_unit=time_unit)
    evs: list[np.ndarray] = []
    trs: list[np.ndarray] = []
    for ev, tr in _iter(p, st, DEFAULT_CHUNK_LINES):
        evs.append(ev)
        trs.append(tr)
    events = np.concatenate(evs) if len(evs) > 1 else evs[0]
    triggers = np.concatenate(trs) if len(trs) > 1 else trs[0]
    meta: dict[str, Any] = dict(st.metadata or {})
    file_geo = (st.width, st.height) if st.width is not None and st.height is not None else None
    if (st.width is None) != (st.height is None):
        raise ValueError(f"{p}: the comments give only one of width and height")
    geo = resolve_geometry(str(p), file_geo, width, height, source="header comments")
    if geo is None:
        if events.size == 0:
            raise ValueError(f"{p}: no events and no geometry; pass width=... and height=...")
        w, h = check_geometry(str(p), int(events["x"].max()) + 1, int(events["y"].max()) + 1,
                              "the largest x and y")
        meta["geometry_inferred"] = True
        logger.warning("%s: no geometry in the file; using %dx%d from the largest x and y",
                       p, w, h)
    else:
        w, h = geo[0], geo[1]
    if st.unit is not None and st.unit != "us":
        meta["time_unit_source"] = st.unit
        meta["time_unit_detected"] = st.detected
    return recording(str(p), events=events, width=w, height=h, triggers=triggers,
                      metadata=meta)


class TextWriter(FileWriter):
    """Stream a recording into a text file, atomically: comment lines with the geometry
    and the metadata (JSON), a header line ``t x y p``, then one event a line (``t`` in
    integer µs, ``p`` 1 ON / 0 OFF) and, among them, a ``# trigger: t rising id`` line
    for each trigger, before the events of its batch."""

    def __init__(self, path: str | os.PathLike[str], *, width: int, height: int,
                 metadata: dict[str, Any] | None = None, delimiter: str | None = None,
                 header: bool = True, overwrite: bool = True) -> None:
        super().__init__(path, overwrite=overwrite)
        d = delimiter if delimiter is not None else (
            "," if self.path.suffix.lower() == ".csv" else " ")
        if d not in (" ", ",", "\t"):
            raise ValueError(f"{path}: delimiter must be ' ', ',' or a tab, got {d!r}")
        self.width, self.height = check_geometry(str(path), width, height,
                                                 "the writer's arguments")
        self._meta = json_metadata(str(path), metadata)
        self._d = d
        self._header = header
        self.events_written = 0

    def _open(self, tmp: Path) -> TextIO:
        return open(tmp, "w", encoding="utf-8", newline="\n")

    def _start(self, f: TextIO) -> None:
        f.write("# asynhdr events: t x y p, one a line; t in µs, p 1 = ON, 0 = OFF\n")
        f.write(f"# width: {self.width}\n# height: {self.height}\n")
        f.write(f"# metadata: {self._meta}\n")
        if self._header:
            f.write(self._d.join(_FIELDS) + "\n")

    def write(self, events: np.ndarray, triggers: np.ndarray | None = None) -> None:
        """Append events (``EVENT_DTYPE``, file order) and triggers."""
        f, d = self._file(), self._d
        validate_events(events, width=self.width, height=self.height, require_sorted=False,
                        name=f"{self.path}: events")
        if triggers is not None and triggers.size:
            validate_triggers(triggers, name=f"{self.path}: triggers")
            for t, r, i in zip(triggers["t"].tolist(), triggers["rising"].tolist(),
                               triggers["id"].tolist(), strict=True):
                f.write(f"# trigger: {t} {int(r)} {i}\n")
        for a in range(0, events.size, 1 << 18):
            c = events[a : a + (1 << 18)]
            pp = (c["p"] > 0).astype(np.int8)
            rows = zip(c["t"].tolist(), c["x"].tolist(), c["y"].tolist(), pp.tolist(),
                       strict=True)
            f.write("".join(f"{t}{d}{x}{d}{y}{d}{q}\n" for t, x, y, q in rows))
        self.events_written += int(events.size)

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        super().__exit__(exc_type, exc, tb)
        if exc_type is None:
            logger.info("%s: wrote %d events as text", self.path, self.events_written)


def save_text(
    path: str | os.PathLike[str],
    recording: Recording,
    *,
    delimiter: str = " ",
    header: bool = True,
    overwrite: bool = True,
) -> None:
    """Write a recording as text, atomically (see :class:`TextWriter`); the triggers come
    first, as comment lines."""
    with TextWriter(path, width=recording.width, height=recording.height,
                    metadata=recording.metadata, delimiter=delimiter, header=header,
                    overwrite=overwrite) as w:
        w.write(recording.events, recording.triggers)


def _header_of(path: Path, opts: ReadOptions) -> Header:
    info = text_info(path)
    if (info["width"] is None) != (info["height"] is None):
        raise ValueError(f"{path}: the comments give only one of width and height")
    return Header(format="text", width=info["width"], height=info["height"],
                  geometry_source="header comments" if info["width"] else None,
                  metadata=info["metadata"], facts=info)


FORMAT = Format(
    name="text",
    extensions=(".txt", ".csv"),
    description="text, one event a line: t x y p (or t,x,y,p)",
    sniff=lambda path, head: b"\x00" not in head,
    header=_header_of,
    chunks=lambda path, header, n, opts: iter_text(path, chunk_lines=n,
                                                   time_unit=opts.time_unit or "auto"),
    read=lambda path, header, opts: read_text(path, width=opts.width, height=opts.height,
                                              time_unit=opts.time_unit or "auto"),
    writer=TextWriter,
    time_unit=True,
)
"""The text record of the format registry (:mod:`asynhdr.io`)."""
