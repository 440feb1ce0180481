"""Waveform design with pre-emphasis, its export, and ``asynhdr waveform``."""

from __future__ import annotations

import math

import numpy as np
import pytest
from typer.testing import CliRunner

import asynhdr.cli.waveform  # noqa: F401  (registers the command)
from asynhdr.cli import app
from asynhdr.panel import get_panel, tn_panel
from asynhdr.rig import Rig, Waveform
from asynhdr.simulate import simulate
from asynhdr.waveform import DEFAULT_CARRIER_HZ, design, read_csv
from asynhdr.waveform_io import (
    channel_scale,
    read_arb,
    read_column_csv,
    read_siglent_csv,
    read_waveform_files,
)

PERIOD_US = 50_000
FS = 200_000.0
RAMP = 0.9


def _targets(**kw):
    # The targets of the brief, written out: exponential T1, linear T2, 50 ms, 0.9 ramp.
    rig = Rig(period_us=PERIOD_US, ramp_fraction=RAMP, t1_shape="exponential",
              t2_shape="linear", t2_stop=0.5, **kw)
    return rig.waveforms()


def _design(p1, p2, **kw):
    t1, t2 = _targets()
    return design(t1, t2, panel1=p1, panel2=p2, period_us=PERIOD_US, sample_rate_hz=FS,
                  ramp_fraction=RAMP, **kw)


def _report(label, d):
    for k, ch in enumerate(d.channels, start=1):
        print(f"{label} T{k} {ch.panel.name}: with pre-emphasis {ch.rms_error_pct:.3f} % "
              f"(ramp {ch.rms_error_ramp_pct:.3f} %), without {ch.naive_rms_error_pct:.3f} % "
              f"(ramp {ch.naive_rms_error_ramp_pct:.3f} %)")


def _exact_zoh(x, y0, rise_us, fall_us, fs):
    """Independent exact first-order update, written out here."""
    dt = 1e6 / fs
    y = np.empty(x.size + 1)
    y[0] = y0
    for n in range(x.size):
        tau = rise_us if x[n] > y[n] else fall_us
        y[n + 1] = x[n] - (x[n] - y[n]) * math.exp(-dt / tau)
    return y


def test_pre_emphasis_follows_default_targets_within_1pct():
    d = _design(get_panel("fast_shutter"), get_panel("fast_shutter"))
    _report("fast_shutter", d)
    for ch in d.channels:
        assert ch.rms_error_pct < 1.0           # the whole cycle, return included
        assert ch.naive_rms_error_pct > 1.0     # the direct command does not make it
        assert ch.naive_rms_error_pct > 5 * ch.rms_error_pct


def test_tn_panels_ramp_and_return_reported_apart():
    d = _design(get_panel("tn_generic"), get_panel("tn_generic_nb"))
    _report("tn_generic/tn_generic_nb", d)
    t1, t2 = d.channels
    # pre-emphasis helps everywhere
    for ch in d.channels:
        assert ch.rms_error_pct < 0.5 * ch.naive_rms_error_pct
        assert ch.rms_error_ramp_pct < 0.5 * ch.naive_rms_error_ramp_pct
        assert ch.rms_log_error_ramp < ch.naive_rms_log_error_ramp
        # the return is too fast for TN time constants: the cycle error exceeds the ramp's
        assert ch.rms_error_pct > ch.rms_error_ramp_pct
    # the reference panel (normally black: the return is field driven) stays within 1 %
    assert t2.rms_error_ramp_pct < 1.0
    # the scene panel does not reach its floor before the next cycle starts
    assert t1.result[0] > 10 * t1.target[0]


def test_result_is_exact_simulation_of_commands():
    panel1, panel2 = get_panel("tn_generic"), get_panel("tn_generic_nb")
    d = _design(panel1, panel2)
    assert d.n_samples == PERIOD_US * FS / 1e6 == 10_000
    for ch, panel in zip(d.channels, (panel1, panel2), strict=True):
        x = panel.curve.transmittance(ch.voltage_v)
        np.testing.assert_allclose(x, ch.command, atol=1e-12)
        assert np.all((ch.command >= panel.t_min) & (ch.command <= panel.t_max))
        y = _exact_zoh(x, ch.result[0], panel.response.rise_us, panel.response.fall_us, FS)
        np.testing.assert_allclose(y[:-1], ch.result, atol=1e-12)
        assert y[-1] == pytest.approx(ch.result[0], abs=1e-12)  # periodic steady state
        # wherever the command did not clip, the next sample lands on the target
        free = (ch.command[:-1] > panel.t_min + 1e-9) & (ch.command[:-1] < panel.t_max - 1e-9)
        np.testing.assert_allclose(ch.result[1:][free], ch.target[1:][free], atol=1e-9)
        assert free.mean() > 0.7


