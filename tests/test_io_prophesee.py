"""Tests of the Prophesee .raw codec (EVT 2.0, EVT 2.1, EVT 3.0 read; EVT 3.0 write).

Answers come from the manifest of real files (checked there with two decoders),
from faery 0.7.1 where it decodes correctly (EVT 2.0; EVT 3.0 files without
backward TIME_LOW steps or untimed first words), from word streams built by hand
in these tests (expected events worked out from the format specifications), and
from small EVT 2.0 / EVT 2.1 encoders written here independently of the module.
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from asynhdr.events import (
    EVENT_DTYPE,
    TRIGGER_DTYPE,
    Recording,
    make_events,
    make_triggers,
    validate_events,
)
from asynhdr.io import prophesee as pr

RAW_KEYS = ("evtemmap_imx636_evt3.raw", "imx636_evt3_triggers.raw", "gen41_evt3.raw",
            "gen3_evt2.raw")


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _write(path: Path, header: str, payload: np.ndarray | bytes) -> Path:
    data = payload if isinstance(payload, bytes) else np.ascontiguousarray(payload).tobytes()
    path.write_bytes(header.encode() + data)
    return path


def _rows(events: np.ndarray) -> list[list[int]]:
    """[t, x, y, p] with p 1 = ON, 0 = OFF (the manifest's convention)."""
    return [[int(e["t"]), int(e["x"]), int(e["y"]), 1 if e["p"] > 0 else 0] for e in events]


def _ev(rows: list[tuple[int, int, int, int]]) -> np.ndarray:
    """Events from (t, x, y, p) rows, p as +1 / -1."""
    if not rows:
        return np.zeros(0, EVENT_DTYPE)
    t, x, y, p = zip(*rows, strict=True)
    return make_events(x, y, p, t)


def _tr(rows: list[tuple[int, bool, int]]) -> np.ndarray:
    out = np.zeros(len(rows), TRIGGER_DTYPE)
    for i, (t, rising, ch) in enumerate(rows):
        out[i] = (t, rising, ch)
    return out


def _concat(chunks: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    return (np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks]))


def _faery_decode(path: Path, dims: tuple[int, int] | None = None) -> tuple[Any, Any]:
    faery = pytest.importorskip("faery")
    ev: list[np.ndarray] = []
    tr: list[np.ndarray] = []
    with faery.evt.Decoder(path, dimensions_fallback=dims, version_fallback=None) as decoder:
        for packet in decoder:
            if "events" in packet:
                ev.append(packet["events"])
            if "triggers" in packet:
                tr.append(packet["triggers"])
    events = np.concatenate(ev) if ev else None
    triggers = np.concatenate(tr) if tr else None
    return events, triggers


def _assert_same_as_faery_events(ours: np.ndarray, theirs: np.ndarray) -> None:
    assert theirs is not None and theirs.shape[0] == ours.shape[0]
    np.testing.assert_array_equal(theirs["t"].astype(np.int64), ours["t"])
    np.testing.assert_array_equal(theirs["x"], ours["x"])
    np.testing.assert_array_equal(theirs["y"], ours["y"])
    np.testing.assert_array_equal(np.where(theirs["on"], 1, -1), ours["p"])


def _encode_evt2(events: np.ndarray, triggers: np.ndarray) -> np.ndarray:
    """Independent EVT 2.0 encoder: TIME_HIGH = t >> 6 before each change, then CD/trigger words."""
    t = np.concatenate([events["t"], triggers["t"]])
    order = np.argsort(t, kind="stable")
    n_ev = events.shape[0]
    words = np.empty(t.shape[0], np.uint32)
    ts = (events["t"] & 63).astype(np.uint32)
    words[:n_ev] = (
        (np.where(events["p"] > 0, 1, 0).astype(np.uint32) << 28)
        | (ts << 22)
        | (events["x"].astype(np.uint32) << 11)
        | events["y"].astype(np.uint32)
    )
    tts = (triggers["t"] & 63).astype(np.uint32)
    words[n_ev:] = (
        (np.uint32(0xA) << 28)
        | (tts << 22)
        | (triggers["id"].astype(np.uint32) << 8)
        | triggers["rising"].astype(np.uint32)
    )
    t, words = t[order], words[order]
    th = t >> 6
    need = np.ones(t.shape[0], bool)
    need[1:] = th[1:] != th[:-1]
    pos = np.arange(t.shape[0]) + np.cumsum(need)
    out = np.empty(t.shape[0] + int(need.sum()), np.uint32)
    out[pos] = words
    out[pos[need] - 1] = (np.uint32(0x8) << 28) | (th[need] & 0xFFFFFFF).astype(np.uint32)
    return out


def _encode_evt21(events: np.ndarray, legacy: bool) -> np.ndarray:
    """Independent EVT 2.1 encoder: one vector word per event (a single validity bit)."""
    t = events["t"]
    th = t >> 6
    need = np.ones(t.shape[0], bool)
    need[1:] = th[1:] != th[:-1]
    n = t.shape[0]
    pos = np.arange(n) + np.cumsum(need)
    lo = np.zeros(n + int(need.sum()), np.uint64)
    hi = np.zeros_like(lo)
    x = events["x"].astype(np.uint64)
    lo[pos] = np.uint64(1) << (x & np.uint64(31))
    hi[pos] = (
        (np.where(events["p"] > 0, 1, 0).astype(np.uint64) << np.uint64(28))
        | ((t & 63).astype(np.uint64) << np.uint64(22))
        | ((x & ~np.uint64(31)) << np.uint64(11))
        | events["y"].astype(np.uint64)
    )
    hi[pos[need] - 1] = (np.uint64(0x8) << np.uint64(28)) | (th[need] & 0xFFFFFFF).astype(
        np.uint64
    )
    halves = np.empty(2 * lo.shape[0], np.uint32)
    first, second = (hi, lo) if legacy else (lo, hi)
    halves[0::2] = first.astype(np.uint32)
    halves[1::2] = second.astype(np.uint32)
    return halves


def _random_recording(
    rng: np.random.Generator, n: int, width: int, height: int, n_trig: int = 0
) -> Recording:
    t = np.cumsum(rng.integers(0, 4, n)).astype(np.int64) + int(rng.integers(0, 5000))
    x = rng.integers(0, width, n)
    y = rng.integers(0, height, n)
    p = rng.choice(np.array([-1, 1]), n)
    events = make_events(x, y, p, t)
    tt = np.sort(rng.integers(int(t[0]), int(t[-1]) + 1, n_trig))
    triggers = make_triggers(tt, rising=rng.random(n_trig) < 0.5, id=rng.integers(0, 16, n_trig))
    return Recording(events, width, height, triggers)


# --------------------------------------------------------------------------------------
# real files: manifest facts, faery cross-check, chunked reading
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", RAW_KEYS)
def test_real_file_matches_manifest(name: str, data_dir: Path, manifest: dict[str, Any]) -> None:
    facts = manifest["events"][f"events/{name}"]
    rec = pr.read_raw(data_dir / "events" / name)
    assert rec.metadata["format"] == facts["format"]
    assert rec.metadata["source"] == str(data_dir / "events" / name)
    assert (rec.width, rec.height) == (facts["width"], facts["height"])
    assert rec.events.dtype == EVENT_DTYPE
    assert rec.events.shape[0] == facts["events"]
    assert _rows(rec.events[:1])[0] == facts["first"]
    assert _rows(rec.events[-1:])[0] == facts["last"]
    triggers = [[int(t["t"]), int(t["rising"]), int(t["id"])] for t in rec.triggers]
    assert triggers == facts["triggers"]
    validate_events(rec.events, width=rec.width, height=rec.height, require_sorted=False)


@pytest.mark.parametrize("name", RAW_KEYS)
def test_raw_info_reads_header_only(name: str, data_dir: Path, manifest: dict[str, Any]) -> None:
    facts = manifest["events"][f"events/{name}"]
    info = pr.raw_info(data_dir / "events" / name)
    assert info["format"] == facts["format"]
    assert (info["width"], info["height"]) == (facts["width"], facts["height"])
    assert info["payload_bytes"] + info["header_bytes"] == os.path.getsize(
        data_dir / "events" / name
    )
    assert "evt" in info["header"]


