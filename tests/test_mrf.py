"""The Potts labelling: exact for two labels, never worse than the likeliest labels, and
what it is for (an isolated weak label outvoted, a confident one kept)."""

from __future__ import annotations

import itertools
from dataclasses import replace

import maxflow
import numpy as np
import pytest

import optimizers
from spatialseg import mrf
from spatialseg.grid import VoxelGrid
from spatialseg.metrics import segmentation_metrics
from spatialseg.mrf import (
    FLOOR,
    _expand,
    conditional_labels,
    neighbour_pairs,
    potts_labels,
    space_time,
)
from spatialseg.neighbours import agreeing_labels, grid_order
from spatialseg.points import Prepared
from spatialseg.recording import Camera
from spatialseg.scenes import load_scene
from spatialseg.settings import ClusteringSettings, settings_from
from spatialseg.window import image_speed, segment_window, smoothed_labels
from tests.test_pipeline import _config


def _energy(p: np.ndarray, labels: np.ndarray, first, second, weight: float) -> float:
    unary = -np.log(np.maximum(p[np.arange(len(p)), labels], FLOOR)).sum()
    return float(unary + weight * np.sum(labels[first] != labels[second]))


def _brute_force(p: np.ndarray, first, second, weight: float) -> float:
    return min(
        _energy(p, np.array(choice), first, second, weight)
        for choice in itertools.product(range(p.shape[1]), repeat=len(p))
    )


@pytest.mark.parametrize("seed", range(5))
def test_two_labels_reach_the_minimum_and_more_stay_within_twice_it(seed):
    rng = np.random.default_rng(seed)
    points = rng.uniform(0, 3, (9, 3))
    first, second = neighbour_pairs(points, k=3)
    for k in (2, 3):
        p = rng.dirichlet(np.ones(k), size=9)
        labels = potts_labels(p, first, second, 0.8)
        found = _energy(p, labels, first, second, 0.8)
        best = _brute_force(p, first, second, 0.8)
        assert found <= _energy(p, p.argmax(axis=1), first, second, 0.8) + 1e-9
        if k == 2:
            assert found == pytest.approx(best)
        else:
            assert found <= 2 * best + 1e-9


@pytest.mark.parametrize("weight", [0.3, 1.0, 3.0, 10.0])
def test_two_labels_take_one_cut_to_the_minimum(weight, monkeypatch):
    """Two labels: the brute-force minimum on 12 events, weak to strong smoothing, from one
    minimum cut (no expansion)."""
    rng = np.random.default_rng(int(weight * 10))
    points = rng.uniform(0, 3, (12, 3))
    first, second = neighbour_pairs(points, k=4)
    p = rng.dirichlet(np.full(2, 0.7), size=12)
    monkeypatch.setattr(mrf, "_expand", None)  # an expansion would fail
    labels = potts_labels(p, first, second, weight)
    assert _energy(p, labels, first, second, weight) == pytest.approx(
        _brute_force(p, first, second, weight)
    )


@pytest.mark.parametrize("k", [2, 3, 4])
def test_the_labels_returned_are_a_fixed_point_of_every_expansion(k):
    rng = np.random.default_rng(k)
    points = rng.uniform(0, 10, (500, 3))
    first, second = neighbour_pairs(points)
    p = rng.dirichlet(np.full(k, 0.5), size=len(points))
    labels = potts_labels(p, first, second, 1.0)
    assert not np.array_equal(labels, p.argmax(axis=1))
    cost = -np.log(np.maximum(p, FLOOR))
    for alpha in range(k):
        assert np.array_equal(_expand(cost, labels, first, second, 1.0, alpha), labels)


def _full_graph_expand(cost, labels, first, second, weight, alpha):
    """The expansion move with every event in the graph (the implementation until session 51)."""
    n = len(labels)
    both_kept = weight * (labels[first] != labels[second])
    first_kept = weight * (labels[first] != alpha)
    second_kept = weight * (labels[second] != alpha)
    delta = cost[:, alpha] - cost[np.arange(n), labels]
    delta += np.bincount(first, second_kept - both_kept, minlength=n)
    delta -= np.bincount(second, second_kept, minlength=n)
    graph = maxflow.Graph[float](n, len(first))
    nodes = graph.add_nodes(n)
    graph.add_grid_tedges(nodes, np.maximum(delta, 0.0), np.maximum(-delta, 0.0))
    cut = first_kept + second_kept - both_kept
    graph.add_edges(first, second, cut, np.zeros_like(cut))
    graph.maxflow()
    return np.where(graph.get_grid_segments(nodes), alpha, labels)


