"""The VWE evaluator against the numpy reference and finite differences; edge cases, errors."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from spatialseg import reference as ref
from spatialseg import volume
from spatialseg.grid import VoxelGrid
from spatialseg.objectives import Objective, make_objective, objective_names
from spatialseg.volume import VolumeObjective, _stable_order, counting_sort

GRID = VoxelGrid(np.array([0.0, -0.5, 1.0]), np.array([0.1, 0.1, 0.25]), (14, 11, 6))
#: A grid over pixels and inverse depth (1.5-2.5 m) of a 300 px focal length camera.
IMAGE_GRID = VoxelGrid(
    np.array([150.0, 110.0, 0.4]),
    np.array([2.0, 2.0, 0.05]),
    (14, 11, 6),
    projection=np.array([300.0, 300.0, 172.5, 129.5]),
)
GRIDS = pytest.mark.parametrize("grid", [GRID, IMAGE_GRID], ids=["metric", "image"])
THETA = np.array([0.9, -0.6, 1.3])
#: Agreement with the reference (float32 volumes round each vote: worst seen 3e-7).
RTOL = {np.float64: 1e-9, np.float32: 1e-6}
CASES = [(name, sigma) for name in ref.OBJECTIVES for sigma in (0.0, 0.8)]


def _events(n: int, seed: int = 0, margin: float = 2.0, grid: VoxelGrid = GRID):
    """Random events over ``grid``, ``margin`` voxels beyond it on every side (border cases)."""
    rng = np.random.default_rng(seed)
    lo = grid.origin - margin * grid.voxel_size
    hi = grid.origin + (np.array(grid.shape) - 1 + margin) * grid.voxel_size
    coords = rng.uniform(lo, hi, (n, 3))
    if grid.projection is not None:  # back from (u, v, 1/Z) to (X, Y, Z)
        fx, fy, cx, cy = grid.projection
        z = 1.0 / coords[:, 2]
        coords = np.column_stack([(coords[:, 0] - cx) * z / fx, (coords[:, 1] - cy) * z / fy, z])
    return coords, rng.uniform(-0.05, 0.05, n), rng.uniform(0.0, 1.0, n)


def _close(actual, expected, rtol):
    """Relative agreement against the largest magnitude of ``expected``."""
    expected = np.asarray(expected, np.float64)
    scale = max(float(np.max(np.abs(expected), initial=0.0)), 1e-300)
    assert np.max(np.abs(np.asarray(actual) - expected), initial=0.0) <= rtol * scale


def _central_difference(f, theta, step=1e-5):
    """Central finite-difference gradient of ``f`` at ``theta``."""
    grad = np.zeros(3)
    for a in range(3):
        e = np.zeros(3)
        e[a] = step
        grad[a] = (f(theta + e) - f(theta - e)) / (2 * step)
    return grad


@GRIDS
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize(("name", "sigma"), CASES)
def test_matches_reference(name, sigma, dtype, grid):
    points, dt, w = _events(800, grid=grid)
    ev = VolumeObjective(points, dt, grid, make_objective(name, blur_sigma=sigma), w, dtype)
    # the reference sees the same (rounded) inputs
    p, t, ww = (a.astype(dtype) for a in (points, dt, w))
    value, grad = ev.value_and_grad(THETA)
    ref_value, ref_grad = ref.value_and_grad(p, t, THETA, grid, ww, name, sigma)
    _close(value, ref_value, RTOL[dtype])
    _close(grad, ref_grad, RTOL[dtype])
    assert ev.value(THETA) == value
    np.testing.assert_array_equal(ev.grad(THETA), grad)
    volume = ev.volume(THETA)
    assert volume.shape == grid.shape and volume.dtype == dtype
    _close(volume, ref.volume(p, t, THETA, grid, ww), RTOL[dtype])
    _close(
        ev.sample(THETA),
        ref.sample(p, t, THETA, grid, ref.volume(p, t, THETA, grid, ww)),
        RTOL[dtype],
    )


@GRIDS
@pytest.mark.parametrize("name", objective_names())
@pytest.mark.parametrize("sigma", [0.0, 0.8])
def test_gradient_matches_finite_differences(name, sigma, grid):
    points, dt, w = _events(400, seed=1, grid=grid)
    ev = VolumeObjective(points, dt, grid, make_objective(name, blur_sigma=sigma), w)
    for theta in (THETA, np.array([-0.3, 0.4, -0.7])):
        _close(ev.grad(theta), _central_difference(ev.value, theta), 1e-6)


@GRIDS
def test_reference_gradient_matches_finite_differences(grid):
    points, dt, w = _events(300, seed=2, grid=grid)

    def value(theta):
        return ref.value(points, dt, theta, grid, w)

    _close(
        ref.value_and_grad(points, dt, THETA, grid, w)[1], _central_difference(value, THETA), 1e-6
    )


@dataclass(frozen=True)
class _MeanOfCubes(Objective):
    """A non-moment objective (the docs' one-file recipe) to exercise the unfused path."""

    name: ClassVar[str] = "mean_of_cubes"

    def value(self, volume):
        return float(np.mean(np.asarray(volume, np.float64) ** 3))

    def value_and_derivative(self, volume, out):
        np.multiply(volume, volume, out=out)
        out *= 3.0 / volume.size
        return self.value(volume)


def test_custom_objective_uses_the_generic_path():
    points, dt, w = _events(400, seed=3)
    ev = VolumeObjective(points, dt, GRID, _MeanOfCubes(), w)
    volume = ref.volume(points, dt, THETA, GRID, w)
    assert ev.value(THETA) == pytest.approx(np.mean(volume**3), rel=1e-12)
    _close(ev.grad(THETA), _central_difference(ev.value, THETA), 1e-6)
    np.testing.assert_array_equal(
        ev.batch_value(np.stack([THETA, -THETA])), [ev.value(THETA), ev.value(-THETA)]
    )


@GRIDS
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_batch_value_equals_value_one_by_one(dtype, grid):
    points, dt, w = _events(500, seed=4, grid=grid)
    ev = VolumeObjective(points, dt, grid, "variance", w, dtype)
    thetas = np.random.default_rng(0).normal(0.0, 1.0, (7, 3))
    np.testing.assert_array_equal(ev.batch_value(thetas), [ev.value(t) for t in thetas])
    assert ev.batch_value(np.zeros((0, 3))).shape == (0,)


@GRIDS
@pytest.mark.parametrize("n_events", [30, 5000])
def test_volume_buffer_is_zero_between_calls(n_events, grid):
    """Both clearing strategies (by the events' cells, by a memset) leave the buffer zero."""
    points, dt, w = _events(n_events, seed=5, grid=grid)
    ev = VolumeObjective(points, dt, grid, "variance", w)
    first = ev.value_and_grad(THETA)
    for theta in (THETA, -THETA, 2 * THETA):
        ev.value_and_grad(theta)
        ev.sample(theta)
        assert not ev._padded.any()
    assert ev.value_and_grad(THETA)[0] == first[0]
    np.testing.assert_array_equal(ev.value_and_grad(THETA)[1], first[1])


def test_weights_and_samples_follow_the_callers_order():
    points, dt, w = _events(300, seed=6)
    w[::3] = 0.0  # events without membership still get sampled for the P-step
    ev = VolumeObjective(points, dt, GRID, "variance")
    ev.set_weights(w)
    _close(ev.value(THETA), ref.value(points, dt, THETA, GRID, w), 1e-9)
    _close(ev.grad(THETA), ref.value_and_grad(points, dt, THETA, GRID, w)[1], 1e-9)
    volume = ref.volume(points, dt, THETA, GRID, w)
    _close(ev.sample(THETA), ref.sample(points, dt, THETA, GRID, volume), 1e-9)
    other = np.random.default_rng(1).uniform(0.0, 2.0, GRID.shape)
    _close(ev.sample(THETA, other), ref.sample(points, dt, THETA, GRID, other), 1e-9)


def test_empty_input():
    ev = VolumeObjective(np.zeros((0, 3)), np.zeros(0), GRID, "variance")
    value, grad = ev.value_and_grad(THETA)
    assert value == 0.0 and np.array_equal(grad, np.zeros(3))
    assert ev.n_events == 0 and ev.sample(THETA).shape == (0,)
    assert not ev.volume(THETA).any()
    np.testing.assert_array_equal(ev.batch_value(np.ones((3, 3))), np.zeros(3))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_single_event(dtype):
    point = GRID.origin + np.array([3.3, 4.6, 2.2]) * GRID.voxel_size
    ev = VolumeObjective(point[None], [0.01], GRID, "variance", [0.5], dtype)
    volume = ev.volume(THETA)
    assert volume.sum() == pytest.approx(0.5) and np.count_nonzero(volume) == 8
    expected = ref.value_and_grad(point[None], np.array([0.01]), THETA, GRID, np.array([0.5]))
    _close(ev.value_and_grad(THETA)[0], expected[0], RTOL[dtype])
    _close(ev.value_and_grad(THETA)[1], expected[1], RTOL[dtype])


def test_corners_outside_are_dropped_one_by_one():
    """An event leaving the grid fades out continuously: its mass is the in-grid weight."""
    grid = VoxelGrid(np.zeros(3), np.ones(3), (4, 4, 4))
    for x, mass in [(-0.25, 0.75), (-0.999, 0.001), (-1.0, 0.0), (2.5, 1.0), (3.4, 0.6)]:
        ev = VolumeObjective([[x, 1.5, 1.5]], [0.0], grid, "variance")
        assert ev.volume(np.zeros(3)).sum() == pytest.approx(mass, abs=1e-12)
    # the value is continuous across the border, as a function of theta
    ev = VolumeObjective([[0.0, 1.5, 1.5]], [1.0], grid, "sum_of_squares")
    values = [ev.value(np.array([t, 0.0, 0.0])) for t in (0.999, 0.9999, 1.0, 1.0001)]
    assert np.all(np.diff(values) <= 0) and values[-2] < 1e-7 and values[-1] == 0.0


def test_image_grid_behind_the_camera_votes_nothing():
    """A point warped to Z <= 0 leaves a projective grid (no vote, no NaN in value or grad)."""
    point = np.array([[0.0, 0.0, 0.5]])
    ev = VolumeObjective(point, [1.0], IMAGE_GRID, "variance")
    for vz in (0.5, 0.6):  # warped depth 0 and -0.1
        value, grad = ev.value_and_grad(np.array([0.0, 0.0, vz]))
        assert value == 0.0 and np.array_equal(grad, np.zeros(3))
    assert not ev.volume(np.array([0.0, 0.0, 0.5])).any()


def test_image_grid_images_a_point_at_its_pixel():
    """On a projective grid a point votes at its pixel and inverse depth."""
    fx, fy, cx, cy = IMAGE_GRID.projection
    pixel, depth = np.array([160.0, 118.0]), 2.0
    point = np.array([[(pixel[0] - cx) * depth / fx, (pixel[1] - cy) * depth / fy, depth]])
    index = IMAGE_GRID.continuous_index(point)[0]
    np.testing.assert_allclose(index, (np.array([*pixel, 0.5]) - IMAGE_GRID.origin) / [2, 2, 0.05])
    volume = VolumeObjective(point, [0.0], IMAGE_GRID, "variance").volume(np.zeros(3))
    assert volume.sum() == pytest.approx(1.0)
    assert np.isclose(volume[tuple(np.rint(index).astype(int))], 1.0)


def test_planar_model_on_a_single_layer():
    """nz == 1: points on the layer get z weight 1, dO/dtheta_z = 0, x/y match the 2-D reference."""
    rng = np.random.default_rng(7)
    grid = VoxelGrid(np.array([0.0, 0.0, 0.0]), np.ones(3), (24, 18, 1))
    n = 600
    points = np.column_stack([rng.integers(0, 24, n), rng.integers(0, 18, n), np.zeros(n)])
    dt = rng.uniform(-0.05, 0.05, n)
    theta = np.array([14.0, -9.0, 0.0])
    ev = VolumeObjective(points, dt, grid, "variance")
    volume = ev.volume(theta)
    assert volume.sum() == pytest.approx(ref.volume(points, dt, theta, grid).sum())
    ones = VolumeObjective(points, np.zeros(n), grid, "variance").volume(np.zeros(3))
    np.testing.assert_array_equal(
        ones[..., 0],
        np.histogram2d(*points[:, :2].T, bins=(24, 18), range=((-0.5, 23.5), (-0.5, 17.5)))[0],
    )
    value, grad = ev.value_and_grad(theta)
    ref_value, ref_grad = ref.value_and_grad(points, dt, theta, grid)
    _close(value, ref_value, 1e-9)
    _close(grad, ref_grad, 1e-9)
    assert grad[2] == 0.0
    _close(grad, _central_difference(ev.value, theta), 1e-6)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"points": np.full((3, 3), np.nan)}, "points has 9 NaN/inf"),
        ({"points": np.zeros((3, 2))}, r"points must have shape N x 3"),
        ({"dt": np.zeros(2)}, r"dt must have shape 3"),
        ({"dt": [0.0, np.inf, 0.0]}, "dt has 1 NaN/inf values .first at index .1,"),
        ({"weights": [1.0, np.nan, 1.0]}, "weights has 1 NaN"),
        ({"weights": np.ones(4)}, "weights must have shape 3"),
        ({"objective": "entropy"}, "unknown objective 'entropy'"),
        ({"grid": (4, 4, 4)}, "grid must be a VoxelGrid"),
        ({"dtype": np.int32}, "dtype must be float32 or float64"),
    ],
)
def test_invalid_inputs_raise(kwargs, match):
    args = {"points": np.zeros((3, 3)), "dt": np.zeros(3), "grid": GRID, "objective": "variance"}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        VolumeObjective(**args)


