"""Segmentation metrics on hand-made label vectors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spatialseg.metrics import recording_metrics, segmentation_metrics

TRUTH = np.array([0, 0, 0, 0, 1, 1, 1, 2, 2, 2])


def test_perfect_segmentation():
    m = segmentation_metrics(TRUTH, TRUTH)
    assert m["accuracy"] == 1.0 and m["mean_iou"] == 1.0
    assert m["matching"] == {"0": 0, "1": 1, "2": 2}
    assert m["unassigned_share"] == 0.0 and m["noise_unassigned_share"] is None
    assert (m["n_events"], m["n_noise"], m["n_objects"], m["n_clusters"]) == (10, 0, 3, 3)


def test_permuted_cluster_ids_are_matched():
    pred = np.array([5, 5, 5, 5, 0, 0, 0, 3, 3, 3])
    m = segmentation_metrics(pred, TRUTH)
    assert m["accuracy"] == 1.0
    assert m["matching"] == {"0": 1, "3": 2, "5": 0}
    assert m["iou"] == {"0": 1.0, "1": 1.0, "2": 1.0}


def test_partial_segmentation():
    pred = np.array([1, 1, 1, 0, 0, 0, 1, 2, 2, 0])
    # table (cluster x object): c0: o0 1, o1 2, o2 1; c1: o0 3, o1 1; c2: o2 2
    # best matching c1->o0 (3), c0->o1 (2), c2->o2 (2): 7 of 10 correct
    m = segmentation_metrics(pred, TRUTH)
    assert m["matching"] == {"0": 1, "1": 0, "2": 2}
    assert m["accuracy"] == pytest.approx(0.7)
    # IoU o0 with c1: 3 / |{0,1,2,3,6}| = 3/5; o1 with c0: 2 / |{3,4,5,6,9}| = 2/5; o2 with c2: 2/3
    assert m["iou"] == pytest.approx({"0": 0.6, "1": 0.4, "2": 2 / 3})
    assert m["mean_iou"] == pytest.approx((0.6 + 0.4 + 2 / 3) / 3)


def test_noise_is_excluded_from_accuracy_and_reported_apart():
    truth = np.array([0, 0, 1, 1, -1, -1, -1, -1])
    pred = np.array([0, 0, 1, 1, 0, -1, -1, 1])
    m = segmentation_metrics(pred, truth)
    assert m["accuracy"] == 1.0 and m["mean_iou"] == 1.0
    assert m["n_noise"] == 4 and m["noise_share"] == 0.5
    assert m["noise_unassigned_share"] == 0.5


def test_unassigned_predictions_count_as_wrong():
    pred = np.array([0, 0, -1, -1, 1, 1, 1, 2, 2, -1])
    m = segmentation_metrics(pred, TRUTH)
    assert m["accuracy"] == pytest.approx(0.7)
    assert m["unassigned_share"] == pytest.approx(0.3)
    assert m["iou"]["0"] == pytest.approx(0.5)
    assert m["iou"]["2"] == pytest.approx(2 / 3)


def test_more_clusters_than_objects():
    pred = np.array([0, 0, 3, 3, 1, 1, 1, 2, 2, 2])  # object 0 split over clusters 0 and 3
    m = segmentation_metrics(pred, TRUTH)
    assert m["n_clusters"] == 4 and len(m["matching"]) == 3
    assert m["accuracy"] == pytest.approx(0.8)
    assert m["iou"]["0"] == pytest.approx(0.5)


def test_fewer_clusters_than_objects():
    pred = np.array([0, 0, 0, 0, 1, 1, 1, 1, 1, 1])  # objects 1 and 2 merged into cluster 1
    m = segmentation_metrics(pred, TRUTH)
    assert len(m["matching"]) == 2 and m["matching"]["0"] == 0
    assert m["accuracy"] == pytest.approx(0.7)
    unmatched = {"1", "2"} - {str(o) for o in m["matching"].values()}
    assert [m["iou"][o] for o in unmatched] == [0.0]


def test_no_overlap_is_no_match_and_all_noise_has_no_accuracy():
    m = segmentation_metrics(np.array([-1, -1, 0]), np.array([0, 0, -1]))
    assert m["matching"] == {} and m["accuracy"] == 0.0 and m["iou"] == {"0": 0.0}
    only_noise = segmentation_metrics(np.array([0, -1]), np.array([-1, -1]))
    assert only_noise["accuracy"] is None and only_noise["mean_iou"] is None


def test_velocity_errors_of_matched_clusters():
    pred = np.array([1, 1, 1, 1, 0, 0, 0, 2, 2, 2])
    velocities = np.array([[0.0, 1.0, 0.0], [3.0, 4.0, 0.0], [9.0, 9.0, 9.0]])
    motions = {0: np.array([3.0, 0.0, 0.0]), 1: np.array([0.0, 2.0, 0.0]), 2: np.zeros(3)}
    m = segmentation_metrics(pred, TRUTH, pred_velocities=velocities, true_motions=motions)
    err = m["velocity_error"]
    assert err["0"] == {"cluster": 1, "abs": 4.0, "rel": pytest.approx(4.0 / 3.0)}
    assert err["1"] == {"cluster": 0, "abs": 1.0, "rel": 0.5}
    assert err["2"]["abs"] == pytest.approx(np.sqrt(243.0)) and err["2"]["rel"] is None
    assert m["velocity_error_abs"] == pytest.approx((4.0 + 1.0 + np.sqrt(243.0)) / 3)
    assert m["velocity_error_rel"] == pytest.approx((4.0 / 3.0 + 0.5) / 2)


def test_velocity_errors_need_both_velocities_and_motions():
    m = segmentation_metrics(TRUTH, TRUTH, true_motions={0: np.zeros(3)})
    assert "velocity_error" not in m and m["accuracy"] == 1.0


def test_result_survives_a_json_round_trip():
    pred = np.array([1, 1, 1, 0, 0, 0, 1, 2, 2, -1])
    truth = TRUTH.copy()
    truth[0] = -1
    m = segmentation_metrics(
        pred,
        truth,
        pred_velocities=np.ones((3, 3)),
        true_motions={k: np.full(3, 2.0) for k in range(3)},
    )
    assert json.loads(json.dumps(m)) == m


def test_bad_input_raises_clear_errors():
    cases = [
        ((np.array([0, 1]), np.array([0])), {}, "2 labels but truth has 1"),
        ((np.array([0.0, np.nan]), np.array([0, 1])), {}, "integer labels"),
        ((np.array([0, -2]), np.array([0, 1])), {}, "-1 or >= 0"),
        ((np.zeros((2, 2), int), np.zeros((2, 2), int)), {}, "1-D"),
        ((np.array([], int), np.array([], int)), {}, "empty"),
        (
            (TRUTH, TRUTH),
            {"pred_velocities": np.zeros((2, 3)), "true_motions": {0: np.zeros(3)}},
            "cluster 2 has no row",
        ),
        (
            (TRUTH, TRUTH),
            {"pred_velocities": np.zeros((3, 3)), "true_motions": {0: np.zeros(3)}},
            "no velocity for object 1",
        ),
    ]
    for args, kwargs, message in cases:
        with pytest.raises(ValueError, match=message):
            segmentation_metrics(*args, **kwargs)


def test_one_matching_over_the_recording_counts_ids_swapped_between_windows():
    """Each window perfect on its own, but window 2's ids swapped: one matching over the
    whole recording loses window 2's events, the per-window matching does not."""
    truth = np.array([1, 1, 2, 2, 1, 1, 2, 2])
    pred = np.array([0, 0, 1, 1, 1, 1, 0, 0])
    windows = [np.arange(4), np.arange(4, 8)]
    m = recording_metrics(pred, truth, windows)
    assert m["accuracy"] == 0.5 and m["accuracy_per_window"] == 1.0
    consistent = recording_metrics(np.array([0, 0, 1, 1, 0, 0, 1, 1]), truth, windows)
    assert consistent["accuracy"] == consistent["accuracy_per_window"] == 1.0


def test_recording_velocity_error_takes_each_window_s_own_velocity():
    truth = np.array([1, 1, 2, 2, 1, 1, 2, 2])
    windows = [np.arange(4), np.arange(4, 8)]
    motions = {1: np.array([1.0, 0, 0]), 2: np.array([0.0, 2, 0])}
    velocities = [np.array([[1.0, 0, 0], [0, 2, 0]]), np.array([[1.5, 0, 0], [0, 2, 0]])]
    m = recording_metrics(
        np.array([0, 0, 1, 1, 0, 0, 1, 1]),
        truth,
        windows,
        window_velocities=velocities,
        true_motions=motions,
    )
    assert m["velocity_error_rel"] == pytest.approx(0.5 / 4)  # one of four pairs off by 50 %
    assert "velocity_error_rel" not in recording_metrics(truth - 1, truth, windows)
