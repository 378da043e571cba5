"""EDPA: per-event depth, unknown-depth policies, back-projection, voxel size."""

from __future__ import annotations

import numpy as np
import pytest

from spatialseg.edpa import (
    back_project,
    event_depth,
    fill_depth,
    lift,
    occlusion_edges,
    voxel_size,
)
from spatialseg.events import EventStream
from spatialseg.grid import grid_around
from spatialseg.recording import Camera, DepthMap, Recording

NAN = np.nan
CAM = Camera(fx=100.0, fy=50.0, cx=1.5, cy=1.0, width=4, height=3)
# 3 x 4 sensor; unknown depth: NaN, 0 or negative.
Z1 = np.array([[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 3.0, NAN], [2.0, NAN, 7.0, 8.0]])
Z2 = np.array([[3.0, 4.0, 1.0, 6.0], [5.0, 2.0, 2.0, 5.0], [0.0, -1.0, 9.0, 8.0]])
T1, T2 = 10.0, 12.0
# (x, y, t, hand-computed depth)
CASES = [
    (0, 0, 9.0, 1.0),  # before T1: clamped to Z1
    (0, 0, 10.0, 1.0),  # at T1: Z1 (the printed Eq. 1 gives 0)
    (1, 0, 11.0, 3.0),  # halfway between 2 and 4
    (2, 1, 11.5, 2.25),  # 3 + 0.75 * (2 - 3): depth decreasing
    (3, 1, 11.5, 5.0),  # Z1 unknown (NaN): Z2
    (0, 2, 11.5, 2.0),  # Z2 unknown (0): Z1
    (1, 2, 11.5, NAN),  # unknown in both (NaN, -1)
    (2, 0, 12.0, 1.0),  # at T2: Z2
    (3, 2, 13.0, 8.0),  # after T2: clamped to Z2
]


def _events(cases: list[tuple[int, int, float, float]]) -> EventStream:
    x, y, t, _ = zip(*cases, strict=True)
    return EventStream(np.array(x), np.array(y), np.array(t), np.ones(len(x)), 4, 3)


def _expected(cases: list[tuple[int, int, float, float]]) -> np.ndarray:
    return np.array([c[3] for c in cases])


def _window(cases, z1=Z1, z2=Z2) -> Recording:
    maps = (DepthMap(T1, z1), DepthMap(T2, z2))
    return Recording(_events(cases), CAM, maps)


def test_event_depth_matches_hand_computed_interpolation():
    z = event_depth(_events(CASES), DepthMap(T1, Z1), DepthMap(T2, Z2))
    np.testing.assert_allclose(z, _expected(CASES), equal_nan=True)


def test_printed_equation_1_would_fail_this_test():
    """The misprinted Eq. 1, (t - T1)/(T2 - T1) |Z2 - Z1|, disagrees with the hand values."""
    ev = _events(CASES[1:4])
    s = (ev.t - T1) / (T2 - T1)
    misread = s * np.abs(Z2[ev.y, ev.x] - Z1[ev.y, ev.x])
    assert not np.allclose(misread, _expected(CASES[1:4]))
    z = event_depth(ev, DepthMap(T1, Z1), DepthMap(T2, Z2))
    assert not np.allclose(z, misread)


def test_event_depth_equal_map_times_uses_first_map_then_second():
    ev = _events([(0, 0, 10.0, 0), (3, 1, 10.0, 0), (1, 2, 10.0, 0)])
    z = event_depth(ev, DepthMap(T1, Z1), DepthMap(T1, Z2))
    np.testing.assert_allclose(z, [1.0, 5.0, NAN], equal_nan=True)


def test_event_depth_rejects_swapped_maps_and_wrong_shape():
    ev = _events(CASES[:1])
    with pytest.raises(ValueError, match="pass the earlier map first"):
        event_depth(ev, DepthMap(T2, Z2), DepthMap(T1, Z1))
    with pytest.raises(ValueError, match="does not match the events' sensor"):
        event_depth(ev, DepthMap(T1, np.ones((4, 4))), DepthMap(T2, Z2))


def test_back_project_hand_values_and_round_trip_through_projection():
    xyz = back_project(np.array([3.5]), np.array([0.0]), np.array([2.0]), CAM)
    np.testing.assert_allclose(xyz, [[(3.5 - 1.5) * 2.0 / 100.0, (0.0 - 1.0) * 2.0 / 50.0, 2.0]])
    rng = np.random.default_rng(0)
    pts = np.column_stack((rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50), rng.uniform(0.5, 5, 50)))
    u = CAM.fx * pts[:, 0] / pts[:, 2] + CAM.cx
    v = CAM.fy * pts[:, 1] / pts[:, 2] + CAM.cy
    np.testing.assert_allclose(back_project(u, v, pts[:, 2], CAM), pts)


def test_back_project_rejects_nan_and_mismatched_lengths():
    with pytest.raises(ValueError, match="NaN or inf"):
        back_project(np.zeros(1), np.zeros(1), np.array([NAN]), CAM)
    with pytest.raises(ValueError, match="equal length"):
        back_project(np.zeros(2), np.zeros(1), np.ones(1), CAM)


