"""Rig design for dynamic range: the modulation that lets ``ml`` measure the widest range.

What the rig sets (Wu et al. 2024 leave it to the builder):

- a pixel of radiance ``L`` sees ``V(t) = ln(k (T1(t) L + T2(t) L_const))``; it tells its
  radiance through the instant where the two terms cross, ``T1 L = T2 L_const``. That
  instant exists for ``L`` between ``L_const T2_end / T1_end`` and ``L_const T2_0 / T1_0``:
  about ``CR_2`` below and ``CR_1`` above ``L_const`` (the panels' contrast ratios), a
  range of ``CR_1 CR_2`` (120 dB for two 1000:1 panels) before the margins;
- with the paper's linear ramps and the reference stopping half way (``t2_stop = 0.5``) a
  pixel at ``0.5 L_const`` sees constant irradiance (``rho dT1 + dT2 = 0``) and fires
  nothing: a blind band in the middle of the range; and pixels darker than
  ``L_const T2_end`` never cross;
- the photoreceptor is slow in the dark (``tau ~ 1 / I``): the crossing must happen when
  the pixel gets as much light as it can.

The family designed here, ``sequential``, meets all three: over ``[0, a]`` the scene panel
opens log-linearly from its floor to fully open (``T2 = 1``): pixels brighter than
``L_const`` cross, at irradiance ``2 k L_const``; over ``[a, b]`` the reference closes
log-linearly to its floor (``T1 = 1``): darker pixels cross, at irradiance ``2 k L`` (the
most a pixel can get); over ``[b, R]`` both hold, so the slow dark pixels settle; then
both return. Every pixel's signal moves by at least ``ln 2`` each way: no blind band.
The paper's rule ``|dT2/dt| < |dT1/dt|`` is not kept (``T1`` is still while ``T2``
falls): with ``ml`` it is unnecessary, and ``asynhdr design --compare`` measures the
rule-keeping rig (linear ramps, ``t2_stop = 0.5``) beside it.

The family ``round_trip`` goes there and back within the cycle: the sequential ramps over
``[0, a]`` and ``[a, b]``, then the same in reverse (the reference reopens over
``[b, 2b - a]``, the scene panel closes over ``[2b - a, 2b]``), then holds where it
started; ``two_round_trips`` makes that trip twice, back to back. A pixel tells ``ln L``
only near a crossing of the two terms: elsewhere ``V`` follows ``ln T1 + ln L`` or
``ln T2 + ln L_const``, and the DVS, which sees changes of ``V``, sees no ``L`` in them. A
crossing gives a few events whose reset noise sets the error of ``ln L``, so ``n``
crossings per cycle divide its variance by about ``n``: the round trip crosses twice, two
round trips four times, for twice and four times the events of a one-way ramp (the
readout's load and ``ml``'s time) and shorter ramps (the photoreceptor's settling). The
cycle ends where it began, so there is no return to hide.

:func:`design` searches ``L_const``, the split ``a``, the end of the reference's ramp ``b``
and its floor for the longest run of radiance levels whose predicted per-pixel SNR
(``-20 log10(sigma_ln L)``, ``sigma`` the Cramér-Rao bound of :mod:`asynhdr.ml` on the
noiseless events of the sensor preset, with the spread the readout's queue adds) is at
least ``min_snr_db`` and whose estimate the readout's queue biases by at most
:data:`MAX_BIAS` (:func:`predict`: the array's share of the readout, with a quarter of the
array at one radiance), over the families; the cycle
length is the frame rate's period. Between rigs of equal range, those whose mean SNR over
the run reaches ``mean_snr_db`` (:data:`DEFAULT_MEAN_SNR_DB`) win, among them the simplest
family (sequential, round trip, two round trips), then the higher mean SNR; if none
reaches it, the highest mean SNR wins. Round trips cost events (the readout and ``ml``'s
time), and the paper's weightings and c-map lose their meaning on them (their net swing
over the cycle is zero), so the sequential rig is kept wherever it is good enough.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from asynhdr.rig import Rig, Waveform
from asynhdr.sensor.params import SensorParams, get_preset

__all__ = [
    "DEFAULT_FRAME_RATE_HZ",
    "DEFAULT_MARGIN_DB",
    "DEFAULT_MEAN_SNR_DB",
    "DEFAULT_SCENE_RANGE",
    "DESIGNED",
    "FAMILIES",
    "MAX_BIAS",
    "SPLITS",
    "UNIFORM_SHARE",
    "DesignResult",
    "Prediction",
    "default_rig",
    "design",
    "predict",
    "reference_radiances",
    "round_trip_rig",
    "sequential_rig",
    "two_round_trips_rig",
]

logger = logging.getLogger(__name__)

DEFAULT_FRAME_RATE_HZ = 20.0
"""The paper's 20 cycles per second."""

