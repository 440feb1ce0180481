"""Tests of asynhdr.io (formats other than the .raw codec, the entry point, streaming)
and of the ``asynhdr info`` command."""

from __future__ import annotations

import importlib.util
import json
import logging
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from asynhdr.events import EVENT_DTYPE, Recording, make_events, make_triggers, validate_events
from asynhdr.io import (
    SUPPORTED_FORMATS,
    iter_chunks,
    open_recording,
    recording_info,
    write_recording,
)
from asynhdr.io.aedat import aedat_info, iter_aedat, read_aedat
from asynhdr.io.hdf5 import Hdf5Writer, iter_hdf5, load_hdf5, save_hdf5
from asynhdr.io.npz import load_npz, npz_info, save_npz
from asynhdr.io.text import iter_text, read_text, save_text

HAVE_PROPHESEE = importlib.util.find_spec("asynhdr.io.prophesee") is not None
needs_prophesee = pytest.mark.skipif(not HAVE_PROPHESEE,
                                     reason="asynhdr.io.prophesee not available")

AEDAT_FILES = ["events/dvxplorer.aedat4", "events/davis346_triggers.aedat4"]


# ----------------------------------------------------------------------------- helpers


def sample_recording(seed: int = 0, n: int = 5_000, *, width: int = 346,
                     height: int = 260) -> Recording:
    """Random events in file order with a few backward time steps, triggers on two
    channels, metadata with nesting, unicode and floats."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(1_000_000, 3_000_000, size=n))
    back = rng.choice(n - 1, size=n // 100, replace=False) + 1
    t[back] -= rng.integers(1, 5, size=back.size)  # EVT 3.0 streams step back like this
    ev = make_events(rng.integers(0, width, n), rng.integers(0, height, n),
                     rng.choice(np.array([-1, 1], np.int8), n), t)
    tt = np.arange(1_000_000, 3_000_000, 50_000, dtype=np.int64)
    tr = make_triggers(np.sort(np.concatenate([tt, tt + 25_000])),
                       np.tile([True, False], tt.size), np.tile([0, 1], tt.size))
    meta = {"rig": {"period_us": 50_000, "panels": ["T1", "T2"]}, "note": "ümlaut µs",
            "ratio": 0.1, "flag": True, "none": None}
    return Recording(events=ev, width=width, height=height, triggers=tr, metadata=meta)


def concat(chunks: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    return (np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks]))


def manifest_events(ev: np.ndarray, i: int) -> list[int]:
    """Event i as the manifest writes it: [t, x, y, p] with p 1 = ON, 0 = OFF."""
    e = ev[i]
    return [int(e["t"]), int(e["x"]), int(e["y"]), 1 if int(e["p"]) > 0 else 0]


def dv_writer(path: Path, *, compression: str = "LZ4", size: tuple[int, int] = (32, 24),
              triggers: bool = True, imu: bool = False, camera: str = "TESTCAM") -> Any:
    """dv-processing's AEDAT 4.0 writer for ``path`` (the file is closed when the writer
    is deleted)."""
    import dv_processing as dv

    cfg = dv.io.MonoCameraWriter.Config(camera)
    cfg.compression = getattr(dv.CompressionType, compression)
    cfg.addEventStream(size)
    if imu:
        cfg.addImuStream()
    if triggers:
        cfg.addTriggerStream()
    return dv.io.MonoCameraWriter(str(path), cfg)


def dv_reference(path: Path) -> dict[str, Any]:
    """What dv-processing, iniVation's library, reads from an AEDAT 4.0 file: events as
    EVENT_DTYPE, trigger records (type name, timestamp), camera, streams, resolution."""
    import dv_processing as dv

    r = dv.io.MonoCameraRecording(str(path))
    parts = []
    while (batch := r.getNextEventBatch()) is not None:
        parts.append(batch.numpy())
    if not parts:
        ev = make_events([], [], [], [])
    else:
        a = np.concatenate(parts)
        ev = make_events(a["x"], a["y"], np.where(a["polarity"], 1, -1), a["timestamp"])
    records = []
    if r.isTriggerStreamAvailable():
        while (tb := r.getNextTriggerBatch()) is not None:
            records += [(t.type.name, t.timestamp) for t in tb]
    return {"events": ev, "triggers": records, "camera": r.getCameraName(),
            "streams": list(r.getStreamNames()), "resolution": tuple(r.getEventResolution())}


def assert_same_as_dv(path: Path) -> None:
    """read_aedat and iter_aedat give what dv-processing reads."""
    from collections import Counter

    ref = dv_reference(path)
    rec = read_aedat(path)
    np.testing.assert_array_equal(rec.events, ref["events"])
    assert (rec.width, rec.height) == ref["resolution"]
    assert rec.metadata["camera"] == ref["camera"]
    assert rec.metadata["streams"] == ref["streams"]
    assert rec.metadata["trigger_records"] == dict(Counter(k for k, _ in ref["triggers"]))
    edges = {"EXTERNAL_SIGNAL_RISING_EDGE": (True, 0), "EXTERNAL_SIGNAL_FALLING_EDGE": (False, 0),
             "EXTERNAL_SIGNAL_PULSE": (True, 0), "EXTERNAL_GENERATOR_RISING_EDGE": (True, 1),
             "EXTERNAL_GENERATOR_FALLING_EDGE": (False, 1)}
    expected = sorted(((t, *edges[k]) for k, t in ref["triggers"] if k in edges),
                      key=lambda e: e[0])
    assert [(int(t["t"]), bool(t["rising"]), int(t["id"])) for t in rec.triggers] == expected
    ev, tr = concat(list(iter_aedat(path, chunk_events=997)))
    np.testing.assert_array_equal(ev, rec.events)
    np.testing.assert_array_equal(tr, rec.triggers)
    info = aedat_info(path)
    assert (info["width"], info["height"], info["triggers"]) == (rec.width, rec.height,
                                                                 rec.triggers.size)


# ----------------------------------------------------------------------------- real .aedat4


@pytest.mark.parametrize("rel", AEDAT_FILES)
def test_aedat4_matches_manifest(data_dir: Path, manifest: dict[str, Any], rel: str) -> None:
    facts = manifest["events"][rel]
    rec = open_recording(data_dir / rel)
    assert rec.events.dtype == EVENT_DTYPE
    assert rec.events.size == facts["events"]
    assert manifest_events(rec.events, 0) == facts["first"]
    assert manifest_events(rec.events, -1) == facts["last"]
    assert (rec.width, rec.height) == (facts["width"], facts["height"])
    # No external-input edges in either file: no modulation triggers.
    assert rec.triggers.size == 0
    records = rec.metadata["trigger_records"]
    assert sum(records.values()) == facts.get("triggers_count", 0)
    if records:  # the DAVIS346 sample: frame and exposure markers only
        assert all(k.startswith("APS_") for k in records)


@pytest.mark.parametrize("rel", AEDAT_FILES)
def test_aedat4_real_files_equal_dv_processing(data_dir: Path, rel: str) -> None:
    pytest.importorskip("dv_processing")
    assert_same_as_dv(data_dir / rel)


@pytest.mark.parametrize("rel", AEDAT_FILES)
def test_aedat4_streaming_equals_whole(data_dir: Path, rel: str) -> None:
    whole = open_recording(data_dir / rel)
    ev, tr = concat(list(iter_chunks(data_dir / rel, chunk_events=7_000)))
    np.testing.assert_array_equal(ev, whole.events)
    assert tr.size == 0
    chunks = list(iter_chunks(data_dir / rel, chunk_events=7_000))
    assert all(c[0].size == 7_000 for c in chunks[:-1])
    ev_w, _ = concat(list(iter_chunks(data_dir / rel, window_us=10_000)))
    np.testing.assert_array_equal(ev_w, whole.events)


def test_aedat4_info_counts_trigger_records(data_dir: Path, manifest: dict[str, Any]) -> None:
    rel = "events/davis346_triggers.aedat4"
    facts = manifest["events"][rel]
    info = recording_info(data_dir / rel)
    assert info["format"] == "aedat4"
    assert info["events"] == facts["events"]
    assert info["first_t_us"] == facts["first"][0]
    assert info["last_t_us"] == facts["last"][0]
    assert info["duration_us"] == facts["last"][0] - facts["first"][0]
    assert info["trigger_edges"] == {}
    assert sum(info["trigger_records"].values()) == facts["triggers_count"]
    assert info["sensor"].startswith("DAVIS346")


@pytest.mark.parametrize("compression", ["LZ4", "ZSTD"])
def test_aedat4_external_triggers_and_compression(tmp_path: Path, compression: str) -> None:
    dv = pytest.importorskip("dv_processing")
    path = tmp_path / f"ext_{compression}.aedat4"
    writer = dv_writer(path, compression=compression)
    store = dv.EventStore()
    ts = [1_000 + 10 * i for i in range(40)]
    for i, t in enumerate(ts):
        store.push_back(t, i % 32, i % 24, bool(i % 3))
    writer.writeEvents(store)
    T = dv.TriggerType
    records = [(1_005, T.EXTERNAL_SIGNAL_RISING_EDGE), (1_050, T.APS_FRAME_START),
               (1_105, T.EXTERNAL_SIGNAL_FALLING_EDGE), (1_200, T.EXTERNAL_SIGNAL_PULSE),
               (1_250, T.EXTERNAL_GENERATOR_RISING_EDGE), (1_300, T.APS_EXPOSURE_END),
               (1_350, T.EXTERNAL_GENERATOR_FALLING_EDGE)]
    for t, kind in records:
        writer.writeTrigger(dv.Trigger(t, kind))
    del writer  # closes the file
    rec = open_recording(path)
    assert (rec.width, rec.height) == (32, 24)
    np.testing.assert_array_equal(rec.events["t"], ts)
    np.testing.assert_array_equal(rec.events["x"], np.arange(40) % 32)
    np.testing.assert_array_equal(rec.events["p"], np.where(np.arange(40) % 3, 1, -1))
    np.testing.assert_array_equal(rec.triggers["t"], [1_005, 1_105, 1_200, 1_250, 1_350])
    np.testing.assert_array_equal(rec.triggers["rising"], [True, False, True, True, False])
    np.testing.assert_array_equal(rec.triggers["id"], [0, 0, 0, 1, 1])
    assert rec.metadata["trigger_records"] == {
        "APS_EXPOSURE_END": 1, "APS_FRAME_START": 1, "EXTERNAL_GENERATOR_FALLING_EDGE": 1,
        "EXTERNAL_GENERATOR_RISING_EDGE": 1, "EXTERNAL_SIGNAL_FALLING_EDGE": 1,
        "EXTERNAL_SIGNAL_PULSE": 1, "EXTERNAL_SIGNAL_RISING_EDGE": 1}
    ev, tr = concat(list(iter_chunks(path, chunk_events=15)))
    np.testing.assert_array_equal(ev, rec.events)
    np.testing.assert_array_equal(tr, rec.triggers)


@pytest.mark.parametrize("compression", ["NONE", "LZ4", "LZ4_HIGH", "ZSTD", "ZSTD_HIGH"])
def test_aedat4_every_compression_equals_dv_processing(tmp_path: Path, compression: str) -> None:
    """Files written by dv-processing with each compression, many packets (one empty),
    IMU and trigger streams beside the events: read as dv-processing reads them."""
    dv = pytest.importorskip("dv_processing")
    path = tmp_path / f"c_{compression}.aedat4"
    writer = dv_writer(path, compression=compression, size=(640, 480), imu=True,
                       camera="CAM_" + compression)
    rng = np.random.default_rng(3)
    kinds = list(dv.TriggerType.__members__.values())
    t = 1_700_000_000_000_000
    for k in range(9):
        store = dv.EventStore()
        for _ in range(0 if k == 4 else int(rng.integers(1, 3_000))):
            t += int(rng.integers(0, 3))
            store.push_back(t, int(rng.integers(0, 640)), int(rng.integers(0, 480)),
                            bool(rng.integers(0, 2)))
        writer.writeEvents(store)
        writer.writeImu(dv.IMU(t, 25.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
        for j in range(k):
            writer.writeTrigger(dv.Trigger(t + j, kinds[(k + j) % len(kinds)]))
        t += k
    del writer  # closes the file
    rec = read_aedat(path)
    assert rec.events.size > 10_000
    assert sum(rec.metadata["trigger_records"].values()) == sum(range(9))
    assert rec.metadata["camera"] == "CAM_" + compression
    assert_same_as_dv(path)


def write_aedat4_packets(path: Path, packets: list[list[tuple[int, int, int, bool]]], *,
                        size: tuple[int, int] = (32, 24)) -> None:
    """An AEDAT 4.0 file (Zstd) with one event packet per list of (t, x, y, on)."""
    import dv_processing as dv

    writer = dv_writer(path, compression="ZSTD", size=size, triggers=False)
    for packet in packets:
        store = dv.EventStore()
        for t, x, y, on in packet:
            store.push_back(t, x, y, on)
        writer.writeEvents(store)
    del writer  # closes the file


@pytest.mark.parametrize("group_events, initial_events, copy_trim_bytes", [
    (None, None, None),  # the reader's own sizes: one group, an exact-size array
    (5_000, None, None),  # groups into a buffer, trimmed by a copy
    (5_000, 1_000, None),  # the buffer doubles several times
    (5_000, 1_000, 0),  # ... and is trimmed in place
])
def test_aedat4_many_packets_any_buffer_size(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, group_events: int | None,
    initial_events: int | None, copy_trim_bytes: int | None,
) -> None:
    pytest.importorskip("dv_processing")
    from asynhdr.io import aedat

    n, per_packet = 24_000, 2_000
    i = np.arange(n)
    x, y, on = i % 32, (i // 32) % 24, (i % 3) == 0
    t = 5_000 + i // 2
    path = tmp_path / "many.aedat4"
    write_aedat4_packets(path, [
        [(int(t[k]), int(x[k]), int(y[k]), bool(on[k])) for k in range(s, s + per_packet)]
        for s in range(0, n, per_packet)])
    if group_events is not None:
        monkeypatch.setattr(aedat, "_GROUP_EVENTS", group_events)
    if initial_events is not None:
        monkeypatch.setattr(aedat, "_MAX_INITIAL_EVENTS", initial_events)
    if copy_trim_bytes is not None:
        monkeypatch.setattr(aedat, "_COPY_TRIM_BYTES", copy_trim_bytes)
    rec = open_recording(path)
    assert rec.events.dtype == EVENT_DTYPE and rec.events.shape == (n,)
    assert rec.events.flags.owndata and rec.events.flags.c_contiguous
    np.testing.assert_array_equal(rec.events["t"], t)
    np.testing.assert_array_equal(rec.events["x"], x)
    np.testing.assert_array_equal(rec.events["y"], y)
    np.testing.assert_array_equal(rec.events["p"], np.where(on, 1, -1))
    ev, _ = concat(list(iter_chunks(path, chunk_events=5_000)))
    np.testing.assert_array_equal(ev, rec.events)


@pytest.mark.parametrize("bad, message", [
    ((2_002, 40, 3), r"event 1002 at x=40 is outside the sensor \(width=32\)"),
    ((2_002, 5, 24), r"event 1002 at y=24 is outside the sensor \(height=24\)"),
    ((2_002, -1, 3), r"event 1002 at x=-1 is outside the sensor \(width=32\)"),
])
def test_aedat4_event_outside_the_resolution_is_named(
    tmp_path: Path, bad: tuple[int, int, int], message: str
) -> None:
    pytest.importorskip("dv_processing")
    first = [(1_000 + k, k % 32, k % 24, True) for k in range(1_000)]
    second = [(2_000 + k, 1, 1, False) for k in range(2)] + [(*bad, True)]
    second += [(2_003 + k, 2, 2, True) for k in range(10)]
    path = tmp_path / "outside.aedat4"
    write_aedat4_packets(path, [first, second])
    with pytest.raises(ValueError, match=r"outside\.aedat4: events: " + message):
        open_recording(path)
    with pytest.raises(ValueError, match=r"outside\.aedat4: events: " + message):
        list(iter_chunks(path, chunk_events=100))


# ----------------------------------------------------------------------------- .raw dispatch


@needs_prophesee
def test_raw_dispatch_matches_manifest(data_dir: Path, manifest: dict[str, Any]) -> None:
    rel = "events/gen3_evt2.raw"
    facts = manifest["events"][rel]
    rec = open_recording(data_dir / rel)
    assert rec.events.size == facts["events"]
    assert manifest_events(rec.events, 0) == facts["first"]
    assert manifest_events(rec.events, -1) == facts["last"]
    ev, _ = concat(list(iter_chunks(data_dir / rel, chunk_events=100_000)))
    np.testing.assert_array_equal(ev, rec.events)
    info = recording_info(data_dir / rel)
    assert info["format"] == "evt2" and info["events"] == facts["events"]


@needs_prophesee
def test_raw_triggers_through_the_entry_point(data_dir: Path, manifest: dict[str, Any]) -> None:
    rel = "events/imx636_evt3_triggers.raw"
    facts = manifest["events"][rel]
    rec = open_recording(data_dir / rel)
    got = [[int(t["t"]), int(t["rising"]), int(t["id"])] for t in rec.triggers]
    assert got == facts["triggers"]
    _, tr = concat(list(iter_chunks(data_dir / rel, window_us=100_000)))
    np.testing.assert_array_equal(tr, rec.triggers)
    assert recording_info(data_dir / rel)["trigger_edges"] == {
        "channel 0 rising": 1, "channel 0 falling": 1}


@needs_prophesee
def test_raw_write_through_the_entry_point(tmp_path: Path) -> None:
    rec = sample_recording(1, width=640, height=480)
    rec = rec.with_events(np.sort(rec.events, order="t", kind="stable"))
    out = tmp_path / "r.raw"
    write_recording(out, rec)
    back = open_recording(out)
    np.testing.assert_array_equal(back.events, rec.events)
    np.testing.assert_array_equal(back.triggers, rec.triggers)
    assert (back.width, back.height) == (640, 480)


@needs_prophesee
def test_raw_unknown_header_lists_supported_formats(tmp_path: Path) -> None:
    bad = tmp_path / "future.raw"
    bad.write_bytes(b"% evt 4.0\n% geometry 640x480\n% end\n" + bytes(64))
    with pytest.raises(ValueError, match=r"future\.raw") as exc:
        open_recording(bad)
    assert ".aedat4" in str(exc.value) and ".h5" in str(exc.value)


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("ext", [".npz", ".h5", ".hdf5", ".txt", ".csv"])
def test_round_trip_is_exact(tmp_path: Path, ext: str) -> None:
    rec = sample_recording(2)
    path = tmp_path / f"rec{ext}"
    write_recording(path, rec)
    back = open_recording(path)
    assert back.equals(rec), (back.metadata, rec.metadata)
    assert back.metadata == rec.metadata


def test_hdf5_writer_in_several_chunks(tmp_path: Path) -> None:
    rec = sample_recording(3, n=20_000)
    path = tmp_path / "chunks.h5"
    with Hdf5Writer(path, width=rec.width, height=rec.height, metadata=rec.metadata) as w:
        cuts = [0, 1, 4_000, 4_000, 13_500, 20_000]
        tcuts = [0, 0, 10, 25, 60, rec.triggers.size]
        for a, b, ta, tb in zip(cuts[:-1], cuts[1:], tcuts[:-1], tcuts[1:], strict=True):
            w.write(rec.events[a:b], rec.triggers[ta:tb])
        assert not path.exists()  # atomic: only renamed at the end
    assert load_hdf5(path).equals(rec)
    with h5py.File(path) as f:
        assert f["events/t"].chunks is not None
        assert f.attrs["time_unit"] == "us"
        assert f["events/t"].dtype == np.int64


def test_hdf5_writer_leaves_nothing_on_error(tmp_path: Path) -> None:
    rec = sample_recording(4, n=100)
    path = tmp_path / "broken.h5"
    with pytest.raises(ValueError, match="outside the sensor"):
        with Hdf5Writer(path, width=10, height=10) as w:
            w.write(rec.events)
    assert list(tmp_path.iterdir()) == []


def test_hdf5_seconds_are_converted(tmp_path: Path) -> None:
    path = tmp_path / "seconds.h5"
    t_s = np.array([0.5, 0.5000015, 1.25, 2.0])
    with h5py.File(path, "w") as f:
        f["events/x"] = np.array([1, 2, 3, 4], np.uint16)
        f["events/y"] = np.array([0, 0, 1, 1], np.uint16)
        f["events/t"] = t_s
        f["events/p"] = np.array([1, -1, 1, -1], np.int8)
        f.attrs["width"] = 8
        f.attrs["height"] = 4
        f.attrs["time_unit"] = "s"
    rec = load_hdf5(path)
    np.testing.assert_array_equal(rec.events["t"], [500_000, 500_002, 1_250_000, 2_000_000])
    assert rec.metadata["time_unit_source"] == "s"
    assert rec.triggers.size == 0
    ev, _ = concat(list(iter_hdf5(path, chunk_events=3)))
    np.testing.assert_array_equal(ev, rec.events)


def test_hdf5_time_unit_argument_and_missing_geometry(tmp_path: Path) -> None:
    path = tmp_path / "ms.h5"
    with h5py.File(path, "w") as f:
        f["events/x"] = np.array([1, 2], np.uint16)
        f["events/y"] = np.array([0, 0], np.uint16)
        f["events/t"] = np.array([3, 7], np.int64)
        f["events/p"] = np.array([1, 1], np.int8)
    with pytest.raises(ValueError, match=r"ms\.h5: attributes 'width' and 'height' missing"):
        load_hdf5(path)
    rec = open_recording(path, width=4, height=2, time_unit="ms")
    np.testing.assert_array_equal(rec.events["t"], [3_000, 7_000])
    assert rec.metadata["time_unit_source"] == "ms"


@pytest.mark.parametrize("ext", [".npz", ".h5", ".txt"])
def test_iter_chunks_concatenate_to_whole(tmp_path: Path, ext: str) -> None:
    rec = sample_recording(5, n=12_345)
    path = tmp_path / f"r{ext}"
    write_recording(path, rec)
    chunks = list(iter_chunks(path, chunk_events=1_000))
    assert [c[0].size for c in chunks] == [1_000] * 12 + [345]
    ev, tr = concat(chunks)
    np.testing.assert_array_equal(ev, rec.events)
    np.testing.assert_array_equal(tr, rec.triggers)
    # Count mode: a chunk's triggers are not later than the latest event so far.
    seen = -(2 ** 62)
    for e, t in chunks[:-1]:
        seen = max(seen, int(e["t"].max()))
        assert t.size == 0 or int(t["t"].max()) <= seen
    # Time windows of 100 ms from the first event; cut in file order.
    w = 100_000
    windows = list(iter_chunks(path, window_us=w))
    ev_w, tr_w = concat(windows)
    np.testing.assert_array_equal(ev_w, rec.events)
    np.testing.assert_array_equal(tr_w, rec.triggers)
    t0 = int(rec.events["t"][0])
    for k, (e, t) in enumerate(windows[:-1]):
        lo, hi = t0 + k * w, t0 + (k + 1) * w
        if e.size:
            assert int(e["t"].max()) < hi
            assert int(e["t"][0]) >= lo - 5  # at most the few µs a backward step carries
        assert t.size == 0 or (int(t["t"].max()) < hi)
    assert len(windows) == (int(rec.events["t"].max()) - t0) // w + 1


def test_iter_chunks_yields_empty_windows_for_gaps(tmp_path: Path) -> None:
    ev = make_events([0, 1, 2], [0, 0, 0], [1, 1, 1], [0, 10, 35])
    rec = Recording(events=ev, width=4, height=1)
    path = tmp_path / "gap.npz"
    save_npz(path, rec)
    sizes = [c[0].size for c in iter_chunks(path, window_us=10)]
    assert sizes == [1, 1, 0, 1]
    with pytest.raises(ValueError, match="not both"):
        iter_chunks(path, window_us=10, chunk_events=5)


def test_recording_info_rates_by_hand(tmp_path: Path) -> None:
    # 5 events in the 1 ms bin starting at 10 ms, 12 in the bin at 13 ms, 1 at 20 ms.
    t = np.concatenate([10_000 + np.arange(5) * 100, 13_000 + np.arange(12) * 50, [20_000]])
    ev = make_events(np.zeros(t.size, int), np.zeros(t.size, int), np.ones(t.size, int), t)
    tr = make_triggers([10_500, 12_000, 15_000], [True, False, True], [0, 0, 2])
    path = tmp_path / "rates.h5"
    save_hdf5(path, Recording(events=ev, width=2, height=2, triggers=tr))
    info = recording_info(path)
    assert info["events"] == 18
    assert info["duration_us"] == 10_000
    assert info["mean_rate_hz"] == pytest.approx(18 / 0.01)
    assert info["peak_rate_hz"] == pytest.approx(12_000.0)
    assert info["peak_rate_at_us"] == 13_000
    assert info["trigger_edges"] == {"channel 0 rising": 1, "channel 0 falling": 1,
                                     "channel 2 rising": 1, "channel 2 falling": 0}
    assert info["on_events"] == 18 and info["time_sorted"] is True


# ----------------------------------------------------------------------------- text


def test_text_seconds_detected(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "sec.csv"
    path.write_text("# from another tool\nt,x,y,p\n0.000001,1,2,1\n0.5,3,4,0\n"
                    "1.2500005,5,6,-1  # trailing comment\n\n2.0,0,0,1\n")
    with caplog.at_level(logging.INFO, logger="asynhdr.io.text"):
        rec = read_text(path, width=8, height=8)
    np.testing.assert_array_equal(rec.events["t"], [1, 500_000, 1_250_000, 2_000_000])
    np.testing.assert_array_equal(rec.events["p"], [1, -1, -1, 1])
    assert rec.metadata == {"time_unit_source": "s", "time_unit_detected": True}
    # a guess (milliseconds with fractions would read 1000x too long): a warning, which
    # the command line shows, naming the option that settles it
    said = [r for r in caplog.records if "seconds" in r.getMessage()]
    assert said and said[0].levelno == logging.WARNING
    assert "--time-unit" in said[0].getMessage()
    assert read_text(path, width=8, height=8, time_unit="ms").events["t"].tolist() == [
        0, 500, 1_250, 2_000]


def test_text_units_columns_and_inferred_geometry(tmp_path: Path) -> None:
    path = tmp_path / "ms.txt"
    path.write_text("x y p t_ms\n3 1 1 1.5\n7 2 0 2\n")
    rec = read_text(path)
    np.testing.assert_array_equal(rec.events["t"], [1_500, 2_000])
    np.testing.assert_array_equal(rec.events["x"], [3, 7])
    assert (rec.width, rec.height) == (8, 3)
    assert rec.metadata["geometry_inferred"] is True
    assert rec.metadata["time_unit_source"] == "ms"
    plain = tmp_path / "plain.txt"
    plain.write_text("10 1 1 1\n20 2 2 -1\n")
    assert read_text(plain, time_unit="ms").events["t"].tolist() == [10_000, 20_000]
    assert read_text(plain).events["t"].tolist() == [10, 20]
    frac = tmp_path / "frac.txt"
    frac.write_text("10.5 1 1 1\n200000.25 2 2 1\n")
    with pytest.raises(ValueError, match=r"frac\.txt: cannot tell the time unit"):
        read_text(frac)


def test_text_streams_in_chunks(tmp_path: Path) -> None:
    rec = sample_recording(6, n=3_001)
    path = tmp_path / "s.txt"
    save_text(path, rec)
    chunks = list(iter_text(path, chunk_lines=250))
    ev, tr = concat(chunks)
    np.testing.assert_array_equal(ev, rec.events)
    np.testing.assert_array_equal(tr, rec.triggers)
    assert max(c[0].size for c in chunks) <= 250


@pytest.mark.parametrize(
    ("content", "pattern"),
    [
        ("1 2 3 1\n2 3 4 0\n3 abc 5 1\n", r"bad\.txt:3: field 'x': 'abc' is not a number"),
        ("t,x,y,p\n1,2,3,1\n2,3,4\n", r"bad\.txt:3: expected 4 fields"),
        ("1 2 3 1\n2 3 4 7\n", r"bad\.txt:2: field 'p': '7' is not a polarity"),
        ("1 2 3 1\n2 -3 4 1\n", r"bad\.txt:2: field 'x'"),
        ("1 2 3 1\n2.5 3 4 1\n", r"bad\.txt:2: field 't': '2.5' is not a whole number of µs"),
        ("time x y size\n1 2 3 1\n", r"bad\.txt:1: header names a column 'size'"),
        ("# width: 4\n# height: 4\n1 5 0 1\n", r"bad\.txt:3: field 'x'.*outside the sensor"),
        ("1 2 3 nan\n", r"bad\.txt:1: field 'p'"),
    ],
)
def test_text_errors_name_file_line_field(tmp_path: Path, content: str, pattern: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(ValueError, match=pattern):
        read_text(path, time_unit="us")


# ----------------------------------------------------------------------------- .dat


def _write_dat_by_hand(path: Path, t: np.ndarray, x: np.ndarray, y: np.ndarray,
                       p: np.ndarray, header: bytes) -> None:
    """Prophesee DAT 2 layout: header, type 0x0C (CD), size 8, then t:u32, data:u32
    with x in bits 0-13, y in 14-27, p in 28-31."""
    rec = np.empty(t.size, dtype=[("t", "<u4"), ("d", "<u4")])
    rec["t"] = t
    rec["d"] = x.astype(np.uint32) | (y.astype(np.uint32) << 14) | (p.astype(np.uint32) << 28)
    path.write_bytes(header + bytes([0x0C, 8]) + rec.tobytes())


def test_dat_through_faery_and_by_hand(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    n = 3_000
    t = np.sort(rng.integers(0, 2_000_000, n)).astype(np.uint32)
    x, y, p = rng.integers(0, 304, n), rng.integers(0, 240, n), rng.integers(0, 2, n)
    full = tmp_path / "hand.dat"
    _write_dat_by_hand(full, t, x, y, p, b"% Date 2024-01-01\n% Version 2\n% Width 304\n"
                       b"% Height 240\n")
    rec = open_recording(full)
    assert (rec.width, rec.height) == (304, 240)
    np.testing.assert_array_equal(rec.events["t"], t.astype(np.int64))
    np.testing.assert_array_equal(rec.events["x"], x)
    np.testing.assert_array_equal(rec.events["y"], y)
    np.testing.assert_array_equal(rec.events["p"], np.where(p > 0, 1, -1))
    ev, _ = concat(list(iter_chunks(full, chunk_events=700)))
    np.testing.assert_array_equal(ev, rec.events)
    assert recording_info(full)["events"] == n

    nogeo = tmp_path / "nogeo.dat"
    _write_dat_by_hand(nogeo, t, x, y, p, b"% Version 2\n")
    guessed = open_recording(nogeo)
    assert (guessed.width, guessed.height) == (int(x.max()) + 1, int(y.max()) + 1)
    assert guessed.metadata["geometry_inferred"] is True
    assert (open_recording(nogeo, width=320, height=240).width) == 320

    faery_dat = pytest.importorskip("faery.extension").dat
    enc = tmp_path / "faery.dat"
    packet = np.zeros(n, dtype=[("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("payload", "u1")])
    packet["t"], packet["x"], packet["y"], packet["payload"] = t, x, y, p
    with faery_dat.Encoder(str(enc), version="dat2", event_type="cd", zero_t0=False,
                           dimensions=(304, 240)) as e:
        e.write(packet)
    from_faery = open_recording(enc)
    np.testing.assert_array_equal(from_faery.events, rec.events)
    assert (from_faery.width, from_faery.height) == (304, 240)


def test_dat_trigger_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "trig.dat"
    path.write_bytes(b"% Version 2\n" + bytes([0x0E, 8]) + bytes(16))
    with pytest.raises(ValueError, match=r"trig\.dat: holds trigger events"):
        open_recording(path)


# ----------------------------------------------------------------------------- errors


def test_missing_file_is_named(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere.h5"
    for call in (open_recording, recording_info, iter_chunks):
        with pytest.raises(FileNotFoundError, match=r"nowhere\.h5"):
            call(missing)


def test_unknown_extension_lists_formats(tmp_path: Path) -> None:
    path = tmp_path / "events.bin"
    path.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    with pytest.raises(ValueError, match=r"events\.bin: unknown extension '\.bin'") as exc:
        open_recording(path)
    msg = str(exc.value)
    assert "looks like hdf5" in msg
    for ext in SUPPORTED_FORMATS:
        assert ext in msg
    with pytest.raises(ValueError, match="writable"):
        write_recording(tmp_path / "x.bin", sample_recording(0, n=10))


def test_content_that_does_not_match_the_extension(tmp_path: Path) -> None:
    path = tmp_path / "fake.h5"
    path.write_text("1 2 3 1\n")
    with pytest.raises(ValueError, match=r"fake\.h5: not a HDF5") as exc:
        open_recording(path)
    assert ".aedat4" in str(exc.value)
    aedat = tmp_path / "fake.aedat4"
    aedat.write_bytes(b"PK\x03\x04" + bytes(40))
    with pytest.raises(ValueError, match=r"fake\.aedat4: .*looks like npz"):
        open_recording(aedat)
    raw = tmp_path / "fake.raw"
    raw.write_bytes(b"#!AER-DAT4.0\r\n" + bytes(40))
    with pytest.raises(ValueError, match=r"fake\.raw: .*looks like aedat4"):
        open_recording(raw)


def test_missing_dataset_names_file_field_and_hint(tmp_path: Path) -> None:
    path = tmp_path / "events.h5"
    with h5py.File(path, "w") as f:
        f["events/x"] = np.zeros(3, np.uint16)
        f["events/y"] = np.zeros(3, np.uint16)
        f["events/ts"] = np.zeros(3)
        f["events/p"] = np.ones(3, np.int8)
        f.attrs["width"] = 4
        f.attrs["height"] = 4
    with pytest.raises(ValueError, match=r"events\.h5: dataset 'events/t' missing; found .*"
                       r"'events/ts'.*time_unit='s'"):
        open_recording(path)


def test_npz_missing_field_and_bad_polarity(tmp_path: Path) -> None:
    path = tmp_path / "bad.npz"
    np.savez(path, events_x=np.zeros(2, np.uint16))
    with pytest.raises(ValueError, match=r"bad\.npz: field 'events_y' missing"):
        load_npz(path)
    rec = sample_recording(0, n=10)
    good = tmp_path / "good.npz"
    save_npz(good, rec)
    facts = npz_info(good)
    assert (facts["events"], facts["triggers"]) == (10, rec.triggers.size)
    assert facts["metadata"] == rec.metadata and facts["width"] == 346
    with np.load(good) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["events_p"] = np.zeros(10, np.int8)
    np.savez(path, **arrays)
    with pytest.raises(ValueError, match=r"bad\.npz: .*polarity must be \+1 or -1"):
        load_npz(path)
    arrays["events_p"] = np.ones(10, np.int8)
    arrays["events_t"] = np.linspace(0, 1, 10)
    np.savez(path, **arrays)
    with pytest.raises(ValueError, match=r"bad\.npz: field 'events_t' has dtype float64"):
        load_npz(path)


# ----------------------------------------------------------------------------- corrupted input


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One folder for the property tests (hypothesis runs many examples per test)."""
    return tmp_path_factory.mktemp("fuzz")