def test_headerless_geometry_comes_from_sensor_table(data_dir: Path) -> None:
    gen3 = pr.raw_info(data_dir / "events" / "gen3_evt2.raw")
    gen41 = pr.raw_info(data_dir / "events" / "gen41_evt3.raw")
    assert gen3["geometry_source"].startswith("sensor table")
    assert gen41["geometry_source"].startswith("sensor table")
    assert gen3["header"]["plugin_name"] == "hal_plugin_gen3_fx3"
    # Explicit arguments that agree are fine; the header wins when it has geometry.
    assert pr.raw_info(data_dir / "events" / "gen3_evt2.raw", width=640, height=480)[
        "geometry_source"
    ] == "arguments"
    with pytest.raises(ValueError, match=r"header says 1280x720.*width=640"):
        pr.read_raw(data_dir / "events" / "imx636_evt3_triggers.raw", width=640, height=480)


def test_gen3_evt2_equals_faery(data_dir: Path) -> None:
    path = data_dir / "events" / "gen3_evt2.raw"
    rec = pr.read_raw(path)
    events, triggers = _faery_decode(path, (640, 480))
    _assert_same_as_faery_events(rec.events, events)
    assert triggers is None and rec.triggers.size == 0


def test_imx636_triggers_file_equals_faery(data_dir: Path) -> None:
    path = data_dir / "events" / "imx636_evt3_triggers.raw"
    rec = pr.read_raw(path)
    events, triggers = _faery_decode(path)
    _assert_same_as_faery_events(rec.events, events)
    np.testing.assert_array_equal(triggers["t"].astype(np.int64), rec.triggers["t"])
    np.testing.assert_array_equal(triggers["rising"], rec.triggers["rising"])
    np.testing.assert_array_equal(triggers["source"], rec.triggers["id"])


def test_gen41_backward_time_low_sets_the_time(data_dir: Path) -> None:
    path = data_dir / "events" / "gen41_evt3.raw"
    info = pr.raw_info(path)
    words = np.frombuffer(path.read_bytes()[info["header_bytes"] :], "<u2")
    kind = words >> 12
    timing = words[(kind == 0x6) | (kind == 0x8)]
    low_after_low = ((timing[1:] >> 12) == 0x6) & ((timing[:-1] >> 12) == 0x6)
    backward = low_after_low & ((timing[1:] & 0xFFF) < (timing[:-1] & 0xFFF))
    assert int(backward.sum()) > 0  # the stream has TIME_LOW words that step back
    rec = pr.read_raw(path)
    events, _ = _faery_decode(path, (1280, 720))
    late = events["t"].astype(np.int64) - rec.events["t"]
    # faery ignores the backward TIME_LOW words: the manifest counts 1,455 events late
    # by 1 to 11 µs; everything else agrees.
    assert int(np.count_nonzero(late)) == 1455
    assert late.min() == 0 and late[late > 0].min() >= 1 and late.max() <= 11
    np.testing.assert_array_equal(events["x"], rec.events["x"])
    np.testing.assert_array_equal(events["y"], rec.events["y"])


@pytest.mark.parametrize("name", RAW_KEYS)
@pytest.mark.parametrize(
    ("chunk_events", "block_bytes"),
    [(1_000_000, 1 << 22), (4096, 8), (777, 24), (50_000, 1 << 12)],
)
def test_iter_raw_concatenates_to_read_raw(
    name: str, chunk_events: int, block_bytes: int, data_dir: Path
) -> None:
    path = data_dir / "events" / name
    rec = pr.read_raw(path)
    chunks = list(pr.iter_raw(path, chunk_events=chunk_events, block_bytes=block_bytes))
    assert all(c[0].shape[0] == chunk_events for c in chunks[:-1])
    assert 0 < chunks[-1][0].shape[0] <= chunk_events
    events, triggers = _concat(chunks)
    np.testing.assert_array_equal(events, rec.events)
    np.testing.assert_array_equal(triggers, rec.triggers)


def test_iter_raw_single_event_chunks(data_dir: Path) -> None:
    path = data_dir / "events" / "imx636_evt3_triggers.raw"
    rec = pr.read_raw(path)
    chunks = list(pr.iter_raw(path, chunk_events=1, block_bytes=16))
    assert len(chunks) == rec.events.shape[0]
    events, triggers = _concat(chunks)
    np.testing.assert_array_equal(events, rec.events)
    np.testing.assert_array_equal(triggers, rec.triggers)


# --------------------------------------------------------------------------------------
# hand-built word streams
# --------------------------------------------------------------------------------------

EVT3_HEADER = "% evt 3.0\n% format EVT3;height=8;width=64\n% geometry 64x8\n% end\n"


def test_evt3_hand_built_stream(tmp_path: Path) -> None:
    words = np.array(
        [
            0x2005,  # EVT_ADDR_X before any TIME_HIGH: dropped
            0x0003,  # EVT_ADDR_Y before any TIME_HIGH: dropped
            0x8001,  # TIME_HIGH 1 -> t = 4096
            0x2007,  # EVT_ADDR_X with no row yet: dropped
            0x0803,  # EVT_ADDR_Y y=3 (bit 11 is the system type)
            0x6010,  # TIME_LOW 0x10 -> t = 4112
            0x2807,  # ON at x=7
            0x6008,  # TIME_LOW 8 -> t = 4104 (steps back)
            0x2006,  # OFF at x=6
            0x3820,  # VECT_BASE_X 32, ON
            0x4805,  # VECT_12 bits 0, 2, 11 -> x = 32, 34, 43
            0x4000,  # VECT_12 empty, base -> 56
            0x5081,  # VECT_8 bits 0, 7 -> x = 56, 63
            0x7ABC,  # CONTINUED_4: ignored
            0xE014,  # OTHERS: ignored
            0xF123,  # CONTINUED_12: ignored
            0xA101,  # EXT_TRIGGER channel 1, value 1
            0x1005,  # non-CD row
            0x2009,  # event on a non-CD row: dropped
            0x0004,  # EVT_ADDR_Y y=4
            0x8FFF,  # TIME_HIGH 0xFFF (low reset) -> t = 0xFFF000
            0x2001,  # OFF at x=1
            0x8000,  # TIME_HIGH 0 after 0xFFF: a 24-bit wrap -> t = 2**24
            0x6005,  # t = 2**24 + 5
            0x2802,  # ON at x=2
            0xA000,  # EXT_TRIGGER channel 0, value 0
            0x8800,  # TIME_HIGH 0x800 -> t = 2**24 + 0x800000
            0x2003,  # OFF at x=3
            0x8400,  # TIME_HIGH 0x400: falls by less than 2048, no wrap -> steps back
            0x2004,  # OFF at x=4
        ],
        dtype="<u2",
    )
    path = _write(tmp_path / "hand.raw", EVT3_HEADER, words)
    rec = pr.read_raw(path)
    expected = _ev(
        [
            (4112, 7, 3, 1),
            (4104, 6, 3, -1),
            (4104, 32, 3, 1),
            (4104, 34, 3, 1),
            (4104, 43, 3, 1),
            (4104, 56, 3, 1),
            (4104, 63, 3, 1),
            (0xFFF000, 1, 4, -1),
            (2**24 + 5, 2, 4, 1),
            (2**24 + 0x800000, 3, 4, -1),
            (2**24 + 0x400000, 4, 4, -1),
        ]
    )
    np.testing.assert_array_equal(rec.events, expected)
    np.testing.assert_array_equal(rec.triggers, _tr([(4104, True, 1), (2**24 + 5, False, 0)]))
    for block in (8, 16, 24):
        events, triggers = _concat(list(pr.iter_raw(path, chunk_events=2, block_bytes=block)))
        np.testing.assert_array_equal(events, expected)
        np.testing.assert_array_equal(triggers, rec.triggers)


