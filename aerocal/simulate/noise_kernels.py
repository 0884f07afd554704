"""Compiled value noise: the scene's sub-cell texture detail (:meth:`aerocal.simulate.scene.Scene.thermal_at`),
one point at a time.

The same lattice hash and smoothstep interpolation as the numpy arrays computed before (that code is the
reference in ``tests/test_scene.py``, which compares the two to the last bit), without numpy's temporary arrays
per octave. Integer arithmetic is done in 64 bits and masked to 32, as numpy's ``uint32`` wraps.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_MASK = np.uint64(0xFFFFFFFF)
_SHIFT16 = np.uint64(16)
_SHIFT13 = np.uint64(13)


@njit(cache=True)
def _hash_uniform(ix: int, iy: int, salt_term: np.uint64) -> float:  # pragma: no cover - compiled
    """A lattice point (``ix``, ``iy``) -> a reproducible uniform value in [-1, 1]: a 32-bit integer hash, the
    finaliser of MurmurHash3 applied to a mix of the coordinates and the salt (``salt_term``: the salt's 32-bit
    product, computed once per octave)."""
    hx = (np.uint64(ix & 0xFFFFFFFF) * np.uint64(0x8DA6B343)) & _MASK
    hy = (np.uint64(iy & 0xFFFFFFFF) * np.uint64(0xD8163841)) & _MASK
    h = (hx ^ hy) ^ salt_term
    h ^= h >> _SHIFT16
    h = (h * np.uint64(0x85EBCA6B)) & _MASK
    h ^= h >> _SHIFT13
    h = (h * np.uint64(0xC2B2AE35)) & _MASK
    h ^= h >> _SHIFT16
    return float(h) * (2.0 / 4294967295.0) - 1.0


@njit(cache=True)
def _value_noise(x: float, y: float, salt_term: np.uint64) -> float:  # pragma: no cover - compiled
    """Value noise in [-1, 1] on the unit integer lattice at (``x``, ``y``), smoothstep-interpolated (C1)."""
    fx = math.floor(x)
    fy = math.floor(y)
    tx = x - fx
    ty = y - fy
    tx = tx * tx * (3.0 - 2.0 * tx)
    ty = ty * ty * (3.0 - 2.0 * ty)
    ix = np.int64(fx)
    iy = np.int64(fy)
    v00 = _hash_uniform(ix, iy, salt_term)
    v10 = _hash_uniform(ix + 1, iy, salt_term)
    v01 = _hash_uniform(ix, iy + 1, salt_term)
    v11 = _hash_uniform(ix + 1, iy + 1, salt_term)
    a = v00 + tx * (v10 - v00)
    b = v01 + tx * (v11 - v01)
    return a + ty * (b - a)


@njit(cache=True)
def detail(e: np.ndarray, n: np.ndarray, footprint: np.ndarray, spacings: np.ndarray,
           salts: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Sub-cell value noise summed over octaves at points (``e``, ``n``: flat, metres from the scene's origin),
    each octave of lattice ``spacings[k]`` metres and hash salt ``salts[k]`` weighted ``clip(2 - 2 footprint /
    spacing, 0, 1)``: 1 for a sample's ground ``footprint`` (metres, flat, one per point) up to half the spacing,
    faded out by a whole spacing."""
    out = np.zeros(e.shape[0])
    for k in range(spacings.shape[0]):
        spacing = spacings[k]
        salt_term = (np.uint64(salts[k] & 0xFFFFFFFF) * np.uint64(0xCB1AB31F)) & _MASK
        for i in range(e.shape[0]):
            weight = 2.0 - 2.0 * footprint[i] / spacing
            weight = 0.0 if weight < 0.0 else (1.0 if weight > 1.0 else weight)
            if weight > 0.0:
                out[i] = out[i] + weight * _value_noise(e[i] / spacing, n[i] / spacing, salt_term)
    return out
