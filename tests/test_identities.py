"""One identity per object across windows: the boundary link and the recording's labels."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import optimizers
from spatialseg.config import conf_dir
from spatialseg.identities import boundary, link_clusters
from spatialseg.metrics import recording_metrics
from spatialseg.pipeline import segment_recording
from spatialseg.scenes import load_scene


def _blobs(centres: list[tuple[float, float]], labels: list[int], n: int = 300):
    """``n`` events per blob around each centre (2 px spread), in time order, and labels."""
    rng = np.random.default_rng(0)
    xy = np.concatenate([rng.normal(c, 2.0, (n, 2)) for c in centres])
    ids = np.repeat(labels, n)
    order = rng.permutation(len(ids))
    return xy[order], ids[order]


def test_the_first_window_s_clusters_become_objects_0_to_k():
    ids, next_id = link_clusters(None, np.zeros((5, 2)), np.zeros(5, int), 3)
    assert ids.tolist() == [0, 1, 2] and next_id == 3


def test_clusters_take_the_ids_of_the_objects_they_continue_whatever_their_order():
    xy, objects = _blobs([(20, 20), (80, 40)], [4, 7])
    edge = boundary(xy, objects, next_id=8)
    xy2, clusters = _blobs([(21, 20), (81, 41)], [1, 0])  # swapped cluster indices
    ids, next_id = link_clusters(edge, xy2, clusters, 2)
    assert ids.tolist() == [7, 4] and next_id == 8


def test_an_entering_object_gets_a_new_id_and_a_leaving_one_keeps_its_id_retired():
    xy, objects = _blobs([(20, 20), (80, 40)], [0, 1])
    edge = boundary(xy, objects, next_id=2)
    xy2, clusters = _blobs([(20, 21), (150, 90)], [0, 1])  # object 1 left, one entered
    ids, next_id = link_clusters(edge, xy2, clusters, 2)
    assert ids.tolist() == [0, 2] and next_id == 3
    edge = boundary(xy2, ids[clusters], next_id)
    xy3, clusters = _blobs([(80, 40), (150, 91)], [0, 1])  # something where 1 was: new
    ids, _ = link_clusters(edge, xy3, clusters, 2)
    assert ids.tolist() == [3, 2]


def test_a_large_cluster_keeps_its_object_s_id_against_a_few_events_on_it():
    """Votes are counted, not shared: a 30-event cluster wholly on object 0 does not take
    the id of object 0 from the cluster of thousands that continues it."""
    xy, objects = _blobs([(20, 20), (80, 40)], [0, 1])
    edge = boundary(xy, objects, next_id=2)
    xy2, clusters = _blobs([(20, 20), (80, 40)], [0, 1], n=600)
    every = np.arange(len(clusters))
    clusters[(clusters == 0) & (every % 50 == 0)] = 2  # a sliver of object 0, all on it
    clusters[(clusters == 1) & (every % 5 == 0)] = 0  # cluster 0 also holds some of 1
    ids, _ = link_clusters(edge, xy2, clusters, 3)
    assert ids[:2].tolist() == [0, 1] and ids[2] == 2


def _config(*overrides: str) -> dict:
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "+scene=interior",
                "window.events=4000",
                # the tile start separates the carts in each window (per window 0.99 at 8,
                # 15 and 30 evaluations per theta-step); from the image-flow start window 1
                # stayed mixed, and the linking of mixed windows is a guess
                "init.method=tiles",
                "clustering.max_iterations=8",
                "window.context=0",
                # interior's depth is exact; the default floor for a 10 % depth error
                # coarsens these 4,000-event windows (from the tile start 0.973 per window
                # against 0.991; from the image-flow start it was 0.77), and the linking is
                # what is tested here
                "volume.depth_error=0",
                *overrides,
            ],
        )
    return OmegaConf.to_container(cfg, resolve=True)


def test_ids_stay_stable_over_windows_when_a_window_s_clusters_come_out_permuted(monkeypatch):
    """Window 1's clusters reversed (as another start would order them) give the same
    object labels for the recording, so one matching over it scores what each window does."""
    import spatialseg.pipeline as pipeline

    cfg = _config()
    rec = load_scene(cfg["scene"], seed=0, window_events=4000, windows=3)
    plain = segment_recording(rec, cfg, optimizers.create("ssa_ga"), seed=0)
    original, calls = pipeline.segment_window, []

    def reversed_in_window_1(*args, **kwargs):
        res = original(*args, **kwargs)
        calls.append(res)
        if len(calls) != 2:
            return res
        c = res.clustering
        flipped = replace(c, thetas=c.thetas[::-1], probabilities=c.probabilities[:, ::-1])
        labels = np.where(res.labels >= 0, 1 - res.labels, -1)
        return replace(
            res, labels=labels, probabilities=res.probabilities[:, ::-1], clustering=flipped
        )

    monkeypatch.setattr(pipeline, "segment_window", reversed_in_window_1)
    permuted = segment_recording(rec, cfg, optimizers.create("ssa_ga"), seed=0)
    np.testing.assert_array_equal(permuted.labels, plain.labels)
    assert permuted.windows[1].ids.tolist() == plain.windows[1].ids[::-1].tolist()
    scores = recording_metrics(permuted.labels, rec.ground_truth.labels, permuted.indices)
    assert scores["accuracy_per_window"] >= 0.95  # each window separates the carts
    assert scores["accuracy"] >= scores["accuracy_per_window"] - 0.01  # with one id each
    assert permuted.probabilities.shape == (len(rec.events), permuted.n_objects)
    labelled = permuted.labels >= 0
    best = permuted.probabilities[labelled].argmax(axis=1)
    assert np.mean(best == permuted.labels[labelled]) > 0.8  # smoothed: 0.99; columns swapped: few
