"""Chart and image metrics against values computed by hand or independently here."""

from __future__ import annotations

import math

import numpy as np
import pytest

from asynhdr.metrics import (
    PatchStats,
    central_rois,
    compare_images,
    distinct_grey_levels,
    dynamic_range,
    dynamic_range_steps,
    fit_response,
    fit_scale,
    input_referred_snr,
    log_rmse,
    mean_snr_db,
    patch_event_fraction,
    patch_stats,
    pu21_decode,
    pu21_encode,
    pu21_psnr,
    radiometric_error,
    relative_error,
    ssim_tonemapped,
)


def test_patch_stats_and_paper_snr_by_hand() -> None:
    img = np.zeros((4, 8))
    img[:, :4] = [[10, 10, 12, 12]] * 4  # mean 11, std 1 -> 20 log10(11)
    img[:, 4:] = 5.0
    st = patch_stats(img, {0: (0, 4, 0, 4), 1: (0, 4, 4, 8)})
    assert st.mean.tolist() == [11.0, 5.0]
    assert st.std.tolist() == [1.0, 0.0]
    assert st.snr_db[0] == pytest.approx(20 * math.log10(11.0))
    assert math.isinf(st.snr_db[1])
    s = mean_snr_db(st)
    # the noiseless patch is counted apart, not averaged in
    assert (s.mean_db, s.n_patches, s.n_noiseless) == (pytest.approx(20 * math.log10(11)), 1, 1)
    assert math.isinf(mean_snr_db(PatchStats(np.array([3.0]), np.array([0.0]))).mean_db)
    two = PatchStats(np.array([10.0, 10.0]), np.array([1.0, 10.0]))
    assert mean_snr_db(two).mean_db == pytest.approx(10.0)  # (20 + 0) / 2
    only = mean_snr_db(two, responding=[False, True])
    assert (only.mean_db, only.n_patches, only.n_total) == (pytest.approx(0.0), 1, 2)
    assert math.isnan(mean_snr_db(two, responding=[False, False]).mean_db)


def test_central_rois_fixed_count() -> None:
    rois = {0: (0, 20, 0, 30), 1: (10, 27, 40, 57)}
    c = central_rois(rois, shape=(16, 16))
    assert c[0] == (2, 18, 7, 23) and c[1] == (10, 26, 40, 56)
    assert all((y1 - y0) * (x1 - x0) == 256 for y0, y1, x0, x1 in c.values())
    with pytest.raises(ValueError, match="patch 0 region is 30x10"):
        central_rois({0: (0, 10, 0, 30)}, shape=(16, 16))


def test_patch_event_fraction() -> None:
    cnt = np.zeros((2, 4), int)
    cnt[0, :3] = 1
    assert patch_event_fraction(cnt, {0: (0, 2, 0, 2), 1: (0, 2, 2, 4)}).tolist() == [0.5, 0.25]


def test_input_referred_snr_of_a_log_response() -> None:
    # img = a ln L + b: dR/d ln L = a everywhere, so SNR_in = a / sigma exactly
    lum = 10.0 ** np.arange(6)
    a, sigma = 3.0, np.array([0.5, 1.0, 2.0, 3.0, 6.0, 12.0])
    st = PatchStats(a * np.log(lum) + 7.0, sigma)
    assert input_referred_snr(st, lum) == pytest.approx(a / sigma)
    fit = fit_response(lum, st.mean)
    assert fit.increasing and fit.slope_ln == pytest.approx(np.full(6, a))


def test_input_referred_snr_of_a_linear_response() -> None:
    # img = g L on a geometric chart of ratio r: the secants in ln L around L_i are
    # g L_i (1 - 1/r) / ln r (below) and g L_i (r - 1) / ln r (above); the smaller counts
    r, g = 4.0, 2.5
    lum = r ** np.arange(5)
    sd = np.sqrt(g * lum)
    st = PatchStats(g * lum, sd)
    below = g * lum * (1 - 1 / r) / math.log(r)
    above = g * lum * (r - 1) / math.log(r)
    expect = np.minimum(below, above) / sd
    expect[0] = above[0] / sd[0]  # one-sided at the ends
    assert input_referred_snr(st, lum) == pytest.approx(expect)
    # a decreasing response is found as such; the slope is its magnitude
    down = fit_response(lum, -g * lum)
    assert not down.increasing and down.slope_ln[1:] == pytest.approx(below[1:])


