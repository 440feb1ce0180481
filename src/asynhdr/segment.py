"""Segmentation of a recording into modulation cycles.

Each modulation cycle starts when panel 1 begins to open (``T1 ~ 0``, ``T2 = 1``).
A rig marks it with a rising trigger edge; without triggers the start is found
from the event rate, because the panels make every pixel fire in a burst each
cycle (brightest pixels first).

Everything here is pure: arrays or a :class:`~asynhdr.source.Source` in, arrays out; no
file is opened here. Times are integer microseconds.

Public API
----------
- :class:`Cycles`: cycle starts, period, where they came from and how sure we are.
- :func:`cycles_from_triggers`: rising edges = cycle starts, with missing and extra
  edges reported (never silently mis-split).
- :func:`cycles_from_events`: period and phase from the event-rate envelope.
- :func:`cycles_from_rate`: the same from an event-rate histogram (for callers that
  bin a large recording while streaming it).
- :func:`find_cycles`: the one cycle policy (triggers, else a simulated recording's rig,
  else the event-rate envelope with a confidence below which there are no cycles),
  used by every command.
- :func:`event_rate`: events per bin.
- :func:`split_cycles`: ``(start, stop)`` event indices of each cycle.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from asynhdr.events import Recording, sort_events, validate_events, validate_triggers
from asynhdr.source import Progress, Source, as_source

__all__ = [
    "MIN_COVERAGE",
    "MIN_RATE_CONFIDENCE",
    "Cycles",
    "NoCyclesError",
    "cycles_from_events",
    "cycles_from_rate",
    "cycles_from_triggers",
    "estimate_period_from_rate",
    "event_rate",
    "find_cycles",
    "split_cycles",
]

logger = logging.getLogger(__name__)

SOURCES = ("triggers", "rig", "event_rate")
"""Where cycle starts can come from."""

MIN_RATE_CONFIDENCE = 0.2
"""Cycles found from the event rate with a lower confidence are not used: the
recording shows no periodic bursts (it may not be modulated)."""

MIN_COVERAGE = 0.5
"""Cycles found from the event rate are not used when, in a typical cycle, fewer than this
fraction of the active pixels fire: the panels make every pixel fire each cycle, so
bursts of part of the sensor (an APS frame readout, a flicker) are not modulation."""

DEFAULT_PERIOD_RANGE_US = (1_000, 1_000_000)
"""Period search range (µs) of :func:`cycles_from_events` when none is given: 1 ms to 1 s."""

ONSET_FRACTION = 0.1
"""A burst starts where the event rate, rising, crosses 10 % of the way from the
baseline to the burst's plateau (see ``_template_onset``)."""


def _empty_i64() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


