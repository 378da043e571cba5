"""The voxel grid of the volume of warped events (the paper's "coordinate normalisation").

A grid maps a 3-D point to continuous voxel coordinates ``(p - origin) / voxel_size``: voxel
``(i, j, k)`` has its centre at integer coordinates, so a point at ``origin`` sits exactly on
the centre of voxel (0, 0, 0). Trilinear voting splits a point between the 8 surrounding
voxel centres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["VoxelGrid", "grid_around"]


@dataclass(frozen=True, eq=False)
class VoxelGrid:
    """An axis-aligned grid: ``shape`` voxels of ``voxel_size``, voxel 0 centred at ``origin``."""

    origin: np.ndarray
    voxel_size: np.ndarray
    shape: tuple[int, int, int]

    def __post_init__(self) -> None:
        origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        size = np.asarray(self.voxel_size, dtype=np.float64).reshape(3)
        shape = tuple(int(s) for s in self.shape)
        if len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"grid shape {self.shape} must be three positive integers")
        if not (np.all(np.isfinite(origin)) and np.all(np.isfinite(size)) and np.all(size > 0)):
            raise ValueError(f"grid origin {origin} / voxel size {size} must be finite, size > 0")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "voxel_size", size)
        object.__setattr__(self, "shape", shape)

    @property
    def n_voxels(self) -> int:
        """Total number of voxels, |Omega|."""
        return int(np.prod(self.shape))

    def continuous_index(self, points: np.ndarray) -> np.ndarray:
        """Continuous voxel coordinates of ``points`` (N x 3)."""
        return (np.asarray(points, dtype=np.float64) - self.origin) / self.voxel_size


def grid_around(
    points: np.ndarray, voxel_size: np.ndarray, margin: float, max_voxels: int
) -> VoxelGrid:
    """The grid covering the bounding box of ``points`` enlarged by ``margin`` (a fraction of
    its extent per axis, at least one voxel), with the given ``voxel_size``.

    Raises ``ValueError`` when there are no points or the grid would exceed ``max_voxels``
    (the fix is a coarser voxel size).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts):
        raise ValueError(f"need a non-empty N x 3 array of points for the grid, got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points for the grid contain NaN or inf; drop events without depth")
    size = np.broadcast_to(np.asarray(voxel_size, dtype=np.float64), (3,)).copy()
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = np.maximum(margin * (hi - lo), size)
    lo, hi = lo - pad, hi + pad
    shape = tuple(int(n) for n in np.ceil((hi - lo) / size).astype(np.int64) + 1)
    n = int(np.prod(shape, dtype=np.int64))
    if n > max_voxels:
        raise ValueError(
            f"the volume would have {shape} = {n} voxels (limit {max_voxels}); "
            "increase model.xy_scale or decrease volume.z_bins"
        )
    return VoxelGrid(origin=lo, voxel_size=size, shape=shape)
