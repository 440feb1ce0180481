"""Calibration from data: per-pixel ON and OFF thresholds, the response, the panels' curves.

- **Thresholds from flat fields** (:func:`thresholds_from_flats`). On a flat field of known
  radiance ``L_flat`` every pixel's events are fitted by :mod:`asynhdr.ml` with ``ln L``
  held at ``ln L_flat``: what is left to estimate per pixel and cycle is ``(u, c_on,
  c_off)``, linear in the chain's equations, with the nominal thresholds as a weak prior
  (``prior_sigma``, 0.1 by default: the data decide). The estimates of all cycles and
  captures are averaged per pixel (cycles more than four robust sigmas from the
  per-pixel median left out), weighted by the events of that polarity each cycle
  fired beyond the first (what identifies the threshold); the stated error is that
  weighted mean's, from the weighted scatter of the cycles (a cycle's estimate taken to
  have a variance inversely proportional to its weight). A pixel fires ON and OFF events in a cycle
  when its signal falls and then rises: with the cross-fading rig of ``asynhdr design``
  that is every pixel near ``L_const``, the default flat radiance.
- **Dead pixels** from the same flat fields: those that fired no event in any cycle while
  the typical pixel fired several (:func:`asynhdr.defects.dead_pixels`); ``ml`` fills them
  from their neighbours, flagged.
- **Thresholds from a capture's own events**: ``ml`` fits ``c_on`` and ``c_off`` with the
  radiance (:class:`asynhdr.ml.MlResult`); where a pixel's events identify them (both
  polarities, several events of each) their posterior is narrower than the prior.
  :func:`thresholds_from_results` averages them over cycles, weighted by how many events
  of each polarity the pixel fired.
- **Response** (:func:`fit_response`): on a chart capture with known patch radiances, a
  monotone piecewise-linear map from ``ln`` of the reconstructed patch medians to ``ln`` of
  the truth (isotonic, then interpolated; clamped outside). It removes what the model
  leaves (a global scale, a slow curvature).
- **Panel curves from a voltage sweep** (:func:`read_sweep_csv`, :func:`simulate_sweep`,
  :func:`fit_panel_curves`): the transmittance of each panel at DC drive levels, fitted by
  :func:`asynhdr.panel.calibrate_curve`. The sweep file is a CSV::

      # asynhdr panel sweep: transmittance normalised to the open state
      voltage_v,transmittance_1,transmittance_2
      0.0,0.998,0.0011
      0.1,0.997,0.0012
      ...

  (one row per drive level; a panel's column may be empty where it was not measured).

One :class:`Calibration` holds all of it with a record of how it was made
(:mod:`asynhdr.io.calibration` reads and writes it).
"""

from __future__ import annotations

import csv
import logging
import math
import os
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr.defects import dead_pixels
from asynhdr.events import Recording
from asynhdr.panel import Panel, PanelCurve, calibrate_curve
from asynhdr.rig import Rig
from asynhdr.sensor.params import SensorParams

__all__ = [
    "FLAT_ROI_PIXELS",
    "Calibration",
    "Response",
    "fit_panel_curves",
    "fit_response",
    "flat_capture_sensor",
    "moderated_variance",
    "read_sweep_csv",
    "simulate_sweep",
    "thresholds_from_flats",
    "thresholds_from_results",
]

logger = logging.getLogger(__name__)

FLAT_ROI_PIXELS = 4096
"""Flat fields are captured through regions of interest of this many pixels, read one at
a time. On the whole array every pixel of a flat field fires in the same instant and the
readout's queue stamps the events late (a 400x180 flat at 30x ``L_const`` waits up to
4.9 ms at the IMX636's share); a wave of 4,096 events takes 3.8 µs at its 1.066 Gev/s."""


def flat_capture_sensor(sensor: SensorParams, n_pixels: int) -> SensorParams:
    """The sensor as a simulated flat-field capture of ``n_pixels`` pixels sees it: read
    through regions of interest of :data:`FLAT_ROI_PIXELS` (each region has the whole
    readout), one simulation for all of them. Unchanged without a shared readout."""
    return sensor.region_of_interest(min(FLAT_ROI_PIXELS, int(n_pixels)))

