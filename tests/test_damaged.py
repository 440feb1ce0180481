"""Damage that never passes: each defect found by feeding damaged files and hostile paths
to the API and the command line has its test here. A damaged file ends in a
``ValueError`` naming it (or, for a file cut short, a warning saying what was kept),
never in silent garbage, a traceback, a hang or a giant allocation."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from asynhdr._atomic import TEMP_PREFIX
from asynhdr.cli import _register, app
from asynhdr.events import Recording, make_events, make_triggers
from asynhdr.io import iter_chunks, open_recording, open_source, recording_info, write_recording
from asynhdr.io import prophesee as pr
from asynhdr.io.hdf5 import hdf5_info, load_hdf5

_register()
runner = CliRunner()


class _Run:
    """A command's exit code and its output with line wraps undone."""

    def __init__(self, *args: object) -> None:
        r = runner.invoke(app, [str(a) for a in args])
        self.exit_code = r.exit_code
        self.output = " ".join(r.output.split())


run = _Run


@contextlib.contextmanager
def no_hang(seconds: int = 10) -> Iterator[None]:
    """Fail (instead of hanging the run) when the block takes longer than ``seconds``."""
    def boom(signum: int, frame: object) -> None:
        raise TimeoutError(f"blocked for more than {seconds} s")

    old = signal.signal(signal.SIGALRM, boom)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _rec(n: int = 50, width: int = 16, height: int = 12) -> Recording:
    rng = np.random.default_rng(1)
    t = np.sort(rng.integers(0, 100_000, n))
    return Recording(make_events(rng.integers(0, width, n), rng.integers(0, height, n),
                                 rng.choice([-1, 1], n), t), width, height,
                     make_triggers([0, 50_000]), {"k": 1})


# ------------------------------------------------------------------ geometry beyond any sensor


def test_huge_geometry_is_refused_by_every_format(tmp_path: Path) -> None:
    """width=99999 used to be accepted from .h5/.npz/text, then ask reconstruct for a
    74.5 GiB array."""
    h5 = tmp_path / "wide.h5"
    write_recording(h5, _rec())
    with h5py.File(h5, "r+") as f:
        f.attrs["width"] = 99999
    npz = tmp_path / "wide.npz"
    write_recording(npz, _rec())
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["width"] = np.int64(99999)
    with open(npz, "wb") as fh:
        np.savez(fh, **arrays)
    txt = tmp_path / "wide.txt"
    txt.write_text("# width: 99999\n# height: 10\n1 2 3 1\n")
    for path in (h5, npz, txt):
        for reader in (open_recording, recording_info, open_source):
            with pytest.raises(ValueError, match=rf"{path.name}.*(99999.*4096|4096.*99999)"):
                reader(path)
    (tmp_path / "plain.txt").write_text("1 2 3 1\n")
    with pytest.raises(ValueError, match=r"arguments is outside 1\.\.4096"):
        open_recording(tmp_path / "plain.txt", width=99999, height=10)
    r = run("reconstruct", h5, "-o", tmp_path / "img")
    assert r.exit_code == 2 and "outside 1..4096" in r.output and "Traceback" not in r.output


def test_hdf5_attribute_that_is_not_a_number_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "attr.h5"
    write_recording(path, _rec())
    with h5py.File(path, "r+") as f:
        f.attrs["width"] = "wide"
    for reader in (hdf5_info, load_hdf5, open_recording, recording_info):
        with pytest.raises(ValueError, match=r"attr\.h5: attribute width='wide' is not a whole"):
            reader(path)


# ------------------------------------------------------------------ a payload in another format


