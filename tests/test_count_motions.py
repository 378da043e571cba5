"""n_clusters=auto: wasted clusters found, and the number of motions chosen by the sweep
over 1, 2, ... motions (:func:`spatialseg.clustering.count_motions`)."""

from __future__ import annotations

import numpy as np

import optimizers
from spatialseg.clustering import MIN_GAIN, ClusteringResult, count_motions, weak_cluster
from spatialseg.scenes import load_scene
from spatialseg.settings import settings_from
from spatialseg.window import segment_window
from tests.test_pipeline import _config


def _apart(voxels: float):
    """A separation function: every two motions ``voxels`` apart."""
    return lambda a, b: voxels


def test_a_cluster_nobody_picks_or_a_duplicate_motion_is_weak():
    thetas = np.zeros((3, 3))
    p = np.tile([0.6, 0.35, 0.05], (100, 1))  # cluster 2 holds 5 % of every membership ...
    p[60:] = [0.3, 0.65, 0.05]
    assert weak_cluster(thetas, p, _apart(5.0)) == 2  # ... but is nobody's likeliest
    p[:2] = [0.0, 0.0, 1.0]
    assert weak_cluster(thetas, p, _apart(5.0)) is None  # 2 % of the events pick it
    assert weak_cluster(thetas, p, _apart(0.5)) == 1  # the smaller of a pair


def _fit_with_sharpness(sharpness: dict[int, float], weak_at: int | None = None):
    """A ``fit(k)`` whose k clusters (events split evenly, all clusters picked) have the
    given sharpness; at ``weak_at`` motions the last cluster is nobody's likeliest."""
    fitted: list[int] = []

    def fit(k: int) -> ClusteringResult:
        fitted.append(k)
        n = 100 * k
        p = np.eye(k)[np.arange(n) % k]
        if k == weak_at:
            p = np.eye(k)[np.arange(n) % (k - 1)]
        # sum_j values_j / (N mass_j) with mass_j = N / k: values_j = sharpness N^2 / k^2
        values = np.full(k, sharpness[k] * n * n / (k * k))
        return ClusteringResult(np.arange(3.0 * k).reshape(k, 3), p, values)

    return fit, fitted


def _count(sharpness: dict[int, float], *, weak_at: int | None = None, apart: float = 5.0):
    """The number of motions :func:`count_motions` keeps, and the counts it fitted."""
    fit, fitted = _fit_with_sharpness(sharpness, weak_at)
    found = count_motions(fit, lambda r: r, _apart(apart), max_clusters=max(sharpness))
    return len(found.thetas), fitted


def test_a_motion_is_added_while_it_raises_the_sharpness_by_the_gain():
    paid = 1 + MIN_GAIN
    assert _count({1: 1.0, 2: 0.9 * paid, 3: 9.0}) == (1, [1, 2])  # two do not pay: stop
    assert _count({1: 1.0, 2: 1.1 * paid, 3: (1.1 * paid) ** 2}) == (3, [1, 2, 3])
    assert _count({1: 1.0, 2: 1.1 * paid, 3: 1.2 * paid}) == (2, [1, 2, 3])


def test_the_sweep_stops_at_a_weak_cluster():
    doubling = {k: 2.0**k for k in range(1, 6)}
    assert _count(doubling, weak_at=3) == (2, [1, 2, 3])  # a cluster nobody picks
    assert _count(doubling, apart=0.5) == (1, [1, 2])  # two motions a voxel apart are one


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
