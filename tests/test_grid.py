"""The voxel grid: extent, continuous coordinates, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from spatialseg.grid import VoxelGrid, grid_around


def test_grid_around_covers_points_with_margin():
    pts = np.array([[0.0, 0.0, 1.0], [1.0, 2.0, 1.5]])
    grid = grid_around(pts, np.array([0.1, 0.1, 0.05]), margin=0.1, max_voxels=10**7)
    c = grid.continuous_index(pts)
    assert np.all(c >= 1.0) and np.all(c <= np.array(grid.shape) - 2.0)
    assert np.allclose(grid.continuous_index(grid.origin[None]), 0.0)


def test_grid_around_rejects_too_many_voxels_and_nan():
    pts = np.array([[0.0, 0.0, 0.0], [10.0, 10.0, 10.0]])
    with pytest.raises(ValueError, match=r"increase model\.xy_scale"):
        grid_around(pts, 0.01, margin=0.0, max_voxels=1000)
    with pytest.raises(ValueError, match="NaN"):
        grid_around(np.array([[np.nan, 0.0, 0.0]]), 0.1, margin=0.0, max_voxels=1000)


def test_voxel_grid_validates():
    with pytest.raises(ValueError, match="size > 0"):
        VoxelGrid(np.zeros(3), np.array([1.0, 0.0, 1.0]), (2, 2, 2))


@pytest.mark.parametrize("shape", [(14, 11, 6), (15, 1, 1)])
def test_coarsened_grid_covers_the_fine_one_in_x_and_y(shape):
    """Voxel 0 stays put, x and y voxels grow by the stride (a one-voxel axis and depth keep
    theirs), and the last fine voxel's centre is inside the coarse grid."""
    proj = np.array([300.0, 300.0, 172.5, 129.5])
    grid = VoxelGrid(np.array([1.0, 2.0, 0.4]), np.array([2.0, 3.0, 0.05]), shape, proj)
    coarse = grid.coarsened(3)
    strides = np.array([3, 3 if shape[1] > 1 else 1, 1])
    assert np.allclose(coarse.voxel_size, grid.voxel_size * strides)
    assert np.allclose(coarse.origin, grid.origin)
    assert np.array_equal(coarse.projection, grid.projection)
    last = grid.origin + (np.array(shape) - 1) * grid.voxel_size
    assert np.all((last - coarse.origin) / coarse.voxel_size <= np.array(coarse.shape) - 1)
    assert grid.coarsened(1).shape == grid.shape
    with pytest.raises(ValueError, match="grid stride must be an integer >= 1"):
        grid.coarsened(0)


def test_occupied_counts_the_voxels_whose_centre_is_nearest_to_some_point():
    """Points go to the voxel whose centre is nearest (centres at integer coordinates), two
    points in one voxel count once, a point beyond the grid counts in its border voxel, and
    a projective grid counts in (u, v, 1/Z)."""
    grid = VoxelGrid(origin=np.zeros(3), voxel_size=np.full(3, 2.0), shape=(4, 3, 2))
    points = np.array([[0.9, 0.0, 0.0], [-0.9, 0.0, 0.0], [1.1, 0.0, 0.0], [50.0, 50.0, 0.0]])
    assert grid.occupied(points) == 3  # (0,0,0) twice, (1,0,0), (3,2,0)
    assert grid.occupied(np.zeros((0, 3))) == 0
    image = VoxelGrid(np.array([0.0, 0.0, 0.0]), np.ones(3), (10, 10, 3), (2.0, 2.0, 0.0, 0.0))
    points = np.array([[1.0, 1.0, 1.0], [1.1, 1.1, 1.0], [1.0, 1.0, 0.5]])  # u = 2, 2.2, 4
    assert image.occupied(points) == 2
