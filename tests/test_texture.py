"""The procedural texture kernel against a plain numpy statement of the same value noise:
the yardstick's cached recordings were simulated with the numpy version, so the kernel must
give the same reflectance to the last bit."""

from __future__ import annotations

import numpy as np
import pytest

from spatialseg.simulate.scene import Texture
from spatialseg.simulate.texture import _MIX_1 as MIX_1
from spatialseg.simulate.texture import _MIX_2 as MIX_2
from spatialseg.simulate.texture import _MUL_I as MUL_I
from spatialseg.simulate.texture import _MUL_J as MUL_J
from spatialseg.simulate.texture import sample_texture


def _hashed(i: np.ndarray, j: np.ndarray, key: np.uint64) -> np.ndarray:
    """splitmix64 / murmur3 finaliser of (i, j, key), as uniform [0, 1) doubles."""
    h = i.view(np.uint64) * MUL_I ^ j.view(np.uint64) * MUL_J ^ key
    for mix in (MIX_1, MIX_2):
        h = (h ^ h >> np.uint64(33)) * mix
    h ^= h >> np.uint64(33)
    return (h >> np.uint64(11)).astype(np.float64) * 2.0**-53


def _reference(texture: Texture, key: int, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Octaves of bilinear value noise, array by array."""
    total, weight_sum = np.zeros_like(s), 0.0
    for octave in range(texture.octaves):
        scale, weight = 2.0**octave / texture.cell, 0.5**octave
        a, b = s * scale, t * scale
        i, j = np.floor(a), np.floor(b)
        fs, ft = a - i, b - j
        i, j, k = i.astype(np.int64), j.astype(np.int64), np.uint64(key + octave)
        v00, v10 = _hashed(i, j, k), _hashed(i + 1, j, k)
        v01, v11 = _hashed(i, j + 1, k), _hashed(i + 1, j + 1, k)
        total += weight * (
            (v00 * (1 - fs) + v10 * fs) * (1 - ft) + (v01 * (1 - fs) + v11 * fs) * ft
        )
        weight_sum += weight
    return texture.low + (texture.high - texture.low) * (total / weight_sum)


@pytest.mark.parametrize("octaves", [1, 3, 5])
def test_noise_texture_equals_the_numpy_statement_bit_for_bit(octaves):
    rng = np.random.default_rng(octaves)
    s, t = rng.normal(0.0, 20.0, (2, 5_000))  # negative lattice indices too
    texture = Texture(kind="noise", cell=0.37, low=0.1, high=0.9, octaves=octaves)
    key = int(rng.integers(0, 2**62))
    got = sample_texture(texture, key, s, t)
    assert np.array_equal(got, _reference(texture, key, s, t))
    assert got.min() >= 0.1 and got.max() <= 0.9 and np.ptp(got) > 0.5


def test_noise_texture_keeps_the_shape_of_its_coordinates():
    s, t = np.meshgrid(np.linspace(-1, 1, 7), np.linspace(0, 2, 5))
    texture = Texture(kind="noise", cell=0.2, low=0.0, high=1.0, octaves=2)
    assert sample_texture(texture, 3, s, t).shape == (5, 7)
