"""The counter-based normal draws every per-event noise of the simulator comes from.

Expected values are the standard normal's own (its distribution function, moments and
tail areas from scipy.stats): a wrong ziggurat table, a wrong wedge or tail test, or
bits shared between a layer and its point would move them by many standard errors.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import pytest
from scipy import stats

from asynhdr.sensor._rng import _ZIG_R, Z_MAX, hash_normal2, normal_pairs

N = 1_000_000


@nb.njit(cache=True)
def _draws(seed, n):
    out = np.empty((n, 2))
    for k in range(n):
        out[k, 0], out[k, 1] = hash_normal2(seed, k % 977, 3, k // 977)
    return out


@pytest.fixture(scope="module")
def draws() -> np.ndarray:
    return _draws(np.uint64(20261127), N)


def test_hash_normals_follow_the_standard_normal(draws: np.ndarray) -> None:
    z = draws.ravel()
    se = 1.0 / math.sqrt(z.size)
    assert abs(z.mean()) < 5 * se
    assert abs(z.var() - 1.0) < 5 * math.sqrt(2.0) * se
    assert abs(stats.skew(z)) < 5 * math.sqrt(6.0) * se
    assert abs(stats.kurtosis(z)) < 5 * math.sqrt(24.0) * se
    assert stats.kstest(z, "norm").pvalue > 1e-3


@pytest.mark.parametrize("c", [0.5, 1.0, 2.0, 3.0, _ZIG_R, 4.0])
def test_hash_normals_have_the_normal_tails(draws: np.ndarray, c: float) -> None:
    """Beyond ``_ZIG_R`` every draw comes from the tail's algorithm; between the layers'
    edges many come from the wedges' test."""
    z = draws.ravel()
    p = 2.0 * stats.norm.sf(c)
    k = int(np.count_nonzero(np.abs(z) > c))
    assert abs(k - p * z.size) < 5.0 * math.sqrt(p * (1.0 - p) * z.size) + 1.0


def test_the_two_draws_of_a_counter_are_independent(draws: np.ndarray) -> None:
    a, b = draws[:, 0], draws[:, 1]
    assert abs(np.corrcoef(a, b)[0, 1]) < 5.0 / math.sqrt(a.size)
    # and independent in magnitude, which a shared radius would break
    assert abs(np.corrcoef(a * a, b * b)[0, 1]) < 5.0 / math.sqrt(a.size)
    assert np.abs(draws).max() < Z_MAX


def test_normal_pairs_are_the_hash_draws_on_any_number_of_threads() -> None:
    a, b = normal_pairs(11, 5000)
    n_threads = nb.get_num_threads()
    nb.set_num_threads(1)
    try:
        a1, b1 = normal_pairs(11, 5000)
    finally:
        nb.set_num_threads(n_threads)
    assert np.array_equal(a, a1) and np.array_equal(b, b1)
    one = np.array([hash_normal2(np.uint64(11), i, 0, 0) for i in (0, 17, 4999)])
    assert np.array_equal(one[:, 0], a[[0, 17, 4999]])
    assert np.array_equal(one[:, 1], b[[0, 17, 4999]])
    assert not np.array_equal(a, b)
