"""Procedural textures: reflectance as a pure function of surface coordinates and a key.

Value noise hashes integer lattice points instead of storing a lattice, so infinite
background planes need no bounds and the same key always gives the same surface. The noise
is one numba pass over the points (every octave of a point at once, no temporaries): the
renderer samples each visible surface point of every frame, the simulator's main cost.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from spatialseg.simulate.scene import Texture

__all__ = ["sample_texture"]

# Constants of the splitmix64 / murmur3 finaliser (a standard integer hash, not tunables).
_MUL_I = np.uint64(0x9E3779B97F4A7C15)
_MUL_J = np.uint64(0xC2B2AE3D27D4EB4F)
_MIX_1 = np.uint64(0xFF51AFD7ED558CCD)
_MIX_2 = np.uint64(0xC4CEB9FE1A85EC53)
_SHIFT = np.uint64(33)
_MANTISSA = np.uint64(11)


@njit(cache=True, inline="always")
def _lattice(i: np.int64, j: np.int64, key: np.uint64) -> float:
    """A uniform [0, 1) value hashed from the integer lattice point (i, j) and a key."""
    h = np.uint64(i) * _MUL_I
    h ^= np.uint64(j) * _MUL_J
    h ^= key
    h ^= h >> _SHIFT
    h *= _MIX_1
    h ^= h >> _SHIFT
    h *= _MIX_2
    h ^= h >> _SHIFT
    return np.float64(h >> _MANTISSA) * 2.0**-53


@njit(cache=True, inline="always")
def _value_noise(s: float, t: float, key: np.uint64) -> float:
    """The lattice values bilinearly interpolated at continuous lattice coordinates (s, t)."""
    s0, t0 = np.floor(s), np.floor(t)
    fs, ft = s - s0, t - t0
    i0, j0 = np.int64(s0), np.int64(t0)
    v00, v10 = _lattice(i0, j0, key), _lattice(i0 + 1, j0, key)
    v01, v11 = _lattice(i0, j0 + 1, key), _lattice(i0 + 1, j0 + 1, key)
    return (v00 * (1 - fs) + v10 * fs) * (1 - ft) + (v01 * (1 - fs) + v11 * fs) * ft


@njit(cache=True)
def _octave_noise_kernel(
    s: np.ndarray, t: np.ndarray, scales: np.ndarray, weights: np.ndarray, keys: np.ndarray
) -> np.ndarray:
    """Value noise at each point (s, t), summed over octaves and normalised to [0, 1]."""
    weight_sum = 0.0
    for weight in weights:
        weight_sum += weight
    out = np.empty(s.size)
    for n in range(s.size):
        total = 0.0
        for octave in range(scales.size):
            scale = scales[octave]
            total += weights[octave] * _value_noise(s[n] * scale, t[n] * scale, keys[octave])
        out[n] = total / weight_sum
    return out


def _octave_noise(s: np.ndarray, t: np.ndarray, texture: Texture, key: int) -> np.ndarray:
    """Value noise summed over octaves (each twice as fine, half the weight), in [0, 1]."""
    octaves = range(texture.octaves)
    scales = np.array([2.0**octave / texture.cell for octave in octaves])
    weights = np.array([0.5**octave for octave in octaves])
    keys = np.array([np.uint64(key + octave) for octave in octaves], dtype=np.uint64)
    flat_s = np.ascontiguousarray(s, dtype=np.float64).ravel()
    flat_t = np.ascontiguousarray(t, dtype=np.float64).ravel()
    return _octave_noise_kernel(flat_s, flat_t, scales, weights, keys).reshape(np.shape(s))


def sample_texture(texture: Texture, key: int, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Reflectance in [0, 1] of ``texture`` at surface coordinates (s, t) in metres."""
    if texture.kind == "uniform":
        return np.full(np.shape(s), texture.level)
    if texture.kind == "checker":
        parity = (np.floor(s / texture.cell) + np.floor(t / texture.cell)) % 2
        return np.where(parity == 0, texture.low, texture.high)
    return texture.low + (texture.high - texture.low) * _octave_noise(s, t, texture, key)
