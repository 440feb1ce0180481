"""One HTML page of the bench's figures: tables beside the paper's, plots, the settings.

Pure string building from the bench's JSON summary (:func:`render_report`), one atomic
write (:func:`write_report`). Images are linked by relative path, so the page and its
folder move together.
"""

from __future__ import annotations

import html
import math
import os
from pathlib import Path
from typing import Any

from asynhdr._atomic import atomic_path

__all__ = ["render_report", "write_report"]

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:24px auto;
max-width:1280px;color:#222;line-height:1.4}
h1{font-size:1.6em;margin-bottom:0}h2{margin-top:1.8em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:10px 0;font-size:0.9em}
td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f0f0f0}td:first-child,th:first-child{text-align:left}
td.paper{background:#fff8e0}.note{color:#555;font-size:0.88em;max-width:1100px}
img{max-width:100%;border:1px solid #ddd;margin:6px 0}
.grid{display:grid;grid-template-columns:1fr 1fr;gap:12px}
code{background:#f4f4f4;padding:1px 4px}
"""


def range_note(md: dict[str, Any]) -> str | None:
    """The line that says how much of a scene lies beyond the rig's working range at its
    exposure (None when nothing does)."""
    above = md.get("above_range_fraction") or 0.0
    below = md.get("below_range_fraction") or 0.0
    if not (above or below):
        return None
    lo, hi = md["rig_range_lux"]
    parts = []
    if above:
        parts.append(f"{100 * above:.3g} % lie above it (the brightest at "
                     f"{md['max_over_range']:.3g}x its top)")
    if below:
        parts.append(f"{100 * below:.3g} % {'' if above else 'lie '}below it")
    return (f"The rig's range is {lo:.3g} to {hi:.3g} lux. Of the scene's pixels, "
            f"{' and '.join(parts)}. 'In range': the same figures over the rest.")


def scene_table(sc: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    """One evaluated scene's figures as text, ``(head, rows)``, a row per method: the
    report's table and the command line's. With a share of the scene beyond the rig's
    range (:func:`range_note`), the figures over the rest as two more columns."""
    in_range = range_note(sc["metadata"]) is not None
    head = ["method", "capture (ms)", "log RMSE (stops)", "rel. error", "PU21-PSNR (dB)",
            "SSIM"]
    if in_range:
        head += ["in range: log RMSE", "in range: PU21"]
    rows = []
    for m, v in sc["methods"].items():
        row = [m, _num(1000 * v["capture_s"], 1), _num(v["log_rmse_stops"], 3),
               _num(v["rel_error"], 3), _num(v["pu21_psnr_db"]), _num(v["ssim"], 3)]
        if in_range:
            row += [_num(v.get("log_rmse_in_range_stops"), 3),
                    _num(v.get("pu21_psnr_in_range_db"))]
        rows.append(row)
    return head, rows


def _num(v: float | None, nd: int = 2) -> str:
    """A figure as text: ``-`` for none (None or NaN), ``inf``, else ``nd`` decimals."""
    if v is None or math.isnan(v):
        return "-"
    return "inf" if math.isinf(v) else f"{v:.{nd}f}"


def _fmt(v: Any, nd: int = 2) -> str:
    if v is None or isinstance(v, float):
        return _num(v, nd)
    return html.escape(str(v))


def _table(head: list[str], rows: list[list[str]], paper_cols: tuple[int, ...] = ()) -> str:
    out = ["<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"]
    for r in rows:
        cells = []
        for i, c in enumerate(r):
            cls = ' class="paper"' if i in paper_cols else ""
            cells.append(f"<td{cls}>{c}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _method(chart: dict[str, Any], name: str, cmap: bool) -> dict[str, Any] | None:
    for m in chart.get("methods", []):
        if m["method"] == name and m["with_cmap"] == cmap:
            return m
    for m in chart.get("frame_camera", []):
        if m["method"] == name:
            return m
    return None


def _snr_cell(m: dict[str, Any] | None) -> str:
    if m is None:
        return "-"
    n = f"{m['snr_patches']}" + (f"+{m['snr_noiseless_patches']}"
                                 if m.get("snr_noiseless_patches") else "")
    return f"{_fmt(m['mean_snr_db'])} <small>[{n}]</small>"


def _img(path: str, alt: str) -> str:
    return f'<img src="{html.escape(path)}" alt="{html.escape(alt)}">'


def render_report(summary: dict[str, Any], figures: dict[str, str]) -> str:
    """The page: ``summary`` as written to ``bench.json``; ``figures`` maps a key
    (``"<preset>/response"``, ``"k_sweep"``, ``"scene/<name>"``...) to a relative path."""
    presets: dict[str, Any] = summary.get("presets", {})
    paper = summary.get("paper", {})
    paper_snr: dict[str, list[float]] = paper.get("snr_db", {})
    settings = summary.get("settings", {})
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>asynhdr bench"
             f"</title><style>{_CSS}</style></head><body>",
             "<h1>asynhdr bench: the paper's experiments in simulation</h1>",
             f"<p class='note'>Command: <code>{html.escape(settings.get('command', ''))}</code>"
             f" &middot; wall time {_fmt(summary.get('wall_s'), 0)} s &middot; "
             f"{html.escape(summary.get('date', ''))}</p>"]

    # ------------------------------------------------------------------ SNR table
    parts.append("<h2>SNR table (the paper's Table 1)</h2>")
    parts.append(
        "<p class='note'>Mean of the paper's patch SNR <code>10 log10(mu^2/sigma^2)</code> over "
        "the central 16x16 pixels (256) of each patch, on the last cycle, averaged over the "
        "patches that respond: at least half of the region fired an event and the "
        "input-referred SNR is at least 1. [n]: patches averaged (+k: responding patches "
        "without noise, infinite SNR, left out). Each cell: no c-map / with c-map.</p>")
    names = list(presets)
    head = ["weighting", *[f"{p} ({presets[p]['metadata']['width']}x"
                           f"{presets[p]['metadata']['height']})" for p in names], "paper"]
    rows = []
    for w in ("raw", "linear", "quadratic", "poly5", "exp", "ttfe", "count", "invert"):
        row = [w]
        for p in names:
            ch = presets[p]
            row.append(f"{_snr_cell(_method(ch, w, False))} / {_snr_cell(_method(ch, w, True))}")
        pv = paper_snr.get(w)
        row.append(f"{pv[0]:.2f} / {pv[1]:.2f}" if pv else "-")
        rows.append(row)
    for fm in ("mef-10", "mef-budget"):
        row = [f"frame camera {fm}"]
        for p in names:
            row.append(_snr_cell(_method(presets[p], fm, False)))
        row.append("-")
        rows.append(row)
    parts.append(_table(head, rows, paper_cols=(len(head) - 1,)))

    # ------------------------------------------------------------------ DR table
    parts.append("<h2>Dynamic range, with c-map</h2>")
    parts.append(
        "<p class='note'>EMVA: <code>20 log10(Lmax/Lmin)</code> over the longest run of patches "
        "(by radiance) with events, input-referred SNR <code>|dR/d ln L| / sigma</code> &ge; 1 "
        "and a strictly monotone response. Steps: the paper's criterion, neighbouring "
        "densities whose means are apart by more than the sum of their pixel spreads. "
        f"Paper: {paper.get('dr_db', 102.6)} dB (levels 2 to 29). The chart spans 164.4 dB "
        "(densities 0 to 8.22).</p>")
    head = ["method", *[f"{p}: EMVA / steps (dB)" for p in names], "paper"]
    rows = []
    for w in ("raw", "linear", "quadratic", "poly5", "exp", "ttfe", "count", "invert",
              "mef-10", "mef-budget"):
        row = [w if not w.startswith("mef") else f"frame camera {w}"]
        for p in names:
            m = _method(presets[p], w, True)
            row.append("-" if m is None else
                       f"{_fmt(m['dr_db'], 1)} / {_fmt(m['dr_steps_db'], 1)}")
        row.append(_fmt(paper.get("dr_db")) if w == "exp" else "")
        rows.append(row)
    parts.append(_table(head, rows, paper_cols=(len(head) - 1,)))

    parts.append("<h2>Radiometric error and grey levels, with c-map</h2>")
    parts.append("<p class='note'>Median over responding patches of the relative RMS error "
                 "against the true patch radiance after one global scale; distinct levels of "
                 "the 8-bit log tone map of the whole image.</p>")
    head = ["method", *[f"{p}: rel. error / levels" for p in names]]
    rows = []
    for w in ("raw", "linear", "quadratic", "poly5", "exp", "ttfe", "count", "invert",
              "mef-10", "mef-budget"):
        row = [w]
        for p in names:
            m = _method(presets[p], w, True)
            row.append("-" if m is None else
                       f"{_fmt(m['median_rel_error'], 3)} / {m['grey_levels']}")
        rows.append(row)
    parts.append(_table(head, rows))

    # ------------------------------------------------------------------ k sweep
    if "k_sweep" in figures:
        parts.append("<h2>k sweep (the paper's Fig. 5b)</h2>")
        parts.append(_img(figures["k_sweep"], "k sweep"))
        head = ["k", *[f"{p}: SNR no / with c-map (dB)" for p in names]]
        ks = sorted({r["k"] for p in names for r in presets[p].get("k_sweep", [])})
        rows = []
        for kk in ks:
            row = [f"{kk:g}"]
            for p in names:
                r = next((r for r in presets[p].get("k_sweep", []) if r["k"] == kk), None)
                row.append("-" if r is None else
                           f"{_fmt(r['snr_db_raw'])} / {_fmt(r['snr_db_cmap'])}")
            rows.append(row)
        parts.append(_table(head, rows))

    # ------------------------------------------------------------------ per preset
    for p in names:
        meta = presets[p]["metadata"]
        parts.append(f"<h2>Sensor {html.escape(p)}: figures</h2>")
        parts.append(f"<p class='note'>{meta['width']}x{meta['height']}, {meta['n_cycles']} "
                     f"cycles, c-map from {meta['n_flat']} flat fields at "
                     f"{meta['illuminance_lux'] * 10 ** -meta['flat_density']:.0f} lux, "
                     f"{meta['n_events']:,} chart events; patches with events: "
                     f"{meta['patches_with_events']} of 36.</p>")
        parts.append("<div class='grid'>")
        for key, alt in (("response", "chart response"), ("input_snr", "input-referred SNR")):
            if f"{p}/{key}" in figures:
                parts.append(_img(figures[f"{p}/{key}"], f"{p} {alt}"))
        parts.append("</div>")
        for key, alt in (("snr", "SNR per level"), ("mosaic", "images")):
            if f"{p}/{key}" in figures:
                parts.append(_img(figures[f"{p}/{key}"], f"{p} {alt}"))

    # ------------------------------------------------------------------ scenes
    scenes = summary.get("scenes", [])
    if scenes:
        parts.append("<h2>Real HDR scenes against ground truth (the paper's Fig. 7)</h2>")
        parts.append(
            "<p class='note'>Each scene is put in lux by automatic exposure (its log-average "
            "at the middle of the rig's range, <code>Rig.mid_radiance</code>), padded onto "
            "the sensor with its aspect kept. Every image gets one global scale, then: RMS "
            "of log2 error (stops), median relative error, PU21-PSNR (Mantiuk and Azimi "
            "2021; truth's maximum at 4,000 cd/m^2), SSIM on the truth's log tone map. "
            "Capture time: one modulation cycle for the event methods; the sum of the "
            "frames' times (each at least 1/155 s) for the frame camera.</p>")
        for sc in scenes:
            md = sc["metadata"]
            note = range_note(md)
            parts.append(f"<h3>{html.escape(sc['name'])}</h3><p class='note'>scale "
                         f"{md['scale']:.4g} to lux, span {md['span_stops']:.1f} stops, "
                         f"log-average {md['log_average_lux']:.3g} lux, max "
                         f"{md['max_lux']:.3g} lux, sensor {html.escape(md['sensor'])}"
                         + (f". {html.escape(note)}" if note else "") + "</p>")
            head, rows = scene_table(sc)
            parts.append(_table(head, [[html.escape(r[0]), *r[1:]] for r in rows]))
            if f"scene/{sc['name']}" in figures:
                parts.append(_img(figures[f"scene/{sc['name']}"], sc["name"]))
            if f"scene/{sc['name']}/error" in figures:
                parts.append(_img(figures[f"scene/{sc['name']}/error"],
                                  f"{sc['name']}: error per pixel"))

    # ------------------------------------------------------------------ settings
    parts.append("<h2>Settings</h2><pre style='font-size:0.8em;white-space:pre-wrap'>")
    import json

    parts.append(html.escape(json.dumps(settings, indent=1, default=str)))
    for p in names:
        meta = presets[p]["metadata"]
        parts.append(html.escape(f"\n{p}: sensor " + json.dumps(meta["sensor"], default=str)))
        if meta.get("frame_camera"):
            parts.append(html.escape(f"\n{p}: frame camera " +
                                     json.dumps(meta["frame_camera"], default=str)))
    rig = next(iter(presets.values()))["metadata"]["rig"] if presets else {}
    parts.append(html.escape("\nrig " + json.dumps(rig, default=str)))
    parts.append("</pre></body></html>")
    return "\n".join(parts)


def write_report(path: str | os.PathLike[str], page: str) -> Path:
    """Write the page atomically."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(target) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return target
