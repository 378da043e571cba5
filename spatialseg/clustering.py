"""Iterative clustering (the paper's Algorithm 1): alternate a theta-step and a P-step.

theta-step, memberships P fixed: each cluster's velocity maximises the contrast of its own
volume of warped events (with P fixed the clusters do not interact, so the joint objective
splits into one small problem per cluster), solved by the configured optimiser starting at
the current velocity. P-step, velocities fixed (Eq. 26): ``p_kj = c_j(x'_kj) / sum_i c_i(x'_ki)``
with ``c_j`` the cluster's volume sampled at the event's warped position.

Once ``patience`` theta-steps in a row have moved no velocity, the loop runs P-steps only
(ours): the optimiser searches from the current velocity and keeps it unless a better one
turns up; on four dev recordings of the yardstick 4 of 1,009 theta-steps after the second
moved a velocity, at half a 15,000-event window's time (docs/method.md, "Iterative
clustering").

Converged (the paper's three rules, all configurable) when the total contrast is flat
(relative change below ``tol`` for ``patience`` iterations), reaches ``target``, or the
iteration limit is hit; and (a fourth rule, ours) when fewer than ``label_tol`` of the
events change their most likely cluster for ``patience`` iterations.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol, TypeVar

import numba
import numpy as np
from numba import njit
from scipy.spatial import cKDTree

__all__ = [
    "MIN_GAIN",
    "MIN_SHARE",
    "ClusterEvaluator",
    "ClusteringResult",
    "ConvergenceRules",
    "IterationRecord",
    "StepStage",
    "cluster_responses",
    "count_motions",
    "initial_memberships",
    "iterative_clustering",
    "maximize_contrast",
    "p_step",
    "p_step_from_every_event",
    "repaired_memberships",
    "squarem_step",
    "update_memberships",
    "weak_cluster",
]

log = logging.getLogger(__name__)


class ClusterEvaluator(Protocol):
    """What the loop needs from an objective over one cluster's warped events."""

    dim: int
    n_events: int
    #: Its event order: weights and responses ``ordered`` list input event ``order[i]`` i-th.
    order: np.ndarray

    def set_weights(self, weights: np.ndarray, *, ordered: bool = False) -> None: ...
    def value(self, theta: np.ndarray) -> float: ...
    def grad(self, theta: np.ndarray) -> np.ndarray: ...
    def batch_value(self, thetas: np.ndarray) -> np.ndarray: ...
    def p_step(
        self,
        theta: np.ndarray,
        sigma: float | Sequence[float],
        stride: int = 1,
        *,
        ordered: bool = False,
    ) -> tuple[np.ndarray, float]: ...


class Maximizer(Protocol):
    """The optimiser interface of the ``optimizers`` package."""

    def maximize(self, fun, bounds, x0=None, grad=None, max_evals=2000, seed=0, **kwargs): ...


@dataclass(frozen=True)
class ConvergenceRules:
    """The paper's three stopping rules, and stable labels (``label_tol``, None: off).

    Decision: the total contrast keeps rising while the memberships harden, even with the
    velocities fixed, so the paper's flat-contrast rule rarely fires and the loop ran to its
    limit; the share of events whose most likely cluster changes measures the segmentation
    itself (docs/performance.md).
    """

    max_iterations: int
    tol: float
    patience: int
    target: float | None = None
    label_tol: float | None = None

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or self.patience < 1 or self.tol < 0:
            raise ValueError(
                "clustering.max_iterations and clustering.patience must be >= 1 and "
                "clustering.tol >= 0"
            )
        if self.label_tol is not None and not 0 <= self.label_tol < 1:
            raise ValueError(
                f"clustering.label_tol must be in [0, 1) or null, got {self.label_tol}"
            )