def test_invalid_theta_raises():
    ev = VolumeObjective(np.zeros((3, 3)), np.zeros(3), GRID, "variance")
    for call in (ev.value, ev.value_and_grad, ev.grad, ev.volume, ev.sample):
        with pytest.raises(ValueError, match="theta has 1 NaN"):
            call(np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="theta must have shape 3"):
        ev.value(np.zeros(2))
    with pytest.raises(ValueError, match="thetas must have shape N x 3"):
        ev.batch_value(np.zeros(3))
    with pytest.raises(ValueError, match="volume must have shape 14 x 11 x 6"):
        ev.sample(np.zeros(3), np.zeros((2, 2, 2)))


@GRIDS
@pytest.mark.parametrize("sigma", [0.0, 1.5, (1.0, 1.0, 2.5)])
def test_p_step_is_the_references(grid, sigma):
    """Vote, smooth (mirrored at the border; one sigma or one per axis), interpolate at each
    warped event, and the contrast of the vote; twice, as the buffers are reused."""
    points, dt, w = _events(400, seed=8, grid=grid)
    ev = VolumeObjective(points, dt, grid, "variance", w)
    per_axis = np.broadcast_to(sigma, (3,))
    sigmas = [s if n > 1 else 0.0 for s, n in zip(per_axis, grid.shape, strict=True)]
    volume = gaussian_filter(ref.volume(points, dt, THETA, grid, w), sigmas, mode="reflect")
    for _ in range(2):
        responses, value = ev.p_step(THETA, sigma)
        _close(responses, ref.sample(points, dt, THETA, grid, volume), 1e-9)
        _close(value, ref.value(points, dt, THETA, grid, w), 1e-9)
        assert not ev._padded.any()