def test_without_pre_emphasis_commands_target_directly():
    panel = get_panel("fast_shutter")
    d = _design(panel, panel, pre_emphasis=False)
    for ch in d.channels:
        np.testing.assert_allclose(panel.curve.transmittance(ch.voltage_v), ch.target,
                                   atol=1e-12)
        np.testing.assert_array_equal(ch.result, ch.naive_result)
        assert ch.rms_error_pct == ch.naive_rms_error_pct


def test_design_errors():
    t1, t2 = _targets()
    p = get_panel("tn_generic")
    with pytest.raises(ValueError, match="period_us"):
        design(t1, t2, panel1=p, panel2=p, period_us=0, sample_rate_hz=FS)
    with pytest.raises(ValueError, match="sample_rate_hz"):
        design(t1, t2, panel1=p, panel2=p, period_us=PERIOD_US, sample_rate_hz=0.0)
    with pytest.raises(ValueError, match="whole number"):
        design(t1, t2, panel1=p, panel2=p, period_us=50_001, sample_rate_hz=FS)
    low = tn_panel(contrast_ratio=100.0)  # floor 0.01 above the target's 0.001
    with pytest.raises(ValueError, match=r"target_t1: sample 0 \(t = 0 µs\)") as exc:
        design(t1, t2, panel1=low, panel2=p, period_us=PERIOD_US, sample_rate_hz=FS)
    assert "0.001" in str(exc.value) and "panel1" in str(exc.value)
    with pytest.raises(ValueError, match="carrier_hz"):
        design(t1, t2, panel1=p, panel2=p, period_us=PERIOD_US, sample_rate_hz=FS,
               carrier_hz=3000.0)


def test_carrier_keeps_transmittance():
    p1, p2 = get_panel("tn_generic"), get_panel("tn_generic_nb")
    dc = _design(p1, p2, carrier_hz=None)
    ac = _design(p1, p2)  # the AC carrier is the default
    assert ac.carrier_hz == DEFAULT_CARRIER_HZ == 1000.0 and dc.carrier_hz is None
    for a, b in zip(ac.channels, dc.channels, strict=True):
        np.testing.assert_array_equal(np.abs(a.voltage_v), b.voltage_v)
        np.testing.assert_array_equal(a.result, b.result)
        signs = np.sign(a.voltage_v[a.voltage_v != 0])
        assert np.all(signs[:100] == 1) and np.all(signs[100:200] == -1)