def _evt3_reference(
    words: list[int], width: int, height: int
) -> tuple[list[tuple[int, int, int, int]], list[tuple[int, bool, int]], tuple[int, str] | None]:
    """A plain EVT 3.0 decoder, one word at a time, written from the format page and
    OpenEB's rules: ``(events as (t, x, y, p), triggers, (word index, 'x=..' or 'y=..')
    of the first event outside the sensor, or None)``."""
    events: list[tuple[int, int, int, int]] = []
    triggers: list[tuple[int, bool, int]] = []
    started = False
    loop = high = low = 0
    y = 0
    cd_row = False
    base_x, base_p, has_base = 0, 1, False
    for i, w in enumerate(words):
        typ, v = w >> 12, w & 0xFFF
        if not started:
            if typ != 0x8:
                continue  # words before the first TIME_HIGH cannot be timed
            started, high = True, v
            continue
        t = (loop << 24) | (high << 12) | low
        if typ == 0x8:
            if v != high:
                loop += high >= 2048 + v  # a fall of half the range or more is a wrap
                high, low = v, 0
        elif typ == 0x6:
            low = v
        elif typ == 0x0:
            y, cd_row = v & 0x7FF, True
        elif typ == 0x1:
            cd_row = False
        elif typ == 0x2 and cd_row:
            x = v & 0x7FF
            if x >= width or y >= height:
                return events, triggers, (i, f"x={x}" if x >= width else f"y={y}")
            events.append((t, x, y, 1 if v >> 11 else -1))
        elif typ == 0x3:
            base_x, base_p, has_base = v & 0x7FF, 1 if v >> 11 else -1, True
        elif typ in (0x4, 0x5) and cd_row:
            size = 12 if typ == 0x4 else 8
            if has_base:
                for bit in range(size):
                    if (v >> bit) & 1:
                        x = base_x + bit
                        if y >= height:
                            return events, triggers, (i, f"y={y}")
                        if x >= width:
                            return events, triggers, (i, f"x={x}")
                        events.append((t, x, y, base_p))
            base_x += size
        elif typ == 0xA:
            triggers.append((t, bool(v & 1), (v >> 8) & 0xF))
    return events, triggers, None


# Words of a plausible EVT 3.0 stream on a 64x8 sensor, with time-high values that wrap
# and step back, and every other word type; one word may point outside the sensor.
_TIME_HIGH = st.sampled_from([0x000, 0x001, 0x002, 0x7FF, 0x800, 0x801, 0xFFF])
_COLUMN = st.integers(0, 63)
_ROW = st.integers(0, 7)
_EVT3_WORD = st.one_of(
    _TIME_HIGH.map(lambda v: 0x8000 | v),
    st.integers(0, 0xFFF).map(lambda v: 0x6000 | v),
    _ROW.map(lambda v: v | (0x800 if v % 3 == 0 else 0)),  # EVT_ADDR_Y (bit 11: system type)
    _ROW.map(lambda v: 0x1000 | v),
    st.tuples(_COLUMN, st.booleans()).map(lambda a: 0x2000 | a[0] | (a[1] << 11)),
    st.tuples(st.integers(0, 72), st.booleans()).map(lambda a: 0x3000 | a[0] | (a[1] << 11)),
    st.integers(0, 0xFFF).map(lambda v: 0x4000 | v),
    st.integers(0, 0xFF).map(lambda v: 0x5000 | v),
    st.integers(0, 0xFFF).map(lambda v: 0xA000 | (v & 0xF01)),
    st.sampled_from([0x7ABC, 0x9000, 0xB000, 0xC000, 0xD000, 0xE014, 0xF123]),
)
_EVT3_GROUPS = st.one_of(
    _EVT3_WORD.map(lambda w: [w]),
    st.tuples(_TIME_HIGH, _TIME_HIGH).map(lambda a: [0x8000 | a[0], 0x8000 | a[1]]),
    # the word groups the decoder takes in one step: a lone event, a 32-column vector
    st.tuples(st.integers(0, 0xFFF), _ROW, _COLUMN, st.booleans()).map(
        lambda a: [0x6000 | a[0], a[1], 0x2000 | a[2] | (a[3] << 11)]
    ),
    st.tuples(st.integers(0, 40), st.integers(0, 0xFFFFFFFF)).map(
        lambda a: [0x3000 | a[0], 0x4000 | (a[1] & 0xFFF), 0x4000 | ((a[1] >> 12) & 0xFFF),
                   0x5000 | (a[1] >> 24)]
    ),
    # a sparse stream's lone events between TIME_HIGH words, repeated or not
    st.tuples(_TIME_HIGH, _TIME_HIGH, st.integers(0, 0xFFF), _ROW, _COLUMN).map(
        lambda a: [0x8000 | a[0], 0x6000 | a[2], a[3], 0x2000 | a[4], 0x8000 | a[1],
                   0x6000 | a[2], a[3], 0x2000 | a[4], 0x8000 | a[1]]
    ),
    # sensor monitoring: OTHERS + CONTINUED_12 + CONTINUED_12 + CONTINUED_4, whole or cut
    st.tuples(st.integers(1, 8), st.integers(0, 4)).map(
        lambda a: ([0xE014, 0xF015, 0xF000, 0x7000] * a[0])[: 4 * a[0] - a[1]]
    ),
)
_OUTSIDE = st.sampled_from(
    [[0x2040], [0x0008], [0x6000, 0x0008, 0x2001], [0x6000, 0x0001, 0x2840], [0x303C, 0x4010],
     [0x3820, 0x4000, 0x4000, 0x5001]]
)


@settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    groups=st.lists(_EVT3_GROUPS, min_size=10, max_size=60),
    outside=st.one_of(st.none(), st.tuples(st.integers(0, 60), _OUTSIDE)),
)
def test_evt3_decoder_equals_a_plain_reference(
    tmp_path: Path, groups: list[list[int]], outside: tuple[int, list[int]] | None
) -> None:
    if outside is not None:
        groups.insert(min(outside[0], len(groups)), outside[1])
    words = [0x8000, 0x0001] + [w for g in groups for w in g]
    path = _write(tmp_path / "ref.raw", EVT3_HEADER, np.array(words, dtype="<u2"))
    events, triggers, error = _evt3_reference(words, 64, 8)
    # Both compiled variants (dense and sparse streams), whichever the stream would get.
    with pytest.MonkeyPatch.context() as mp:
        for kernel in (pr._k.decode_evt3, pr._k.decode_evt3_sparse):
            mp.setattr(pr, "_evt3_kernel", lambda words, pos, kernel=kernel: kernel)
            if error is not None:
                offset = len(EVT3_HEADER) + 2 * error[0]
                with pytest.raises(ValueError,
                                   match=rf"ref\.raw.*byte offset {offset}\b.*{error[1]}\b"):
                    pr.read_raw(path)
                with pytest.raises(ValueError, match=rf"byte offset {offset}\b"):
                    list(pr.iter_raw(path, chunk_events=3, block_bytes=8))
                continue
            rec = pr.read_raw(path)
            np.testing.assert_array_equal(rec.events, _ev(events))
            expected_tr = _tr(triggers)
            by_time = np.argsort(expected_tr["t"], kind="stable")
            np.testing.assert_array_equal(rec.triggers, expected_tr[by_time])
            for chunk_events, block_bytes in ((3, 8), (1000, 1 << 12)):
                got, got_tr = _concat(list(pr.iter_raw(path, chunk_events=chunk_events,
                                                       block_bytes=block_bytes)))
                np.testing.assert_array_equal(got, rec.events)
                np.testing.assert_array_equal(got_tr, expected_tr)


def test_evt3_vector_without_base_is_dropped(tmp_path: Path) -> None:
    # OpenEB drops vectors until a VECT_BASE_X has set the base column.
    words = np.array([0x8000, 0x0001, 0x4FFF, 0x3002, 0x4003], dtype="<u2")
    rec = pr.read_raw(_write(tmp_path / "v.raw", EVT3_HEADER, words))
    np.testing.assert_array_equal(rec.events, _ev([(0, 2, 1, -1), (0, 3, 1, -1)]))


