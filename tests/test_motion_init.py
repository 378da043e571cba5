"""Initial motions: time surfaces, plane fits, k-means on a synthetic two-plane scene."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from spatialseg.edpa import back_project, voxel_size
from spatialseg.grid import VoxelGrid, grid_around
from spatialseg.motion_init import (
    _plane_fits,
    initial_motions,
    kmeans,
    lift_constraints,
    time_surfaces,
    without_depth_motion,
)
from spatialseg.recording import Camera

CAM = Camera(fx=200.0, fy=200.0, cx=120.0, cy=90.0, width=240, height=180)
PARAMS = dict(
    seed=0,
    dim=3,
    radius=3,
    min_points=6,
    max_condition=100.0,
    max_speed=2.0,
    max_events=5000,
    n_init=4,
    min_r2=0.5,
)


def two_planes(
    velocities: np.ndarray,
    *,
    seed: int,
    n_events: int = 15000,
    n_texture: int = 400,
    duration: float = 0.1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Events of two textured fronto-parallel 0.3 m squares at 1.0 and 1.2 m, translating.

    Each square carries ``n_texture`` random texture points; an event is a random texture
    point at a random time, projected to its (integer) pixel and back-projected with its
    true depth, as EDPA would with exact depth maps. Returns points, sorted t and labels.
    """
    rng = np.random.default_rng(seed)
    centres = np.array([[-0.18, 0.0, 1.0], [0.2, 0.02, 1.2]])
    per_plane = n_events // 2
    pts, ts, labels = [], [], []
    for k, (centre, v) in enumerate(zip(centres, velocities, strict=True)):
        texture = rng.uniform(-0.15, 0.15, (n_texture, 2))
        uv = texture[rng.integers(0, n_texture, per_plane)]
        t = rng.uniform(0.0, duration, per_plane)
        p = centre + np.column_stack((uv, np.zeros(per_plane))) + t[:, None] * v
        pts.append(p)
        ts.append(t)
        labels.append(np.full(per_plane, k))
    p, t, labels = np.concatenate(pts), np.concatenate(ts), np.concatenate(labels)
    order = np.argsort(t, kind="stable")
    p, t, labels = p[order], t[order], labels[order]
    x = np.rint(CAM.fx * p[:, 0] / p[:, 2] + CAM.cx)
    y = np.rint(CAM.fy * p[:, 1] / p[:, 2] + CAM.cy)
    return back_project(x, y, p[:, 2], CAM), t, labels


def _grid(points: np.ndarray) -> VoxelGrid:
    return grid_around(points, voxel_size(points, CAM, xy_scale=1.0, z_bins=32), 0.05, 10**8)


def _xy_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees between the image-plane parts (vx, vy) of two velocities."""
    cos = a[:2] @ b[:2] / (np.linalg.norm(a[:2]) * np.linalg.norm(b[:2]))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _matched(thetas: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The estimated velocities reordered to match the true ones (least total error)."""
    cost = np.linalg.norm(thetas[:, None, :] - truth[None, :, :], axis=2)
    rows, cols = linear_sum_assignment(cost)
    return thetas[rows[np.argsort(cols)]]


@pytest.mark.parametrize(
    "velocities",
    [
        [[0.4, 0.2, 0.15], [-0.3, 0.25, -0.15]],  # opposite lateral and depth motions
        [[0.4, 0.2, 0.1], [-0.3, 0.25, 0.1]],  # same vz: only the image plane separates
    ],
)
@pytest.mark.parametrize("seed", [0, 1])
def test_initial_motions_recover_image_plane_directions(velocities, seed):
    truth = np.array(velocities)
    points, t, _ = two_planes(truth, seed=seed)
    result = initial_motions(points, t, _grid(points), 2, **(PARAMS | {"seed": seed}))
    assert not result.fallback and result.thetas.shape == (2, 3)
    assert result.n_valid == np.isfinite(result.flows[:, 0]).sum() > 1000
    est = _matched(result.thetas, truth)
    for e, v in zip(est, truth, strict=True):
        assert _xy_angle(e, v) < 30.0
        assert 0.5 < np.linalg.norm(e[:2]) / np.linalg.norm(v[:2]) < 2.0
        assert np.sign(e[2]) == np.sign(v[2])