@dataclass(frozen=True, eq=False)
class Cycles:
    """Modulation cycles of a recording.

    Attributes
    ----------
    start_us : int64 array, strictly increasing: the start time of each cycle (µs).
    period_us : float, the modulation period ``P`` (µs).
    source : ``"triggers"``, ``"rig"`` (a simulated recording's own) or ``"event_rate"``.
    confidence : float in [0, 1]. From triggers: the fraction of cycle starts that
        came from a trigger edge on the expected grid, ``n_ok / (n_ok + n_missing +
        n_extra)``. From the event rate: template contrast × fraction of cycles whose
        burst was found × ``1 / (1 + (rms / 0.01 P)^2)`` with ``rms`` the scatter of
        the burst onsets about the fitted line.
    missing : int64 array, times (µs) where an edge (or a burst) was expected and
        none came. With ``fill_missing`` these times are also in ``start_us``.
    extra : int64 array, times (µs) of edges that are off the period grid and were
        not used as cycle starts.
    warmup : the number of leading cycles (0 or 1) whose pixels start adapted to the
        light before the modulation rather than to the end of a cycle (see
        :func:`find_cycles`): a static scene's image differs in them.

    Cycle ``i`` spans ``[start_us[i], stop_us[i])``; see :attr:`stop_us`.
    """

    start_us: np.ndarray
    period_us: float
    source: str
    confidence: float
    missing: np.ndarray = field(default_factory=_empty_i64)
    extra: np.ndarray = field(default_factory=_empty_i64)
    warmup: int = 0

    def __post_init__(self) -> None:
        for name in ("start_us", "missing", "extra"):
            a = np.asarray(getattr(self, name))
            if a.ndim != 1:
                raise ValueError(f"cycles: {name} must be 1-D, got shape {a.shape}")
            if a.size and not np.issubdtype(a.dtype, np.integer):
                raise ValueError(f"cycles: {name} must hold integer µs, got dtype {a.dtype}")
            object.__setattr__(self, name, a.astype(np.int64, copy=False))
        s = self.start_us
        if s.size > 1 and not (np.diff(s) > 0).all():
            i = int(np.argmax(np.diff(s) <= 0)) + 1
            raise ValueError(
                f"cycles: start_us must increase strictly; start {i} ({int(s[i])} µs) "
                f"follows {int(s[i - 1])} µs"
            )
        if not (np.isfinite(self.period_us) and self.period_us > 0):
            raise ValueError(f"cycles: period_us must be positive, got {self.period_us}")
        if self.source not in SOURCES:
            raise ValueError(f"cycles: source must be one of {SOURCES}, got {self.source!r}")
        if not (0.0 <= self.confidence <= 1.0):
            raise ValueError(f"cycles: confidence must be in [0, 1], got {self.confidence}")

    def __len__(self) -> int:
        return int(self.start_us.size)

    @property
    def stop_us(self) -> np.ndarray:
        """End of each cycle (µs, exclusive).

        ``stop[i] = start[i + 1]`` when the next start is less than 1.5 periods away,
        else ``start[i] + round(period_us)`` (the last cycle, and a cycle before a gap
        left by a missing edge that was not filled).
        """
        s = self.start_us
        own = s + round(self.period_us)
        if s.size == 0:
            return own
        stop = own.copy()
        nxt = s[1:]
        near = (nxt - s[:-1]) < 1.5 * self.period_us
        stop[:-1] = np.where(near, nxt, own[:-1])
        return stop

    def bounds(self, events: np.ndarray) -> list[tuple[int, int]]:
        """``(start index, stop index)`` of each cycle; see :func:`split_cycles`."""
        return split_cycles(events, self)

    def split(self, events: np.ndarray) -> list[np.ndarray]:
        """The events of each cycle, as views into the time-sorted events."""
        ev, _ = sort_events(events)
        return [ev[a:b] for a, b in split_cycles(ev, self)]

    def events_of(self, events: np.ndarray, i: int) -> np.ndarray:
        """The events of cycle ``i`` (``events`` must be sorted by time)."""
        n = len(self)
        if not -n <= i < n:
            raise ValueError(f"cycles: cycle {i} does not exist ({n} cycles)")
        t = events["t"]
        if t.size > 1 and (t[1:] < t[:-1]).any():
            raise ValueError(
                "cycles.events_of: events are not sorted by time; use "
                "asynhdr.events.sort_events or Cycles.split"
            )
        a, b = np.searchsorted(t, [self.start_us[i], self.stop_us[i]], side="left")
        return events[int(a):int(b)]

    def within(self, t_first_us: int, t_last_us: int) -> Cycles:
        """Only the cycles that lie wholly in ``[t_first_us, t_last_us]`` (complete cycles)."""
        keep = (self.start_us >= t_first_us) & (self.stop_us <= t_last_us + 1)
        return replace(self, start_us=self.start_us[keep],
                       warmup=int(bool(self.warmup and keep.size and keep[0])))

    def summary(self) -> dict[str, Any]:
        """A JSON-serialisable summary (counts, period, confidence)."""
        return {
            "cycles": len(self),
            "period_us": float(self.period_us),
            "frequency_hz": 1e6 / float(self.period_us),
            "source": self.source,
            "confidence": float(self.confidence),
            "first_start_us": int(self.start_us[0]) if len(self) else None,
            "missing": int(self.missing.size),
            "extra": int(self.extra.size),
            "warmup": int(self.warmup),
        }


# --------------------------------------------------------------------------- triggers