DEFAULT_SCENE_RANGE = (0.1, 10 ** 5.5)
"""Radiance range (lux) the designs are made for: 0.1 to 316,000 lux (132 dB)."""

DEFAULT_MIN_SNR_DB = 20.0
"""Per-pixel SNR a level needs to count in the predicted range."""

DEFAULT_MARGIN_DB = 1.5
"""How far above ``min_snr_db`` a level's predicted SNR must be to count in the range
:func:`design` ranks rigs by first. The prediction is the bound's median over a few
pixels; a capture's per-pixel SNR over a patch scatters about it: a patch of 256 pixels
measures its standard deviation to ``1 / sqrt(2 x 256)``, 0.38 dB, and a new capture is
another draw of the sensor's mismatch too (on the IMX636 chart, ten captures of a level
predicted at 19.7 dB read 19.3 to 20.7 dB: docs/ml.md). A rig whose range ends on the
line keeps its end level in only some captures; 1.5 dB is about four such standard
errors. The range at ``min_snr_db`` itself settles a tie, and is the one printed as the
predicted range."""

DEFAULT_MEAN_SNR_DB = 30.0
"""The mean per-pixel SNR over the range a design aims for (a standard deviation of about
3 % in ``L``): between rigs of equal range, the simplest that reaches it is kept
(:func:`design`)."""

UNIFORM_SHARE = 0.25
"""The share of the array at one radiance the readout must carry in a design's prediction
(:func:`predict`): a quarter of the image on a dark surround or a sky."""

MAX_BIAS = 0.05
"""The largest error in ``ln L`` (about 5 %) the readout's queue may make at a level that
counts in the predicted range."""

RAMP_FRACTION = 0.9
"""The part of the cycle the designed rigs integrate (ramps and hold); the rest returns."""

REFINE_ROUNDS = 2
"""After the grid, :func:`design` tries the best rig's ``L_const`` halfway (in log) to its
neighbours on either side, then halfway again: the grid's step shrinks fourfold."""

MAX_EXTEND = 2
"""Steps :func:`design` takes beyond the ``L_const`` grid's end while the best rig sits
there."""

N_KNOTS = 512
"""Knots per log-linear ramp: within 2e-5 (relative) of the exact exponential."""


def sequential_rig(*, period_us: int, l_const: float, a: float, b: float,
                   floor_1: float = 1e-3, floor_2: float = 1e-3, k_lens: float = 1.0,
                   ramp_fraction: float = RAMP_FRACTION, n_knots: int = N_KNOTS) -> Rig:
    """The ``sequential`` rig of the module docstring: ``T1`` log-linear from ``floor_1`` to
    1 over phase ``[0, a]`` (``T2 = 1``); ``T2`` log-linear from 1 to ``floor_2`` over
    ``[a, b]`` (``T1 = 1``); hold to ``ramp_fraction``; return over half the rest; hold."""
    if not 0.0 < a < b <= ramp_fraction < 1.0:
        raise ValueError(f"sequential rig: need 0 < a < b <= ramp_fraction < 1, got a={a}, "
                         f"b={b}, ramp_fraction={ramp_fraction}")
    s = np.linspace(0.0, 1.0, n_knots + 1)
    ph = [s * a, a + s[1:] * (b - a)]
    v1 = [floor_1 ** (1.0 - s), np.ones(n_knots)]
    v2 = [np.ones(n_knots + 1), floor_2 ** s[1:]]
    settle = ramp_fraction + 0.5 * (1.0 - ramp_fraction)
    tail = [ramp_fraction, settle, 1.0] if b < ramp_fraction else [settle, 1.0]
    ph.append(np.array(tail))
    v1.append(np.array([1.0, floor_1, floor_1][-len(tail):]))
    v2.append(np.array([floor_2, 1.0, 1.0][-len(tail):]))
    w1 = Waveform(np.concatenate(ph), np.concatenate(v1), name=f"sequential T1 {floor_1:g}->1")
    w2 = Waveform(np.concatenate(ph), np.concatenate(v2), name=f"sequential T2 1->{floor_2:g}")
    return Rig(period_us=int(period_us), ramp_fraction=ramp_fraction, l_const=float(l_const),
               k_lens=k_lens, contrast_ratio_1=1.0 / floor_1, contrast_ratio_2=1.0 / floor_2,
               t1=w1, t2=w2)


