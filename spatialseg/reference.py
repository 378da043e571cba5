"""Plain numpy reference of the volume of warped events, for tests and benchmarks.

The same quantities as :mod:`spatialseg.volume`, written for clarity, not speed: the 8
trilinear corners of every event as arrays, the volume by ``np.bincount``, the objective
straight from its definition, the gradient by a numpy gather. Conventions (corners outside
the grid dropped one by one; zero derivative on the peak of a one-voxel axis) match the
kernels'.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.ndimage import gaussian_filter

from spatialseg.grid import VoxelGrid

__all__ = [
    "OBJECTIVES",
    "corners",
    "objective_and_derivative",
    "sample",
    "value",
    "value_and_grad",
    "volume",
    "warped_coordinates",
]


def _variance(v: np.ndarray) -> tuple[float, np.ndarray]:
    """``mean((V - mu)^2)`` and ``2 (V - mu) / |Omega|``."""
    centred = v - v.mean()
    return float(np.mean(centred**2)), 2.0 * centred / v.size


def _sum_of_squares(v: np.ndarray) -> tuple[float, np.ndarray]:
    """``mean(V^2)`` and ``2 V / |Omega|``."""
    return float(np.mean(v**2)), 2.0 * v / v.size


#: The reference objectives by name: volume (float64) -> (value, dO/dV).
OBJECTIVES: dict[str, Callable[[np.ndarray], tuple[float, np.ndarray]]] = {
    "variance": _variance,
    "sum_of_squares": _sum_of_squares,
}


def warped_coordinates(
    points: np.ndarray, dt: np.ndarray, theta: np.ndarray, grid: VoxelGrid
) -> np.ndarray:
    """Continuous voxel coordinates (N x 3) of ``x_k - dt_k theta`` (-2, outside the grid,
    for a point behind the camera of a projective grid)."""
    return np.nan_to_num(grid.continuous_index(_warped(points, dt, theta)), nan=-2.0)


def _warped(points: np.ndarray, dt: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The warped points ``x_k - dt_k theta`` (N x 3)."""
    return np.asarray(points, np.float64) - np.outer(np.asarray(dt, np.float64), theta)


def corners(coords: np.ndarray, shape: tuple[int, int, int]):
    """The 8 trilinear corners of each coordinate: flat index, weight, d(weight)/dc.

    Returns ``(index (8, N) int, weight (8, N), dweight (8, N, 3))``; corners outside the
    grid have weight and derivative 0 and a clamped (valid) index.
    """
    n = np.array(shape)
    lower = np.floor(coords)
    frac = coords - lower
    lower = lower.astype(np.int64)
    # derivative scale: 0 on the peak of a one-voxel axis (symmetric derivative), else 1
    slope = np.where((n == 1) & (frac == 0.0), 0.0, 1.0)
    index, weight, dweight = [], [], []
    for offset in np.ndindex(2, 2, 2):
        corner = lower + np.array(offset)
        inside = np.all((corner >= 0) & (corner < n), axis=1)
        axis_w = np.where(np.array(offset) == 1, frac, 1.0 - frac)
        axis_d = np.where(np.array(offset) == 1, 1.0, -1.0) * slope
        w = np.prod(axis_w, axis=1) * inside
        d = np.stack(
            [axis_d[:, a] * np.prod(np.delete(axis_w, a, axis=1), axis=1) for a in range(3)],
            axis=1,
        )
        index.append(np.ravel_multi_index(np.clip(corner, 0, n - 1).T, shape))
        weight.append(w)
        dweight.append(d * inside[:, None])
    return np.array(index).reshape(8, -1), np.array(weight), np.array(dweight).reshape(8, -1, 3)


def volume(
    points: np.ndarray,
    dt: np.ndarray,
    theta: np.ndarray,
    grid: VoxelGrid,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """The VWE: ``V[v] = sum_k w_k W(v, c_k)`` by ``np.bincount`` (float64)."""
    n_events = len(dt)
    w = np.ones(n_events) if weights is None else np.asarray(weights, np.float64)
    index, weight, _ = corners(warped_coordinates(points, dt, theta, grid), grid.shape)
    votes = np.bincount(index.ravel(), (weight * w).ravel(), minlength=grid.n_voxels)
    return votes.reshape(grid.shape)


def _blur(v: np.ndarray, blur_sigma: float) -> np.ndarray:
    """Gaussian blur with zero padding (a symmetric operator); one-voxel axes untouched."""
    if blur_sigma <= 0:
        return v
    sigma = [blur_sigma if n > 1 else 0.0 for n in v.shape]
    return gaussian_filter(v, sigma=sigma, mode="constant", cval=0.0)


def objective_and_derivative(
    v: np.ndarray, objective: str, blur_sigma: float = 0.0
) -> tuple[float, np.ndarray]:
    """``O(K V)`` and ``dO/dV = K dO/dB`` (``K`` the blur, symmetric)."""
    value_, derivative = OBJECTIVES[objective](_blur(v, blur_sigma))
    return value_, _blur(derivative, blur_sigma)


def value(
    points: np.ndarray,
    dt: np.ndarray,
    theta: np.ndarray,
    grid: VoxelGrid,
    weights: np.ndarray | None = None,
    objective: str = "variance",
    blur_sigma: float = 0.0,
) -> float:
    """The objective of the VWE at ``theta``."""
    v = volume(points, dt, theta, grid, weights)
    return OBJECTIVES[objective](_blur(v, blur_sigma))[0]


def value_and_grad(
    points: np.ndarray,
    dt: np.ndarray,
    theta: np.ndarray,
    grid: VoxelGrid,
    weights: np.ndarray | None = None,
    objective: str = "variance",
    blur_sigma: float = 0.0,
) -> tuple[float, np.ndarray]:
    """The objective and ``dO/dtheta = sum_k w_k sum_corners G dW/dc dc/dtheta`` with
    ``dc/dtheta = -dt_k (dq/dp)(x'_k) / voxel_size`` (``q`` the grid's coordinates)."""
    n_events = len(dt)
    w = np.ones(n_events) if weights is None else np.asarray(weights, np.float64)
    v = volume(points, dt, theta, grid, w)
    value_, g = objective_and_derivative(v, objective, blur_sigma)
    index, _, dweight = corners(warped_coordinates(points, dt, theta, grid), grid.shape)
    dvalue_dc = np.einsum("cn,cna->na", g.ravel()[index], dweight)
    jacobian = grid.jacobian(_warped(points, dt, theta)) / grid.voxel_size[:, None]
    dc_dtheta = -np.asarray(dt, np.float64)[:, None, None] * np.nan_to_num(jacobian)
    return value_, np.einsum("n,na,nab->b", w, dvalue_dc, dc_dtheta)


def sample(
    points: np.ndarray, dt: np.ndarray, theta: np.ndarray, grid: VoxelGrid, v: np.ndarray
) -> np.ndarray:
    """``v`` interpolated trilinearly at each warped event (corners outside count 0)."""
    index, weight, _ = corners(warped_coordinates(points, dt, theta, grid), grid.shape)
    return np.sum(np.asarray(v, np.float64).ravel()[index] * weight, axis=0)