@dataclass(frozen=True)
class IterationRecord:
    """One outer iteration: contrast per cluster after the theta-step, and the velocities."""

    iteration: int
    per_cluster: np.ndarray
    thetas: np.ndarray
    n_evals: int
    seconds: float
    labels_changed: float = float("nan")  # share of events whose most likely cluster changed

    @property
    def total(self) -> float:
        """Sum of the clusters' contrasts (the joint objective)."""
        return float(np.sum(self.per_cluster))


@dataclass(frozen=True)
class ClusteringResult:
    """Final velocities, memberships and the full per-iteration history."""

    thetas: np.ndarray
    probabilities: np.ndarray
    values: np.ndarray
    history: list[IterationRecord] = field(default_factory=list)
    converged: bool = False
    reason: str = ""

    @property
    def iterations(self) -> int:
        """Number of outer iterations run."""
        return len(self.history)

    @property
    def total(self) -> float:
        """The joint objective at the end: the sum of the clusters' contrasts."""
        return float(np.sum(self.values))

    @property
    def sharpness(self) -> float:
        """The clusters' contrasts per squared membership mass, averaged over the events
        (``sum_j values_j / (N mass_j)``): unchanged when a cluster splits into two alike
        halves of one motion, so it compares segmentations with different numbers of
        clusters, where the sum of contrasts (quadratic in the mass) favours fewer."""
        mass = self.probabilities.sum(axis=0)
        used = mass > 0
        n = max(len(self.probabilities), 1)
        return float(np.sum(self.values[used] / mass[used]) / n)


def update_memberships(responses: np.ndarray) -> np.ndarray:
    """Eq. 26: normalise each event's per-cluster responses to probabilities.

    Negative responses count 0; events no cluster responds to (all responses zero, e.g.
    warped outside every volume) get uniform memberships rather than a division by zero.
    """
    return _normalised_rows(np.ascontiguousarray(responses, dtype=np.float64))


@njit(cache=True)
def _normalised_rows(responses: np.ndarray) -> np.ndarray:
    """Each row of ``responses`` (N x K), its negative entries taken as 0, divided by its
    sum (added in column order), or ``1 / K`` throughout where that sum is not positive.

    Decision: one pass per event in a kernel: the loop normalises every iteration, and in
    numpy the temporaries of its four steps cost 0.35 ms on 15,000 events, this 0.04 ms (the
    same numbers for up to 7 clusters; beyond, numpy's sum pairs the terms differently)."""
    n, k = responses.shape
    p = np.empty((n, k))
    for i in range(n):
        total = 0.0
        for j in range(k):
            r = responses[i, j]
            total += 0.0 if r < 0.0 else r
        for j in range(k):
            r = responses[i, j]
            p[i, j] = (0.0 if r < 0.0 else r) / total if total > 0.0 else 1.0 / k
    return p


def initial_memberships(
    points: np.ndarray,
    scale: np.ndarray,
    labels: np.ndarray,
    k: int,
    *,
    mode: str,
    confidence: float,
) -> np.ndarray:
    """Starting memberships P (M x K): ``uniform`` (the paper's 1/K) or ``flow``.

    Decision: with uniform memberships every cluster sees the same objective in the first
    theta-step, so a global optimiser sends all of them to the same (strongest) motion and
    the P-step can never separate them. ``flow`` breaks the symmetry with the initial flow
    clustering: each event takes its own label, or without one that of its nearest (in
    voxels) event with a valid flow, held with probability ``confidence``, the rest shared
    by the other clusters.
    """
    m = points.shape[0]
    uniform = np.full((m, k), 1.0 / k)
    if mode == "uniform":
        return uniform
    if mode != "flow":
        raise ValueError(f"clustering.init_memberships must be 'uniform' or 'flow', got {mode!r}")
    if k == 1:
        return uniform
    if not 1.0 / k <= confidence <= 1.0:
        raise ValueError(f"clustering.init_confidence must be in [1/K, 1], got {confidence}")
    known = labels >= 0
    if not known.any():
        return uniform
    nearest = labels.copy()
    if not known.all():
        tree = cKDTree(points[known] / scale)
        found = tree.query(points[~known] / scale, workers=numba.get_num_threads())[1]
        nearest[~known] = labels[known][found]
    p = np.full((m, k), (1.0 - confidence) / (k - 1))
    p[np.arange(m), nearest] = confidence
    return p


