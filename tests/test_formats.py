"""The format registry: every writer, read back through the registry and, where it reads
the format, through faery (an independent decoder); metadata that survives every format;
Metavision's HDF5 layout; the EVT writers' word rules; ``asynhdr convert``."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from asynhdr.cli import _register, app
from asynhdr.events import Recording, make_events, make_triggers
from asynhdr.io import FORMATS, convert, open_recording, open_source, write_recording
from asynhdr.io import prophesee as pr
from asynhdr.io.metavision import CD_DTYPE, ECF_FILTER_ID, TRIGGER_RECORD_DTYPE
from asynhdr.reconstruct import METHODS, reconstruct, reconstruct_cycles
from asynhdr.scene import step_chart
from asynhdr.simulate import simulate

_register()
runner = CliRunner()

# (file name, writer options, holds triggers, faery reads it)
TARGETS = [
    ("r.raw", {}, True, True),
    ("r2.raw", {"evt": "2.0"}, True, True),
    ("r.h5", {}, True, False),
    ("r.hdf5", {}, True, False),
    ("r.npz", {}, True, False),
    ("r.txt", {}, True, False),
    ("r.csv", {}, True, True),
    ("r.dat", {}, False, True),
    ("r.aedat4", {}, True, True),
]


def _faery_events(path: Path) -> np.ndarray:
    faery = pytest.importorskip("faery")
    if path.suffix == ".csv":
        props = faery.CsvProperties(has_header=False, separator=b",", t_index=0, x_index=1,
                                    y_index=2, on_index=3, t_scale=0.0, on_value=b"1",
                                    off_value=b"0", skip_errors=True)  # skips '#' lines
        stream = faery.events_stream_from_file(path, csv_properties=props)
    else:
        stream = faery.events_stream_from_file(path)
    return stream.to_array()


@st.composite
def recordings(draw: Any) -> Recording:
    w, h = draw(st.integers(1, 70)), draw(st.integers(1, 50))
    n = draw(st.integers(0, 200))
    t0 = draw(st.integers(0, 5_000_000))
    steps = draw(st.lists(st.sampled_from([0, 0, 1, 3, 70, 5000, 70_000]), min_size=n,
                          max_size=n))
    t = t0 + np.cumsum(np.array(steps, dtype=np.int64))
    xs = draw(st.lists(st.integers(0, w - 1), min_size=n, max_size=n))
    ys = draw(st.lists(st.integers(0, h - 1), min_size=n, max_size=n))
    ps = draw(st.lists(st.sampled_from([-1, 1]), min_size=n, max_size=n))
    m = draw(st.integers(0, 6))
    tt = np.sort(np.array(draw(st.lists(st.integers(0, 6_000_000), min_size=m, max_size=m)),
                          dtype=np.int64))
    tr = make_triggers(tt, np.array(draw(st.lists(st.booleans(), min_size=m, max_size=m)),
                                    dtype=bool),
                       np.array(draw(st.lists(st.integers(0, 15), min_size=m, max_size=m)),
                                dtype=np.uint8))
    meta = draw(st.dictionaries(st.text(min_size=1, max_size=8),
                                st.one_of(st.integers(-10**6, 10**6), st.text(max_size=12),
                                          st.floats(allow_nan=False, allow_infinity=False)),
                                max_size=4))
    return Recording(make_events(xs, ys, ps, t), w, h, tr, meta)


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(rec=recordings())
def test_every_format_round_trips_through_the_registry_and_faery(
        tmp_path_factory: pytest.TempPathFactory, rec: Recording) -> None:
    d = tmp_path_factory.mktemp("rt")
    two = rec.triggers.copy()
    two["id"] %= 2  # AEDAT 4.0 edges: channel 0 (signal), 1 (generator)
    for name, opts, has_triggers, by_faery in TARGETS:
        path = d / name
        if name.endswith(".aedat4"):
            rec = Recording(rec.events, rec.width, rec.height, two, rec.metadata)
        write_recording(path, rec, **opts)
        back = open_recording(path)
        np.testing.assert_array_equal(back.events, rec.events, err_msg=name)
        assert (back.width, back.height) == (rec.width, rec.height), name
        assert back.metadata == rec.metadata, name
        if has_triggers:
            np.testing.assert_array_equal(back.triggers, rec.triggers, err_msg=name)
        else:
            assert back.triggers.size == 0
        streamed = np.concatenate([ev for ev, _ in open_source(path).chunks(chunk_events=17)])
        np.testing.assert_array_equal(streamed, rec.events, err_msg=name)
        if by_faery and rec.events.size:
            fa = _faery_events(path)
            assert fa.size == rec.events.size, name
            np.testing.assert_array_equal(fa["t"].astype(np.int64), rec.events["t"])
            np.testing.assert_array_equal(fa["x"], rec.events["x"])
            np.testing.assert_array_equal(fa["y"], rec.events["y"])
            np.testing.assert_array_equal(fa["on"], rec.events["p"] > 0)
        if name.endswith(".aedat4") and rec.events.size:
            _assert_dv_reads(path, rec)


def _assert_dv_reads(path: Path, rec: Recording) -> None:
    """dv-processing, iniVation's own library, reads what asynhdr's AEDAT 4.0 writer wrote."""
    dv = pytest.importorskip("dv_processing")
    r = dv.io.MonoCameraRecording(str(path))
    assert tuple(r.getEventResolution()) == (rec.width, rec.height)
    parts = []
    while (batch := r.getNextEventBatch()) is not None:
        parts.append(batch.numpy())
    a = np.concatenate(parts)
    np.testing.assert_array_equal(a["timestamp"], rec.events["t"])
    np.testing.assert_array_equal(a["x"], rec.events["x"])
    np.testing.assert_array_equal(a["polarity"], rec.events["p"] > 0)
    kinds = {(True, 0): "EXTERNAL_SIGNAL_RISING_EDGE", (False, 0): "EXTERNAL_SIGNAL_FALLING_EDGE",
             (True, 1): "EXTERNAL_GENERATOR_RISING_EDGE",
             (False, 1): "EXTERNAL_GENERATOR_FALLING_EDGE"}
    got = []
    while (tb := r.getNextTriggerBatch()) is not None:
        got += [(t.type.name, t.timestamp) for t in tb]
    assert got == [(kinds[(bool(e["rising"]), int(e["id"]))], int(e["t"])) for e in rec.triggers]


def test_the_registry_has_one_record_per_format() -> None:
    names = [f.name for f in FORMATS]
    assert len(set(names)) == len(names)
    assert {"raw", "dat", "aedat4", "hdf5", "metavision-hdf5", "npz", "text"} <= set(names)
    for f in FORMATS:
        assert f.extensions and callable(f.sniff) and callable(f.header) and callable(f.chunks)
        assert f.writer is not None, f.name  # every format is written too


@pytest.fixture(scope="module")
def simulated() -> Recording:
    # davis346: ON and OFF thresholds differ (0.134, 0.203), noise, mismatch
    return simulate(step_chart(width=40, height=30), sensor="davis346", n_cycles=3, rng=5,
                    sensor_seed=2)


@pytest.mark.parametrize("name", ["r.raw", "r2.raw", "r.h5", "r.hdf5", "r.npz", "r.txt",
                                  "r.dat", "r.aedat4"])
def test_a_simulated_recording_reconstructs_alike_from_every_format(
        tmp_path: Path, simulated: Recording, name: str) -> None:
    """The rig and the sensor travel with the events, so the same image comes back,
    bit for bit (the .dat holds no triggers: its cycles come from the rig)."""
    path = tmp_path / name
    write_recording(path, simulated, **({"evt": "2.0"} if name == "r2.raw" else {}))
    src = open_source(path)
    assert src.metadata["rig"] == simulated.metadata["rig"]
    assert src.metadata["sensor"] == simulated.metadata["sensor"]
    for method in ("exp", "invert"):
        whole = reconstruct(simulated, method=method)
        streamed = np.stack([img for _, _, img in reconstruct_cycles(src, method=method)])
        np.testing.assert_array_equal(streamed, whole)


def test_invert_uses_the_off_threshold_for_off_events(simulated: Recording) -> None:
    """On the DAVIS346 preset (c_on 0.134, c_off 0.203) the OFF events must move the level
    by c_off: giving c_off the ON value changes the image, giving it the sensor's value
    does not."""
    c_on = simulated.metadata["sensor"]["threshold_on"]
    c_off = simulated.metadata["sensor"]["threshold_off"]
    assert c_off > 1.4 * c_on
    base = reconstruct(simulated, method="invert")
    same = reconstruct(simulated, method="invert", threshold_off=c_off)
    wrong = reconstruct(simulated, method="invert", threshold_off=c_on)
    np.testing.assert_array_equal(base, same)
    assert not np.array_equal(base, wrong)
    for m in METHODS:  # every method takes both thresholds
        if m in ("count", "ttfe"):  # ON events only
            continue
        a = reconstruct(simulated, method=m, threshold_off=c_off)
        b = reconstruct(simulated, method=m, threshold_off=2 * c_off)
        assert not np.array_equal(a, b), m


def test_evt3_writer_puts_a_time_low_after_every_time_high(tmp_path: Path) -> None:
    """Real sensors write a TIME_LOW word after a TIME_HIGH word before any event (the
    shared recordings all do); a decoder that keeps the low bits of the previous time
    would otherwise mis-time events whose low 12 bits are 0."""
    t = np.array([5, 4096, 4096, 8192 + 7, 3 * 4096, 20 * 4096], dtype=np.int64)
    rec = Recording(make_events(np.arange(6) % 4, np.zeros(6), np.ones(6), t), 4, 1,
                    make_triggers([4096 * 5], True, 1))
    path = tmp_path / "low.raw"
    write_recording(path, rec)
    info = pr.raw_info(path)
    words = np.frombuffer(path.read_bytes()[info["header_bytes"]:], "<u2")
    typ = words >> 12
    for i in np.flatnonzero(typ == 0x8):
        nxt = typ[i + 1] if i + 1 < typ.size else None
        assert nxt in (0x8, 0x6, None), (i, hex(int(words[i])), nxt)
    # the events at low bits 0 are announced by an explicit TIME_LOW 0 word
    assert int(np.count_nonzero(words == 0x6000)) >= 3
    np.testing.assert_array_equal(open_recording(path).events, rec.events)


def test_evt2_writer_words(tmp_path: Path) -> None:
    rec = Recording(make_events([3, 5], [1, 2], [1, -1], [64 * 7 + 5, 64 * 9]), 8, 4,
                    make_triggers([64 * 7 + 5], False, 3))
    path = tmp_path / "e2.raw"
    write_recording(path, rec, evt="2.0")
    text = path.read_bytes()
    assert b"% evt 2.0\n" in text and b"% format EVT2;height=4;width=8\n" in text
    info = pr.raw_info(path)
    words = np.frombuffer(text[info["header_bytes"]:], "<u4")
    expected = [0x80000000 | 7,                                 # TIME_HIGH 7
                0xA0000000 | (5 << 22) | (3 << 8),              # trigger: ts 5, id 3, falling
                0x10000000 | (5 << 22) | (3 << 11) | 1,         # ON at x=3 y=1 ts 5
                0x80000000 | 9,                                 # TIME_HIGH 9
                0x00000000 | (0 << 22) | (5 << 11) | 2]         # OFF at x=5 y=2 ts 0
    assert words.tolist() == expected
    assert open_recording(path).equals(rec)


def test_metavision_hdf5_layout(tmp_path: Path, simulated: Recording) -> None:
    """Written in Metavision's layout (compound CD/events with p 0/1, indexes every 2 ms
    from the first event) and read back; plain h5py reads it (gzip when ECF is absent)."""
    path = tmp_path / "mv.hdf5"
    write_recording(path, simulated)
    with h5py.File(path, "r") as f:
        assert f.attrs["geometry"] == "40x30" and f.attrs["version"] == "1.0"
        cd = f["CD/events"][:]
        assert cd.dtype == CD_DTYPE and f["EXT_TRIGGER/events"].dtype == TRIGGER_RECORD_DTYPE
        ev = simulated.events
        np.testing.assert_array_equal(cd["p"], (ev["p"] > 0).astype(np.int16))
        np.testing.assert_array_equal(cd["t"], ev["t"])
        idx = f["CD/indexes"][:]
        t0 = int(ev["t"][0])
        assert int(f["CD/indexes"].attrs["offset"]) == -t0
        assert (int(idx["id"][0]), int(idx["ts"][0])) == (0, -1)
        for k in (1, 2, 10, len(idx) - 1):
            first = int(np.searchsorted(ev["t"], t0 + (k - 1) * 2000))
            assert (int(idx["id"][k]), int(idx["ts"][k])) == (first, int(ev["t"][first]) - t0)
        assert json.loads(f.attrs["asynhdr_metadata"]) == simulated.metadata
    assert open_recording(path).equals(simulated)


def test_metavision_file_from_elsewhere_is_read(tmp_path: Path) -> None:
    """A file with Metavision's layout and attributes only (no asynhdr metadata)."""
    path = tmp_path / "cam.hdf5"
    cd = np.zeros(3, CD_DTYPE)
    cd["x"], cd["y"], cd["p"], cd["t"] = [1, 2, 3], [4, 5, 6], [1, 0, 1], [10, 11, 20]
    tr = np.zeros(1, TRIGGER_RECORD_DTYPE)
    tr["p"], tr["t"], tr["id"] = 1, 15, 0
    with h5py.File(path, "w") as f:
        f.attrs["geometry"] = "1280x720"
        f.attrs["serial_number"] = "00ca0009"
        f.create_dataset("CD/events", data=cd)
        f.create_dataset("EXT_TRIGGER/events", data=tr)
    rec = open_recording(path)
    assert (rec.width, rec.height) == (1280, 720)
    assert rec.events["p"].tolist() == [1, -1, 1] and rec.triggers["t"].tolist() == [15]
    assert rec.metadata["format"] == "metavision-hdf5"
    assert open_source(path).header.sensor == "serial_number=00ca0009"


