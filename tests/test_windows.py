"""Streaming a recording window by window, and reconstructing a file cycle by cycle."""

from __future__ import annotations

import itertools
import logging
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from asynhdr.events import Recording, empty_triggers, make_events, make_triggers
from asynhdr.io import open_recording, open_source, write_recording
from asynhdr.reconstruct import reconstruct, reconstruct_cycles, windows_for
from asynhdr.scene import step_chart
from asynhdr.segment import NoCyclesError, cycles_from_events, find_cycles
from asynhdr.simulate import simulate
from asynhdr.source import Window, windows_from_chunks


def _events(t: list[int]) -> np.ndarray:
    n = len(t)
    return make_events(np.arange(n) % 7, np.arange(n) % 5, np.where(np.arange(n) % 2, 1, -1),
                       np.array(t, dtype=np.int64))


def _chunks(ev: np.ndarray, cuts: list[int], tr: np.ndarray | None = None
            ) -> list[tuple[np.ndarray, np.ndarray]]:
    bounds = [0, *cuts, ev.size]
    out = [(ev[a:b], make_triggers(np.zeros(0, np.int64)))
           for a, b in itertools.pairwise(bounds)]
    if tr is not None:
        out[0] = (out[0][0], tr)
    return out


def test_windows_by_hand(caplog: pytest.LogCaptureFixture) -> None:
    # file order, with a 4 µs step back (8 after 12: inside the 5 µs hold-back) and a
    # late event (35 after 50: window [30, 40) was yielded once the stream reached 45)
    t = [1, 5, 9, 12, 8, 25, 31, 39, 41, 45, 50, 35, 52]
    ev = _events(t)
    tr = make_triggers([30, 0, 10], True, 0)  # not sorted: windows sort their own
    starts = np.array([0, 10, 30])
    stops = np.array([10, 20, 40])
    with caplog.at_level(logging.WARNING):
        wins = list(windows_from_chunks(_chunks(ev, [3, 7, 11], tr), starts, stops,
                                        holdback_us=5, name="hand"))
    assert [w.i for w in wins] == [0, 1, 2]
    assert [list(w.events["t"]) for w in wins] == [[1, 5, 9, 8], [12], [31, 39]]
    assert [list(w.triggers["t"]) for w in wins] == [[0], [10], [30]]
    np.testing.assert_array_equal(wins[0].events, ev[[0, 1, 2, 4]])  # fields kept
    assert "hand: 1 events stepped back more than 5 µs" in caplog.text


def test_overlapping_and_empty_windows() -> None:
    ev = _events([0, 3, 6, 9, 12])
    wins = list(windows_from_chunks(_chunks(ev, [2]), np.array([0, 5, 20]),
                                    np.array([10, 8, 30]), holdback_us=0))
    assert [list(w.events["t"]) for w in wins] == [[0, 3, 6, 9], [6], []]
    assert wins[2] == Window(2, 20, 30, wins[2].events, wins[2].triggers)