def round_trip_rig(*, period_us: int, l_const: float, a: float, b: float,
                   floor_1: float = 1e-3, floor_2: float = 1e-3, k_lens: float = 1.0,
                   ramp_fraction: float = RAMP_FRACTION, n_knots: int = N_KNOTS,
                   trips: int = 1) -> Rig:
    """The ``round_trip`` rig of the module docstring: the sequential ramps over ``[0, a]``
    and ``[a, b]``, the same in reverse over ``[b, 2b]``, then a hold at the start.
    ``trips`` > 1 repeats the trip back to back (trip ``j`` over ``[2bj, 2b(j + 1)]``): every
    pixel crosses ``2 trips`` times per cycle."""
    if int(trips) != trips or trips < 1:
        raise ValueError(f"round-trip rig: trips must be a whole number >= 1, got {trips}")
    trips = int(trips)
    if not (0.0 < a < b and 2.0 * b * trips <= ramp_fraction < 1.0):
        raise ValueError(f"round-trip rig: need 0 < a < b and 2 b trips <= ramp_fraction < 1, "
                         f"got a={a}, b={b}, trips={trips}, ramp_fraction={ramp_fraction}")
    s = np.linspace(0.0, 1.0, n_knots + 1)[1:]
    c = 2.0 * b - a
    ph: list[np.ndarray] = [np.zeros(1)]
    v1: list[np.ndarray] = [np.full(1, floor_1)]
    v2: list[np.ndarray] = [np.ones(1)]
    for j in range(trips):
        o = 2.0 * b * j
        ph += [o + s * a, o + a + s * (b - a), o + b + s * (c - b), o + c + s * (2.0 * b - c)]
        v1 += [floor_1 ** (1.0 - s), np.ones(n_knots), np.ones(n_knots), floor_1 ** s]
        v2 += [np.ones(n_knots), floor_2 ** s, floor_2 ** (1.0 - s), np.ones(n_knots)]
    if 2.0 * b * trips < 1.0:
        ph.append(np.ones(1))
        v1.append(np.full(1, floor_1))
        v2.append(np.ones(1))
    times = "" if trips == 1 else f" x{trips}"
    w1 = Waveform(np.concatenate(ph), np.concatenate(v1),
                  name=f"round trip{times} T1 {floor_1:g}->1->{floor_1:g}")
    w2 = Waveform(np.concatenate(ph), np.concatenate(v2),
                  name=f"round trip{times} T2 1->{floor_2:g}->1")
    return Rig(period_us=int(period_us), ramp_fraction=ramp_fraction, l_const=float(l_const),
               k_lens=k_lens, contrast_ratio_1=1.0 / floor_1, contrast_ratio_2=1.0 / floor_2,
               t1=w1, t2=w2)


def two_round_trips_rig(**kwargs: Any) -> Rig:
    """The ``two_round_trips`` rig: :func:`round_trip_rig` with ``trips=2``."""
    return round_trip_rig(trips=2, **kwargs)


FAMILIES: dict[str, Callable[..., Rig]] = {"sequential": sequential_rig,
                                           "round_trip": round_trip_rig,
                                           "two_round_trips": two_round_trips_rig}
"""The rig families :func:`design` searches, by name (module docstring)."""

SPLITS: dict[str, tuple[tuple[float, float], ...]] = {
    "sequential": ((0.2, 0.55), (0.25, 0.65), (0.3, 0.8), (0.35, 0.9), (0.2, 0.9)),
    "round_trip": ((0.1, 0.35), (0.1, 0.45), (0.15, 0.4), (0.15, 0.45), (0.2, 0.45)),
    "two_round_trips": ((0.05, 0.2), (0.075, 0.2), (0.05, 0.225), (0.075, 0.225),
                        (0.1, 0.225)),
}
"""The phases ``(a, b)`` :func:`design` tries per family."""


