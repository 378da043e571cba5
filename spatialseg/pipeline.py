"""The method end to end on one recording: windows -> points -> initial motions -> clustering.

Each stage is a plain function with arrays in and arrays out, timed separately:
``prepare`` (EDPA or the planar embedding, and the voxel grid), ``initialise`` (time-surface
flows + k-means), ``cluster`` (Algorithm 1), and ``assign`` (labels from memberships).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from spatialseg import edpa, hypotheses, motion_init
from spatialseg.checks import (
    boolean_setting,
    integer_setting,
    is_integer,
    number_setting,
    optional_positive,
    plural,
)
from spatialseg.clustering import (
    ClusteringResult,
    ConvergenceRules,
    IterationRecord,
    Repair,
    StepStage,
    cluster_responses,
    grow_clusters,
    initial_memberships,
    iterative_clustering,
    maximize_contrast,
    p_step,
    update_memberships,
)
from spatialseg.compilation import announce_compilation
from spatialseg.denoise import denoise_mask
from spatialseg.executors import check_parallel, map_in_order
from spatialseg.grid import VoxelGrid, grid_around, project_jacobian
from spatialseg.identities import Boundary, boundary, link_clusters
from spatialseg.objectives import make_objective
from spatialseg.progress import progress_bar
from spatialseg.recording import (
    Camera,
    Recording,
    check_depth_maps,
    check_event_times,
    check_window_context,
)
from spatialseg.volume import VolumeObjective, check_p_step_blur

__all__ = [
    "Handover",
    "Prepared",
    "SegmentationResult",
    "WindowResult",
    "assign_labels",
    "check_config",
    "check_events_per_cluster",
    "cluster_count",
    "depth_change_cap",
    "fit_support",
    "init_candidates",
    "label_rest",
    "motion_separation",
    "off_edge_events",
    "p_step_settings",
    "prepare",
    "previous_init",
    "prior_weights",
    "reference_time",
    "refit_velocities",
    "relabel_prior_scale",
    "search_bounds",
    "segment_loaded",
    "segment_recording",
    "segment_window",
    "spatial_velocities",
    "window_objective",
]

log = logging.getLogger(__name__)


#: init.method choices that compute one start (``auto`` tries several of them).
INIT_METHODS = ("tiles", "image_flow", "time_surface")

#: The start ``init.auto`` may add: the preceding window's final velocities (windows after
#: a recording's first; :func:`segment_recording`).
PREVIOUS = "previous"

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


@dataclass(frozen=True, eq=False)
class Prepared:
    """A window's events as points in the model's space, ready for the volume.

    ``points`` (M x 3) are the usable events (``valid`` marks them among the window's N);
    ``dim`` is the number of velocity components the model estimates (3 spatial, 2 planar).
    ``search_extent`` (3,) is the extent the search box is measured on (:func:`search_bounds`);
    None means the grid's. ``on_edge`` (M,) marks points whose depth came from an occlusion
    edge (:func:`spatialseg.edpa.occlusion_edges`); None: no such points. ``rest``: the
    points, times and mask (N,) of the events with depth left out of the fit (noise, sparse
    depth bands), labelled from the fitted motions at the end; None: none.
    """

    points: np.ndarray
    t: np.ndarray
    valid: np.ndarray
    grid: VoxelGrid
    dim: int
    units: str
    search_extent: np.ndarray | None = None
    on_edge: np.ndarray | None = None
    rest: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def labelled(self) -> np.ndarray:
        """The window's events that get a label (N,): the fitted ones and the ``rest``."""
        return self.valid if self.rest is None else self.valid | self.rest[2]


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


@dataclass(frozen=True, eq=False)
class Handover:
    """What a recording's last window hands the next chunk of a stream: its final
    velocities (the ``previous`` start) and its last events with their object ids."""

    velocities: np.ndarray
    boundary: Boundary


@dataclass(frozen=True, eq=False)
class SegmentationResult:
    """All windows of a recording; ``labels`` (object ids, one identity per object across
    the windows; -1 unassigned) and ``probabilities`` (N x objects, column = object id)
    cover every event in order; ``handover`` continues the recording in a next chunk."""

    labels: np.ndarray
    probabilities: np.ndarray
    windows: list[WindowResult] = field(default_factory=list)
    indices: list[np.ndarray] = field(default_factory=list)
    handover: Handover | None = None

    @property
    def n_objects(self) -> int:
        """Object ids in use (0 .. n_objects - 1; a stream's earlier chunks count)."""
        return self.probabilities.shape[1]


class ModelEvaluator:
    """A cluster's volume objective seen through the model's velocity components.

    The volume kernels always warp in 3-D; the planar model estimates only (vx, vy), so its
    velocity is padded with zeros and the gradient truncated.
    """

    def __init__(self, volume: VolumeObjective, dim: int) -> None:
        self.inner, self.dim = volume, dim

    @property
    def n_events(self) -> int:
        """Number of events in the volume."""
        return self.inner.n_events

    def _full(self, theta: np.ndarray) -> np.ndarray:
        full = np.zeros(3)
        full[: self.dim] = theta
        return full

    def set_weights(self, weights: np.ndarray) -> None:
        """Memberships of the cluster being optimised."""
        self.inner.set_weights(weights)

    def value(self, theta: np.ndarray) -> float:
        """Contrast of the volume warped by ``theta``."""
        return self.inner.value(self._full(theta))

    def grad(self, theta: np.ndarray) -> np.ndarray:
        """Analytic gradient of the contrast with respect to the model's components."""
        return self.inner.grad(self._full(theta))[: self.dim]

    def batch_value(self, thetas: np.ndarray) -> np.ndarray:
        """Contrast of many candidate velocities (n x dim) in one parallel call."""
        return self.inner.batch_value(spatial_velocities(thetas))

    def volume(self, theta: np.ndarray) -> np.ndarray:
        """The volume of warped events for ``theta``."""
        return self.inner.volume(self._full(theta))

    def p_step(
        self, theta: np.ndarray, sigma: float | Sequence[float], stride: int = 1
    ) -> tuple[np.ndarray, float]:
        """The volume for ``theta``, smoothed by ``sigma`` voxels (one number, or x, y,
        depth), at each warped event, and the contrast of the volume (the P-step)."""
        return self.inner.p_step(self._full(theta), sigma, stride)


def _planar_points(
    window: Recording, xy_scale: float, support: np.ndarray | None = None
) -> Prepared:
    """Image-plane embedding (Stoffregen et al. 2019): points (x, y, 0) in pixels, no depth;
    the ``support``ed events (default all) are fitted, the others kept aside."""
    ev = window.events
    every = np.column_stack([ev.x, ev.y, np.zeros(len(ev))]).astype(np.float64)
    fit = np.ones(len(ev), dtype=bool) if support is None else support  # fit_support: never empty
    points = every[fit]
    lo = points.min(axis=0) - np.array([2 * xy_scale, 2 * xy_scale, 0.0])
    hi = points.max(axis=0) + np.array([2 * xy_scale, 2 * xy_scale, 0.0])
    shape = (*(np.ceil((hi[:2] - lo[:2]) / xy_scale).astype(int) + 1), 1)
    grid = VoxelGrid(origin=lo, voxel_size=np.array([xy_scale, xy_scale, 1.0]), shape=shape)
    rest = (every[~fit], ev.t[~fit], ~fit)
    return Prepared(points, ev.t[fit], fit.copy(), grid, 2, "px/s", rest=rest)


def _image_flow_init(
    window: Recording,
    prepared: Prepared,
    k: int,
    params: dict[str, Any],
    *,
    seed: int,
    bounds: np.ndarray,
) -> motion_init.InitResult:
    """Initial motions from the image-plane time surface S1, its flow constraints lifted to
    3-D velocities by each event's depth (:func:`motion_init.lift_constraints`).

    Decision: the three-plane surfaces resolve depth motion only when objects cross several
    depth bins per window, which fails on wide-depth scenes; the image surface is robust,
    and lifting each event by its own depth makes a translating camera's static scene, whose
    image speed varies with depth, one motion instead of one per depth layer.
    """
    events = window.events.select(prepared.valid)
    planar = _planar_points(replace(window, events=events, ground_truth=None), 1.0)
    cam = window.camera
    intrinsics = np.array([cam.fx, cam.fy, cam.cx, cam.cy])
    lift = project_jacobian(prepared.points, intrinsics)[:, :2]
    return motion_init.initial_motions(
        planar.points,
        planar.t,
        planar.grid,
        k,
        seed=seed,
        dim=2,
        max_speed=float(bounds[:, 1].max()),
        lift=lift,
        **params,
    )


def _check_optimizer_name(name: str, key: str) -> None:
    """Raise a one-line error unless ``name`` is a ``conf/optimizer`` option (``key``: the
    config key that named it)."""
    from spatialseg.config import check_option

    check_option("optimizer", name, key)


def named_optimizer(name: str, key: str) -> Any:
    """The optimiser of ``conf/optimizer/<name>.yaml`` with its defaults (``key``: the
    config key that named it, for the error message)."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from spatialseg.config import conf_dir

    _check_optimizer_name(name, key)
    return instantiate(OmegaConf.load(conf_dir() / "optimizer" / f"{name}.yaml"))


def _tiles_init(
    window: Recording,
    prepared: Prepared,
    cfg: Mapping[str, Any],
    k: int,
    bounds: np.ndarray,
    optimizer: Any,
    *,
    seed: int,
) -> motion_init.InitResult | None:
    """Initial motions from each image tile's own contrast maximum and a greedy cover
    (:mod:`spatialseg.hypotheses`); None when fewer than ``k`` tiles are dense enough."""
    params = cfg["init"]["tiles"]
    t_ref = reference_time(prepared.t, cfg["volume"]["t_ref"])
    events = window.events
    xy = np.column_stack([events.x, events.y])[prepared.valid]
    event_tile, counts = hypotheses.image_tiles(
        xy, float(params["size"]), int(params["min_events"])
    )
    if len(counts) < k:
        return None

    def evaluator_for(index: np.ndarray) -> ModelEvaluator:
        return window_objective(prepared, t_ref, cfg, index)

    tiles = hypotheses.Tiles(evaluator_for, event_tile, len(counts))
    velocities, tile_label = hypotheses.tile_motions(
        tiles,
        k,
        optimizer,
        bounds,
        named_optimizer(str(params["refit"]), "init.tiles.refit"),
        evals=int(params["evals"]),
        rounds=int(params["rounds"]),
        explained=None if params["explained"] is None else float(params["explained"]),
        seed=seed,
    )
    thetas = spatial_velocities(velocities)
    labels = np.where(event_tile >= 0, tile_label[np.maximum(event_tile, 0)], -1)
    flows = np.full((len(labels), 3), np.nan)
    return motion_init.InitResult(thetas, flows, 0, False, labels)


def initialise(
    window: Recording,
    prepared: Prepared,
    cfg: Mapping[str, Any],
    k: int,
    bounds: np.ndarray,
    *,
    seed: int,
    optimizer: Any = None,
) -> motion_init.InitResult:
    """Initial motions by ``init.method``: ``image_flow`` (default), ``tiles`` (needs the
    run's ``optimizer``) or ``time_surface`` (the paper's three planes; the flow-based
    choice for the planar model's own 2-D space).

    ``bounds`` is the model's search box (:func:`search_bounds`); flows faster than it are
    discarded. ``tiles`` falls back to ``image_flow`` when fewer than K tiles have enough
    events. ``auto`` is resolved by :func:`segment_window` (:func:`init_candidates`)."""
    params = dict(cfg["init"])
    method = params.pop("method")
    params.pop("tiles")
    params.pop("auto")
    _check_init_method(method)
    if method == "tiles":
        if optimizer is None:
            raise ValueError("init.method=tiles needs the run's optimizer")
        init = _tiles_init(window, prepared, cfg, k, bounds, optimizer, seed=seed)
        if init is not None:
            return init
        log.info("fewer than %d tiles with init.tiles.min_events events: flow init", k)
        method = "image_flow"
    if method == "image_flow" and prepared.dim == 3:
        return _image_flow_init(window, prepared, k, params, seed=seed, bounds=bounds)
    grid = prepared.grid
    if grid.projection is not None:  # the paper's three planes are metric
        grid = _volume_grid(prepared.points, window.camera, cfg, "metric")
    return motion_init.initial_motions(
        prepared.points,
        prepared.t,
        grid,
        k,
        seed=seed,
        dim=prepared.dim,
        max_speed=float(bounds[:, 1].max()),
        **params,
    )


def _check_init_method(method: str) -> None:
    """Raise a one-line error unless ``method`` is one start of :data:`INIT_METHODS`."""
    if method not in INIT_METHODS:
        raise ValueError(f"init.method must be one of {(*INIT_METHODS, 'auto')}, got {method!r}")


def check_config(cfg: Mapping[str, Any]) -> None:
    """Refuse, before any data is loaded or simulated, the settings that would otherwise fail
    only once the run reaches them, or never (an optimiser named for a stage that does not
    run): the starts, the optimisers named by key, the refit's budget, the P-step and
    relabelling smoothing and its grid (for windows with neighbours and alone), the context,
    the depth-change cap, the relabelling prior, the stopping rules and EDPA's edge radius."""
    init_candidates(cfg["init"])
    init_candidates({**cfg["init"], "method": "auto"})  # init.auto, read only with auto
    _check_optimizer_name(str(cfg["init"]["tiles"]["refit"]), "init.tiles.refit")
    _check_optimizer_name(str(cfg["clustering"]["coarse"]["refine"]), "clustering.coarse.refine")
    _check_optimizer_name(
        str(cfg["clustering"]["refit"]["optimizer"]), "clustering.refit.optimizer"
    )
    _refit_budget(cfg)
    p_step_settings(cfg["clustering"], alone=False)
    p_step_settings(cfg["clustering"], alone=True)
    check_window_context(cfg["window"]["context"])
    check_parallel(cfg["window"]["parallel"], cfg["window"]["workers"])
    depth_change_cap(cfg["clustering"])
    relabel_sigmas(cfg["clustering"], alone=False)
    relabel_sigmas(cfg["clustering"], alone=True)
    relabel_prior_scale(cfg["clustering"])
    _rules(cfg["clustering"])
    cluster_count(cfg)
    _max_clusters(cfg["clustering"])
    edpa.check_edge_radius(cfg["edpa"]["edge_radius"])


def relabel_sigmas(ccfg: Mapping[str, Any], *, alone: bool) -> tuple[float, float, float] | None:
    """``clustering.relabel_sigma`` (``clustering.p_step_alone.relabel_sigma`` for a window
    clustered alone) as (x, y, depth) voxels, or None (off), validated.

    Decision: once the velocities are final (after the refit), one more P-step at them,
    smoothed less than the loop's, gives the labels. The loop needs its wider blur while
    velocities and memberships still move; at the final velocities a sharper response
    follows an object's outline more closely. A window alone holds a third of the events
    per voxel, and there it cost accuracy (docs/method.md, "Relabelling")."""
    value, key = _p_step_option(ccfg, "relabel_sigma", alone=alone)
    return None if value is None else p_step_sigmas(value, key)


def relabel_prior_scale(ccfg: Mapping[str, Any]) -> float | None:
    """``clustering.relabel_prior_scale``, validated: a positive number of voxels, or None."""
    return optional_positive(ccfg["relabel_prior_scale"], "clustering.relabel_prior_scale")


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


def depth_change_cap(ccfg: Mapping[str, Any]) -> float | None:
    """``clustering.max_depth_change``, validated: a positive number, or None for no cap."""
    return optional_positive(ccfg["max_depth_change"], "clustering.max_depth_change")


def init_candidates(init_cfg: Mapping[str, Any]) -> list[str]:
    """The starts a window is clustered from: ``init.method``, or for ``auto`` each of
    ``init.auto`` (:func:`segment_window` keeps the result with the highest total contrast;
    ``previous`` runs only where a preceding window has been segmented).

    Decision: the flow start fails where per-event flows do not separate the motions (a
    camera walking forward, ``ego_forward``), the tile start where a tile cannot tell motion
    across the image from motion in depth (``noon``, ``three``); the total contrast is the
    objective the clustering maximises, so it judges the two without ground truth. Judging
    after a few iterations instead of at the end disagreed with the final ranking on 3-4 of
    24 scene-seeds, so each start runs the whole loop (docs/method.md, "Both starts").
    """
    method = init_cfg["method"]
    if method != "auto":
        _check_init_method(method)
        return [method]
    names = list(init_cfg["auto"] or [])
    known = (*INIT_METHODS, PREVIOUS)
    if not any(n in INIT_METHODS for n in names) or any(n not in known for n in names):
        raise ValueError(
            f"init.auto must list one or more of {INIT_METHODS}, and optionally "
            f"{PREVIOUS!r} (a recording's first window has no previous one), got {names!r}"
        )
    return names


def prepare(window: Recording, cfg: Mapping[str, Any]) -> Prepared:
    """Lift the window's events into the model's space and build the voxel grid around the
    events the motions are fitted on (:func:`fit_support`);
    the other events with depth are kept aside (``Prepared.rest``) and labelled at the end."""
    model, vol = cfg["model"], cfg["volume"]
    if len(window.events) == 0:
        raise ValueError(f"{window.name}: the window has no events; choose a longer window")
    support = fit_support(window, cfg)
    if model["name"] == "planar":
        return _planar_points(window, float(model["xy_scale"]), support)
    lifted = edpa.lift(
        window,
        unknown_depth=cfg["edpa"]["unknown_depth"],
        fill_radius=int(cfg["edpa"]["fill_radius"]),
        edge_ratio=cfg["edpa"]["edge_ratio"],
        edge_radius=cfg["edpa"]["edge_radius"],
    )
    supported = support[lifted.valid]
    dense = edpa.dense_depth_bands(
        lifted.points[supported, 2], gap=float(vol["depth_gap"]), min_share=vol["min_band_share"]
    )
    fit = np.zeros(len(supported), dtype=bool)
    fit[np.flatnonzero(supported)[dense]] = True
    if not fit.any():
        fit[:] = True  # nothing supported: fit on every event with depth
    points = lifted.points[fit]
    grid = _volume_grid(points, window.camera, cfg)
    valid = lifted.valid.copy()
    valid[np.flatnonzero(valid)[~fit]] = False
    rest_valid = lifted.valid & ~valid
    extent = _search_extent(lifted.points[supported], grid, float(vol["margin"]))
    on_edge = lifted.on_edge[lifted.valid][fit]
    rest = (lifted.points[~fit], lifted.t[~fit], rest_valid)
    return Prepared(points, lifted.t[fit], valid, grid, 3, "m/s", extent, on_edge, rest)


def fit_support(window: Recording, cfg: Mapping[str, Any]) -> np.ndarray:
    """The window's events the motions are fitted on (N,): with ``denoise.enabled``, those
    the background-activity filter supports (:func:`spatialseg.denoise.denoise_mask`), else
    all. The others are labelled at the end from the fitted motions.

    Decision: an isolated noise event carries no motion but, lifted to the depth behind
    it, stretches the grid and blurs every volume; 4.6 % of noise turned a three-object
    scene from 1.0 to 0.73. Dropping such events (the filter's usual use) loses the signal
    events it rejects too; leaving them out of the fit alone keeps their labels."""
    den = cfg["denoise"]
    support = np.ones(len(window.events), dtype=bool)
    if boolean_setting(den["enabled"], "denoise.enabled"):
        support = denoise_mask(window.events, radius=den["radius"], window=den["window"])
        support |= not support.any()  # a window rejected whole (a few events): fit them all
    return support


def _volume_grid(
    points: np.ndarray, camera: Camera, cfg: Mapping[str, Any], coordinates: str | None = None
) -> VoxelGrid:
    """The spatial model's voxel grid around ``points`` in ``volume.coordinates`` (or
    ``coordinates``): ``image`` (pixels and inverse depth, default) or ``metric`` (metres).

    Decision: on an image grid a voxel has the same footprint in the image at every depth,
    so near and far events are equally sharp when compensated, and an object moving in
    depth is sharpened by its expansion in the image, resolved to a pixel, instead of by
    its few depth bins only (``docs/volume.md`` has the measurements).
    """
    vol = cfg["volume"]
    coordinates = coordinates or str(vol["coordinates"])
    size = edpa.voxel_size(
        points,
        camera,
        xy_scale=float(cfg["model"]["xy_scale"]),
        z_bins=int(vol["z_bins"]),
        coordinates=coordinates,
    )
    projection = None
    if coordinates == "image":
        projection = np.array([camera.fx, camera.fy, camera.cx, camera.cy])
    return grid_around(points, size, float(vol["margin"]), int(vol["max_voxels"]), projection)


def _search_extent(all_points: np.ndarray, grid: VoxelGrid, margin: float) -> np.ndarray:
    """Per axis (metres), the larger of a metric grid's extent and all lifted points' extent
    (``margin`` added).

    Decision: events left out of the grid (sparse depth bands) still count for the search
    box, so trimming the grid makes the voxels finer without narrowing the velocities the
    optimiser may try. Otherwise ``approach``'s grid, trimmed to 0.9 m deep, would cap vz
    at 1.1 m/s, below the approaching box's 2.5 m/s. An image grid is not in metres, so
    there only the points count.
    """
    span = (1 + 2 * margin) * (all_points.max(axis=0) - all_points.min(axis=0))
    if grid.projection is not None:
        return span
    return np.maximum(np.asarray(grid.shape, float) * grid.voxel_size, span)


def search_bounds(
    prepared: Prepared, max_displacement: float, max_depth_change: float | None = None
) -> np.ndarray:
    """Velocity box: a motion may move a point at most ``max_displacement`` times the grid's
    extent (``prepared.search_extent`` when set) along each axis over the window (dim x 2,
    centred on zero); with ``max_depth_change`` (spatial model) ``|vz|`` is also capped so a
    motion changes the points' median depth by at most that share over the window.

    Decision: the depth cap is a time to contact of at least ``1 / max_depth_change``
    windows. Without it a few far outliers in the depth maps stretch the depth extent (to
    hundreds of metres on ``road_cars``) and the box admits velocities that push half the
    window's events far away and pull the other half close: event collapse, which the
    variance rewards (docs/method.md, "Event collapse").
    """
    if prepared.search_extent is not None:
        extent = np.asarray(prepared.search_extent, float)
    else:
        extent = np.asarray(prepared.grid.shape, float) * prepared.grid.voxel_size
    duration = max(float(prepared.t.max() - prepared.t.min()), 1e-9)
    half = max_displacement * extent[: prepared.dim] / duration
    if max_depth_change is not None and prepared.dim == 3:
        depth = float(np.median(prepared.points[:, 2]))
        half[2] = min(half[2], max_depth_change * depth / duration)
    return np.column_stack([-half, half])


def reference_time(t: np.ndarray, mode: str) -> float:
    """The warp's reference time: the window's start or its middle."""
    if mode == "start":
        return float(t.min())
    if mode == "middle":
        return float(0.5 * (t.min() + t.max()))
    raise ValueError(f"volume.t_ref must be 'start' or 'middle', got {mode!r}")


def label_rest(
    prepared: Prepared,
    t_ref: float,
    cfg: Mapping[str, Any],
    result: ClusteringResult,
    blur: tuple[tuple[float, float, float], int],
) -> np.ndarray:
    """Memberships (R x K) of the events left out of the fit (``prepared.rest``): each
    cluster's volume of the fitted events (their final memberships), smoothed as in the
    P-step (``blur``: sigmas and stride), sampled where the cluster's motion warps each of
    them; normalised (Eq. 26). An event no cluster's volume reaches takes the memberships of
    the nearest fitted event, not a tie that the column order would break."""
    points, t, _ = prepared.rest
    both = np.vstack([prepared.points, points])
    volume = VolumeObjective(
        both,
        np.concatenate([prepared.t, t]) - t_ref,
        prepared.grid,
        make_objective(**cfg["objective"]),
        dtype=str(cfg["volume"]["dtype"]),
    )
    evaluator = ModelEvaluator(volume, prepared.dim)
    zeros = np.zeros((len(points), result.probabilities.shape[1]))
    memberships = np.vstack([result.probabilities, zeros])
    responses = cluster_responses(evaluator, result.thetas, memberships, *blur)[0]
    responses = responses[len(prepared.points) :]
    rest = update_memberships(responses)
    unexplained = ~np.any(responses > 0, axis=1)
    if unexplained.any() and len(prepared.points):
        nearest = cKDTree(prepared.points).query(points[unexplained])[1]
        rest[unexplained] = result.probabilities[nearest]
    return rest


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


def spatial_velocities(thetas: np.ndarray) -> np.ndarray:
    """Velocities of a model's components (K x 2 planar, K x 3 spatial) as K x 3, the
    missing vz zero: the form the volume and the results take."""
    thetas = np.asarray(thetas, dtype=np.float64)
    full = np.zeros((len(thetas), 3))
    full[:, : thetas.shape[1]] = thetas
    return full


def _full_probabilities(p: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Memberships for all N events (zeros for events that were not clustered)."""
    full = np.zeros((valid.shape[0], p.shape[1]), dtype=np.float32)
    full[valid] = p
    return full


def off_edge_events(prepared: Prepared, k: int) -> np.ndarray:
    """Indices of the points off occlusion edges (their depth is reliable), or of every point
    when fewer than ``k`` are off them (or no edges are marked), so each cluster has events."""
    if prepared.on_edge is not None and np.count_nonzero(~prepared.on_edge) >= k:
        return np.flatnonzero(~prepared.on_edge)
    return np.arange(prepared.points.shape[0])


def _step_subset(
    prepared: Prepared, t_ref: float, cfg: Mapping[str, Any], *, seed: int
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
    ccfg = cfg["clustering"]
    limit = ccfg["step_events"]
    if limit is not None and int(limit) < 1:
        raise ValueError(f"clustering.step_events must be >= 1 or null, got {limit}")
    n = prepared.points.shape[0]
    pool = (
        np.arange(n)
        if ccfg["step_edges"]
        else off_edge_events(prepared, cluster_count(cfg) or _max_clusters(ccfg))
    )
    if len(pool) == n and (limit is None or n <= int(limit)):
        return None
    if limit is not None and len(pool) > int(limit):
        pool = np.sort(np.random.default_rng(seed).choice(pool, int(limit), replace=False))
    return window_objective(prepared, t_ref, cfg, pool), pool


def _step_stages(
    prepared: Prepared,
    t_ref: float,
    cfg: Mapping[str, Any],
    optimizer: Any,
    evaluator: ModelEvaluator,
    *,
    seed: int,
) -> tuple[StepStage, ...]:
    """The theta-step's stages: the optimiser on the theta-step's events (:func:`_step_subset`;
    none: the loop's default stage); with ``clustering.coarse`` set, first on a grid
    ``stride`` times coarser and at most ``events`` of them, then ``refine`` on them at full
    resolution (a coarse-to-fine search: the global phase on the cheaper problem).
    ``evaluator`` is the loop's, over every event: the refinement's when they all step."""
    ccfg = cfg["clustering"]
    budget, coarse = int(ccfg["evals_per_step"]), ccfg["coarse"]
    step = _step_subset(prepared, t_ref, cfg, seed=seed)
    if int(coarse["stride"]) == 1 and coarse["events"] is None:
        return () if step is None else (StepStage(step[0], optimizer, budget, step[1]),)
    if coarse["events"] is not None and int(coarse["events"]) < 1:
        raise ValueError(f"clustering.coarse.events must be >= 1 or null, got {coarse['events']}")
    fine, pool = step or (evaluator, np.arange(len(prepared.t)))
    sample = pool
    if coarse["events"] is not None and len(pool) > int(coarse["events"]):
        draw = np.random.default_rng(seed + 1).choice(len(pool), int(coarse["events"]), False)
        sample = pool[np.sort(draw)]
    grid = prepared.grid.coarsened(int(coarse["stride"]))
    refine = named_optimizer(str(coarse["refine"]), "clustering.coarse.refine")
    return (
        StepStage(window_objective(prepared, t_ref, cfg, sample, grid), optimizer, budget, sample),
        StepStage(fine, refine, int(coarse["refine_evals"]), pool),
    )


def window_objective(
    prepared: Prepared,
    t_ref: float,
    cfg: Mapping[str, Any],
    index: Any = slice(None),
    grid: VoxelGrid | None = None,
) -> ModelEvaluator:
    """The configured objective (one cluster's contrast, weights set by the caller) over the
    window's events ``index`` (default all) on ``grid`` (default the window's), stored in
    ``volume.dtype`` (float32 halves the memory per event, float64 is the more accurate)."""
    volume = VolumeObjective(
        prepared.points[index],
        prepared.t[index] - t_ref,
        prepared.grid if grid is None else grid,
        make_objective(**cfg["objective"]),
        dtype=str(cfg["volume"]["dtype"]),
    )
    return ModelEvaluator(volume, prepared.dim)


def p_step_sigmas(value: Any, key: str = "clustering.p_step_sigma") -> tuple[float, float, float]:
    """``clustering.p_step_sigma`` (or the setting ``key``) as (x, y, depth) voxels: one number
    for every axis, or a pair ``[image, depth]`` (x and y share the first)."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        parts = [value]
    elif isinstance(value, Sequence) and not isinstance(value, str):
        parts = list(value)
    else:
        parts = []
    numbers = all(isinstance(v, int | float) and not isinstance(v, bool) for v in parts)
    sigmas = [float(v) for v in parts] if numbers else []
    if len(sigmas) not in (1, 2) or not all(np.isfinite(v) and v >= 0 for v in sigmas):
        raise ValueError(
            f"{key} must be a number >= 0 or a pair [image, depth] of them (voxels), got {value!r}"
        )
    return (sigmas[0], sigmas[0], sigmas[-1])


def p_step_settings(
    ccfg: Mapping[str, Any], *, alone: bool
) -> tuple[tuple[float, float, float], int]:
    """The P-step's smoothing (x, y, depth voxels) and grid stride, checked:
    ``clustering.p_step_sigma`` and ``p_step_stride`` for a window clustered with neighbouring
    windows, ``clustering.p_step_alone`` for one clustered alone.

    Decision: a window alone holds a third of a three-window span's events, and its volumes
    want the wider blur; the span wants the narrower one, which keeps the static scene's
    cluster off the events around a moving object (docs/method.md, "Defaults for a moving
    camera")."""
    given, sigma_key = _p_step_option(ccfg, "sigma", alone=alone)
    stride, stride_key = _p_step_option(ccfg, "stride", alone=alone)
    if not is_integer(stride, 1):
        raise ValueError(f"{stride_key} must be an integer >= 1, got {stride!r}")
    sigmas = p_step_sigmas(given, sigma_key)
    check_p_step_blur(sigmas[0], stride, given, (sigma_key, stride_key))
    return sigmas, stride


def _p_step_option(ccfg: Mapping[str, Any], name: str, *, alone: bool) -> tuple[Any, str]:
    """The P-step setting ``name`` (``sigma``, ``stride`` or ``relabel_sigma``) and its key:
    ``clustering.p_step_alone.NAME`` for a window clustered alone, else the top-level one."""
    if alone:
        return ccfg["p_step_alone"][name], f"clustering.p_step_alone.{name}"
    top = {"sigma": "p_step_sigma", "stride": "p_step_stride"}.get(name, name)
    return ccfg[top], f"clustering.{top}"


def _rules(ccfg: Mapping[str, Any]) -> ConvergenceRules:
    """The loop's stopping rules from ``clustering``, checked (their ranges: ConvergenceRules)."""
    return ConvergenceRules(
        max_iterations=integer_setting(ccfg["max_iterations"], "clustering.max_iterations", 1),
        tol=number_setting(ccfg["tol"], "clustering.tol", 0),
        patience=integer_setting(ccfg["patience"], "clustering.patience", 1),
        target=number_setting(ccfg["target"], "clustering.target", optional=True),
        label_tol=number_setting(ccfg["label_tol"], "clustering.label_tol", 0, optional=True),
    )


def _cluster_from(
    init: motion_init.InitResult,
    prepared: Prepared,
    objectives: tuple[ModelEvaluator, tuple[StepStage, ...]],
    cfg: Mapping[str, Any],
    optimizer: Any,
    bounds: np.ndarray,
    *,
    seed: int,
    on_iteration: Any,
    alone: bool,
    xy: np.ndarray,
    seed_motion: Any,
    auto: bool = False,
) -> ClusteringResult:
    """Algorithm 1 from one start: its memberships, then the configured loop (``alone``: the
    window has no neighbouring windows, :func:`p_step_settings`); with ``auto``
    (``n_clusters=auto``) the clusters then grow and shrink
    (:func:`spatialseg.clustering.grow_clusters`, up to ``clustering.max_clusters``;
    ``xy``: the points' image positions; ``seed_motion(points, seed)``: the motion of a
    group of points)."""
    ccfg = cfg["clustering"]
    sigmas, stride = p_step_settings(ccfg, alone=alone)
    init_p = initial_memberships(
        prepared.grid.coordinates(prepared.points),
        prepared.grid.voxel_size,
        init.labels,
        len(init.thetas),
        mode=ccfg["init_memberships"],
        confidence=float(ccfg["init_confidence"]),
    )
    evaluator, stages = objectives
    budget = int(ccfg["evals_per_step"])

    def run(thetas: np.ndarray, p: np.ndarray, run_seed: int) -> ClusteringResult:
        return iterative_clustering(
            evaluator,
            optimizer,
            thetas,
            p,
            bounds,
            rules=_rules(ccfg),
            evals_per_step=budget,
            p_step_sigma=sigmas,
            p_step_stride=stride,
            seed=run_seed,
            on_iteration=on_iteration,
            stages=stages,
        )

    result = run(init.thetas[:, : prepared.dim], init_p, seed)
    if not auto:
        return result
    repair = Repair(
        run=run,
        responses=lambda thetas, p: cluster_responses(evaluator, thetas, p, sigmas, stride)[0],
        fit=seed_motion,
        separation=lambda a, b: motion_separation(prepared, a, b),
        xy=xy,
    )
    return grow_clusters(result, repair, seed=seed + 1, max_clusters=_max_clusters(ccfg))


def _better(result: ClusteringResult, than: ClusteringResult, *, auto: bool) -> bool:
    """Whether one start's result beats another's: by the total contrast, or with
    n_clusters=auto (different numbers of clusters) by the sharpness."""
    if auto:
        return result.sharpness > than.sharpness
    return result.total > than.total


def cluster_count(cfg: Mapping[str, Any]) -> int | None:
    """``n_clusters``: a whole number >= 1, or None for ``auto``; a one-line error otherwise."""
    value = cfg["n_clusters"]
    if value == "auto":
        return None
    if not is_integer(value, 1):
        raise ValueError(
            f"n_clusters must be a whole number >= 1 or auto (the number found per window), "
            f"got {value!r}"
        )
    return int(value)


def _max_clusters(ccfg: Mapping[str, Any]) -> int:
    """``clustering.max_clusters`` (n_clusters=auto's limit), checked."""
    return integer_setting(ccfg["max_clusters"], "clustering.max_clusters", 1)


def motion_separation(prepared: Prepared, a: np.ndarray, b: np.ndarray) -> float:
    """How far apart (voxels, median over up to 2,000 of the points) two velocities of the
    model move the window's points over half its span: below a voxel the volume cannot
    tell the two motions apart."""
    points = prepared.points[:: max(1, len(prepared.points) // 2000)]
    half = 0.5 * float(prepared.t.max() - prepared.t.min())
    va, vb = spatial_velocities(np.array([a, b]))
    grid = prepared.grid
    gap = grid.continuous_index(points - half * va) - grid.continuous_index(points - half * vb)
    return float(np.nanmedian(np.linalg.norm(gap, axis=1)))


def _refit_budget(cfg: Mapping[str, Any]) -> int:
    """``clustering.refit.evals``, an integer >= 0 (0: no refit), after checking
    ``clustering.refit.radius`` is in (0, 1]; a one-line error otherwise."""
    rcfg = cfg["clustering"]["refit"]
    budget, radius = rcfg["evals"], rcfg["radius"]
    if not is_integer(budget, 0):
        raise ValueError(f"clustering.refit.evals must be an integer >= 0 (0: off), got {budget!r}")
    if isinstance(radius, bool) or not isinstance(radius, int | float) or not 0 < radius <= 1:
        raise ValueError(f"clustering.refit.radius must be a number in (0, 1], got {radius!r}")
    return budget


def refit_velocities(
    result: ClusteringResult,
    prepared: Prepared,
    t_ref: float,
    cfg: Mapping[str, Any],
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
    budget = _refit_budget(cfg)
    if budget == 0:
        return result
    rcfg = cfg["clustering"]["refit"]
    index = off_edge_events(prepared, result.thetas.shape[0])
    evaluator = window_objective(prepared, t_ref, cfg, index)
    optimizer = named_optimizer(str(rcfg["optimizer"]), "clustering.refit.optimizer")
    reach = float(rcfg["radius"]) * (bounds[:, 1] - bounds[:, 0])
    thetas = result.thetas.copy()
    for j in range(thetas.shape[0]):
        evaluator.set_weights(result.probabilities[index, j])
        near = np.column_stack(
            [
                np.maximum(bounds[:, 0], thetas[j] - reach),
                np.minimum(bounds[:, 1], thetas[j] + reach),
            ]
        )
        thetas[j], _ = maximize_contrast(evaluator, optimizer, thetas[j], near, budget, seed)
    return replace(result, thetas=thetas)


def _window_objectives(
    prepared: Prepared, t_ref: float, cfg: Mapping[str, Any], optimizer: Any, *, seed: int
) -> tuple[ModelEvaluator, tuple[StepStage, ...]]:
    """The P-step's evaluator over every event and the theta-step's stages, shared by the
    window's starts."""
    evaluator = window_objective(prepared, t_ref, cfg)
    return evaluator, _step_stages(prepared, t_ref, cfg, optimizer, evaluator, seed=seed)


def previous_init(
    previous: np.ndarray,
    prepared: Prepared,
    evaluator: ModelEvaluator,
    ccfg: Mapping[str, Any],
    bounds: np.ndarray,
    *,
    alone: bool,
) -> motion_init.InitResult:
    """The ``previous`` start: the preceding window's final velocities (K x the model's
    components, clipped into this window's search box), each event labelled by one P-step
    at them from uniform memberships.

    Decision: motions change little from one window to the next, and a start that already
    holds every motion keeps a small object that the window's own starts both lose
    (docs/method.md, "The previous window's velocities").
    """
    previous = np.asarray(previous, dtype=np.float64)
    if previous.ndim != 2 or previous.shape[1] < prepared.dim or not np.isfinite(previous).all():
        raise ValueError(
            f"previous velocities must be finite, K x {prepared.dim}; got shape {previous.shape}"
        )
    k = len(previous)
    thetas = np.clip(previous[:, : prepared.dim], bounds[:, 0], bounds[:, 1])
    sigmas, stride = p_step_settings(ccfg, alone=alone)
    uniform = np.full((prepared.points.shape[0], k), 1.0 / k)
    labels = np.argmax(p_step(evaluator, thetas, uniform, sigmas, stride), axis=1)
    return motion_init.InitResult(
        spatial_velocities(thetas), np.full((len(labels), 3), np.nan), 0, False, labels
    )


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


def segment_window(
    window: Recording,
    cfg: Mapping[str, Any],
    optimizer: Any,
    *,
    seed: int,
    on_iteration: Any = None,
    previous: np.ndarray | None = None,
    progress: str | None = None,
) -> WindowResult:
    """Segment one window (two depth maps) into ``cfg['n_clusters']`` motions; with
    ``init.method=auto``, from each start of ``init.auto``, keeping the highest total
    contrast. ``previous`` (K x the model's components): the preceding window's final
    velocities, the ``previous`` start (skipped when None). ``progress``: the window's name
    in a DEBUG line per iteration and per start (None: no such lines)."""
    wanted = cluster_count(cfg)
    k = wanted or (1 if previous is None else len(previous))
    starts = [s for s in init_candidates(cfg["init"]) if s != PREVIOUS or previous is not None]
    if wanted is None and previous is not None:  # auto: the window before's motions, grown
        starts = [PREVIOUS]
    alone = len(window.depth_maps) == 2  # no neighbouring windows in this span
    timings: dict[str, float] = {}
    start = time.perf_counter()
    prepared = prepare(window, cfg)
    check_events_per_cluster(prepared.points.shape[0], k, window.name)
    t_ref = reference_time(prepared.t, cfg["volume"]["t_ref"])
    xy = np.column_stack([window.events.x, window.events.y])[prepared.valid].astype(np.float64)
    timings["prepare"] = time.perf_counter() - start
    ccfg = cfg["clustering"]
    bounds = search_bounds(prepared, float(ccfg["max_displacement"]), depth_change_cap(ccfg))
    objectives: tuple[ModelEvaluator, tuple[StepStage, ...]] | None = None
    kept: tuple[ClusteringResult, motion_init.InitResult, str] | None = None

    def seed_motion(group: np.ndarray, group_seed: int) -> np.ndarray:
        """The image_flow start's single motion of a group of the points."""
        valid = np.zeros(len(window.events), dtype=bool)
        valid[np.flatnonzero(prepared.valid)[group]] = True
        part = replace(
            prepared, points=prepared.points[group], t=prepared.t[group], valid=valid, rest=None
        )
        flow_cfg = {**cfg, "init": {**cfg["init"], "method": "image_flow"}}
        init = initialise(window, part, flow_cfg, 1, bounds, seed=group_seed)
        return init.thetas[0, : prepared.dim]

    timings["init"] = timings["cluster"] = 0.0
    for method in starts:
        start = time.perf_counter()
        if method == PREVIOUS:
            if objectives is None:
                objectives = _window_objectives(prepared, t_ref, cfg, optimizer, seed=seed)
            assert previous is not None  # starts keeps PREVIOUS only with a previous window
            init = previous_init(previous, prepared, objectives[0], ccfg, bounds, alone=alone)
        else:
            method_cfg = {**cfg, "init": {**cfg["init"], "method": method}}
            init = initialise(
                window, prepared, method_cfg, k, bounds, seed=seed, optimizer=optimizer
            )
        timings["init"] += time.perf_counter() - start
        start = time.perf_counter()
        if objectives is None:  # after the first start, so a tile start's volumes are freed
            objectives = _window_objectives(prepared, t_ref, cfg, optimizer, seed=seed)
        result = _cluster_from(
            init,
            prepared,
            objectives,
            cfg,
            optimizer,
            bounds,
            seed=seed,
            on_iteration=_iteration_logger(progress, method, on_iteration),
            alone=alone,
            xy=xy,
            seed_motion=seed_motion,
            auto=wanted is None,
        )
        timings["cluster"] += time.perf_counter() - start
        if progress is not None and len(starts) > 1:
            log.debug("%s, start %s: total contrast %.6g", progress, method, result.total)
        if kept is None or _better(result, kept[0], auto=wanted is None):
            kept = (result, init, method)
    assert kept is not None and objectives is not None  # init_candidates names a start
    result, init, method = kept
    start = time.perf_counter()
    result = refit_velocities(result, prepared, t_ref, cfg, bounds, seed=seed)
    timings["refit"] = time.perf_counter() - start
    sigmas = relabel_sigmas(cfg["clustering"], alone=alone)
    if sigmas is not None:
        start = time.perf_counter()
        scale = relabel_prior_scale(ccfg)
        prior = (
            None
            if scale is None
            else prior_weights(prepared, result.thetas, result.probabilities, scale)
        )
        relabelled = p_step(objectives[0], result.thetas, result.probabilities, sigmas, 1, prior)
        result = replace(result, probabilities=relabelled)
        timings["relabel"] = time.perf_counter() - start
    start = time.perf_counter()
    probabilities = _full_probabilities(result.probabilities, prepared.valid)
    if prepared.rest is not None and len(prepared.rest[0]):
        rest = label_rest(prepared, t_ref, cfg, result, p_step_settings(ccfg, alone=alone))
        probabilities[prepared.rest[2]] = rest
    timings["label"] = time.perf_counter() - start
    labels = assign_labels(
        probabilities[prepared.labelled],
        prepared.labelled,
        float(cfg["clustering"]["min_probability"]),
    )
    return WindowResult(
        labels, probabilities, result, prepared, t_ref, timings, bool(init.fallback), method
    )


def segment_recording(
    recording: Recording,
    cfg: Mapping[str, Any],
    optimizer: Any,
    *,
    seed: int,
    on_iteration: Any = None,
    handover: Handover | None = None,
    progress: bool = True,
    first_window: int | None = None,
    on_window: Callable[[np.ndarray, WindowResult], None] | None = None,
) -> SegmentationResult:
    """Segment every window (each pair of consecutive depth maps); labels cover all events.

    ``progress`` (``output.progress``): an INFO line as each window ends and a DEBUG line
    per iteration (:func:`_window_name` names the window; ``first_window``: in a stream,
    the index of this chunk's first window, as the stream's count is unknown).
    ``on_window(event_indices, result)`` is called as each window ends, its object ids
    linked (a live MLflow run logs it).

    With ``window.context`` = c > 0 each window is clustered together with up to c
    neighbouring windows on each side (EDPA between each event's own pair of maps) and
    keeps the labels of its own events. Decision: a longer span pins the velocities down
    (a moving camera's static scene) while each event is still labelled once, by the span
    centred on its window (docs/method.md, "Context windows"). Each window after the first
    is handed the one before's final velocities (the ``previous`` start of ``init.auto``),
    and its clusters are linked to the objects of the window before
    (:func:`spatialseg.identities.link_clusters`), so an object keeps one id;
    ``handover`` continues a stream's previous chunk (None: a recording's start).
    Events outside every window (before the first or after the last depth map) are -1.
    """
    n = len(recording.events)
    labels = np.full(n, -1, dtype=np.int64)
    results, indices = [], []
    previous = None if handover is None else handover.velocities
    edge = None if handover is None else handover.boundary
    next_id = 0 if edge is None else edge.next_id
    xy = np.column_stack([recording.events.x, recording.events.y])
    windows = _segmented_windows(
        recording.spans(cfg["window"]["context"]),
        len(recording.depth_maps) - 1,
        cfg,
        optimizer,
        seed=seed,
        previous=previous,
        on_iteration=on_iteration,
        first_window=first_window,
        progress=progress,
    )
    for index, inner, res in windows:
        previous = res.clustering.thetas
        own = res.labels[inner]
        ids, next_id = link_clusters(edge, xy[index], own, res.clustering.thetas.shape[0])
        res = replace(res, labels=own, probabilities=res.probabilities[inner], ids=ids)
        labels[index] = np.where(own >= 0, ids[np.maximum(own, 0)], -1)
        edge = boundary(xy[index], labels[index], next_id)
        results.append(res)
        indices.append(index)
        if on_window is not None:
            on_window(index, res)
    probabilities = np.zeros((n, max(next_id, 1)), dtype=np.float32)
    for res, index in zip(results, indices, strict=True):
        probabilities[index[:, None], res.ids[None, :]] = res.probabilities
    carry = None if edge is None or previous is None else Handover(previous, edge)
    return SegmentationResult(labels, probabilities, results, indices, carry)


@dataclass(frozen=True)
class WindowTask:
    """One window's work for a worker: :func:`segment_window`'s arguments (no previous
    window's velocities and no per-iteration hook: windows on other workers are independent)."""

    span: Recording
    cfg: Mapping[str, Any]
    optimizer: Any
    seed: int


def _run_task(task: WindowTask) -> tuple[WindowResult, float]:
    """The task's window segmented, and the seconds it took (a module-level function, so a
    process pool can pickle it)."""
    start = time.perf_counter()
    result = segment_window(task.span, task.cfg, task.optimizer, seed=task.seed)
    return result, time.perf_counter() - start


def _segmented_windows(
    spans: Iterator[tuple[np.ndarray, Recording, np.ndarray]],
    count: int,
    cfg: Mapping[str, Any],
    optimizer: Any,
    *,
    seed: int,
    previous: np.ndarray | None,
    on_iteration: Any,
    first_window: int | None,
    progress: bool,
) -> Iterator[tuple[np.ndarray, np.ndarray, WindowResult]]:
    """The ``count`` spans (``(event_indices, span, inner)`` of :meth:`Recording.spans`,
    made one at a time) segmented, in order, each as ``(event_indices, inner, result)``:
    one after the other, each handed the one before's velocities (the ``previous`` start),
    or with ``window.parallel`` on workers that see no other window
    (:mod:`spatialseg.executors`; every span is then made up front). With ``progress``, an
    INFO line as each ends (``first_window`` not None: a stream's chunk, count unknown) and,
    on a terminal, a bar over two windows or more (:mod:`spatialseg.progress`)."""
    engine, workers = check_parallel(cfg["window"]["parallel"], cfg["window"]["workers"])
    seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=max(count, 1))
    total = count if first_window is None else None
    names = [_window_name((first_window or 0) + w, total) for w in range(count)]
    if engine == "none":
        hooks = names if progress else [None] * count  # DEBUG lines per iteration
        done = _serial_windows(spans, cfg, optimizer, seeds, previous, on_iteration, hooks)
    else:
        spans = list(spans)
        tasks = [
            WindowTask(span, cfg, optimizer, int(s))
            for (_, span, _), s in zip(spans, seeds, strict=False)
        ]
        runs = map_in_order(_run_task, tasks, engine=engine, workers=workers)
        done = ((window, *run) for window, run in zip(spans, runs, strict=True))
    with progress_bar(count, "window", enabled=progress and total is not None and count > 1) as bar:
        for name, ((index, span, inner), res, seconds) in zip(names, done, strict=True):
            if progress:
                _log_window(name, len(index), len(span.events), res, seconds)
            bar(1)
            yield index, inner, res


def _serial_windows(
    spans: Iterator[tuple[np.ndarray, Recording, np.ndarray]],
    cfg: Mapping[str, Any],
    optimizer: Any,
    seeds: np.ndarray,
    previous: np.ndarray | None,
    on_iteration: Any,
    names: list[str | None],
) -> Iterator[tuple[tuple[np.ndarray, Recording, np.ndarray], WindowResult, float]]:
    """The spans segmented here, one after the other, each from the one before's velocities
    too (the ``previous`` start); each span with its result and seconds."""
    for name, window, window_seed in zip(names, spans, seeds, strict=False):
        span = window[1]
        start = time.perf_counter()
        res = segment_window(
            span,
            cfg,
            optimizer,
            seed=int(window_seed),
            on_iteration=on_iteration,
            previous=previous,
            progress=name,
        )
        previous = res.clustering.thetas
        yield window, res, time.perf_counter() - start


def segment_loaded(
    recording: Recording,
    cfg: Mapping[str, Any],
    optimizer: Any,
    *,
    seed: int,
    on_iteration: Any = None,
    handover: Handover | None = None,
    progress: bool = True,
    first_window: int | None = None,
    on_window: Callable[[np.ndarray, WindowResult], None] | None = None,
) -> tuple[Recording, SegmentationResult]:
    """A loaded recording through the ``depth`` source and :func:`segment_recording`
    (``handover``: a stream's previous chunk; ``progress``, ``first_window``: its progress
    lines); the result covers every input event. Also
    returns the recording the result describes: the input with the depth maps used.

    Every run (command line, :func:`spatialseg.segment`, experiments) comes through here,
    so the units are checked here, before any work: times in seconds, depths in metres,
    events and depth maps on one clock (:func:`spatialseg.recording.check_depth_maps`).
    A process's first segmentation announces the kernels' compilation on a fresh install
    (:func:`spatialseg.compilation.announce_compilation`)."""
    from spatialseg.depth import with_configured_depth

    check_event_times(recording)  # before a depth source spends work on the events
    recording = with_configured_depth(recording, cfg)
    check_depth_maps(recording)
    with announce_compilation():
        seg = segment_recording(
            recording,
            cfg,
            optimizer,
            seed=seed,
            on_iteration=on_iteration,
            handover=handover,
            progress=progress,
            first_window=first_window,
            on_window=on_window,
        )
    return recording, seg


def _window_name(index: int, count: int | None) -> str:
    """``window 2/3`` (its index as in result.json, of the recording's count), or
    ``window 2`` in a stream, whose count is unknown."""
    return f"window {index}" if count is None else f"window {index}/{count}"


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


def _log_window(name: str, events: int, span: int, result: WindowResult, seconds: float) -> None:
    """The INFO line as a window ends: its events (``span``: with its context windows'),
    clusters, iterations and time."""
    extra = f" ({span} with its context)" if span > events else ""
    log.info(
        "%s: %d events%s, %s, %d iterations, %.1f s",
        name,
        events,
        extra,
        plural(result.clustering.thetas.shape[0], "cluster"),
        result.clustering.iterations,
        seconds,
    )