_PROPERTY = settings(max_examples=60, deadline=None,
                     suppress_health_check=[HealthCheck.too_slow,
                                            HealthCheck.function_scoped_fixture])


def _valid_or_named_error(read: Any, path: Path) -> None:
    try:
        rec = read(path)
    except ValueError as exc:
        assert path.name in str(exc), str(exc)
        return
    assert isinstance(rec, Recording)
    assert rec.events.dtype == EVENT_DTYPE
    # independent of the reader's own checks (Recording.from_checked trusts them)
    validate_events(rec.events, width=rec.width, height=rec.height, require_sorted=False)


def _every_reader_valid_or_named(path: Path) -> None:
    """open_recording gives valid events or a ValueError naming the file; recording_info
    and streaming in chunks raise nothing but a ValueError naming it."""
    _valid_or_named_error(open_recording, path)
    for reader in (recording_info, lambda q: list(iter_chunks(q, chunk_events=1000))):
        try:
            reader(path)
        except ValueError as exc:
            assert path.name in str(exc), str(exc)


@_PROPERTY
@given(data=st.binary(max_size=400))
def test_text_reader_on_random_bytes(fuzz_dir: Path, data: bytes) -> None:
    path = fuzz_dir / "fuzz.txt"
    path.write_bytes(data)
    _valid_or_named_error(read_text, path)


