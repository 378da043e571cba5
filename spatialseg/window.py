"""Clustering one window: its starts, Algorithm 1 from each, the refit and the labels.

A window (a :class:`~spatialseg.recording.Recording` of two depth maps, or more with its
context) and the run's settings in; a :class:`WindowResult` out: a label (N,) and
memberships (N x K) per event, the clustering (K velocities, history) and its timings.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

import optimizers
from spatialseg import motion_init, mrf
from spatialseg.clustering import (
    ClusteringResult,
    ConvergenceRules,
    IterationRecord,
    StepStage,
    count_motions,
    initial_memberships,
    iterative_clustering,
    maximize_contrast,
    p_step,
    repaired_memberships,
    update_memberships,
    weak_cluster,
)
from spatialseg.depth import make_depth_source
from spatialseg.neighbours import grid_order
from spatialseg.points import (
    ModelEvaluator,
    Prepared,
    image_jacobian,
    off_edge_events,
    p_step_settings,
    prepare,
    reference_time,
    relabel_sigmas,
    search_bounds,
    seeded_subset,
    spatial_velocities,
    voxel_shifts,
    window_objective,
)
from spatialseg.recording import Camera, Recording
from spatialseg.settings import ClusteringSettings, Settings, settings_from
from spatialseg.starts import (
    PLANAR,
    PREVIOUS,
    init_candidates,
    initialise,
    previous_init,
)

__all__ = [
    "BOX_FACE",
    "FEW_EVENTS_PER_CLUSTER",
    "MIN_EVENTS_PER_CLUSTER",
    "WindowResult",
    "assign_labels",
    "check_config",
    "check_events_per_cluster",
    "label_rest",
    "motion_separation",
    "nearest_memberships",
    "prior_weights",
    "refit_velocities",
    "segment_window",
    "widened_box",
]

# The per-iteration, per-start and too-few-events lines stay on the logger they always had:
# Hydra prints its name, and hydra.verbose=spatialseg.pipeline shows the DEBUG ones (README).
log = logging.getLogger("spatialseg.pipeline")


#: Fewest usable events per cluster a window is segmented with: a cluster's velocity is
#: three numbers fitted to the sharpness of its events' warped volume, and under about three
#: events per number any velocity stacks them in as few voxels, so the fit is noise.
MIN_EVENTS_PER_CLUSTER = 10

#: Fewer usable events per cluster than this are segmented with a warning. Measured on
#: ``interior`` (one window, two clusters, context 0, seeds 0-5): about 27 and 140 usable
#: events per cluster gave a median accuracy of 0.70, 370 gave 0.96, 800 0.91
#: and 1,700 0.98; a window's usable events are its events with depth that the
#: background-activity filter supports (55-85 % of them there).
FEW_EVENTS_PER_CLUSTER = 200

#: A velocity within this share of the search box's half-width from its face presses on
#: it (:func:`widened_box`); the optimisers clip to the face, so a clipped motion sits on it.
BOX_FACE = 0.02


@dataclass(frozen=True, eq=False)
class WindowResult:
    """The segmentation of one window: labels and probabilities cover its own events; the
    clustering, ``prepared`` and ``t_ref`` describe the span it was clustered on (the
    window with its ``window.context`` neighbours; the window alone by default)."""

    labels: np.ndarray
    probabilities: np.ndarray
    clustering: ClusteringResult
    prepared: Prepared
    t_ref: float
    timings: dict[str, float]
    init_fallback: bool
    init_method: str = ""  # the start kept (init.method, or the one init.method=auto chose)
    ids: np.ndarray | None = None  # the object id of each cluster (segment_recording links)
    #: Each start's total contrast at the end of its loop, with the number of motions kept
    #: (the judge of ``init.method=auto``; before the search box grows and the refit).
    start_totals: dict[str, float] = field(default_factory=dict)


#: One start's loop: its result, its start and the start's name.
Run = tuple[ClusteringResult, motion_init.InitResult, str]

#: Another start replaces the ``previous`` one only when its total contrast is more than
#: this share above it. Chosen on the dev split (0.02-0.2 screened on every start's logged
#: loop, 0.05 run): loops from different starts that end in the same partition differ in
#: total by 9 % (median; docs/results.md, session 60).
PREVIOUS_MARGIN = 0.05


def kept_run(runs: list[Run]) -> Run:
    """The run a window keeps: the highest total contrast, but the ``previous`` start's
    (the window before's motions) as long as no other is more than
    :data:`PREVIOUS_MARGIN` above it.

    Decision: loops from different starts that end in the same partition differ in total
    by several per cent, with a bias of their own (the flow start's 9-14 % below the
    others'), so where totals are close the highest wins by chance; the window before's
    motions are the likeliest to hold then (an object keeps its motion from one window to
    the next), so they stay unless the evidence against them is larger than that noise."""
    best = max(runs, key=lambda run: run[0].total)
    previous = next((run for run in runs if run[2] == PREVIOUS), None)
    if previous is not None and best[0].total <= (1 + PREVIOUS_MARGIN) * previous[0].total:
        return previous
    return best


def segment_window(
    window: Recording,
    settings: Settings,
    optimizer: Any,
    *,
    seed: int,
    on_iteration: Any = None,
    previous: np.ndarray | None = None,
    progress: str | None = None,
    inner: np.ndarray | None = None,
) -> WindowResult:
    """Segment one window (two depth maps) into ``n_clusters`` motions (``auto``: as many
    as :func:`~spatialseg.clustering.count_motions` finds); with ``init.method=auto``, from
    each start of ``init.auto``, keeping the one :func:`kept_run` chooses. ``previous`` (K x the
    model's components): the preceding window's final velocities, the ``previous`` start
    (skipped when None, or with another K). ``progress``: the window's name
    in a DEBUG line per iteration and per start (None: no such lines). ``inner``: the
    window's own events when ``window`` is a span with context windows (``inner`` of
    :meth:`~spatialseg.recording.Recording.spans`; None: every event); only their labels are
    smoothed, as each context window's own span labels it."""
    wanted = settings.cluster_count
    timings: dict[str, float] = {}
    start = time.perf_counter()
    prepared = prepare(window, settings, seed=seed)
    check_events_per_cluster(prepared.points.shape[0], wanted or 1, window.name)
    t_ref = reference_time(prepared.t, settings.volume.t_ref)
    timings["prepare"] = time.perf_counter() - start
    fit = _WindowFit(
        window=window,
        prepared=prepared,
        t_ref=t_ref,
        settings=settings,
        optimizer=optimizer,
        seed=seed,
        previous=previous,
        progress=progress,
        on_iteration=on_iteration,
        timings=timings,
    )
    timings["init"] = timings["cluster"] = 0.0
    if wanted is None:  # n_clusters=auto: one motion first, then one more while it pays
        kept = count_motions(
            fit.best_start,
            lambda found: found[0],
            fit.separation,
            max_clusters=settings.clustering.max_clusters,
        )
    else:
        kept = fit.best_start(wanted)
    result, init, method = kept
    start_totals = fit.totals[len(result.thetas)]
    start = time.perf_counter()
    result = fit.grown(result, method, auto=wanted is None)
    timings["cluster"] += time.perf_counter() - start
    start = time.perf_counter()
    result = refit_velocities(result, prepared, t_ref, settings, fit.bounds, seed=seed)
    timings["refit"] = time.perf_counter() - start
    if relabel_sigmas(settings.clustering, alone=fit.alone) is not None:
        start = time.perf_counter()
        result = fit.relabelled(result)
        timings["relabel"] = time.perf_counter() - start
    start = time.perf_counter()
    probabilities = fit.probabilities(result)
    timings["label"] = time.perf_counter() - start
    clustering = settings.clustering
    labels = assign_labels(
        probabilities[prepared.labelled], prepared.labelled, clustering.min_probability
    )
    if clustering.smoothness > 0:
        start = time.perf_counter()
        labels = smoothed_labels(window, prepared, result, probabilities, labels, clustering, inner)
        timings["smooth"] = time.perf_counter() - start
    return WindowResult(
        labels,
        probabilities,
        result,
        prepared,
        t_ref,
        timings,
        bool(init.fallback),
        method,
        start_totals=start_totals,
    )


@dataclass(eq=False)
class _WindowFit:
    """One window's clustering, shared by its starts: the prepared events, the search box
    (grown where a motion presses on it), the objectives every start's loop uses, each
    start's total per number of motions and the stage times of :func:`segment_window`."""

    window: Recording
    prepared: Prepared
    t_ref: float
    settings: Settings
    optimizer: Any
    seed: int
    previous: np.ndarray | None
    progress: str | None
    on_iteration: Any
    timings: dict[str, float]
    clustering: ClusteringSettings = field(init=False)
    starts: list[str] = field(init=False)
    alone: bool = field(init=False)
    bounds: np.ndarray = field(init=False)  # the search box, grown by grown()
    ceiling: np.ndarray = field(init=False)
    totals: dict[int, dict[str, float]] = field(default_factory=dict, init=False)
    _objectives: tuple[ModelEvaluator, StepStage | None] | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        """The starts to run, whether the span is the window alone, and the search box with
        the ceiling it may grow to."""
        clustering = self.clustering = self.settings.clustering
        self.starts = _window_starts(self.settings, self.previous is not None)
        self.alone = len(self.window.depth_maps) == 2  # no neighbouring windows in this span
        self.bounds = search_bounds(
            self.prepared, clustering.max_displacement, clustering.max_depth_change
        )
        self.ceiling = search_bounds(
            self.prepared,
            1.0,
            clustering.max_depth_change,
            windows=len(self.window.depth_maps) - 1,
        )

    def objectives(self) -> tuple[ModelEvaluator, StepStage | None]:
        """The objectives every start's loop shares, built on first use: after the first
        start, so a tile start's volumes are freed first (or for the ``previous`` start)."""
        if self._objectives is None:
            self._objectives = _window_objectives(
                self.prepared, self.t_ref, self.settings, self.optimizer, seed=self.seed
            )
        return self._objectives

    def cluster(
        self, init: motion_init.InitResult, method: str, box: np.ndarray
    ) -> ClusteringResult:
        """Algorithm 1 from ``init`` in the search box ``box`` (``method``: the start's name)."""
        return _cluster_from(
            init,
            self.prepared,
            self.objectives(),
            self.clustering,
            self.optimizer,
            box,
            seed=self.seed,
            on_iteration=_iteration_logger(self.progress, method, self.on_iteration),
            alone=self.alone,
        )

    def separation(self, a: np.ndarray, b: np.ndarray) -> float:
        """How far apart (voxels) two velocities move this window's points."""
        return motion_separation(self.prepared, a, b)

    def initial(self, method: str, k: int) -> motion_init.InitResult:
        """The start ``method``'s ``k`` initial motions and labels."""
        if method == PREVIOUS:
            assert self.previous is not None  # best_start skips it otherwise
            return previous_init(
                self.previous,
                self.prepared,
                self.objectives()[0],
                self.clustering,
                self.bounds,
                alone=self.alone,
            )
        return initialise(
            self.window,
            self.prepared,
            _with_start(self.settings, method),
            k,
            self.bounds,
            seed=self.seed,
            optimizer=self.optimizer,
        )

    def best_start(self, k: int) -> Run:
        """The loop from each start with ``k`` motions (``previous`` only where the window
        before found ``k``), the one :func:`kept_run` chooses kept."""
        runs: list[Run] = []
        self.totals[k] = {}
        for method in self.starts:
            if method == PREVIOUS and (self.previous is None or len(self.previous) != k):
                continue
            start = time.perf_counter()
            init = self.initial(method, k)
            self.timings["init"] += time.perf_counter() - start
            start = time.perf_counter()
            result = self.cluster(init, method, self.bounds)
            self.timings["cluster"] += time.perf_counter() - start
            self.totals[k][method] = float(result.total)
            if self.progress is not None and len(self.starts) > 1:
                log.debug("%s, start %s: total contrast %.6g", self.progress, method, result.total)
            runs.append((result, init, method))
        return kept_run(runs)

    def grown(self, result: ClusteringResult, method: str, *, auto: bool) -> ClusteringResult:
        """``result``, or the loop run again from its velocities in a search box grown
        (:func:`widened_box`) while that beats it (:func:`_better`); the box kept grown."""
        evaluator = self.objectives()[0]
        while (wider := widened_box(result.thetas, self.bounds, self.ceiling)) is not None:
            start_wider = previous_init(
                result.thetas, self.prepared, evaluator, self.clustering, wider, alone=self.alone
            )
            regrown = self.cluster(start_wider, f"{method}, box grown", wider)
            kept_wider = _better(regrown, result, auto=auto)
            if self.progress is not None:
                log.debug(
                    "%s: a velocity on the search box's face; box grown to +-%s, %s",
                    self.progress,
                    np.array2string(wider[:, 1], precision=3),
                    "kept" if kept_wider else "not kept",
                )
            if not kept_wider:
                break
            result, self.bounds = regrown, wider
        return result

    def relabelled(self, result: ClusteringResult) -> ClusteringResult:
        """``result`` with each event's memberships from one P-step at its final velocities
        (``clustering.relabel_sigma``, weighted by the relabelling prior where set); where
        that leaves a cluster weak, rebuilt from every event in every volume."""
        sigmas = relabel_sigmas(self.clustering, alone=self.alone)
        scale = self.clustering.relabel_prior_scale
        prior = (
            None
            if scale is None
            else prior_weights(self.prepared, result.thetas, result.probabilities, scale)
        )
        evaluator = self.objectives()[0]
        relabelled = p_step(evaluator, result.thetas, result.probabilities, sigmas, 1, prior)
        weak = weak_cluster(result.thetas, relabelled, self.separation)
        if weak is not None:
            if self.progress is not None:
                log.debug(
                    "%s: cluster %d wasted; memberships rebuilt from every event",
                    self.progress,
                    weak,
                )
            relabelled = repaired_memberships(
                evaluator, result.thetas, sigmas, self.clustering.max_iterations
            )
        return replace(result, probabilities=relabelled)

    def probabilities(self, result: ClusteringResult) -> np.ndarray:
        """Memberships (N x K) of every event of the window: the fitted ones' own, those of
        the events left out of the fit from the fitted motions (:func:`label_rest`), zeros
        for events without depth."""
        probabilities = _full_probabilities(result.probabilities, self.prepared.valid)
        rest = self.prepared.rest
        if rest is not None and len(rest[0]):
            blur = p_step_settings(self.clustering, alone=self.alone)
            probabilities[rest[2]] = label_rest(
                self.prepared, self.t_ref, self.objectives()[0], result, blur
            )
        return probabilities


def widened_box(thetas: np.ndarray, bounds: np.ndarray, ceiling: np.ndarray) -> np.ndarray | None:
    """The search box doubled (up to ``ceiling``) along each axis a velocity of ``thetas``
    presses on (within :data:`BOX_FACE` of its face), or None when none presses on a face
    that can still move.

    Decision: the box (``clustering.max_displacement`` over the window's whole span) keeps
    the optimiser's few evaluations where the motions are, but a real recording's fast
    objects can lie outside it (the road recording's cars at a third of their speed). A
    motion that ends on the face is the data asking for more, so only that axis grows,
    until the points move at most the grid's whole extent (and the depth
    ``clustering.max_depth_change``) per window; a box 3x wider everywhere cost most
    families on the dev seeds (docs/method.md, "The search box grows where a motion
    presses on it").
    """
    half, top = bounds[:, 1], ceiling[:, 1]
    reach = np.max(np.abs(np.asarray(thetas, dtype=np.float64)), axis=0)
    pressed = (reach >= (1.0 - BOX_FACE) * half) & (half < top)
    if not pressed.any():
        return None
    grown = np.where(pressed, np.minimum(2.0 * half, top), half)
    return np.column_stack([-grown, grown])


def check_events_per_cluster(n_events: int, k: int, name: str) -> None:
    """Refuse a window of ``n_events`` usable events for ``k`` clusters under
    :data:`MIN_EVENTS_PER_CLUSTER` each and warn under :data:`FEW_EVENTS_PER_CLUSTER`, so a
    window too short for its velocities says so instead of returning them."""

    def too_few(floor: int) -> str:
        return (
            f"{name}: {n_events} usable events for {k} clusters (under {floor} per cluster); "
            "use fewer clusters or a longer window"
        )

    if n_events < MIN_EVENTS_PER_CLUSTER * k:
        raise ValueError(too_few(MIN_EVENTS_PER_CLUSTER))
    if n_events < FEW_EVENTS_PER_CLUSTER * k:
        log.warning("%s: its velocities are poorly determined", too_few(FEW_EVENTS_PER_CLUSTER))


def check_config(settings: Settings | Mapping[str, Any]) -> Settings:
    """The run's :class:`~spatialseg.settings.Settings`, checked before any data is loaded or
    simulated (:func:`~spatialseg.settings.settings_from`), and the starts ``init.method``
    and ``init.auto`` name looked up in the registry of starts, which the settings do not
    know (:func:`~spatialseg.starts.init_candidates`; ``init.auto`` is read only with auto),
    and the depth source's parameters (:func:`~spatialseg.depth.make_depth_source`)."""
    settings = settings_from(settings)
    init_candidates(settings.init)
    init_candidates(replace(settings.init, method="auto"))
    if settings.depth.name != "onnx":  # building it is its check; onnx's loads the network
        make_depth_source(settings.depth.as_config())
    return settings


def _window_starts(settings: Settings, has_previous: bool) -> list[str]:
    """The starts a window runs (:func:`~spatialseg.starts.init_candidates`), each once:
    ``previous`` only with a preceding window's velocities; for the planar model the
    ``planar`` start is its ``image_flow`` start (:func:`~spatialseg.starts.initialise`), so
    ``init.method=planar`` runs that and ``init.auto`` does not run it twice."""
    names: list[str] = []
    for name in init_candidates(settings.init):
        if name == PLANAR and settings.model.name == "planar":
            name = "image_flow"
        if (name != PREVIOUS or has_previous) and name not in names:
            names.append(name)
    return names


def _with_start(settings: Settings, method: str) -> Settings:
    """``settings`` with ``init.method`` set to the start ``method``."""
    return replace(settings, init=replace(settings.init, method=method))


def _window_objectives(
    prepared: Prepared, t_ref: float, settings: Settings, optimizer: Any, *, seed: int
) -> tuple[ModelEvaluator, StepStage | None]:
    """The P-step's evaluator over every event and the theta-step on a sample of them
    (:func:`_step_subset`; None: on every event), shared by the window's starts."""
    evaluator = window_objective(prepared, t_ref, settings)
    step = _step_subset(prepared, t_ref, settings, seed=seed)
    budget = settings.clustering.evals_per_step
    return evaluator, None if step is None else StepStage(step[0], optimizer, budget, step[1])


def _step_subset(
    prepared: Prepared, t_ref: float, settings: Settings, *, seed: int
) -> tuple[ModelEvaluator, np.ndarray] | None:
    """The theta-step's evaluator over at most ``clustering.step_events`` events drawn with
    ``seed`` (and their indices), or None to optimise on all events. Unless
    ``clustering.step_edges``, events on occlusion edges are left out of the draw.

    Decision: the contrast's maximum is set by the motion, not by the event count, so the
    velocities can be found on a sample while the P-step labels every event; the cost of
    the theta-step then stops growing with the window (measured in docs/performance.md).
    An event on an occlusion edge takes the nearer depth, which is wrong for the background
    seen just after the occluder passed; such events biased the static scene's vz in
    ``ego_street`` (docs/scenes.md), so they are labelled but do not steer the velocities.
    """
    clustering = settings.clustering
    limit = clustering.step_events
    n = prepared.points.shape[0]
    pool = (
        np.arange(n)
        if clustering.step_edges
        else off_edge_events(prepared, settings.cluster_count or clustering.max_clusters)
    )
    if len(pool) == n and (limit is None or n <= limit):
        return None
    if limit is not None and len(pool) > limit:
        pool = seeded_subset(pool, limit, seed)
    return window_objective(prepared, t_ref, settings, pool), pool


def _rules(clustering: ClusteringSettings) -> ConvergenceRules:
    """The loop's stopping rules from ``clustering``."""
    return ConvergenceRules(
        max_iterations=clustering.max_iterations,
        tol=clustering.tol,
        patience=clustering.patience,
        target=clustering.target,
        label_tol=clustering.label_tol,
    )


def _cluster_from(
    init: motion_init.InitResult,
    prepared: Prepared,
    objectives: tuple[ModelEvaluator, StepStage | None],
    clustering: ClusteringSettings,
    optimizer: Any,
    bounds: np.ndarray,
    *,
    seed: int,
    on_iteration: Any,
    alone: bool,
) -> ClusteringResult:
    """Algorithm 1 from one start: its memberships, then the configured loop (``alone``: the
    window has no neighbouring windows, :func:`~spatialseg.points.p_step_settings`)."""
    sigmas, stride = p_step_settings(clustering, alone=alone)
    init_p = initial_memberships(
        prepared.grid.coordinates(prepared.points),
        prepared.grid.voxel_size,
        init.labels,
        len(init.thetas),
        mode=clustering.init_memberships,
        confidence=clustering.init_confidence,
    )
    evaluator, step = objectives
    return iterative_clustering(
        evaluator,
        optimizer,
        init.thetas[:, : prepared.dim],
        init_p,
        bounds,
        rules=_rules(clustering),
        evals_per_step=clustering.evals_per_step,
        p_step_sigma=sigmas,
        p_step_stride=stride,
        seed=seed,
        on_iteration=on_iteration,
        step=step,
    )


def _better(result: ClusteringResult, than: ClusteringResult, *, auto: bool) -> bool:
    """Whether the loop run again in a grown search box beats the result kept: by the total
    contrast, or with n_clusters=auto by the sharpness, which chose its number of motions
    (:func:`~spatialseg.clustering.count_motions`)."""
    if auto:
        return result.sharpness > than.sharpness
    return result.total > than.total


#: Points :func:`motion_separation` measures two velocities on.
SEPARATION_PROBES = 2000


def motion_separation(prepared: Prepared, a: np.ndarray, b: np.ndarray) -> float:
    """How far apart (voxels, median over up to 2,000 of the points) two velocities of the
    model move the window's points over half its span: below a voxel the volume cannot
    tell the two motions apart."""
    shifts = voxel_shifts(prepared, np.array([a, b]), SEPARATION_PROBES)
    return float(np.nanmedian(np.linalg.norm(shifts[0] - shifts[1], axis=1)))


def refit_velocities(
    result: ClusteringResult,
    prepared: Prepared,
    t_ref: float,
    settings: Settings,
    bounds: np.ndarray,
    *,
    seed: int,
) -> ClusteringResult:
    """``result`` with each velocity re-fitted once (``clustering.refit``), memberships fixed,
    on the events off occlusion edges, within ``radius`` of the search box around the loop's
    velocity; the history keeps the loop's velocities.

    Decision: an edge event takes the nearer depth, wrong for the far surface seen just
    after the occluder passed, yet an object crossing the background has most of its events
    there, so the loop may need them to label it (``clustering.step_edges``); the velocities
    are then measured on the events whose depth holds, with the final memberships the loop's
    last theta-step never saw. The refit polishes and does not search: over the whole box
    the local optimiser's first steps, sized by the box, wandered along the flat ridge of a
    short window's depth velocity (docs/method.md, "The velocity refit").
    """
    refit = settings.clustering.refit
    if refit.evals == 0:
        return result
    index = off_edge_events(prepared, result.thetas.shape[0])
    evaluator = window_objective(prepared, t_ref, settings, index)
    optimizer = optimizers.preset(refit.optimizer)
    reach = refit.radius * (bounds[:, 1] - bounds[:, 0])
    thetas = result.thetas.copy()
    for j in range(thetas.shape[0]):
        evaluator.set_weights(result.probabilities[index, j])
        near = np.column_stack(
            [
                np.maximum(bounds[:, 0], thetas[j] - reach),
                np.minimum(bounds[:, 1], thetas[j] + reach),
            ]
        )
        thetas[j], _ = maximize_contrast(evaluator, optimizer, thetas[j], near, refit.evals, seed)
    return replace(result, thetas=thetas)


def prior_weights(
    prepared: Prepared, thetas: np.ndarray, p: np.ndarray, scale: float
) -> np.ndarray:
    """Per event, ``exp(-d^2 / 2 scale^2)``: ``d`` is how far apart (voxels) its point lands
    when moved over half the span by its two likeliest motions (by ``p``); 1 where the two
    cannot tell the event apart, towards 0 where they clearly can (N,).

    Decision: where two motions move a region alike (a forward-moving camera's far wall
    near the focus of expansion, seen past a person crossing), both volumes hold the same
    events there and the P-step keeps whatever memberships they had: its labels depend on
    the start, not on evidence. There the clusters' shares decide
    (:func:`spatialseg.clustering.p_step`, docs/method.md, "Relabelling")."""
    if len(thetas) < 2:
        return np.zeros(len(p))
    half = 0.5 * float(prepared.t.max() - prepared.t.min())
    moved = np.stack(
        [
            prepared.grid.continuous_index(prepared.points - half * v)
            for v in spatial_velocities(thetas)
        ],
        axis=1,
    )
    top = np.argsort(-p, axis=1, kind="stable")[:, :2]
    rows = np.arange(len(p))
    gap = np.linalg.norm(moved[rows, top[:, 0]] - moved[rows, top[:, 1]], axis=1)
    return np.exp(-0.5 * (np.nan_to_num(gap, nan=np.inf) / scale) ** 2)


def label_rest(
    prepared: Prepared,
    t_ref: float,
    fitted: ModelEvaluator,
    result: ClusteringResult,
    blur: tuple[tuple[float, float, float], int],
) -> np.ndarray:
    """Memberships (R x K) of the events left out of the fit (``prepared.rest``): each
    cluster's volume of the fitted events (``fitted``, the window's P-step evaluator over
    them; weighted by their final memberships), smoothed as in the P-step (``blur``: sigmas
    and stride), sampled where the cluster's motion warps each of them; normalised (Eq.
    26). An event no cluster's volume reaches takes the memberships of the nearest fitted
    events (:func:`nearest_memberships`), not a tie that the column order would break."""
    points, t, _ = prepared.rest
    dt = t - t_ref
    responses = np.empty((len(points), len(result.thetas)))
    for j, theta in enumerate(result.thetas):
        fitted.set_weights(result.probabilities[:, j])
        responses[:, j] = fitted.p_step_at(theta, *blur, points, dt)
    rest = update_memberships(responses)
    unexplained = ~np.any(responses > 0, axis=1)
    if unexplained.any() and len(prepared.points):
        rest[unexplained] = nearest_memberships(
            prepared.points, result.probabilities, points[unexplained]
        )
    return rest


def nearest_memberships(
    points: np.ndarray, memberships: np.ndarray, queries: np.ndarray
) -> np.ndarray:
    """Per query point (Q x 3), the mean memberships (Q x K) of the events (``points``,
    M x 3, and their ``memberships``, M x K) at the point nearest to it: events at one point
    share one answer, whichever of them the tree would have returned.

    Decision: the queries are events no volume reaches, often far from every fitted event;
    there scipy's default tree (compact, balanced) took 2-3.7 s for 30,000 of them on the
    yardstick's ``long`` dev seed 3, this one (neither) 0.06 s for the same neighbours."""
    unique, inverse = unique_rows(points)
    counts = np.bincount(inverse, minlength=len(unique))
    sums = [np.bincount(inverse, column, len(unique)) for column in memberships.T]
    mean = np.column_stack(sums) / counts[:, None]
    tree = cKDTree(unique, compact_nodes=False, balanced_tree=False)
    return mean[tree.query(queries)[1]]


def unique_rows(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``points`` (M x D) in lexicographic order, and each row's index
    among them: ``np.unique(points, axis=0, return_inverse=True)``'s answer by one
    ``lexsort``, 3.4x faster than its sort of the rows as records (1,000,000 events)."""
    order = np.lexsort(points.T[::-1])
    ordered = points[order]
    first = np.ones(len(ordered), dtype=np.bool_)
    first[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    inverse = np.empty(len(points), dtype=np.int64)
    inverse[order] = np.cumsum(first) - 1
    return ordered[first], inverse


def image_speed(prepared: Prepared, thetas: np.ndarray, p: np.ndarray, camera: Camera) -> float:
    """The fitted events' median image speed (pixels per second) under their likeliest
    motion: a planar velocity is one; a spatial one moves its point across the image by the
    pinhole's Jacobian (:func:`~spatialseg.points.image_jacobian`)."""
    if not len(p):
        return 0.0
    own = spatial_velocities(thetas)[p.argmax(axis=1)]
    if prepared.dim == 2:
        return float(np.median(np.linalg.norm(own[:, :2], axis=1)))
    jacobian = image_jacobian(prepared, camera)
    flow = np.einsum("nij,nj->ni", jacobian, own)
    return float(np.median(np.linalg.norm(flow, axis=1)))


def smoothed_labels(
    window: Recording,
    prepared: Prepared,
    result: ClusteringResult,
    probabilities: np.ndarray,
    labels: np.ndarray,
    clustering: ClusteringSettings,
    inner: np.ndarray | None = None,
) -> np.ndarray:
    """``labels`` (N,) with every labelled event's label (of the events ``inner`` only, when
    given) Potts-smoothed (:mod:`spatialseg.mrf`, weight ``clustering.smoothness``, from its
    memberships ``probabilities``, N x K): jointly, except for the events a dense window's
    fit left out (``prepared.unsampled``), each labelled given the others'
    (:func:`~spatialseg.mrf.conditional_labels`); neighbours in space-time, the time scaled
    by the events' image speed (:func:`image_speed`; at least a pixel over the window).
    Unlabelled events stay -1."""
    smoothable = labels >= 0
    if inner is not None:
        own = np.zeros_like(smoothable)
        own[inner] = True
        smoothable &= own
    index = np.flatnonzero(smoothable)
    if len(index) < 2:
        return labels
    ev = window.events
    t = ev.t[index]
    span = max(float(t.max() - t.min()), 1e-9)
    speed = max(image_speed(prepared, result.thetas, result.probabilities, window.camera), 1 / span)
    xy = np.column_stack([ev.x[index], ev.y[index]])
    where = mrf.space_time(xy, t, speed)
    joint = np.ones(len(index), dtype=bool)
    if prepared.unsampled is not None:
        joint = ~prepared.unsampled[index]
        joint |= np.count_nonzero(joint) < 2  # too few fitted events to hold: all jointly
    fitted = np.flatnonzero(joint)
    fitted = fitted[grid_order(where[fitted])]  # the cuts' graph numbered near to near
    core, others, weight = index[fitted], index[~joint], clustering.smoothness
    first, second = mrf.neighbour_pairs(where[fitted])
    smoothed = labels.copy()
    smoothed[core] = mrf.potts_labels(probabilities[core], first, second, weight)
    smoothed[others] = mrf.conditional_labels(
        probabilities[others], where[~joint], where[fitted], smoothed[core], weight
    )
    return smoothed


def _full_probabilities(p: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Memberships for all N events (zeros for events that were not clustered)."""
    full = np.zeros((valid.shape[0], p.shape[1]), dtype=np.float32)
    full[valid] = p
    return full


def assign_labels(
    probabilities: np.ndarray, valid: np.ndarray, min_probability: float
) -> np.ndarray:
    """Labels for all N events: argmax membership, -1 where invalid or below the threshold."""
    labels = np.full(valid.shape[0], -1, dtype=np.int64)
    if probabilities.size:
        best = probabilities.argmax(axis=1)
        confident = probabilities.max(axis=1) >= min_probability
        labels[np.flatnonzero(valid)[confident]] = best[confident]
    return labels


def _iteration_logger(
    window: str | None, start: str, on_iteration: Any
) -> Callable[[IterationRecord], None] | None:
    """The per-iteration hook: a DEBUG line naming the window and the start (none when
    ``window`` is None), then ``on_iteration`` (the caller's own, if any)."""
    if window is None:
        return on_iteration

    def hook(record: IterationRecord) -> None:
        """Log one outer iteration, then pass it on."""
        log.debug(
            "%s, start %s, iteration %d: total contrast %.6g, evaluations %d, %.2f s",
            window,
            start,
            record.iteration,
            record.total,
            record.n_evals,
            record.seconds,
        )
        if on_iteration is not None:
            on_iteration(record)

    return hook
