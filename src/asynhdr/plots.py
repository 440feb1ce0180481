"""Figures for people: chart response, SNR per level, k sweep, image mosaics, scene
comparisons. Written atomically."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from asynhdr._atomic import atomic_path
from asynhdr.tonemap import tonemap

if TYPE_CHECKING:
    from asynhdr.experiments import ChartResult, MethodResult

__all__ = [
    "ERROR_MAP_STOPS",
    "HOLE_RGB",
    "plot_chart_response",
    "plot_error_maps",
    "plot_input_snr",
    "plot_k_sweep",
    "plot_linear_run",
    "plot_mosaic",
    "plot_snr_per_level",
]

_BASELINES = ("ttfe", "count")


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: str | os.PathLike[str]) -> Path:
    plt = _pyplot()
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(target) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)
    return target


def _label(r: MethodResult) -> str:
    v = r.snr.mean_db
    snr = "inf" if math.isinf(v) else ("-" if math.isnan(v) else f"{v:.1f}")
    return f"{r.method} ({snr} dB, {r.snr.n_patches} p.)"


def plot_snr_per_level(result: ChartResult, path: str | os.PathLike[str]) -> Path:
    """The paper's patch SNR against density per weighting, without and with c-map
    (its Fig. 6a). Filled markers joined by the line: patches that respond (counted in the
    mean); hollow markers, not joined: the others (a patch where too few pixels fired,
    or whose level does not follow the radiance, has an SNR that is no signal's)."""
    plt = _pyplot()
    d = np.asarray(result.scene.densities)
    order = np.argsort(d)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.3), sharey=True)
    for ax, use in zip(axes, (False, True), strict=True):
        for r in result.results:
            if r.with_cmap != use or r.method in _BASELINES:
                continue
            snr = np.clip(r.stats.snr_db, -20.0, 80.0)[order]
            resp = np.asarray(r.responding, dtype=bool)[order]
            (line,) = ax.plot(d[order], np.where(resp, snr, np.nan), "o-", lw=1, ms=3.5,
                              label=_label(r))
            ax.plot(d[order][~resp], snr[~resp], "o", ms=3.5, mfc="none",
                    color=line.get_color())
        for r in result.frame:
            snr = np.clip(r.stats.snr_db, -20.0, 80.0)
            ax.plot(d[order], snr[order], ls="--", lw=1, color="0.4" if "budget" in r.method
                    else "0.1", label=f"frame {_label(r)}")
        ax.set_title("with c-map" if use else "without c-map")
        ax.set_xlabel("density D (radiance 160,000 lux x 10^-D)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[0].set_ylabel("patch SNR 10 log10(mu^2/sigma^2) (dB)")
    fig.text(0.5, -0.04, "filled, joined: patches that respond (in the mean); hollow: "
             "patches that do not (no signal); clipped to [-20, 80] dB",
             ha="center", fontsize=8)
    return _save(fig, path)


def plot_input_snr(result: ChartResult, path: str | os.PathLike[str]) -> Path:
    """Input-referred SNR (EMVA 1288) per patch against radiance, with c-map, and the
    SNR_in = 1 line that bounds the dynamic range."""
    plt = _pyplot()
    truth = np.asarray(result.scene.truth)
    order = np.argsort(truth)
    fig, ax = plt.subplots(figsize=(7.5, 4.6))
    for r in (*[r for r in result.results if r.with_cmap], *result.frame):
        s = np.clip(np.asarray(r.snr_in, dtype=np.float64), 1e-3, 1e4)
        ax.plot(truth[order], s[order], marker=".", lw=1,
                ls="--" if r.method.startswith("mef") else "-",
                label=f"{r.method}: DR {r.dr.dr_db:.1f} dB")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("true patch radiance (lux)")
    ax.set_ylabel("input-referred SNR  L |dR/dL| / sigma")
    ax.set_title("Input-referred SNR (with c-map; dashed: frame camera)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=2)
    return _save(fig, path)


def plot_chart_response(result: ChartResult, path: str | os.PathLike[str]) -> Path:
    """Reconstructed patch mean against true patch radiance (log-log, normalised at the
    median of the responding patches), every method with c-map and the frame camera;
    circles: the patches inside the EMVA dynamic range. A patch that does not respond
    (``MethodResult.responding``: too few pixels fired) is no point on its method's line:
    it is marked with an ``x`` on a floor line below every responding patch, so a
    near-zero mean neither stretches the axis nor reads as a level."""
    plt = _pyplot()
    truth = np.asarray(result.scene.truth)
    order = np.argsort(truth)
    fig, ax = plt.subplots(figsize=(7.5, 5))
    silent: list[tuple[np.ndarray, str]] = []
    low = np.inf
    for r in (*[r for r in result.results if r.with_cmap], *result.frame):
        resp = np.asarray(r.responding, dtype=bool) & (np.asarray(r.stats.mean) > 0)
        mu = np.where(resp, r.stats.mean, np.nan)
        norm = mu / np.nanmedian(mu) if resp.any() else mu
        (line,) = ax.plot(truth[order], norm[order], marker=".", lw=1,
                          ls="--" if r.method.startswith("mef") else "-",
                          label=f"{r.method}: DR {r.dr.dr_db:.1f} / {r.dr_steps.dr_db:.1f} dB")
        c = np.asarray(r.dr.counted) & resp
        ax.plot(truth[c], norm[c], "o", mfc="none", color=line.get_color(), ms=7)
        if resp.any():
            low = min(low, float(np.nanmin(norm)))
        if (~resp).any():
            silent.append((~resp, line.get_color()))
    ax.set_xscale("log")
    ax.set_yscale("log")
    title = "Chart response, with c-map (circles: inside the EMVA range"
    if silent:
        floor = (low if np.isfinite(low) else 1.0) / 10.0
        ax.axhline(floor, color="0.6", lw=0.8, ls=":")
        for k, (mask, colour) in enumerate(silent):
            ax.plot(truth[mask], np.full(int(mask.sum()), floor * 1.25 ** k), "x",
                    color=colour, ms=5)
        title += ";\nx on the dotted floor: patches that do not respond"
    ax.set_xlabel("true patch radiance (lux)")
    ax.set_ylabel("patch mean / median responding patch mean")
    ax.set_title(title + ";\nlegend: DR EMVA / DR by the paper's steps)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    return _save(fig, path)


def plot_linear_run(levels: Sequence[float], curves: dict[str, dict[str, Any]],
                    path: str | os.PathLike[str], *, bound_snr_db: Sequence[float] | None = None,
                    stated_snr_db: Sequence[float] | None = None,
                    min_snr_db: float = 20.0, max_bias: float = 0.05,
                    title: str = "") -> Path:
    """Per-pixel SNR and bias per radiance level, the two lines a level must stay within to
    count in the run of :func:`asynhdr.metrics.linear_run`, and the run itself: filled
    markers inside it, hollow ones outside. ``curves[name]`` holds ``snr_db``, ``bias``
    (after the run's global scale) and ``run`` (the indices of its ends, or ``None``);
    ``bound_snr_db``: the SNR the model's Cramér-Rao bound allows, dashed, so a run whose
    end sits on the line shows as one; ``stated_snr_db``: the SNR an estimator's own
    per-pixel deviations state (``-20 log10`` of their median), dotted: where it meets
    the measured curve, the stated uncertainty is the real one."""
    plt = _pyplot()
    lv = np.asarray(levels, dtype=np.float64)
    fig, (ax_s, ax_b) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True,
                                     gridspec_kw={"height_ratios": [3, 2]})
    if bound_snr_db is not None:
        ax_s.plot(lv, np.asarray(bound_snr_db, dtype=np.float64), "--", color="0.3", lw=1,
                  label="the bound's SNR")
    if stated_snr_db is not None:
        ax_s.plot(lv, np.asarray(stated_snr_db, dtype=np.float64), ":", color="0.1", lw=1.2,
                  label="the SNR stated (median deviation)")
    for name, c in curves.items():
        snr = np.clip(np.asarray(c["snr_db"], dtype=np.float64), -20.0, 90.0)
        bias = np.clip(100.0 * np.abs(np.asarray(c["bias"], dtype=np.float64)), 1e-3, 1e4)
        inside = np.zeros(lv.size, dtype=bool)
        run = c.get("run")
        if run is not None:
            inside[run[0]:run[1] + 1] = True
        span = 20.0 * math.log10(lv[run[1]] / lv[run[0]]) if run is not None else 0.0
        (line,) = ax_s.plot(lv, snr, "-", lw=1, label=f"{name}: run {span:.1f} dB")
        for ax, y in ((ax_s, snr), (ax_b, bias)):
            ax.plot(lv[inside], y[inside], "o", ms=4, color=line.get_color())
            ax.plot(lv[~inside], y[~inside], "o", ms=4, mfc="none", color=line.get_color())
        ax_b.plot(lv, bias, "-", lw=1, color=line.get_color())
    ax_s.axhline(min_snr_db, color="k", lw=0.8)
    ax_b.axhline(100.0 * max_bias, color="k", lw=0.8)
    ax_s.set_ylabel("per-pixel SNR 20 log10(mean/std) (dB)")
    ax_b.set_ylabel("|bias| after one scale (%)")
    ax_b.set_yscale("log")
    ax_b.set_xscale("log")
    ax_b.set_xlabel("true radiance (lux)")
    ax_s.set_title((title + "\n" if title else "") + f"filled: levels in the run (SNR >= "
                   f"{min_snr_db:g} dB and |bias| <= {100 * max_bias:g} %); hollow: outside")
    for ax in (ax_s, ax_b):
        ax.grid(alpha=0.3, which="both")
    ax_s.legend(fontsize=8)
    return _save(fig, path)


def plot_k_sweep(sweeps: dict[str, list[dict[str, Any]]], path: str | os.PathLike[str],
                 *, paper_k: float = 10.0) -> Path:
    """Mean SNR of the exponential weighting ``2^(-k t)`` against ``k`` (the paper's Fig.
    5b), per sensor (colour), without (dashed) and with (solid) c-map. One legend below
    both panels: the sensors, then the two line styles, drawn long enough to tell apart.
    A sensor without any finite SNR (a noise-free pixel) says so in its entry."""
    from matplotlib.lines import Line2D

    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    handles = []
    for i, (name, rows) in enumerate(sweeps.items()):
        if not rows:
            continue
        color = f"C{i}"
        ks = [r["k"] for r in rows]
        finite = False
        for tag, ls in (("raw", "--"), ("cmap", "-")):
            snr = [np.nan if r[f"snr_db_{tag}"] is None else r[f"snr_db_{tag}"] for r in rows]
            finite = finite or bool(np.isfinite(snr).any())
            axes[0].plot(ks, snr, ls=ls, lw=1.6, marker=".", color=color)
            axes[1].plot(ks, [r[f"dr_db_{tag}"] for r in rows], ls=ls, lw=1.6, marker=".",
                         color=color)
        label = name if finite else f"{name} (no noise: SNR not finite, not drawn)"
        handles.append(Line2D([], [], color=color, lw=3, label=label))
    handles += [Line2D([], [], color="0.25", ls="--", lw=1.6, label="no c-map"),
                Line2D([], [], color="0.25", ls="-", lw=1.6, label="with c-map")]
    for ax in axes:
        ax.axvline(paper_k, color="0.6", lw=0.8)
        ax.set_xlabel("k of 2^(-k t)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("mean patch SNR over responding patches (dB)")
    axes[1].set_ylabel("dynamic range, EMVA (dB)")
    axes[0].set_title("k sweep: SNR (grey line: the paper's k = 10)")
    axes[1].set_title("k sweep: dynamic range")
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8,
               handlelength=3.5, frameon=False)
    fig.tight_layout(rect=(0.0, 0.07, 1.0, 1.0))
    return _save(fig, path)


HOLE_RGB = (255, 0, 255)
"""Colour of the pixels an image leaves without a value in :func:`plot_mosaic`."""


ERROR_MAP_STOPS = 0.5
"""The error maps' scale (:func:`plot_error_maps`): +- this many stops of
``log2(image / truth)``."""


def plot_error_maps(
    images: Sequence[np.ndarray],
    titles: Sequence[str],
    truth: np.ndarray,
    path: str | os.PathLike[str],
    *,
    columns: int = 4,
    limit_stops: float = ERROR_MAP_STOPS,
    outside: np.ndarray | None = None,
) -> Path:
    """Each image's error against ``truth`` per pixel, ``log2(image / truth)`` in stops,
    on one diverging scale clipped at ``+-limit_stops`` (blue: too dark, red: too
    bright), with one colour bar. Pixels an image leaves without a value (NaN, 0 or
    below) are drawn in :data:`HOLE_RGB`, those without truth (0) in grey; ``outside``
    (the pixels the capture cannot measure, a rig's range) is outlined in black."""
    from matplotlib import colors

    plt = _pyplot()
    n = len(images)
    columns = min(columns, n)
    rows = (n + columns - 1) // columns
    h, w = truth.shape
    # the panels' own aspect, room for a title each and the colour bar beside them
    fig, axes = plt.subplots(rows, columns, squeeze=False, layout="constrained",
                             figsize=(3.2 * columns + 1.0, (3.2 * h / w + 0.3) * rows + 0.3))
    flat = axes.ravel()
    for ax in flat:
        ax.axis("off")
    cmap = plt.get_cmap("RdBu_r")
    norm = colors.Normalize(-limit_stops, limit_stops)
    t = np.asarray(truth, dtype=np.float64)
    any_hole = False
    for ax, img, title in zip(flat, images, titles, strict=False):
        a = np.asarray(img, dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            err = np.log2(a / t)
            holes = ~(a > 0) & (t > 0)
        rgb = cmap(norm(np.clip(np.nan_to_num(err, nan=0.0), -limit_stops, limit_stops)))[..., :3]
        rgb[~(t > 0)] = 0.6
        rgb[holes] = np.asarray(HOLE_RGB) / 255.0
        any_hole = any_hole or bool(holes.any())
        ax.imshow(rgb, interpolation="nearest")
        if outside is not None and outside.any():
            ax.contour(outside.astype(float), levels=[0.5], colors="k", linewidths=0.6)
        ax.set_title(title, fontsize=8)
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=axes, shrink=0.8,
                 label="log2(image / truth), stops")
    notes = []
    if any_hole:
        notes.append("magenta: pixels the method leaves without a value")
    if outside is not None and outside.any():
        notes.append("outlined: beyond the rig's range")
    if notes:
        fig.supxlabel("; ".join(notes), fontsize=8)
    return _save(fig, path)


def plot_mosaic(
    images: Sequence[np.ndarray],
    titles: Sequence[str],
    path: str | os.PathLike[str],
    *,
    columns: int = 4,
    tonemap_method: str = "log",
    reference: np.ndarray | None = None,
) -> Path:
    """Tone-mapped images side by side with titles. With ``reference``, every image uses
    the reference's log tone map (same black and white in radiance), so brightness can
    be compared across panels, and the pixels an image leaves without a value (NaN, or 0
    and below, as :func:`asynhdr.experiments.finite_image` writes NaN) are drawn in
    :data:`HOLE_RGB`, not black: a hole in the brightest part of a scene would otherwise
    read as a dark spot. Otherwise each is tone-mapped on its own."""
    plt = _pyplot()
    n = len(images)
    columns = min(columns, n)
    rows = (n + columns - 1) // columns
    h, w = images[0].shape
    fig, axes = plt.subplots(rows, columns, layout="constrained",
                             figsize=(3.2 * columns, (3.2 * h / w + 0.3) * rows + 0.3))
    axes = np.atleast_1d(axes).ravel()
    for ax in axes:
        ax.axis("off")
    lo = hi = 0.0
    if reference is not None:
        pos = reference[reference > 0]
        lo, hi = (float(v) for v in np.percentile(pos, [0.5, 99.5]))
    any_hole = False
    for ax, img, title in zip(axes, images, titles, strict=False):
        if reference is not None and hi > lo:
            v = (np.log(np.clip(img, lo, hi)) - math.log(lo)) / (math.log(hi) - math.log(lo))
            disp = np.floor(np.clip(v, 0, 1) * 255 + 0.5)
        else:
            disp = tonemap(img, method=tonemap_method)
        grey = np.nan_to_num(np.asarray(disp, dtype=np.float64), nan=0.0).astype(np.uint8)
        rgb = np.repeat(grey[..., None], 3, axis=2)
        if reference is not None and img is not reference:
            with np.errstate(invalid="ignore"):
                holes = ~(np.asarray(img) > 0)
            rgb[holes] = HOLE_RGB
            any_hole = any_hole or bool(holes.any())
        ax.imshow(rgb)
        ax.set_title(title, fontsize=8)
    if any_hole:
        fig.supxlabel("magenta: pixels the method leaves without a value", fontsize=8)
    return _save(fig, path)