def test_evt2_payload_under_an_evt21_header_is_refused(tmp_path: Path) -> None:
    """EVT 2.0 words read as EVT 2.1 vectors give garbage (3.4 M events instead of
    539,481 for the shared Gen3 file); the time-high words in the mask halves show it."""
    e2 = tmp_path / "e2.raw"
    rec = _rec(5000, 640, 480)
    write_recording(e2, rec, evt="2.0")
    data = e2.read_bytes()
    payload = data[pr.raw_info(e2)["header_bytes"]:]
    bad = tmp_path / "wrong21.raw"
    bad.write_bytes(b"% evt 2.1\n% geometry 640x480\n% end\n" + payload[: len(payload) // 8 * 8])
    for reader in (pr.read_raw, open_recording, lambda p: list(pr.iter_raw(p))):
        with pytest.raises(ValueError, match=r"wrong21\.raw: the header says EVT 2.1 but the "
                                             r"payload holds 32-bit EVT 2.0 words"):
            reader(bad)
    assert open_recording(e2).events.size == 5000  # the same words as EVT 2.0 are fine


def test_real_evt2_payload_under_an_evt21_header(data_dir: Path, tmp_path: Path) -> None:
    src = data_dir / "events" / "gen3_evt2.raw"
    info = pr.raw_info(src)
    payload = src.read_bytes()[info["header_bytes"]:]
    bad = tmp_path / "gen3_as_21.raw"
    bad.write_bytes(b"% evt 2.1\n% geometry 640x480\n% end\n" + payload[: len(payload) // 8 * 8])
    with pytest.raises(ValueError, match=r"header says EVT 2\.1 but the payload holds 32-bit"):
        open_recording(bad)


@pytest.mark.parametrize(("evt", "header"), [("3.0", "% evt 3.0\n% geometry 64x48\n% end\n"),
                                             ("2.0", "% evt 2.0\n% geometry 64x48\n% end\n")])
def test_a_run_of_0xff_is_not_sensor_data(tmp_path: Path, evt: str, header: str) -> None:
    """200 KB of 0xFF decode as ignored continuation words: zero events, no word said."""
    only = tmp_path / "ff.raw"
    only.write_bytes(header.encode() + b"\xff" * 200_000)
    good = tmp_path / "good.raw"
    write_recording(good, _rec(2000, 64, 48), evt=evt)
    mixed = tmp_path / "mixed.raw"
    mixed.write_bytes(good.read_bytes() + b"\xff" * 200_000)
    for path in (only, mixed):
        for reader in (pr.read_raw, lambda p: list(pr.iter_raw(p, block_bytes=1 << 16)),
                       open_recording, recording_info):
            with pytest.raises(ValueError, match=rf"{path.name}: \d+ identical \d-byte words "
                                                 r"0xF+ from byte offset \d+: not EVT"):
                reader(path)
    assert open_recording(good).events.size == 2000


# ------------------------------------------------------------------ files cut short


def test_evt3_stream_cut_inside_a_vector_group_is_reported(tmp_path: Path,
                                                           caplog: pytest.LogCaptureFixture
                                                           ) -> None:
    # six events of one time, row and polarity: a VECT_BASE_X + VECT_12 + VECT_12 + VECT_8
    ev = make_events([0, 1, 2, 3, 4, 5], [2] * 6, [1] * 6, [100] * 6)
    path = tmp_path / "vec.raw"
    write_recording(path, Recording(ev, 64, 8))
    data = path.read_bytes()
    words = np.frombuffer(data[pr.raw_info(path)["header_bytes"]:], "<u2")
    assert (words[-4:] >> 12).tolist() == [0x3, 0x4, 0x4, 0x5]
    cut = tmp_path / "cut.raw"
    cut.write_bytes(data[:-4])  # the last VECT_12 and the VECT_8 are gone
    with caplog.at_level(logging.WARNING):
        rec = open_recording(cut)
    assert "cut.raw: the stream ends inside a vector group (12 of 32 columns" in caplog.text
    assert rec.events["x"].tolist() == [0, 1, 2, 3, 4, 5]  # all six lie in the first 12
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        open_recording(path)
    assert "vector group" not in caplog.text


def test_raw_cut_inside_its_header_is_refused(tmp_path: Path,
                                             caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "whole.raw"
    write_recording(path, Recording(_rec().events, 16, 12))
    data = path.read_bytes()
    n_head = pr.raw_info(path)["header_bytes"]
    second = data.index(b"\n") + 1  # the cut falls inside the header's second line
    cut = tmp_path / "cut.raw"
    cut.write_bytes(data[:second + 4])
    r = _Run("info", cut)
    assert r.exit_code == 2
    assert "cut.raw: the file ends inside its header" in r.output
    assert "Files asynhdr reads" not in r.output  # a .raw file: the formats list is noise
    with pytest.raises(ValueError, match="ends inside its header"):
        open_source(cut)
    # cut at the end of a header line, before '% end': no events, and said so
    lines = tmp_path / "lines.raw"
    lines.write_bytes(data[:second])
    with caplog.at_level(logging.WARNING):
        assert open_recording(lines, width=16, height=12).events.size == 0
    assert "lines.raw: the file ends after 1 header lines without '% end'" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert open_recording(path).events.size == _rec().events.size
    assert "header lines" not in caplog.text and data[n_head - 6:n_head] == b"% end\n"


def test_dat_cut_inside_a_record_is_reported(tmp_path: Path,
                                             caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "whole.dat"
    write_recording(path, Recording(_rec().events, 16, 12))
    cut = tmp_path / "cut.dat"
    cut.write_bytes(path.read_bytes()[:-3])
    with caplog.at_level(logging.WARNING):
        rec = open_recording(cut)
    assert "cut.dat: the file ends 5 bytes into an 8-byte record: it was cut; the 49 whole" \
        in caplog.text
    assert rec.events.size == 49


# ------------------------------------------------------------------ times beyond any clock


@pytest.mark.parametrize("ext", [".txt", ".h5", ".npz"])
def test_time_at_int64_max_is_refused(tmp_path: Path, ext: str) -> None:
    t_max = np.iinfo(np.int64).max
    path = tmp_path / f"late{ext}"
    if ext == ".txt":
        path.write_text(f"# width: 4\n# height: 4\n0 1 1 1\n{t_max} 1 2 1\n")
    else:
        ev = make_events([1, 1], [1, 2], [1, 1], [0, t_max])
        write_recording(path, Recording(ev, 4, 4))
    for reader in (open_recording, recording_info,
                   lambda p: list(iter_chunks(p, chunk_events=1))):
        with pytest.raises(ValueError, match=rf"{path.name}: events: time {t_max} µs at "
                                             r"index \d is beyond"):
            reader(path)


# ------------------------------------------------------------------ what is not a file


@pytest.mark.parametrize("name", ["x.raw", "x.h5", "x.txt", "x.npz", "x.aedat4", "x.dat"])
def test_a_fifo_is_refused_not_waited_on(tmp_path: Path, name: str) -> None:
    fifo = tmp_path / name
    os.mkfifo(fifo)
    readers = [open_recording, open_source, recording_info, iter_chunks]
    if name.endswith(".raw"):
        readers += [pr.read_raw, pr.raw_info, lambda p: list(pr.iter_raw(p))]
    with no_hang():
        for reader in readers:
            with pytest.raises(ValueError, match=rf"{name}: is a FIFO \(named pipe\); "
                                                 "recordings are read from regular files only"):
                reader(fifo)
        for args in (("info", fifo), ("reconstruct", fifo, "-o", tmp_path / "o"),
                     ("convert", fifo, tmp_path / "o.npz"),
                     ("calibrate", fifo, "-o", tmp_path / "c.npz")):
            r = run(*args)
            assert r.exit_code != 0 and "is a FIFO" in r.output, (args, r.output)


# ------------------------------------------------------------------ outputs


def test_outputs_are_checked_before_any_work(tmp_path: Path) -> None:
    rec = tmp_path / "rec.h5"
    write_recording(rec, _rec())
    a_file = tmp_path / "taken"
    a_file.write_text("x")
    r = run("reconstruct", rec, "-o", a_file)
    assert r.exit_code == 2 and "taken: exists and is not a folder" in r.output
    assert "Traceback" not in r.output
    r = run("calibrate", rec, "-o", a_file / "c.npz")
    assert r.exit_code == 2 and "cannot create the folder" in r.output
    # the output is refused before the (missing) input is even opened
    r = run("convert", tmp_path / "missing.raw", a_file)
    assert r.exit_code == 2 and "taken: exists; pass --overwrite" in r.output
    assert a_file.read_text() == "x"


def test_existing_outputs_need_overwrite_and_read_only_ones_stay(tmp_path: Path) -> None:
    rec = tmp_path / "rec.h5"
    write_recording(rec, Recording(_rec().events, 16, 12, make_triggers([0, 50_000])))
    out = tmp_path / "img"
    r = run("reconstruct", rec, "-o", out, "--formats", "npy")
    assert r.exit_code == 0, r.output
    first = sorted(p.name for p in out.iterdir())
    assert first == ["rec_exp_0000.npy", "rec_exp_0001.npy"]
    r = run("reconstruct", rec, "-o", out, "--formats", "npy")
    assert r.exit_code == 2 and "rec_exp_0000.npy: exists; pass --overwrite" in r.output
    r = run("reconstruct", rec, "-o", out, "--formats", "npy", "--overwrite")
    assert r.exit_code == 0, r.output
    os.chmod(out / "rec_exp_0000.npy", 0o444)
    try:
        r = run("reconstruct", rec, "-o", out, "--formats", "npy", "--overwrite")
        assert r.exit_code == 2 and "is read-only; not replaced" in r.output
    finally:
        os.chmod(out / "rec_exp_0000.npy", 0o644)
    cm = tmp_path / "c.npz"
    cm.write_text("keep")
    r = run("calibrate", rec, "-o", cm)
    assert r.exit_code == 2 and "exists; pass --overwrite" in r.output
    assert cm.read_text() == "keep"
    plot = tmp_path / "rate.png"
    plot.write_text("keep")
    r = run("info", rec, "--plot", plot)
    assert r.exit_code == 2 and "exists; pass --overwrite" in r.output


def test_a_failed_write_removes_the_folders_it_made(tmp_path: Path) -> None:
    from asynhdr._atomic import atomic_path

    kept = tmp_path / "kept"
    kept.mkdir()
    with pytest.raises(RuntimeError), atomic_path(kept / "a" / "b" / "f.txt") as tmp:
        tmp.write_text("half")
        raise RuntimeError("the writer failed")
    assert list(kept.iterdir()) == []  # a and a/b made for it and gone; kept stays
    with atomic_path(kept / "a" / "b" / "f.txt") as tmp:
        tmp.write_text("whole")
    assert (kept / "a" / "b" / "f.txt").read_text() == "whole"
    # from the command line: a conversion that fails leaves nothing behind
    ev = make_events([0, 1], [0, 1], [1, -1], [0, 2**40])
    src = tmp_path / "late.npz"
    write_recording(src, Recording(ev, 4, 4))
    r = _Run("convert", src, tmp_path / "new" / "sub" / "late.raw")
    assert r.exit_code == 2 and "--start-at-zero" in r.output
    assert not (tmp_path / "new").exists()


def test_temporary_files_of_a_killed_writer_are_swept(tmp_path: Path) -> None:
    """SIGKILL while writing leaves the temporary file; the next write into the folder
    removes it (its process no longer runs). A live process's file is left alone."""
    out = tmp_path / "out"
    code = (
        "import os, signal, numpy as np\n"
        "from asynhdr.io.hdf5 import Hdf5Writer\n"
        "from asynhdr.events import make_events\n"
        f"w = Hdf5Writer({str(out / 'rec.h5')!r}, width=4, height=4).__enter__()\n"
        "w.write(make_events(np.zeros(1000), np.zeros(1000), np.ones(1000), np.arange(1000)))\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    left = [p.name for p in out.iterdir()]
    assert len(left) == 1 and left[0].startswith(TEMP_PREFIX) and left[0].endswith("rec.h5")
    alive = out / f"{TEMP_PREFIX}{os.getpid()}-x-other.h5"  # this process: still running
    alive.write_bytes(b"")
    write_recording(out / "next.npz", _rec())
    assert sorted(p.name for p in out.iterdir()) == sorted(["next.npz", alive.name])
    assert not (out / "rec.h5").exists()


# ------------------------------------------------------------------ what a new user saw


def test_info_prints_no_triggers_for_a_file_without_any(tmp_path: Path) -> None:
    path = tmp_path / "plain.raw"
    write_recording(path, Recording(_rec().events, 16, 12))
    r = run("info", path)
    assert r.exit_code == 0, r.output
    assert "with triggers" not in r.output
    assert "trigger edges none" in r.output


def test_errors_name_flags_not_parameters(tmp_path: Path) -> None:
    path = tmp_path / "steady.h5"
    rng = np.random.default_rng(2)
    n = 20_000
    ev = make_events(rng.integers(0, 32, n), rng.integers(0, 24, n), rng.choice([-1, 1], n),
                     np.sort(rng.integers(0, 2_000_000, n)))
    write_recording(path, Recording(ev, 32, 24))
    r = run("reconstruct", path, "-o", tmp_path / "img")
    assert r.exit_code == 2
    assert "no cycles found" in r.output and "pass --period-us or --single" in r.output
    assert "period_us" not in r.output and not (tmp_path / "img").exists()
    r = run("reconstruct", path, "-o", tmp_path / "img", "--period-us", "50000")
    assert r.exit_code == 2 and "pass --single" in r.output and "--period-us or" not in r.output
    r = run("reconstruct", path, "-o", tmp_path / "img", "--threshold-on", "-1", "--single")
    assert r.exit_code == 2 and "--threshold-on must be positive" in r.output
    r = run("info", path, "--json")
    assert r.exit_code == 0 and "pass --period-us or --single" in r.output


def test_negative_pixels_are_reported_once(tmp_path: Path) -> None:
    scene = np.ones((6, 8), np.float32)
    scene[0, :3] = -1.0
    np.save(tmp_path / "neg.npy", scene)
    r = run("simulate", tmp_path / "neg.npy", "-o", tmp_path / "rec.npz", "--width", "8",
            "--height", "6", "--n-cycles", "1")
    assert r.exit_code == 0, r.output
    assert r.output.count("negative pixels") == 1, r.output


def test_version() -> None:
    from asynhdr import __version__

    r = run("--version")
    assert r.exit_code == 0 and r.output.strip() == f"asynhdr {__version__}"