def test_metavision_ecf_filter_named_when_missing(tmp_path: Path) -> None:
    if h5py.h5z.filter_avail(ECF_FILTER_ID):
        pytest.skip("the ECF filter is installed here")
    path = tmp_path / "ecf.hdf5"
    with h5py.File(path, "w") as f:
        f.attrs["geometry"] = "64x48"
        f.create_dataset("CD/events", shape=(4,), dtype=CD_DTYPE, chunks=(4,),
                         compression=ECF_FILTER_ID, allow_unknown_filter=True)
    with pytest.raises(ValueError, match=r"ecf\.hdf5: dataset 'CD/events' is compressed with "
                                         r"the Prophesee ECF HDF5 filter \(id 36559\), which "
                                         r"is not installed.*hdf5_ecf"):
        open_recording(path)
    with pytest.raises(ValueError, match=r"ECF HDF5 filter .* is not installed"):
        write_recording(tmp_path / "w.hdf5", Recording(make_events([0], [0], [1], [0]), 2, 2),
                        codec="ecf")


def test_a_converted_file_keeps_its_camera(tmp_path: Path) -> None:
    ev = make_events([1, 2, 3], [0, 1, 2], [1, -1, 1], [10, 20, 30])
    cam = tmp_path / "cam.raw"
    write_recording(cam, Recording(ev, 4, 4),
                    header_extra={"plugin_name": "hal_plugin_gen41_evk3", "serial_number": "7"})
    want = "plugin_name=hal_plugin_gen41_evk3, serial_number=7"
    assert open_source(cam).describe()["sensor"] == want
    for ext in (".h5", ".aedat4", ".dat", ".npz", ".raw"):
        out = tmp_path / f"copy{ext}"
        convert(cam, out)
        assert open_source(out).describe()["sensor"] == want, ext