def _stop_reason(history: list[IterationRecord], rules: ConvergenceRules) -> str:
    """Which rule (if any) says the loop has converged, as a short phrase."""
    totals = [r.total for r in history]
    if rules.target is not None and totals[-1] >= rules.target:
        return f"total contrast reached the target {rules.target:g}"
    if rules.label_tol is not None and len(history) > rules.patience:
        changed = [r.labels_changed for r in history[-rules.patience :]]
        if all(c < rules.label_tol for c in changed):
            return f"labels changed < {rules.label_tol:g} for {rules.patience} iterations"
    if len(totals) > rules.patience:
        recent = np.asarray(totals[-rules.patience - 1 :])
        change = np.abs(np.diff(recent)) / np.maximum(np.abs(recent[1:]), 1e-300)
        if np.all(change < rules.tol):
            return f"total contrast changed < {rules.tol:g} for {rules.patience} iterations"
    return ""


def maximize_contrast(
    evaluator: ClusterEvaluator,
    optimizer: Maximizer,
    theta: np.ndarray,
    bounds: np.ndarray,
    budget: int,
    seed: int,
) -> tuple[np.ndarray, int]:
    """Maximise one objective's contrast from ``theta`` (clipped into ``bounds``) with the
    analytic gradient and batched evaluation; return the best velocity and the evaluations
    spent (the theta-step of one cluster)."""
    x0 = np.clip(theta, bounds[:, 0], bounds[:, 1])
    res = optimizer.maximize(
        evaluator.value,
        bounds,
        x0=x0,
        grad=evaluator.grad,
        max_evals=budget,
        seed=seed,
        batch_fun=evaluator.batch_value,
    )
    return np.asarray(res.x, dtype=np.float64), int(res.n_evals)


@dataclass(frozen=True)
class StepStage:
    """Each cluster's theta-step: ``optimizer`` with ``budget`` evaluations on
    ``evaluator``, whose events are ``subset`` of the P-step's (every one: ``slice(None)``)."""

    evaluator: ClusterEvaluator
    optimizer: Maximizer
    budget: int
    subset: np.ndarray | slice = field(default_factory=lambda: slice(None))


def p_step(
    evaluator: ClusterEvaluator,
    thetas: np.ndarray,
    p: np.ndarray,
    sigma: float | Sequence[float],
    stride: int,
    prior_weight: np.ndarray | None = None,
) -> np.ndarray:
    """One P-step (Eq. 26) outside the loop: the memberships the volumes of ``thetas``,
    weighted by ``p`` and smoothed by ``sigma`` voxels, give each event (N x K).

    ``prior_weight`` (N,) in [0, 1]: each event's responses are multiplied by the clusters'
    shares (mean memberships) raised to it, a prior on the cluster sizes where the warps
    say little (0 or None: none, the paper's P-step)."""
    responses = cluster_responses(evaluator, thetas, p, sigma, stride)[0]
    if prior_weight is not None:
        weight = np.asarray(prior_weight, dtype=np.float64)
        if weight.shape != (len(p),) or not np.all((weight >= 0) & (weight <= 1)):
            raise ValueError(f"prior_weight must be {len(p)} numbers in [0, 1]")
        responses = responses * p.mean(axis=0)[None, :] ** weight[:, None]
    return update_memberships(responses)


def p_step_from_every_event(
    evaluator: ClusterEvaluator,
    thetas: np.ndarray,
    sigma: float | Sequence[float],
    stride: int,
) -> np.ndarray:
    """One P-step at ``thetas`` with every event voting equally into every motion's volume
    (N x K): the memberships the motions alone give, whatever earlier memberships were."""
    uniform = np.full((evaluator.n_events, len(thetas)), 1.0 / len(thetas))
    return p_step(evaluator, thetas, uniform, sigma, stride)