def test_flat_response_has_no_dynamic_range() -> None:
    lum = 10.0 ** np.arange(8)
    for std in (0.0, 0.01, 1.0):
        st = PatchStats(np.full(8, 42.0), np.full(8, std))
        assert dynamic_range(st, lum).dr_db == 0.0
        assert dynamic_range_steps(st, -np.log10(lum)).dr_db == 0.0
    # a flat floor with noise-driven wiggles of the means does not count either
    rng = np.random.default_rng(0)
    st = PatchStats(42.0 + rng.normal(0, 0.01, 8), np.full(8, 1.0))
    assert dynamic_range(st, lum).dr_db == 0.0


def test_dynamic_range_emva_by_hand() -> None:
    lum = 10.0 ** np.arange(8)  # 1 .. 1e7
    a = 1.0
    mean = a * np.log(lum)
    sigma = np.full(8, 0.5)  # SNR_in = 2
    sigma[[0, 6, 7]] = 5.0  # SNR_in = 0.2: out
    dr = dynamic_range(PatchStats(mean, sigma), lum)
    assert dr.dr_db == pytest.approx(20 * 4)  # patches 1..5: L 10 .. 1e5
    assert (dr.l_min, dr.l_max, dr.n_patches) == (10.0, 1e5, 5)
    assert dr.counted.tolist() == [False, True, True, True, True, True, False, False]
    # a patch without events never counts, whatever its numbers
    ev = np.ones(8, bool)
    ev[2] = False
    cut = dynamic_range(PatchStats(mean, sigma), lum, has_events=ev)
    assert cut.dr_db == pytest.approx(20 * 2)  # 1e3 .. 1e5 beats 10 alone
    # a response that turns back ends the run (the fit pools it flat: slope 0)
    back = mean.copy()
    back[4] = back[2]
    assert dynamic_range(PatchStats(back, np.full(8, 0.01)), lum).dr_db < 20 * 7
    # the order of the patches does not matter
    p = np.random.default_rng(1).permutation(8)
    assert dynamic_range(PatchStats(mean[p], sigma[p]), lum[p]).dr_db == pytest.approx(80.0)


def test_dynamic_range_steps_by_hand() -> None:
    st = PatchStats(np.array([100.0, 10.0, 9.5, 1.0, 0.9]), np.array([1.0, 1.0, 1.0, 0.1, 1.5]))
    # steps: 90 > 2 yes; 0.5 > 2 no; 8.5 > 1.1 yes; 0.1 > 1.6 no: two runs of one step
    dr = dynamic_range_steps(st, np.arange(5.0), illuminance=1000.0)
    assert dr.dr_db == pytest.approx(20.0)
    assert (dr.d_brightest, dr.d_darkest) == (0.0, 1.0)
    assert (dr.l_min, dr.l_max) == (pytest.approx(100.0), pytest.approx(1000.0))
    wide = PatchStats(st.mean, np.array([1.0, 1.0, 0.1, 0.1, 0.1]))  # 0.5 > 1.1? no
    assert dynamic_range_steps(wide, np.arange(5.0)).dr_db == pytest.approx(20.0)
    tight = PatchStats(st.mean, np.full(5, 0.01))
    assert dynamic_range_steps(tight, np.arange(5.0)).dr_db == pytest.approx(80.0)
    no_ev = dynamic_range_steps(tight, np.arange(5.0), has_events=[1, 1, 0, 1, 1])
    assert no_ev.dr_db == pytest.approx(20.0)


def test_radiometric_error_after_one_scale() -> None:
    st = PatchStats(np.array([2.0, 4.0, 8.8]), np.zeros(3))
    err, s = radiometric_error(st, np.array([1.0, 2.0, 4.0]))
    assert s == pytest.approx(0.5)  # median of 0.5, 0.5, 0.4545
    assert err == pytest.approx([0.0, 0.0, 0.1])
    st2 = PatchStats(np.array([1.0]), np.array([0.3]))
    assert radiometric_error(st2, np.array([1.0]))[0] == pytest.approx([0.3])