@pytest.mark.parametrize("k", [2, 3, 5])
def test_an_expansion_over_the_free_events_is_the_one_over_every_event(k):
    """Leaving the events labelled alpha out of the graph changes no label: the same cut."""
    rng = np.random.default_rng(10 + k)
    points = rng.uniform(0, 12, (3000, 3))
    first, second = neighbour_pairs(points)
    cost = -np.log(np.maximum(rng.dirichlet(np.full(k, 0.7), size=len(points)), FLOOR))
    for weight in (0.37, 1.0, 3.0):
        labels = rng.integers(0, k, len(points))
        for alpha in range(k):
            expected = _full_graph_expand(cost, labels, first, second, weight, alpha)
            assert not np.array_equal(expected, labels)  # the move changes labels
            np.testing.assert_array_equal(
                _expand(cost, labels, first, second, weight, alpha), expected
            )
    everyone = np.zeros(len(points), dtype=np.int64)
    np.testing.assert_array_equal(_expand(cost, everyone, first, second, 1.0, 0), everyone)


def test_an_isolated_weak_label_is_outvoted_and_a_confident_one_kept():
    xy = np.array([(x, y) for x in range(10) for y in range(10)], dtype=float)
    t = np.zeros(len(xy))
    p = np.tile([0.9, 0.1], (len(xy), 1))
    p[45] = [0.4, 0.6]  # mislabelled, weakly
    p[54] = [0.001, 0.999]  # a confident event of the other cluster
    first, second = neighbour_pairs(space_time(xy, t, 1.0))
    labels = potts_labels(p, first, second, 0.3)
    assert p.argmax(axis=1)[45] == 1 and labels[45] == 0
    assert labels[54] == 1 and np.all(np.delete(labels, 54) == 0)
    assert np.array_equal(potts_labels(p, first, second, 0.0), p.argmax(axis=1))


def test_an_event_labelled_given_held_neighbours_takes_the_cheapest_label():
    """conditional_labels: each event's label minimises its own cost plus the weight per
    held neighbour of another label (checked against every label's energy); a weak
    membership follows its neighbours, a confident one is kept, weight 0 is the argmax."""
    rng = np.random.default_rng(2)
    fixed = rng.uniform(0, 20, (400, 3))
    fixed_labels = (fixed[:, 0] > 10).astype(np.int64)  # two halves
    points = np.array([[5.0, 10.0, 10.0], [5.0, 10.0, 10.0], [15.0, 10.0, 10.0]])
    p = np.array([[0.4, 0.6], [0.001, 0.999], [0.6, 0.4]])
    # weight 0.5: eight neighbours of the other label cost 4, a membership of 0.001 6.9
    labels = conditional_labels(p, points, fixed, fixed_labels, 0.5)
    assert labels.tolist() == [0, 1, 1]
    assert conditional_labels(p, points, fixed, fixed_labels, 0.0).tolist() == [1, 1, 0]
    queries = rng.uniform(0, 20, (50, 3))
    q = rng.dirichlet([1.0, 1.0, 1.0], 50)
    # labels at random (every event searched) and in halves of a denser set (away from
    # the middle, the grid tells an event its neighbours' one label without the search)
    dense = rng.uniform(0, 20, (6000, 3))
    for held_at, held in (
        (fixed, rng.integers(0, 3, 400)),
        (dense, 2 * (dense[:, 0] > 10).astype(np.int64)),
    ):
        found = conditional_labels(q, queries, held_at, held, 0.7)
        distance = ((queries[:, None] - held_at[None]) ** 2).sum(axis=2)
        near = held[np.argsort(distance, axis=1, kind="stable")[:, :8]]
        energy = -np.log(np.maximum(q, FLOOR)) + 0.7 * np.stack(
            [(near != label).sum(axis=1) for label in range(3)], axis=1
        )
        np.testing.assert_array_equal(found, energy.argmin(axis=1))
    assert np.mean(agreeing_labels(held_at, held, 8, queries) >= 0) > 0.2
    # a tie (equal memberships, four held neighbours of each label) goes to the lower label,
    # as numpy's argmin of the energies would
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    for held in ([0, 1] * 4, [1, 0] * 4):
        tie = conditional_labels(np.full((1, 2), 0.5), np.zeros((1, 3)), corners, held, 0.5)
        assert tie.tolist() == [0]


