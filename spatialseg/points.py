"""The model stage for one window: its events as points in the model's space, and the volume.

Recording window in; :class:`Prepared` out (points M x 3 in metres, or pixels for the planar
model, their times, the voxel grid, the events kept aside), then the search box (dim x 2),
the warp's reference time and :class:`ModelEvaluator`, one cluster's contrast of the volume.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from spatialseg import edpa
from spatialseg.denoise import denoise_mask
from spatialseg.grid import VoxelGrid, grid_around, project_jacobian
from spatialseg.objectives import make_objective
from spatialseg.recording import Camera, Recording
from spatialseg.settings import ClusteringSettings, DenoiseSettings, Settings, smoothing
from spatialseg.volume import VolumeObjective

__all__ = [
    "ModelEvaluator",
    "Prepared",
    "fit_sample",
    "fit_support",
    "image_jacobian",
    "off_edge_events",
    "p_step_settings",
    "planar_points",
    "prepare",
    "reference_time",
    "relabel_sigmas",
    "search_bounds",
    "seeded_subset",
    "spatial_velocities",
    "volume_grid",
    "volume_objective",
    "voxel_shifts",
    "window_objective",
]


@dataclass(frozen=True, eq=False)
class Prepared:
    """A window's events as points in the model's space, ready for the volume.

    ``points`` (M x 3) are the usable events (``valid`` marks them among the window's N);
    ``dim`` is the number of velocity components the model estimates (3 spatial, 2 planar).
    ``search_extent`` (3,) is the extent the search box is measured on (:func:`search_bounds`);
    None means the grid's. ``on_edge`` (M,) marks points whose depth came from an occlusion
    edge (:func:`spatialseg.edpa.occlusion_edges`); None: no such points. ``rest``: the
    points, times and mask (N,) of the events with depth left out of the fit (the
    background filter's rejects and, in a dense window, those its sample left out:
    :func:`fit_sample`), labelled from the fitted motions at the end; None: none.
    ``unsampled`` (N,) marks the latter; None: no sample was drawn.
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
    unsampled: np.ndarray | None = None

    @property
    def labelled(self) -> np.ndarray:
        """The window's events that get a label (N,): the fitted ones and the ``rest``."""
        return self.valid if self.rest is None else self.valid | self.rest[2]


def prepare(window: Recording, settings: Settings, *, seed: int = 0) -> Prepared:
    """Lift the window's events into the model's space and build the voxel grid around the
    events the motions are fitted on (:func:`fit_support`; in a dense window a sample of
    them drawn with ``seed``, :func:`fit_sample`, on the same grid); the other events with
    depth are kept aside (``Prepared.rest``) and labelled at the end."""
    vol, lifting = settings.volume, settings.edpa
    if len(window.events) == 0:
        raise ValueError(f"{window.name}: the window has no events; choose a longer window")
    support = fit_support(window, settings.denoise)
    per_voxel = settings.clustering.fit_per_voxel
    if settings.model.name == "planar":
        prepared = planar_points(window, settings.model.voxel_scale, support)
        sample = fit_sample(prepared.valid, prepared.points, prepared.grid, per_voxel, seed)
        if sample is None:
            return prepared
        unsampled = prepared.valid & ~sample
        return replace(planar_points(window, prepared.grid, sample), unsampled=unsampled)
    lifted = edpa.lift(
        window,
        unknown_depth=lifting.unknown_depth,
        fill_radius=lifting.fill_radius,
        edge_ratio=lifting.edge_ratio,
    )
    fit = support[lifted.valid]
    if not fit.any():
        fit[:] = True  # nothing supported: fit on every event with depth
    fitted = lifted.points[fit]
    grid = volume_grid(fitted, window.camera, settings)
    extent = _search_extent(fitted, grid, vol.margin)
    sample = fit_sample(fit, fitted, grid, per_voxel, seed)
    unsampled = None
    if sample is not None:
        unsampled = np.zeros_like(lifted.valid)
        unsampled[np.flatnonzero(lifted.valid)[fit & ~sample]] = True
        fit, fitted = sample, lifted.points[sample]
    valid = lifted.valid.copy()
    valid[np.flatnonzero(valid)[~fit]] = False
    rest_valid = lifted.valid & ~valid
    on_edge = lifted.on_edge[lifted.valid][fit]
    rest = (lifted.points[~fit], lifted.t[~fit], rest_valid)
    return Prepared(fitted, lifted.t[fit], valid, grid, 3, "m/s", extent, on_edge, rest, unsampled)


def fit_support(window: Recording, denoise: DenoiseSettings) -> np.ndarray:
    """The window's events the motions are fitted on (N,): with ``denoise.enabled``, those
    the background-activity filter supports (:func:`spatialseg.denoise.denoise_mask`), else
    all. The others are labelled at the end from the fitted motions.

    Decision: an isolated noise event carries no motion but, lifted to the depth behind
    it, stretches the grid and blurs every volume; 4.6 % of noise turned a three-object
    scene from 1.0 to 0.73. Dropping such events (the filter's usual use) loses the signal
    events it rejects too; leaving them out of the fit alone keeps their labels."""
    support = np.ones(len(window.events), dtype=bool)
    if denoise.enabled:
        support = denoise_mask(window.events, radius=denoise.radius, window=denoise.window)
        support |= not support.any()  # a window rejected whole (a few events): fit them all
    return support


def planar_points(
    window: Recording, scale: float | VoxelGrid, support: np.ndarray | None = None
) -> Prepared:
    """Image-plane embedding (Stoffregen et al. 2019): points (x, y, 0) in pixels, no depth;
    the ``support``ed events (default all) are fitted, the others kept aside. ``scale``:
    the voxel side in pixels, the grid then built around the fitted points; or the grid."""
    ev = window.events
    every = np.column_stack([ev.x, ev.y, np.zeros(len(ev))]).astype(np.float64)
    fit = np.ones(len(ev), dtype=bool) if support is None else support  # fit_support: never empty
    points = every[fit]
    grid = scale if isinstance(scale, VoxelGrid) else _planar_grid(points, scale)
    rest = (every[~fit], ev.t[~fit], ~fit)
    return Prepared(points, ev.t[fit], fit.copy(), grid, 2, "px/s", rest=rest)


def _planar_grid(points: np.ndarray, xy_scale: float) -> VoxelGrid:
    """The planar model's grid: ``xy_scale``-pixel voxels over the points, two voxels beyond."""
    lo = points.min(axis=0) - np.array([2 * xy_scale, 2 * xy_scale, 0.0])
    hi = points.max(axis=0) + np.array([2 * xy_scale, 2 * xy_scale, 0.0])
    shape = (*(np.ceil((hi[:2] - lo[:2]) / xy_scale).astype(int) + 1), 1)
    return VoxelGrid(origin=lo, voxel_size=np.array([xy_scale, xy_scale, 1.0]), shape=shape)


def fit_sample(
    fit: np.ndarray, points: np.ndarray, grid: VoxelGrid, per_voxel: float | None, seed: int
) -> np.ndarray | None:
    """``fit`` (a mask of the events the motions are fitted on, at ``points``, K x 3 for
    its K events) with at most ``per_voxel`` events per voxel those points occupy in
    ``grid`` (:meth:`VoxelGrid.occupied`, unwarped) kept, drawn uniformly with ``seed``;
    None when it holds no more (or ``per_voxel`` is None). The others are labelled once
    at the end.

    Decision: a motion's contrast peak is set by how its events line up in the voxels they
    fall in, so more events per such voxel sharpen little while every pass costs them all;
    and the defaults were chosen at about ten (the dev split's spans), so a denser window
    fitted whole lost accuracy where its sample did not (docs/results.md, session 54). The
    voxels the events occupy, not the grid's, measure it: a grid is mostly empty (its depth
    bins span the scene's depth, an object one or two), so events per voxel of the grid
    would call a deep scene sparse at any event count."""
    if per_voxel is None or len(points) <= per_voxel:
        return None
    limit = int(per_voxel * grid.occupied(points))
    if len(points) <= limit:
        return None
    kept = np.zeros_like(fit)
    kept[seeded_subset(np.flatnonzero(fit), limit, seed)] = True
    return kept


def seeded_subset(pool: np.ndarray | int, size: int, seed: int) -> np.ndarray:
    """``size`` of ``pool``'s entries (of ``range(pool)`` for a count) drawn uniformly
    without replacement with ``seed``, in increasing order: the one way the method samples
    events (the fit, the theta-step, the flow start)."""
    return np.sort(np.random.default_rng(seed).choice(pool, size, replace=False))


def volume_grid(
    points: np.ndarray, camera: Camera, settings: Settings, coordinates: str | None = None
) -> VoxelGrid:
    """The spatial model's voxel grid around ``points`` in ``volume.coordinates`` (or
    ``coordinates``): ``image`` (pixels and inverse depth, default) or ``metric`` (metres).

    Decision: on an image grid a voxel has the same footprint in the image at every depth,
    so near and far events are equally sharp when compensated, and an object moving in
    depth is sharpened by its expansion in the image, resolved to a pixel, instead of by
    its few depth bins only (``docs/volume.md`` has the measurements).
    """
    vol = settings.volume
    coordinates = coordinates or vol.coordinates
    size = edpa.voxel_size(
        points,
        camera,
        xy_scale=settings.model.voxel_scale,
        z_bins=vol.z_bins,
        coordinates=coordinates,
        depth_error=vol.depth_error,
    )
    projection = camera.intrinsics if coordinates == "image" else None
    return grid_around(points, size, vol.margin, vol.max_voxels, projection)


def _search_extent(points: np.ndarray, grid: VoxelGrid, margin: float) -> np.ndarray | None:
    """Per axis (metres), the fitted points' extent with ``margin`` added on each side, for
    an image grid, which is not in metres; None for a metric grid, built around the same
    points with the same margin, whose own extent is then measured (it is at least as
    large: a voxel more, rounded up)."""
    if grid.projection is None:
        return None
    return (1 + 2 * margin) * (points.max(axis=0) - points.min(axis=0))


def search_bounds(
    prepared: Prepared,
    max_displacement: float,
    max_depth_change: float | None = None,
    windows: int = 1,
) -> np.ndarray:
    """Velocity box: a motion may move a point at most ``max_displacement`` times the grid's
    extent (``prepared.search_extent`` when set) along each axis over one window (dim x 2,
    centred on zero); with ``max_depth_change`` (spatial model) ``|vz|`` is also capped so a
    motion changes the points' median depth by at most that share over one window.
    ``windows``: how many windows the points span (a window with its context windows); the
    box is measured over one of them.

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
    duration = max(float(prepared.t.max() - prepared.t.min()), 1e-9) / windows
    half = max_displacement * extent[: prepared.dim] / duration
    if max_depth_change is not None and prepared.dim == 3:
        depth = float(np.median(prepared.points[:, 2]))
        half[2] = min(half[2], max_depth_change * depth / duration)
    return np.column_stack([-half, half])


def voxel_shifts(prepared: Prepared, velocities: np.ndarray, probes: int) -> np.ndarray:
    """Where each of the model's velocities (H x dim) carries up to ``probes`` of the
    window's points (every n-th) over half the window's span, in voxels of its grid
    (H x P x 3): what the volume sees of a velocity, so two are compared by their shifts."""
    points = prepared.points[:: max(1, len(prepared.points) // probes)]
    half = 0.5 * float(prepared.t.max() - prepared.t.min())
    moved = spatial_velocities(velocities)
    return np.stack([prepared.grid.continuous_index(points - half * v) for v in moved])


def reference_time(t: np.ndarray, mode: str) -> float:
    """The warp's reference time: the window's start or its middle."""
    if mode == "start":
        return float(t.min())
    if mode == "middle":
        return float(0.5 * (t.min() + t.max()))
    raise ValueError(f"volume.t_ref must be 'start' or 'middle', got {mode!r}")


def image_jacobian(prepared: Prepared, camera: Camera) -> np.ndarray:
    """Each point's pinhole Jacobian ``d(u, v) / d(X, Y, Z)`` (M x 2 x 3): how a 3-D velocity
    moves its event across the image (:func:`~spatialseg.grid.project_jacobian`'s first two
    rows), the link the flow and planar starts and the image speed use."""
    return project_jacobian(prepared.points, camera.intrinsics)[:, :2]


def spatial_velocities(thetas: np.ndarray) -> np.ndarray:
    """Velocities of a model's components (K x 2 planar, K x 3 spatial) as K x 3, the
    missing vz zero: the form the volume and the results take."""
    thetas = np.asarray(thetas, dtype=np.float64)
    full = np.zeros((len(thetas), 3))
    full[:, : thetas.shape[1]] = thetas
    return full


def off_edge_events(prepared: Prepared, k: int) -> np.ndarray:
    """Indices of the points off occlusion edges (their depth is reliable), or of every point
    when fewer than ``k`` are off them (or no edges are marked), so each cluster has events."""
    if prepared.on_edge is not None and np.count_nonzero(~prepared.on_edge) >= k:
        return np.flatnonzero(~prepared.on_edge)
    return np.arange(prepared.points.shape[0])


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

    @property
    def order(self) -> np.ndarray:
        """The volume's event order (:attr:`~spatialseg.volume.VolumeObjective.order`)."""
        return self.inner.order

    def set_weights(self, weights: np.ndarray, *, ordered: bool = False) -> None:
        """Memberships of the cluster being optimised (in :attr:`order` if ``ordered``)."""
        self.inner.set_weights(weights, ordered=ordered)

    def value(self, theta: np.ndarray) -> float:
        """Contrast of the volume warped by ``theta``."""
        return self.inner.value(self._full(theta))

    def grad(self, theta: np.ndarray) -> np.ndarray:
        """Analytic gradient of the contrast with respect to the model's components."""
        return self.inner.grad(self._full(theta))[: self.dim]

    def batch_value(self, thetas: np.ndarray) -> np.ndarray:
        """Contrast of many candidate velocities (n x dim) in one parallel call."""
        return self.inner.batch_value(spatial_velocities(thetas))

    def group_values(self, thetas: np.ndarray) -> np.ndarray:
        """Contrast of each event group alone (the volume's ``groups``) under each candidate
        velocity (n x dim): groups x n."""
        return self.inner.group_values(spatial_velocities(thetas))

    def group(self, g: int) -> ModelEvaluator:
        """Group ``g``'s events alone, voting into this evaluator's volumes: use the two one
        at a time (:meth:`~spatialseg.volume.VolumeObjective.group`)."""
        return ModelEvaluator(self.inner.group(g), self.dim)

    def volume(self, theta: np.ndarray) -> np.ndarray:
        """The volume of warped events for ``theta``."""
        return self.inner.volume(self._full(theta))

    def p_step(
        self,
        theta: np.ndarray,
        sigma: float | Sequence[float],
        stride: int = 1,
        *,
        ordered: bool = False,
    ) -> tuple[np.ndarray, float]:
        """The volume for ``theta``, smoothed by ``sigma`` voxels (one number, or x, y,
        depth), at each warped event (in :attr:`order` if ``ordered``), and the contrast of
        the volume (the P-step)."""
        return self.inner.p_step(self._full(theta), sigma, stride, ordered=ordered)

    def p_step_at(
        self,
        theta: np.ndarray,
        sigma: float | Sequence[float],
        stride: int,
        points: np.ndarray,
        dt: np.ndarray,
    ) -> np.ndarray:
        """The P-step's smoothed volume for ``theta`` at other events (``points``, ``dt``),
        each warped by ``theta`` (:meth:`VolumeObjective.p_step_at`)."""
        return self.inner.p_step_at(self._full(theta), sigma, stride, points, dt)


def window_objective(
    prepared: Prepared,
    t_ref: float,
    settings: Settings,
    index: Any = slice(None),
    groups: np.ndarray | None = None,
) -> ModelEvaluator:
    """The configured objective (one cluster's contrast, weights set by the caller) over the
    window's events ``index`` (default all) on the window's grid; ``groups``: a group
    number per selected event, for :meth:`ModelEvaluator.group_values`
    (:func:`volume_objective`)."""
    volume = volume_objective(
        prepared.points[index], prepared.t[index] - t_ref, prepared.grid, settings, groups
    )
    return ModelEvaluator(volume, prepared.dim)


def volume_objective(
    points: np.ndarray,
    dt: np.ndarray,
    grid: VoxelGrid,
    settings: Settings,
    groups: np.ndarray | None = None,
) -> VolumeObjective:
    """The volume of ``points`` warped over ``dt`` on ``grid``, judged by the configured
    objective (``objective.name``, ``objective.blur_sigma``) and stored in ``volume.dtype``
    (float32 halves the memory per event, float64 is the more accurate); ``groups``: see
    :class:`~spatialseg.volume.VolumeObjective`."""
    objective = settings.objective
    return VolumeObjective(
        points,
        dt,
        grid,
        make_objective(name=objective.name, blur_sigma=objective.blur_sigma),
        dtype=settings.volume.dtype,
        groups=groups,
    )


def p_step_settings(
    clustering: ClusteringSettings, *, alone: bool
) -> tuple[tuple[float, float, float], int]:
    """The P-step's smoothing (x, y, depth voxels) and grid stride:
    ``clustering.p_step_sigma`` and ``p_step_stride`` for a window clustered with neighbouring
    windows, ``clustering.p_step_alone`` for one clustered alone.

    Decision: a window alone holds a third of a three-window span's events, and its volumes
    want the wider blur; the span wants the narrower one, which keeps the static scene's
    cluster off the events around a moving object (docs/method.md, "Defaults for a moving
    camera")."""
    if alone:
        own = clustering.p_step_alone
        return smoothing(own.sigma, "clustering.p_step_alone.sigma"), own.stride
    return smoothing(clustering.p_step_sigma, "clustering.p_step_sigma"), clustering.p_step_stride


def relabel_sigmas(
    clustering: ClusteringSettings, *, alone: bool
) -> tuple[float, float, float] | None:
    """``clustering.relabel_sigma`` as (x, y, depth) voxels, or None (off, and always for a
    window clustered alone).

    Decision: once the velocities are final (after the refit), one more P-step at them,
    smoothed less than the loop's, gives the labels. The loop needs its wider blur while
    velocities and memberships still move; at the final velocities a sharper response
    follows an object's outline more closely. A window alone holds a third of the events
    per voxel, and there it cost accuracy (docs/method.md, "Relabelling")."""
    if alone or clustering.relabel_sigma is None:
        return None
    return smoothing(clustering.relabel_sigma, "clustering.relabel_sigma")
