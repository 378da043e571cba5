"""Split and merge: wasted clusters found, re-seeded from the worst-explained group for a
fixed number of motions, new motions seeded with n_clusters=auto, and the number found."""

from __future__ import annotations

import numpy as np

import optimizers
from spatialseg import motion_init, starts, window
from spatialseg.clustering import (
    ClusteringResult,
    Repair,
    repair_wasted,
    weak_cluster,
    worst_explained,
)
from spatialseg.metrics import segmentation_metrics
from spatialseg.scenes import load_scene
from spatialseg.settings import settings_from
from spatialseg.starts import StartInput, register_start
from spatialseg.window import segment_window
from tests.test_pipeline import _config


def _repair(separation: float = 5.0, min_share: float = 0.01) -> Repair:
    """A Repair whose motions are ``separation`` voxels apart (only the checks use it)."""

    def unused(*args):
        raise AssertionError("not called")

    return Repair(unused, unused, unused, lambda a, b: separation, np.zeros((0, 2)), min_share)


def test_a_cluster_nobody_picks_or_a_duplicate_motion_is_weak():
    thetas = np.zeros((3, 3))
    p = np.tile([0.6, 0.35, 0.05], (100, 1))  # cluster 2 holds 5 % of every membership ...
    p[60:] = [0.3, 0.65, 0.05]
    assert weak_cluster(thetas, p, _repair()) == 2  # ... but is nobody's likeliest
    p[:2] = [0.0, 0.0, 1.0]
    assert weak_cluster(thetas, p, _repair()) is None  # 2 % of the events pick it
    assert weak_cluster(thetas, p, _repair(separation=0.5)) == 1  # the smaller of a pair


def test_the_worst_explained_group_is_where_poorly_explained_events_crowd():
    rng = np.random.default_rng(0)
    xy = np.vstack([rng.uniform(0, 200, (500, 2)), rng.normal(150, 4, (100, 2))])
    responses = np.ones((600, 2))
    responses[500:, 0] = 0.05  # blurred under their cluster's motion
    p = np.tile([1.0, 0.0], (600, 1))
    group = worst_explained(responses, p, xy)
    assert group is not None and set(group) <= set(range(500, 600)) and len(group) > 90
    assert worst_explained(np.ones((600, 2)), p, xy) is None


def test_n_clusters_auto_finds_one_two_and_three_motions():
    """One cart, the interior scene's two carts, the three scene's three objects."""
    found = {}
    for scene, drop in (("interior", 1), ("interior", 0), ("three", 0)):
        cfg = _config("window.events=15000", "window.context=0", "n_clusters=auto", scene=scene)
        scene_cfg = dict(cfg["scene"])
        if drop:
            scene_cfg["objects"] = scene_cfg["objects"][:1]
        rec = load_scene(scene_cfg, seed=0, window_events=15000)
        _, window = next(rec.windows())
        res = segment_window(window, settings_from(cfg), optimizers.create("ssa_ga"), seed=0)
        found[len(rec.ground_truth.motions)] = len(res.clustering.thetas)
    assert found == {1: 1, 2: 2, 3: 3}


def _segment_from_one_motion(monkeypatch) -> tuple[window.WindowResult, float]:
    """The interior window (two carts) segmented into two motions from a start that puts
    every event in cluster 0, both clusters on cart 1's true velocity: its result and its
    accuracy."""
    monkeypatch.setattr(starts, "_REGISTRY", dict(starts._REGISTRY))
    cfg = _config("window.events=15000", "window.context=0", "init.method=one_motion")
    rec = load_scene(cfg["scene"], seed=0, window_events=15000)
    _, win = next(rec.windows())
    cart = np.asarray(rec.ground_truth.motions[min(rec.ground_truth.motions)], float)

    @register_start("one_motion")
    def one_motion(given: StartInput) -> motion_init.InitResult:
        labels = np.zeros(len(given.prepared.points), dtype=np.int64)
        flows = np.full((len(labels), 3), np.nan)
        return motion_init.InitResult(np.tile(cart, (given.k, 1)), flows, 0, False, labels)

    res = segment_window(win, settings_from(cfg), optimizers.create("ssa_ga"), seed=0)
    return res, segmentation_metrics(res.labels, win.ground_truth.labels)["accuracy"]


def test_a_cluster_emptied_on_purpose_is_reseeded(monkeypatch):
    """Both clusters start on one cart's motion, all events in one: the repair re-seeds the
    empty one from the other cart's events, and the carts end apart."""
    res, accuracy = _segment_from_one_motion(monkeypatch)
    shares = np.bincount(res.labels[res.labels >= 0], minlength=2) / len(res.labels)
    assert accuracy > 0.95 and shares.min() > 0.2


def test_without_the_repair_the_emptied_cluster_stays_wasted(monkeypatch):
    """The same start with the repair switched off: the loop alone keeps a wasted cluster,
    so the test above measures the repair."""
    monkeypatch.setattr(window, "repair_wasted", lambda result, repair, *, seed: result)
    res, accuracy = _segment_from_one_motion(monkeypatch)
    assert accuracy < 0.9 and np.unique(res.labels[res.labels >= 0]).size == 1


def _wasted_pair_repair(rerun_thetas: np.ndarray) -> tuple[ClusteringResult, Repair]:
    """Two clusters on one motion (0, 0, 0) and a crowd of 100 events blurred under it; a
    Repair whose loop returns ``rerun_thetas`` with twice the contrast."""
    rng = np.random.default_rng(0)
    xy = np.vstack([rng.uniform(0, 200, (500, 2)), rng.normal(150, 4, (100, 2))])
    p = np.tile([0.7, 0.3], (600, 1))
    result = ClusteringResult(np.zeros((2, 3)), p, np.array([1.0, 0.5]))

    def responses(thetas, p):  # motion 0 sharpens the first 500 events, (1, 1, 1) the crowd
        crowd = np.arange(600) >= 500
        return np.column_stack([np.where(crowd == t.any(), 1.0, 0.05) for t in thetas])

    def run(thetas, p, seed):
        return ClusteringResult(rerun_thetas, p, 2 * result.values)

    def separation(a, b):
        return float(np.linalg.norm(a - b) * 10)

    return result, Repair(run, responses, lambda group, seed: np.ones(3), separation, xy)


def test_a_repair_is_kept_when_the_total_rises_and_nothing_is_wasted():
    result, repair = _wasted_pair_repair(np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
    repaired = repair_wasted(result, repair, seed=0)
    np.testing.assert_array_equal(repaired.thetas, [[0, 0, 0], [1, 1, 1]])
    assert repaired.total == 2 * result.total


def test_a_repair_that_leaves_a_wasted_cluster_is_undone():
    """The loop brings the re-seeded motion back onto the other: the total rose, but the
    slot is wasted again, so the result before the move is kept."""
    result, repair = _wasted_pair_repair(np.zeros((2, 3)))
    assert repair_wasted(result, repair, seed=0) is result