#: The repair's weighted P-steps stop once under this share of the events changes cluster.
REPAIR_LABEL_TOL = 0.005


def repaired_memberships(
    evaluator: ClusterEvaluator,
    thetas: np.ndarray,
    sigma: float | Sequence[float],
    max_steps: int,
) -> np.ndarray:
    """Memberships (N x K) at ``thetas`` rebuilt without the loop's: one P-step with every
    event voting into every motion's volume, then P-steps weighted by their own memberships
    until under :data:`REPAIR_LABEL_TOL` of the events change cluster (at most
    ``max_steps``).

    Decision: a P-step weighted by the memberships is a fixed point for a cluster that has
    none: its volume is empty, so it never takes back the events its motion sharpens (dev
    ``same_direction`` seed 3: the second object's velocity found, none of its events).
    With every event in every volume each motion gets the events it sharpens; alone, those
    memberships are soft and sweep short windows to one cluster, so the weighted steps then
    harden them (docs/method.md, "Relabelling")."""
    p = p_step_from_every_event(evaluator, thetas, sigma, 1)
    labels = p.argmax(axis=1)
    for _ in range(max_steps):
        p = p_step(evaluator, thetas, p, sigma, 1)
        previous, labels = labels, p.argmax(axis=1)
        if np.mean(labels != previous) < REPAIR_LABEL_TOL:
            break
    return p