def test_fill_depth_takes_median_of_known_neighbours():
    d = np.array([[1.0, NAN, 3.0, 4.0], [NAN, NAN, 0.0, 8.0], [2.0, 6.0, -1.0, NAN]])
    # radius 1 around (x, y) = (1, 1): known 1, 3, 2, 6 -> 2.5; corner (0, 0): 1; (3, 2): 8
    out = fill_depth(d, np.array([1, 0, 3]), np.array([1, 0, 2]), radius=1)
    np.testing.assert_allclose(out, [2.5, 1.0, 8.0])
    hole = np.full((3, 4), NAN)
    assert np.isnan(fill_depth(hole, np.array([1]), np.array([1]), radius=2)).all()
    np.testing.assert_allclose(fill_depth(d, np.array([1]), np.array([1]), radius=0), [NAN])


def test_lift_drop_policy_excludes_events_without_depth():
    lifted = lift(_window(CASES), unknown_depth="drop", fill_radius=1)
    expected = _expected(CASES)
    assert lifted.valid.tolist() == np.isfinite(expected).tolist()
    np.testing.assert_allclose(lifted.depth, expected, equal_nan=True)
    ev = _events(CASES)
    keep = lifted.valid
    np.testing.assert_allclose(
        lifted.points, back_project(ev.x[keep], ev.y[keep], expected[keep], CAM)
    )
    np.testing.assert_allclose(lifted.t, ev.t[keep])
    assert np.all(np.isfinite(lifted.points))


def test_lift_fill_policy_uses_neighbourhood_median_of_each_map():
    # event at (1, 2), t = 11.5, s = 0.75; radius 1 known neighbours:
    # Z1: 5, 6, 3, 2, 7 -> median 5; Z2: 5, 2, 2, 9 -> median 3.5; 5 + 0.75 (3.5 - 5) = 3.875
    lifted = lift(_window(CASES), unknown_depth="fill", fill_radius=1)
    assert lifted.valid.all()
    assert lifted.depth[6] == pytest.approx(3.875)
    assert lifted.points.shape == (len(CASES), 3)


def test_lift_fill_with_radius_zero_keeps_dropping():
    lifted = lift(_window(CASES), unknown_depth="fill", fill_radius=0)
    assert not lifted.valid[6] and lifted.valid.sum() == len(CASES) - 1


def test_lift_errors_are_clear():
    holes = np.full((3, 4), NAN)
    with pytest.raises(ValueError, match="all events in the window have unknown depth"):
        lift(_window(CASES[6:7]), unknown_depth="drop", fill_radius=1)
    with pytest.raises(ValueError, match="all events in the window have unknown depth"):
        lift(_window(CASES, holes, holes), unknown_depth="fill", fill_radius=2)
    with pytest.raises(ValueError, match="the window has no events"):
        lift(_window(CASES).select(slice(0, 0)), unknown_depth="drop", fill_radius=1)
    with pytest.raises(ValueError, match="unknown_depth must be one of"):
        lift(_window(CASES), unknown_depth="zero", fill_radius=1)
    one_map = Recording(_events(CASES), CAM, (DepthMap(T1, Z1),))
    with pytest.raises(ValueError, match="needs two depth maps"):
        lift(one_map, unknown_depth="drop", fill_radius=1)


def test_lift_over_a_span_takes_each_events_bracketing_maps():
    """Three maps (a span of two windows): an event before T2 is interpolated between the
    first two maps, one after T2 between the last two, exactly as a window of its own."""
    t3, z3 = 14.0, np.full((3, 4), 10.0)
    maps = (DepthMap(T1, Z1), DepthMap(T2, Z2), DepthMap(t3, z3))
    later = [(0, 0, 13.0, 6.5), (2, 1, 13.5, 8.0), (3, 2, 15.0, 10.0)]  # Z2 -> 10, clamped
    first = CASES[1:8]
    lifted = lift(Recording(_events(first + later), CAM, maps), unknown_depth="drop", fill_radius=1)
    np.testing.assert_allclose(lifted.depth, _expected(first + later), equal_nan=True)
    alone = lift(_window(first), unknown_depth="drop", fill_radius=1)
    np.testing.assert_array_equal(lifted.depth[: len(first)], alone.depth)


def test_voxel_size_rule():
    pts = np.array([[0.0, 0.0, 1.5], [0.1, 0.2, 2.0], [0.3, 0.1, 2.5]])
    # median Z 2.0: X = 2 * 2.0 / 100, Y = 2 * 2.0 / 50; Z = (2.5 - 1.5) / 10
    np.testing.assert_allclose(voxel_size(pts, CAM, xy_scale=2.0, z_bins=10), [0.04, 0.08, 0.1])
    # a thin depth range is floored at the smaller lateral size
    np.testing.assert_allclose(voxel_size(pts, CAM, xy_scale=2.0, z_bins=1000), [0.04, 0.08, 0.04])
    flat = pts.copy()
    flat[:, 2] = 2.0
    np.testing.assert_allclose(voxel_size(flat, CAM, xy_scale=1.0, z_bins=10), [0.02, 0.04, 0.02])


