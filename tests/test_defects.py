"""Dead pixels: the map from flat-field counts and the fill from neighbours, by hand."""

from __future__ import annotations

import numpy as np
import pytest

from asynhdr.defects import dead_pixels, fill_defects


def test_dead_pixels_are_the_silent_ones_when_the_others_fire() -> None:
    counts = np.full((3, 4), 9)
    counts[1, 2] = 0
    counts[0, 0] = 1  # one event: alive
    np.testing.assert_array_equal(np.argwhere(dead_pixels(counts)), [[1, 2]])
    # a capture where the typical pixel fired less than MIN_TYPICAL_EVENTS proves nothing
    assert not dead_pixels(np.where(counts > 0, 3, 0)).any()
    with pytest.raises(ValueError, match="height, width"):
        dead_pixels(np.zeros(5))


def test_fill_takes_the_median_of_measured_neighbours_only() -> None:
    img = np.arange(25, dtype=np.float64).reshape(5, 5)
    img[2, 2] = np.nan  # dead: 7 8 11 13 16 17 18 (6 is dead too) -> median 13
    img[0, 0] = np.nan  # dead in the corner: 1, 5, 6 -> 5; but 6 is dead too: 1, 5 -> 3
    img[1, 1] = np.nan
    img[4, 4] = 7.0  # in the map but measured: kept
    dead = np.zeros((5, 5), dtype=bool)
    dead[[2, 0, 1, 4], [2, 0, 1, 4]] = True
    out, done = fill_defects(img, dead)
    # (1, 1): 1, 2, 5, 7, 10, 11 ((0, 0) and (2, 2) are dead) -> median 6
    assert out[2, 2] == 13.0 and out[0, 0] == 3.0 and out[1, 1] == 6.0
    assert out[4, 4] == 7.0
    np.testing.assert_array_equal(np.argwhere(done), [[0, 0], [1, 1], [2, 2]])
    assert np.isnan(img[2, 2])  # the input is not touched
    # a dead pixel with no measured neighbour stays without a value
    lone = np.full((3, 3), np.nan)
    out, done = fill_defects(lone, np.ones((3, 3), dtype=bool))
    assert np.isnan(out).all() and not done.any()
    with pytest.raises(ValueError, match="same"):
        fill_defects(img, dead[:4])
