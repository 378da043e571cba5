"""The voxel grid of the volume of warped events (the paper's "coordinate normalisation").

A grid maps a 3-D point to continuous voxel coordinates ``(q(p) - origin) / voxel_size``:
voxel ``(i, j, k)`` has its centre at integer coordinates, so a point with ``q(p) = origin``
sits exactly on the centre of voxel (0, 0, 0). Trilinear voting splits a point between the
8 surrounding voxel centres.

``q`` is the identity (a metric grid, the paper's) or, when the grid has a ``projection``
``(fx, fy, cx, cy)``, the pinhole projection plus inverse depth
``q(X, Y, Z) = (fx X / Z + cx, fy Y / Z + cy, 1 / Z)``: a grid over image pixels and inverse
depth, on which near and far events are equally sharp (``docs/volume.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["VoxelGrid", "grid_around", "project", "project_jacobian"]


def project(points: np.ndarray, projection: np.ndarray | None) -> np.ndarray:
    """``q(points)`` (N x 3): the points themselves, or ``(fx X/Z + cx, fy Y/Z + cy, 1/Z)``
    for ``projection = (fx, fy, cx, cy)``; NaN for Z <= 0 (behind the camera: in no voxel)."""
    pts = np.asarray(points, dtype=np.float64)
    if projection is None:
        return pts
    fx, fy, cx, cy = projection
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = np.where(pts[..., 2] > 0, 1.0 / pts[..., 2], np.nan)
    return np.stack(
        [fx * pts[..., 0] * inverse + cx, fy * pts[..., 1] * inverse + cy, inverse], axis=-1
    )


def project_jacobian(points: np.ndarray, projection: np.ndarray | None) -> np.ndarray:
    """``dq/dp`` (N x 3 x 3) of :func:`project` at ``points``: the identity, or the pinhole's
    ``[[fx/Z, 0, -fx X/Z^2], [0, fy/Z, -fy Y/Z^2], [0, 0, -1/Z^2]]``."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    jac = np.zeros((len(pts), 3, 3))
    if projection is None:
        jac[:] = np.eye(3)
        return jac
    fx, fy = projection[:2]
    inverse = 1.0 / pts[:, 2]
    jac[:, 0, 0] = fx * inverse
    jac[:, 0, 2] = -fx * pts[:, 0] * inverse**2
    jac[:, 1, 1] = fy * inverse
    jac[:, 1, 2] = -fy * pts[:, 1] * inverse**2
    jac[:, 2, 2] = -(inverse**2)
    return jac


@dataclass(frozen=True, eq=False)
class VoxelGrid:
    """An axis-aligned grid: ``shape`` voxels of ``voxel_size``, voxel 0 centred at ``origin``.

    ``projection`` (fx, fy, cx, cy) makes it a grid over ``(u, v, 1/Z)``; None, over the
    points themselves.
    """

    origin: np.ndarray
    voxel_size: np.ndarray
    shape: tuple[int, int, int]
    projection: np.ndarray | None = None

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
        if self.projection is not None:
            proj = np.asarray(self.projection, dtype=np.float64).reshape(4)
            if not (np.all(np.isfinite(proj)) and proj[0] > 0 and proj[1] > 0):
                raise ValueError(f"grid projection {proj} must be finite (fx, fy, cx, cy), f > 0")
            object.__setattr__(self, "projection", proj)

    @property
    def n_voxels(self) -> int:
        """Total number of voxels, |Omega|."""
        return int(np.prod(self.shape))

    def coordinates(self, points: np.ndarray) -> np.ndarray:
        """The grid's coordinates ``q`` of ``points`` (N x 3), see :func:`project`."""
        return project(points, self.projection)

    def jacobian(self, points: np.ndarray) -> np.ndarray:
        """``dq/dp`` (N x 3 x 3) at ``points``, see :func:`project_jacobian`."""
        return project_jacobian(points, self.projection)

    def coarsened(self, stride: int) -> VoxelGrid:
        """This grid with voxels ``stride`` times larger in x and y (axes of one voxel and
        depth keep theirs), voxel 0 on this grid's voxel 0, covering the same extent."""
        if not (isinstance(stride, int | np.integer) and stride >= 1):
            raise ValueError(f"a grid stride must be an integer >= 1, got {stride!r}")
        fine = np.array(self.shape)
        strides = np.where((fine > 1) & (np.arange(3) < 2), stride, 1)
        shape = np.where(strides > 1, (fine - 1) // strides + 2, fine)
        return VoxelGrid(self.origin, self.voxel_size * strides, tuple(shape), self.projection)

    def continuous_index(self, points: np.ndarray) -> np.ndarray:
        """Continuous voxel coordinates of ``points`` (N x 3)."""
        return (self.coordinates(points) - self.origin) / self.voxel_size

    def occupied(self, points: np.ndarray) -> int:
        """How many voxels hold at least one of ``points`` (N x 3, each in the voxel whose
        centre is nearest; points outside the grid in its border voxels)."""
        if not len(points):
            return 0
        index = np.rint(self.continuous_index(points))
        inside = np.clip(np.nan_to_num(index), 0, np.array(self.shape) - 1).astype(np.int64)
        marks = np.zeros(self.n_voxels, dtype=bool)
        marks[np.ravel_multi_index(tuple(inside.T), self.shape)] = True
        return int(np.count_nonzero(marks))


def grid_around(
    points: np.ndarray,
    voxel_size: np.ndarray,
    margin: float,
    max_voxels: int,
    projection: np.ndarray | None = None,
) -> VoxelGrid:
    """The grid covering the bounding box of ``points`` (in the grid's coordinates: projected
    when ``projection`` is given) enlarged by ``margin`` (a fraction of its extent per axis,
    at least one voxel), with the given ``voxel_size``.

    Raises ``ValueError`` when there are no points or the grid would exceed ``max_voxels``
    (the fix is a coarser voxel size).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts):
        raise ValueError(f"need a non-empty N x 3 array of points for the grid, got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points for the grid contain NaN or inf; drop events without depth")
    size = np.broadcast_to(np.asarray(voxel_size, dtype=np.float64), (3,)).copy()
    coords = project(pts, projection)
    if not np.all(np.isfinite(coords)):
        raise ValueError("points for a projective grid must have positive depth Z")
    lo, hi = coords.min(axis=0), coords.max(axis=0)
    pad = np.maximum(margin * (hi - lo), size)
    lo, hi = lo - pad, hi + pad
    shape = tuple(int(n) for n in np.ceil((hi - lo) / size).astype(np.int64) + 1)
    n = int(np.prod(shape, dtype=np.int64))
    if n > max_voxels:
        raise ValueError(
            f"the volume would have {shape} = {n} voxels (limit {max_voxels}); "
            "increase model.xy_scale or decrease volume.z_bins"
        )
    return VoxelGrid(origin=lo, voxel_size=size, shape=shape, projection=projection)
