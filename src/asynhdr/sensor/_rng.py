"""Counter-based random numbers for the numba kernels.

Per-event draws (reset noise, jitter) happen inside parallel loops. Drawing from a
shared generator would make the result depend on thread scheduling; instead each draw
is a hash of ``(seed, pixel, counter, stream)`` (SplitMix64 finaliser), so the same
seed gives the same events bit for bit on any number of threads.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["Z_MAX", "hash_normal2", "hash_normal2_at", "hash_stream", "hash_uniform",
           "normal_pairs", "seed_from"]

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
def hash_stream(seed, a, b):
    """The mix of ``(seed, a, b)`` that :func:`hash_normal2_at` continues: computed once
    for a stream of draws."""
    z = _mix(np.uint64(seed) + _GOLD * np.uint64(a + 1))
    return _mix(z + _GOLD * np.uint64(b + 1))


def _ziggurat_tables(n: int = 128, r: float = 3.442619855899,
                     v: float = 9.91256303526217e-3) -> tuple[np.ndarray, np.ndarray]:
    """The ziggurat of the standard normal's density in ``n`` layers of area ``v``
    (Marsaglia and Tsang 2000, in the layout of Doornik 2005): ``x[i]`` is the right edge
    of layer ``i`` (``x[0] = v / f(r)``: the base, whose rectangle stands in for the tail
    beyond ``r``), ``ratio[i] = x[i + 1] / x[i]`` the share of the layer wholly under the
    density."""
    x = np.empty(n + 1)
    f = math.exp(-0.5 * r * r)
    x[0] = v / f
    x[1] = r
    x[n] = 0.0
    for i in range(2, n):
        x[i] = math.sqrt(-2.0 * math.log(v / x[i - 1] + f))
        f = math.exp(-0.5 * x[i] * x[i])
    return x, x[1:] / x[:-1]


_ZIG_R = 3.442619855899
_ZIG_X, _ZIG_RATIO = _ziggurat_tables(r=_ZIG_R)

Z_MAX = _ZIG_R + math.sqrt(2.0 * 54.0 * math.log(2.0))
"""Largest ``|z|`` a hash normal can take: the tail's draws beyond ``r`` stop where a
53-bit uniform's logarithm does (12.09)."""


@nb.njit(cache=True, inline="always", error_model="numpy")
def _unit(z):
    """Uniform in (0, 1) from the top 53 bits of ``z``."""
    return (np.float64(z >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


@nb.njit(cache=True, error_model="numpy")
def _ziggurat_slow(z):
    """:func:`_ziggurat` when the first draw fell outside its layer's inner rectangle:
    the wedge's test, the tail, and new draws (further mixes of ``z``) until one is
    taken."""
    while True:
        i = np.int64(z & np.uint64(127))
        u = 2.0 * _unit(z) - 1.0
        if abs(u) < _ZIG_RATIO[i]:
            return u * _ZIG_X[i]
        z = _mix(z + _GOLD)
        if i == 0:
            # the tail beyond r (Marsaglia 1964)
            while True:
                x = -math.log(_unit(z)) / _ZIG_R
                z = _mix(z + _GOLD)
                y = -math.log(_unit(z))
                z = _mix(z + _GOLD)
                if 2.0 * y > x * x:
                    return _ZIG_R + x if u > 0.0 else -_ZIG_R - x
        x = u * _ZIG_X[i]
        xi = _ZIG_X[i]
        xo = _ZIG_X[i + 1]
        f0 = math.exp(-0.5 * (xi * xi - x * x))
        f1 = math.exp(-0.5 * (xo * xo - x * x))
        if f1 + _unit(z) * (f0 - f1) < 1.0:
            return x
        z = _mix(z + _GOLD)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _ziggurat(z):
    """A standard normal from the 64-bit hash ``z`` (ziggurat): the low 7 bits pick a
    layer, the top 53 a point across it; inside the layer's inner rectangle (97.2 % of
    draws) that point is the draw, with no transcendental function."""
    i = np.int64(z & np.uint64(127))
    u = 2.0 * _unit(z) - 1.0
    if abs(u) < _ZIG_RATIO[i]:
        return u * _ZIG_X[i]
    return _ziggurat_slow(z)


@nb.njit(cache=True, inline="always", error_model="numpy")
def hash_normal2_at(z, c):
    """:func:`hash_normal2` at counter ``c`` of the stream ``z = hash_stream(seed, a, b)``."""
    return (_ziggurat(_mix(z + _GOLD * np.uint64(2 * c + 1))),
            _ziggurat(_mix(z + _GOLD * np.uint64(2 * c + 2))))


@nb.njit(cache=True, inline="always", error_model="numpy")
def hash_normal2(seed, a, b, c):
    """Two independent standard normals for one counter (each a ziggurat draw from its own
    hash: of ``(seed, a, b, 2c)`` and ``(.., 2c + 1)``)."""
    return hash_normal2_at(hash_stream(seed, a, b), c)


def seed_from(rng: np.random.Generator) -> int:
    """A 63-bit seed for the hash draws, taken from ``rng``."""
    return int(rng.integers(0, 2**63 - 1))


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _normal_pairs(seed, out_a, out_b):
    for i in nb.prange(out_a.shape[0]):
        out_a[i], out_b[i] = hash_normal2(seed, i, 0, 0)


def normal_pairs(seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Two arrays of ``n`` independent standard normals: element ``i`` of each is a draw of
    :func:`hash_normal2` at ``(seed, i, 0, 0)`` (the same on any number of threads)."""
    a = np.empty(n)
    b = np.empty(n)
    _normal_pairs(np.uint64(seed), a, b)
    return a, b