@pytest.mark.parametrize(
    ("words", "offset_words", "what"),
    [
        ([0x8000, 0x0001, 0x2040], 2, "x=64"),
        ([0x8000, 0x0008, 0x6001, 0x2001], 3, "y=8"),
        ([0x8000, 0x0001, 0x303C, 0x4010], 3, "x=64"),
        ([0x8000, 0x0001, 0x303C, 0x4008, 0x4001], 4, "x=72"),
    ],
)
def test_evt3_event_outside_geometry_names_offset_and_pixel(
    tmp_path: Path, words: list[int], offset_words: int, what: str
) -> None:
    path = _write(tmp_path / "bad.raw", EVT3_HEADER, np.array(words, dtype="<u2"))
    offset = len(EVT3_HEADER) + 2 * offset_words
    with pytest.raises(ValueError, match=rf"bad\.raw.*byte offset {offset}\b.*{what}"):
        pr.read_raw(path)
    with pytest.raises(ValueError, match=rf"byte offset {offset}\b"):
        list(pr.iter_raw(path, block_bytes=8))
    assert pr.raw_info(path)["format"] == "evt3"  # the header alone is fine


def test_evt3_vector_at_edge_is_inside(tmp_path: Path) -> None:
    words = np.array([0x8000, 0x0007, 0x383C, 0x4008], dtype="<u2")  # base 60, bit 3 -> x=63
    rec = pr.read_raw(_write(tmp_path / "edge.raw", EVT3_HEADER, words))
    np.testing.assert_array_equal(rec.events, _ev([(0, 63, 7, 1)]))


def test_evt3_vector_groups(tmp_path: Path) -> None:
    # VECT_BASE_X + VECT_12 + VECT_12 + VECT_8 groups: bit i of the 32-bit mask is column
    # base + i; a group may reach past the sensor edge as long as no set bit does.
    words = np.array(
        [
            0x8000,
            0x0002,  # y = 2
            0x3830, 0x4801, 0x4008, 0x5000,  # base 48 ON: bits 0, 11, 15 -> 48, 59, 63
            0x3000, 0x4003, 0x4000, 0x5080,  # base 0 OFF: bits 0, 1, 31 -> 0, 1, 31
            0x2805,  # a single event after the groups
        ],
        dtype="<u2",
    )
    rec = pr.read_raw(_write(tmp_path / "g.raw", EVT3_HEADER, words))
    expected = _ev([(0, 48, 2, 1), (0, 59, 2, 1), (0, 63, 2, 1), (0, 0, 2, -1), (0, 1, 2, -1),
                    (0, 31, 2, -1), (0, 5, 2, 1)])
    np.testing.assert_array_equal(rec.events, expected)
    bad = np.array([0x8000, 0x0002, 0x3830, 0x4000, 0x4000, 0x5001], dtype="<u2")
    path = _write(tmp_path / "gbad.raw", EVT3_HEADER, bad)
    with pytest.raises(ValueError, match=rf"byte offset {len(EVT3_HEADER) + 10}\b.*x=72"):
        pr.read_raw(path)


def test_evt2_hand_built_stream(tmp_path: Path) -> None:
    header = "% evt 2.0\n% geometry 64x8\n"  # no '% end', like older files
    words = np.array(
        [
            0x1000_0000 | (5 << 11) | 1,  # CD before any TIME_HIGH: dropped
            0x8000_0005,  # TIME_HIGH 5 -> base 320 µs
            0x1000_0000 | (3 << 22) | (10 << 11) | 2,  # ON ts 3 at (10, 2)
            0xA000_0000 | (7 << 22) | (3 << 8) | 0,  # trigger ts 7, channel 3, falling
            0x0000_0000 | (63 << 22) | (63 << 11) | 7,  # OFF ts 63 at (63, 7)
            0xE000_1234,  # OTHERS: ignored
            0xF000_0000,  # CONTINUED: ignored
            0x8FFF_FFFF,  # TIME_HIGH max -> base 2**34 - 64
            0x1000_0000 | (1 << 22) | 4,  # ON at (0, 4), t = 2**34 - 63
            0x8000_0000,  # TIME_HIGH 0 after the maximum: a 34-bit wrap
            0x0000_0000 | (2 << 22) | (1 << 11) | 5,  # OFF at (1, 5), t = 2**34 + 2
            0xA000_0000 | (1 << 22) | (31 << 8) | 1,  # trigger channel 31, rising
        ],
        dtype="<u4",
    )
    rec = pr.read_raw(_write(tmp_path / "e2.raw", header, words))
    assert rec.metadata["format"] == "evt2"
    np.testing.assert_array_equal(
        rec.events,
        _ev([(323, 10, 2, 1), (383, 63, 7, -1), (2**34 - 63, 0, 4, 1), (2**34 + 2, 1, 5, -1)]),
    )
    np.testing.assert_array_equal(rec.triggers, _tr([(327, False, 3), (2**34 + 1, True, 31)]))


@pytest.mark.parametrize("legacy", [False, True])
def test_evt21_hand_built_stream(tmp_path: Path, legacy: bool) -> None:
    words64 = [
        (0x8 << 60) | (2 << 32),  # TIME_HIGH 2 -> t = 128
        (0x1 << 60) | (5 << 54) | (32 << 43) | (6 << 32) | 0b1011,  # ON at x 32, 33, 35
        (0x0 << 60) | (9 << 54) | (0 << 43) | (1 << 32) | (1 << 31),  # OFF at x 31
        (0xA << 60) | (4 << 54) | (2 << 40) | (1 << 32),  # trigger channel 2, rising, t=132
        (0xE << 60) | 0xFFFF_FFFF,  # OTHERS: ignored
    ]
    w = np.array(words64, dtype=np.uint64)
    lo, hi = (w & np.uint64(0xFFFF_FFFF)).astype("<u4"), (w >> np.uint64(32)).astype("<u4")
    halves = np.empty(2 * w.shape[0], "<u4")
    halves[0::2], halves[1::2] = (hi, lo) if legacy else (lo, hi)
    fmt = "EVT21;height=8;width=64" + (";endianness=legacy" if legacy else "")
    rec = pr.read_raw(_write(tmp_path / "e21.raw", f"% format {fmt}\n% end\n", halves))
    assert rec.metadata["format"] == "evt21"
    np.testing.assert_array_equal(
        rec.events,
        _ev([(133, 32, 6, 1), (133, 33, 6, 1), (133, 35, 6, 1), (137, 31, 1, -1)]),
    )
    np.testing.assert_array_equal(rec.triggers, _tr([(132, True, 2)]))
    info = pr.raw_info(tmp_path / "e21.raw")
    assert info["evt21_layout"] == ("legacy" if legacy else "standard")


@pytest.mark.parametrize(
    ("header", "layout"),
    [
        ("% evt 2.1\n% geometry 64x8\n% system_ID 48\n% end\n", "legacy"),
        ("% evt 2.1\n% geometry 64x8\n% system_ID 64\n% end\n", "standard"),
        ("% evt 2.1\n% geometry 64x8\n% endianness little\n% system_ID 48\n% end\n", "standard"),
        ("% evt 2.1\n% geometry 64x8\n% system_ID 48\n% integrator_name Acme\n% end\n",
         "standard"),
    ],
)
def test_evt21_layout_rule(tmp_path: Path, header: str, layout: str) -> None:
    path = _write(tmp_path / "l.raw", header, b"")
    assert pr.raw_info(path)["evt21_layout"] == layout


# --------------------------------------------------------------------------------------
# round trips
# --------------------------------------------------------------------------------------


