"""Procedural textures: reflectance as a pure function of surface coordinates and a key.

Value noise hashes integer lattice points instead of storing a lattice, so infinite
background planes need no bounds and the same key always gives the same surface.
"""

from __future__ import annotations

import numpy as np

from spatialseg.simulate.scene import Texture

__all__ = ["sample_texture"]

# Constants of the splitmix64 / murmur3 finaliser (a standard integer hash, not tunables).
_MUL_I = np.uint64(0x9E3779B97F4A7C15)
_MUL_J = np.uint64(0xC2B2AE3D27D4EB4F)
_MIX_1 = np.uint64(0xFF51AFD7ED558CCD)
_MIX_2 = np.uint64(0xC4CEB9FE1A85EC53)
_SHIFT = np.uint64(33)
_MANTISSA = np.uint64(11)


def _lattice(i: np.ndarray, j: np.ndarray, key: np.uint64) -> np.ndarray:
    """Uniform [0, 1) values hashed from integer lattice points (i, j) and a key."""
    h = i.astype(np.int64).view(np.uint64) * _MUL_I
    h ^= j.astype(np.int64).view(np.uint64) * _MUL_J
    h ^= key
    h ^= h >> _SHIFT
    h *= _MIX_1
    h ^= h >> _SHIFT
    h *= _MIX_2
    h ^= h >> _SHIFT
    return (h >> _MANTISSA).astype(np.float64) * 2.0**-53


def _value_noise(s: np.ndarray, t: np.ndarray, key: np.uint64) -> np.ndarray:
    """Bilinearly interpolated lattice values at continuous lattice coordinates (s, t)."""
    i0, j0 = np.floor(s), np.floor(t)
    fs, ft = s - i0, t - j0
    i0, j0 = i0.astype(np.int64), j0.astype(np.int64)
    v00, v10 = _lattice(i0, j0, key), _lattice(i0 + 1, j0, key)
    v01, v11 = _lattice(i0, j0 + 1, key), _lattice(i0 + 1, j0 + 1, key)
    return (v00 * (1 - fs) + v10 * fs) * (1 - ft) + (v01 * (1 - fs) + v11 * fs) * ft


def _octave_noise(s: np.ndarray, t: np.ndarray, texture: Texture, key: int) -> np.ndarray:
    """Value noise summed over octaves (each twice as fine, half the weight), in [0, 1]."""
    total = np.zeros_like(s)
    weight_sum = 0.0
    for octave in range(texture.octaves):
        scale, weight = 2.0**octave / texture.cell, 0.5**octave
        total += weight * _value_noise(s * scale, t * scale, np.uint64(key + octave))
        weight_sum += weight
    return total / weight_sum


def sample_texture(texture: Texture, key: int, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Reflectance in [0, 1] of ``texture`` at surface coordinates (s, t) in metres."""
    if texture.kind == "uniform":
        return np.full(np.shape(s), texture.level)
    if texture.kind == "checker":
        parity = (np.floor(s / texture.cell) + np.floor(t / texture.cell)) % 2
        return np.where(parity == 0, texture.low, texture.high)
    return texture.low + (texture.high - texture.low) * _octave_noise(s, t, texture, key)
