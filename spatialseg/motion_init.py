"""Initial motions from three time surfaces and k-means (METHOD.md section 2).

Each lifted event is dropped onto three time surfaces, S1 = (X, Y), S2 = (Y, Z) and
S3 = (Z, X), the cell grids of the volume's voxel grid; each cell keeps the latest timestamp
that fell on it. A plane ``t = a u + b v + c`` fitted around an event's cell gives the
constraint ``a v_u + b v_v = 1`` (Benosman et al. 2014). A time surface only sees the
motion along its gradient (the aperture problem), and S2, S3 project the scene along X or
Y, which collapses the texture, so for a fronto-parallel surface they mostly see ``vz``.
The per-event system of the (up to) three constraints is therefore often rank-deficient;
its minimum-norm solution is the event's 3-D *normal flow*. k-means over the normal flows
gives a first partition, which a k-means on the constraints themselves then refines (see
:func:`_refine_clusters`). The image-plane model (``dim = 2``: points (x, y, 0) in pixels)
uses S1 alone and gives (vx, vy, 0) in px/s. Given each event's ``lift``, the derivative of
its image velocity with respect to a 3-D velocity, the S1 constraints are re-expressed on
the 3-D velocity (:func:`lift_constraints`), so that events at different depths sharing one
3-D motion (a translating camera's static scene) share one cluster.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from spatialseg.grid import VoxelGrid
from spatialseg.points import seeded_subset

__all__ = [
    "PLANES",
    "InitResult",
    "initial_motions",
    "kmeans",
    "lift_constraints",
    "lift_velocities",
    "time_surfaces",
    "without_depth_motion",
]

#: The axis pairs (u, v) of the time surfaces S1 = (X, Y), S2 = (Y, Z), S3 = (Z, X).
PLANES = ((0, 1), (1, 2), (2, 0))
#: k-means stops when its centres move less than this share of the points' mean variance
#: per axis (squared distance, summed over the centres), as scikit-learn's ``tol``.
KMEANS_TOLERANCE = 1e-4


@dataclass(frozen=True, eq=False)
class InitResult:
    """Initial motions ``thetas`` (K, 3) and the per-event flows behind them (m/s; px/s for
    the image-plane model).

    ``flows`` (M, 3) is each event's normal flow, NaN where the event was not sampled or
    gave no valid estimate; ``n_valid`` counts the finite rows. ``labels`` (M,) is the
    initial motion whose velocity best satisfies each such event's own constraints (-1
    elsewhere). ``fallback`` is True when too few valid flows existed and ``thetas`` were
    spread around their mean instead (then every label is -1).
    """

    thetas: np.ndarray
    flows: np.ndarray
    n_valid: int
    fallback: bool
    labels: np.ndarray


def _check_points(points: np.ndarray, t: np.ndarray) -> None:
    """Raise a one-line ValueError for empty, mis-shaped or non-finite points and times."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be an M x 3 array, got shape {points.shape}")
    if t.shape != (len(points),):
        raise ValueError(f"t must have one time per point ({len(points)}), got shape {t.shape}")
    if not len(points):
        raise ValueError("no points to estimate motions from; the window is empty")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(t))):
        raise ValueError("points or t contain NaN or inf; drop events without depth first")


def _check_parameters(
    t: np.ndarray,
    n_clusters: int,
    radius: int,
    min_points: int,
    max_condition: float,
    max_speed: float,
    max_events: int,
    n_init: int,
    min_r2: float,
) -> None:
    """Raise a one-line ValueError for a zero time span or a parameter out of range."""
    checks = (
        (t.max() > t.min(), "all events share one timestamp; a motion needs a time span"),
        (
            int(n_clusters) == n_clusters and n_clusters >= 1,
            f"n_clusters must be an integer >= 1, got {n_clusters}",
        ),
        (int(radius) == radius and radius >= 1, f"radius must be an integer >= 1, got {radius}"),
        (
            int(min_points) == min_points and min_points >= 3,
            f"min_points must be an integer >= 3 (a plane has 3 unknowns), got {min_points}",
        ),
        (max_condition >= 1.0, f"max_condition must be >= 1, got {max_condition}"),
        (max_speed > 0.0, f"max_speed must be > 0 m/s, got {max_speed}"),
        (
            int(max_events) == max_events and max_events >= 1,
            f"max_events must be an integer >= 1, got {max_events}",
        ),
        (int(n_init) == n_init and n_init >= 1, f"n_init must be an integer >= 1, got {n_init}"),
        (0.0 <= min_r2 <= 1.0, f"min_r2 must lie in [0, 1], got {min_r2}"),
    )
    for ok, message in checks:
        if not ok:
            raise ValueError(message)