def test_convert_streams_between_formats(tmp_path: Path, simulated: Recording,
                                         caplog: pytest.LogCaptureFixture) -> None:
    src = tmp_path / "a.h5"
    write_recording(src, simulated)
    r = runner.invoke(app, ["convert", str(src), str(tmp_path / "b.raw"), "--evt", "2.0"])
    assert r.exit_code == 0, r.output
    assert b"% evt 2.0" in (tmp_path / "b.raw").read_bytes()[:200]
    r = runner.invoke(app, ["convert", str(tmp_path / "b.raw"), str(tmp_path / "c.npz")])
    assert r.exit_code == 0, r.output
    assert open_recording(tmp_path / "c.npz").equals(simulated)
    # an existing target is refused unless --overwrite, before anything is read
    r = runner.invoke(app, ["convert", str(src), str(tmp_path / "c.npz")])
    assert r.exit_code == 2 and "exists; pass --overwrite" in r.output
    assert "\n" not in r.output.strip()  # one line, the path whole, however long it is
    with caplog.at_level(logging.WARNING):
        convert(src, tmp_path / "d.dat")
    assert "3 trigger edges left out" in caplog.text
    # a camera's clock since 1970 does not fit a .raw file: --start-at-zero shifts it,
    # and the metadata keeps the shift
    ev = simulated.events.copy()
    ev["t"] += 1_605_537_493_718_345
    tr = simulated.triggers.copy()
    tr["t"] += 1_605_537_493_718_345
    epoch = tmp_path / "epoch.npz"
    write_recording(epoch, Recording(ev, simulated.width, simulated.height, triggers=tr))
    r = runner.invoke(app, ["convert", str(epoch), str(tmp_path / "e.raw")])
    assert r.exit_code == 2 and "--start-at-zero" in r.output
    assert not (tmp_path / "e.raw").exists()
    r = runner.invoke(app, ["convert", str(epoch), str(tmp_path / "e.raw"), "--start-at-zero"])
    assert r.exit_code == 0, r.output
    back = open_recording(tmp_path / "e.raw")
    shift = back.metadata["time_shift_us"]
    assert shift == min(int(ev["t"].min()), int(tr["t"].min())) and shift > 1e15
    np.testing.assert_array_equal(back.events["t"] + shift, ev["t"])
    np.testing.assert_array_equal(back.triggers["t"] + shift, tr["t"])
    assert back.events[["x", "y", "p"]].tolist() == ev[["x", "y", "p"]].tolist()
    r = runner.invoke(app, ["convert", str(src), str(tmp_path / "n.h5"), "--evt", "2.0"])
    assert r.exit_code == 2 and "--evt 2.0: applies to a .raw target only" in r.output
    assert not (tmp_path / "n.h5").exists()
    # milliseconds with fractions: --time-unit settles what the guess cannot
    ms = tmp_path / "ms.txt"
    ms.write_text("1.5 1 2 1\n2.25 3 4 0\n")
    r = runner.invoke(app, ["convert", str(ms), str(tmp_path / "ms.npz"), "--time-unit", "ms",
                            "--width", "8", "--height", "8"])
    assert r.exit_code == 0, r.output
    assert open_recording(tmp_path / "ms.npz").events["t"].tolist() == [1_500, 2_250]