@pytest.mark.parametrize("stride", [1, 2])
def test_weights_and_responses_in_the_kernels_order_are_the_same_ones(stride):
    """Weights set and responses read in :attr:`VolumeObjective.order` are the input order's
    permuted, to the bit, and the objective the same."""
    points, dt, w = _events(400, seed=10)
    ev = VolumeObjective(points, dt, GRID, "variance")
    order = ev.order
    assert np.array_equal(np.sort(order), np.arange(400))
    ev.set_weights(w)
    responses, value = ev.p_step(THETA, 1.5, stride)
    ev.set_weights(w[order], ordered=True)
    ordered, ordered_value = ev.p_step(THETA, 1.5, stride, ordered=True)
    assert np.array_equal(ordered, responses[order]) and ordered_value == value


@GRIDS
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("stride", [1, 2])
def test_p_step_at_other_events_is_theirs_with_weight_zero(grid, dtype, stride):
    """p_step_at: the fitted events' smoothed volume read at other events is, to the bit,
    the P-step response those events get in one objective with both, theirs weighted 0."""
    points, dt, w = _events(300, seed=11, grid=grid)
    others, others_dt, _ = _events(200, seed=12, grid=grid)
    both = VolumeObjective(
        np.vstack([points, others]), np.concatenate([dt, others_dt]), grid, "variance",
        np.concatenate([w, np.zeros(200)]), dtype,
    )  # fmt: skip
    fitted = VolumeObjective(points, dt, grid, "variance", w, dtype)
    expected = both.p_step(THETA, 1.5, stride)[0][300:]
    for _ in range(2):  # buffers reused
        found = fitted.p_step_at(THETA, 1.5, stride, others, others_dt)
        assert np.array_equal(found, expected) and np.any(found > 0)
    with pytest.raises(ValueError, match="points must have shape N x 3"):
        fitted.p_step_at(THETA, 1.5, stride, others[:, :2], others_dt)