THRESHOLD_ERROR_FLOOR = 0.002
"""Added in quadrature to calibrated thresholds' stated errors when ``ml`` uses them."""

DEFAULT_PRIOR_SIGMA = 0.1
"""Spread of the nominal thresholds used as the prior in the flat-field fit (log units):
wide against the mismatch (0.03 to 0.05), so the events decide."""


@dataclass(frozen=True, eq=False)
class Response:
    """A monotone map of ``ln L``: ``ln L_true = interp(ln L_est, x, y)`` (clamped to the
    end slopes of 1 outside ``[x[0], x[-1]]``)."""

    x: np.ndarray
    y: np.ndarray

    def __call__(self, image: np.ndarray) -> np.ndarray:
        a = np.asarray(image, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            g = np.log(a)
        out = np.interp(g, self.x, self.y)
        out = np.where(g < self.x[0], self.y[0] + (g - self.x[0]), out)
        out = np.where(g > self.x[-1], self.y[-1] + (g - self.x[-1]), out)
        res = np.exp(out)
        res[~np.isfinite(g)] = np.nan
        return res.astype(np.float32)


@dataclass(eq=False)
class Calibration:
    """Everything calibrated for one sensor and rig.

    Attributes
    ----------
    c_on, c_off : float32 ``(height, width)`` per-pixel thresholds (log units), or None.
    sigma_on, sigma_off : their stated errors (same shape), or None.
    defects : bool ``(height, width)``, the dead pixels (no event in any flat-field cycle;
        :func:`asynhdr.defects.dead_pixels`), or None.
    response : a :class:`Response`, or None.
    panel_curves : ``{"1": PanelCurve, "2": PanelCurve}`` fitted to a sweep (either may be
        missing).
    sensor : the pixel model the thresholds were fitted with, or None.
    how : how it was made (JSON-serialisable: inputs, radiances, counts, errors).
    """

    c_on: np.ndarray | None = None
    c_off: np.ndarray | None = None
    sigma_on: np.ndarray | None = None
    sigma_off: np.ndarray | None = None
    defects: np.ndarray | None = None
    response: Response | None = None
    panel_curves: dict[str, PanelCurve] = field(default_factory=dict)
    sensor: SensorParams | None = None
    how: dict[str, Any] = field(default_factory=dict)

    def threshold_maps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``(c_on, c_off, sigma)`` for :func:`asynhdr.ml.reconstruct_ml`, or None."""
        if self.c_on is None or self.c_off is None:
            return None
        if self.sigma_on is not None and self.sigma_off is not None:
            sig = np.maximum(self.sigma_on, self.sigma_off).astype(np.float64)
        else:
            sig = np.full(self.c_on.shape, 0.005)
        # the stated errors, in quadrature with a floor for what they miss (a cycle's fit
        # that a background event spoilt, the model's own approximations)
        return (np.asarray(self.c_on, np.float64), np.asarray(self.c_off, np.float64),
                np.sqrt(sig ** 2 + THRESHOLD_ERROR_FLOOR ** 2))


# ----------------------------------------------------------------------------- thresholds


def _warn_readout(cap: Recording, what: str) -> None:
    """Warn when the readout's queue moved a capture's timestamps by more than the
    sensor's µs: every pixel of a flat field fires at once, and the queue turns pixel
    order into time."""
    ro = cap.metadata.get("readout") or {}
    delay = float(ro.get("max_delay_us") or 0.0)
    if delay > 1.0:
        logger.warning("%s: the readout delayed %s of %s events of a capture by up to %.0f "
                       "µs; thresholds fitted to them carry that delay. Capture flat "
                       "fields through a region of interest the readout keeps up with (or "
                       "at a lower cycle rate).", what, f"{int(ro.get('delayed', 0)):,}",
                       f"{int(ro.get('emitted', 0)):,}", delay)


def thresholds_from_flats(
    captures: Iterable[Recording],
    *,
    radiance: float | Sequence[float],
    rig: Rig,
    sensor: SensorParams,
    prior_sigma: float = DEFAULT_PRIOR_SIGMA,
    skip_first_cycle: bool = True,
) -> Calibration:
    """Per-pixel ``c_on``, ``c_off`` from flat-field captures of known radiance.

    ``radiance``: the flat field's radiance in the rig's unit, one for all captures or one
    per capture. ``skip_first_cycle``: leave out each capture's first cycle (the pixel's
    reference before it is not the cycle's). Returns a :class:`Calibration` whose errors
    are the standard errors of the per-cycle estimates' weighted mean (per pixel; the
    scatter of a pixel's few cycles moderated by the other pixels', :func:`moderated_variance`;
    pixels with fewer than two usable cycles get the prior's spread).
    """
    from asynhdr.ml import cached_model, estimate, thresholds_prior

    caps = list(captures)
    if not caps:
        raise ValueError("thresholds_from_flats: no flat-field captures given")
    rads = [float(radiance)] * len(caps) if isinstance(radiance, int | float) else \
        [float(r) for r in radiance]
    if len(rads) != len(caps):
        raise ValueError(f"thresholds_from_flats: {len(rads)} radiances for {len(caps)} "
                         "captures")
    h, w = caps[0].height, caps[0].width
    model = cached_model(rig, sensor, window_us=rig.ramp_us)
    base = SensorParams(threshold_on=sensor.threshold_on, threshold_off=sensor.threshold_off)
    on0, off0, _, _ = thresholds_prior(base, width=w, height=h)
    sp = np.full(w * h, float(prior_sigma))
    priors = (on0, off0, sp, sp.copy())
    # per polarity: sums of weights, weighted values and squares (weight: that cycle's
    # events of the polarity, which is what identifies the threshold)
    vals: list[list[np.ndarray]] = [[], []]  # per polarity: each cycle's estimates
    wts: list[list[np.ndarray]] = [[], []]  # and their weights
    fired = np.zeros((h, w), dtype=np.int64)  # events per pixel over the cycles used
    n_cycles = 0
    for cap, lf in zip(caps, rads, strict=True):
        if (cap.height, cap.width) != (h, w):
            raise ValueError(f"thresholds_from_flats: capture is {cap.width}x{cap.height}, "
                             f"expected {w}x{h}")
        if not (lf > 0 and math.isfinite(lf)):
            raise ValueError(f"thresholds_from_flats: flat radiance must be positive, got {lf}")
        _warn_readout(cap, "thresholds_from_flats")
        starts = _starts(cap, rig)
        if skip_first_cycle and starts.size > 1:
            starts = starts[1:]
        g = np.full(w * h, math.log(lf))
        res = estimate(cap.events, width=w, height=h, starts_us=starts, model=model,
                       priors=priors, g_prior=g, g_prior_sigma=np.full(w * h, 1e-6))
        for c in range(starts.size):
            ok = res.flags[c] == 0
            n_on, n_off = _polarity_counts(cap, int(starts[c]), model.window_us, w, h)
            fired += n_on + n_off
            for k, (n_p, cc) in enumerate(((n_on, res.c_on[c]), (n_off, res.c_off[c]))):
                wts[k].append(np.where(ok, np.maximum(n_p - 1, 0), 0).astype(np.float64))
                vals[k].append(cc.astype(np.float64))
        n_cycles += starts.size
    out = []
    counts = []
    for k, nom in ((0, sensor.threshold_on), (1, sensor.threshold_off)):
        v = np.stack(vals[k])
        wt = np.stack(wts[k])
        # robust: cycles further than 4 robust sigmas (or 0.01) from the per-pixel median of
        # the cycles that count are left out (a background event can spoil a cycle's fit)
        masked = np.where(wt > 0, v, np.nan)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(masked, axis=0)
            mad = np.nanmedian(np.abs(masked - med), axis=0) * 1.4826
        keep = (wt > 0) & (np.abs(v - med) <= np.maximum(4.0 * np.nan_to_num(mad), 0.01))
        wt = np.where(keep, wt, 0.0)
        sw = wt.sum(axis=0)
        s1 = (wt * v).sum(axis=0)
        s2 = (wt * v * v).sum(axis=0)
        nc = keep.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(sw > 0, s1 / sw, nom)
            # cycle i's estimate has variance sigma1^2 / w_i: the weighted mean's variance
            # is sigma1^2 / sum(w)
            scatter = np.maximum(s2 - 2 * mean * s1 + mean ** 2 * sw, 0.0)
            # sigma1^2 from the weighted scatter over (N - 1), moderated by the other pixels'
            dof = np.maximum(nc - 1, 1.0)
            sig1 = moderated_variance(scatter / dof, dof, nc > 1)
            err = np.sqrt(sig1 / np.maximum(sw, 1.0))
        err = np.where(nc > 1, np.maximum(err, 1e-4), prior_sigma)
        out.append((mean.astype(np.float32), err.astype(np.float32)))
        counts.append(sw)
    n1, n2 = counts
    dead = dead_pixels(fired)
    how = {"kind": "thresholds from flat fields", "captures": len(caps),
           "cycles": n_cycles, "flat_radiance": rads, "prior_sigma": prior_sigma,
           "median_error_on": float(np.median(out[0][1])),
           "median_error_off": float(np.median(out[1][1])),
           "pixels_without_on": int(np.count_nonzero(n1 == 0)),
           "pixels_without_off": int(np.count_nonzero(n2 == 0)),
           "dead_pixels": int(np.count_nonzero(dead)),
           "median_events_per_pixel": float(np.median(fired))}
    logger.info("thresholds from %d flat fields (%d cycles): median error ON %.4f, OFF %.4f",
                len(caps), n_cycles, how["median_error_on"], how["median_error_off"])
    return Calibration(c_on=out[0][0], c_off=out[1][0], sigma_on=out[0][1],
                       sigma_off=out[1][1], defects=dead, sensor=sensor, how=how)


def _trigamma_inverse(x: float) -> float:
    """``y`` with ``trigamma(y) = x`` (Newton's method from ``0.5 + 1 / x``; x > 0)."""
    from scipy.special import polygamma

    y = 0.5 + 1.0 / x
    for _ in range(50):
        tri = float(polygamma(1, y))
        step = tri * (1.0 - tri / x) / float(polygamma(2, y))
        y += step
        if -step / y < 1e-8:
            break
    return y


def moderated_variance(s2: np.ndarray, dof: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Each pixel's variance estimate ``s2`` (``dof`` degrees of freedom) moderated by
    the others' (Smyth 2004, empirical Bayes): the pixels' true variances are taken as
    scaled inverse chi-square with ``d0`` degrees of freedom about ``s0^2``, both fitted to
    the spread of ``log s2`` over the pixels in ``use``; the result is the posterior
    ``(d0 s0^2 + dof s2) / (d0 + dof)``. With a few cycles per pixel a sample variance
    alone is now and then ten times too small by chance; pooled alone it misstates the
    pixels whose noise really differs."""
    from scipy.special import digamma, polygamma

    ok = use & (s2 > 0) & np.isfinite(s2)
    if np.count_nonzero(ok) < 3:
        return s2
    nu = dof[ok]
    e = np.log(s2[ok]) - digamma(nu / 2.0) + np.log(nu / 2.0)
    n = e.size
    emean = float(e.mean())
    evar = float(np.sum((e - emean) ** 2) / (n - 1) - np.mean(polygamma(1, nu / 2.0)))
    if evar > 0:
        d0 = 2.0 * _trigamma_inverse(evar)
        s0 = math.exp(emean + float(digamma(d0 / 2.0)) - math.log(d0 / 2.0))
        return (d0 * s0 + dof * s2) / (d0 + dof)
    return np.full_like(s2, math.exp(emean))  # no spread beyond chance: one variance


def _starts(rec: Recording, rig: Rig) -> np.ndarray:
    tr = rec.triggers
    if tr.size:
        return np.asarray(tr["t"][tr["rising"]], dtype=np.int64)
    n = int(rec.metadata.get("n_cycles", 1))
    return rig.cycle_starts_us(n, t0_us=int(rec.metadata.get("t0_us", 0)))


def _polarity_counts(rec: Recording, start: int, window: int, w: int, h: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    ev = rec.events
    sel = (ev["t"] >= start) & (ev["t"] < start + window)
    idx = ev["y"][sel].astype(np.int64) * w + ev["x"][sel]
    p = ev["p"][sel]
    on = np.bincount(idx[p > 0], minlength=w * h).reshape(h, w)
    off = np.bincount(idx[p < 0], minlength=w * h).reshape(h, w)
    return on, off


def thresholds_from_results(c_on: np.ndarray, c_off: np.ndarray, n_on: np.ndarray,
                            n_off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel thresholds from ``ml``'s joint fits over cycles ``(n_cycles, h, w)``:
    the average of each cycle's fitted ``c_on`` (``c_off``) weighted by the ON (OFF)
    events that cycle fired; NaN where none."""
    with np.errstate(invalid="ignore", divide="ignore"):
        on = np.sum(c_on * n_on, axis=0) / np.sum(n_on, axis=0)
        off = np.sum(c_off * n_off, axis=0) / np.sum(n_off, axis=0)
    return on, off


# ----------------------------------------------------------------------------- response


def fit_response(estimates: Sequence[float], truth: Sequence[float]) -> Response:
    """A monotone map from estimated to true ``ln L`` through the points
    ``(ln estimate_i, ln truth_i)`` (patches of a chart): sorted by truth, the estimates
    made non-decreasing (pool-adjacent-violators), repeated abscissae merged."""
    e = np.log(np.asarray(estimates, dtype=np.float64))
    t = np.log(np.asarray(truth, dtype=np.float64))
    ok = np.isfinite(e) & np.isfinite(t)
    if ok.sum() < 2:
        raise ValueError("fit_response: fewer than two patches with finite estimates")
    e, t = e[ok], t[ok]
    order = np.argsort(t)
    e, t = e[order], t[order]
    e = _pava(e)
    xs = np.unique(np.round(e, 9))
    ys = np.array([t[(np.round(e, 9) == x)].mean() for x in xs])
    if xs.size < 2:
        raise ValueError("fit_response: the estimates do not vary over the chart")
    return Response(xs, ys)


def _pava(y: np.ndarray) -> np.ndarray:
    """Isotonic (non-decreasing) least-squares fit of ``y`` (pool adjacent violators)."""
    vals: list[float] = []
    wts: list[float] = []
    for v in y:
        vals.append(float(v))
        wts.append(1.0)
        while len(vals) > 1 and vals[-2] > vals[-1]:
            w2 = wts[-2] + wts[-1]
            v2 = (vals[-2] * wts[-2] + vals[-1] * wts[-1]) / w2
            vals[-2:] = [v2]
            wts[-2:] = [w2]
    return np.repeat(np.array(vals), np.array(wts, dtype=np.int64))


# ----------------------------------------------------------------------------- panels


def read_sweep_csv(path: str | os.PathLike[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """A voltage sweep (module docstring): ``{"1": (voltages_v, transmittance), "2": ...}``
    for the panels whose column holds values."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: sweep file not found") from None
    rows = [r for r in csv.reader(line for line in text.splitlines()
                                  if line.strip() and not line.lstrip().startswith("#"))]
    if not rows:
        raise ValueError(f"{p}: empty sweep file")
    head = [h.strip() for h in rows[0]]
    if "voltage_v" not in head:
        raise ValueError(f"{p}: header must name 'voltage_v' and 'transmittance_1' and/or "
                         f"'transmittance_2'; got {head}")
    cols = {name: head.index(name) for name in ("transmittance_1", "transmittance_2")
            if name in head}
    if not cols:
        raise ValueError(f"{p}: no 'transmittance_1' or 'transmittance_2' column in {head}")
    iv = head.index("voltage_v")
    out: dict[str, tuple[list[float], list[float]]] = {k[-1]: ([], []) for k in cols}
    for ln, r in enumerate(rows[1:], start=2):
        try:
            v = float(r[iv])
        except (ValueError, IndexError):
            raise ValueError(f"{p}: data row {ln}: voltage_v {r[iv] if iv < len(r) else ''!r}"
                             " is not a number") from None
        for name, j in cols.items():
            cell = r[j].strip() if j < len(r) else ""
            if not cell:
                continue
            try:
                tv = float(cell)
            except ValueError:
                raise ValueError(f"{p}: data row {ln}: {name} {cell!r} is not a number"
                                 ) from None
            if not (math.isfinite(tv) and 0.0 <= tv <= 1.5):
                raise ValueError(f"{p}: data row {ln}: {name} = {tv} is not a transmittance "
                                 "normalised to the open state")
            out[name[-1]][0].append(v)
            out[name[-1]][1].append(tv)
    return {k: (np.asarray(a), np.asarray(b)) for k, (a, b) in out.items() if a}


def simulate_sweep(panels: tuple[Panel, Panel], *, voltages_v: np.ndarray | None = None,
                   noise: float = 0.002, rng: np.random.Generator | int | None = 0
                   ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """A simulated sweep of both panels: the static curve at each DC level, with a
    photodiode's additive noise ``noise`` (in transmittance units), clipped at 0."""
    gen = np.random.default_rng(rng)
    out = {}
    for name, pn in zip(("1", "2"), panels, strict=True):
        v = np.linspace(pn.curve.v_min_v, pn.curve.v_max_v, 41) if voltages_v is None \
            else np.asarray(voltages_v, dtype=np.float64)
        t = pn.curve.transmittance(v) + gen.normal(0.0, noise, v.size)
        out[name] = (v, np.clip(t, 0.0, 1.5))
    return out


def write_sweep_csv(path: str | os.PathLike[str],
                    sweep: dict[str, tuple[np.ndarray, np.ndarray]]) -> Path:
    """Write a sweep in the CSV of the module docstring (both panels on one voltage grid
    when they share it, else one block of rows per panel)."""
    from asynhdr._atomic import atomic_path

    p = Path(path)
    lines = ["# asynhdr panel sweep: transmittance normalised to the open state",
             "voltage_v,transmittance_1,transmittance_2"]
    for name in ("1", "2"):
        if name not in sweep:
            continue
        v, t = sweep[name]
        for vv, tt in zip(v, t, strict=True):
            cells = [repr(float(vv)), "", ""]
            cells[int(name)] = repr(float(tt))
            lines.append(",".join(cells))
    with atomic_path(p) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p


def fit_panel_curves(sweep: dict[str, tuple[np.ndarray, np.ndarray]], *,
                     method: str = "logistic") -> dict[str, PanelCurve]:
    """Each swept panel's static curve (:func:`asynhdr.panel.calibrate_curve`). A sweep
    whose noise puts the open state above 1 is renormalised to its fitted open state
    (scaled down until the fitted curve stays within (0, 1]; the factor is logged)."""
    out = {}
    for k, (v, t) in sweep.items():
        tt = np.asarray(t, dtype=np.float64)
        scale = 1.0
        for _ in range(20):
            try:
                out[k] = calibrate_curve(v, tt * scale, method=method)  # type: ignore[arg-type]
                break
            except ValueError as exc:
                if "leaves (0, 1]" not in str(exc):
                    raise
                scale *= 0.995
        else:
            raise ValueError(f"panel {k}: the sweep cannot be normalised to its open state")
        if scale != 1.0:
            logger.info("panel %s: sweep scaled by %.4f to its fitted open state", k, scale)
    return out