def test_evt3_round_trip_edges_ties_gaps_and_triggers(tmp_path: Path) -> None:
    width, height = 1280, 720
    rows = [
        (0, 0, 0, 1),
        (0, width - 1, height - 1, -1),  # geometry edge
        (0, width - 1, height - 1, -1),  # duplicate
        (3, 5, 5, 1),
        (3, 6, 5, 1),  # equal times
        (4095, 2, 2, -1),
        (4096, 2, 2, -1),  # TIME_HIGH step by one
        (2**24 - 1, 1, 1, 1),
        (2**24, 1, 1, 1),  # 24-bit wrap
        (2**24 + 3 * 2**24 + 777, 9, 9, -1),  # gap of > 3 wraps
        (2**33 + 12345, 100, 700, 1),  # gap of hours
    ]
    # a vector run of 32 columns (same time, row, polarity) at the right edge
    rows += [(2**33 + 20000, x, 719, 1) for x in range(width - 32, width)]
    rows += [(2**33 + 20000, x, 718, -1) for x in (0, 3, 4, 5, 31, 40)]
    events = _ev(rows)
    triggers = _tr([(0, True, 0), (3, False, 15), (2**24, True, 7), (2**33 + 20000, False, 1)])
    rec = Recording(events, width, height, triggers)
    path = tmp_path / "rt.raw"
    pr.write_raw_evt3(path, rec)
    back = pr.read_raw(path)
    np.testing.assert_array_equal(back.events, events)
    np.testing.assert_array_equal(back.triggers, triggers)
    assert (back.width, back.height) == (width, height)
    text = path.read_bytes()[:200]
    assert text.startswith(
        b"% evt 3.0\n% format EVT3;height=720;width=1280\n% geometry 1280x720\n"
        b"% asynhdr_metadata {}\n% end\n"
    )
    # an independent decoder reads the same stream
    theirs, their_triggers = _faery_decode(path)
    _assert_same_as_faery_events(back.events, theirs)
    np.testing.assert_array_equal(their_triggers["t"].astype(np.int64), triggers["t"])
    np.testing.assert_array_equal(their_triggers["source"], triggers["id"])


def test_evt3_round_trip_first_time_beyond_wraps(tmp_path: Path) -> None:
    events = _ev([(5 * 2**24 + 17, 1, 1, 1), (5 * 2**24 + 17, 2, 1, 1), (9 * 2**24, 3, 3, -1)])
    pr.write_raw_evt3(tmp_path / "late.raw", Recording(events, 16, 16))
    np.testing.assert_array_equal(pr.read_raw(tmp_path / "late.raw").events, events)


def test_evt3_payload_starting_with_percent_byte(tmp_path: Path) -> None:
    # The first payload word is TIME_HIGH 0x25: its first byte is '%'; '% end' protects it.
    events = _ev([(0x25 << 12, 4, 4, 1)])
    pr.write_raw_evt3(tmp_path / "pct.raw", Recording(events, 8, 8))
    data = (tmp_path / "pct.raw").read_bytes()
    assert data[data.index(b"% end\n") + 6] == ord("%")
    np.testing.assert_array_equal(pr.read_raw(tmp_path / "pct.raw").events, events)


def test_evt3_writer_streams_batches_like_one_write(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    rec = _random_recording(rng, 20_000, 640, 480, n_trig=40)
    pr.write_raw_evt3(tmp_path / "one.raw", rec)
    extra = {"camera_integrator_name": "Prophesee", "serial_number": "00ff"}
    with pr.Evt3Writer(tmp_path / "many.raw", width=640, height=480, header_extra=extra) as w:
        cuts = [0, 1, 5000, 5001, 13_000, 20_000]
        t_ev, t_tr = rec.events["t"], rec.triggers["t"]
        for a, b in itertools.pairwise(cuts):
            lo = t_ev[a] if a else np.iinfo(np.int64).min
            hi = t_ev[b] if b < t_ev.shape[0] else np.iinfo(np.int64).max
            w.write(rec.events[a:b], rec.triggers[(t_tr >= lo) & (t_tr < hi)])
    back = pr.read_raw(tmp_path / "many.raw")
    np.testing.assert_array_equal(back.events, rec.events)
    np.testing.assert_array_equal(back.triggers, rec.triggers)
    assert back.metadata["header"]["serial_number"] == "00ff"
    assert pr.read_raw(tmp_path / "one.raw").events.shape[0] == 20_000


def test_real_file_round_trip(data_dir: Path, tmp_path: Path) -> None:
    rec = pr.read_raw(data_dir / "events" / "imx636_evt3_triggers.raw")
    pr.write_raw_evt3(tmp_path / "copy.raw", rec)
    back = pr.read_raw(tmp_path / "copy.raw")
    np.testing.assert_array_equal(back.events, rec.events)
    np.testing.assert_array_equal(back.triggers, rec.triggers)


def test_evt2_round_trip_with_test_encoder(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    rec = _random_recording(rng, 5000, 640, 480, n_trig=10)
    events = rec.events.copy()
    events["t"] += 2**34 - 3000  # the stream crosses the 34-bit wrap
    triggers = rec.triggers.copy()
    triggers["t"] += 2**34 - 3000
    words = _encode_evt2(events, triggers)
    path = _write(tmp_path / "e2.raw", "% evt 2.0\n% format EVT2;height=480;width=640\n% end\n",
                  words.astype("<u4"))
    back = pr.read_raw(path)
    np.testing.assert_array_equal(back.events, events)
    np.testing.assert_array_equal(back.triggers, triggers)
    assert (events["t"] < 2**34).any() and (events["t"] > 2**34).any()
    theirs, _ = _faery_decode(path)
    _assert_same_as_faery_events(back.events, theirs)


@pytest.mark.parametrize("legacy", [False, True])
def test_evt21_round_trip_with_test_encoder(tmp_path: Path, legacy: bool) -> None:
    rng = np.random.default_rng(4)
    events = _random_recording(rng, 5000, 320, 320).events
    halves = _encode_evt21(events, legacy)
    opt = ";endianness=legacy" if legacy else ""
    path = _write(tmp_path / "e21.raw", f"% format EVT21;height=320;width=320{opt}\n% end\n",
                  halves.astype("<u4"))
    np.testing.assert_array_equal(pr.read_raw(path).events, events)
    chunks = list(pr.iter_raw(path, chunk_events=333, block_bytes=64))
    np.testing.assert_array_equal(_concat(chunks)[0], events)


# --------------------------------------------------------------------------------------
# headers and errors
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("header", "geometry"),
    [
        ("% evt 3.0\n% sensor_generation 3.1\n% end\n", (640, 480)),
        ("% evt 3.0\n% generation 4.2\n% end\n", (1280, 720)),
        ("% evt 3.0\n% sensor_name GenX320\n% end\n", (320, 320)),
        ("% evt 3.0\n% sensor_name IMX636\n% end\n", (1280, 720)),
        ("% evt 3.0\n% system_ID 48\n% integrator_name Prophesee\n% end\n", (1280, 720)),
        ("% evt 2.0\n% system_ID 21\n", (640, 480)),
        ("% evt 2.0\n% plugin_name hal_plugin_gen31_evk3\n% end\n", (640, 480)),
        ("% evt 3.0\n% plugin_name hal_plugin_imx636_evk4\n% end\n", (1280, 720)),
        ("% format EVT3;height=240;width=320\n% end\n", (320, 240)),
    ],
)
def test_geometry_sources(tmp_path: Path, header: str, geometry: tuple[int, int]) -> None:
    info = pr.raw_info(_write(tmp_path / "g.raw", header, b""))
    assert (info["width"], info["height"]) == geometry


def test_missing_geometry_asks_for_width_and_height(tmp_path: Path) -> None:
    path = _write(tmp_path / "nogeom.raw", "% evt 3.0\n% system_ID 48\n% integrator_name Acme\n",
                  np.array([0x8000, 0x0001, 0x2002], "<u2"))
    with pytest.raises(ValueError, match=r"nogeom\.raw.*width=.*height="):
        pr.read_raw(path)
    rec = pr.read_raw(path, width=4, height=4)
    np.testing.assert_array_equal(rec.events, _ev([(0, 2, 1, -1)]))
    with pytest.raises(ValueError, match="both width and height"):
        pr.raw_info(path, width=4)


def test_conflicting_header_geometry(tmp_path: Path) -> None:
    path = _write(tmp_path / "c.raw", "% format EVT3;height=8;width=64\n% geometry 32x8\n", b"")
    with pytest.raises(ValueError, match="disagrees"):
        pr.raw_info(path)


@pytest.mark.parametrize(
    "header",
    ["% evt 4.0\n% geometry 8x8\n", "% format HISTO3D;height=8;width=8\n", "% date today\n", ""],
)
def test_unsupported_or_missing_format_lists_supported(tmp_path: Path, header: str) -> None:
    path = _write(tmp_path / "u.raw", header, b"\x00\x80\x01\x00")
    with pytest.raises(ValueError, match=r"u\.raw.*EVT 2\.0.*EVT 2\.1.*EVT 3\.0"):
        pr.read_raw(path)


def test_long_header_lines_across_reads(tmp_path: Path) -> None:
    # Header lines longer than the first read and than the later ones; the payload
    # starts right after '% end', whatever its first byte.
    long_value = "v" * 70_000
    body = EVT3_HEADER.replace("% end\n", "")
    header = f"% note {long_value}\n{body}% other {long_value}x\n% end\n"
    words = np.array([0x8000, 0x0001, 0x2002], "<u2").tobytes()
    path = _write(tmp_path / "long.raw", header, words)
    info = pr.raw_info(path)
    assert info["header_bytes"] == len(header)
    assert info["header"]["note"] == long_value
    assert info["header"]["other"] == long_value + "x"
    np.testing.assert_array_equal(pr.read_raw(path).events, _ev([(0, 2, 1, -1)]))


def test_header_past_the_limit_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pr, "_MAX_HEADER_BYTES", 10_000)
    path = _write(tmp_path / "noeol.raw", "%" + "a" * 200_000, b"")
    with pytest.raises(ValueError, match=r"noeol\.raw: header line at byte 0 runs past 10000"):
        pr.raw_info(path)
    path = _write(tmp_path / "many.raw", "% note x\n" * 2_000 + EVT3_HEADER, b"")
    with pytest.raises(ValueError, match=r"many\.raw: header is longer than 10000 bytes"):
        pr.raw_info(path)
    # Just under the limit is fine.
    path = _write(tmp_path / "fits.raw", "% note x\n" * 1_000 + EVT3_HEADER, b"")
    assert pr.raw_info(path)["header_bytes"] == 9_000 + len(EVT3_HEADER)