@dataclass(frozen=True, eq=False)
class DesignResult:
    """A designed rig and what it is predicted to do.

    Attributes
    ----------
    rig : the rig.
    params : the design's parameters (``family``, ``l_const``, ``a``, ``b``, floors, period).
    prediction : what the rig is predicted to give at each level (:class:`Prediction`).
    range_db : the predicted dynamic range (the longest run of levels with
        ``snr_db >= min_snr_db`` and the readout's bias within :data:`MAX_BIAS`);
        ``l_lo``, ``l_hi`` its ends.
    margin_db, margin_range_db : the margin the design ranked by and the range with it
        (``snr_db >= min_snr_db + margin_db``).
    candidates : every candidate tried, with its range.
    """

    rig: Rig
    params: dict[str, Any]
    prediction: Prediction
    range_db: float
    l_lo: float
    l_hi: float
    min_snr_db: float
    sensor: SensorParams
    margin_db: float = 0.0
    margin_range_db: float = float("nan")
    candidates: list[dict[str, Any]] = field(default_factory=list)

    @property
    def levels(self) -> np.ndarray:
        return self.prediction.levels

    @property
    def snr_db(self) -> np.ndarray:
        return self.prediction.snr_db

    def summary(self) -> dict[str, Any]:
        pr = self.prediction
        return {"params": self.params, "range_db": self.range_db, "l_lo": self.l_lo,
                "l_hi": self.l_hi, "min_snr_db": self.min_snr_db, "margin_db": self.margin_db,
                "margin_range_db": self.margin_range_db, "sensor": self.sensor.name,
                "levels": pr.levels.tolist(), "snr_db": pr.snr_db.tolist(),
                "readout_bias": pr.bias.tolist(), "events_per_cycle": pr.events_per_cycle,
                "readout_load": pr.readout_load, "max_delay_us": pr.max_delay_us,
                "queue_sd": None if pr.queue_sd is None else pr.queue_sd.tolist(),
                "candidates": self.candidates}


def _preference(range_db: float, mean_snr: float, family_rank: int,
                mean_snr_db: float, margin_range_db: float | None = None,
                ) -> tuple[float, float, bool, float, float]:
    """How :func:`design` ranks a candidate (larger is better): the range with the margin
    (:data:`DEFAULT_MARGIN_DB`; ``margin_range_db``, the range itself where not given)
    first, then the range; between equal ranges, reaching ``mean_snr_db``, then the
    simpler family (``family_rank``, its place in :data:`FAMILIES`), then the higher mean
    SNR."""
    good = mean_snr >= mean_snr_db
    robust = range_db if margin_range_db is None else margin_range_db
    return (robust, range_db, good, -family_rank if good else mean_snr, mean_snr)