@_PROPERTY
@given(text=st.text(alphabet="0123456789 ,.-+e#\nxytpna\t", max_size=300))
def test_text_reader_on_random_text(fuzz_dir: Path, text: str) -> None:
    path = fuzz_dir / "fuzz.csv"
    path.write_text(text, encoding="utf-8")
    _valid_or_named_error(read_text, path)


_TEMPLATES: dict[str, bytes] = {}


def _template(ext: str, folder: Path) -> bytes:
    if ext not in _TEMPLATES:
        p = folder / f"template{ext}"
        write_recording(p, sample_recording(9, n=300))
        _TEMPLATES[ext] = p.read_bytes()
    return _TEMPLATES[ext]


@_PROPERTY
@given(ext=st.sampled_from([".npz", ".h5", ".txt"]), cut=st.floats(0.0, 1.0),
       flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 255)), max_size=4))
def test_readers_on_truncated_or_flipped_files(fuzz_dir: Path, ext: str, cut: float,
                                               flips: list[tuple[float, int]]) -> None:
    data = bytearray(_template(ext, fuzz_dir))
    for pos, xor in flips:
        i = min(int(pos * len(data)), len(data) - 1)
        data[i] ^= xor
    data = data[: max(0, int(cut * len(data)))] if cut < 1.0 else data
    path = fuzz_dir / f"damaged{ext}"
    path.write_bytes(bytes(data))
    reader = {".npz": load_npz, ".h5": load_hdf5, ".txt": read_text}[ext]
    _valid_or_named_error(reader, path)
    try:
        for _ in iter_chunks(path, chunk_events=64):
            pass
    except ValueError as exc:
        assert path.name in str(exc), str(exc)
    try:
        recording_info(path)
    except ValueError as exc:
        assert path.name in str(exc), str(exc)