def _pu21_by_hand(y: float) -> float:
    # the banding + glare parameters of Mantiuk and Azimi 2021, typed out again
    p = [0.353487901, 0.3734658629, 8.277049286e-05, 0.9062562627, 0.09150303166,
         0.9099517204, 596.3148142]
    y = min(max(y, 0.005), 10000.0)
    return p[6] * (math.pow((p[0] + p[1] * y ** p[3]) / (1 + p[2] * y ** p[3]), p[4]) - p[5])


def test_pu21_encode_against_the_formula() -> None:
    ys = [0.001, 0.005, 0.1, 1.0, 10.0, 100.0, 1000.0, 10000.0, 50000.0]
    assert pu21_encode(ys) == pytest.approx([_pu21_by_hand(y) for y in ys], rel=1e-12)
    # PU21 matches 8-bit sRGB's range on an SDR display: 100 cd/m^2 encodes to about 256
    assert pu21_encode(100.0) == pytest.approx(256.0, rel=0.005)
    assert np.all(np.diff(pu21_encode(np.logspace(-2.3, 4, 50))) > 0)
    y = np.logspace(math.log10(0.005), 4, 30)
    assert pu21_decode(pu21_encode(y)) == pytest.approx(y, rel=1e-9)
    with pytest.raises(ValueError, match="unknown variant"):
        pu21_encode(1.0, variant="nope")


def test_pu21_psnr_by_hand() -> None:
    ref = np.full((4, 4), 100.0)
    test = ref.copy()
    test[0, 0] = 200.0  # one pixel of 16 off
    d = _pu21_by_hand(200.0) - _pu21_by_hand(100.0)
    expect = 10 * math.log10(256.0**2 / (d * d / 16))
    assert pu21_psnr(test, ref) == pytest.approx(expect, rel=1e-12)
    assert math.isinf(pu21_psnr(ref, ref))
    mask = np.ones((4, 4), bool)
    mask[0, 0] = False
    assert math.isinf(pu21_psnr(test, ref, mask=mask))


def test_log_and_relative_errors() -> None:
    t = np.array([[1.0, 2.0], [4.0, 8.0]])
    big = np.tile(t, (5, 5))
    assert log_rmse(2 * t, t) == pytest.approx(1.0)  # one stop everywhere
    assert fit_scale(2 * t, t) == pytest.approx(0.5)
    assert relative_error(1.1 * t, t) == pytest.approx(0.1)
    holes = 2 * t
    holes[0, 0] = 0.0  # read as the smallest positive value, 4: log2(4/1) = 2 stops
    assert log_rmse(holes, t) == pytest.approx(math.sqrt((4 + 1 + 1 + 1) / 4))
    c = compare_images(3 * big, big)
    assert c.scale == pytest.approx(1 / 3) and c.log_rmse_stops == pytest.approx(0.0, abs=1e-12)
    assert math.isinf(c.pu21_psnr_db) and c.ssim == pytest.approx(1.0)


def test_ssim_on_the_tonemapped_pair_matches_scikit_image() -> None:
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(3)
    t = np.exp(rng.normal(0, 2, (40, 50)))
    img = t * np.exp(rng.normal(0, 0.3, t.shape))
    lo, hi = np.percentile(t, [0.5, 99.5])

    def tm(x: np.ndarray) -> np.ndarray:
        return (np.log(np.clip(x, lo, hi)) - np.log(lo)) / (np.log(hi) - np.log(lo))

    expect = structural_similarity(tm(img), tm(t), data_range=1.0)
    assert ssim_tonemapped(img, t) == pytest.approx(expect, rel=1e-9)
    assert ssim_tonemapped(t, t) == pytest.approx(1.0)


def test_distinct_grey_levels() -> None:
    img = np.repeat(np.array([[1.0, 10.0, 100.0]]), 4, axis=0)
    assert distinct_grey_levels(img) == 3
    assert distinct_grey_levels(np.outer(np.ones(10), np.logspace(0, 3, 1000))) == 256