@pytest.mark.parametrize("starts, stops, message", [
    ([0, 0], [5, 6], "must increase strictly"),
    ([0, 10], [5, 10], "window 1 ends"),
    ([[0]], [[5]], "1-D"),
])
def test_bad_windows_are_named(starts: list[int], stops: list[int], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        list(windows_from_chunks([], np.array(starts), np.array(stops)))


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_any_chunking_gives_the_direct_selection(data: st.DataObject) -> None:
    """Step-backs within the hold-back, cut into chunks anywhere: each window holds
    exactly the events whose time falls in it, in file order."""
    n = data.draw(st.integers(0, 120))
    steps = data.draw(st.lists(st.integers(-6, 9), min_size=n, max_size=n))
    t = np.maximum.accumulate(np.cumsum(np.array(steps, dtype=np.int64)))  # running max
    back = np.array(data.draw(st.lists(st.integers(0, 6), min_size=n, max_size=n)),
                    dtype=np.int64)
    times = (t - back).tolist()  # at most 6 µs behind the latest time so far
    ev = _events(times)
    k = data.draw(st.integers(1, 8))
    starts = np.cumsum(np.array(data.draw(st.lists(st.integers(1, 40), min_size=k,
                                                   max_size=k)))) - 20
    lengths = np.array(data.draw(st.lists(st.integers(1, 60), min_size=k, max_size=k)))
    cuts = sorted(data.draw(st.lists(st.integers(0, n), max_size=6)))
    wins = list(windows_from_chunks(_chunks(ev, cuts), starts, starts + lengths,
                                    holdback_us=6))
    assert len(wins) == k
    tt = ev["t"]
    for w, s, e in zip(wins, starts, starts + lengths, strict=True):
        np.testing.assert_array_equal(w.events, ev[(tt >= s) & (tt < e)])


# ------------------------------------------------------------------ files, cycle by cycle


@pytest.fixture(scope="module")
def simulated() -> Recording:
    return simulate(step_chart(width=48, height=36), sensor="v2e", n_cycles=4, rng=5)


@pytest.mark.parametrize("ext", [".h5", ".raw"])
@pytest.mark.parametrize("method", ["exp", "ttfe", "count", "invert"])
def test_file_cycle_by_cycle_equals_whole(tmp_path: Path, simulated: Recording, ext: str,
                                          method: str) -> None:
    path = tmp_path / f"rec{ext}"
    write_recording(path, simulated)
    whole = reconstruct(open_recording(path), method=method)
    plan = reconstruct_cycles(open_source(path), method=method)
    assert len(plan) == whole.shape[0] == 4
    streamed = [(i, s, img) for i, s, img in plan]
    assert [i for i, _, _ in streamed] == [0, 1, 2, 3]
    np.testing.assert_array_equal(np.stack([img for _, _, img in streamed]), whole)
    assert plan.n_events == simulated.events.size


def test_file_without_triggers_takes_the_event_rate(tmp_path: Path,
                                                    simulated: Recording) -> None:
    bare = Recording(simulated.events, simulated.width, simulated.height, empty_triggers())
    path = tmp_path / "no_triggers.raw"
    write_recording(path, bare)
    cyc = find_cycles(open_source(path))
    ref = cycles_from_events(bare.events)
    np.testing.assert_array_equal(cyc.start_us, ref.start_us)
    assert cyc.period_us == ref.period_us and cyc.source == "event_rate"
    assert find_cycles(bare).start_us.tolist() == cyc.start_us.tolist()  # in memory: same
    whole = open_recording(path)
    plan = reconstruct_cycles(open_source(path), method="exp")
    np.testing.assert_array_equal(plan.windows.start_us, windows_for(whole).start_us)
    np.testing.assert_array_equal(np.stack([img for _, _, img in plan]),
                                  reconstruct(whole, method="exp"))


def test_iter_windows_reads_a_file(tmp_path: Path, simulated: Recording) -> None:
    path = tmp_path / "rec.h5"
    write_recording(path, simulated)
    starts = np.array([0, 50_000, 120_000])
    stops = starts + 20_000
    t = simulated.events["t"]
    for w in open_source(path).windows(starts, stops):
        np.testing.assert_array_equal(
            w.events, simulated.events[(t >= starts[w.i]) & (t < stops[w.i])])
        assert w.triggers["t"].tolist() == [s for s in (0, 50_000, 100_000, 150_000)
                                            if starts[w.i] <= s < stops[w.i]]


def test_an_unmodulated_file_is_refused_not_cut_at_random(tmp_path: Path) -> None:
    """No triggers and no periodic bursts: an error that says so and what to give,
    instead of images cut at a guessed period."""
    rng = np.random.default_rng(2)
    n = 40_000
    ev = make_events(rng.integers(0, 32, n), rng.integers(0, 24, n),
                     rng.choice(np.array([-1, 1], np.int8), n),
                     np.sort(rng.integers(0, 2_000_000, n)))
    path = tmp_path / "steady.h5"
    write_recording(path, Recording(ev, 32, 24))
    with pytest.raises(NoCyclesError, match=r"no modulation in the event rate .*confidence "
                                            r"0\.\d\d.*give the modulation period"):
        reconstruct_cycles(open_source(path))
    with pytest.raises(NoCyclesError, match=r"; treat the recording as one ramp"):
        reconstruct_cycles(open_source(path), period_us=50_000)