def _aedat4_template(folder: Path, compression: str = "LZ4") -> bytes:
    """An AEDAT 4.0 file written by dv-processing: 12 packets of events, triggers."""
    key = ".aedat4" + compression
    if key not in _TEMPLATES:
        dv = pytest.importorskip("dv_processing")
        path = folder / f"template_{compression}.aedat4"
        writer = dv_writer(path, compression=compression, size=(64, 48))
        rng = np.random.default_rng(4)
        for k in range(12):
            store = dv.EventStore()
            for i in range(400):
                store.push_back(10_000 + 1_000 * k + i, int(rng.integers(0, 64)),
                                int(rng.integers(0, 48)), bool(i % 2))
            writer.writeEvents(store)
            writer.writeTrigger(dv.Trigger(10_000 + 1_000 * k,
                                           dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE))
        del writer  # closes the file
        _TEMPLATES[key] = path.read_bytes()
    return _TEMPLATES[key]


def _dat_template() -> bytes:
    if ".dat" not in _TEMPLATES:
        rng = np.random.default_rng(6)
        n = 600
        rec = np.empty(n, dtype=[("t", "<u4"), ("d", "<u4")])
        rec["t"] = np.sort(rng.integers(0, 200_000, n))
        rec["d"] = (rng.integers(0, 304, n).astype(np.uint32)
                    | (rng.integers(0, 240, n).astype(np.uint32) << 14)
                    | (rng.integers(0, 2, n).astype(np.uint32) << 28))
        _TEMPLATES[".dat"] = (b"% Version 2\n% Width 304\n% Height 240\n" + bytes([0x0C, 8])
                              + rec.tobytes())
    return _TEMPLATES[".dat"]