def cycles_from_triggers(
    triggers: np.ndarray,
    *,
    period_us: float | None = None,
    channel: int | None = None,
    tolerance: float = 0.05,
    fill_missing: bool = True,
) -> Cycles:
    """Cycle starts from rising trigger edges.

    Each rising edge on ``channel`` starts a cycle. The period ``P`` is the median
    interval between consecutive rising edges unless ``period_us`` is given (then
    the median interval must agree with it within ``tolerance``). Starting from an
    edge whose neighbours are both one period away, edges are accepted when they lie
    ``m`` periods (``m >= 1``) after the last accepted edge, within ``tolerance * P``:

    - ``m >= 2``: ``m - 1`` edges are missing; their times (evenly spaced) are
      reported in ``missing`` and, with ``fill_missing``, used as cycle starts;
    - an edge off the grid (``|d - m P| > tolerance * P``, including ``d < P``) is
      extra: reported in ``extra`` and not used.

    A warning is logged when edges are missing or extra. The reported period is the
    least-squares slope of accepted edge times over their cycle index.

    Parameters
    ----------
    triggers : array of ``TRIGGER_DTYPE`` (t in µs, sorted).
    period_us : expected period (µs), or None to estimate it.
    channel : trigger id to use; None when the triggers hold one id only.
    tolerance : allowed deviation of an interval, as a fraction of the period.
    fill_missing : insert the estimated times of missing edges as cycle starts.

    Raises
    ------
    ValueError : no rising edge on the channel, several channels and none chosen,
        fewer than two edges and no ``period_us``, or a ``period_us`` that the edges
        contradict.
    """
    validate_triggers(triggers)
    if not 0 < tolerance < 0.5:
        raise ValueError(f"cycles_from_triggers: tolerance must be in (0, 0.5), got {tolerance}")
    ids = np.unique(triggers["id"])
    if channel is None:
        rising_ids = np.unique(triggers["id"][triggers["rising"]])
        if rising_ids.size > 1:
            counts = {int(i): int(np.count_nonzero(triggers["id"][triggers["rising"]] == i))
                      for i in rising_ids}
            raise ValueError(
                f"cycles_from_triggers: rising edges on several channels {counts} "
                "(channel: count); pass channel= to choose one"
            )
        channel = int(rising_ids[0]) if rising_ids.size else (int(ids[0]) if ids.size else 0)
    sel = triggers["rising"] & (triggers["id"] == channel)
    edges = triggers["t"][sel].astype(np.int64)
    if edges.size == 0:
        raise ValueError(
            f"cycles_from_triggers: no rising edge on channel {channel} "
            f"({triggers.size} trigger records, ids {ids.tolist()}); "
            "use cycles_from_events to find cycles from the event rate"
        )
    if period_us is not None and not (np.isfinite(period_us) and period_us > 0):
        raise ValueError(f"cycles_from_triggers: period_us must be positive, got {period_us}")
    if edges.size < 2:
        if period_us is None:
            raise ValueError(
                "cycles_from_triggers: one rising edge only; cannot estimate the period — "
                "pass period_us"
            )
        return Cycles(start_us=edges, period_us=float(period_us), source="triggers",
                      confidence=1.0)

    d = np.diff(edges).astype(np.float64)
    med = float(np.median(d))
    if period_us is None:
        p0 = med
    else:
        p0 = float(period_us)
        if abs(med - p0) > tolerance * p0:
            raise ValueError(
                f"cycles_from_triggers: rising edges are {med:.1f} µs apart (median), "
                f"but period_us={p0:g}; check the trigger channel or the period"
            )
    if p0 <= 0:
        raise ValueError("cycles_from_triggers: rising edges share one time; cannot find a period")

    tol_us = tolerance * p0
    good = np.abs(d - p0) <= tol_us  # interval i (between edge i and i+1) is one period
    both = np.zeros(edges.size, dtype=bool)
    both[1:-1] = good[:-1] & good[1:]
    one = np.zeros(edges.size, dtype=bool)
    one[:-1] |= good
    one[1:] |= good
    if both.any():
        anchor = int(np.argmax(both))
    elif one.any():
        anchor = int(np.argmax(one))
    else:
        raise ValueError(
            f"cycles_from_triggers: no two consecutive rising edges are one period "
            f"({p0:.1f} µs ± {100 * tolerance:g} %) apart; cannot anchor the cycles"
        )

    accepted: list[tuple[int, int]] = [(int(edges[anchor]), 0)]  # (time, cycle index)
    missing: list[int] = []
    extra: list[int] = []

    def walk(order: range, sign: int) -> None:
        last_t, last_k = accepted[0]
        for j in order:
            e = int(edges[j])
            dd = sign * (e - last_t)
            m = round(dd / p0)
            if m >= 1 and abs(dd - m * p0) <= tol_us:
                for q in range(1, m):
                    missing.append(round(last_t + sign * q * dd / m))
                last_t, last_k = e, last_k + sign * m
                accepted.append((e, last_k))
            else:
                extra.append(e)

    walk(range(anchor + 1, edges.size), +1)
    walk(range(anchor - 1, -1, -1), -1)

    acc = np.array(sorted(accepted), dtype=np.int64)
    t_acc, k_acc = acc[:, 0], acc[:, 1]
    if t_acc.size >= 2:
        kk = (k_acc - k_acc[0]).astype(np.float64)
        period = float(np.polyfit(kk, (t_acc - t_acc[0]).astype(np.float64), 1)[0])
    else:
        period = p0
    miss = np.array(sorted(missing), dtype=np.int64)
    ext = np.array(sorted(extra), dtype=np.int64)
    starts = np.union1d(t_acc, miss) if fill_missing else t_acc
    conf = t_acc.size / (t_acc.size + miss.size + ext.size)
    if miss.size or ext.size:
        logger.warning(
            "cycles from triggers (channel %d, period %.1f µs): %d missing edge(s)%s%s, "
            "%d extra edge(s)%s ignored",
            channel, period, miss.size, f" at {miss[:5].tolist()} µs" if miss.size else "",
            " (filled)" if (fill_missing and miss.size) else "",
            ext.size, f" at {ext[:5].tolist()} µs" if ext.size else "",
        )
    return Cycles(start_us=starts, period_us=period, source="triggers",
                  confidence=float(conf), missing=miss, extra=ext)


# --------------------------------------------------------------------------- event rate