def _cells(points: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """Integer voxel index (M, 3) of each point (nearest voxel centre); raise if outside."""
    cells = np.rint(grid.continuous_index(points)).astype(np.int64)
    if np.any(cells < 0) or np.any(cells >= np.asarray(grid.shape)):
        raise ValueError("points lie outside the voxel grid; build it with grid_around(points)")
    return cells


def _surfaces_from_cells(
    cells: np.ndarray, t: np.ndarray, shape: tuple[int, int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Latest time per cell on S1, S2, S3; -inf marks a cell no event fell on."""
    surfaces = []
    for u, v in PLANES:
        surface = np.full((shape[u], shape[v]), -np.inf)
        np.maximum.at(surface, (cells[:, u], cells[:, v]), t)
        surfaces.append(surface)
    return surfaces[0], surfaces[1], surfaces[2]


def time_surfaces(
    points: np.ndarray, t: np.ndarray, grid: VoxelGrid
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The time surfaces S1 (nx, ny), S2 (ny, nz), S3 (nz, nx): latest ``t`` per cell, -inf
    where no event fell (so any time origin works, including negative ``t - t_ref``)."""
    points = np.asarray(points, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    _check_points(points, t)
    return _surfaces_from_cells(_cells(points, grid), t, grid.shape)


def _window_moments(
    surface: np.ndarray,
    cu: np.ndarray,
    cv: np.ndarray,
    cell_size: tuple[float, float],
    radius: int,
) -> tuple[np.ndarray, ...]:
    """Hit count and centred second moments (uu, vv, uv, ut, vt, tt) of the hit cells in the
    (2r+1)^2 window around each cell, u, v in metres, t relative to the centre cell's time.

    One window offset at a time, so memory stays O(E) for any radius; times relative to
    the event's own cell keep the sums exact for large absolute times.
    """
    nu, nv = surface.shape
    t0 = surface[cu, cv]
    raw = np.zeros((10, len(cu)))  # n, u, v, t, uu, vv, uv, ut, vt, tt
    for i in range(-radius, radius + 1):
        for j in range(-radius, radius + 1):
            iu, iv = cu + i, cv + j
            inside = (iu >= 0) & (iu < nu) & (iv >= 0) & (iv < nv)
            value = surface[np.clip(iu, 0, nu - 1), np.clip(iv, 0, nv - 1)]
            hit = inside & np.isfinite(value)
            dt = np.where(hit, value - t0, 0.0)
            u, v = i * cell_size[0], j * cell_size[1]
            terms = (1.0, u, v, dt, u * u, v * v, u * v, u * dt, v * dt, dt * dt)
            raw += hit * np.stack(np.broadcast_arrays(*terms))
    n, su, sv, st, suu, svv, suv, sut, svt, stt = raw
    k = np.maximum(n, 1.0)
    return (
        n,
        suu - su * su / k,
        svv - sv * sv / k,
        suv - su * sv / k,
        sut - su * st / k,
        svt - sv * st / k,
        stt - st * st / k,
    )


def _plane_fits(
    surface: np.ndarray,
    cu: np.ndarray,
    cv: np.ndarray,
    cell_size: tuple[float, float],
    *,
    radius: int,
    min_points: int,
    max_condition: float,
    min_r2: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane ``t = a u + b v + c`` around each cell: gradients (E, 2) in s/m
    and validity (at least ``min_points`` hit cells, a cell layout with singular-value
    ratio <= ``max_condition``, coefficient of determination R^2 >= ``min_r2``)."""
    n, cuu, cvv, cuv, cut, cvt, ctt = _window_moments(surface, cu, cv, cell_size, radius)
    det = cuu * cvv - cuv * cuv
    half_trace = 0.5 * (cuu + cvv)
    spread = np.sqrt(np.maximum(half_trace**2 - det, 0.0))
    lam_max, lam_min = half_trace + spread, half_trace - spread
    well_posed = (lam_min > 0) & (lam_max <= max_condition**2 * lam_min)
    safe_det = np.where(well_posed, det, 1.0)
    a = (cvv * cut - cuv * cvt) / safe_det
    b = (cuu * cvt - cuv * cut) / safe_det
    r2 = np.where(ctt > 0, (a * cut + b * cvt) / np.where(ctt > 0, ctt, 1.0), 0.0)
    ok = (n >= min_points) & well_posed & (ctt > 0) & (r2 >= min_r2)
    return np.column_stack((a, b)), ok


def _constraints(
    gradients: list[np.ndarray], valid: list[np.ndarray], max_speed: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per-event constraint rows A (E, 3, 3) and right-hand sides b (E, 3), in m/s, from the
    gradients of the first ``len(gradients)`` surfaces.

    Row k of an event is ``n . theta = s`` with ``n = g/|g|`` and ``s = 1/|g|`` for the
    gradient g of surface k (the constraint ``g . theta = 1`` divided by ``|g|``), so every
    row weighs equally in m/s. Missing or rejected surfaces give zero rows; so does a
    gradient flatter than ``1/max_speed``, which only says the normal speed exceeds
    ``max_speed``.
    """
    e = len(gradients[0])
    a = np.zeros((e, 3, 3))
    b = np.zeros((e, 3))
    for k, (g, ok) in enumerate(zip(gradients, valid, strict=True)):
        u, v = PLANES[k]
        norm = np.hypot(g[:, 0], g[:, 1])
        use = ok & np.isfinite(norm) & (norm > 0) & (norm >= 1.0 / max_speed)
        a[use, k, u] = g[use, 0] / norm[use]
        a[use, k, v] = g[use, 1] / norm[use]
        b[use, k] = 1.0 / norm[use]
    return a, b


def _normal_flows(
    a: np.ndarray, b: np.ndarray, *, max_condition: float, max_speed: float
) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-norm solution (E, 3) of each event's constraints and its validity.

    Decision: directions with a singular value below ``s_max / max_condition`` are treated
    as unobserved (truncated pseudo-inverse) instead of discarding the event, because the
    system is rank-deficient by construction for most events (S2 and S3 both see mainly
    ``vz``). Valid: at least one constraint and a finite speed <= ``max_speed``.
    """
    flows = np.einsum("eij,ej->ei", np.linalg.pinv(a, rcond=1.0 / max_condition), b)
    speed = np.linalg.norm(flows, axis=1)
    ok = np.any(a != 0, axis=(1, 2)) & np.isfinite(speed) & (speed <= max_speed)
    return flows, ok


def _pooled_velocity(a: np.ndarray, b: np.ndarray, max_condition: float) -> np.ndarray:
    """The velocity that best satisfies all given constraint rows (least squares, m/s)."""
    rows, rhs = a.reshape(-1, 3), b.reshape(-1)
    return np.linalg.lstsq(rows, rhs, rcond=1.0 / max_condition)[0]


def _constraint_cost(a: np.ndarray, b: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Squared constraint residual (E, K) of each event under each candidate velocity."""
    return ((np.einsum("eij,kj->eki", a, centres) - b[:, None, :]) ** 2).sum(axis=2)


def kmeans(
    points: np.ndarray, n_clusters: int, *, n_init: int, seed: int, max_iter: int = 300
) -> tuple[np.ndarray, np.ndarray]:
    """Lloyd's k-means of ``points`` (N, D) from ``n_init`` k-means++ seedings drawn with
    ``seed``; the partition of least inertia wins: (labels (N,), centres (K, D)).

    Decision: the flow start partitions a few thousand 3-vectors, which takes milliseconds
    here; scikit-learn's KMeans did the same but its import cost about a second per run.
    """
    rng = np.random.default_rng(seed)
    best: tuple[np.ndarray, np.ndarray, float] | None = None
    for _ in range(n_init):
        labels, centres, inertia = _lloyd(
            points, _kmeans_plus_plus(points, n_clusters, rng), max_iter
        )
        if best is None or inertia < best[2]:
            best = (labels, centres, inertia)
    assert best is not None
    return best[0], best[1]


def _squared_distances(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(N, K) squared Euclidean distances between ``points`` (N, D) and ``centres`` (K, D),
    expanded as |x|^2 - 2 x.c + |c|^2 (one matrix product; clipped at zero)."""
    cross = points @ centres.T
    squared = (points**2).sum(axis=1)[:, None] - 2.0 * cross + (centres**2).sum(axis=1)[None, :]
    return np.maximum(squared, 0.0)


def _kmeans_plus_plus(points: np.ndarray, n_clusters: int, rng: np.random.Generator) -> np.ndarray:
    """Greedy k-means++ seeding (Arthur and Vassilvitskii, 2007): each next centre is the best
    of ``2 + ln K`` candidates drawn in proportion to the squared distance to the nearest
    centre so far, best meaning the lowest total of those distances once it is added."""
    trials = 2 + int(np.log(n_clusters))
    centres = [points[rng.integers(len(points))]]
    nearest = _squared_distances(points, centres[0][None])[:, 0]
    for _ in range(1, n_clusters):
        total = float(nearest.sum())
        if total > 0:
            drawn = np.searchsorted(np.cumsum(nearest), rng.random(trials) * total, side="right")
            candidates = np.minimum(drawn, len(points) - 1)
        else:  # every point sits on a centre
            candidates = rng.integers(len(points), size=trials)
        reach = np.minimum(nearest[None, :], _squared_distances(points, points[candidates]).T)
        pick = int(reach.sum(axis=1).argmin())
        centres.append(points[candidates[pick]])
        nearest = reach[pick]
    return np.array(centres, dtype=np.float64)


def _lloyd(
    points: np.ndarray, centres: np.ndarray, max_iter: int
) -> tuple[np.ndarray, np.ndarray, float]:
    """Lloyd iterations from ``centres`` until the partition stops changing, the centres move
    less than :data:`KMEANS_TOLERANCE` in total (squared, relative to the points' mean
    variance per axis) or ``max_iter``: (labels, centres, inertia). A cluster that empties
    takes the point farthest from its centre among clusters of two or more."""
    centres = centres.copy()
    labels = np.full(len(points), -1)
    tolerance = KMEANS_TOLERANCE * float(points.var(axis=0).mean())
    for _ in range(max_iter):
        distances = _squared_distances(points, centres)
        new_labels = distances.argmin(axis=1)
        if np.array_equal(new_labels, labels):
            break
        labels, previous = new_labels, centres
        for j in np.flatnonzero(np.bincount(labels, minlength=len(centres)) == 0):
            shared = np.bincount(labels, minlength=len(centres))[labels] > 1
            spread = np.where(shared, distances[np.arange(len(points)), labels], -1.0)
            labels[int(spread.argmax())] = j
        centres = _cluster_means(points, labels, len(centres))
        if ((centres - previous) ** 2).sum() <= tolerance:
            break
    distances = _squared_distances(points, centres)
    return distances.argmin(axis=1), centres, float(distances.min(axis=1).sum())


def _cluster_means(points: np.ndarray, labels: np.ndarray, n_clusters: int) -> np.ndarray:
    """(K, D) mean of each cluster's ``points``; every cluster must have a member."""
    counts = np.bincount(labels, minlength=n_clusters)
    sums = [np.bincount(labels, weights=axis, minlength=n_clusters) for axis in points.T]
    return np.stack(sums, axis=1) / counts[:, None]


def _refine_clusters(
    a: np.ndarray, b: np.ndarray, labels: np.ndarray, centres: np.ndarray, max_condition: float
) -> np.ndarray:
    """Lloyd iterations of k-means on the constraints, from a k-means partition of the flows.

    Decision: the mean of normal flows shrinks every direction an event does not observe
    towards zero (an event seeing only ``vz`` reports ``vx = vy = 0``), which biases the plain
    k-means centres low and lets such events dominate the partition. Here an event joins
    the centre that best satisfies its own constraints, and a centre is the least-squares
    velocity of its members' constraints (pooling normal flows resolves the aperture
    problem). Both steps lower the total constraint residual; stop when it stops falling.
    Decision: a cluster that empties keeps its previous centre.
    """
    centres = centres.copy()
    best = np.inf
    while True:
        for j in range(len(centres)):
            members = labels == j
            if members.any():
                centres[j] = _pooled_velocity(a[members], b[members], max_condition)
        cost = _constraint_cost(a, b, centres)
        new_labels = cost.argmin(axis=1)
        total = float(cost[np.arange(len(cost)), new_labels].sum())
        if total >= best:
            return centres
        best, labels = total, new_labels


def lift_constraints(
    a: np.ndarray, b: np.ndarray, lift: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """S1 constraints ``n . (u', v') = s`` (row 0 of ``a``, px/s) as constraints on the 3-D
    velocity: ``(n^T L) . theta = s`` with ``L`` (E, 2, 3) the event's ``d(u', v')/dtheta``,
    scaled to a unit row so every row weighs equally in m/s. Zero rows stay zero.

    For a pinhole camera ``L = [[fx, 0, -(u - cx)], [0, fy, -(v - cy)]] / Z``: the image speed
    of a static point falls with its depth while its 3-D velocity does not, and motion along
    the optical axis is observed through the expansion ``(u - cx) / Z``.
    """
    rows = np.einsum("ei,eij->ej", a[:, 0, :2], lift)
    norm = np.linalg.norm(rows, axis=1)
    use = norm > 0
    lifted_a, lifted_b = np.zeros_like(a), np.zeros_like(b)
    lifted_a[use, 0] = rows[use] / norm[use, None]
    lifted_b[use, 0] = b[use, 0] / norm[use]
    return lifted_a, lifted_b


def lift_velocities(lift: np.ndarray, labels: np.ndarray, flows: np.ndarray) -> np.ndarray:
    """The 3-D velocity (K x 3) of each of K image-plane motions ``flows`` (K x 2, px/s):
    the least-squares ``theta`` with ``L theta = flow`` over the events labelled with it,
    ``L`` (M, 2, 3) each event's ``d(u', v')/dtheta`` (:func:`lift_constraints`); zero for a
    motion without events."""
    thetas = np.zeros((len(flows), 3))
    for c in range(len(flows)):
        own = lift[labels == c]
        if len(own):
            thetas[c] = _nearest_velocity(own, flows[c, :2])
    return thetas


def _nearest_velocity(jacobians: np.ndarray, image_motion: np.ndarray) -> np.ndarray:
    """The velocity (the last axis of ``jacobians``, M x 2 x C, each event's
    ``d(u', v')/dtheta``) whose image motion over the M events is nearest ``image_motion``
    (M x 2, or 2 for every event), in the least-squares sense (normal equations)."""
    motion = np.broadcast_to(image_motion, jacobians.shape[:2])
    normal = np.einsum("nij,nik->jk", jacobians, jacobians)
    right = np.einsum("nij,ni->j", jacobians, motion)
    return np.linalg.lstsq(normal, right, rcond=None)[0]


def without_depth_motion(
    lift: np.ndarray, groups: Sequence[np.ndarray], velocities: np.ndarray
) -> np.ndarray:
    """Each group's 3-D velocity (G x 3) replaced by the one with ``vz = 0`` that moves the
    group's events (indices into ``lift``, M x 2 x 3, each event's ``d(u', v')/dtheta``)
    across the image most alike, in the least-squares sense: the same image motion
    without motion in depth."""
    out = np.array(velocities, dtype=np.float64, copy=True)
    for g, members in enumerate(groups):
        own = lift[members]
        if not len(own):
            continue
        out[g, :2] = _nearest_velocity(own[:, :, :2], np.einsum("nij,j->ni", own, out[g]))
        out[g, 2] = 0.0
    return out


def _spread(centre: np.ndarray, radius: float, k: int, dim: int) -> np.ndarray:
    """``k`` velocities spread evenly around ``centre``: on a circle in (vx, vy) for
    ``dim = 2``, on a sphere (Fibonacci lattice) for 3; ``k = 1`` gives the centre itself."""
    if k == 1:
        return centre[None, :].copy()
    i = np.arange(k) + 0.5
    if dim == 2:
        phi = 2.0 * np.pi * i / k
        return centre + radius * np.column_stack((np.cos(phi), np.sin(phi), np.zeros(k)))
    z = 1.0 - 2.0 * i / k
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    return centre + radius * np.column_stack((r * np.cos(phi), r * np.sin(phi), z))


def _sample_constraints(
    cells: np.ndarray,
    t: np.ndarray,
    grid: VoxelGrid,
    sample: np.ndarray,
    *,
    dim: int,
    radius: int,
    min_points: int,
    max_condition: float,
    max_speed: float,
    min_r2: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Constraint rows A (E, 3, 3) and b (E, 3) of the sampled events from the time surfaces
    (S1 only for ``dim = 2``: image-plane points have no depth axis to build S2, S3 on)."""
    surfaces = _surfaces_from_cells(cells, t, grid.shape)
    gradients, valid = [], []
    for surface, (u, v) in zip(surfaces[: 1 if dim == 2 else 3], PLANES, strict=False):
        g, ok = _plane_fits(
            surface,
            cells[sample, u],
            cells[sample, v],
            (grid.voxel_size[u], grid.voxel_size[v]),
            radius=radius,
            min_points=min_points,
            max_condition=max_condition,
            min_r2=min_r2,
        )
        gradients.append(g)
        valid.append(ok)
    return _constraints(gradients, valid, max_speed)


def initial_motions(
    points: np.ndarray,
    t: np.ndarray,
    grid: VoxelGrid,
    n_clusters: int,
    *,
    seed: int,
    dim: int,
    radius: int,
    min_points: int,
    max_condition: float,
    max_speed: float,
    max_events: int,
    n_init: int,
    min_r2: float,
    lift: np.ndarray | None = None,
) -> InitResult:
    """Initial velocities of ``n_clusters`` motions from time surfaces + k-means.

    ``points`` (M, 3) and ``t`` (M,) in the model's units (metres and seconds; ``dim = 2``:
    image-plane points (x, y, 0) in pixels, velocities (vx, vy, 0) in px/s), any time
    origin (absolute ``t`` or ``t - t_ref``: only differences matter). At most
    ``max_events`` events, drawn with ``seed``, get a normal flow; :func:`kmeans` (``n_init``
    seedings drawn with ``seed``) partitions the valid flows and
    :func:`_refine_clusters` turns the partition into velocities. With fewer valid
    (distinct) flows than ``n_clusters`` the velocities are spread around the mean valid
    flow (zero if none) at one voxel per window duration, the smallest velocity difference
    the volume resolves, and ``fallback`` is True.

    ``lift`` (M, 2, 3; image-plane points, ``dim = 2``) makes the velocities 3-D, in the units
    of the lift (m/s): see :func:`lift_constraints`. ``max_speed`` bounds them in those units.
    """
    points = np.asarray(points, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    _check_points(points, t)
    _check_parameters(
        t, n_clusters, radius, min_points, max_condition, max_speed, max_events, n_init, min_r2
    )
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 (image plane) or 3 (space), got {dim}")
    if lift is not None and (dim != 2 or np.shape(lift) != (len(points), 2, 3)):
        raise ValueError(f"lift must be M x 2 x 3 for image-plane points, got {np.shape(lift)}")
    cells = _cells(points, grid)
    m = len(points)
    sample = seeded_subset(m, min(m, int(max_events)), seed)
    a, b = _sample_constraints(
        cells,
        t,
        grid,
        sample,
        dim=dim,
        radius=int(radius),
        min_points=min_points,
        max_condition=max_condition,
        max_speed=max_speed if lift is None else np.inf,  # lifted: bounded after the lift
        min_r2=min_r2,
    )
    if lift is not None:
        a, b = lift_constraints(a, b, lift[sample])
    sample_flows, ok = _normal_flows(a, b, max_condition=max_condition, max_speed=max_speed)
    flows = np.full((m, 3), np.nan)
    flows[sample[ok]] = sample_flows[ok]
    good = sample_flows[ok]
    if len(np.unique(good, axis=0)) < n_clusters:
        centre = good.mean(axis=0) if len(good) else np.zeros(3)
        step = float(grid.voxel_size[:dim].min() / (t.max() - t.min()))
        if lift is not None:  # a voxel per window at the median event's scale, in 3-D
            step /= float(np.median(np.linalg.norm(lift[:, 0], axis=1)))
        spread = _spread(centre, step, int(n_clusters), 2 if lift is None else 3)
        return InitResult(spread, flows, len(good), True, np.full(m, -1))
    partition, centres = kmeans(good, int(n_clusters), n_init=int(n_init), seed=seed)
    thetas = _refine_clusters(a[ok], b[ok], partition, centres, max_condition)
    labels = np.full(m, -1)
    labels[sample[ok]] = _constraint_cost(a[ok], b[ok], thetas).argmin(axis=1)
    return InitResult(thetas, flows, len(good), False, labels)
