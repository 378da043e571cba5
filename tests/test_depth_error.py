"""Depth error on the simulator's output depth maps: statistics, holes, scale, determinism."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf
from scipy import ndimage

from spatialseg.config import conf_dir
from spatialseg.io import read_recording
from spatialseg.recording import DepthMap
from spatialseg.simulate import simulate_scene
from spatialseg.simulate.depth_error import corrupt_depth_maps, hole_mask, smooth_field
from spatialseg.simulate.scene import DepthError
from tests.helpers import run_module

OFF = {
    "sigma": 0.0,
    "correlation": 40.0,
    "holes": 0.0,
    "hole_size": 15.0,
    "scale": 1.0,
    "shared": False,
    "bias": 0.0,
    "seed_offset": 0,
}


def _error(**changes) -> DepthError:
    """A DepthError: everything off except ``changes``."""
    return DepthError(**{**OFF, **changes})


def _maps(shape=(180, 240)) -> tuple[DepthMap, ...]:
    """Two exact depth maps: a slanted plane from 2 to 8 m, then the same 1 % nearer."""
    ramp = np.linspace(2.0, 8.0, shape[1])[None, :].repeat(shape[0], axis=0)
    return DepthMap(0.0, ramp), DepthMap(0.1, 0.99 * ramp)


def _autocorrelation(field: np.ndarray, lag: int) -> float:
    """Correlation of the field with itself shifted by ``lag`` columns."""
    return float(np.corrcoef(field[:, :-lag].ravel(), field[:, lag:].ravel())[0, 1])


def _scene(name: str = "ego_street", **error):
    """A shipped scene config with its depth_error block changed by ``error``."""
    cfg = OmegaConf.load(conf_dir() / "scene" / f"{name}.yaml")
    cfg.depth_error = {**OFF, **error}
    return cfg


def test_smooth_field_has_unit_std_and_falls_to_1_over_e_at_its_correlation_length():
    length = 8
    field = smooth_field(np.random.default_rng(0), (512, 512), float(length))
    assert abs(field.mean()) < 1e-9 and field.std() == pytest.approx(1.0)
    assert _autocorrelation(field, 1) > 0.95
    assert 0.25 < _autocorrelation(field, length) < 0.5  # exp(-1) = 0.37
    assert abs(_autocorrelation(field, 4 * length)) < 0.1


@pytest.mark.parametrize("sigma", [0.02, 0.1, 0.3])
def test_error_field_has_the_requested_std_and_is_smooth(sigma):
    exact = _maps()
    corrupted = corrupt_depth_maps(exact, _error(sigma=sigma, correlation=20.0), seed=0)
    for true, noisy in zip(exact, corrupted, strict=True):
        log_error = np.log(noisy.depth.astype(np.float64) / true.depth)
        assert log_error.std() == pytest.approx(sigma, rel=0.01)
        assert abs(log_error.mean()) < 0.01 * sigma
        relative = noisy.depth / true.depth - 1
        assert relative.std() == pytest.approx(sigma, rel=0.2)
        assert _autocorrelation(log_error, 1) > 0.95
        assert np.all(noisy.depth > 0) and noisy.t == true.t


@pytest.mark.parametrize(("share", "size"), [(0.05, 8.0), (0.2, 15.0)])
def test_holes_cover_the_requested_share_of_pixels_in_blobs(share, size):
    exact = _maps()
    corrupted = corrupt_depth_maps(exact, _error(holes=share, hole_size=size), seed=3)
    pixels = exact[0].depth.size
    for true, noisy in zip(exact, corrupted, strict=True):
        holes = np.isnan(noisy.depth)
        assert holes.sum() == round(share * pixels)
        assert np.array_equal(noisy.depth[~holes], true.depth[~holes])
        _, count = ndimage.label(holes)
        assert holes.sum() / count >= size**2 / 4, "holes are scattered, not blobs"


def test_scale_multiplies_every_depth():
    exact = _maps()
    corrupted = corrupt_depth_maps(exact, _error(scale=1.1), seed=0)
    for true, scaled in zip(exact, corrupted, strict=True):
        assert np.allclose(scaled.depth, 1.1 * true.depth, rtol=1e-6)


def test_shared_draw_is_the_same_in_both_maps_and_independent_draws_differ():
    exact = _maps()
    for shared in (True, False):
        error = _error(sigma=0.1, holes=0.1, shared=shared)
        first, second = corrupt_depth_maps(exact, error, seed=0)
        ratios = [m.depth / e.depth for m, e in zip((first, second), exact, strict=True)]
        same = np.allclose(ratios[0], ratios[1], equal_nan=True)
        assert same == shared


def test_same_seed_repeats_and_seed_or_offset_change_the_draw():
    exact = _maps()
    error = _error(sigma=0.1, holes=0.1)
    a, b = (corrupt_depth_maps(exact, error, seed=5)[0].depth for _ in range(2))
    assert np.array_equal(a, b, equal_nan=True)
    other_seed = corrupt_depth_maps(exact, error, seed=6)[0].depth
    other_offset = corrupt_depth_maps(exact, _error(sigma=0.1, holes=0.1, seed_offset=1), seed=5)
    assert not np.array_equal(a, other_seed, equal_nan=True)
    assert not np.array_equal(a, other_offset[0].depth, equal_nan=True)


def test_hole_mask_of_zero_share_is_empty():
    assert not hole_mask(np.random.default_rng(0), (10, 10), 0.0, 5.0).any()


def test_zero_settings_leave_simulated_depth_maps_bit_identical():
    plain = OmegaConf.load(conf_dir() / "scene" / "ego_street.yaml")
    del plain["depth_error"]
    without = simulate_scene(plain, seed=0, max_events=500)
    off = simulate_scene(_scene(), seed=0, max_events=500)
    for a, b in zip(without.depth_maps, off.depth_maps, strict=True):
        assert a.depth.tobytes() == b.depth.tobytes()


def test_depth_error_changes_only_the_depth_maps_not_events_or_truth():
    exact = simulate_scene(_scene(), seed=0, max_events=500)
    noisy = simulate_scene(_scene(sigma=0.1, holes=0.1, scale=1.05), seed=0, max_events=500)
    assert np.array_equal(exact.events.t, noisy.events.t)
    assert np.array_equal(exact.ground_truth.labels, noisy.ground_truth.labels)
    assert [k.image.tobytes() for k in exact.keyframes] == [
        k.image.tobytes() for k in noisy.keyframes
    ]
    for a, b in zip(exact.depth_maps, noisy.depth_maps, strict=True):
        assert a.t == b.t
        assert np.isnan(b.depth).mean() == pytest.approx(0.1, abs=1e-3)
        known = ~np.isnan(b.depth)
        ratio = np.log(b.depth[known] / a.depth[known] / 1.05)
        assert ratio.std() == pytest.approx(0.1, rel=0.1)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"holes": 1.0}, r"depth_error.holes must be a share of the pixels in \[0, 1\)"),
        ({"sigma": -0.1}, r"depth_error.sigma must be >= 0"),
        ({"bias": -0.1}, r"depth_error.bias must be >= 0"),
        ({"correlation": 0.0}, r"depth_error.correlation must be > 0"),
        ({"scale": 0.0}, r"depth_error.scale must be > 0"),
        ({"shared": 1}, r"depth_error.shared must be true or false"),
        ({"typo": 1}, r"depth_error.typo is not a known key"),
    ],
)
def test_bad_depth_error_raises_one_line_value_error(change, message):
    with pytest.raises(ValueError, match=message) as info:
        simulate_scene(_scene(**change), seed=0, max_events=10)
    assert "\n" not in str(info.value)


def test_missing_depth_error_key_is_named():
    cfg = _scene()
    del cfg.depth_error["scale"]
    with pytest.raises(ValueError, match=r"depth_error.scale is missing"):
        simulate_scene(cfg, seed=0, max_events=10)


def test_cli_override_writes_corrupted_depth_maps(tmp_path):
    done = run_module(
        "spatialseg.simulate",
        "+scene=interior",
        "out=rec",
        "window.events=500",
        "scene.depth_error.holes=0.05",
        "scene.depth_error.sigma=0.1",
        "preview=false",
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    rec = read_recording(tmp_path / "rec")
    for depth_map in rec.depth_maps:
        assert np.isnan(depth_map.depth).mean() == pytest.approx(0.05, abs=1e-3)


def test_bias_is_one_field_every_map_shares_beside_each_map_s_own_flicker():
    exact = _maps()
    logs = [
        [np.log(m.depth / e.depth) for m, e in zip(maps, exact, strict=True)]
        for maps in (
            corrupt_depth_maps(exact, _error(bias=0.1), seed=0),
            corrupt_depth_maps(exact, _error(bias=0.1, sigma=0.1), seed=0),
        )
    ]
    bias_only, both = logs
    np.testing.assert_allclose(bias_only[0], bias_only[1], atol=1e-6)
    assert bias_only[0].std() == pytest.approx(0.1, rel=0.05)
    correlation = np.corrcoef(both[0].ravel(), both[1].ravel())[0, 1]
    assert 0.3 < correlation < 0.7  # half shared (the bias), half each map's own
    flicker = corrupt_depth_maps(exact, _error(sigma=0.1), seed=0)
    with_bias = corrupt_depth_maps(exact, _error(sigma=0.1, bias=0.1), seed=0)
    own = [np.log(m.depth / b.depth) for m, b in zip(with_bias, flicker, strict=True)]
    np.testing.assert_allclose(own[0], own[1], atol=1e-6)  # adding a bias keeps the flicker
