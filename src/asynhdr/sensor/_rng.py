"""Counter-based random numbers for the numba kernels.

Per-event draws (reset noise, jitter) happen inside parallel loops. Drawing from a
shared generator would make the result depend on thread scheduling; instead each draw
is a hash of ``(seed, pixel, counter, stream)`` (SplitMix64 finaliser), so the same
seed gives the same events bit for bit on any number of threads.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["hash_normal", "hash_normal2", "hash_normal2_at", "hash_stream", "hash_uniform",
           "seed_from"]

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _mix(z):
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


@nb.njit(cache=True, inline="always", error_model="numpy")
def hash_uniform(seed, a, b, c):
    """Uniform in (0, 1) from the 64-bit ``seed`` and three integer counters."""
    z = np.uint64(seed)
    z = _mix(z + _GOLD * np.uint64(a + 1))
    z = _mix(z + _GOLD * np.uint64(b + 1))
    z = _mix(z + _GOLD * np.uint64(c + 1))
    return (np.float64(z >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


@nb.njit(cache=True, inline="always", error_model="numpy")
def hash_normal(seed, a, b, c):
    """Standard normal (Box-Muller) from the seed and three counters."""
    u1 = hash_uniform(seed, a, b, 2 * c)
    u2 = hash_uniform(seed, a, b, 2 * c + 1)
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)


@nb.njit(cache=True, inline="always", error_model="numpy")
def hash_stream(seed, a, b):
    """The mix of ``(seed, a, b)`` that :func:`hash_normal2_at` continues: computed once
    for a stream of draws."""
    z = _mix(np.uint64(seed) + _GOLD * np.uint64(a + 1))
    return _mix(z + _GOLD * np.uint64(b + 1))


@nb.njit(cache=True, inline="always", error_model="numpy")
def hash_normal2_at(z, c):
    """:func:`hash_normal2` at counter ``c`` of the stream ``z = hash_stream(seed, a, b)``."""
    z1 = _mix(z + _GOLD * np.uint64(2 * c + 1))
    z2 = _mix(z + _GOLD * np.uint64(2 * c + 2))
    u1 = (np.float64(z1 >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)
    u2 = (np.float64(z2 >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)
    r = np.sqrt(-2.0 * np.log(u1))
    ang = 2.0 * np.pi * u2
    return r * np.cos(ang), r * np.sin(ang)


@nb.njit(cache=True, inline="always", error_model="numpy")
def hash_normal2(seed, a, b, c):
    """Two independent standard normals (both Box-Muller outputs) for one counter."""
    # the same values as hash_uniform(seed, a, b, 2c) and (.., 2c + 1)
    return hash_normal2_at(hash_stream(seed, a, b), c)


def seed_from(rng: np.random.Generator) -> int:
    """A 63-bit seed for the hash draws, taken from ``rng``."""
    return int(rng.integers(0, 2**63 - 1))
