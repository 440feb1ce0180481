"""Shared fixtures: the real-data folder and its manifest."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest

_HERE = Path(__file__).resolve().parent


def _data_dir() -> Path | None:
    env = os.environ.get("ASYNHDR_DATA")
    candidates = [Path(env)] if env else []
    candidates += [_HERE.parent.parent / "shared" / "data", Path.cwd().parent / "shared" / "data"]
    for c in candidates:
        if (c / "manifest.json").is_file():
            return c
    return None


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The real-data folder (ASYNHDR_DATA, else ../shared/data); skip when absent."""
    d = _data_dir()
    if d is None:
        pytest.skip(
            "real data not found: set ASYNHDR_DATA to the folder holding manifest.json "
            "(default ../shared/data beside the repository)"
        )
    return d


@pytest.fixture(scope="session")
def manifest(data_dir: Path) -> dict[str, Any]:
    """The parsed manifest.json of the real-data folder."""
    with open(data_dir / "manifest.json", encoding="utf-8") as f:
        return json.load(f)


def _compile_kernels(part: str) -> None:
    """Compile one part of the package's numba kernels on a tiny case (numba caches them
    on disk: the other workers then load what this one compiled)."""
    import numpy as np

    from asynhdr.design import default_rig
    from asynhdr.reconstruct import CycleWindows, reconstruct
    from asynhdr.simulate import simulate

    rig = default_rig("imx636")
    scene = np.full((4, 4), 100.0)
    if part == "simulate":
        for engine in ("exact", "stepped"):
            simulate(scene, rig=rig, sensor="imx636", n_cycles=1, rng=0, engine=engine)
    else:
        rec = simulate(np.full((2, 2), 100.0), rig=rig, sensor="ideal", n_cycles=1, rng=0)
        windows = CycleWindows(np.array([0]), rig.ramp_us)
        for method in ("ml", "exp", "invert"):
            reconstruct(rec, method=method, windows=windows)


def pytest_sessionstart(session: pytest.Session) -> None:
    """Under pytest-xdist, the first two workers compile different halves of the numba
    kernels before their first test, so that a cold run compiles each kernel about once
    instead of once per worker at the same time."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if worker in ("gw0", "gw1"):
        _compile_kernels("simulate" if worker == "gw0" else "reconstruct")