def event_rate(t_us: np.ndarray, *, bin_us: float, t0_us: int | None = None) -> np.ndarray:
    """Events per bin: ``counts[i] = #{t : t0 + i*bin_us <= t < t0 + (i+1)*bin_us}``.

    ``t0_us`` defaults to the earliest time; events before ``t0_us`` are ignored.
    Returns an int64 array (empty when there are no events).
    """
    if not bin_us > 0:
        raise ValueError(f"event_rate: bin_us must be positive, got {bin_us}")
    t = np.asarray(t_us, dtype=np.int64)
    if t.size == 0:
        return np.zeros(0, dtype=np.int64)
    t0 = int(t.min()) if t0_us is None else int(t0_us)
    idx = np.floor((t - t0) / float(bin_us)).astype(np.int64)
    idx = idx[idx >= 0]
    return np.bincount(idx).astype(np.int64)


def estimate_period_from_rate(
    counts: np.ndarray,
    *,
    bin_us: float,
    period_range_us: tuple[float, float] = DEFAULT_PERIOD_RANGE_US,
) -> tuple[float, float]:
    """Period of an event-rate series from its autocorrelation.

    The autocorrelation ``R(L) = sum_i x_i x_{i+L} / sum_i x_i^2`` of the mean-removed
    counts ``x`` is searched beyond its central lobe (after it first drops below 0)
    and within ``period_range_us``; the highest peak is replaced by its smallest
    integer submultiple that reaches 70 % of its height (so ``P`` wins over ``2P``),
    and refined by a parabola through the peak and its neighbours.

    Returns ``(period_us, strength)`` with ``strength = R(P)`` in [0, 1].
    Raises ``ValueError`` when the series is shorter than two periods of the range's
    lower end, or flat.
    """
    x = np.asarray(counts, dtype=np.float64)
    lo_us, hi_us = float(period_range_us[0]), float(period_range_us[1])
    if not (0 < lo_us < hi_us):
        raise ValueError(f"period_range_us must be (low, high) with 0 < low < high, "
                         f"got {period_range_us}")
    n = x.size
    lag_lo = max(2, int(np.floor(lo_us / bin_us)))
    lag_hi = min(int(np.ceil(hi_us / bin_us)), n // 2)
    if lag_hi <= lag_lo:
        raise ValueError(
            f"event rate: {n} bins of {bin_us:g} µs ({n * bin_us / 1e3:.1f} ms) are too "
            f"few to find a period in {lo_us:g}..{hi_us:g} µs (need at least two periods)"
        )
    x = x - x.mean()
    power = float(np.dot(x, x))
    if power <= 0:
        raise ValueError("event rate: the rate is constant; no modulation to find")
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(x, nfft)
    ac = np.fft.irfft(f.real ** 2 + f.imag ** 2, nfft)[: lag_hi + 2] / power
    below = np.nonzero(ac[1 : lag_hi + 1] < 0)[0]
    start = max(lag_lo, int(below[0]) + 1 if below.size else lag_hi)
    if start >= lag_hi:
        raise ValueError(
            "event rate: the autocorrelation never drops below zero within the period "
            "range; no periodic bursts found"
        )
    seg = ac[start : lag_hi + 1]
    best = start + int(np.argmax(seg))
    height = ac[best]
    for q in range(int(best // start), 1, -1):
        c = best / q
        a, b = max(start, int(np.floor(c)) - 2), min(lag_hi, int(np.ceil(c)) + 2)
        if b < a:
            continue
        j = a + int(np.argmax(ac[a : b + 1]))
        if ac[j] >= 0.7 * height:
            best = j
            break
    lag = float(best)
    if 1 <= best < ac.size - 1:
        y0, y1, y2 = ac[best - 1], ac[best], ac[best + 1]
        den = y0 - 2 * y1 + y2
        if den < 0:
            lag += float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5))
    return lag * bin_us, float(np.clip(ac[best], 0.0, 1.0))


def _crossing(prof: np.ndarray, level: float, i_hi: int) -> float:
    """Walking back (circularly) from index ``i_hi`` where ``prof >= level``, the
    fractional index where ``prof`` crosses ``level`` (linear interpolation)."""
    n = prof.size
    i = i_hi
    for _ in range(n):
        j = i - 1
        if prof[j % n] < level:
            lo, hi = prof[j % n], prof[i % n]
            frac = (level - lo) / (hi - lo) if hi > lo else 0.0
            return j + frac
        i = j
    return float(i_hi)


def _template_onset(template: np.ndarray) -> float:
    """Cycle onset in a one-period profile, in bin units (may be negative: circular).

    The profile is smoothed over 3 bins (circularly). Baseline ``b`` = its 10th
    percentile; plateau ``h`` = the median of the values above ``b + (max - b) / 2``;
    level ``b + 0.1 (h - b)``. From the profile's maximum, walk forward (circularly)
    until the profile falls below the level, then on to where it first rises through
    it again (linear interpolation, at the bins' centres): the cycle starts when
    activity resumes after the biggest burst has died down. For a burst that opens
    each cycle this is that burst's own onset; for a rig whose panels reset fast at the
    end of the ramp (a bigger burst than the ramp's), it is the rise after the reset.
    """
    prof = (np.roll(template, 1) + template + np.roll(template, -1)) / 3.0
    n = prof.size
    base = float(np.percentile(prof, 10))
    peak = int(np.argmax(prof))
    top = float(prof[peak])
    plateau = float(np.median(prof[prof > base + 0.5 * (top - base)]))
    level = base + ONSET_FRACTION * (plateau - base)
    i = peak
    fell = False
    for _ in range(2 * n):
        j = i + 1
        if not fell:
            fell = prof[j % n] < level
        elif prof[j % n] >= level:
            lo, hi = prof[i % n], prof[j % n]
            frac = (level - lo) / (hi - lo) if hi > lo else 0.0
            onset = i + frac + 0.5
            return onset - n if onset >= n else onset
        i = j
    return _crossing(prof, level, peak) + 0.5


def _fold(counts: np.ndarray, bin_us: float, period_us: float, offset_us: float) -> np.ndarray:
    """Mean counts per phase bin over one period; phase 0 at ``offset_us`` from bin 0's start."""
    if not (math.isfinite(period_us) and period_us > 0 and math.isfinite(offset_us)):
        raise ValueError(f"cycles_from_rate: no period to fold the event rate by "
                         f"(period {period_us:g} µs, offset {offset_us:g} µs)")
    nf = max(8, round(period_us / bin_us))
    centers = (np.arange(counts.size) + 0.5) * bin_us - offset_us
    ph = np.floor(np.mod(centers, period_us) / period_us * nf).astype(np.int64)
    ph = np.minimum(ph, nf - 1)
    s = np.bincount(ph, weights=counts, minlength=nf)
    c = np.bincount(ph, minlength=nf)
    return s / np.maximum(c, 1)


def _robust_line(
    k: np.ndarray, y: np.ndarray, slope: float | None
) -> tuple[float, float, np.ndarray]:
    """Fit ``y = a + b k`` (``b`` fixed when ``slope`` is given), dropping points off the
    line by more than 4 × the median absolute residual (twice). Returns a, b, inlier mask."""
    keep = np.ones(k.size, dtype=bool)
    a, b = 0.0, 0.0 if slope is None else slope
    for _ in range(3):
        kk, yy = k[keep], y[keep]
        if slope is None and kk.size >= 2:
            b, a = (float(v) for v in np.polyfit(kk, yy, 1))
        else:
            b = float(slope) if slope is not None else b
            a = float(np.median(yy - b * kk))
        r = y - (a + b * k)
        mad = float(np.median(np.abs(r[keep]))) if keep.any() else 0.0
        new = np.abs(r) <= max(4.0 * 1.4826 * mad, 1e-9)
        if new.sum() < max(2, keep.sum() // 2) or np.array_equal(new, keep):
            break
        keep = new
    return a, b, keep


def cycles_from_rate(
    counts: np.ndarray,
    *,
    bin_us: float,
    t0_us: int,
    period_us: float | None = None,
    period_range_us: tuple[float, float] = DEFAULT_PERIOD_RANGE_US,
    refine_period: bool | None = None,
) -> Cycles:
    """Cycle starts from an event-rate histogram (``counts[i]`` events in
    ``[t0_us + i*bin_us, t0_us + (i+1)*bin_us)``).

    1. Period ``P``: ``period_us`` or :func:`estimate_period_from_rate`.
    2. Template: the counts folded modulo ``P`` (mean per phase bin); its burst onset
       ``phi``: where the rising rate crosses 10 % of the way from the baseline to the
       burst's plateau (the cycle starts when the rate rises).
    3. Each cycle ``k``: the lag that maximises the cross-correlation of the counts
       with the mean-removed template, searched within ``P/4`` of the prediction and
       refined by a parabola; onset ``o_k = lag_k + phi``. Cycles whose correlation
       peak is below a quarter of the median are reported in ``missing``.
    4. A robust line ``o_k = a + b k`` gives ``P = b`` and the starts
       ``a + b k`` within the histogram's span. Steps 2-4 run twice, the second time
       with the refined period.

    ``refine_period`` (default: only when ``period_us`` is None) lets the line fit
    change the period; otherwise ``b = P`` is kept fixed and only the phase is fitted.

    Raises ``ValueError`` when the bins are too coarse (fewer than 8 per period) or
    the recording holds fewer than two periods.
    """
    x = np.asarray(counts, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"cycles_from_rate: counts must be 1-D, got shape {x.shape}")
    if not bin_us > 0:
        raise ValueError(f"cycles_from_rate: bin_us must be positive, got {bin_us}")
    strength = 1.0
    given = period_us is not None
    if period_us is None:
        p, strength = estimate_period_from_rate(x, bin_us=bin_us, period_range_us=period_range_us)
    else:
        if not (np.isfinite(period_us) and period_us > 0):
            raise ValueError(f"cycles_from_rate: period_us must be positive, got {period_us}")
        p = float(period_us)
    if p / bin_us < 8:
        raise ValueError(
            f"cycles_from_rate: bins of {bin_us:g} µs are too coarse for a period of "
            f"{p:.1f} µs (need at least 8 bins per period)"
        )
    span_us = x.size * bin_us
    if span_us < 2 * p:
        raise ValueError(
            f"cycles_from_rate: the recording spans {span_us:.0f} µs, less than two "
            f"periods of {p:.1f} µs"
        )
    fixed = not (refine_period if refine_period is not None else not given)
    a_us = 0.0  # phase-0 reference of the template, µs from t0
    res: dict[str, Any] = {}
    for _ in range(2):
        tmpl = _fold(x, bin_us, p, a_us)
        nf = tmpl.size
        tbin = p / nf  # template bin width (µs)
        onset_bins = _template_onset(tmpl)
        phi_us = onset_bins * tbin
        # Resample the template at the histogram's bin width, for correlation.
        m = round(p / bin_us)
        tz = np.interp((np.arange(m) + 0.5) * bin_us, (np.arange(nf) + 0.5) * tbin, tmpl,
                       period=p)
        tz = tz - tz.mean()
        if not np.any(tz):
            raise ValueError("cycles_from_rate: the folded event rate is flat; no bursts found")
        nc = x.size - m + 1
        nfft = 1 << int(np.ceil(np.log2(x.size + m)))
        corr = np.fft.irfft(np.fft.rfft(x, nfft) * np.conj(np.fft.rfft(tz, nfft)), nfft)[:nc]
        # Cycle k's template start: a_us + k p (µs from t0); keep those inside corr.
        k_lo = int(np.ceil((0 - a_us) / p))
        k_hi = int(np.floor(((nc - 1) * bin_us - a_us) / p))
        ks, lags, peaks = [], [], []
        half = max(1, int(p / 4 / bin_us))
        for k in range(k_lo, k_hi + 1):
            c = (a_us + k * p) / bin_us
            i0, i1 = max(0, round(c) - half), min(nc - 1, round(c) + half)
            if i1 - i0 < 2:
                continue
            j = i0 + int(np.argmax(corr[i0 : i1 + 1]))
            lag = float(j)
            if 0 < j < nc - 1:
                y0, y1, y2 = corr[j - 1], corr[j], corr[j + 1]
                den = y0 - 2 * y1 + y2
                if den < 0:
                    lag += float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5))
            ks.append(k)
            lags.append(lag * bin_us)
            peaks.append(corr[j])
        if len(ks) < 2:
            raise ValueError("cycles_from_rate: fewer than two whole cycles to measure")
        ka = np.array(ks, dtype=np.float64)
        la = np.array(lags)
        pk = np.array(peaks)
        strong = pk >= 0.25 * float(np.median(pk))
        a_fit, b_fit, inl = _robust_line(ka[strong], la[strong], p if fixed else None)
        if not (math.isfinite(b_fit) and b_fit > 0 and math.isfinite(a_fit)):
            raise ValueError("cycles_from_rate: the cycles' onsets fit no period "
                             f"(fitted {b_fit:g} µs)")
        p = b_fit
        a_us = a_fit  # template phase-0 of cycle k = a_us + k p
        res = {"phi_us": phi_us, "tmpl": tmpl, "ka": ka, "la": la, "strong": strong,
               "inl": inl}
    phi_us = res["phi_us"]
    tmpl = res["tmpl"]
    ka, la, strong, inl = res["ka"], res["la"], res["strong"], res["inl"]
    onset0 = a_us + phi_us  # µs from t0: start of cycle k = onset0 + k p
    # Starts within the histogram's span. A cycle whose first events open the recording
    # starts a little before the first event (the sensor needs time to reach its first
    # threshold): a start up to a tenth of the period before the first bin is kept.
    k_first = int(np.ceil((-max(bin_us, 0.1 * p) - onset0) / p))
    k_last = int(np.floor((span_us - onset0) / p))
    kk = np.arange(k_first, k_last + 1)
    starts = int(t0_us) + np.rint(onset0 + kk * p).astype(np.int64)
    weak_k = ka[~strong]
    missing = int(t0_us) + np.rint(onset0 + weak_k * p).astype(np.int64)
    resid = la[strong][inl] - (a_us + p * ka[strong][inl])
    rms = float(np.sqrt(np.mean(resid ** 2))) if resid.size else p
    base = float(np.percentile(tmpl, 10))
    top = float(tmpl.max())
    contrast = (top - base) / (top + base) if top + base > 0 else 0.0
    found = float(inl.sum()) / float(ka.size)
    conf = contrast * found / (1.0 + (rms / (0.01 * p)) ** 2)
    if not given:
        conf *= max(strength, 0.0) ** 0.25
    conf = float(np.clip(conf, 0.0, 1.0))
    if missing.size:
        # Missing bursts matter when the modulation is clear; otherwise they are noise.
        logger.log(logging.WARNING if conf >= 0.5 else logging.INFO,
                   "cycles from the event rate: no clear burst in %d cycle(s), at %s µs",
                   missing.size, missing[:5].tolist())
    logger.info("cycles from the event rate: period %.3f µs, %d cycles, confidence %.2f",
                p, starts.size, conf)
    return Cycles(start_us=starts, period_us=float(p), source="event_rate", confidence=conf,
                  missing=missing)


