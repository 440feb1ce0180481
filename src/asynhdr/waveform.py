"""Waveform design: the voltages that make real panels give the wanted transmittance.

The rig asks for transmittances ``T1(t)`` (scene panel) and ``T2(t)`` (reference
panel) over one cycle. A panel (:mod:`asynhdr.panel`) turns a commanded voltage into
its static transmittance ``x = T_s(|V|)`` and then lags it, first order, with different
time constants for rising and falling transmittance. :func:`design` inverts both
steps for every generator sample (pre-emphasis), then simulates the panels on the
resulting voltages to report what they really produce.

Inverse of the dynamics (sample-and-hold command, ``a = exp(-dt / tau)``): the exact
update over one sample is ``T[n+1] = x[n] + (T[n] - x[n]) a``, so the command that
reaches the next target sample is::

    x[n] = (T*[n+1] - a T[n]) / (1 - a),   a = a_rise if T*[n+1] > T[n] else a_fall

clipped to the achievable ``[t_min, t_max]``; where it clips the panel lags and the
next sample starts from where it really is. This is the discrete, exact form of
``x = T* + tau dT*/dt``. Over a cycle the start state is the periodic steady state
(solved exactly). The voltage is then ``|V| = T_s^{-1}(x)``.
"""

from __future__ import annotations

import json
import logging
import math
import numbers
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr._atomic import atomic_path
from asynhdr.panel import _RANGE_TOL, Panel, _periodic_state
from asynhdr.transmittance import Waveform

__all__ = [
    "DEFAULT_CARRIER_HZ",
    "DEFAULT_SAMPLE_RATE_HZ",
    "ChannelDesign",
    "Design",
    "design",
    "read_csv",
]

logger = logging.getLogger(__name__)

DEFAULT_SAMPLE_RATE_HZ = 200_000.0
"""Generator sample rate: 10,000 points per 50 ms cycle (fits a 16 k-point arbitrary
waveform memory); 5 µs per sample, far below the panels' time constants."""


DEFAULT_CARRIER_HZ = 1000.0
"""Polarity-reversing square carrier of the panel drive, Hz. A DC component across a
liquid-crystal cell moves ions to the alignment layers (image sticking, then lasting
damage), so panels are driven by a DC-free AC voltage whose RMS sets the
transmittance; 1 kHz is the customary drive frequency of TN test cells and shutters
(fast against the ms-scale response, slow against the cell's RC): 50 periods per 50 ms
cycle; at the default sample rate half a period is 100 samples. ``carrier_hz=None`` is the
explicit DC drive."""


@dataclass(frozen=True, eq=False)
class ChannelDesign:
    """One panel's part of a design; arrays hold one cycle at the generator rate.

    Attributes
    ----------
    panel : the panel model.
    target : wanted transmittance at the sample instants ``t_n = n / fs``.
    command : commanded static transmittance ``x[n] = T_s(|V[n]|)``, held over a sample.
    voltage_v : commanded voltage (RMS amplitude, signed when an AC carrier is used).
    result : the panel's actual transmittance at ``t_n`` (periodic steady state).
    naive_voltage_v, naive_result : the same without pre-emphasis (``x[n] = T*[n]``).
    rms_error_pct, rms_error_ramp_pct : RMS of ``result - target`` over the cycle and
        over the ramp, in % of the panel's full scale ``t_max - t_min`` (ramp: NaN
        when the design was given no ``ramp_fraction``).
    naive_rms_error_pct, naive_rms_error_ramp_pct : the same without pre-emphasis.
    rms_log_error_ramp, naive_rms_log_error_ramp : RMS of ``ln(result / target)`` over
        the ramp (natural-log units, as the DVS sees it: compare with its contrast
        threshold), with and without pre-emphasis; NaN without ``ramp_fraction``.
    """

    panel: Panel
    target: np.ndarray
    command: np.ndarray
    voltage_v: np.ndarray
    result: np.ndarray
    naive_voltage_v: np.ndarray
    naive_result: np.ndarray
    rms_error_pct: float
    rms_error_ramp_pct: float
    naive_rms_error_pct: float
    naive_rms_error_ramp_pct: float
    rms_log_error_ramp: float
    naive_rms_log_error_ramp: float


