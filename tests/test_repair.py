"""n_clusters=auto's split and merge: wasted clusters found, new motions seeded from the
worst-explained group, and the number of motions found."""

from __future__ import annotations

import numpy as np

import optimizers
from spatialseg.clustering import Repair, weak_cluster, worst_explained
from spatialseg.scenes import load_scene
from spatialseg.settings import settings_from
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