def cycles_from_events(
    events: np.ndarray,
    *,
    period_us: float | None = None,
    period_range_us: tuple[float, float] = DEFAULT_PERIOD_RANGE_US,
    bin_us: float | None = None,
) -> Cycles:
    """Cycle starts from the event-rate envelope of a recording without triggers.

    The events are sorted stably by time (how many moved is logged). Without
    ``period_us``, the period is first estimated from the autocorrelation of the
    rate binned at ``period_range_us[0] / 20`` (coarser when the recording would need
    more than 2^23 bins). The rate is then binned at ``bin_us`` (default ``P / 200``,
    at least 1 µs) and passed to :func:`cycles_from_rate`, whose line fit over the
    cycles' burst onsets refines the period to a fraction of a bin.

    Parameters
    ----------
    events : array of ``EVENT_DTYPE``.
    period_us : the modulation period (µs), when known; it is then kept fixed.
    period_range_us : (low, high) search range for the period, µs.
    bin_us : width of the rate bins for the phase (µs).
    """
    validate_events(events, require_sorted=False)
    if events.size == 0:
        raise ValueError("cycles_from_events: no events")
    ev, moved = sort_events(events)
    if moved:
        logger.info("cycles_from_events: %d events moved when sorting by time", moved)
    t = ev["t"]
    t0 = int(t[0])
    span = int(t[-1]) - t0 + 1
    p0 = period_us
    if p0 is None:
        coarse = max(1.0, float(period_range_us[0]) / 20.0, span / float(1 << 23))
        p0, _ = estimate_period_from_rate(event_rate(t, bin_us=coarse, t0_us=t0),
                                          bin_us=coarse, period_range_us=period_range_us)
    fine = float(bin_us) if bin_us is not None else max(1.0, p0 / 200.5)
    counts = event_rate(t, bin_us=fine, t0_us=t0)
    return cycles_from_rate(counts, bin_us=fine, t0_us=t0, period_us=p0,
                            refine_period=period_us is None)