@dataclass(frozen=True, eq=False)
class Design:
    """Commanded voltages for both panels over one cycle, and what the panels do.

    Attributes
    ----------
    channels : ``(panel 1, panel 2)``: the scene panel (``T1``) and the reference (``T2``).
    period_us : cycle length, µs.
    sample_rate_hz : generator sample rate, Hz.
    pre_emphasis : whether ``voltage_v`` inverts the dynamics (else it is the naive one).
    ramp_fraction : the ramp part of the cycle used for the ramp errors, or None.
    carrier_hz : frequency of the polarity-reversing square carrier, or None (DC).
    """

    channels: tuple[ChannelDesign, ChannelDesign]
    period_us: int
    sample_rate_hz: float
    pre_emphasis: bool
    ramp_fraction: float | None = None
    carrier_hz: float | None = None

    @property
    def n_samples(self) -> int:
        """Samples per cycle, ``period_us * sample_rate_hz / 1e6``."""
        return int(self.channels[0].voltage_v.size)

    @property
    def time_s(self) -> np.ndarray:
        """Sample instants ``n / sample_rate_hz`` in seconds (float64)."""
        return np.arange(self.n_samples, dtype=np.float64) / self.sample_rate_hz

    def samples(self, channel: int) -> np.ndarray:
        """Commanded voltages of panel ``channel`` (1 or 2) at the generator rate, volts."""
        return self._channel(channel).voltage_v.copy()

    def _channel(self, channel: int) -> ChannelDesign:
        if channel not in (1, 2):
            raise ValueError(f"channel must be 1 (scene panel) or 2 (reference panel), "
                             f"got {channel!r}")
        return self.channels[channel - 1]

    def to_waveforms(self) -> tuple[Waveform, Waveform]:
        """The panels' *resulting* transmittance as rig waveforms ``(T1, T2)``.

        One knot per generator sample plus the closing knot at phase 1 (equal to the
        first: periodic), so ``Rig(t1=..., t2=...)`` simulates what the real panels do.
        Between samples the true curve is exponential; the knots are ``dt / tau``
        apart in time constants, so the linear segments follow it closely.
        """
        out = []
        for k, ch in enumerate(self.channels, start=1):
            vals = np.clip(np.append(ch.result, ch.result[0]), 0.0, 1.0)
            kind = "pre-emphasis" if self.pre_emphasis else "direct"
            out.append(Waveform.from_samples(vals, name=f"T{k} {ch.panel.name} ({kind})"))
        return out[0], out[1]

    def to_metadata(self) -> dict[str, Any]:
        """JSON-serialisable summary: rates, panels, errors."""
        return {
            "period_us": int(self.period_us),
            "sample_rate_hz": float(self.sample_rate_hz),
            "n_samples": self.n_samples,
            "pre_emphasis": self.pre_emphasis,
            "ramp_fraction": self.ramp_fraction,
            "carrier_hz": self.carrier_hz,
            "panels": [ch.panel.to_metadata() for ch in self.channels],
            "rms_error_pct": [ch.rms_error_pct for ch in self.channels],
            "rms_error_ramp_pct": [ch.rms_error_ramp_pct for ch in self.channels],
            "naive_rms_error_pct": [ch.naive_rms_error_pct for ch in self.channels],
            "naive_rms_error_ramp_pct": [ch.naive_rms_error_ramp_pct for ch in self.channels],
            "rms_log_error_ramp": [ch.rms_log_error_ramp for ch in self.channels],
            "naive_rms_log_error_ramp": [ch.naive_rms_log_error_ramp for ch in self.channels],
        }

    def write_files(self, folder: str | os.PathLike[str]) -> dict[str, Path]:
        """Write both panels' voltages in the generators' formats and a JSON sidecar.

        See :func:`asynhdr.waveform_io.write_waveform_files` (``panel{k}.csv``,
        ``panel{k}.arb``, ``panel{k}_sdg.csv``, ``waveform.json``); read back with
        :func:`asynhdr.waveform_io.read_waveform_files`.
        """
        from asynhdr.waveform_io import write_waveform_files

        return write_waveform_files(folder, (self.samples(1), self.samples(2)),
                                    sample_rate_hz=self.sample_rate_hz,
                                    period_us=self.period_us, metadata=self.to_metadata())

    def to_csv(self, path: str | os.PathLike[str]) -> Path:
        """Write ``time_s,v1_v,v2_v`` (one row per sample, one cycle), atomically.

        A ``#`` comment header names the sample rate, period, sample count, carrier and
        both panels' parameters (one JSON object per line after ``# key:``).
        """
        target = Path(path)
        meta = self.to_metadata()
        lines = ["# asynhdr waveform design: commanded panel voltages over one cycle"]
        for key in ("sample_rate_hz", "period_us", "n_samples", "pre_emphasis",
                    "ramp_fraction", "carrier_hz"):
            lines.append(f"# {key}: {json.dumps(meta[key])}")
        for k, pm in enumerate(meta["panels"], start=1):
            lines.append(f"# panel{k}: {json.dumps(pm)}")
        for key in ("rms_error_pct", "rms_error_ramp_pct", "naive_rms_error_pct",
                    "naive_rms_error_ramp_pct", "rms_log_error_ramp", "naive_rms_log_error_ramp"):
            lines.append(f"# {key}: {json.dumps(meta[key])}")
        data = np.column_stack([self.time_s, self.channels[0].voltage_v,
                                self.channels[1].voltage_v])
        with atomic_path(target) as tmp:
            with open(tmp, "w", encoding="utf-8", newline="\n") as fh:
                fh.write("\n".join(lines) + "\n")
                fh.write("time_s,v1_v,v2_v\n")
                np.savetxt(fh, data, fmt="%.12g", delimiter=",")
        return target


