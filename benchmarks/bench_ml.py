"""ml on a 24-level chart from 0.1 to 316,000 lux (132 dB), every preset, with the CLI's
default (designed) rig: the longest run of levels with |bias| <= 5 % (after one global
scale) and per-pixel SNR >= 20 dB, beside ``invert`` and the paper's ``exp`` + c-map; ml's
spread against the model's Cramér-Rao bound; and ml's speed on a 1280x720 cycle beside
``numpy.bincount`` over the same events (and the paper's weightings beside it).

Run: ``python benchmarks/bench_ml.py --out out/bench`` (``make bench`` runs it).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from asynhdr import ml
from asynhdr.calib import flat_capture_sensor, thresholds_from_flats
from asynhdr.calibrate import estimate_cmap
from asynhdr.design import default_rig
from asynhdr.memory import retain_freed_memory
from asynhdr.metrics import central_rois, linear_run
from asynhdr.plots import plot_linear_run
from asynhdr.reconstruct import CycleWindows, reconstruct, weighted_sums
from asynhdr.scene import flat_field, step_chart
from asynhdr.sensor.params import get_preset
from asynhdr.simulate import draw_thresholds, simulate

LEVELS = 24
L_TOP = 10 ** 5.5
DENSITIES = np.linspace(0.0, 6.5, LEVELS)  # 316,000 lux down to 0.1 lux
MAX_BIAS = 0.05
MIN_SNR_DB = 20.0


def chart_figures(img: np.ndarray, scene: Any) -> dict[str, Any]:
    """Per level (sorted by radiance): per-pixel SNR over the central 16x16 region, bias
    after one global scale; the longest run with |bias| <= 5 % and SNR >= 20 dB
    (:func:`asynhdr.metrics.linear_run`)."""
    rois = central_rois(scene.rois)
    truth = np.asarray(scene.truth, dtype=np.float64)
    order = np.argsort(truth)
    means, snrs, fin = [], [], []
    for k in order:
        y0, y1, x0, x1 = rois[int(k)]
        px = np.asarray(img[y0:y1, x0:x1], dtype=np.float64).ravel()
        ok = np.isfinite(px) & (px > 0)
        fin.append(float(ok.mean()))
        if ok.sum() < 0.5 * px.size:
            means.append(np.nan)
            snrs.append(-np.inf)
            continue
        m, s = float(px[ok].mean()), float(px[ok].std())
        means.append(m)
        snrs.append(20 * math.log10(m / s) if s > 0 else np.inf)
    return {**run_figures(truth[order], means, snrs), "means": means, "finite_fraction": fin}


def run_figures(lv: np.ndarray, means: list[float], snrs: list[float]) -> dict[str, Any]:
    """The longest run with |bias| <= 5 % and SNR >= 20 dB over levels ``lv`` (ascending)."""
    run = linear_run(lv, np.array(means), np.array(snrs), max_bias=MAX_BIAS,
                     min_snr_db=MIN_SNR_DB)
    i, j = run.lo, run.hi
    return {"run_db": run.span_db, "run_lux": [float(lv[i]), float(lv[j])] if i >= 0 else None,
            "run_index": [int(i), int(j)] if i >= 0 else None,
            "run_levels": run.n_levels, "run_mean_snr_db": run.mean_snr_db,
            "scale": run.scale, "levels_lux": lv.tolist(), "bias": run.bias.tolist(),
            "snr_db": [float(x) for x in snrs]}


def run_preset(preset: str, *, width: int, height: int, seed: int = 0,
               rig: Any = None, hold: bool = False, captures: int = 1,
               out_dir: Path | None = None) -> dict[str, Any]:
    """The chart for ``preset``: every method on the capture of ``seed``; with
    ``captures`` > 1, ``ml``'s runs on as many captures (seeds ``seed``, ``seed + 1``, ..;
    the same sensor and calibration), so a run that sits on the SNR line shows as one.
    With ``out_dir``, ``ml_run_<preset>.png`` draws ``ml``'s levels, the run and the bound
    (:func:`asynhdr.plots.plot_linear_run`)."""
    sensor = get_preset(preset)
    if hold:
        sensor = sensor.with_(name=preset, arbiter="hold")
    rig = rig or default_rig(preset)
    scene = step_chart(width=width, height=height, densities=DENSITIES, illuminance_lux=L_TOP,
                       columns=8)
    t0 = time.perf_counter()
    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=2, rng=seed, sensor_seed=1)
    t_sim = time.perf_counter() - t0
    # calibration: thresholds from flat fields 30x above and below L_const; the paper's
    # c-map from flat fields at L_const; both through regions of interest
    roi = flat_capture_sensor(sensor, width * height)
    rads = [rig.l_const * 30, rig.l_const / 30] * 2
    flats = [simulate(flat_field(width=width, height=height, radiance=r), rig=rig,
                      sensor=roi, n_cycles=3, rng=100 + i, sensor_seed=1)
             for i, r in enumerate(rads)]
    cal = thresholds_from_flats(flats, radiance=rads, rig=rig, sensor=sensor)
    cflats = [simulate(flat_field(width=width, height=height, radiance=rig.l_const), rig=rig,
                       sensor=roi, n_cycles=2, rng=200 + i, sensor_seed=1) for i in range(2)]
    cmap = estimate_cmap(cflats)
    out: dict[str, Any] = {"preset": preset, "rig": {"l_const": rig.l_const,
                                                     "period_us": rig.period_us},
                           "events": int(rec.events.size), "simulate_s": t_sim,
                           "readout": rec.metadata.get("readout"),
                           "calibration": cal.how}
    thr = cal.threshold_maps()
    runs = {
        "ml": dict(method="ml"),
        "ml + calibration": dict(method="ml", ml_options={"thresholds": thr}),
        "ml fast + calibration": dict(method="ml", ml_options={"thresholds": thr,
                                                               "fast": True}),
        "invert": dict(method="invert"),
        "invert + c-map": dict(method="invert", cmap=cmap),
        "exp + c-map (paper)": dict(method="exp", cmap=cmap),
    }
    ro = rec.metadata.get("readout") or {}
    print(f"  {preset:9s} {rig.period_us / 1e3:g} ms cycle, {rec.events.size:,} events; readout "
          f"{ro.get('rate_hz', 0):.3g} ev/s for these pixels: {ro.get('delayed', 0):,} "
          f"delayed, by up to {ro.get('max_delay_us', 0):.0f} µs"
          + (f"; pixels held until read in {ro['held_cycles']} cycles"
             if ro.get("pixels_held") else ""), flush=True)
    res: dict[str, Any] = {}
    for name, kw in runs.items():
        flags: dict[str, Any] = {}
        if kw["method"] == "ml":
            kw = {**kw, "ml_options": {**kw.get("ml_options", {}), "out": flags}}
        t0 = time.perf_counter()
        imgs = reconstruct(rec, **kw)  # type: ignore[arg-type]
        dt = time.perf_counter() - t0
        if flags:
            # a pixel at a bound of ml's range holds the bound, and a pixel of fewer than
            # two events holds what its silence says (the same for every silent pixel of
            # the same thresholds): neither measures its level by the patch's spread (a
            # patch of them would read flat, at infinite SNR); only fits count
            imgs = np.where(flags["flags"] == 0, imgs, np.nan)
        f = chart_figures(imgs[-1], scene)
        f["seconds"] = dt
        res[name] = f
        print(f"  {preset:9s} {name:22s} run {f['run_db']:6.1f} dB over {f['run_levels']:2d} "
              f"levels {f['run_lux']}, mean SNR {f['run_mean_snr_db']:5.1f} dB ({dt:.1f} s)",
              flush=True)
        if name == "ml":
            # the CLI's default learns the thresholds from the recording: its first cycle
            # too, measured (the figures above are the last cycle's)
            f0 = chart_figures(imgs[0], scene)
            res["ml, first cycle"] = f0
            print(f"  {preset:9s} {'ml, first cycle':22s} run {f0['run_db']:6.1f} dB over "
                  f"{f0['run_levels']:2d} levels {f0['run_lux']}, mean SNR "
                  f"{f0['run_mean_snr_db']:5.1f} dB", flush=True)
    out["methods"] = res
    if captures > 1:
        names = ("ml", "ml, first cycle", "ml + calibration", "ml fast + calibration")
        spread: dict[str, list[float]] = {name: [res[name]["run_db"]] for name in names}
        snr: dict[str, list[float]] = {name: [res[name]["run_mean_snr_db"]]
                                       for name in spread}
        for sd in range(seed + 1, seed + captures):  # the first capture is measured above
            other = simulate(scene, rig=rig, sensor=sensor, n_cycles=2, rng=sd, sensor_seed=1)
            for name in names:
                if name == "ml, first cycle":
                    continue  # with "ml"
                fl: dict[str, Any] = {}
                opts = {**runs[name].get("ml_options", {}), "out": fl}
                imgs = reconstruct(other, method="ml", ml_options=opts)
                imgs = np.where(fl["flags"] == 0, imgs, np.nan)
                measured = [(name, imgs[-1])]
                if name == "ml":
                    measured.append(("ml, first cycle", imgs[0]))
                for key, img in measured:
                    f = chart_figures(img, scene)
                    spread[key].append(f["run_db"])
                    snr[key].append(f["run_mean_snr_db"])
        out["captures"] = {"seeds": list(range(seed, seed + captures)), **spread,
                           "mean_snr_db": snr}
        for name, v in spread.items():
            print(f"  {preset:9s} {name:22s} over {captures} captures: "
                  + ", ".join(f"{x:.1f}" for x in v) + f" dB (median {np.median(v):.1f}); "
                  "mean SNR over each run " + ", ".join(f"{x:.1f}" for x in snr[name])
                  + " dB", flush=True)
    # ml's spread against the model's bound, calibrated thresholds, per level
    model = ml.cached_model(rig, sensor, window_us=rig.ramp_us)
    quiet = sensor.with_(name="quiet", reset_noise_sigma=0.0, jitter_sigma_us=0.0,
                         leak_rate_hz=0.0, shot_noise_rate_hz=0.0, hot_pixel_fraction=0.0,
                         dead_pixel_fraction=0.0, max_event_rate_hz=0.0)
    assert thr is not None
    clean = simulate(scene, rig=rig, sensor=quiet, n_cycles=2, rng=seed,
                     thresholds=(thr[0], thr[1]))
    pri = ml.thresholds_prior(sensor, width=width, height=height, c_on=thr[0], c_off=thr[1],
                              sigma=thr[2])
    bound = ml.fisher_information(clean.events, width=width, height=height,
                                  start_us=int(rig.period_us), model=model, priors=pri,
                                  log_radiance=np.log(scene.radiance))
    extra: dict[str, Any] = {}
    img = reconstruct(rec, method="ml", ml_options={"thresholds": thr, "out": extra})[-1]
    rois = central_rois(scene.rois)
    rows = []
    for k in np.argsort(scene.truth):
        y0, y1, x0, x1 = rois[int(k)]
        g = np.log(img[y0:y1, x0:x1].astype(np.float64))
        crb = float(np.nanmedian(bound[y0:y1, x0:x1]))
        spread = float(np.nanstd(g)) if np.isfinite(g).sum() > 10 else float("nan")
        stated = float(np.nanmedian(extra["sigma_log"][-1][y0:y1, x0:x1]))
        rows.append({"lux": float(scene.truth[k]), "std_ln": spread, "crb_ln": crb,
                     "stated_ln": stated, "ratio": spread / crb if crb > 0 else None})
    out["crb"] = rows
    # the run that the bound's SNR gives with the measured biases: where an average capture
    # ends (a measured run's ends move with the capture where a level sits on the line)
    cal = res["ml + calibration"]
    lv = np.asarray(cal["levels_lux"])
    bound_snr = [-20 * math.log10(r["crb_ln"]) if r["crb_ln"] > 0 else np.nan for r in rows]
    by_bound = run_figures(lv, cal["means"], bound_snr)
    out["ml + calibration, bound's SNR"] = by_bound
    if out_dir is not None:
        curves = {("ml, last cycle" if name == "ml" else name):
                  {"snr_db": res[name]["snr_db"], "bias": res[name]["bias"],
                   "run": res[name]["run_index"]}
                  for name in ("ml", "ml, first cycle", "ml + calibration",
                               "ml fast + calibration")}
        stated_snr = [-20 * math.log10(r["stated_ln"]) if r["stated_ln"] > 0 else np.nan
                      for r in rows]
        plot_linear_run(lv, curves, out_dir / f"ml_run_{preset}.png", bound_snr_db=bound_snr,
                        stated_snr_db=stated_snr, min_snr_db=MIN_SNR_DB, max_bias=MAX_BIAS,
                        title=f"ml on the {LEVELS}-level chart, {preset}, the CLI's rig")
    print(f"  {preset:9s} {'bound SNR (ml + cal.)':22s} run {by_bound['run_db']:6.1f} "
          f"dB over {by_bound['run_levels']:2d} levels {by_bound['run_lux']}, mean SNR "
          f"{by_bound['run_mean_snr_db']:5.1f} dB", flush=True)
    ratios = [r["ratio"] for r in rows if r["ratio"] and math.isfinite(r["ratio"])]
    print(f"  {preset:9s} ml spread / bound over the levels: median {np.median(ratios):.2f} "
          f"(25-75 %: {np.percentile(ratios, 25):.2f}-{np.percentile(ratios, 75):.2f})",
          flush=True)
    return out


def speed(width: int = 1280, height: int = 720, repeats: int = 3) -> dict[str, Any]:
    """ml on one 1280x720 cycle of a scene spanning the range, beside numpy.bincount over
    the same events, and the paper's weightings (weighted sums) beside it; ml's fast fit
    with the sensor's own thresholds as the calibration (known to 1 %, stated 0.005: a
    flat-field calibration's precision)."""
    preset = "imx636"
    sensor = get_preset(preset)
    rig = default_rig(preset)
    gen = np.random.default_rng(0)
    scene = np.exp(gen.uniform(math.log(0.3), math.log(3e5), (height, width)))
    rec = simulate(scene, rig=rig, sensor=sensor, n_cycles=1, rng=1, sensor_seed=1)
    ev = rec.events
    w = CycleWindows(np.array([0]), rig.ramp_us)
    c_on, c_off = draw_thresholds(sensor, width=width, height=height,
                                  rng=np.random.default_rng(1))  # sensor_seed=1's
    off = np.random.default_rng(2).normal(1.0, 0.01, (2, height, width))
    fast = {"thresholds": (c_on * off[0], c_off * off[1], 0.005), "fast": True}
    reconstruct(rec, method="ml", windows=w)  # tables and compilation
    reconstruct(rec, method="ml", windows=w, ml_options=fast)
    weighted_sums(rec, w, method="exp")

    def med(f: Any) -> float:
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t0)
        return float(np.median(ts))

    def binc() -> None:
        idx = ev["y"].astype(np.int64) * width + ev["x"]
        np.bincount(idx, minlength=width * height)

    def paired(f: Any) -> tuple[float, float]:
        """Medians of ``f`` and of the bincount, each run of ``f`` right after one of the
        bincount (a figure of a few hundred ms moves with the machine's state: the
        reference is taken in the same state)."""
        tf, tb = [], []
        for _ in range(max(repeats, 5)):
            t0 = time.perf_counter()
            binc()
            t1 = time.perf_counter()
            f()
            tf.append(time.perf_counter() - t1)
            tb.append(t1 - t0)
        return float(np.median(tf)), float(np.median(tb))

    t_b = med(binc)
    t_ml = med(lambda: reconstruct(rec, method="ml", windows=w))
    t_fast = med(lambda: reconstruct(rec, method="ml", windows=w, ml_options=fast))
    t_b2 = med(binc)  # the reference again, after ml: the ratios from both
    t_b = float(np.median([t_b, t_b2]))
    t_w = {m: paired(lambda m=m: weighted_sums(rec, w, method=m)) for m in ("raw", "exp")}
    out = {"events": int(ev.size), "bincount_s": t_b, "ml_s": t_ml, "ml_ratio": t_ml / t_b,
           "ml_fast_s": t_fast, "ml_fast_ratio": t_fast / t_b,
           **{f"{m}_s": v[0] for m, v in t_w.items()},
           **{f"{m}_bincount_s": v[1] for m, v in t_w.items()},
           **{f"{m}_ratio": v[0] / v[1] for m, v in t_w.items()}}
    def rate(s: float) -> str:
        return f"{ev.size / s / 1e6:.1f} M events/s"

    # the rates beside the ratios: the bincount is bound by memory and the fits by
    # arithmetic, so the ratio moves with the machine (docs/ml.md)
    print(f"  speed 1280x720, {ev.size:,} events: bincount {t_b * 1e3:.0f} ms "
          f"({rate(t_b)}); ml {t_ml * 1e3:.0f} ms ({t_ml / t_b:.1f}x, {rate(t_ml)}); "
          f"ml --fast {t_fast * 1e3:.0f} ms ({t_fast / t_b:.1f}x, {rate(t_fast)}); "
          + "; ".join(f"{m} {v[0] * 1e3:.0f} ms against bincount {v[1] * 1e3:.0f} ms beside "
                      f"it ({v[0] / v[1]:.2f}x)" for m, v in t_w.items()), flush=True)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("out/bench"))
    ap.add_argument("--presets", nargs="*", default=["ideal", "v2e", "davis346", "imx636"])
    ap.add_argument("--width", type=int, default=400)
    ap.add_argument("--height", type=int, default=180)
    ap.add_argument("--no-speed", action="store_true")
    ap.add_argument("--captures", type=int, default=1,
                    help="ml's runs on this many captures of the chart (seeds 0, 1, ..)")
    ap.add_argument("--rig", type=Path, default=None,
                    help="a rig file to use instead of each preset's designed rig")
    ap.add_argument("--hold", action="store_true",
                    help="the readout holds a waiting pixel until it is read "
                         "(arbiter 'hold'; default: the preset's readout)")
    args = ap.parse_args(argv)
    retain_freed_memory()  # as the asynhdr command does
    rig = None
    if args.rig is not None:
        from asynhdr.io.rigfile import read_rig

        rig = read_rig(args.rig).rig
    results: dict[str, Any] = {"presets": {}}
    for p in args.presets:
        results["presets"][p] = run_preset(p, width=args.width, height=args.height, rig=rig,
                                           captures=args.captures, out_dir=args.out,
                                           hold=args.hold)
    if not args.no_speed:
        results["speed"] = speed()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_ml.json").write_text(json.dumps(results, indent=1, default=float))


if __name__ == "__main__":
    main()