def test_missing_file_or_folder(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"missing\.raw"):
        pr.read_raw(tmp_path / "missing.raw")
    with pytest.raises(ValueError, match="is a folder"):
        pr.raw_info(tmp_path)


def test_trailing_partial_word_is_ignored(tmp_path: Path) -> None:
    words = np.array([0x8000, 0x0001, 0x2002], "<u2").tobytes() + b"\x05"
    rec = pr.read_raw(_write(tmp_path / "t.raw", EVT3_HEADER, words))
    np.testing.assert_array_equal(rec.events, _ev([(0, 2, 1, -1)]))


def test_header_only_file_has_no_events(tmp_path: Path) -> None:
    rec = pr.read_raw(_write(tmp_path / "h.raw", EVT3_HEADER, b""))
    assert rec.events.shape == (0,) and rec.triggers.shape == (0,)
    chunks = list(pr.iter_raw(tmp_path / "h.raw"))
    assert len(chunks) == 1 and chunks[0][0].shape == (0,)


def test_writer_rejects_bad_input_and_leaves_no_file(tmp_path: Path) -> None:
    path = tmp_path / "w.raw"
    unsorted = _ev([(5, 1, 1, 1), (4, 1, 1, 1)])
    with pytest.raises(ValueError, match="not sorted"), pr.Evt3Writer(
        path, width=8, height=8
    ) as w:
        w.write(unsorted)
    assert not path.exists() and list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="before the last time"), pr.Evt3Writer(
        path, width=8, height=8
    ) as w:
        w.write(_ev([(10, 1, 1, 1)]))
        w.write(_ev([(9, 1, 1, 1)]))
    with pytest.raises(ValueError, match="outside the sensor"), pr.Evt3Writer(
        path, width=8, height=8
    ) as w:
        w.write(_ev([(10, 8, 1, 1)]))
    with pytest.raises(ValueError, match="channel 16"), pr.Evt3Writer(
        path, width=8, height=8
    ) as w:
        w.write(_ev([]), _tr([(1, True, 16)]))
    with pytest.raises(ValueError, match="subtract a start time"), pr.Evt3Writer(
        path, width=8, height=8
    ) as w:
        w.write(_ev([(2**34 + 1, 1, 1, 1)]))
    with pytest.raises(ValueError, match="header_extra key"):
        pr.Evt3Writer(path, width=8, height=8, header_extra={"bad key": 1})
    with pytest.raises(ValueError, match="written by the writer"):
        pr.Evt3Writer(path, width=8, height=8, header_extra={"geometry": "1x1"})
    with pytest.raises(ValueError, match=r"not open \(use it in a with block\)"):
        pr.Evt3Writer(path, width=8, height=8).write(_ev([(1, 1, 1, 1)]))
    assert not path.exists()
    unsorted_rec = Recording(unsorted, 8, 8)
    with pytest.raises(ValueError, match="not sorted"):
        pr.write_raw_evt3(path, unsorted_rec)
    assert list(tmp_path.iterdir()) == []


def test_supported_formats() -> None:
    assert set(pr.SUPPORTED_RAW_FORMATS) == {"evt2", "evt21", "evt3"}


# --------------------------------------------------------------------------------------
# property tests: corrupt input ends in valid events or a ValueError
# --------------------------------------------------------------------------------------

FUZZ_HEADERS = [
    EVT3_HEADER,
    "% evt 2.0\n% geometry 64x8\n",
    "% format EVT21;height=8;width=64\n% end\n",
    "% format EVT21;height=8;width=64;endianness=legacy\n% end\n",
]
_FUZZ = settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@pytest.fixture(scope="module")
def fuzz_seed_file(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A small EVT 3.0 file with vectors, gaps and triggers, as bytes."""
    rng = np.random.default_rng(11)
    rec = _random_recording(rng, 600, 64, 8, n_trig=5)
    ev = rec.events.copy()
    ev["t"][300:] += 2**24
    ev[100:140]["t"] = ev[100]["t"]
    ev[100:140]["y"] = 2
    ev[100:140]["p"] = 1
    ev[100:140]["x"] = np.arange(40) + 10
    ev = np.sort(ev, order="t", kind="stable")
    path = tmp_path_factory.mktemp("fuzz") / "seed.raw"
    pr.write_raw_evt3(path, Recording(ev, 64, 8, rec.triggers))
    return path.read_bytes()


def _decode_or_value_error(path: Path) -> None:
    try:
        rec = pr.read_raw(path)
    except ValueError as exc:
        assert str(path) in str(exc)
        return
    validate_events(rec.events, width=rec.width, height=rec.height, require_sorted=False)
    events, _ = _concat(list(pr.iter_raw(path, chunk_events=37, block_bytes=32)))
    np.testing.assert_array_equal(events, rec.events)


@_FUZZ
@given(cut=st.integers(min_value=0, max_value=10_000))
def test_truncated_files(tmp_path: Path, fuzz_seed_file: bytes, cut: int) -> None:
    path = tmp_path / "cut.raw"
    path.write_bytes(fuzz_seed_file[: cut % (len(fuzz_seed_file) + 1)])
    _decode_or_value_error(path)


@_FUZZ
@given(header=st.sampled_from(FUZZ_HEADERS), payload=st.binary(max_size=1500))
def test_random_payloads(tmp_path: Path, header: str, payload: bytes) -> None:
    path = _write(tmp_path / "rnd.raw", header, payload)
    _decode_or_value_error(path)


@_FUZZ
@given(data=st.binary(max_size=600))
def test_random_files(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "junk.raw"
    path.write_bytes(data)
    _decode_or_value_error(path)


@_FUZZ
@given(flips=st.lists(st.integers(min_value=0, max_value=10**7), min_size=1, max_size=12))
def test_flipped_bits(tmp_path: Path, fuzz_seed_file: bytes, flips: list[int]) -> None:
    data = bytearray(fuzz_seed_file)
    for f in flips:
        bit = f % (8 * len(data))
        data[bit // 8] ^= 1 << (bit % 8)
    path = tmp_path / "flip.raw"
    path.write_bytes(bytes(data))
    _decode_or_value_error(path)


# --------------------------------------------------------------------------------------
# parallel EVT 3.0 decoding: the same result as the sequential decoder, however cut
# --------------------------------------------------------------------------------------

EVT3_FILES = ("evtemmap_imx636_evt3.raw", "gen41_evt3.raw", "imx636_evt3_triggers.raw")


def _force_parallel(monkeypatch: pytest.MonkeyPatch, threads: int) -> list[int]:
    """Decode every EVT 3.0 payload / block in parallel parts; returns a call counter."""
    calls: list[int] = []
    real = pr._evt3_decode_parallel

    def counting(*args: Any, **kwargs: Any) -> Any:
        calls.append(len(args[4]) - 1)  # parts
        return real(*args, **kwargs)

    monkeypatch.setattr(pr, "_decode_threads", lambda: threads)
    monkeypatch.setattr(pr, "_PARALLEL_MIN_WORDS", 1)
    monkeypatch.setattr(pr, "_PARALLEL_MIN_PART_WORDS", 1)
    monkeypatch.setattr(pr, "_evt3_decode_parallel", counting)
    return calls


def _sequential(path: Path, **kwargs: Any) -> tuple[Recording, list[tuple[np.ndarray, np.ndarray]]]:
    """read_raw and iter_raw on one thread (the reference)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pr, "_decode_threads", lambda: 1)
        return pr.read_raw(path), list(pr.iter_raw(path, **kwargs))


