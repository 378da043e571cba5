"""Background-activity filter: exact against a brute-force reference, and on a noisy edge."""

from __future__ import annotations

import numpy as np
import pytest

import optimizers
from spatialseg.denoise import denoise_mask
from spatialseg.events import EventStream
from spatialseg.points import prepare
from spatialseg.recording import Camera, DepthMap, Recording
from spatialseg.settings import settings_from
from spatialseg.window import nearest_memberships, segment_window, unique_rows
from tests.test_pipeline import _config

WIDTH, HEIGHT = 64, 48


def _stream(x, y, t, width=WIDTH, height=HEIGHT) -> EventStream:
    order = np.argsort(t, kind="stable")
    x, y, t = np.asarray(x)[order], np.asarray(y)[order], np.asarray(t)[order]
    return EventStream(x, y, t, np.ones(len(t)), width, height)


def _reference(events: EventStream, radius: int, window: float) -> np.ndarray:
    """The filter's definition, evaluated directly: O(N^2), for small inputs."""
    keep = np.zeros(len(events), dtype=bool)
    for i in range(len(events)):
        earlier = slice(0, i)
        near = (np.abs(events.x[earlier] - events.x[i]) <= radius) & (
            np.abs(events.y[earlier] - events.y[i]) <= radius
        )
        other = (events.x[earlier] != events.x[i]) | (events.y[earlier] != events.y[i])
        recent = events.t[i] - events.t[earlier] <= window
        keep[i] = bool(np.any(near & other & recent))
    return keep


def _noisy_edge(seed: int, noise_rate: float) -> tuple[EventStream, np.ndarray]:
    """A vertical edge sweeping right at 400 px/s (one event per pixel, 0.2 ms jitter) plus
    uniform background activity at ``noise_rate`` events per pixel per second; the second
    value is True for the edge's events."""
    rng = np.random.default_rng(seed)
    speed, duration = 400.0, WIDTH / 400.0
    gx, gy = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    t_edge = gx.ravel() / speed + rng.normal(0.0, 2e-4, gx.size)
    n_noise = rng.poisson(noise_rate * WIDTH * HEIGHT * duration)
    x = np.r_[gx.ravel(), rng.integers(0, WIDTH, n_noise)]
    y = np.r_[gy.ravel(), rng.integers(0, HEIGHT, n_noise)]
    t = np.r_[t_edge, rng.uniform(0.0, duration, n_noise)]
    signal = np.r_[np.ones(gx.size, bool), np.zeros(n_noise, bool)]
    order = np.argsort(t, kind="stable")
    events = EventStream(x[order], y[order], t[order], np.ones(len(t)), WIDTH, HEIGHT)
    return events, signal[order]


@pytest.mark.parametrize(("radius", "window"), [(1, 0.001), (2, 0.0005), (3, 0.0002)])
def test_matches_the_brute_force_definition(radius, window):
    rng = np.random.default_rng(radius)
    n = 1500
    events = _stream(
        rng.integers(0, 20, n), rng.integers(0, 15, n), rng.uniform(0, 0.05, n), 20, 15
    )
    keep = denoise_mask(events, radius=radius, window=window)
    assert keep.dtype == bool and keep.shape == (n,)
    np.testing.assert_array_equal(keep, _reference(events, radius, window))
    assert 0.05 < keep.mean() < 0.95  # a test that both decisions occur


def test_keeps_a_moving_edge_and_removes_isolated_noise():
    events, signal = _noisy_edge(seed=0, noise_rate=1.0)
    keep = denoise_mask(events, radius=1, window=0.005)
    recall = keep[signal].mean()
    noise_removed = 1.0 - keep[~signal].mean()
    precision = signal[keep].mean()
    # measured: recall 0.9948, noise removed 0.909, precision 0.985 (3,072 edge and 516 noise
    # events; keeping everything has precision 0.856)
    assert recall >= 0.99
    assert noise_removed >= 0.85
    assert precision >= 0.975


def test_too_short_a_window_loses_the_edge():
    """The edge reaches the next column after 2.5 ms: a 1 ms window cannot bridge it."""
    events, signal = _noisy_edge(seed=1, noise_rate=1.0)
    assert denoise_mask(events, radius=1, window=0.001)[signal].mean() < 0.8
    assert denoise_mask(events, radius=2, window=0.005)[signal].mean() >= 0.99


def test_a_hot_pixel_does_not_support_itself():
    t = np.arange(200) * 1e-4
    events = _stream(np.full(200, 10), np.full(200, 10), t)
    assert not denoise_mask(events, radius=2, window=0.01).any()