def test_the_depth_voxel_is_never_finer_than_the_depth_error():
    """A 10 % depth error at the median depth (2.0 m, 0.5 /m) floors the depth voxel of both
    grids; a coarser voxel (z_bins=1) is kept."""
    pts = np.array([[0.0, 0.0, 1.5], [0.1, 0.2, 2.0], [0.3, 0.1, 2.5]])
    metric = voxel_size(pts, CAM, xy_scale=2.0, z_bins=10, depth_error=0.1)
    np.testing.assert_allclose(metric, [0.04, 0.08, 0.2])
    image = voxel_size(pts, CAM, xy_scale=2.0, z_bins=10, coordinates="image", depth_error=0.1)
    np.testing.assert_allclose(image, [2.0, 2.0, 0.05])
    coarse = voxel_size(pts, CAM, xy_scale=2.0, z_bins=1, coordinates="image", depth_error=0.1)
    np.testing.assert_allclose(coarse, [2.0, 2.0, 1 / 1.5 - 1 / 2.5])


def test_voxel_size_rejects_bad_input():
    pts = np.array([[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="NaN"):
        voxel_size(np.array([[0.0, NAN, 1.0]]), CAM, xy_scale=1.0, z_bins=10)
    with pytest.raises(ValueError, match="non-empty"):
        voxel_size(np.zeros((0, 3)), CAM, xy_scale=1.0, z_bins=10)
    with pytest.raises(ValueError, match="positive depth"):
        voxel_size(np.array([[0.0, 0.0, -1.0]]), CAM, xy_scale=1.0, z_bins=10)
    with pytest.raises(ValueError, match="xy_scale"):
        voxel_size(pts, CAM, xy_scale=0.0, z_bins=10)
    with pytest.raises(ValueError, match="z_bins"):
        voxel_size(pts, CAM, xy_scale=1.0, z_bins=0)
    with pytest.raises(ValueError, match="depth_error"):
        voxel_size(pts, CAM, xy_scale=1.0, z_bins=10, depth_error=NAN)


def test_lifted_points_feed_the_grid():
    lifted = lift(_window(CASES), unknown_depth="drop", fill_radius=1)
    size = voxel_size(lifted.points, CAM, xy_scale=1.0, z_bins=8)
    grid = grid_around(lifted.points, size, margin=0.1, max_voxels=10**6)
    c = grid.continuous_index(lifted.points)
    assert np.all(c >= 0) and np.all(c <= np.array(grid.shape) - 1)


def test_occlusion_edges_take_the_nearer_depth():
    """A pixel whose depth jumps between the maps (an edge passing) takes the occluder's depth."""
    from spatialseg.edpa import _interpolate

    z1, z2, s = np.array([1.0, 1.0]), np.array([5.0, 1.1]), np.array([0.5, 0.5])
    assert np.allclose(_interpolate(z1, z2, s), [3.0, 1.05])
    assert np.allclose(_interpolate(z1, z2, s, edge_ratio=0.2), [1.0, 1.05])


def test_lift_marks_the_events_on_occlusion_edges():
    """Known in both maps and differing by more than edge_ratio x the nearer depth."""
    z1 = np.array([1.0, 1.0, 2.0, NAN])
    z2 = np.array([5.0, 1.1, 2.5, 1.0])
    assert occlusion_edges(z1, z2, 0.2).tolist() == [True, False, True, False]
    assert not occlusion_edges(z1, z2, None).any()
    lifted = lift(_window(CASES), unknown_depth="drop", fill_radius=1, edge_ratio=0.2)
    ev = _events(CASES)
    expected = occlusion_edges(Z1[ev.y, ev.x], Z2[ev.y, ev.x], 0.2)
    assert lifted.on_edge.tolist() == expected.tolist() and expected.any()


def _approaching_box() -> tuple[np.ndarray, np.ndarray]:
    """A 5 x 12 pair of maps: a box at 4.0 m over columns 0-5 in the first comes 10 % nearer
    (3.6 m) and covers columns 0-7 in the second; a wall at 8 m behind it."""
    z1 = np.full((5, 12), 8.0)
    z2 = np.full((5, 12), 8.0)
    z1[:, :6] = 4.0
    z2[:, :8] = 3.6
    return z1, z2


def test_lift_gives_an_edge_event_the_nearer_depth():
    """An event on an occlusion edge (the approaching box's outline) takes the nearer of its
    pixel's two depths, 3.6 m; one on the box's surface interpolates (3.8 m halfway)."""
    z1, z2 = _approaching_box()
    camera = Camera(fx=100.0, fy=100.0, cx=5.5, cy=2.0, width=12, height=5)
    ev = EventStream(np.array([7, 2]), np.array([2, 2]), np.array([11.0, 11.0]), np.ones(2), 12, 5)
    window = Recording(ev, camera, (DepthMap(T1, z1), DepthMap(T2, z2)))
    lifted = lift(window, unknown_depth="drop", fill_radius=1, edge_ratio=0.2)
    np.testing.assert_allclose(lifted.depth, [3.6, 3.8])
    assert lifted.on_edge.tolist() == [True, False]