def test_linear_run_takes_the_scale_of_the_levels_it_measures() -> None:
    from asynhdr.metrics import linear_run

    lv = 10.0 ** np.arange(8)
    # a unit of 2 from level 4 up; the four darkest read 50, 20, 10 and 5x too high
    mu = 2.0 * lv
    mu[:4] *= np.array([50.0, 20.0, 10.0, 5.0])
    mu[5] *= 1.04  # within 5 %
    snr = np.full(8, 30.0)
    snr[7] = 19.0  # the brightest is too noisy
    run = linear_run(lv, mu, snr)
    assert (run.lo, run.hi) == (4, 6)
    assert run.span_db == pytest.approx(40.0)
    assert run.mean_snr_db == pytest.approx(30.0)
    assert run.scale == pytest.approx(0.5, rel=0.05)
    # one scale from all eight levels (their median ratio, 0.29) fits none of them
    s_all = float(np.exp(np.median(np.log(lv / mu))))
    assert np.all(np.abs(mu * s_all / lv - 1.0) > 0.05)
    # nothing loud enough: no run
    none = linear_run(lv, mu, np.full(8, 10.0))
    assert none.n_levels == 0 and none.span_db == 0.0
    with pytest.raises(ValueError, match="ascending"):
        linear_run(lv[::-1], mu, snr)