def test_support_is_by_distance_and_border_safe():
    # corner pixel (0, 0) supported by (1, 1) at radius 1; (3, 0) is too far at radius 1
    events = _stream([1, 0, 3], [1, 0, 0], [0.0, 0.001, 0.002])
    np.testing.assert_array_equal(denoise_mask(events, radius=1, window=0.01), [0, 1, 0])
    np.testing.assert_array_equal(denoise_mask(events, radius=2, window=0.01), [0, 1, 1])


def test_is_deterministic_and_handles_empty_streams():
    events, _ = _noisy_edge(seed=2, noise_rate=1.0)
    a = denoise_mask(events, radius=1, window=0.005)
    np.testing.assert_array_equal(a, denoise_mask(events, radius=1, window=0.005))
    empty = _stream([], [], np.zeros(0))
    assert denoise_mask(empty, radius=1, window=0.01).shape == (0,)


@pytest.mark.parametrize(
    ("radius", "window", "message"),
    [
        (0, 0.01, "denoise.radius must be an integer >= 1"),
        (1.5, 0.01, "denoise.radius must be an integer >= 1"),
        (None, 0.01, "denoise.radius must be an integer >= 1"),
        (1, 0.0, "denoise.window must be a positive number"),
        (1, float("nan"), "denoise.window must be a positive number"),
        (1, None, "denoise.window must be a positive number"),
    ],
)
def test_bad_parameters_are_one_line_errors(radius, window, message):
    events = _stream([1, 2], [1, 1], [0.0, 0.001])
    with pytest.raises(ValueError, match=message):
        denoise_mask(events, radius=radius, window=window)


def test_noise_is_left_out_of_the_fit_and_still_labelled():
    """With denoise.enabled the filter's rejects build no volume (the grid spans the fitted
    events) but get a label from the fitted motion: nothing is dropped."""
    events, _ = _noisy_edge(seed=3, noise_rate=1.0)
    camera = Camera(100.0, 100.0, WIDTH / 2, HEIGHT / 2, WIDTH, HEIGHT)
    depth = np.full((HEIGHT, WIDTH), 2.0)
    maps = (DepthMap(events.t[0], depth), DepthMap(events.t[-1], depth))
    window = Recording(events, camera, maps)
    cfg = _config("denoise.enabled=true", "denoise.window=0.005", "n_clusters=1")
    prepared = prepare(window, settings_from(cfg))
    keep = denoise_mask(events, radius=1, window=0.005)
    np.testing.assert_array_equal(prepared.valid, keep)
    np.testing.assert_array_equal(prepared.rest[2], ~keep)
    assert len(prepared.points) == keep.sum() < len(events)
    result = segment_window(window, settings_from(cfg), optimizers.create("ssa_ga"), seed=0)
    assert np.all(result.labels == 0)
    off = prepare(window, settings_from(_config("n_clusters=1", "denoise.enabled=false")))
    assert off.valid.all() and not off.rest[2].any()
    with pytest.raises(ValueError, match=r"denoise\.enabled must be true or false"):
        settings_from({**cfg, "denoise": {**cfg["denoise"], "enabled": 1}})


def test_an_event_no_volume_reaches_takes_the_mean_memberships_at_the_nearest_point():
    """Two fitted events share the nearest point: a far query gets their mean, whichever of
    the two a tree would return; a query by a lone event gets that event's memberships."""
    points = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [5.0, 5.0, 3.0]])
    memberships = np.array([[1.0, 0.0], [0.0, 1.0], [0.2, 0.8]])
    queries = np.array([[-40.0, 1.0, 2.0], [6.0, 5.0, 3.0]])
    got = nearest_memberships(points, memberships, queries)
    np.testing.assert_allclose(got, [[0.5, 0.5], [0.2, 0.8]])


@pytest.mark.parametrize("columns", [1, 3])
def test_unique_rows_are_numpys(columns):
    """The distinct rows and each row's index among them, as ``np.unique(axis=0)`` gives
    them: rows repeated, rows equal in their first columns only, negative zero."""
    rng = np.random.default_rng(columns)
    points = rng.integers(-3, 3, (5000, columns)).astype(np.float64) / 2
    points[::7, -1] += rng.uniform(0, 1e-9, len(points[::7]))
    points[1] = -0.0 * points[1]
    unique, inverse = unique_rows(points)
    expected, expected_inverse = np.unique(points, axis=0, return_inverse=True)
    np.testing.assert_array_equal(unique, expected)
    np.testing.assert_array_equal(inverse, expected_inverse.reshape(-1))
    assert len(unique) < len(points)