# --------------------------------------------------------------------------- the policy


class NoCyclesError(ValueError):
    """No modulation cycles were found; ``reason`` says why (and :func:`find_cycles`'s
    message what to give instead: the period, or the whole recording as one ramp)."""

    def __init__(self, name: str, reason: str, *, period_given: bool) -> None:
        self.reason = reason
        hint = ("treat the recording as one ramp (single=True)" if period_given else
                "give the modulation period (period_us) or treat the recording as one ramp "
                "(single=True)")
        super().__init__(f"{name}: no cycles found: {reason}; {hint}")


def _coverage(source: Source, starts: np.ndarray, stops: np.ndarray) -> float:
    """Median over (up to 16, evenly spread) cycles of the fraction of the pixels active
    in any of them that fire in that cycle. The panels modulate every pixel each cycle,
    so a modulated recording scores near 1; bursts of a few pixels (a frame readout, a
    flicker on part of the scene) score low."""
    n = starts.size
    pick = np.unique(np.linspace(0, n - 1, min(n, 16)).round().astype(np.int64))
    w = int(source.width)
    seen: list[np.ndarray] = []
    for win in source.windows(starts[pick], stops[pick]):
        ev = win.events
        seen.append(np.unique(ev["y"].astype(np.int64) * w + ev["x"]))
    union = np.unique(np.concatenate(seen)) if seen else np.zeros(0, np.int64)
    if union.size == 0:
        return 0.0
    return float(np.median([s.size / union.size for s in seen]))