def test_mosaic_draws_holes_in_their_own_colour(tmp_path) -> None:
    # a bright scene whose method left its brightest pixel without a value: the hole is
    # drawn magenta, not black (it would read as a dark spot), and the truth as it is
    import matplotlib.image as mpimg

    from asynhdr.plots import HOLE_RGB, plot_mosaic

    truth = np.geomspace(1.0, 1e4, 64 * 64).reshape(64, 64)
    img = truth.copy()
    img[40:, 40:] = np.nan
    path = plot_mosaic([truth, img], ["truth", "method"], tmp_path / "m.png", columns=2,
                       reference=truth)
    rgb = (mpimg.imread(path)[..., :3] * 255).round().astype(int)
    magenta = np.all(np.abs(rgb - np.array(HOLE_RGB)) <= 2, axis=2)
    left, right = magenta[:, : rgb.shape[1] // 2], magenta[:, rgb.shape[1] // 2:]
    assert right.sum() > 20 and left.sum() == 0


def test_k_sweep_legend_names_each_sensor_and_both_line_styles(tmp_path, monkeypatch) -> None:
    import asynhdr.plots as plots

    seen = {}

    def keep(fig, path):
        seen["fig"] = fig
        return tmp_path / "k.png"

    monkeypatch.setattr(plots, "_save", keep)
    row = {"snr_db_raw": 12.0, "dr_db_raw": 30.0, "snr_db_cmap": 20.0, "dr_db_cmap": 60.0}
    quiet = {"snr_db_raw": None, "dr_db_raw": 80.0, "snr_db_cmap": None, "dr_db_cmap": 80.0}
    sweeps = {"ideal": [{"k": k, **quiet} for k in (1.0, 10.0)],
              "v2e": [{"k": k, **row} for k in (1.0, 10.0)]}
    plots.plot_k_sweep(sweeps, tmp_path / "k.png")
    fig = seen["fig"]
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels[1:] == ["v2e", "no c-map", "with c-map"]
    assert labels[0].startswith("ideal (no noise")
    # the legend sits below the panels, over none of the data
    assert not any(ax.get_legend() for ax in fig.axes)
    styles = [h.get_linestyle() for h in fig.legends[0].legend_handles[-2:]]
    assert styles == ["--", "-"]


def test_chart_response_marks_silent_patches_on_a_floor_not_as_levels(tmp_path,
                                                                      monkeypatch) -> None:
    """A patch where nothing fires has a mean near 0: drawn as a level it would stretch the
    log axis over ten decades and read as a response. It is an x on a floor line below
    every responding patch instead, and no point of the method's line."""
    from types import SimpleNamespace

    import asynhdr.plots as plots

    seen = {}

    def keep(fig, path):
        seen["fig"] = fig
        return tmp_path / "r.png"

    monkeypatch.setattr(plots, "_save", keep)
    truth = np.array([1.0, 10.0, 100.0, 1000.0])
    mean = np.array([1e-15, 0.1, 1.0, 10.0])  # the first patch never fired
    responding = np.array([False, True, True, True])
    r = SimpleNamespace(method="ttfe", with_cmap=True, responding=responding,
                        stats=SimpleNamespace(mean=mean),
                        dr=SimpleNamespace(dr_db=40.0, counted=np.ones(4, bool)),
                        dr_steps=SimpleNamespace(dr_db=40.0))
    result = SimpleNamespace(scene=SimpleNamespace(truth=truth), results=[r], frame=[])
    plots.plot_chart_response(result, tmp_path / "r.png")
    ax = seen["fig"].axes[0]
    line = ax.lines[0]
    y = np.asarray(line.get_ydata(), dtype=float)
    assert np.isnan(y[0]) and np.allclose(y[1:], [0.1, 1.0, 10.0])  # median 1.0
    circles = ax.lines[1]
    assert list(circles.get_xdata()) == [10.0, 100.0, 1000.0]
    floor = ax.lines[2]  # the dotted floor: a tenth of the lowest responding level
    assert np.allclose(floor.get_ydata(), 0.01)
    cross = ax.lines[3]
    assert list(cross.get_xdata()) == [1.0] and cross.get_marker() == "x"
    assert ax.get_ylim()[0] > 1e-3
    assert "do not respond" in ax.get_title()


def test_snr_per_level_joins_only_the_patches_that_respond(tmp_path, monkeypatch) -> None:
    """The line runs through the responding patches alone; a silent patch's SNR (here a
    flattering 40 dB) is a hollow marker off the line."""
    from types import SimpleNamespace

    import asynhdr.plots as plots

    seen = {}

    def keep(fig, path):
        seen["fig"] = fig
        return tmp_path / "s.png"

    monkeypatch.setattr(plots, "_save", keep)
    snr = np.array([10.0, 20.0, 40.0])
    r = SimpleNamespace(method="exp", with_cmap=True, responding=np.array([True, True, False]),
                        stats=SimpleNamespace(snr_db=snr),
                        snr=SimpleNamespace(mean_db=15.0, n_patches=2))
    r_raw = SimpleNamespace(**{**vars(r), "with_cmap": False})
    result = SimpleNamespace(scene=SimpleNamespace(densities=np.array([0.0, 1.0, 2.0])),
                             results=[r_raw, r], frame=[])
    plots.plot_snr_per_level(result, tmp_path / "s.png")
    ax = seen["fig"].axes[1]  # with c-map
    joined, hollow = ax.lines
    y = np.asarray(joined.get_ydata(), dtype=float)
    assert np.allclose(y[:2], [10.0, 20.0]) and np.isnan(y[2])
    assert list(hollow.get_ydata()) == [40.0] and hollow.get_markerfacecolor() == "none"


def test_linear_run_plot_is_written_as_a_png(tmp_path) -> None:
    import asynhdr.plots as plots

    lv = np.array([0.1, 1.0, 10.0])
    out = plots.plot_linear_run(lv, {"ml": {"snr_db": [15.0, 25.0, 30.0],
                                            "bias": [0.01, 0.0, 0.02], "run": None}},
                                tmp_path / "run.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_linear_run_plot_marks_the_run(tmp_path, monkeypatch) -> None:
    """Levels 1 to 3 form the run: filled markers there, hollow ones at 0 and 4 (one too
    noisy, one biased); the 20 dB and 5 % lines and the bound's curve are drawn, and the
    legend gives the run's span."""
    import asynhdr.plots as plots

    seen = {}

    def keep(fig, path):
        seen["fig"] = fig
        return tmp_path / "r.png"

    monkeypatch.setattr(plots, "_save", keep)
    lv = np.array([0.1, 1.0, 10.0, 100.0, 1000.0])
    plots.plot_linear_run(lv, {"ml": {"snr_db": [15.0, 25.0, 30.0, 28.0, 26.0],
                                      "bias": [0.01, 0.0, 0.02, -0.03, 0.2], "run": [1, 3]}},
                          tmp_path / "r.png", bound_snr_db=[16.0, 25.5, 30.5, 28.5, 26.5])
    ax_s, ax_b = seen["fig"].axes
    bound, _, filled, hollow = ax_s.lines[:4]
    assert list(bound.get_ydata()) == [16.0, 25.5, 30.5, 28.5, 26.5]
    assert list(filled.get_xdata()) == [1.0, 10.0, 100.0]
    assert list(hollow.get_xdata()) == [0.1, 1000.0] and hollow.get_markerfacecolor() == "none"
    assert any(list(ln.get_ydata()) == [20.0, 20.0] for ln in ax_s.lines)
    assert any(list(ln.get_ydata()) == [5.0, 5.0] for ln in ax_b.lines)
    assert "run 40.0 dB" in ax_s.get_legend().get_texts()[1].get_text()