def cluster_responses(
    evaluator: ClusterEvaluator,
    thetas: np.ndarray,
    p: np.ndarray,
    sigma: float | Sequence[float],
    stride: int,
    *,
    ordered: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """``c_j(x'_kj)``: each cluster's (smoothed) volume sampled at its warped events (N x K),
    and each cluster's contrast over all events (K,), from the same votes; memberships and
    responses in the evaluator's :attr:`~ClusterEvaluator.order` if ``ordered``."""
    responses = np.empty_like(p)
    values = np.empty(len(thetas))
    for j, theta in enumerate(thetas):
        evaluator.set_weights(p[:, j], ordered=ordered)
        responses[:, j], values[j] = evaluator.p_step(theta, sigma, stride, ordered=ordered)
    return responses, values


def _step_rows(step: StepStage, order: np.ndarray) -> np.ndarray:
    """The rows of memberships held in ``order`` (the P-step evaluator's) that the
    theta-step's evaluator takes, in its own order."""
    position = np.empty_like(order)
    position[order] = np.arange(len(order))
    return position[np.arange(len(order))[step.subset]][step.evaluator.order]


def _theta_step(
    step: StepStage,
    rows: np.ndarray,
    thetas: np.ndarray,
    p: np.ndarray,
    bounds: np.ndarray,
    seeds: np.ndarray,
) -> int:
    """Each cluster's velocity (rows of ``thetas``, in place) maximised on its weighted events
    (``p``'s ``rows``: :func:`_step_rows`), one optimiser seed each; return the evaluations
    spent."""
    evals = 0
    for j in range(len(thetas)):
        step.evaluator.set_weights(p[rows, j], ordered=True)
        thetas[j], n = maximize_contrast(
            step.evaluator, step.optimizer, thetas[j], bounds, step.budget, int(seeds[j])
        )
        evals += n
    return evals


def iterative_clustering(
    evaluator: ClusterEvaluator,
    optimizer: Maximizer,
    init_thetas: np.ndarray,
    init_p: np.ndarray,
    bounds: np.ndarray,
    *,
    rules: ConvergenceRules,
    evals_per_step: int,
    p_step_sigma: float | Sequence[float],
    seed: int,
    p_step_stride: int = 1,
    on_iteration: Callable[[IterationRecord], None] | None = None,
    step: StepStage | None = None,
) -> ClusteringResult:
    """Run Algorithm 1 from velocities ``init_thetas`` (K x dim) and memberships ``init_p``.

    ``bounds`` (dim x 2) is the search box for every velocity. The optimiser seed of each
    theta-step derives from ``seed`` so the whole loop is deterministic. ``p_step_sigma``
    (voxels, 0 = off; one number, or one per axis x, y, depth) smooths each volume before
    the P-step samples it, so an event's response reflects its neighbourhood rather than
    the texture of a single voxel;
    ``p_step_stride`` does so on a grid that many times coarser in x and y (same total blur).
    ``step`` replaces the theta-step (``optimizer`` with ``evals_per_step`` on
    ``evaluator``), e.g. to optimise on a subset of the events; the P-step and the recorded
    contrasts always use ``evaluator``, every event. After ``rules.patience`` theta-steps in
    a row that moved no velocity the velocities stay fixed and each iteration is a P-step;
    every second such P-step is extrapolated (:func:`squarem_step`).

    Decision: at fixed velocities the P-steps are a fixed-point iteration that hardens the
    memberships slowly (the total contrast still rose by 0.5 % a step at the twentieth),
    and the hardening carries the accuracy: 10 plain iterations lost 0.013 on the dev
    split, 40 gained 0.003. SQUAREM, the standard accelerator of EM's fixed points, gets
    further in 10 iterations than 20 plain ones: 0.903 -> 0.914 in 0.74x the time
    (docs/performance.md, session 57).
    """
    step = step or StepStage(evaluator, optimizer, evals_per_step)
    thetas = np.array(init_thetas, dtype=np.float64, copy=True)
    k = thetas.shape[0]
    if k < 1:
        raise ValueError("n_clusters must be >= 1")
    seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=(rules.max_iterations, k))
    n_events = evaluator.n_events
    p = np.asarray(init_p, dtype=np.float64)
    if p.shape != (n_events, k):
        raise ValueError(f"initial memberships have shape {p.shape}, expected {(n_events, k)}")
    order = evaluator.order
    p = p[order]  # the loop's memberships in the evaluator's order: no gather, no scatter
    rows = _step_rows(step, order)
    values = np.zeros(k)
    history: list[IterationRecord] = []
    labels = p.argmax(axis=1)
    reason = ""
    still = 0  # theta-steps in a row that moved no velocity
    steps: list[np.ndarray] = []  # the memberships two P-steps at fixed velocities began from
    for it in range(rules.max_iterations):
        start = time.perf_counter()
        evals = 0
        if still < rules.patience:
            before = thetas.copy()
            evals = _theta_step(step, rows, thetas, p, bounds, seeds[it])
            still = still + 1 if np.array_equal(thetas, before) else 0
        responses, values = cluster_responses(
            evaluator, thetas, p, p_step_sigma, p_step_stride, ordered=True
        )
        if still >= rules.patience and evals == 0:  # a P-step at velocities fixed for good
            steps.append(p)
        p = update_memberships(responses)
        if len(steps) == 2:
            p = squarem_step(steps[0], steps[1], p)
            steps = []
        previous, labels = labels, p.argmax(axis=1)
        changed = float(np.mean(labels != previous)) if n_events else 0.0
        elapsed = time.perf_counter() - start
        record = IterationRecord(it + 1, values.copy(), thetas.copy(), evals, elapsed, changed)
        history.append(record)
        if on_iteration is not None:
            on_iteration(record)
        reason = _stop_reason(history, rules)
        if reason:
            break
    converged = bool(reason)
    if not converged:
        reason = f"iteration limit {rules.max_iterations} reached"
    memberships = np.empty_like(p)
    memberships[order] = p
    return ClusteringResult(thetas, memberships, values.copy(), history, converged, reason)