def _assert_same_chunks(
    ours: list[tuple[np.ndarray, np.ndarray]], ref: list[tuple[np.ndarray, np.ndarray]]
) -> None:
    assert [c[0].shape[0] for c in ours] == [c[0].shape[0] for c in ref]
    for (ev, tr), (ev_ref, tr_ref) in zip(ours, ref, strict=True):
        np.testing.assert_array_equal(ev, ev_ref)
        np.testing.assert_array_equal(tr, tr_ref)


def _decode_in_parts(
    words: np.ndarray, width: int, height: int, starts: list[int], first_apart: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, np.ndarray]:
    """Events, triggers, trigger index, status, stop word and end state of a parallel decode
    (all parts in one buffer, or part 0 in the result and the others in scratch)."""
    state = np.zeros(pr._k.EVT3_STATE_SIZE, np.int64)
    out = np.empty(pr._evt3_scratch_size(starts), EVENT_DTYPE)
    if first_apart:
        scratch = np.empty(pr._evt3_scratch_size(starts, 1), EVENT_DTYPE)
        dec = pr._evt3_decode_parallel(words, state, width, height, starts, scratch, first=out)
    else:
        dec = pr._evt3_decode_parallel(words, state, width, height, starts, out)
    events = pr._join_pieces(dec, out)[: dec.n_events]
    return events, dec.triggers, dec.tr_index, dec.status, dec.pos, state


def _evt3_words(path: Path) -> np.ndarray:
    info = pr.raw_info(path)
    return np.frombuffer(path.read_bytes()[info["header_bytes"] :], "<u2").copy()


def _sequential_state(words: np.ndarray, width: int, height: int) -> np.ndarray:
    """Decoder state after the whole stream, from one sequential kernel call."""
    state = np.zeros(pr._k.EVT3_STATE_SIZE, np.int64)
    events = np.empty(12 * words.shape[0] + 64, EVENT_DTYPE)
    triggers = np.empty(words.shape[0] + 1, TRIGGER_DTYPE)
    status, *_ = pr._k.decode_evt3(
        words, 0, state, width, height, events, 0, events.shape[0], triggers, 0,
        np.empty(0, np.int64),
    )
    assert status == pr._k.STATUS_DONE
    return state


