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
