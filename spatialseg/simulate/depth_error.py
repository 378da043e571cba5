"""Realistic depth error: corrupt the simulator's output depth maps, not its ground truth.

A real depth source (stereo, structured light, a depth network) is wrong smoothly over
regions, misses whole blobs, and may carry a global scale error. :func:`corrupt_depth_maps`
applies all three to the depth maps a Recording hands to EDPA, as configured by a scene's
``depth_error`` block (:class:`~spatialseg.simulate.scene.DepthError`):

- ``scale * depth * exp(e)``: ``e`` is white noise smoothed by a Gaussian filter and
  normalised to mean 0 and standard deviation ``sigma``. Its autocorrelation falls to 1/e at
  ``correlation`` pixels (filter std ``correlation / 2``). ``exp`` keeps depths positive;
  the relative error's std is about ``sigma`` for small ``sigma``. With ``bias`` > 0 a
  second such field of std ``bias``, one for every map, is added to ``e``: a fixed bias
  beside each map's own flicker.
- holes: the largest ``holes`` share of a second smooth field (correlation ``hole_size``
  px) becomes NaN, the project's "unknown depth", so holes are blobs of about that size.

The draws come from their own seed stream, so they never change the events.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from spatialseg.recording import DepthMap
from spatialseg.simulate.scene import DepthError

__all__ = ["DEPTH_ERROR_STREAM", "corrupt_depth_maps", "hole_mask", "smooth_field"]

#: Child of the depth-error stream that draws the shared ``bias`` field.
BIAS_STREAM = 1

#: Index of the depth-error stream among the children of ``SeedSequence(seed)`` (0 and 1
#: are the textures and the pixels), so adding it leaves every earlier draw unchanged.
DEPTH_ERROR_STREAM = 2


def smooth_field(rng: np.random.Generator, shape: tuple[int, int], length: float) -> np.ndarray:
    """A Gaussian random field with mean 0 and std 1 whose autocorrelation is 1/e at ``length`` px.

    White noise filtered by a Gaussian of std s has autocorrelation exp(-d^2 / (4 s^2)),
    which is 1/e at d = 2 s; hence s = length / 2. ``wrap`` borders keep the edges as
    rough as the middle.
    """
    field = gaussian_filter(rng.standard_normal(shape), sigma=length / 2, mode="wrap")
    field -= field.mean()
    std = field.std()
    if std == 0:
        raise ValueError(f"a smooth field of length {length} px on a {shape} map is constant")
    return field / std


def hole_mask(rng: np.random.Generator, shape: tuple[int, int], share: float, size: float):
    """A boolean mask of exactly ``round(share * pixels)`` pixels in blobs about ``size`` px wide.

    The blobs are the highest values of a smooth field, so their count per area and their
    size follow from ``size`` and ``share`` alone.
    """
    count = round(share * shape[0] * shape[1])
    mask = np.zeros(shape, dtype=bool)
    if count == 0:
        return mask
    field = smooth_field(rng, shape, size).ravel()
    mask.ravel()[np.argpartition(field, field.size - count)[field.size - count :]] = True
    return mask


def _corrupt(depth: np.ndarray, error: DepthError, field: np.ndarray, holes: np.ndarray):
    """One map: scale, multiplicative field (``sigma`` times a unit field, plus the bias),
    NaN in the holes (float64)."""
    out = error.scale * depth.astype(np.float64) * np.exp(field)
    out[holes] = np.nan
    return out


def _draws(rng: np.random.Generator, shape: tuple[int, int], error: DepthError):
    """One error field of std ``sigma`` (zeros without it) and one hole mask, drawn in that
    order."""
    field = (
        error.sigma * smooth_field(rng, shape, error.correlation)
        if error.sigma > 0
        else np.zeros(shape)
    )
    return field, hole_mask(rng, shape, error.holes, error.hole_size)


def _bias_field(seed: int, shape: tuple[int, int], error: DepthError) -> np.ndarray:
    """The field of std ``bias`` every map shares (zeros without it), from a stream of its
    own so that adding a bias leaves the other draws unchanged."""
    if error.bias == 0:
        return np.zeros(shape)
    sequence = np.random.SeedSequence(
        seed, spawn_key=(DEPTH_ERROR_STREAM, error.seed_offset, BIAS_STREAM)
    )
    return error.bias * smooth_field(np.random.default_rng(sequence), shape, error.correlation)


def corrupt_depth_maps(
    maps: tuple[DepthMap, ...], error: DepthError, *, seed: int
) -> tuple[DepthMap, ...]:
    """The depth maps with ``error`` applied, deterministically from the run's ``seed``.

    Neutral settings (``sigma`` 0, ``holes`` 0, ``scale`` 1) return the maps themselves,
    bit for bit. ``error.shared`` applies one draw to every map; otherwise each map gets
    its own (per-frame estimation errors); ``error.bias`` adds one more field to every map.
    """
    if not error.active or not maps:
        return maps
    sequence = np.random.SeedSequence(seed, spawn_key=(DEPTH_ERROR_STREAM, error.seed_offset))
    rng = np.random.default_rng(sequence)
    shape = maps[0].depth.shape
    draws = [_draws(rng, shape, error)] if error.shared else None
    bias = _bias_field(seed, shape, error)
    out = []
    for depth_map in maps:
        field, holes = draws[0] if draws else _draws(rng, shape, error)
        corrupted = _corrupt(depth_map.depth, error, field + bias, holes)
        out.append(DepthMap(depth_map.t, corrupted, source=f"{depth_map.source} (depth error)"))
    return tuple(out)