@pytest.mark.parametrize("seed", range(3))
def test_pairs_are_each_points_nearest_others_once_in_order(seed):
    """Every point joined to its k nearest others (ties, here between duplicate points, to
    the lower index), each pair once, in order."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(0, 6, (400, 3))
    points[300:] = points[:100]  # duplicate points, ties between them
    distance = ((points[:, None] - points[None]) ** 2).sum(axis=2)  # squared, summed x, y, t
    np.fill_diagonal(distance, np.inf)
    nearest = np.argsort(distance, axis=1, kind="stable")[:, :4]  # stable: ties by index
    directed = {(i, int(j)) for i, row in enumerate(nearest) for j in row}
    expected = sorted({(min(i, j), max(i, j)) for i, j in directed})
    first, second = neighbour_pairs(points, k=4)
    assert list(zip(first.tolist(), second.tolist(), strict=True)) == expected


def test_pairs_are_symmetric_unique_and_bad_input_is_refused():
    points = np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0], [5, 5, 5]], dtype=float)
    first, second = neighbour_pairs(points, k=2)
    assert np.all(first < second) and len(set(zip(first, second, strict=True))) == len(first)
    assert len(neighbour_pairs(points[:1])[0]) == 0
    with pytest.raises(ValueError, match="finite"):
        potts_labels(np.array([[np.nan, 1.0]]), first[:0], second[:0], 1.0)
    with pytest.raises(ValueError, match=">= 0"):
        potts_labels(np.ones((2, 2)) / 2, first[:0], second[:0], -1.0)


@pytest.fixture(scope="module")
def interior_window():
    """An interior window of 15,000 events (no context), its settings and its segmentation
    without smoothing."""
    cfg = _config("window.events=15000", "window.context=0", "clustering.smoothness=0")
    rec = load_scene(dict(cfg["scene"]), seed=0, window_events=15000)
    _, window = next(rec.windows())
    settings = settings_from(cfg)
    res = segment_window(window, settings, optimizers.create("ssa_ga"), seed=0)
    return window, settings.clustering, res


def test_a_weakly_mislabelled_event_of_a_segmented_window_takes_its_neighbours_label(
    interior_window,
):
    window, clustering, res = interior_window
    smoothing = replace(clustering, smoothness=ClusteringSettings().smoothness)  # the default
    p = res.probabilities.copy()
    labels = res.labels.copy()
    confident = np.flatnonzero((labels == 0) & (p[:, 0] > 0.9))
    event = int(confident[len(confident) // 2])
    p[event] = [0.4, 0.6]  # now weakly the other cluster's
    labels[event] = 1
    unassigned = labels < 0
    labels[np.flatnonzero(~unassigned)[:5]] = -1  # held out by min_probability
    unassigned = labels < 0
    args = (window, res.prepared, res.clustering, p, labels)
    smoothed = smoothed_labels(*args, smoothing)
    assert smoothed[event] == 0
    assert np.array_equal(smoothed < 0, unassigned)
    assert np.array_equal(smoothed_labels(*args, replace(clustering, smoothness=1e-6)), labels)
    truth = window.ground_truth.labels
    assert (
        segmentation_metrics(smoothed, truth)["accuracy"]
        >= (segmentation_metrics(labels, truth)["accuracy"])
    )


def test_only_the_inner_events_of_a_span_are_smoothed(interior_window):
    window, clustering, res = interior_window
    smoothing = replace(clustering, smoothness=ClusteringSettings().smoothness)
    p = res.probabilities.copy()
    labels = res.labels.copy()
    confident = np.flatnonzero((labels == 0) & (p[:, 0] > 0.9))
    early, late = int(confident[10]), int(confident[-10])  # events are in time order
    p[[early, late]] = [0.4, 0.6]  # both weakly the other cluster's
    labels[[early, late]] = 1
    half = len(labels) // 2
    inner = np.arange(half, len(labels))  # the span's second half is the window's own
    smoothed = smoothed_labels(window, res.prepared, res.clustering, p, labels, smoothing, inner)
    assert smoothed[late] == 0 and smoothed[early] == 1
    assert np.array_equal(smoothed[:half], labels[:half])


def test_the_image_speed_is_the_flow_of_the_likeliest_motion():
    camera = Camera(fx=200.0, fy=100.0, cx=0.0, cy=0.0, width=10, height=10)
    grid = VoxelGrid(origin=np.zeros(3), voxel_size=np.ones(3), shape=(2, 2, 2))
    points = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0]])
    spatial = Prepared(points, np.zeros(2), np.ones(2, dtype=bool), grid, 3, "m/s")
    p = np.array([[1.0, 0.0], [0.0, 1.0]])
    thetas = np.array([[0.5, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 50 px/s; 200 * 1 / 4 = 50 px/s
    assert image_speed(spatial, thetas, p, camera) == pytest.approx(50.0)
    planar = replace(spatial, dim=2, units="px/s")
    assert image_speed(planar, np.array([[3.0, 4.0], [0.0, 1.0]]), p[[0, 0]], camera) == 5.0


@pytest.mark.parametrize("k", [2, 3])
def test_the_labels_do_not_depend_on_how_the_events_are_numbered(k):
    """Numbered in grid order (as the window's smoothing does) or in time order, the same
    events with the same memberships get the same labels."""
    rng = np.random.default_rng(11)
    points = np.column_stack([rng.uniform(0, 60, (3000, 2)), rng.uniform(0, 20, 3000)])
    p = rng.dirichlet(np.ones(k), 3000)
    p[points[:, 0] < 30, 0] += 1.0  # a blob leaning to label 0, the rest mixed
    p /= p.sum(axis=1, keepdims=True)
    plain = potts_labels(p, *neighbour_pairs(points), 1.0)
    order = grid_order(points)
    renumbered = np.empty_like(plain)
    renumbered[order] = potts_labels(p[order], *neighbour_pairs(points[order]), 1.0)
    assert np.array_equal(renumbered, plain)
    assert 0 < np.mean(plain != p.argmax(axis=1)) < 0.5  # the smoothing did change labels