def _damage(data: bytes, cut: float, flips: list[tuple[float, int]]) -> bytes:
    b = bytearray(data[: max(0, int(len(data) * cut))] if cut < 1.0 else data)
    for where, value in flips:
        if b:
            b[min(int(where * len(b)), len(b) - 1)] ^= value
    return bytes(b)


@_PROPERTY
@given(cut=st.one_of(st.just(1.0), st.floats(0.0, 1.0)),
       flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 255)), max_size=4))
@example(cut=0.0625, flips=[(0.3046875, 1), (0.0625, 1)])  # a header left with no stream
def test_aedat4_and_dat_readers_on_truncated_or_flipped_files(
        fuzz_dir: Path, cut: float, flips: list[tuple[float, int]]) -> None:
    """Damaged .aedat4 (LZ4) and .dat files: valid events or a ValueError naming the
    file. Decoders can loop on damaged data (dv-processing never returns from some damaged
    LZ4 packets); should a reader here hang, the guard ends the run with a traceback."""
    import faulthandler

    for ext, template in ((".aedat4", _aedat4_template(fuzz_dir)), (".dat", _dat_template())):
        path = fuzz_dir / f"damaged{ext}"
        path.write_bytes(_damage(template, cut, flips))
        faulthandler.dump_traceback_later(60, exit=True)
        try:
            _every_reader_valid_or_named(path)
        finally:
            faulthandler.cancel_dump_traceback_later()