def test_image_plane_model_uses_s1_only_and_pixels():
    truth = np.array([[0.4, 0.2, 0.0], [-0.3, 0.25, 0.0]])
    points, t, _ = two_planes(truth, seed=0)
    pixels = np.column_stack(
        (
            CAM.fx * points[:, 0] / points[:, 2] + CAM.cx,
            CAM.fy * points[:, 1] / points[:, 2] + CAM.cy,
            np.zeros(len(points)),
        )
    )
    grid = grid_around(pixels, np.ones(3), 0.05, 10**7)
    params = PARAMS | {"dim": 2, "max_speed": 1000.0}
    result = initial_motions(pixels, t, grid, 2, **params)
    image_truth = CAM.fx * truth / np.array([[1.0], [1.2]])  # px/s at the planes' depths
    est = _matched(result.thetas, image_truth)
    assert np.all(result.thetas[:, 2] == 0.0)
    for e, v in zip(est, image_truth, strict=True):
        assert _xy_angle(e, v) < 30.0
        assert 0.5 < np.linalg.norm(e[:2]) / np.linalg.norm(v[:2]) < 2.0


def test_initial_motions_ignore_the_time_origin():
    truth = np.array([[0.4, 0.2, 0.15], [-0.3, 0.25, -0.15]])
    points, t, _ = two_planes(truth, seed=0, n_events=6000)
    grid = _grid(points)
    absolute = initial_motions(points, t + 1.0e4, grid, 2, **PARAMS)
    relative = initial_motions(points, t + 1.0e4 - (1.0e4 + 0.05), grid, 2, **PARAMS)
    np.testing.assert_allclose(absolute.thetas, relative.thetas, atol=1e-6)
    np.testing.assert_allclose(absolute.flows, relative.flows, atol=1e-6)


def test_fallback_spreads_thetas_on_a_sphere_around_zero():
    # three static points: every time surface is flat, so no valid flow exists
    points = np.array([[0.0, 0.0, 1.0], [0.05, 0.0, 1.0], [0.0, 0.05, 1.1]])
    t = np.array([0.0, 0.5, 1.0])
    grid = grid_around(points, np.full(3, 0.01), 0.1, 10**6)
    result = initial_motions(points, t, grid, 3, **PARAMS)
    assert result.fallback and result.n_valid == 0
    assert np.isnan(result.flows).all()
    radius = 0.01 / 1.0  # smallest voxel over the window duration
    np.testing.assert_allclose(np.linalg.norm(result.thetas, axis=1), radius)
    assert len(np.unique(result.thetas.round(9), axis=0)) == 3
    single = initial_motions(points, t, grid, 1, **PARAMS)
    np.testing.assert_allclose(single.thetas, np.zeros((1, 3)))
    planar = initial_motions(points, t, grid, 4, **(PARAMS | {"dim": 2}))
    assert planar.fallback and np.all(planar.thetas[:, 2] == 0.0)
    np.testing.assert_allclose(np.linalg.norm(planar.thetas, axis=1), radius)


def test_time_surfaces_keep_the_latest_time_per_cell():
    grid = VoxelGrid(np.zeros(3), np.ones(3), (3, 2, 2))
    points = np.array([[0.0, 0.0, 0.0], [0.2, 0.1, 1.0], [2.0, 1.0, 1.0]])
    t = np.array([-2.0, -1.0, -3.0])  # times relative to a t_ref may be negative
    s1, s2, s3 = time_surfaces(points, t, grid)
    assert s1.shape == (3, 2) and s2.shape == (2, 2) and s3.shape == (2, 3)
    assert s1[0, 0] == -1.0 and s1[2, 1] == -3.0 and np.isneginf(s1[1, 0])
    assert s2[0, 0] == -2.0 and s2[0, 1] == -1.0 and s2[1, 1] == -3.0
    assert s3[0, 0] == -2.0 and s3[1, 0] == -1.0 and s3[1, 2] == -3.0


