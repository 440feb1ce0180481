"""One cycle policy (``find_cycles``) for every command: the same cycles from ``info`` and
``reconstruct`` on every file, no guessing below the confidence, and the warm-up cycle."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from asynhdr.cli import _register, app
from asynhdr.events import Recording, empty_triggers, make_events, make_triggers
from asynhdr.io import open_recording, open_source, write_recording
from asynhdr.io.images import read_image
from asynhdr.reconstruct import first_on_phase, reconstruct, windows_for
from asynhdr.rig import Rig
from asynhdr.scene import step_chart
from asynhdr.segment import MIN_COVERAGE, NoCyclesError, find_cycles
from asynhdr.simulate import simulate

_register()
runner = CliRunner()

REAL = ["davis346_triggers.aedat4", "dvxplorer.aedat4", "evtemmap_imx636_evt3.raw",
        "gen3_evt2.raw", "gen41_evt3.raw", "imx636_evt3_triggers.raw"]


def _info_cycles(path: Path) -> dict | None:
    r = runner.invoke(app, ["info", str(path), "--json"])
    assert r.exit_code == 0, r.output
    return json.loads(r.output)["cycles"]


def _reconstructed(path: Path, out: Path) -> int | None:
    """Images ``reconstruct`` writes, or None when it finds no cycles (and writes none)."""
    r = runner.invoke(app, ["reconstruct", str(path), "-o", str(out), "--formats", "npy"])
    if r.exit_code == 2 and "no cycles found" in r.output:
        assert not out.exists() or not any(out.iterdir())
        return None
    assert r.exit_code == 0, r.output
    return len(list(out.glob("*.npy")))


@pytest.mark.parametrize("name", REAL)
def test_info_and_reconstruct_agree_on_real_files(data_dir: Path, tmp_path: Path,
                                                  name: str) -> None:
    path = data_dir / "events" / name
    if not path.is_file():
        pytest.skip(f"{path} not found")
    cyc = _info_cycles(path)
    n = _reconstructed(path, tmp_path / "img")
    assert (cyc["cycles"] if cyc else None) == n
    # none of the shared recordings is modulated: no triggers (the DAVIS346 sample's 15
    # records are frame markers; the IMX636 file has one rising edge), no regular bursts
    assert n is None


@pytest.mark.parametrize("ext", [".raw", ".h5"])
@pytest.mark.parametrize("triggers", [True, False])
def test_info_and_reconstruct_agree_on_simulated_files(tmp_path: Path, ext: str,
                                                       triggers: bool) -> None:
    rec = simulate(step_chart(width=40, height=24), sensor="v2e", n_cycles=4, rng=1)
    if not triggers:  # neither triggers nor a rig: the event rate alone
        rec = Recording(rec.events, rec.width, rec.height, empty_triggers())
    path = tmp_path / f"rec{ext}"
    write_recording(path, rec)
    cyc = _info_cycles(path)
    assert cyc is not None
    assert cyc["source"] == ("triggers" if triggers else "event_rate")
    assert _reconstructed(path, tmp_path / "img") == cyc["cycles"]


def test_evtemmap_without_single_writes_nothing_and_with_single_shows_the_scene(
        data_dir: Path, tmp_path: Path) -> None:
    path = data_dir / "events" / "evtemmap_imx636_evt3.raw"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    out = tmp_path / "img"
    r = runner.invoke(app, ["reconstruct", str(path), "-o", str(out)])
    text = " ".join(r.output.split())
    assert r.exit_code == 2 and "no cycles found" in text and "pass --period-us or --single" \
        in text and not out.exists()
    r = runner.invoke(app, ["reconstruct", str(path), "-o", str(out), "--single", "--method",
                            "ttfe", "--formats", "exr"])
    assert r.exit_code == 0, r.output
    img = read_image(out / "evtemmap_imx636_evt3_ttfe_0000.exr")
    rec = open_recording(path)
    ref = reconstruct(rec, method="ttfe", windows=windows_for(rec, single=True))[0]
    np.testing.assert_array_equal(img, ref)
    assert img[50:250, 20:120].mean() > 2.5 * img[450:700, 200:380].mean()  # wall vs grille


@pytest.mark.parametrize("method", ["raw", "linear", "quadratic", "poly5", "exp", "ttfe",
                                    "count"])
def test_gen3_single_is_finite_for_every_method(data_dir: Path, method: str) -> None:
    """A hot pixel of gen3_evt2.raw fires 3,323 ON events and no OFF: exp(c S) is beyond
    float32 (it used to overflow into inf and write nothing); such pixels saturate at the
    largest float32 and are counted in a warning, the rest of the image is untouched."""
    path = data_dir / "events" / "gen3_evt2.raw"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    rec = open_recording(path)
    img = reconstruct(rec, method=method, windows=windows_for(rec, single=True))[0]
    assert np.isfinite(img).all()
    hot = (565, 296)  # x, y of the pixel with 3,323 ON events
    if method != "ttfe":
        assert img[hot[1], hot[0]] == np.finfo(np.float32).max
    else:
        assert 0 < img[hot[1], hot[0]] < np.inf


def _bursts(width: int, height: int, fraction: float, rng: np.random.Generator) -> Recording:
    """Bursts every 10 ms on ``fraction`` of the pixels (a different part each time),
    over background noise on every pixel."""
    n_px = width * height
    parts = []
    for k in range(20):
        px = rng.choice(n_px, int(fraction * n_px), replace=False)
        t = k * 10_000 + rng.integers(0, 1500, px.size)
        parts.append((px, t))
    noise_px = rng.integers(0, n_px, 4000)
    parts.append((noise_px, rng.integers(0, 200_000, noise_px.size)))
    px = np.concatenate([p for p, _ in parts])
    t = np.concatenate([t for _, t in parts])
    order = np.argsort(t, kind="stable")
    ev = make_events(px[order] % width, px[order] // width, np.ones(px.size), t[order])
    return Recording(ev, width, height)


def test_bursts_of_part_of_the_sensor_are_not_modulation() -> None:
    """Regular bursts of a tenth of the pixels (an APS frame readout) are refused on the
    coverage; the same bursts on every pixel (what the panels do) give the cycles."""
    rng = np.random.default_rng(3)
    with pytest.raises(NoCyclesError, match=rf"pixel coverage 0\.\d\d; needed: confidence "
                                            rf">= 0.2 and coverage >= {MIN_COVERAGE:g}"):
        find_cycles(_bursts(40, 30, 0.1, rng))
    cyc = find_cycles(_bursts(40, 30, 0.95, rng))
    assert cyc.source == "event_rate" and cyc.period_us == pytest.approx(10_000, rel=0.002)


def test_triggers_come_first_and_only_rising_edges_count() -> None:
    rec = _bursts(20, 10, 0.9, np.random.default_rng(5))
    tr = make_triggers([1000, 5000, 11_000, 21_000, 31_000], [False, False, True, True, True])
    cyc = find_cycles(Recording(rec.events, 20, 10, tr))
    assert cyc.source == "triggers" and cyc.start_us.tolist() == [11_000, 21_000, 31_000]


def test_warmup_cycle_is_flagged_and_differs() -> None:
    """The simulator starts every pixel adapted to the first light of the cycle; after a
    cycle, a pixel whose ON and OFF thresholds differ ends a fraction of a threshold away
    from it, so its first ON event comes later. Cycle 0 is flagged; with identical pixel
    thresholds (the ideal preset) every cycle is alike."""
    chart = step_chart(width=48, height=36)
    for preset, differs in (("v2e", True), ("ideal", False)):
        rec = simulate(chart, rig=Rig(), sensor=preset, n_cycles=3, rng=2, sensor_seed=4)
        cyc = find_cycles(rec)
        assert cyc.warmup == 1
        u = first_on_phase(rec, windows_for(rec))
        med = [float(np.nanmedian(x)) for x in u]
        if differs:
            assert abs(med[0] - med[1]) > 5 * abs(med[1] - med[2]), med
        else:
            assert med[0] == med[1] == med[2]
    # a recording that starts inside a cycle has no warm-up cycle
    late = rec.events[rec.events["t"] >= 20_000]
    cut = Recording(late, rec.width, rec.height, rec.triggers[1:], rec.metadata)
    assert find_cycles(cut).warmup == 0


def test_a_file_and_its_recording_give_the_same_cycles(tmp_path: Path) -> None:
    rec = _bursts(40, 30, 0.95, np.random.default_rng(8))
    path = tmp_path / "b.h5"
    write_recording(path, rec)
    a, b = find_cycles(rec), find_cycles(open_source(path))
    np.testing.assert_array_equal(a.start_us, b.start_us)
    assert (a.period_us, a.confidence, a.warmup) == (b.period_us, b.confidence, b.warmup)


def test_a_single_ramp_starts_at_the_trigger_that_opens_it() -> None:
    from asynhdr.scene import flat_field

    rec = simulate(flat_field(width=12, height=8, radiance=100.0), sensor="ideal", n_cycles=1,
                   rng=0)
    first_edge = int(rec.triggers["t"][rec.triggers["rising"]][0])
    assert first_edge < int(rec.events["t"].min())  # the sensor needs time to fire
    win = windows_for(rec, single=True)
    assert int(win.start_us[0]) == first_edge
    for method in ("invert", "ttfe"):
        img = reconstruct(rec, method=method, windows=win)[0]
        assert abs(float(np.median(img)) / 100.0 - 1.0) < 0.01, method
    # without triggers, the first event opens it
    bare = Recording(rec.events, rec.width, rec.height, triggers=empty_triggers(),
                     metadata=rec.metadata)
    assert int(windows_for(bare, single=True).start_us[0]) == int(rec.events["t"].min())