@pytest.mark.parametrize("name", EVT3_FILES)
@pytest.mark.parametrize("threads", [2, 3, 7])
def test_evt3_parallel_equals_sequential_on_real_files(
    name: str, threads: int, data_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = data_dir / "events" / name
    kwargs = {"chunk_events": 4096, "block_bytes": 1 << 18}
    rec_ref, chunks_ref = _sequential(path, **kwargs)
    calls = _force_parallel(monkeypatch, threads)
    rec = pr.read_raw(path)
    assert calls and calls[0] == pr._PARTS_PER_THREAD * threads  # it did run in parts
    np.testing.assert_array_equal(rec.events, rec_ref.events)
    np.testing.assert_array_equal(rec.triggers, rec_ref.triggers)
    _assert_same_chunks(list(pr.iter_raw(path, **kwargs)), chunks_ref)


@pytest.mark.parametrize("name", EVT3_FILES)
def test_evt3_parallel_without_nearby_vector_base(
    name: str, data_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Parts that must look up the vector base later (or take it from the part before).
    path = data_dir / "events" / name
    rec_ref, chunks_ref = _sequential(path, chunk_events=50_000)
    _force_parallel(monkeypatch, 5)
    monkeypatch.setattr(pr, "_BASE_SCAN_WORDS", 0)
    monkeypatch.setattr(pr, "_SCRATCH_KEEP_EVENTS", 0)  # read_raw: every part in the result
    np.testing.assert_array_equal(pr.read_raw(path).events, rec_ref.events)
    _assert_same_chunks(list(pr.iter_raw(path, chunk_events=50_000)), chunks_ref)


@pytest.fixture(scope="module")
def evt3_mixed_stream(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Recording]:
    """An EVT 3.0 file with every kind of word: single events, 32-column vector groups,
    short runs, triggers, a gap of more than one 24-bit wrap and a dense vector burst."""
    width, height = 96, 6
    rng = np.random.default_rng(23)
    rows: list[tuple[int, int, int, int]] = []
    t = 1000
    for _ in range(60):  # single events on a few rows
        t += int(rng.integers(0, 40))
        rows.append((t, int(rng.integers(0, width)), int(rng.integers(0, height)), 1))
    for k in range(6):  # vector runs: full groups, partial groups, a short run
        t += 5
        xs = [32 + x for x in range(32)] if k % 2 == 0 else [64 + x for x in (1, 2, 5, 9, 30)]
        rows += [(t, x, k % height, 1 if k % 3 else -1) for x in xs]
    t += 2**24 + 4321  # more than a wrap: 4,097 TIME_HIGH words
    for k in range(120):  # dense vector burst: many more events than words
        t += 1
        rows += [(t, x, k % height, -1) for x in range(width)]
    for _ in range(30):
        t += int(rng.integers(0, 5000))
        rows.append((t, int(rng.integers(0, width)), int(rng.integers(0, height)), -1))
    events = _ev(rows)
    tt = np.sort(rng.choice(events["t"], 9, replace=False))
    triggers = make_triggers(tt, rising=np.arange(9) % 2 == 0, id=np.arange(9) % 16)
    rec = Recording(events, width, height, triggers)
    path = tmp_path_factory.mktemp("par") / "mixed.raw"
    pr.write_raw_evt3(path, rec)
    return path, rec


def test_evt3_parallel_split_at_every_word(evt3_mixed_stream: tuple[Path, Recording]) -> None:
    path, rec = evt3_mixed_stream
    words = _evt3_words(path)
    kinds = set((words >> 12).tolist())
    assert {0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x8, 0xA} <= kinds
    n = words.shape[0]
    assert rec.events.shape[0] > n  # the burst makes more events than words
    end_state = _sequential_state(words, rec.width, rec.height)
    # the number of events before each trigger (triggers come before events of their µs)
    tr_index = np.searchsorted(rec.events["t"], rec.triggers["t"], side="left")
    cuts = [[0, s, n] for s in range(1, n)]
    rng = np.random.default_rng(5)
    cuts += [[0, *sorted(rng.choice(np.arange(1, n), 6, replace=False).tolist()), n]
             for _ in range(20)]
    for i, starts in enumerate(cuts):
        events, triggers, index, status, pos, state = _decode_in_parts(
            words, rec.width, rec.height, starts, first_apart=i % 2 == 1
        )
        assert (status, pos) == (pr._k.STATUS_DONE, n), starts
        np.testing.assert_array_equal(events, rec.events, err_msg=str(starts))
        np.testing.assert_array_equal(triggers, rec.triggers, err_msg=str(starts))
        np.testing.assert_array_equal(index, tr_index, err_msg=str(starts))
        np.testing.assert_array_equal(state, end_state, err_msg=str(starts))


EVT3_TRICKY_WORDS = [
    0x2005,  # before any TIME_HIGH: dropped
    0x3004,  # VECT_BASE_X before any TIME_HIGH: dropped
    0x8001,  # TIME_HIGH 1
    0x4FFF,  # vector with no row yet: dropped, base not advanced
    0x0803,  # y = 3
    0x4FFF,  # vector with no VECT_BASE_X yet: dropped, the base is not set
    0x6010,  # TIME_LOW 0x10
    0x3810,  # VECT_BASE_X 16, ON
    0x4003,  # x = 16, 17; base -> 28
    0x6008,  # TIME_LOW 8: steps back
    0x5081,  # x = 28, 35; base -> 36
    0x1002,  # non-CD row
    0x4FFF,  # vector on a non-CD row: dropped, base stays 36
    0x2001,  # event on a non-CD row: dropped
    0xA101,  # trigger on channel 1
    0x0002,  # y = 2
    0x4001,  # x = 36; base -> 48
    0x8001,  # the same TIME_HIGH again: TIME_LOW kept
    0x2805,  # ON at x = 5, t = 4096 + 8
    0x8002,  # TIME_HIGH 2: TIME_LOW reset to 0
    0x2006,  # OFF at x = 6, t = 8192
    0x6FFF,  # TIME_LOW 0xFFF
    0x8003,  # TIME_HIGH 3: TIME_LOW reset to 0
    0x2009,  # OFF at x = 9, t = 3 * 4096
    0x7123,  # CONTINUED_4: ignored
    0x8FFF,  # TIME_HIGH 0xFFF
    0x8000,  # TIME_HIGH 0: a wrap
    0x2807,  # ON at x = 7, t = 2**24
    0xA000,  # trigger on channel 0
    0x8800,  # TIME_HIGH 0x800
    0x8000,  # TIME_HIGH 0: a fall of exactly 2048, another wrap
    0x6007,  # TIME_LOW 7
    0x4001,  # x = 48; base -> 60
    0xE012,  # OTHERS: ignored
    0x2008,  # OFF at x = 8, t = 2 * 2**24 + 7
]


def test_evt3_parallel_hand_built_stream_every_cut(tmp_path: Path) -> None:
    words = np.array(EVT3_TRICKY_WORDS, "<u2")
    path = _write(tmp_path / "tricky.raw", EVT3_HEADER, words)
    expected = _ev([
        (4096 + 0x10, 16, 3, 1), (4096 + 0x10, 17, 3, 1), (4096 + 8, 28, 3, 1),
        (4096 + 8, 35, 3, 1), (4096 + 8, 36, 2, 1), (4096 + 8, 5, 2, 1), (8192, 6, 2, -1),
        (3 * 4096, 9, 2, -1), (2**24, 7, 2, 1), (2 * 2**24 + 7, 48, 2, 1),
        (2 * 2**24 + 7, 8, 2, -1),
    ])
    rec_ref, _ = _sequential(path)
    np.testing.assert_array_equal(rec_ref.events, expected)
    np.testing.assert_array_equal(rec_ref.triggers, _tr([(4096 + 8, True, 1), (2**24, False, 0)]))
    end_state = _sequential_state(words, 64, 8)
    n = words.shape[0]
    for base_scan in (pr._BASE_SCAN_WORDS, 0, 2):
        for a, b in itertools.combinations(range(n + 1), 2):
            starts = sorted({0, a, b, n})
            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(pr, "_BASE_SCAN_WORDS", base_scan)
                events, triggers, _, status, _, state = _decode_in_parts(
                    words, 64, 8, starts, first_apart=(a + b) % 2 == 1
                )
            assert status == pr._k.STATUS_DONE
            np.testing.assert_array_equal(events, expected, err_msg=str(starts))
            np.testing.assert_array_equal(triggers, rec_ref.triggers, err_msg=str(starts))
            np.testing.assert_array_equal(state, end_state, err_msg=str(starts))


@pytest.mark.parametrize(
    ("chunk_events", "block_bytes"), [(1, 8), (3, 16), (4, 64), (100, 1 << 20)]
)
def test_evt3_parallel_blocks_carry_state(
    tmp_path: Path,
    evt3_mixed_stream: tuple[Path, Recording],
    chunk_events: int,
    block_bytes: int,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Every block decoded in parallel parts, the state carried from block to block.
    tricky = _write(tmp_path / "tricky.raw", EVT3_HEADER, np.array(EVT3_TRICKY_WORDS, "<u2"))
    path, _ = evt3_mixed_stream
    refs = {p: _sequential(p, chunk_events=chunk_events, block_bytes=block_bytes)[1]
            for p in (tricky, path)}
    calls = _force_parallel(monkeypatch, 3)
    for p, ref in refs.items():
        _assert_same_chunks(
            list(pr.iter_raw(p, chunk_events=chunk_events, block_bytes=block_bytes)), ref
        )
    assert calls


@pytest.mark.parametrize(
    ("words", "offset_words", "events_before"),
    [
        # x=64 after three events, x=65 later
        ([0x8000, 0x0001, 0x2001, 0x2002, 0x2003, 0x2040, 0x2004, 0x2041, 0x2005], 5, 3),
        # y=8 at the first event, x=64 later
        ([0x8000, 0x0008, 0x6001, 0x2001, 0x0001, 0x2002, 0x2040], 3, 0),
        # x=88 from a vector word, y=9 later
        ([0x8000, 0x0001, 0x2001, 0x303C, 0x4000, 0x4000, 0x4010, 0x2003, 0x0009, 0x2001], 6, 1),
    ],
)
def test_evt3_parallel_reports_the_first_error(
    tmp_path: Path,
    words: list[int],
    offset_words: int,
    events_before: int,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    path = _write(tmp_path / "bad.raw", EVT3_HEADER, np.array(words, dtype="<u2"))
    offset = len(EVT3_HEADER) + 2 * offset_words
    ref_chunks = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pr, "_decode_threads", lambda: 1)
        with pytest.raises(ValueError, match=rf"byte offset {offset}\b"):
            for chunk in pr.iter_raw(path, chunk_events=1):
                ref_chunks.append(chunk)
    _force_parallel(monkeypatch, 3)
    with pytest.raises(ValueError, match=rf"bad\.raw.*byte offset {offset}\b"):
        pr.read_raw(path)
    chunks = []
    with pytest.raises(ValueError, match=rf"byte offset {offset}\b"):
        for chunk in pr.iter_raw(path, chunk_events=1):
            chunks.append(chunk)
    _assert_same_chunks(chunks, ref_chunks)  # the chunks before the error come out first
    assert len(chunks) == events_before  # one event a chunk


@pytest.mark.parametrize("parallel", [False, True])
def test_iter_raw_last_chunk_never_exceeds_chunk_events(
    tmp_path: Path, parallel: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A 32-column vector group at the very end makes 32 events from the last words.
    words = np.array([0x8000, 0x0001, 0x2001, 0x3800, 0x4FFF, 0x4FFF, 0x50FF], "<u2")
    path = _write(tmp_path / "v.raw", "% evt 3.0\n% geometry 64x8\n% end\n", words)
    if parallel:
        _force_parallel(monkeypatch, 2)
    for chunk_events in (1, 5, 32, 33):
        chunks = list(pr.iter_raw(path, chunk_events=chunk_events))
        sizes = [c[0].shape[0] for c in chunks]
        assert sum(sizes) == 33
        assert all(s == chunk_events for s in sizes[:-1]) and 0 < sizes[-1] <= chunk_events