def test_plane_fit_recovers_an_exact_gradient_in_seconds_per_metre():
    cell = (0.01, 0.02)  # metres; different along u and v
    gradient = np.array([2.0, -0.5])  # s/m
    iu, iv = np.meshgrid(np.arange(9), np.arange(9), indexing="ij")
    surface = 5.0 + gradient[0] * iu * cell[0] + gradient[1] * iv * cell[1]
    surface[0, :] = -np.inf  # unhit cells are ignored
    g, ok = _plane_fits(
        surface,
        np.array([4, 1]),
        np.array([4, 0]),
        cell,
        radius=2,
        min_points=6,
        max_condition=100.0,
        min_r2=0.9,
    )
    assert ok.all()
    np.testing.assert_allclose(g, [gradient, gradient])
    flat = np.zeros((9, 9))
    _, ok_flat = _plane_fits(
        flat,
        np.array([4]),
        np.array([4]),
        cell,
        radius=2,
        min_points=6,
        max_condition=100.0,
        min_r2=0.5,
    )
    assert not ok_flat.any()


def test_initial_motions_reject_bad_input():
    points = np.array([[0.0, 0.0, 1.0], [0.05, 0.0, 1.0]])
    t = np.array([0.0, 1.0])
    grid = grid_around(points, np.full(3, 0.01), 0.1, 10**6)
    bad = [
        ((np.zeros((0, 3)), np.zeros(0), grid, 2), {}, "empty"),
        ((points[:, :2], t, grid, 2), {}, "M x 3"),
        ((points, t[:1], grid, 2), {}, "one time per point"),
        ((points, np.array([0.0, np.nan]), grid, 2), {}, "NaN"),
        ((points, np.zeros(2), grid, 2), {}, "one timestamp"),
        ((points + 5.0, t, grid, 2), {}, "outside the voxel grid"),
        ((points, t, grid, 0), {}, "n_clusters"),
        ((points, t, grid, 2), {"dim": 1}, "dim must be 2"),
        ((points, t, grid, 2), {"radius": 0}, "radius"),
        ((points, t, grid, 2), {"min_points": 2}, "min_points"),
        ((points, t, grid, 2), {"max_speed": 0.0}, "max_speed"),
        ((points, t, grid, 2), {"min_r2": 1.5}, "min_r2"),
    ]
    for args, override, message in bad:
        with pytest.raises(ValueError, match=message):
            initial_motions(*args, **(PARAMS | override))


def _pinhole_lift(u: np.ndarray, v: np.ndarray, z: np.ndarray, camera: Camera = CAM) -> np.ndarray:
    """Each event's ``d(u', v')/dtheta`` (N x 2 x 3) for ``camera`` at pixel (u, v) and
    depth z, written out as the pinhole model gives it."""
    lift = np.zeros((len(z), 2, 3))
    lift[:, 0, 0], lift[:, 0, 2] = camera.fx / z, -(u - camera.cx) / z
    lift[:, 1, 1], lift[:, 1, 2] = camera.fy / z, -(v - camera.cy) / z
    return lift


def test_lifted_constraints_make_a_static_scene_at_many_depths_one_velocity():
    """A camera translating sideways: image speed falls with depth (1.5-8 m), but every lifted
    constraint is satisfied by the one 3-D velocity (-2, 0, 0) and the lifted normal flows
    agree, while the image-plane ones spread by the depth ratio."""
    rng = np.random.default_rng(0)
    n = 200
    z = rng.uniform(1.5, 8.0, n)
    u, v = rng.uniform(0, 240, n), rng.uniform(0, 180, n)
    theta = np.array([-2.0, 0.0, 0.0])
    camera = Camera(fx=200.0, fy=200.0, cx=119.5, cy=89.5, width=240, height=180)
    lift = _pinhole_lift(u, v, z, camera)
    flow = lift @ theta  # px/s
    a, b = np.zeros((n, 3, 3)), np.zeros((n, 3))
    a[:, 0, 0] = -1.0  # vertical edges: the normal is the flow's direction
    b[:, 0] = np.abs(flow[:, 0])
    lifted_a, lifted_b = lift_constraints(a, b, lift)
    np.testing.assert_allclose(lifted_a[:, 0] @ theta, lifted_b[:, 0], rtol=1e-12)
    assert b[:, 0].max() / b[:, 0].min() > 4
    assert lifted_b[:, 0].max() / lifted_b[:, 0].min() < 1.2  # only the off-axis angle
    assert not lifted_a[:, 1:].any() and not lifted_b[:, 1:].any()


