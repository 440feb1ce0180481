"""The project's event and trigger types, validation at the boundary, and the recording.

Events follow the Metavision layout: ``x, y: uint16`` (pixel column and row),
``p: int8`` (+1 ON, -1 OFF), ``t: int64`` microseconds. Triggers are
``t: int64`` microseconds, ``rising: bool`` (edge direction) and ``id: uint8``
(the input channel).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Any

import numba as nb
import numpy as np
import numpy.typing as npt

__all__ = [
    "EVENT_DTYPE",
    "TRIGGER_DTYPE",
    "Recording",
    "empty_events",
    "empty_triggers",
    "make_events",
    "make_triggers",
    "sort_events",
    "validate_events",
    "validate_triggers",
]

logger = logging.getLogger(__name__)

EVENT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("p", "i1"), ("t", "<i8")])
"""Structured dtype of one event: x, y (uint16), p (int8, +1/-1), t (int64 µs)."""

TRIGGER_DTYPE = np.dtype([("t", "<i8"), ("rising", "?"), ("id", "u1")])
"""Structured dtype of one trigger edge: t (int64 µs), rising (bool), id (uint8)."""


def empty_events(n: int = 0) -> np.ndarray:
    """Return a zeroed event array of length ``n``."""
    return np.zeros(n, dtype=EVENT_DTYPE)


def empty_triggers(n: int = 0) -> np.ndarray:
    """Return a zeroed trigger array of length ``n``."""
    return np.zeros(n, dtype=TRIGGER_DTYPE)


def make_events(
    x: npt.ArrayLike, y: npt.ArrayLike, p: npt.ArrayLike, t: npt.ArrayLike
) -> np.ndarray:
    """Build an event array from per-field sequences (no validation; see ``validate_events``)."""
    xa = np.asarray(x)
    out = np.empty(xa.shape[0], dtype=EVENT_DTYPE)
    out["x"] = xa
    out["y"] = np.asarray(y)
    out["p"] = np.asarray(p)
    out["t"] = np.asarray(t)
    return out


def make_triggers(
    t: npt.ArrayLike, rising: npt.ArrayLike | bool = True, id: npt.ArrayLike | int = 0
) -> np.ndarray:
    """Build a trigger array; ``rising`` and ``id`` broadcast against ``t``."""
    ta = np.atleast_1d(np.asarray(t, dtype=np.int64))
    out = np.empty(ta.shape[0], dtype=TRIGGER_DTYPE)
    out["t"] = ta
    out["rising"] = rising
    out["id"] = id
    return out


def validate_events(
    events: Any,
    *,
    width: int | None = None,
    height: int | None = None,
    require_sorted: bool = True,
    name: str = "events",
) -> np.ndarray:
    """Check an event array at a boundary and return it unchanged.

    Raises ``ValueError`` naming the first problem found: wrong dtype, polarity not
    in {-1, +1}, a pixel outside ``width`` x ``height``, or (when ``require_sorted``)
    a time that steps back, with the index where it does.
    """
    if not isinstance(events, np.ndarray):
        raise ValueError(f"{name}: expected a numpy structured array, got {type(events).__name__}")
    if events.dtype != EVENT_DTYPE:
        raise ValueError(
            f"{name}: wrong dtype {events.dtype}; expected {EVENT_DTYPE} "
            "(x, y uint16; p int8 ±1; t int64 µs)"
        )
    if events.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D array, got shape {events.shape}")
    if events.size == 0:
        return events
    w = -1 if width is None else int(width)
    h = -1 if height is None else int(height)
    if _all_fine(events["x"], events["y"], events["p"], events["t"], w, h, require_sorted):
        return events
    code, i, back = _scan_events(events["x"], events["y"], events["p"], events["t"], w, h,
                                 require_sorted)
    if code == 1:
        raise ValueError(f"{name}: polarity must be +1 or -1; event {i} has "
                         f"p={int(events['p'][i])}")
    if code == 2:
        raise ValueError(
            f"{name}: event {i} at x={int(events['x'][i])} is outside the sensor "
            f"(width={width})"
        )
    if code == 3:
        raise ValueError(
            f"{name}: event {i} at y={int(events['y'][i])} is outside the sensor "
            f"(height={height})"
        )
    if code == 4:
        t = events["t"]
        raise ValueError(
            f"{name}: times are not sorted: event {i} at t={int(t[i])} µs comes after "
            f"t={int(t[i - 1])} µs ({back} backward steps in all); "
            "use asynhdr.events.sort_events to sort stably"
        )
    return events


@nb.njit(cache=True)
def _all_fine(x, y, p, t, width, height, require_sorted):
    """Branch-free first pass: True when no event has a bad polarity, a pixel outside
    the sensor or (when asked) a time that steps back. Only when it says False does
    ``_scan_events`` look for the first problem."""
    bad = 0
    xmax = np.int64(0)
    ymax = np.int64(0)
    n = x.shape[0]
    for i in range(n):
        pi = p[i]
        bad |= (pi != 1) & (pi != -1)
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        xmax = xi if xi > xmax else xmax
        ymax = yi if yi > ymax else ymax
    if bad:
        return False
    if width >= 0 and xmax >= width:
        return False
    if height >= 0 and ymax >= height:
        return False
    if require_sorted:
        back = 0
        for i in range(1, n):
            back |= t[i] < t[i - 1]
        if back:
            return False
    return True


@nb.njit(cache=True)
def _scan_events(x, y, p, t, width, height, require_sorted):
    """One pass over the fields: (problem code, first index, backward steps).

    Codes: 0 fine, 1 polarity, 2 x outside, 3 y outside, 4 time steps back. Polarity and
    geometry problems are reported before time order.
    """
    back = 0
    first_back = -1
    for i in range(x.shape[0]):
        pi = p[i]
        if pi != 1 and pi != -1:
            return 1, i, 0
        if width >= 0 and x[i] >= width:
            return 2, i, 0
        if height >= 0 and y[i] >= height:
            return 3, i, 0
        if require_sorted and i > 0 and t[i] < t[i - 1]:
            back += 1
            if first_back < 0:
                first_back = i
    if first_back >= 0:
        return 4, first_back, back
    return 0, -1, 0


def validate_triggers(triggers: Any, *, name: str = "triggers") -> np.ndarray:
    """Check a trigger array (dtype, 1-D, times sorted); raise ``ValueError`` naming the problem."""
    if not isinstance(triggers, np.ndarray):
        raise ValueError(
            f"{name}: expected a numpy structured array, got {type(triggers).__name__}"
        )
    if triggers.dtype != TRIGGER_DTYPE:
        raise ValueError(
            f"{name}: wrong dtype {triggers.dtype}; expected {TRIGGER_DTYPE} "
            "(t int64 µs, rising bool, id uint8)"
        )
    if triggers.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D array, got shape {triggers.shape}")
    t = triggers["t"]
    if t.size > 1 and (t[1:] < t[:-1]).any():
        i = int(np.argmax(t[1:] < t[:-1])) + 1
        raise ValueError(f"{name}: times are not sorted at trigger {i} (t={int(t[i])} µs)")
    return triggers


def sort_events(events: np.ndarray) -> tuple[np.ndarray, int]:
    """Sort events by time, stably (file order kept among equal times).

    Returns the sorted array and the number of events whose position changed.
    Real EVT 3.0 streams can step back by a few µs; the steps that need sorted
    time call this and report how many events moved.
    """
    t = events["t"]
    if t.size < 2 or not (t[1:] < t[:-1]).any():
        return events, 0
    order = np.argsort(t, kind="stable")
    moved = int(np.count_nonzero(order != np.arange(order.size)))
    logger.info("sorted %d events by time; %d changed position", t.size, moved)
    return events[order], moved


@dataclass(frozen=True)
class Recording:
    """Events + triggers + sensor geometry + metadata.

    Attributes
    ----------
    events : structured array of ``EVENT_DTYPE``, in file order (sorted by ``t``
        when simulated).
    triggers : structured array of ``TRIGGER_DTYPE``.
    width, height : sensor geometry in pixels; images are ``(height, width)``.
    metadata : JSON-serialisable dict (rig and sensor parameters when simulated,
        the source file and format when read).
    """

    events: np.ndarray
    width: int
    height: int
    triggers: np.ndarray = field(default_factory=empty_triggers)
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._check_geometry()
        validate_events(
            self.events, width=self.width, height=self.height, require_sorted=False
        )
        validate_triggers(self.triggers)

    def _check_geometry(self) -> None:
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(
                f"recording: width and height must be positive, got {self.width}x{self.height}"
            )

    @classmethod
    def from_checked(
        cls,
        *,
        events: np.ndarray,
        width: int,
        height: int,
        triggers: np.ndarray | None = None,
        metadata: dict[str, Any] | None = None,
    ) -> Recording:
        """Build a Recording from events a decoder has already checked, event by event,
        in the pass that produced them: ``EVENT_DTYPE``, every pixel inside ``width`` x
        ``height``, every polarity +1 or -1.

        Geometry, the events' dtype and shape, and the triggers are checked as in the
        constructor; the per-event scan (a full pass over the events) is not repeated.
        """
        validate_events(events[:0] if isinstance(events, np.ndarray) and events.ndim == 1
                        else events)
        rec = object.__new__(cls)
        for name, value in (("events", events), ("width", width), ("height", height),
                            ("triggers", empty_triggers() if triggers is None else triggers),
                            ("metadata", {} if metadata is None else metadata)):
            object.__setattr__(rec, name, value)
        rec._check_geometry()
        validate_triggers(rec.triggers)
        return rec

    @property
    def duration_us(self) -> int:
        """Time from the first to the last event, in µs (0 when empty)."""
        if self.events.size == 0:
            return 0
        t = self.events["t"]
        return int(t.max() - t.min())

    def with_events(self, events: np.ndarray) -> Recording:
        """Return a copy with other events (same geometry, triggers, metadata)."""
        return replace(self, events=events)

    def sorted(self) -> tuple[Recording, int]:
        """Return a copy with events sorted stably by time, and how many moved."""
        ev, moved = sort_events(self.events)
        return replace(self, events=ev), moved

    def equals(self, other: Recording) -> bool:
        """True when events, triggers, geometry and metadata are identical."""
        return (
            self.width == other.width
            and self.height == other.height
            and np.array_equal(self.events, other.events)
            and np.array_equal(self.triggers, other.triggers)
            and self.metadata == other.metadata
        )