def squarem_step(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """The memberships (N x K) that SQUAREM extrapolates from two steps ``p0 -> p1 -> p2``
    of a fixed-point iteration (Varadhan and Roland, 2008, scheme S3: step length
    ``|r| / |v|``, at least 1), each row floored at 1e-12 and normalised back onto the
    simplex; ``p2`` when the two steps are equal."""
    r = p1 - p0
    v = p2 - p1 - r
    curvature = _norm(v)
    if curvature == 0.0:
        return p2
    alpha = min(-_norm(r) / curvature, -1.0)
    q = p0 - 2.0 * alpha * r + alpha * alpha * v
    np.clip(q, 1e-12, 1.0, out=q)
    return q / q.sum(axis=1, keepdims=True)


def _norm(a: np.ndarray) -> float:
    """The Euclidean norm of all of ``a``'s entries, summed by numpy, not BLAS: the same
    to the bit whatever BLAS's thread count (``np.linalg.norm``'s dot product was not, and
    the step length passes the difference on)."""
    return float(np.sqrt(np.sum(a * a)))


#: A cluster that is the likeliest for under this share of the events is empty (mean
#: memberships hide a collapse: an empty cluster keeps a few percent of every event's).
MIN_SHARE = 0.01


def weak_cluster(
    thetas: np.ndarray,
    p: np.ndarray,
    separation: Callable[[np.ndarray, np.ndarray], float],
    min_share: float = MIN_SHARE,
) -> int | None:
    """A cluster that wastes its slot: the smaller of two whose motions coincide (they move
    the events less than a voxel apart, ``separation(a, b)`` in voxels), else one that is
    the likeliest for under ``min_share`` of the events; None if none."""
    shares = np.bincount(p.argmax(axis=1), minlength=p.shape[1]) / max(len(p), 1)
    for j in range(len(thetas)):
        for k in range(j + 1, len(thetas)):
            if separation(thetas[j], thetas[k]) < 1.0:
                return j if shares[j] < shares[k] else k
    smallest = int(np.argmin(shares))
    return smallest if shares[smallest] < min_share else None


#: One motion more must raise the sharpness by this share (5 % until session 24 over-segmented
#: nearly every scene; 25 % lowered the dev split's accuracy in session 36: docs/results.md).
MIN_GAIN = 0.40

#: What :func:`count_motions` fits: a window's segmentation with a given number of motions.
Fitted = TypeVar("Fitted")


def count_motions(
    fit: Callable[[int], Fitted],
    clustering_of: Callable[[Fitted], ClusteringResult],
    separation: Callable[[np.ndarray, np.ndarray], float],
    *,
    max_clusters: int,
    min_gain: float = MIN_GAIN,
) -> Fitted:
    """The number of motions from the data: the window fitted with 1, 2, ... motions
    (``fit(k)``, from every start), one more kept while it raises the sharpness
    (:attr:`ClusteringResult.sharpness`) by at least ``min_gain`` and leaves no cluster
    weak (:func:`weak_cluster`); at most ``max_clusters``.

    Decision: the sum of contrasts is quadratic in each cluster's mass, so it falls when
    one motion's events are split in two; the sharpness does not change then, and rises by
    the share of events one more motion brings into focus, so its gain is the label cost
    of a motion, relative and without a scale. Each count is fitted from the starts, as a
    fixed number is: growing one fit motion by motion (until session 36) kept the first
    motion's compromise between objects, often a spurious motion in depth, and added
    clusters around it (docs/method.md, "The number of motions")."""
    kept = fit(1)
    for k in range(2, max_clusters + 1):
        more = fit(k)
        fewer_result, more_result = clustering_of(kept), clustering_of(more)
        gain = (more_result.sharpness - fewer_result.sharpness) / max(
            abs(fewer_result.sharpness), 1e-300
        )
        wasted = weak_cluster(more_result.thetas, more_result.probabilities, separation)
        log.info(
            "%d motions: sharpness %.6g -> %.6g (%+.1f %%)%s",
            k,
            fewer_result.sharpness,
            more_result.sharpness,
            100 * gain,
            "" if wasted is None else f", cluster {wasted} weak",
        )
        if gain < min_gain or wasted is not None:
            break
        kept = more
    return kept
