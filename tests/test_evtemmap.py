"""The EvTemMap IMX636 recording (one opening of a transmittance ramp) reconstructed
with the time-to-first-event method: the image shows the scene."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from asynhdr.io import open_recording
from asynhdr.reconstruct import first_on_phase, reconstruct, windows_for
from asynhdr.tonemap import tonemap


@pytest.fixture(scope="module")
def evtemmap(data_dir: Path):
    path = data_dir / "events" / "evtemmap_imx636_evt3.raw"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    rec = open_recording(path)
    return rec, windows_for(rec, single=True)


def test_nearly_every_pixel_fires_and_times_spread_over_the_ramp(evtemmap) -> None:
    rec, win = evtemmap
    u = first_on_phase(rec, win)[0]
    assert u.shape == (720, 1280)
    assert np.isfinite(u).mean() > 0.99
    lo, hi = np.nanpercentile(u, [1, 99])
    assert hi - lo > 0.5  # first-ON times spread over more than half the opening


def test_ttfe_image_shows_the_scene(evtemmap) -> None:
    rec, win = evtemmap
    img = reconstruct(rec, method="ttfe", windows=win)[0]
    tm = tonemap(img)
    assert np.unique(tm).size >= 200  # a full grey scale, not a few levels
    # the lit wall (top left) is far brighter than the dark grille of the cabinet
    wall = img[50:250, 20:120].mean()
    grille = img[450:700, 200:380].mean()
    assert wall > 2.5 * grille
