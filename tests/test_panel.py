"""LCD panel physics: static curve, inverse, fit, first-order dynamics, presets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from asynhdr.panel import (
    PRESETS,
    TN_FALL_US,
    TN_RISE_US,
    Panel,
    PanelCurve,
    PanelResponse,
    calibrate_curve,
    get_panel,
    tn_panel,
)

LN9 = math.log(9.0)


def _logistic_inverse(t, *, v_th, v_sat, cr, t_max, v_max, white=True):
    """Independent closed-form inverse of PanelCurve.logistic (same definition)."""
    v_mid = 0.5 * (v_th + v_sat)
    w = (v_sat - v_th) / (2 * LN9)

    def sig(v):
        return 1.0 / (1.0 + np.exp((v - v_mid) / w))

    s0, s1 = sig(0.0), sig(v_max)
    t_open, t_closed = (t_max, t_max / cr) if white else (t_max / cr, t_max)
    frac = (np.asarray(t) - t_closed) / (t_open - t_closed)
    s = s1 + frac * (s0 - s1)
    return v_mid + w * np.log(1.0 / s - 1.0)


# --- static curve ------------------------------------------------------------------

@pytest.mark.parametrize("white", [True, False])
def test_voltage_transmittance_round_trip(white):
    curve = PanelCurve.logistic(1.5, 3.0, contrast_ratio=1000.0, v_max_v=5.0,
                                normally_white=white)
    v = np.linspace(0.0, 5.0, 20_001)
    back = curve.voltage(curve.transmittance(v))
    assert np.max(np.abs(back - v)) < 1e-4
    t = np.geomspace(curve.t_min, curve.t_max, 5001)
    assert np.max(np.abs(curve.transmittance(curve.voltage(t)) - t) / t) < 1e-9


def test_measured_table_round_trip():
    v = np.array([0.0, 0.8, 1.4, 1.9, 2.3, 2.8, 3.5, 5.0])
    t = np.array([1.0, 0.98, 0.85, 0.55, 0.3, 0.1, 0.02, 0.004])
    curve = PanelCurve(v, t)
    # the table points are reproduced exactly, the interpolant is monotone
    np.testing.assert_allclose(curve.transmittance(v), t, rtol=0, atol=1e-15)
    dense = np.linspace(0, 5, 10_001)
    assert np.all(np.diff(curve.transmittance(dense)) < 0)
    assert np.max(np.abs(curve.voltage(curve.transmittance(dense)) - dense)) < 1e-4
    assert curve.contrast_ratio == pytest.approx(250.0)
    assert curve.normally_white


def test_logistic_matches_closed_form():
    cr, t_max = 800.0, 0.9
    curve = PanelCurve.logistic(1.2, 2.7, contrast_ratio=cr, t_max=t_max, v_max_v=4.5)
    assert curve.transmittance(0.0) == pytest.approx(t_max, abs=1e-15)
    assert curve.transmittance(4.5) == pytest.approx(t_max / cr, rel=1e-12)
    t = np.geomspace(t_max / cr * 1.001, t_max * 0.999, 400)
    expected = _logistic_inverse(t, v_th=1.2, v_sat=2.7, cr=cr, t_max=t_max, v_max=4.5)
    np.testing.assert_allclose(curve.voltage(t), expected, atol=1e-4)
    # 10 % and 90 % of the swing at the threshold and saturation voltages (the rescaling
    # to the exact end points moves them by < 1 %)
    swing = curve.t_max - curve.t_min
    assert (t_max - curve.transmittance(1.2)) / swing == pytest.approx(0.1, abs=0.005)
    assert (t_max - curve.transmittance(2.7)) / swing == pytest.approx(0.9, abs=0.005)


def test_negative_voltage_is_its_amplitude():
    curve = PanelCurve.logistic()
    v = np.array([0.5, 1.7, 2.2, 4.0])
    np.testing.assert_array_equal(curve.transmittance(-v), curve.transmittance(v))


def test_non_monotone_table_names_parameter():
    with pytest.raises(ValueError, match="transmittances") as exc:
        PanelCurve([0.0, 1.0, 2.0, 3.0], [1.0, 0.5, 0.6, 0.1])
    assert "index 2" in str(exc.value)
    with pytest.raises(ValueError, match="voltages_v"):
        PanelCurve([0.0, 1.0, 1.0, 3.0], [1.0, 0.5, 0.3, 0.1])
    with pytest.raises(ValueError, match="voltages_v"):
        PanelCurve([-1.0, 1.0, 2.0], [1.0, 0.5, 0.1])
    with pytest.raises(ValueError, match="transmittances"):
        PanelCurve([0.0, 1.0, 2.0], [1.2, 0.5, 0.1])
    with pytest.raises(ValueError, match="transmittances"):
        PanelCurve([0.0, 1.0, 2.0], [1.0, 0.5, 0.0])


def test_out_of_range_names_parameter():
    curve = PanelCurve.logistic(v_max_v=5.0, contrast_ratio=1000.0)
    with pytest.raises(ValueError, match="voltage_v"):
        curve.transmittance([1.0, 5.5])
    with pytest.raises(ValueError, match="transmittance"):
        curve.voltage([0.5, 0.0005])
    with pytest.raises(ValueError, match="v_threshold_v"):
        PanelCurve.logistic(3.0, 2.0)
    with pytest.raises(ValueError, match="contrast_ratio"):
        PanelCurve.logistic(contrast_ratio=1.0)


def test_fit_recovers_sweep_parameters():
    rng = np.random.default_rng(7)
    v = np.linspace(0.0, 5.0, 60)
    v_mid, w, t0, tinf = 2.1, 0.3, 0.97, 0.002
    t = tinf + (t0 - tinf) / (1.0 + np.exp((v - v_mid) / w))
    noisy = t + rng.normal(0.0, 0.002, v.size)
    curve, residual = PanelCurve.fit(v, noisy)
    assert curve.params["v_threshold_v"] == pytest.approx(v_mid - w * LN9, abs=0.02)
    assert curve.params["v_saturation_v"] == pytest.approx(v_mid + w * LN9, abs=0.02)
    assert residual == pytest.approx(0.002, rel=0.3)
    assert np.max(np.abs(curve.transmittance(v) - t)) < 0.004
    # a noisy sweep is not monotone: the table method refuses it, the fit does not
    with pytest.raises(ValueError, match="transmittances"):
        calibrate_curve(v, noisy, method="table")
    assert calibrate_curve(v, noisy).normally_white
    # repeated and negative voltages: averaged by amplitude
    tab = calibrate_curve(np.r_[-v[::6], v[::6]], np.r_[t[::6], t[::6]], method="table")
    np.testing.assert_allclose(tab.transmittances, t[::6])


# --- dynamics ----------------------------------------------------------------------

@pytest.mark.parametrize(("start", "end", "tau_name"), [(0.1, 0.9, "rise_us"),
                                                         (0.9, 0.1, "fall_us")])
def test_step_response_after_tau(start, end, tau_name):
    resp = PanelResponse(rise_us=2000.0, fall_us=500.0)
    tau_us = getattr(resp, tau_name)
    fs = 1e6  # 1 µs samples: tau is a whole number of samples
    n_tau = round(tau_us)
    y = resp.simulate(np.full(3 * n_tau, end), sample_rate_hz=fs, initial=start,
                      periodic=False)
    frac = (y[n_tau] - start) / (end - start)
    assert abs(frac - (1.0 - 1.0 / math.e)) < 1e-6
    # the other time constant would give a different answer
    other = 500.0 if tau_name == "rise_us" else 2000.0
    assert abs(frac - (1.0 - math.exp(-tau_us / other))) > 0.1
    # ten-to-ninety in tau ln 9
    i10 = np.argmax((y - start) / (end - start) >= 0.1)
    i90 = np.argmax((y - start) / (end - start) >= 0.9)
    assert (i90 - i10) == pytest.approx(tau_us * LN9, abs=2)


def test_linear_hold_ramp_is_exact():
    resp = PanelResponse(rise_us=1000.0, fall_us=300.0)
    fs = 20_000.0  # 50 µs samples
    n = 200
    t_us = np.arange(n) * 50.0
    slope = 1e-4  # per µs
    x = slope * t_us
    y = resp.simulate(x, sample_rate_hz=fs, initial=0.0, periodic=False, hold="linear")
    tau = 1000.0
    expected = slope * (t_us - tau) + slope * tau * np.exp(-t_us / tau)
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-13)


def test_linear_hold_direction_switch_matches_fine_sampling():
    # a triangle drive forces switches between rising and falling inside samples
    resp = PanelResponse(rise_us=800.0, fall_us=200.0)
    fs = 10_000.0
    x = np.r_[np.linspace(0.1, 0.9, 15), np.linspace(0.85, 0.2, 12), np.full(10, 0.6)]
    y = resp.simulate(x, sample_rate_hz=fs, initial=0.5, periodic=False, hold="linear")
    up = 2000
    fine_x = np.interp(np.arange((x.size - 1) * up + 1) / up, np.arange(x.size), x)
    fine = resp.simulate(fine_x, sample_rate_hz=fs * up, initial=0.5, periodic=False)
    np.testing.assert_allclose(y[:-1], fine[::up][:-1], atol=2e-4)


def test_periodic_steady_state_square_wave():
    tau = 1000.0
    resp = PanelResponse(rise_us=tau, fall_us=tau)
    fs, half = 1e6, 700
    drive = np.r_[np.ones(half), np.zeros(half)]
    y = resp.simulate(drive, sample_rate_hz=fs)
    # symmetric first order: the minimum is 1 / (1 + exp(h / tau))
    assert y[0] == pytest.approx(1.0 / (1.0 + math.exp(half / tau)), abs=1e-12)
    # a second cycle started from y[0] repeats the first
    again = resp.simulate(np.r_[drive, drive], sample_rate_hz=fs, initial=y[0], periodic=False)
    np.testing.assert_allclose(again[drive.size:], y, atol=1e-12)
    # asymmetric: the rise and fall time constants set different settling
    asym = PanelResponse(rise_us=3000.0, fall_us=300.0).simulate(drive, sample_rate_hz=fs)
    assert asym.max() < y.max() and asym.min() < y.min()


def test_response_rejects_bad_values():
    with pytest.raises(ValueError, match="rise_us"):
        PanelResponse(rise_us=0.0)
    with pytest.raises(ValueError, match="fall_us"):
        PanelResponse(fall_us=float("nan"))
    with pytest.raises(ValueError, match="sample_rate_hz"):
        PanelResponse().simulate([0.1, 0.2], sample_rate_hz=-1.0)
    with pytest.raises(ValueError, match="hold"):
        PanelResponse().simulate([0.1, 0.2], sample_rate_hz=1e3, hold="cubic")  # type: ignore[arg-type]


# --- panel and presets ---------------------------------------------------------------

def test_panel_simulate_goes_through_curve():
    panel = tn_panel()
    fs = 100_000.0
    v = np.r_[np.full(500, 5.0), np.full(500, 0.0)]  # closed, then released
    y = panel.simulate(v, sample_rate_hz=fs, periodic=False)
    assert y[0] == pytest.approx(panel.t_min)
    # opening a normally-white panel is the slow relaxation: rise_us
    n = round(TN_RISE_US * fs / 1e6)
    frac = (y[500 + n] - panel.t_min) / (panel.t_max - panel.t_min)
    assert frac == pytest.approx(1 - 1 / math.e, abs=1e-9)
    np.testing.assert_array_equal(panel.simulate(-v, sample_rate_hz=fs, periodic=False), y)


def test_presets():
    assert set(PRESETS) >= {"tn_generic", "tn_generic_nb", "fast_shutter"}
    white, black = get_panel("tn_generic"), get_panel("tn_generic_nb")
    assert isinstance(white, Panel)
    assert white.curve.normally_white and not black.curve.normally_white
    # the relaxation (field removed) is the slow direction in both
    assert white.response.rise_us == TN_RISE_US > white.response.fall_us == TN_FALL_US
    assert black.response.fall_us == TN_RISE_US > black.response.rise_us == TN_FALL_US
    assert white.contrast_ratio == pytest.approx(1000.0)
    assert white.t_min == pytest.approx(1e-3)
    with pytest.raises(ValueError, match="unknown panel preset"):
        get_panel("ips")