@GRIDS
@pytest.mark.parametrize("depth_sigma", [None, 0.5])
def test_p_step_stride_is_the_coarse_references(grid, depth_sigma):
    """``stride`` 2: the reference vote on a grid twice as coarse in x and y (depth keeps its
    bins and its own sigma when given), smoothed by the narrowed Gaussian, sampled, per fine
    voxel's area."""
    points, dt, w = _events(400, seed=9, grid=grid)
    sigma, (nx, ny, nz) = 1.5, grid.shape
    depth = sigma if depth_sigma is None else depth_sigma
    coarse = VoxelGrid(
        grid.origin,
        grid.voxel_size * [2.0, 2.0, 1.0],
        ((nx - 1) // 2 + 2, (ny - 1) // 2 + 2, nz),
        projection=grid.projection,
    )
    narrowed = np.sqrt(sigma**2 - 1.0) / 2.0
    volume = ref.volume(points, dt, THETA, coarse, w)
    volume = gaussian_filter(volume, [narrowed, narrowed, depth], mode="reflect")
    ev = VolumeObjective(points, dt, grid, "variance", w)
    for stride in (2, 1, 2):  # buffers change with the stride and come back
        responses, value = ev.p_step(THETA, (sigma, sigma, depth), stride)
        if stride == 2:
            _close(responses, ref.sample(points, dt, THETA, coarse, volume) / 4.0, 1e-9)
        _close(value, ref.value(points, dt, THETA, grid, w), 1e-9)
        assert not ev._padded.any() and not ev._pstep[2].any()  # the vote buffers: zero
        halo = ev._pstep[3].copy()  # the sampled buffer: its inside kept, its halo zero
        halo[1:-1, 1:-1, 1:-1] = 0
        assert ev._pstep[3].any() and not halo.any()


@GRIDS
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("budget", [None, 1])
def test_p_steps_at_revisited_velocities_are_a_fresh_objectives(grid, dtype, budget, monkeypatch):
    """The loop's P-steps return to each cluster's velocity with new memberships (some 0):
    the cells located at a velocity's first P-step give, to the bit, what an objective
    locating them anew gives; also when the kept cells must be dropped (``budget`` entries,
    the least recently used taken over) and between the velocities' value calls."""
    points, dt, _ = _events(500, seed=13, grid=grid)
    if budget is not None:  # room for ``budget`` velocities' cells
        monkeypatch.setattr(volume, "LOCATED_BYTES", budget * 64 * 500)
    rng = np.random.default_rng(14)
    thetas = [THETA, -THETA, 0.5 * THETA]
    kept = VolumeObjective(points, dt, grid, "variance", dtype=dtype)
    kept.p_step(THETA, 1.5, 2)
    first = [e.cells for e in next(iter(kept._located.values()))]
    for round_ in range(3):
        for stride in (2, 1):
            for theta in thetas:
                w = np.where(rng.random(500) < 0.3, 0.0, rng.random(500))
                kept.set_weights(w)
                found = kept.p_step(theta, 1.5, stride)
                kept.value(theta + 0.1 * round_)  # votes at another velocity between
                fresh = VolumeObjective(points, dt, grid, "variance", w, dtype)
                expected = fresh.p_step(theta, 1.5, stride)
                assert np.array_equal(found[0], expected[0]) and found[1] == expected[1]
    assert len(kept._located) == (2 * len(thetas) if budget is None else budget)
    if budget == 1:  # the first velocity's arrays, taken over by every other
        now = [e.cells for e in next(iter(kept._located.values()))]
        assert all(a is b for a, b in zip(now, first, strict=True))
    assert not kept._padded.any() and not kept._pstep[2].any()


def test_p_step_stride_keeps_the_fine_responses():
    """On a cloud of blobs, stride 2 moves the responses by well under 1 % (median)."""
    grid = VoxelGrid(np.zeros(3), np.array([0.1, 0.1, 0.25]), (60, 48, 8))
    rng = np.random.default_rng(4)
    centres = rng.uniform([1.0, 1.0, 0.5], [5.0, 4.0, 1.25], (6, 3))
    points = np.concatenate([rng.normal(c, [0.3, 0.3, 0.3], (800, 3)) for c in centres])
    points = np.clip(points, [0.5, 0.5, 0.25], [5.4, 4.2, 1.5])  # clear of the border
    dt = rng.uniform(-0.05, 0.05, len(points))
    ev = VolumeObjective(points, dt, grid, "variance")
    fine, coarse = ev.p_step(THETA, 3.0)[0], ev.p_step(THETA, 3.0, 2)[0]
    assert np.median(np.abs(coarse - fine) / fine) < 0.01
    assert np.corrcoef(fine, coarse)[0, 1] > 0.999


def test_p_step_stride_needs_enough_smoothing():
    ev = VolumeObjective(*_events(50)[:2], GRID, "variance")
    with pytest.raises(ValueError, match=r"stride of 3 needs a smoothing sigma of at least 1\.63"):
        ev.p_step(THETA, 1.0, 3)
    with pytest.raises(ValueError, match="in x and y"):
        ev.p_step(THETA, (1.0, 1.0, 5.0), 3)
    ev.p_step(THETA, (2.0, 2.0, 0.0), 3)  # depth is not coarsened, so any sigma there
    with pytest.raises(ValueError, match="grid stride must be an integer >= 1"):
        ev.p_step(THETA, 1.0, 0)


@pytest.mark.parametrize(("n", "n_keys"), [(2000, 500), (2000, 60000), (300, 1_000_000), (0, 10)])
def test_stable_order_is_numpys_stable_argsort(n, n_keys):
    """By counting (keys' range up to 32 times their count) or by numpy's sort beyond: the
    same permutation, ties kept in their given order."""
    keys = np.random.default_rng(n).integers(0, n_keys, n)
    keys[: n // 2] = keys[0] if n else 0  # many ties
    np.testing.assert_array_equal(_stable_order(keys, n_keys), np.argsort(keys, kind="stable"))


def test_counting_sort_says_where_each_keys_run_starts():
    keys = np.random.default_rng(3).integers(0, 50, 1000)
    order, starts = counting_sort(keys, 60)
    np.testing.assert_array_equal(order, np.argsort(keys, kind="stable"))
    np.testing.assert_array_equal(starts, np.searchsorted(np.sort(keys), np.arange(61)))