@_PROPERTY
@given(cut=st.one_of(st.just(1.0), st.floats(0.0, 1.0)),
       flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 255)), min_size=1,
                      max_size=4))
def test_aedat4_stored_packets_damaged(fuzz_dir: Path, cut: float,
                                       flips: list[tuple[float, int]]) -> None:
    """An uncompressed AEDAT 4.0 file, damaged: every flipped byte of a packet lands in
    its flatbuffer (offsets, counts, trigger tables), which the own decoder checks
    before it reads: valid events or a ValueError naming the file."""
    path = fuzz_dir / "stored.aedat4"
    path.write_bytes(_damage(_aedat4_template(fuzz_dir, "NONE"), cut, flips))
    _every_reader_valid_or_named(path)


def test_aedat4_damaged_lz4_packet_is_refused_with_its_offset(fuzz_dir: Path) -> None:
    """A compressed event packet whose block runs past its end (bytes 0xFF: a literal
    length that never stops) is refused, naming the packet."""
    good = _aedat4_template(fuzz_dir)
    hsize = int.from_bytes(good[14:18], "little")
    at = 18 + hsize  # the first packet; its LZ4 frame starts 8 bytes later
    size = int.from_bytes(good[at + 4: at + 8], "little")
    b = bytearray(good)
    b[at + 8 + 20: at + 8 + size - 8] = b"\xff" * (size - 28)
    path = fuzz_dir / "ff.aedat4"
    path.write_bytes(bytes(b))
    with pytest.raises(ValueError, match=rf"ff\.aedat4: packet at byte {at} \(stream 0\): "
                                         r"its LZ4 data do not decode"):
        open_recording(path)


