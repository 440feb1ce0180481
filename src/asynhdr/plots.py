"""Figures for people: chart response, SNR per level, image mosaics. Written atomically."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from asynhdr._atomic import atomic_path
from asynhdr.tonemap import tonemap

if TYPE_CHECKING:
    from asynhdr.experiments import ChartResult

__all__ = ["plot_chart_response", "plot_mosaic", "plot_snr_per_level"]


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: str | os.PathLike[str]) -> Path:
    plt = _pyplot()
    target = Path(path)
    with atomic_path(target) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return target


def plot_snr_per_level(result: ChartResult, path: str | os.PathLike[str]) -> Path:
    """SNR of each chart patch against its density, per weighting, without and with c-map
    (the paper's Fig. 6a)."""
    plt = _pyplot()
    scene = result.scene
    d = np.asarray(scene.densities)
    order = np.argsort(d)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, use in zip(axes, (False, True), strict=True):
        for r in result.results:
            if r.with_cmap != use or r.method in ("ttfe", "count"):
                continue
            snr = np.minimum(r.stats.snr_db, 100.0)
            ax.plot(d[order], snr[order], marker=".", label=f"{r.method} ({r.mean_snr_db:.1f} dB)")
        ax.set_title("with c-map" if use else "without c-map")
        ax.set_xlabel("density D")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("patch SNR (dB)")
    return _save(fig, path)


def plot_chart_response(result: ChartResult, path: str | os.PathLike[str]) -> Path:
    """Reconstructed patch mean against true patch radiance (log-log), with the resolved
    run marked, for every method with c-map."""
    plt = _pyplot()
    truth = np.asarray(result.scene.truth)
    order = np.argsort(truth)
    fig, ax = plt.subplots(figsize=(7, 5))
    for r in result.results:
        if not r.with_cmap:
            continue
        mu = np.maximum(r.stats.mean, 1e-12)
        norm = mu / np.median(mu)
        (line,) = ax.plot(truth[order], norm[order], marker=".", lw=1,
                          label=f"{r.method}: DR {r.dr.dr_db:.1f} dB")
        res = r.dr.resolved
        ax.plot(truth[res], norm[res], "o", mfc="none", color=line.get_color(), ms=7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("true patch radiance (lux)")
    ax.set_ylabel("reconstructed patch mean / median")
    ax.set_title("Chart response (circles: resolved levels)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return _save(fig, path)


def plot_mosaic(
    images: Sequence[np.ndarray],
    titles: Sequence[str],
    path: str | os.PathLike[str],
    *,
    columns: int = 4,
    tonemap_method: str = "log",
) -> Path:
    """Tone-mapped images side by side with titles."""
    plt = _pyplot()
    n = len(images)
    rows = (n + columns - 1) // columns
    h, w = images[0].shape
    fig, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, 3.2 * rows * h / w + 0.4))
    axes = np.atleast_1d(axes).ravel()
    for ax in axes:
        ax.axis("off")
    for ax, img, title in zip(axes, images, titles, strict=False):
        ax.imshow(tonemap(img, method=tonemap_method), cmap="gray", vmin=0, vmax=255)
        ax.set_title(title, fontsize=9)
    return _save(fig, path)