def _longest_run(levels: np.ndarray, ok: np.ndarray) -> tuple[float, float, float]:
    best = (0.0, float("nan"), float("nan"))
    i = 0
    n = ok.size
    while i < n:
        if not ok[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and ok[j + 1]:
            j += 1
        db = 20.0 * math.log10(levels[j] / levels[i]) if j > i else 0.0
        if db > best[0] or math.isnan(best[1]):
            best = (db, float(levels[i]), float(levels[j]))
        i = j + 1
    return best


@dataclass(frozen=True, eq=False)
class Prediction:
    """What a rig is predicted to give ``ml`` at each radiance of ``levels``.

    Attributes
    ----------
    snr_db : per-pixel SNR (dB): ``-20 log10`` of the standard deviation of ``ln L``, the
        median Cramér-Rao bound over the level's pixels and the queue's spread
        (``queue_sd``) added in quadrature; ``-inf`` where they fire fewer than two events.
    bias : ``ml``'s median error in ``ln L`` on the same noiseless events after the
        readout's queue, the larger of the two scenes of :func:`predict` (0 where the
        readout keeps up); NaN where it gives no estimate.
    queue_sd : the standard deviation over the level's pixels of that error (the
        readout's queue delays each pixel's events by its own amounts), the larger of the
        two scenes; 0 where the readout keeps up.
    events_per_cycle : events per pixel and cycle, the mean over the levels.
    readout_load : the array's mean event rate over the cycle as a fraction of its
        readout (0: no limit), with the levels spread evenly over the array.
    max_delay_us : the longest the readout's queue held an event (either scene).
    """

    levels: np.ndarray
    snr_db: np.ndarray
    bias: np.ndarray
    events_per_cycle: float
    readout_load: float
    max_delay_us: float
    queue_sd: np.ndarray | None = None

    def counts(self, min_snr_db: float, max_bias: float = MAX_BIAS) -> np.ndarray:
        """Levels that count in the range: SNR at least ``min_snr_db`` and ``|bias|`` at
        most ``max_bias``."""
        with np.errstate(invalid="ignore"):
            return (self.snr_db >= min_snr_db) & (np.abs(self.bias) <= max_bias)

    def run(self, min_snr_db: float) -> tuple[float, float, float, float]:
        """The predicted range: ``(dB, lowest level, highest level, mean SNR over it)``
        of the longest run of levels that count."""
        db, lo, hi = _longest_run(self.levels, self.counts(min_snr_db))
        inside = (self.levels >= lo) & (self.levels <= hi)
        return db, lo, hi, float(np.mean(self.snr_db[inside])) if db > 0 else 0.0


def predict(rig: Rig, sensor: SensorParams, *, levels: np.ndarray, pixels: int = 8,
            rng: int = 0, uniform_share: float = UNIFORM_SHARE) -> Prediction:
    """What ``ml`` is predicted to give at each radiance of ``levels``
    (:class:`Prediction`).

    The sensor fires without noise (reset noise, jitter and background off; its
    thresholds drawn with their mismatch) on ``pixels`` pixels per level. The SNR is the
    Cramér-Rao bound of those events with the noise of the real sensor in the model.

    The same events then pass the readout, the array's share for the pixels simulated
    (:meth:`SensorParams.readout`), in two scenes: the levels beside ``uniform_share`` of
    the array at the darkest level, and beside as much at the brightest (a dark surround,
    a sky: pixels of one radiance fire in the same instant, which loads the readout most).
    ``ml`` with the drawn thresholds estimates ``L`` from each scene's delayed events; a
    level's bias is the larger of its two errors. ``uniform_share`` 0: the levels alone,
    spread evenly over the array."""
    from asynhdr.ml import cached_model, estimate, fisher_information, thresholds_prior
    from asynhdr.sensor.noise import apply_arbiter
    from asynhdr.simulate import draw_thresholds, simulate

    if not 0.0 <= uniform_share < 1.0:
        raise ValueError(f"predict: uniform_share must be in [0, 1), got {uniform_share}")
    quiet = sensor.with_(name="quiet", reset_noise_sigma=0.0, jitter_sigma_us=0.0,
                         leak_rate_hz=0.0, shot_noise_rate_hz=0.0, hot_pixel_fraction=0.0,
                         dead_pixel_fraction=0.0, max_event_rate_hz=0.0)
    lv = np.asarray(levels, dtype=np.float64)
    n_lv = lv.size
    n_u = math.ceil(n_lv * uniform_share / (1.0 - uniform_share)) if uniform_share else 0
    # rows: the levels, then n_u rows at the darkest and n_u at the brightest level
    rows = np.concatenate([lv, np.full(n_u, lv.min()), np.full(n_u, lv.max())])
    scene = np.repeat(rows[:, None], pixels, axis=1)
    h, w = scene.shape
    c_on, c_off = draw_thresholds(sensor, width=w, height=h, rng=np.random.default_rng(rng))
    rec = simulate(scene, rig=rig, sensor=quiet, n_cycles=2, rng=rng,
                   thresholds=(c_on, c_off))
    model = cached_model(rig, sensor, window_us=rig.ramp_us)
    start = int(rig.period_us)
    ev = rec.events
    on_levels = ev["y"] < n_lv
    lv_ev = ev[on_levels]
    pri = thresholds_prior(sensor, width=w, height=n_lv, c_on=c_on[:n_lv], c_off=c_off[:n_lv],
                           sigma=0.002)
    sd = fisher_information(lv_ev, width=w, height=n_lv, start_us=start, model=model,
                            priors=pri, log_radiance=np.log(scene[:n_lv]))
    with np.errstate(invalid="ignore", divide="ignore"):
        med = np.nanmedian(np.where(np.isfinite(sd), sd, np.inf), axis=1)
    per_cycle = int(np.count_nonzero(lv_ev["t"] >= start)) / (n_lv * w)
    rate, _ = sensor.readout(n_lv * w)
    load = per_cycle * 1e6 / rig.period_us / rate * (n_lv * w) if rate > 0 else 0.0
    bias = np.zeros(n_lv)
    spread = np.zeros(n_lv)
    max_delay = 0.0
    # the scenes: (rows of the uniform part, in the recording)
    parts = [(n_lv, n_lv + n_u), (n_lv + n_u, n_lv + 2 * n_u)] if n_u else [(n_lv, n_lv)]
    for lo, hi in parts:
        keep = on_levels | ((ev["y"] >= lo) & (ev["y"] < hi))
        sub = ev[keep].copy()
        sub["y"] = np.where(sub["y"] >= lo, sub["y"] - (lo - n_lv), sub["y"])
        hh = n_lv + (hi - lo)
        delayed, stats = apply_arbiter(sub, sensor, n_pixels=hh * w)
        max_delay = max(max_delay, float(stats.max_delay_us))
        if not stats.delayed:
            continue
        idx = np.r_[0:n_lv, lo:hi]
        pri_s = thresholds_prior(sensor, width=w, height=hh, c_on=c_on[idx], c_off=c_off[idx],
                                 sigma=0.002)
        # each row one level, their medians compared: no neighbours' starts
        res = estimate(delayed, width=w, height=hh, starts_us=np.array([start]), model=model,
                       priors=pri_s, neighbours=False)
        err = np.log(res.radiance[0][:n_lv].astype(np.float64)) - np.log(scene[:n_lv])
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(err).all(axis=1)
            b = np.where(ok, np.median(err, axis=1), np.nan)
            bias = np.where(np.isnan(b) | (np.abs(b) > np.abs(bias)), b, bias)
            # the noiseless events' own error is the bound's order or less: their spread
            # over the pixels is what the queue adds
            q = np.where(ok, np.std(err, axis=1, ddof=1), 0.0)
            spread = np.maximum(spread, q)
    with np.errstate(invalid="ignore", divide="ignore"):
        total = np.sqrt(med ** 2 + spread ** 2)
        snr = np.where(np.isfinite(total), -20.0 * np.log10(total), -np.inf)
    return Prediction(levels=lv, snr_db=snr, bias=bias, events_per_cycle=float(per_cycle),
                      readout_load=float(load), max_delay_us=max_delay, queue_sd=spread)


def reference_radiances(l_min: float, l_max: float, contrast_ratio: float,
                        n: int = 12) -> list[float]:
    """The ``L_const`` values :func:`design` tries by default: ``n``, geometric, from a
    tenth of the smaller to ten times the larger of ``l_min x contrast_ratio`` (the
    brightest reference the darkest level still crosses, ``L_const T2_floor = l_min``) and
    ``l_max / contrast_ratio`` (the darkest reference the brightest level crosses,
    ``l_max T1_floor = L_const``). A scene wider than the panels' two ratios cannot have
    both; the search lets it favour either end."""
    ends = (l_min * contrast_ratio, l_max / contrast_ratio)
    return [float(x) for x in np.geomspace(min(ends) / 10.0, max(ends) * 10.0, n)]


def design(
    sensor: SensorParams | str,
    *,
    l_min: float = DEFAULT_SCENE_RANGE[0],
    l_max: float = DEFAULT_SCENE_RANGE[1],
    frame_rate_hz: float = DEFAULT_FRAME_RATE_HZ,
    contrast_ratio: float = 1000.0,
    min_snr_db: float = DEFAULT_MIN_SNR_DB,
    mean_snr_db: float = DEFAULT_MEAN_SNR_DB,
    margin_db: float = DEFAULT_MARGIN_DB,
    l_consts: Sequence[float] | None = None,
    families: Sequence[str] = tuple(FAMILIES),
    n_levels: int = 27,
    progress: Callable[[int, int], None] | None = None,
) -> DesignResult:
    """Choose the rig (of ``families``, module docstring) with the widest predicted range
    with ``margin_db`` to spare, then the widest at ``min_snr_db``; between equal ranges,
    the simplest that reaches ``mean_snr_db``.

    Parameters
    ----------
    sensor : the pixel model (a preset name or parameters).
    l_min, l_max : the scene's radiance range (the rig's unit, lux).
    frame_rate_hz : cycles per second; the cycle is ``1e6 / frame_rate_hz`` µs.
    contrast_ratio : both panels' open/closed ratio (their floors are its inverse).
    min_snr_db : per-pixel SNR a level needs to count.
    mean_snr_db : the mean SNR over the range that settles a tie of ranges (module
        docstring).
    margin_db : how far above ``min_snr_db`` a level must be predicted to count in the
        range ranked first (:data:`DEFAULT_MARGIN_DB`; 0: no margin).
    l_consts : reference radiances tried (default: :func:`reference_radiances`).
    families : rig families tried (:data:`FAMILIES`), each over its :data:`SPLITS`.
    n_levels : radiances evaluated, log-spaced over ``[l_min, l_max]``.
    """
    sensor = get_preset(sensor) if isinstance(sensor, str) else sensor
    if not (0 < l_min < l_max and math.isfinite(l_max)):
        raise ValueError(f"design: need 0 < l_min < l_max, got {l_min}, {l_max}")
    if not (frame_rate_hz > 0 and math.isfinite(frame_rate_hz)):
        raise ValueError(f"design: frame_rate_hz must be positive, got {frame_rate_hz}")
    unknown = [f for f in families if f not in FAMILIES]
    if unknown or not families:
        raise ValueError(f"design: unknown rig families {unknown}; expected some of "
                         f"{list(FAMILIES)}")
    period = round(1e6 / frame_rate_hz)
    levels = np.geomspace(l_min, l_max, n_levels)
    if not (margin_db >= 0 and math.isfinite(margin_db)):
        raise ValueError(f"design: margin_db must be >= 0, got {margin_db}")
    if l_consts is None:
        l_consts = reference_radiances(l_min, l_max, contrast_ratio)
    floor = 1.0 / contrast_ratio
    tried: list[dict[str, Any]] = []
    best: tuple[tuple[float, float, bool, float, float], Rig, dict[str, Any],
                Prediction] | None = None
    n_grid = len(l_consts) * sum(len(SPLITS[f]) for f in families)
    total = n_grid + 2 * REFINE_ROUNDS

    def consider(family: str, lc: float, a: float, b: float) -> None:
        nonlocal best
        rig = FAMILIES[family](period_us=period, l_const=lc, a=a, b=b, floor_1=floor,
                               floor_2=floor)
        pred = predict(rig, sensor, levels=levels)
        db, _, _, mean_snr = pred.run(min_snr_db)
        db_m = pred.run(min_snr_db + margin_db)[0]
        params: dict[str, Any] = {"family": family, "l_const": lc, "a": a, "b": b,
                                  "floor_1": floor, "floor_2": floor,
                                  "period_us": float(period)}
        tried.append(dict(params, range_db=db, margin_range_db=db_m, mean_snr_db=mean_snr,
                          events_per_cycle=pred.events_per_cycle,
                          readout_load=pred.readout_load, max_delay_us=pred.max_delay_us))
        key = _preference(db, mean_snr, list(FAMILIES).index(family), mean_snr_db, db_m)
        if best is None or key > best[0]:
            best = (key, rig, params, pred)
        if progress is not None:
            progress(len(tried), max(total, len(tried)))
        logger.info("design %s: %s L_const %.4g a %.2f b %.2f -> %.1f dB (%.1f dB with the "
                    "margin), mean SNR %.1f dB, readout load %.2f", sensor.name, family, lc,
                    a, b, db, db_m, mean_snr, pred.readout_load)

    for family in families:
        for lc in l_consts:
            for a, b in SPLITS[family]:
                consider(family, lc, a, b)
    # the best family and split, L_const refined: beyond the grid's end while the best
    # sits there, then halfway to the neighbours on either side, twice
    assert best is not None
    grid = np.log(np.sort(np.asarray(l_consts, dtype=np.float64)))
    step = float(np.min(np.diff(grid))) if grid.size > 1 else 0.0
    if step > 0:
        for _ in range(MAX_EXTEND):
            p = best[2]
            at = math.log(p["l_const"])
            if at <= grid[0] + 1e-9 or at >= grid[-1] - 1e-9:
                out = at - step if at <= grid[0] + 1e-9 else at + step
                grid = np.sort(np.append(grid, out))
                total += 1
                consider(p["family"], math.exp(out), p["a"], p["b"])
            if math.log(best[2]["l_const"]) == at:
                break
        for _ in range(REFINE_ROUNDS):
            step /= 2.0
            p = best[2]
            at = math.log(p["l_const"])
            for x in (at - step, at + step):
                consider(p["family"], math.exp(x), p["a"], p["b"])
    assert best is not None
    _, rig, params, pred = best
    rig = dataclasses.replace(rig, design_range=(float(l_min), float(l_max)))
    db, lo_, hi_, _ = pred.run(min_snr_db)
    return DesignResult(rig=rig, params=params, prediction=pred, range_db=db,
                        l_lo=lo_, l_hi=hi_, min_snr_db=min_snr_db, sensor=sensor,
                        margin_db=margin_db,
                        margin_range_db=pred.run(min_snr_db + margin_db)[0],
                        candidates=tried)


DESIGNED: dict[str, dict[str, Any]] = {
    # asynhdr design --preset NAME --frame-rate-hz F (defaults: 0.1 to 316,000 lux, 1000:1
    # panels, per-pixel SNR >= 20 dB with 1.5 dB to spare first, readout bias <= 5 % with a
    # quarter of the array at one radiance); predicted range (with the margin) and mean SNR
    # over it in the comment. F: the fastest of 20, 5 and 2 cycles/s whose predicted range
    # is within 10 dB of the widest of the three.
    "ideal": {"family": "sequential", "l_const": 389.8603702549072, "a": 0.35,
              "b": 0.9, "frame_rate_hz": 20.0},  # 130 (130) dB, 74.5 dB (no readout limit)
    "v2e": {"family": "sequential", "l_const": 231.0129700083158, "a": 0.35,
            "b": 0.9, "frame_rate_hz": 20.0},  # 130 (130) dB, 73.4 dB (no readout limit)
    # 12 Mev/s for 346x260 pixels: at 20 cycles/s 0 dB, at 5 cycles/s 5 dB. At 2 cycles/s,
    # with the queue's spread in the prediction, the search picks L_const 854.7, a 0.35,
    # b 0.9 (80 dB, 70 with the margin), which the chart measures at 101.7, 101.7, 84.8
    # and 101.7 dB calibrated and 33.9 to 39.6 dB without; the default, the search's pick
    # before (75 dB, 65 with the margin, now), measures 96.1 to 101.7 and 45.2 dB: kept
    # for the uncalibrated run (docs/ml.md)
    "davis346": {"family": "sequential", "l_const": 1945.2824912854148, "a": 0.3,
                 "b": 0.8, "frame_rate_hz": 2.0},  # 75 (65) dB, 26.0 dB
    # 1.066 Gev/s for 1280x720 pixels: at 20 cycles/s 95 dB (sequential, L_const 1874,
    # a 0.2, b 0.55); at 2 cycles/s 130 dB. At 5 cycles/s the sequential rig and the round
    # trip reach 120 (115) dB, at 26.6 and 28.5 dB mean SNR. Since the pixels of fewer
    # than two events have estimates (the level beside L_const no longer breaks the run)
    # the search picks L_const 16.9, a 0.1 (130 dB with the margin, 31.7 dB): calibrated
    # the chart measures 130 dB in 5 of 5 captures, but without calibration (the CLI's
    # default) at 29.3 to 29.9 dB mean SNR, where this default reads 30.0 to 30.9: kept
    "imx636": {"family": "two_round_trips", "l_const": 36.99830414406964, "a": 0.075,
               "b": 0.225, "frame_rate_hz": 5.0},  # 130 (125) dB, 31.6 dB
}
"""The CLI's default rig per sensor preset, as ``asynhdr design --preset NAME
--frame-rate-hz F`` chose it for the default scene range (:data:`DEFAULT_SCENE_RANGE`) and
1000:1 panels; ``F`` is the fastest of 20, 5 and 2 cycles per second whose predicted range
is within 10 dB of the widest of the three (the sensor's readout sets it: docs/ml.md
lists the predicted ranges)."""


def default_rig(preset: str, *, period_us: int | None = None) -> Rig:
    """The designed rig of :data:`DESIGNED` for ``preset`` (a preset without an entry gets
    the ``v2e`` one), at its frame rate unless ``period_us`` is given; its
    ``design_range`` is :data:`DEFAULT_SCENE_RANGE`, which it was designed for."""
    p = DESIGNED.get(preset, DESIGNED["v2e"])
    period = round(1e6 / float(p["frame_rate_hz"])) if period_us is None else int(period_us)
    rig = FAMILIES[str(p["family"])](period_us=period, l_const=float(p["l_const"]),
                                     a=float(p["a"]), b=float(p["b"]))
    return dataclasses.replace(rig, design_range=DEFAULT_SCENE_RANGE)