def test_aedat4_damaged_file_table_is_not_read(fuzz_dir: Path) -> None:
    """dv-processing never returns from this file (a byte of its file data table
    flipped, the packets intact); the table is an index the reader does not need."""
    good = _aedat4_template(fuzz_dir)
    from asynhdr.io._aedat_decode import open_container

    c = open_container(fuzz_dir / "template_LZ4.aedat4")
    assert 0 < c.table < len(good)
    ref = open_recording(fuzz_dir / "template_LZ4.aedat4")
    for at in range(c.table, len(good), 7):
        b = bytearray(good)
        b[at] ^= 0x5A
        path = fuzz_dir / "table.aedat4"
        path.write_bytes(bytes(b))
        rec = open_recording(path)
        np.testing.assert_array_equal(rec.events, ref.events)
        np.testing.assert_array_equal(rec.triggers, ref.triggers)


@_PROPERTY
@given(data=st.binary(max_size=600))
def test_binary_readers_on_random_bytes(fuzz_dir: Path, data: bytes) -> None:
    for ext, reader in ((".npz", load_npz), (".h5", load_hdf5)):
        path = fuzz_dir / f"junk{ext}"
        path.write_bytes(data)
        _valid_or_named_error(reader, path)


# ----------------------------------------------------------------------------- the CLI


def _burst_recording(*, with_triggers: bool, period_us: int = 20_000, n_cycles: int = 25
                     ) -> tuple[Recording, np.ndarray]:
    """Every pixel of a 16x12 sensor fires 2 events a cycle at a brightness-dependent
    delay (0 to 0.4 P after the start), plus sparse noise; rising triggers at starts."""
    rng = np.random.default_rng(21)
    starts = 100_000 + np.arange(n_cycles, dtype=np.int64) * period_us
    delay = rng.uniform(0, 0.4 * period_us, 16 * 12)
    ys, xs = np.divmod(np.arange(16 * 12), 16)
    t = (starts[:, None, None] + delay[None, None, :]
         + np.array([0, 0.02 * period_us])[None, :, None]).ravel()
    x = np.tile(xs, n_cycles * 2)
    y = np.tile(ys, n_cycles * 2)
    nn = 400
    t = np.concatenate([t, rng.uniform(starts[0] - 5_000, starts[-1] + 0.9 * period_us, nn)])
    x = np.concatenate([x, rng.integers(0, 16, nn)])
    y = np.concatenate([y, rng.integers(0, 12, nn)])
    order = np.argsort(t, kind="stable")
    ev = make_events(x[order], y[order], np.ones(t.size, np.int8), np.rint(t[order]))
    tr = make_triggers(starts, True, 0) if with_triggers else make_triggers([], True, 0)
    return Recording(events=ev, width=16, height=12, triggers=tr), starts


def _cli() -> Any:
    from typer.testing import CliRunner

    import asynhdr.cli.info  # noqa: F401  (registers the command)
    from asynhdr.cli import app

    return CliRunner(), app