def _rig_cycles(metadata: dict[str, Any]) -> Cycles | None:
    """The cycles a simulated recording was made with (its rig, cycle count, start)."""
    rig = metadata.get("rig")
    if not isinstance(rig, dict) or "period_us" not in rig or "n_cycles" not in metadata:
        return None
    period = float(rig["period_us"])
    n = int(metadata["n_cycles"])
    t0 = int(metadata.get("t0_us", 0))
    return Cycles(start_us=t0 + np.arange(n, dtype=np.int64) * round(period),
                  period_us=period, source="rig", confidence=1.0)


def find_cycles(
    source: Source | Recording,
    *,
    period_us: float | None = None,
    channel: int | None = None,
    period_range_us: tuple[float, float] = DEFAULT_PERIOD_RANGE_US,
    min_confidence: float = MIN_RATE_CONFIDENCE,
    progress: Progress | None = None,
) -> Cycles:
    """The modulation cycles of a recording: the one policy every command follows.

    1. Trigger edges, when the recording has rising ones (readers keep only the
       external-input kind: an AEDAT file's frame markers are not edges): the channel
       with most rising edges (or ``channel``), :func:`cycles_from_triggers`.
    2. Else, for a simulated recording, the rig's own cycles (its metadata; its period
       also serves the trigger edges when ``period_us`` is not given).
    3. Else the event-rate envelope (:func:`cycles_from_rate` on the recording's rate,
       binned first at ``period_range_us[0] / 20`` to find the period, then at
       ``P / 200``), its confidence multiplied by the pixel coverage (the median
       fraction of the active pixels that fire in a cycle: the panels make every pixel
       fire each cycle). Below ``min_confidence``, or with a coverage below
       :data:`MIN_COVERAGE`, there are no cycles.

    ``warmup`` is 1 when the recording holds no event from before its first cycle (none
    earlier than a tenth of a period before its start): the modulation starts with the
    recording, its pixels start adapted to the light before it rather than to the end of
    a cycle, and a static scene's first image differs from the others (in a simulation,
    whose pixels start adapted to the cycle's first light, it is brighter).

    Raises :class:`NoCyclesError` (a ``ValueError``) saying why when none are found.
    """
    src = as_source(source)
    name = src.name
    tr = src.triggers
    rising = tr[tr["rising"]] if tr.size else tr
    notes: list[str] = [] if rising.size else ["no trigger edges"]
    rig = _rig_cycles(src.metadata)
    cyc: Cycles | None = None
    if rising.size:
        ids, counts = np.unique(rising["id"], return_counts=True)
        ch = int(ids[int(np.argmax(counts))]) if channel is None else int(channel)
        try:
            cyc = cycles_from_triggers(tr, channel=ch, period_us=period_us or (
                rig.period_us if rig is not None else None))
        except ValueError as exc:
            notes.append(f"trigger edges not usable ({exc})")
    if cyc is None and rig is not None:
        cyc, notes = rig, []
    scan = src.scan(progress=progress)
    if cyc is None:
        if scan.events == 0:
            raise NoCyclesError(name, "; ".join([*notes, "no events"]),
                                period_given=period_us is not None)
        t0 = int(scan.min_t_us)  # type: ignore[arg-type]
        span = int(scan.max_t_us) - t0 + 1  # type: ignore[arg-type]

        def histogram(b: float) -> np.ndarray:
            return src.event_rate(bin_us=b, t0_us=t0, n_bins=math.floor((span - 1) / b) + 1,
                                  progress=progress)

        try:
            p0 = period_us
            if p0 is None:
                coarse = max(1.0, float(period_range_us[0]) / 20.0, span / float(1 << 23))
                p0, _ = estimate_period_from_rate(histogram(coarse), bin_us=coarse,
                                                  period_range_us=period_range_us)
            fine = max(1.0, p0 / 200.5)
            cyc = cycles_from_rate(histogram(fine), bin_us=fine, t0_us=t0, period_us=p0,
                                   refine_period=period_us is None)
        except ValueError as exc:
            raise NoCyclesError(name, "; ".join([*notes, f"none from the event rate ({exc})"]),
                                period_given=period_us is not None) from None
        cover = _coverage(src, cyc.start_us, cyc.stop_us)
        conf = cyc.confidence * cover
        logger.info("%s: cycles from the event rate: period %.1f µs, burst confidence %.2f, "
                    "pixel coverage %.2f", name, cyc.period_us, cyc.confidence, cover)
        if conf < min_confidence or cover < MIN_COVERAGE:
            raise NoCyclesError(
                name, "; ".join([*notes, (
                    f"no modulation in the event rate (best guess: period "
                    f"{cyc.period_us:.1f} µs, confidence {conf:.2f}: burst regularity "
                    f"{cyc.confidence:.2f} x pixel coverage {cover:.2f}; needed: confidence "
                    f">= {min_confidence:g} and coverage >= {MIN_COVERAGE:g})")]),
                period_given=period_us is not None)
        cyc = replace(cyc, confidence=conf)
        if rising.size:
            logger.warning("%s: %s; cycles from the event rate instead", name, "; ".join(notes))
    if scan.events and len(cyc) and (int(scan.min_t_us)  # type: ignore[arg-type]
                                     >= int(cyc.start_us[0]) - 0.1 * cyc.period_us):
        cyc = replace(cyc, warmup=1)
    return cyc


# --------------------------------------------------------------------------- splitting


def split_cycles(events: np.ndarray, cycles: Cycles) -> list[tuple[int, int]]:
    """``(start index, stop index)`` of each cycle's events: cycle ``i`` holds the
    events with ``start_us[i] <= t < stop_us[i]``.

    Indices refer to the events sorted stably by time, that is to
    ``asynhdr.events.sort_events(events)[0]``, which is ``events`` itself when it is
    already sorted; when events had to move, how many is logged.
    """
    validate_events(events, require_sorted=False)
    ev, moved = sort_events(events)
    if moved:
        logger.info("split_cycles: events are not sorted by time; %d moved when sorted "
                    "stably (indices refer to the sorted events)", moved)
    t = ev["t"]
    a = np.searchsorted(t, cycles.start_us, side="left")
    b = np.searchsorted(t, cycles.stop_us, side="left")
    return [(int(i), int(j)) for i, j in zip(a, b, strict=True)]