def read_csv(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                   dict[str, Any]]:
    """Read a file written by :meth:`Design.to_csv`: ``(time_s, v1_v, v2_v, header)``.

    ``header`` holds the ``# key: value`` comment lines, values parsed as JSON.
    """
    p = Path(path)
    header: dict[str, Any] = {}
    columns: list[str] | None = None
    n_comment = 0
    with open(p, encoding="utf-8") as fh:
        for line in fh:
            if line.startswith("#"):
                n_comment += 1
                body = line[1:].strip()
                if ": " in body:
                    key, _, val = body.partition(": ")
                    try:
                        header[key] = json.loads(val)
                    except json.JSONDecodeError:
                        header[key] = val
                continue
            columns = [c.strip() for c in line.strip().split(",")]
            break
    if columns != ["time_s", "v1_v", "v2_v"]:
        raise ValueError(f"{p}: expected the column header 'time_s,v1_v,v2_v', found "
                         f"{columns!r}")
    data = np.loadtxt(p, delimiter=",", skiprows=n_comment + 1, dtype=np.float64, ndmin=2)
    if data.shape[1] != 3:
        raise ValueError(f"{p}: expected 3 columns, found {data.shape[1]}")
    return data[:, 0].copy(), data[:, 1].copy(), data[:, 2].copy(), header


def _n_samples(period_us: int, sample_rate_hz: float) -> int:
    if isinstance(period_us, bool) or not isinstance(period_us, numbers.Real) \
            or not math.isfinite(period_us) or period_us <= 0 or int(period_us) != period_us:
        raise ValueError(f"period_us must be a positive whole number of µs, got {period_us!r}")
    if isinstance(sample_rate_hz, bool) or not isinstance(sample_rate_hz, numbers.Real) \
            or not math.isfinite(sample_rate_hz) or sample_rate_hz <= 0:
        raise ValueError(f"sample_rate_hz must be positive and finite, got {sample_rate_hz!r}")
    exact = int(period_us) * float(sample_rate_hz) / 1e6
    n = round(exact)
    if abs(exact - n) > 1e-6 * max(1.0, exact):
        raise ValueError(
            f"period_us * sample_rate_hz / 1e6 = {exact:.6g} samples per cycle is not a whole "
            f"number; choose a sample rate that divides the period (period_us={period_us})")
    if n < 2:
        raise ValueError(f"a cycle needs at least 2 samples, got {n} (period_us={period_us}, "
                         f"sample_rate_hz={sample_rate_hz:g})")
    return n


def _check_target(name: str, panel_name: str, values: np.ndarray, panel: Panel,
                  sample_rate_hz: float) -> np.ndarray:
    lo, hi = panel.t_min, panel.t_max
    bad = (values < lo - _RANGE_TOL) | (values > hi + _RANGE_TOL)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f"{name}: sample {i} (t = {i * 1e6 / sample_rate_hz:.6g} µs) asks for "
            f"transmittance {values[i]:.6g}, outside {panel_name} {panel.name!r}'s achievable "
            f"range [{lo:.6g}, {hi:.6g}] (contrast ratio {panel.contrast_ratio:.6g}); "
            f"{int(bad.sum())} samples are out of range")
    return np.clip(values, lo, hi)


