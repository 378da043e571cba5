"""The grid search for each point's nearest others: exact, ties to the lower index, the same
whatever the threads."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from scipy.spatial import cKDTree

from spatialseg.neighbours import agreeing_labels, grid_order, nearest_neighbours


def _brute_force(points: np.ndarray, k: int, queries: np.ndarray | None = None) -> np.ndarray:
    """Each point's k nearest others (or each query's k nearest points) by squared distance
    (summed over x, y, z in order), ties to the lower index."""
    asked = points if queries is None else queries
    distance = ((asked[:, None] - points[None]) ** 2).sum(axis=2)
    if queries is None:
        np.fill_diagonal(distance, np.inf)
    return np.argsort(distance, axis=1, kind="stable")[:, :k]


def _clustered(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points crowded round a few centres in a wide box, most of the box empty."""
    centres = rng.uniform(0, 300, (5, 3))
    return centres[rng.integers(0, 5, n)] + rng.normal(0, 2.0, (n, 3))


@pytest.mark.parametrize(
    "layout",
    ["uniform", "clustered", "flat", "pixels", "duplicates", "two"],
)
def test_every_points_nearest_others_in_order(layout):
    """The same neighbours, in the same order, as a search of every pair."""
    rng = np.random.default_rng(3)
    k = 1 if layout == "two" else 6
    points = {
        "uniform": lambda: rng.uniform(0, 50, (700, 3)),
        "clustered": lambda: _clustered(rng, 700),
        "flat": lambda: np.column_stack([rng.uniform(0, 40, (700, 2)), np.zeros(700)]),
        # integer pixels, times on a coarse clock: many exact ties in distance
        "pixels": lambda: np.column_stack(
            [rng.integers(0, 30, (700, 2)), rng.integers(0, 5, 700) * 0.5]
        ).astype(float),
        "duplicates": lambda: np.repeat(rng.uniform(0, 10, (150, 3)), 4, axis=0),
        "two": lambda: np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]),
    }[layout]()
    assert np.array_equal(nearest_neighbours(points, k), _brute_force(points, k))


def test_the_same_neighbours_as_a_k_d_tree_on_many_points():
    """On 200,000 points in general position, scipy's k-d tree finds the same sets."""
    rng = np.random.default_rng(7)
    points = np.column_stack([rng.integers(0, 346, 200_000), rng.integers(0, 260, 200_000)])
    points = np.column_stack([points, rng.uniform(0, 25, 200_000)]).astype(float)
    found = nearest_neighbours(points, 8)
    expected = cKDTree(points).query(points, k=9)[1][:, 1:]
    assert np.array_equal(np.sort(found, axis=1), np.sort(expected, axis=1))


def test_the_answer_does_not_depend_on_the_threads():
    rng = np.random.default_rng(11)
    points = np.column_stack(
        [rng.integers(0, 40, (5000, 2)), rng.integers(0, 20, 5000) * 0.25]
    ).astype(float)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = nearest_neighbours(points, 8)
    finally:
        numba.set_num_threads(threads)
    assert np.array_equal(one, nearest_neighbours(points, 8))


@pytest.mark.parametrize(
    ("points", "k", "match"),
    [
        (np.zeros((5, 2)), 2, "N x 3"),
        (np.array([[0.0, 0.0, np.nan], [1.0, 1.0, 1.0]]), 1, "finite"),
        (np.zeros((5, 3)), 5, "at most 4 \\(of 5 points\\)"),
        (np.zeros((5, 3)), 0, "at least 1"),
    ],
)
def test_bad_input_is_refused(points, k, match):
    with pytest.raises(ValueError, match=match):
        nearest_neighbours(points, k)


@pytest.mark.parametrize("layout", ["inside", "beyond", "duplicates"])
def test_every_querys_nearest_points_in_order(layout):
    """With queries: each query's nearest points, a point where a query lies at distance 0
    and none left out; queries beyond the points' box (on every side) are searched from the
    grid's edge cells."""
    rng = np.random.default_rng(5)
    points = _clustered(rng, 600)
    queries = {
        "inside": lambda: _clustered(rng, 400),
        "beyond": lambda: rng.uniform(-200, 500, (400, 3)),
        "duplicates": lambda: points[rng.integers(0, 600, 400)],
    }[layout]()
    found = nearest_neighbours(points, 8, queries)
    assert found.shape == (400, 8)
    np.testing.assert_array_equal(found, _brute_force(points, 8, queries))
    assert np.array_equal(nearest_neighbours(points, 600, queries[:3]).shape, (3, 600))


def test_bad_queries_are_refused():
    with pytest.raises(ValueError, match="queries must be a finite N x 3 array"):
        nearest_neighbours(np.zeros((5, 3)), 2, np.array([[np.inf, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="at most 5 \\(of 5 points\\)"):
        nearest_neighbours(np.zeros((5, 3)), 6, np.zeros((2, 3)))


@pytest.mark.parametrize("layout", ["halves", "blobs"])
def test_a_label_said_to_agree_is_every_nearest_points_label(layout):
    """agreeing_labels: where it names a label, each of the query's k nearest points (by a
    search of every pair) carries it; it names one for many queries inside one-label
    regions, none for a query beyond the points' box."""
    rng = np.random.default_rng(11)
    if layout == "halves":
        points = rng.uniform(0, 60, (20000, 3))
        labels = (points[:, 0] > 30).astype(np.int64)
    else:  # a label per blob of points, the blobs apart
        labels = rng.integers(0, 5, 20000)
        points = rng.uniform(0, 300, (5, 3))[labels] + rng.normal(0, 4.0, (20000, 3))
    picked = rng.integers(0, len(points), 500)
    queries = np.vstack([points[picked] + rng.normal(0, 0.5, (500, 3)), [[1e4, 0.0, 0.0]]])
    agreed = agreeing_labels(points, labels, 8, queries)
    near = labels[_brute_force(points, 8, queries)]
    named = agreed >= 0
    assert np.all(near[named] == agreed[named, None])
    assert named.mean() > 0.3 and agreed[-1] == -1
    with pytest.raises(ValueError, match="one label >= 0 per point"):
        agreeing_labels(points, -labels - 1, 8, queries)


def test_the_grid_order_is_a_permutation_that_keeps_near_points_together():
    """Every point once; consecutive points in the order are far nearer than in the events'
    own (random) order; no points, no order."""
    rng = np.random.default_rng(5)
    points = _clustered(rng, 5000)
    order = grid_order(points)
    assert np.array_equal(np.sort(order), np.arange(len(points)))

    def step(ordered: np.ndarray) -> float:
        return float(np.median(np.linalg.norm(np.diff(ordered, axis=0), axis=1)))

    assert step(points[order]) < step(points) / 3
    assert grid_order(np.zeros((0, 3))).shape == (0,)
    with pytest.raises(ValueError, match="finite"):
        grid_order(np.array([[0.0, np.nan, 1.0]]))