def test_a_tiles_velocity_without_depth_motion_moves_its_events_alike():
    """Over a small patch a motion in depth moves the events almost as a sideways one: the
    velocity with vz = 0 moves them across the image within a tenth of their speed, is
    the least-squares one (no other vz = 0 velocity does better), leaves a velocity
    without vz as it is, and works group by group (an empty group unchanged)."""
    rng = np.random.default_rng(1)
    u, v = 200 + rng.uniform(0, 16, 300), 40 + rng.uniform(0, 16, 300)
    lift = _pinhole_lift(u, v, rng.uniform(2.9, 3.1, 300))
    groups = [np.arange(300), np.arange(0), np.arange(150)]
    velocities = np.array([[0.7, 0.3, 0.9], [1.0, 2.0, 3.0], [0.5, -0.2, 0.0]])
    flat = without_depth_motion(lift, groups, velocities)
    assert not flat[:, 2][[0, 2]].any()
    np.testing.assert_array_equal(flat[1], velocities[1])
    np.testing.assert_allclose(flat[2], velocities[2], atol=1e-12)
    before, after = lift @ velocities[0], lift @ flat[0]
    assert np.abs(after - before).max() < 0.1 * np.abs(before).max()
    residual = np.sum((after - before) ** 2)
    for step in ([0.01, 0.0, 0.0], [0.0, -0.01, 0.0]):
        assert np.sum((lift @ (flat[0] + step) - before) ** 2) > residual


def _blobs(
    rng: np.random.Generator, k: int, n: int, spread: float
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` 3-D points around ``k`` random centres, ``spread`` per axis: (points, truth)."""
    truth = rng.integers(k, size=n)
    return rng.normal(size=(k, 3))[truth] * 3.0 + rng.normal(size=(n, 3)) * spread, truth


def test_kmeans_recovers_separated_blobs_and_is_seeded() -> None:
    """Three blobs far apart: one label per blob, centres at the blob means, and the same
    seed gives the same partition."""
    points, truth = _blobs(np.random.default_rng(3), 3, 900, 0.05)
    labels, centres = kmeans(points, 3, n_init=4, seed=7)
    assert len(set(zip(truth.tolist(), labels.tolist(), strict=True))) == 3
    for j in range(3):
        np.testing.assert_allclose(centres[j], points[labels == j].mean(axis=0))
    again, _ = kmeans(points, 3, n_init=4, seed=7)
    np.testing.assert_array_equal(labels, again)


def test_kmeans_inertia_matches_scikit_learn() -> None:
    """On overlapping blobs the partition is as tight as scikit-learn's KMeans (the flow
    start's k-means until session 19): inertia within 0.5 % on each of 20 draws."""
    from sklearn.cluster import KMeans

    rng = np.random.default_rng(11)
    for trial in range(20):
        k = int(rng.integers(2, 6))
        points, _ = _blobs(rng, k, int(rng.integers(50, 3000)), 1.0)
        labels, centres = kmeans(points, k, n_init=10, seed=trial)
        ours = float(((points - centres[labels]) ** 2).sum())
        reference = KMeans(k, n_init=10, random_state=trial).fit(points).inertia_
        assert ours <= reference * 1.005, (trial, ours, reference)


def test_kmeans_keeps_every_cluster_with_as_many_distinct_points() -> None:
    """Points repeated at exactly K places: every cluster ends with the points of one place."""
    places = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    points = np.repeat(places, [40, 1, 1, 1], axis=0)
    labels, centres = kmeans(points, 4, n_init=3, seed=0)
    assert np.bincount(labels, minlength=4).min() >= 1
    np.testing.assert_allclose(np.sort(centres, axis=0), np.sort(places, axis=0))
