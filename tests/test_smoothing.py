"""The numba Gaussian smoothing against scipy.ndimage (both boundary modes), buffers, errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from spatialseg.smoothing import gaussian_kernel, gaussian_smooth

CASES = [
    ((20, 15, 9), 3.0),
    ((7, 1, 5), (1.0, 2.0, 0.0)),
    ((30, 20, 1), (2.0, 2.0, 0.0)),
    ((9, 1, 3), 1.5),  # a kernel wider than the axes
    ((6, 5, 80), (0.0, 0.7, 2.5)),  # a long last axis takes the shifted-sum path
    ((4, 4, 4), 0.0),
]


@pytest.mark.parametrize(("shape", "sigma"), CASES)
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("mode", ["constant", "reflect"])
def test_matches_scipy(shape, sigma, dtype, mode):
    volume = np.random.default_rng(0).random(shape).astype(dtype)
    before = volume.copy()
    expected = gaussian_filter(volume.astype(np.float64), sigma, mode=mode)
    result = gaussian_smooth(volume, sigma, mode=mode)
    assert result.dtype == dtype and result.shape == shape
    tol = 1e-12 if dtype == np.float64 else 1e-6
    np.testing.assert_allclose(result, expected, rtol=0, atol=tol * max(expected.max(), 1e-300))
    np.testing.assert_array_equal(volume, before)  # the input is left alone


@pytest.mark.parametrize("mode", ["constant", "reflect"])
def test_a_sparse_volume_matches_scipy(mode):
    """A volume like a window's: events in a few percent of the voxels, whole rows and
    blocks empty (the passes skip those), one point source at a corner."""
    rng = np.random.default_rng(2)
    volume = np.zeros((40, 90, 12))
    hits = rng.integers(0, volume.size, 400)
    volume.flat[hits] = rng.random(400)
    volume[0, 0, 0] = 5.0
    expected = gaussian_filter(volume, (1.5, 1.5, 1.0), mode=mode)
    result = gaussian_smooth(volume, (1.5, 1.5, 1.0), mode=mode)
    np.testing.assert_allclose(result, expected, rtol=0, atol=1e-12 * expected.max())


def test_into_a_view_and_with_the_input_as_scratch():
    rng = np.random.default_rng(1)
    volume = rng.random((12, 10, 6))
    expected = gaussian_filter(volume, 1.5, mode="constant")
    padded = np.zeros((14, 12, 8))
    view = padded[1:-1, 1:-1, 1:-1]
    assert gaussian_smooth(volume, 1.5, out=view) is view
    np.testing.assert_allclose(view, expected, atol=1e-12)
    assert not padded[0].any() and not padded[:, :, -1].any()  # only the view is written
    out = np.empty_like(volume)
    gaussian_smooth(volume, 1.5, out=out, work=volume)
    np.testing.assert_allclose(out, expected, atol=1e-12)


def test_kernel_is_normalised_and_truncated_at_four_sigma():
    kernel = gaussian_kernel(3.0)
    assert kernel.shape == (25,) and kernel.sum() == pytest.approx(1.0)
    assert kernel.argmax() == 12 and np.allclose(kernel, kernel[::-1])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"volume": np.zeros((3, 3))}, "3-D volume"),
        ({"sigma": -1.0}, ">= 0"),
        ({"sigma": np.nan}, "finite"),
        ({"out": np.zeros((3, 3, 2))}, "out must be"),
        ({"out": np.zeros((3, 3, 3), np.float32)}, "out must be"),
        ({"work": np.zeros((3, 3, 2))}, "work must be"),
        ({"mode": "wrap"}, "mode must be one of"),
    ],
)
def test_errors_name_the_problem(kwargs, message):
    args = {"volume": np.zeros((3, 3, 3)), "sigma": 1.0, **kwargs}
    with pytest.raises(ValueError, match=message):
        gaussian_smooth(args.pop("volume"), args.pop("sigma"), **args)