def test_csv_round_trip(tmp_path):
    d = _design(get_panel("tn_generic"), get_panel("tn_generic_nb"))
    path = d.to_csv(tmp_path / "out" / "design.csv")
    assert sorted(p.name for p in path.parent.iterdir()) == ["design.csv"]
    time_s, v1, v2, header = read_csv(path)
    np.testing.assert_allclose(time_s, np.arange(10_000) / FS, rtol=1e-11, atol=0)
    np.testing.assert_allclose(v1, d.samples(1), rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(v2, d.samples(2), rtol=1e-11, atol=1e-12)
    assert header["sample_rate_hz"] == FS
    assert header["period_us"] == PERIOD_US
    assert header["panel1"]["response"]["rise_us"] == 3000.0
    assert header["panel2"]["curve"]["normally_white"] is False
    with open(path, encoding="utf-8") as fh:
        first = [next(fh) for _ in range(20)]
    assert first[0].startswith("#") and "time_s,v1_v,v2_v\n" in first
    with pytest.raises(ValueError, match="channel"):
        d.samples(3)


def test_read_csv_rejects_other_columns(tmp_path):
    p = tmp_path / "x.csv"
    p.write_text("# a: 1\nt,v1,v2\n0,1,2\n", encoding="utf-8")
    with pytest.raises(ValueError, match="time_s,v1_v,v2_v"):
        read_csv(p)


def test_to_waveforms_drive_the_simulator():
    d = _design(get_panel("tn_generic"), get_panel("tn_generic_nb"))
    w1, w2 = d.to_waveforms()
    assert isinstance(w1, Waveform) and isinstance(w2, Waveform)
    assert w1.values.size == d.n_samples + 1 and w1.values[-1] == w1.values[0]
    np.testing.assert_allclose(w1(np.arange(d.n_samples) / d.n_samples), d.channels[0].result,
                               atol=1e-12)
    rig = Rig(t1=w1, t2=w2)
    assert rig.waveforms() == (w1, w2)
    rec = simulate(np.full((4, 4), 100.0), rig=rig, sensor="ideal")
    ev = rec.events
    assert ev.size > 0 and (ev["p"] > 0).any()
    assert ev["t"].max() <= rig.period_us
    # identical pixels fire identically
    first = ev[(ev["x"] == 0) & (ev["y"] == 0)]
    last = ev[(ev["x"] == 3) & (ev["y"] == 3)]
    np.testing.assert_array_equal(first["t"], last["t"])


# --- command line --------------------------------------------------------------------

def test_cli_writes_csv_plot_and_prints_errors(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["waveform", "--out", str(tmp_path), "--t1-shape",
                                 "exponential", "--panel1", "fast_shutter", "--panel2",
                                 "fast_shutter", "--sample-rate-hz", "100000"])
    assert result.exit_code == 0, result.output
    assert not (tmp_path / "waveform.csv").exists()
    png = (tmp_path / "waveform.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    files = read_waveform_files(tmp_path)
    v1 = files.voltage_v[0]
    assert files.n_samples == 5000 and files.sample_rate_hz == 100_000.0
    assert files.carrier_hz == 1000.0 and v1.min() < 0 < v1.max()  # AC by default
    out = " ".join(result.output.split())
    assert "with pre-emphasis" in out and "without" in out
    rig = Rig(t1_shape="exponential")
    t1, t2 = rig.waveforms()
    p = get_panel("fast_shutter")
    d = design(t1, t2, panel1=p, panel2=p, period_us=rig.period_us, sample_rate_hz=100_000.0,
               ramp_fraction=rig.ramp_fraction)
    assert f"{d.channels[0].rms_error_pct:.3f} %" in out
    assert f"{d.channels[1].naive_rms_error_pct:.3f} %" in out
    np.testing.assert_array_equal(v1, d.samples(1))


def test_cli_options_and_errors(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["waveform", "--out", str(tmp_path), "--no-pre-emphasis",
                                 "--rise-us", "800", "--fall-us", "400",
                                 "--contrast-ratio", "500"])
    assert result.exit_code == 0, result.output
    meta = read_waveform_files(tmp_path).metadata
    assert meta["pre_emphasis"] is False
    assert meta["panels"][0]["response"] == {"rise_us": 800.0, "fall_us": 400.0}
    assert meta["panels"][1]["curve"]["contrast_ratio"] == pytest.approx(500.0)
    dc = runner.invoke(app, ["waveform", "--out", str(tmp_path / "dc"), "--dc"])
    assert dc.exit_code == 0, dc.output
    assert "degrades" in " ".join(dc.output.split())
    files = read_waveform_files(tmp_path / "dc")
    assert files.carrier_hz is None and files.voltage_v[0].min() >= 0
    bad = runner.invoke(app, ["waveform", "--out", str(tmp_path), "--sample-rate-hz", "3"])
    assert bad.exit_code == 2
    assert "whole number" in " ".join(bad.output.split())


# --- generator files -----------------------------------------------------------------

def test_channel_scale_by_hand():
    sc = channel_scale(np.array([-5.0, 0.0, 5.0, 3.0]))
    assert sc.amplitude_vpp == 10.0 and sc.offset_v == 0.0
    np.testing.assert_array_equal(sc.normalized, [-1.0, 0.0, 1.0, 0.6])
    np.testing.assert_array_equal(sc.codes(), [-32767, 0, 32767, 19660])
    dc = channel_scale(np.array([1.0, 4.0]))  # a DC drive: offset 2.5 V, 3 Vpp
    assert (dc.amplitude_vpp, dc.offset_v, dc.high_v, dc.low_v) == (3.0, 2.5, 4.0, 1.0)
    flat = channel_scale(np.array([2.0, 2.0, 2.0]))
    assert flat.amplitude_vpp > 0 and flat.offset_v == 2.0
    with pytest.raises(ValueError, match="non-finite"):
        channel_scale(np.array([0.0, np.nan]))


def test_waveform_files_round_trip(tmp_path):
    d = _design(get_panel("tn_generic"), get_panel("tn_generic_nb"))
    written = d.write_files(tmp_path / "w")
    assert sorted(written) == ["panel1.arb", "panel1.csv", "panel1_sdg.csv", "panel2.arb",
                               "panel2.csv", "panel2_sdg.csv", "waveform.json"]
    back = read_waveform_files(tmp_path / "w")
    assert back.sample_rate_hz == FS and back.period_us == PERIOD_US
    assert back.carrier_hz == 1000.0 and back.metadata["panels"][1]["curve"]["normally_white"] \
        is False
    for k in (1, 2):
        v = d.samples(k)
        np.testing.assert_array_equal(back.voltage_v[k - 1], v)  # %.17g: exact
        np.testing.assert_array_equal(read_column_csv(tmp_path / "w" / f"panel{k}.csv"), v)
        # Keysight .arb: 16-bit codes, so within half a code of the amplitude
        arb, head = read_arb(tmp_path / "w" / f"panel{k}.arb")
        amp = v.max() - v.min()
        assert head["Sample Rate"] == FS and head["Data Points"] == v.size
        assert head["High Level"] == pytest.approx(v.max(), abs=1e-8)
        assert head["Low Level"] == pytest.approx(v.min(), abs=1e-8)
        assert np.max(np.abs(arb - v)) <= amp / 65534 * 0.5 + 1e-8
        assert np.max(np.abs(arb - v)) > 0  # quantised, not a copy
        sdg, shead = read_siglent_csv(tmp_path / "w" / f"panel{k}_sdg.csv")
        np.testing.assert_array_equal(sdg, v)
        assert shead["data length"] == v.size
        assert shead["frequency"] == pytest.approx(FS / v.size)  # 20 Hz: one cycle
        assert shead["amp"] == pytest.approx(amp) and shead["offset"] == pytest.approx(
            (v.max() + v.min()) / 2, abs=1e-9)
    # the Keysight file starts with its header, CRLF line ends, one sample a line after Data:
    raw = (tmp_path / "w" / "panel1.arb").read_bytes()
    assert raw.startswith(b"Copyright:asynhdr\r\nFile Format:1.10\r\nChannel Count:1\r\n")
    lines = raw.decode().split("\r\n")
    assert lines[lines.index("Data:") + 1].lstrip("-").isdigit()
    sdg_lines = (tmp_path / "w" / "panel2_sdg.csv").read_text().splitlines()
    assert sdg_lines[0] == "data length,10000" and sdg_lines[12] == "xpos,value"


def test_waveform_files_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"waveform\.json"):
        read_waveform_files(tmp_path)
    d = _design(get_panel("fast_shutter"), get_panel("fast_shutter"))
    d.write_files(tmp_path)
    (tmp_path / "panel2.csv").write_text("1.0\n2.0\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"panel2.csv: 2 samples, the sidecar says 10000"):
        read_waveform_files(tmp_path)
    bad = tmp_path / "bad.arb"
    bad.write_text("File Format:1.10\nSample Rate:10\nHigh Level:1\nLow Level:0\n"
                   "Data Points:3\nData:\n1\n2\n", encoding="ascii")
    with pytest.raises(ValueError, match="Data Points:3, found 2"):
        read_arb(bad)
    bad.write_text("nonsense\n", encoding="ascii")
    with pytest.raises(ValueError, match="line 1"):
        read_arb(bad)
    col = tmp_path / "c.csv"
    col.write_text("1\nx\n", encoding="utf-8")
    with pytest.raises(ValueError, match="line 2"):
        read_column_csv(col)