def test_cli_info_with_triggers(tmp_path: Path) -> None:
    rec, starts = _burst_recording(with_triggers=True)
    path = tmp_path / "bursts.h5"
    save_hdf5(path, rec)
    runner, app = _cli()
    res = runner.invoke(app, ["info", str(path), "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert out["events"] == rec.events.size
    assert out["width"] == 16 and out["height"] == 12
    assert out["trigger_edges"] == {"channel 0 rising": 25, "channel 0 falling": 0}
    assert out["cycles"]["source"] == "triggers"
    assert out["cycles"]["cycles"] == 25
    assert out["cycles"]["first_start_us"] == int(starts[0])
    assert out["cycles"]["period_us"] == pytest.approx(20_000.0)
    table = runner.invoke(app, ["info", str(path)])
    assert table.exit_code == 0
    assert "hdf5" in table.stdout and "16 x 12" in table.stdout


def test_cli_info_without_triggers_and_plot(tmp_path: Path) -> None:
    rec, starts = _burst_recording(with_triggers=False)
    path = tmp_path / "bursts.txt"
    save_text(path, rec)
    png = tmp_path / "plots" / "rate.png"
    runner, app = _cli()
    res = runner.invoke(app, ["info", str(path), "--json", "--plot", str(png)])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    c = out["cycles"]
    assert c["source"] == "event_rate"
    assert abs(c["period_us"] - 20_000) / 20_000 < 1e-3
    assert abs(c["first_start_us"] - int(starts[0])) < 0.01 * 20_000
    assert c["confidence"] > 0.5
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in png.parent.iterdir()] == ["rate.png"]


def test_cli_info_errors(tmp_path: Path) -> None:
    runner, app = _cli()
    res = runner.invoke(app, ["info", str(tmp_path / "absent.npz")])
    assert res.exit_code == 2  # as every command's errors
    assert "absent.npz" in res.output
    assert "\n" not in res.output.strip()  # one line
    nogeo = tmp_path / "nogeo.raw"
    nogeo.write_bytes(b"% evt 3.0\n% end\n" + bytes(16))
    res = runner.invoke(app, ["info", str(nogeo)])
    assert res.exit_code == 2 and "nogeo.raw" in res.output
    assert "--width ... and --height ..." in res.output, res.output
    empty = tmp_path / "empty.txt"
    empty.write_text("")
    res = runner.invoke(app, ["info", str(empty)])
    assert res.exit_code == 0, res.output
    assert "None" not in res.output and "holds no events" in res.output
    assert "unknown" in res.output  # the geometry
    res = runner.invoke(app, ["info", str(empty), "--plot", str(tmp_path / "rate.xyz")])
    assert res.exit_code == 2 and "rate.xyz" in res.output and ".png" in res.output


def _aedat4_variants(fuzz_dir: Path, compression: str = "LZ4") -> list[bytes]:
    """The template, cut twice, and with a byte changed in twelve places."""
    good = _aedat4_template(fuzz_dir, compression)
    rng = np.random.default_rng(12)
    variants = [good, good[: len(good) - 3], good[: len(good) // 2]]
    for _ in range(12):
        b = bytearray(good)
        i = int(rng.integers(100, len(b)))
        b[i] ^= int(rng.integers(1, 256))
        variants.append(bytes(b))
    return variants


def _aedat4_outcomes(fuzz_dir: Path, variants: list[bytes]) -> list[Any]:
    """Each file's (events, triggers) bytes, or its error message."""
    out: list[Any] = []
    for k, data in enumerate(variants):
        path = fuzz_dir / f"variant_{k}.aedat4"
        path.write_bytes(data)
        try:
            rec = open_recording(path)
            out.append((rec.events.tobytes(), rec.triggers.tobytes()))
        except ValueError as exc:
            out.append(str(exc))
    return out


def test_aedat4_reads_in_windows_of_any_size(fuzz_dir: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The reader reads the file a window at a time (packets larger than a window make
    it grow): results and errors do not depend on the window's size."""
    from asynhdr.io import _aedat_decode

    variants = _aedat4_variants(fuzz_dir)
    reference = _aedat4_outcomes(fuzz_dir, variants)
    assert isinstance(reference[0], tuple)
    assert reference[1] == reference[0]  # cut inside the file data table: packets whole
    # cut in half (the data table its header names lies beyond the end): the packets
    # before the cut, a leading part of the whole file's events
    assert isinstance(reference[2], tuple)
    assert 0 < len(reference[2][0]) < len(reference[0][0])
    assert reference[0][0].startswith(reference[2][0])
    assert reference[0][1].startswith(reference[2][1])
    for window in (64, 700):
        monkeypatch.setattr(_aedat_decode, "_WINDOW_BYTES", window)
        monkeypatch.setattr(_aedat_decode, "_BUFFERS", _aedat_decode.Recycler(keep=2,
                                                                             max_bytes=window))
        assert _aedat4_outcomes(fuzz_dir, variants) == reference


@pytest.mark.parametrize("compression", ["LZ4", "NONE", "ZSTD"])
def test_aedat4_threads_and_batches_do_not_change_results(
        fuzz_dir: Path, monkeypatch: pytest.MonkeyPatch, compression: str) -> None:
    """Packets decoded on one thread or spread over three, in batches of one packet or
    of all, give the same events, triggers and errors (the first damaged packet in file
    order is the one named), and the same as dv-processing where the file is whole. The
    reader converts its packets in groups of 1,000 events here (two or three packets),
    so that it frees decoded packets while a batch is being yielded."""
    from asynhdr import _pool
    from asynhdr.io import _aedat_decode, aedat

    variants = _aedat4_variants(fuzz_dir, compression)
    monkeypatch.setattr(_pool, "worker_threads", lambda: 1)
    reference = _aedat4_outcomes(fuzz_dir, variants)
    assert sum(isinstance(r, str) for r in reference) >= 2  # damage is reported
    monkeypatch.setattr(_pool, "worker_threads", lambda: 3)
    monkeypatch.setattr(_aedat_decode, "_PARALLEL_MIN_BYTES", 0)
    monkeypatch.setattr(aedat, "_GROUP_EVENTS", 1_000)
    for batch in (1, 20_000, 150_000, 1 << 30):
        monkeypatch.setattr(_aedat_decode, "_BATCH_BYTES", batch)
        assert _aedat4_outcomes(fuzz_dir, variants) == reference
        assert_same_as_dv(fuzz_dir / f"template_{compression}.aedat4")


def test_aedat4_many_packets_in_one_window(tmp_path: Path) -> None:
    """1,500 event packets (and as many trigger packets) in one window: the lists of
    packets and of LZ4 blocks grow past their first size, and the recording is what
    dv-processing reads."""
    dv = pytest.importorskip("dv_processing")
    path = tmp_path / "many.aedat4"
    writer = dv_writer(path, size=(16, 8))
    for k in range(1500):
        store = dv.EventStore()
        store.push_back(1_000 + 10 * k, k % 16, k % 8, bool(k % 2))
        writer.writeEvents(store)
        writer.writeTrigger(dv.Trigger(1_000 + 10 * k,
                                       dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE))
    del writer
    assert path.stat().st_size < 16 << 20  # one window
    assert_same_as_dv(path)
    assert read_aedat(path).events.size == 1500


def test_aedat4_file_cut_while_being_read(fuzz_dir: Path) -> None:
    """A file that shrinks between its header's read and its packets' read gives a
    ValueError naming it, not a loop waiting for bytes that never come."""
    from asynhdr.io import _aedat_decode

    path = fuzz_dir / "shrinking.aedat4"
    good = _aedat4_template(fuzz_dir)
    path.write_bytes(good)
    c = _aedat_decode.open_container(path)
    path.write_bytes(good[: len(good) // 2])
    with pytest.raises(ValueError, match=rf"shrinking\.aedat4: file ended at byte "
                                         rf"{len(good) // 2} while reading, {len(good)} bytes"):
        list(_aedat_decode.walk(c, {0}))
