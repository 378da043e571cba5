"""Segmentation metrics against ground truth: matched accuracy, IoU, velocity error.

Clusters are matched one-to-one to ground-truth objects by the Hungarian algorithm on the
contingency table (events of cluster c that belong to object o), maximising the number of
correctly labelled events. Noise events (truth -1) are left out of accuracy and IoU and
reported on their own; unassigned events (prediction -1) count as wrong. A recording of
several windows is scored with one matching over all its events
(:func:`recording_metrics`), so a cluster id must name the same object in every window.
Everything
returned is a plain JSON-serialisable type; dictionary keys are strings so a JSON round
trip gives back the same dictionary.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["recording_metrics", "segmentation_metrics"]


def _labels(a: np.ndarray, name: str) -> np.ndarray:
    """A 1-D integer label vector (-1 or a non-negative id); raise a one-line error otherwise."""
    a = np.asarray(a)
    if a.ndim != 1:
        raise ValueError(f"{name} must be 1-D (one label per event), got shape {a.shape}")
    if a.dtype.kind == "f":
        if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise ValueError(f"{name} must hold integer labels, found NaN, inf or fractions")
    elif a.dtype.kind not in "iu":
        raise ValueError(f"{name} must hold integer labels, got dtype {a.dtype}")
    a = a.astype(np.int64)
    if np.any(a < -1):
        raise ValueError(f"{name} labels must be -1 or >= 0, found {int(a.min())}")
    return a


def _matching(pred: np.ndarray, truth: np.ndarray) -> tuple[dict[int, int], dict[int, int]]:
    """Hungarian matching cluster -> object maximising shared events, and those counts.

    Decision: a pair that shares no event is not a match (the assignment pads rectangular
    tables with such pairs), so an unmatched cluster or object stays unmatched.
    """
    clusters = np.unique(pred[pred >= 0])
    objects = np.unique(truth)
    if not len(clusters) or not len(objects):
        return {}, {}
    table = np.zeros((len(clusters), len(objects)), dtype=np.int64)
    both = pred >= 0
    np.add.at(
        table,
        (np.searchsorted(clusters, pred[both]), np.searchsorted(objects, truth[both])),
        1,
    )
    rows, cols = linear_sum_assignment(table, maximize=True)
    match, shared = {}, {}
    for r, c in zip(rows, cols, strict=True):
        if table[r, c] > 0:
            match[int(clusters[r])] = int(objects[c])
            shared[int(clusters[r])] = int(table[r, c])
    return match, shared


def _iou(
    pred: np.ndarray,
    truth: np.ndarray,
    objects: list[int],
    match: dict[int, int],
    shared: dict[int, int],
) -> dict[str, float]:
    """Intersection over union of each object's events with its matched cluster's (0 if
    unmatched), over the events given (the caller leaves out noise)."""
    cluster_of = {obj: cluster for cluster, obj in match.items()}
    iou = {}
    for obj in objects:
        cluster = cluster_of.get(obj)
        if cluster is None:
            iou[str(obj)] = 0.0
        else:
            union = int(np.sum((truth == obj) | (pred == cluster)))
            iou[str(obj)] = shared[cluster] / union
    return iou


def _velocities(pred_velocities: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """Predicted velocities as a finite (K, 3) array with a row for every cluster id in pred."""
    v = np.asarray(pred_velocities, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
        raise ValueError(f"pred_velocities must be a finite K x 3 array, got shape {v.shape}")
    if pred.max() >= len(v):
        raise ValueError(f"cluster {int(pred.max())} has no row in pred_velocities ({len(v)} rows)")
    return v


def _velocity_errors(
    match: dict[int, int],
    pred_velocities: np.ndarray,
    true_motions: Mapping[int, np.ndarray],
) -> dict[str, dict[str, float | int | None]]:
    """Per matched object: cluster id, |v_pred - v_true| (m/s) and that over |v_true|."""
    out: dict[str, dict[str, float | int | None]] = {}
    for cluster, obj in match.items():
        if obj not in true_motions:
            raise ValueError(f"true_motions has no velocity for object {obj}")
        truth = np.asarray(true_motions[obj], dtype=np.float64)
        if truth.shape != (3,) or not np.all(np.isfinite(truth)):
            raise ValueError(f"true motion of object {obj} must be 3 finite numbers")
        error = float(np.linalg.norm(pred_velocities[cluster] - truth))
        speed = float(np.linalg.norm(truth))
        out[str(obj)] = {
            "cluster": cluster,
            "abs": error,
            "rel": error / speed if speed > 0 else None,
        }
    return out


def _share(numerator: int, denominator: int) -> float | None:
    """``numerator / denominator`` as a float, None when nothing is counted."""
    return numerator / denominator if denominator else None


def segmentation_metrics(
    pred: np.ndarray,
    truth: np.ndarray,
    *,
    pred_velocities: np.ndarray | None = None,
    true_motions: Mapping[int, np.ndarray] | None = None,
) -> dict:
    """Compare predicted cluster labels with ground-truth object labels, event by event.

    ``pred`` (N,) cluster id or -1 (unassigned); ``truth`` (N,) object id or -1 (noise).
    Returns: ``accuracy`` (share of non-noise events whose cluster is matched to their
    object; None without non-noise events), ``iou`` per object id and ``mean_iou`` (over
    non-noise events; 0 for an unmatched object), ``unassigned_share`` (non-noise events
    with -1), ``noise_share`` and ``noise_unassigned_share`` (noise events left -1; None
    without noise), ``matching`` (cluster id -> object id), counts, and when both
    ``pred_velocities`` (K, 3, row = cluster id) and ``true_motions`` (object id -> (3,))
    are given, ``velocity_error`` per matched object and the means ``velocity_error_abs``
    and ``velocity_error_rel`` (one of them alone, e.g. no metric velocities for an
    image-plane model, skips the velocity errors).
    """
    pred = _labels(pred, "pred")
    truth = _labels(truth, "truth")
    if pred.shape != truth.shape:
        raise ValueError(f"pred has {pred.size} labels but truth has {truth.size}; give one each")
    if not pred.size:
        raise ValueError("no events to score; pred and truth are empty")
    signal = truth >= 0
    p, o = pred[signal], truth[signal]
    match, shared = _matching(p, o)
    objects = [int(x) for x in np.unique(o)]
    iou = _iou(p, o, objects, match, shared)
    noise = pred[~signal]
    result: dict = {
        "n_events": int(pred.size),
        "n_noise": int(noise.size),
        "n_objects": len(objects),
        "n_clusters": len(np.unique(p[p >= 0])),
        "accuracy": _share(sum(shared.values()), int(p.size)),
        "iou": iou,
        "mean_iou": float(np.mean(list(iou.values()))) if iou else None,
        "unassigned_share": _share(int(np.sum(p < 0)), int(p.size)),
        "noise_share": float(noise.size / pred.size),
        "noise_unassigned_share": _share(int(np.sum(noise < 0)), int(noise.size)),
        "matching": {str(c): m for c, m in sorted(match.items())},
    }
    if pred_velocities is not None and true_motions is not None:
        velocities = _velocities(pred_velocities, pred)
        errors = _velocity_errors(match, velocities, true_motions)
        rel = [e["rel"] for e in errors.values() if e["rel"] is not None]
        result["velocity_error"] = errors
        result["velocity_error_abs"] = (
            float(np.mean([e["abs"] for e in errors.values()])) if errors else None
        )
        result["velocity_error_rel"] = float(np.mean(rel)) if rel else None
    return result


def _window_velocity_errors(
    match: Mapping[int, int],
    pred: np.ndarray,
    windows: Sequence[np.ndarray],
    window_velocities: Sequence[np.ndarray],
    true_motions: Mapping[int, np.ndarray],
) -> list[float]:
    """|v - v_true| / |v_true| of every matched cluster in every window it has events in,
    its velocity taken from that window (rows of ``window_velocities[w]`` are cluster ids)."""
    errors = []
    for index, velocities in zip(windows, window_velocities, strict=True):
        v = np.asarray(velocities, dtype=np.float64)
        present = set(np.unique(pred[index][pred[index] >= 0]).tolist())
        for cluster, obj in match.items():
            truth = np.asarray(true_motions[obj], dtype=np.float64)
            speed = float(np.linalg.norm(truth))
            if cluster in present and cluster < len(v) and speed > 0:
                errors.append(float(np.linalg.norm(v[cluster] - truth)) / speed)
    return errors


def recording_metrics(
    pred: np.ndarray,
    truth: np.ndarray,
    windows: Sequence[np.ndarray],
    *,
    window_velocities: Sequence[np.ndarray] | None = None,
    true_motions: Mapping[int, np.ndarray] | None = None,
) -> dict:
    """Score a whole recording: :func:`segmentation_metrics` with one Hungarian matching
    over all its events, so a cluster id must name one object in every window (a
    segmentation whose ids swap between windows loses the swapped events).

    ``windows`` holds each window's event indices. Adds ``accuracy_per_window`` (each window
    matched on its own, events pooled: what a method scores if its ids restart per window)
    and, with ``window_velocities`` (per window, K x 3, row = cluster id) and
    ``true_motions``, ``velocity_error_rel``: the mean relative error of every matched cluster
    in every window it has events in (None when nothing is matched).
    """
    pred = _labels(pred, "pred")
    truth = _labels(truth, "truth")
    whole = segmentation_metrics(pred, truth)
    matched = signal = 0
    for index in windows:
        part_truth = truth[index]
        n = int(np.sum(part_truth >= 0))
        if n:
            matched += round(segmentation_metrics(pred[index], part_truth)["accuracy"] * n)
            signal += n
    whole["accuracy_per_window"] = _share(matched, signal)
    if window_velocities is not None and true_motions is not None:
        match = {int(c): o for c, o in whole["matching"].items()}
        errors = _window_velocity_errors(match, pred, windows, window_velocities, true_motions)
        whole["velocity_error_rel"] = float(np.mean(errors)) if errors else None
    return whole