def _invert_response(target: list[float], lo: float, hi: float, a_rise: float,
                     a_fall: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample commands that make the exact update hit ``target[n + 1]`` (clipped).

    ``target`` has ``N + 1`` samples (the last is the next cycle's first). Returns
    ``(x, T)`` of length ``N`` in the periodic steady state.
    """
    n = len(target) - 1

    def run(y0: float, rec: tuple[list[float], list[float]] | None) -> tuple[float, float]:
        y, slope = y0, 1.0
        for k in range(n):
            want = target[k + 1]
            if want > y:
                a = a_rise
                x = (want - a * y) / (1.0 - a)
                clipped = x > hi
                if clipped:
                    x = hi
            elif want < y:
                a = a_fall
                x = (want - a * y) / (1.0 - a)
                clipped = x < lo
                if clipped:
                    x = lo
            else:
                a, x, clipped = a_fall, y, False
            if rec is not None:
                rec[0].append(x)
                rec[1].append(y)
            y = x + (y - x) * a
            slope = slope * a if clipped else 0.0
        return y, slope

    y0 = _periodic_state(lambda y: run(y, None), lo, hi, target[0])
    xs: list[float] = []
    ys: list[float] = []
    run(y0, (xs, ys))
    return np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64)


def _carrier_signs(n: int, sample_rate_hz: float, period_us: int,
                   carrier_hz: float | None) -> np.ndarray:
    """+1/-1 square carrier (DC-free over the cycle) or all +1."""
    if carrier_hz is None:
        return np.ones(n)
    if not (math.isfinite(carrier_hz) and carrier_hz > 0):
        raise ValueError(f"carrier_hz must be positive and finite, got {carrier_hz!r}")
    half = sample_rate_hz / (2.0 * carrier_hz)
    per_cycle = period_us * 1e-6 * carrier_hz
    if abs(half - round(half)) > 1e-9 * half or round(half) < 1:
        raise ValueError(f"carrier_hz={carrier_hz:g}: half a carrier period must be a whole "
                         f"number of samples at sample_rate_hz={sample_rate_hz:g} (got {half:g})")
    if abs(per_cycle - round(per_cycle)) > 1e-9 * max(1.0, per_cycle) or round(per_cycle) < 1:
        raise ValueError(f"carrier_hz={carrier_hz:g}: the period ({period_us} µs) must hold a "
                         f"whole number of carrier periods (got {per_cycle:g}) to stay DC-free")
    k = np.arange(n) // round(half)
    return np.where(k % 2 == 0, 1.0, -1.0)


def _rms_pct(result: np.ndarray, target: np.ndarray, full_scale: float,
             mask: np.ndarray | None = None) -> float:
    d = result - target
    if mask is not None:
        d = d[mask]
    return float(100.0 * np.sqrt(np.mean(d * d)) / full_scale)


def _rms_log(result: np.ndarray, target: np.ndarray, mask: np.ndarray | None) -> float:
    if mask is None:
        return float("nan")
    d = np.log(result[mask] / target[mask])
    return float(np.sqrt(np.mean(d * d)))


def design(
    target_t1: Waveform,
    target_t2: Waveform,
    *,
    panel1: Panel,
    panel2: Panel,
    period_us: int,
    sample_rate_hz: float,
    pre_emphasis: bool = True,
    ramp_fraction: float | None = None,
    carrier_hz: float | None = DEFAULT_CARRIER_HZ,
) -> Design:
    """Commanded voltages (one cycle per panel) giving the target transmittances.

    Parameters
    ----------
    target_t1, target_t2 : wanted actual transmittance of the scene and reference
        panels over one cycle (e.g. ``Rig().waveforms()``).
    panel1, panel2 : the panel models.
    period_us : cycle length in µs (whole number, > 0).
    sample_rate_hz : generator sample rate; ``period_us * sample_rate_hz / 1e6`` must be
        a whole number of samples (held constant between samples).
    pre_emphasis : invert the dynamics (module docstring); False commands the static
        inverse of the target directly, ``|V[n]| = T_s^{-1}(T*[n])``.
    ramp_fraction : the ramp part of the cycle, to report the error over the ramp
        (samples with phase ``n / N <= ramp_fraction``) apart from the return.
    carrier_hz : reverse the drive polarity as a square wave at this frequency (TN
        cells must be driven DC-free; the cell responds to ``V^2``, so the transmittance
        is unchanged). Default :data:`DEFAULT_CARRIER_HZ`; None: unipolar (DC) samples,
        which degrade a real cell: only for panels that are not liquid crystals.

    Returns
    -------
    A :class:`Design`: voltages, commands, simulated results and their RMS errors with
    and without pre-emphasis. Where the target moves faster than the panel can follow
    (the command clips at ``t_min`` or ``t_max``) the result lags; that shows in the
    errors, chiefly over the return after the ramp.

    Raises
    ------
    ValueError : non-positive period or sample rate, a period that is not a whole number
        of samples, a target sample outside a panel's achievable range (named).
    """
    n = _n_samples(period_us, sample_rate_hz)
    if ramp_fraction is not None and not 0.0 < ramp_fraction <= 1.0:
        raise ValueError(f"ramp_fraction must be in (0, 1], got {ramp_fraction}")
    signs = _carrier_signs(n, float(sample_rate_hz), int(period_us), carrier_hz)
    phase = np.arange(n + 1, dtype=np.float64) / n
    ramp_mask = None if ramp_fraction is None else phase[:n] <= ramp_fraction + 1e-12
    channels = []
    for k, (tw, panel) in enumerate(((target_t1, panel1), (target_t2, panel2)), start=1):
        if not isinstance(tw, Waveform):
            raise ValueError(f"target_t{k} must be an asynhdr.transmittance.Waveform, got "
                             f"{type(tw).__name__}")
        if not isinstance(panel, Panel):
            raise ValueError(f"panel{k} must be an asynhdr.panel.Panel, got "
                             f"{type(panel).__name__}")
        tgt = _check_target(f"target_t{k}", f"panel{k}", tw(phase), panel, float(sample_rate_hz))
        lo, hi = panel.t_min, panel.t_max
        naive_x = tgt[:n]
        naive_v = panel.curve.voltage(naive_x) * signs
        naive_y = panel.simulate(naive_v, sample_rate_hz=sample_rate_hz)
        if pre_emphasis:
            a_rise, a_fall = panel.response.step_factors(sample_rate_hz)
            x, predicted = _invert_response(tgt.tolist(), lo, hi, a_rise, a_fall)
            x = np.clip(x, lo, hi)
            volts = panel.curve.voltage(x) * signs
            result = panel.simulate(volts, sample_rate_hz=sample_rate_hz)
            logger.debug("panel%d: designed vs simulated transmittance differ by at most %.3g",
                         k, float(np.max(np.abs(result - predicted))))
        else:
            x, volts, result = naive_x.copy(), naive_v, naive_y
        scale = hi - lo
        target = tgt[:n]
        nan = float("nan")
        ch = ChannelDesign(
            panel=panel, target=target, command=x, voltage_v=volts, result=result,
            naive_voltage_v=naive_v, naive_result=naive_y,
            rms_error_pct=_rms_pct(result, target, scale),
            rms_error_ramp_pct=nan if ramp_mask is None else _rms_pct(result, target, scale,
                                                                      ramp_mask),
            naive_rms_error_pct=_rms_pct(naive_y, target, scale),
            naive_rms_error_ramp_pct=nan if ramp_mask is None else _rms_pct(
                naive_y, target, scale, ramp_mask),
            rms_log_error_ramp=_rms_log(result, target, ramp_mask),
            naive_rms_log_error_ramp=_rms_log(naive_y, target, ramp_mask),
        )
        logger.info("panel%d %s: RMS error %.3g %% of full scale (ramp %.3g %%), without "
                    "pre-emphasis %.3g %% (ramp %.3g %%)", k, panel.name, ch.rms_error_pct,
                    ch.rms_error_ramp_pct, ch.naive_rms_error_pct, ch.naive_rms_error_ramp_pct)
        channels.append(ch)
    return Design(channels=(channels[0], channels[1]), period_us=int(period_us),
                  sample_rate_hz=float(sample_rate_hz), pre_emphasis=bool(pre_emphasis),
                  ramp_fraction=ramp_fraction, carrier_hz=carrier_hz)

