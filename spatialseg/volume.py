"""The volume of warped events (VWE): fused numba kernels and the evaluator the optimisers call.

Event ``k`` (point ``x_k``, time offset ``dt_k = t_k - t_ref``, weight ``w_k = p_kj``) is
warped to ``x'_k = x_k - dt_k theta`` and votes ``w_k prod_a (1 - |c_a - corner_a|)`` into the
8 voxels around its continuous voxel coordinate ``c = (x'_k - origin) / voxel_size``
(:class:`~spatialseg.grid.VoxelGrid`). Corners outside the grid are dropped one by one, so the
objective stays continuous when an event crosses the border. On an axis with a single voxel
(the planar model, ``nz == 1``) the weight is the tent ``1 - |c|`` peaked on the layer; there
the derivative on the peak is taken as 0 (the symmetric derivative), so ``d/dtheta_z = 0``
for points on the layer.

Design (details in ``docs/volume.md``):

* The volume lives in a buffer with a one-voxel zero halo, so out-of-grid corners read 0
  without a test; votes for them are masked to 0. The buffer is all zero between calls: a
  call votes into it, reads it and clears it again (by revisiting the events' cells when
  that is cheaper than a memset), so a small window costs ``O(N)``, not ``O(|Omega|)``.
* For a :class:`~spatialseg.objectives.MomentObjective` without blur nothing scans the
  grid: the voting pass sums the in-grid mass (``sum V``), and the gather pass gives
  ``sum V^2 = sum_k w_k V(x'_k)`` together with the two parts of the gradient, for
  ``dO/dV = slope V + offset``. Other objectives (or a blur) materialise the blurred volume
  and ``G`` in reused buffers and gather ``G``.
* The voting pass caches each interior event's cell and fractions; the gather pass reads
  them instead of warping again. The P-step keeps them per velocity across calls, since the
  clustering loop revisits each cluster's velocity with new memberships. Events are stored
  sorted by their unwarped voxel, so the passes walk the volume almost sequentially;
  results come back in the caller's order.
* Coordinates are computed in float64; points, weights, the cache and the volume are stored
  in ``dtype`` (float32 halves their memory, float64 is the more accurate and, on the
  benchmark machine, the faster).
* Not thread-safe: one evaluator per thread (``batch_value`` parallelises internally).
"""

from __future__ import annotations

import copy
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numba
import numpy as np
import numpy.typing as npt
from numba import njit, prange

from spatialseg.grid import VoxelGrid
from spatialseg.objectives import MomentObjective, Objective, make_objective
from spatialseg.smoothing import gaussian_smooth

__all__ = ["VolumeObjective", "check_p_step_blur"]

#: Storage dtypes the kernels are compiled for.
DTYPES = (np.float32, np.float64)

#: LLVM may fuse multiply-adds (FMA); no other reassociation, so results are reproducible.
_FASTMATH = {"contract"}


@njit(cache=True, inline="always")
def _layout(padded: np.ndarray):
    """Flat view, grid shape and strides (x, y) of a volume padded by one zero voxel per side."""
    px, py, pz = padded.shape
    return padded.reshape(padded.size), (px - 2, py - 2, pz - 2), py * pz, pz


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _axis(c: float, n: int):
    """One axis of a warped event: padded lower-corner index, fraction, masks, derivative scale.

    The masks are 1 for a corner inside the grid, 0 for one in the halo (dropped). The scale
    is 0 on the peak of a one-voxel axis (the symmetric derivative there), else 1.
    """
    lower = np.floor(c)
    frac = c - lower
    i = int(lower) + 1
    return (
        i,
        frac,
        1.0 if i >= 1 else 0.0,
        1.0 if i < n else 0.0,
        0.0 if (n == 1 and frac == 0.0) else 1.0,
    )


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _warped(points, dt, k, theta, proj):
    """Event ``k`` warped by ``theta``, in the grid's coordinates ``q``; False behind the camera.

    ``proj`` is None for a grid over the points themselves (numba compiles that branch
    away), or ``(fx, fy, cx, cy)`` for a grid over pixels and inverse depth.
    """
    t = dt[k]
    x = points[k, 0] - t * theta[0]
    y = points[k, 1] - t * theta[1]
    z = points[k, 2] - t * theta[2]
    if proj is None:
        return True, x, y, z
    if not z > 0.0:
        return False, 0.0, 0.0, 0.0
    inverse = 1.0 / z
    return True, proj[0] * x * inverse + proj[2], proj[1] * y * inverse + proj[3], inverse


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _to_theta(points, dt, k, theta, proj, inv_size, gx, gy, gz):
    """A derivative along the voxel coordinates of event ``k``'s warped position, as one along
    the point ``p' = p - dt theta`` (times ``-dt``: the caller's): ``(dq/dp')^T g / size``."""
    gx, gy, gz = gx * inv_size[0], gy * inv_size[1], gz * inv_size[2]
    if proj is None:
        return gx, gy, gz
    _, qx, qy, inverse = _warped(points, dt, k, theta, proj)
    tz = -inverse * (gx * (qx - proj[2]) + gy * (qy - proj[3]) + gz * inverse)
    return gx * proj[0] * inverse, gy * proj[1] * inverse, tz


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _locate(points, dt, k, theta, origin, inv_size, proj, shape, sx, sy):
    """Warp event ``k``: whether it touches the grid, the flat index of its cell, and its axes."""
    ok, qx, qy, qz = _warped(points, dt, k, theta, proj)
    cx = (qx - origin[0]) * inv_size[0]
    cy = (qy - origin[1]) * inv_size[1]
    cz = (qz - origin[2]) * inv_size[2]
    nx, ny, nz = shape
    inside = ok & (cx > -1.0) & (cx < nx) & (cy > -1.0) & (cy < ny) & (cz > -1.0) & (cz < nz)
    if not inside:
        cx = cy = cz = 0.0
    ax, ay, az = _axis(cx, nx), _axis(cy, ny), _axis(cz, nz)
    return inside, ax[0] * sx + ay[0] * sy + az[0], ax[1:], ay[1:], az[1:]


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _splat(flat, b, sx, sy, w, ax, ay, az) -> float:
    """Add the 8 masked trilinear votes of weight ``w`` at cell ``b`` (per axis: the fraction
    and the masks of the lower and upper corner); return the mass added."""
    cast = flat.dtype.type  # add in the volume's dtype (no float32 -> float64 round trip)
    fx, mx0, mx1 = ax
    fy, my0, my1 = ay
    fz, mz0, mz1 = az
    wx0, wx1 = w * (1.0 - fx) * mx0, w * fx * mx1
    wy0, wy1 = (1.0 - fy) * my0, fy * my1
    wz0, wz1 = (1.0 - fz) * mz0, fz * mz1
    w00, w01, w10, w11 = wy0 * wz0, wy0 * wz1, wy1 * wz0, wy1 * wz1
    flat[b] += cast(wx0 * w00)
    flat[b + 1] += cast(wx0 * w01)
    flat[b + sy] += cast(wx0 * w10)
    flat[b + sy + 1] += cast(wx0 * w11)
    flat[b + sx] += cast(wx1 * w00)
    flat[b + sx + 1] += cast(wx1 * w01)
    flat[b + sx + sy] += cast(wx1 * w10)
    flat[b + sx + sy + 1] += cast(wx1 * w11)
    return (wx0 + wx1) * (wy0 + wy1) * (wz0 + wz1)


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _interpolate(flat, b, sx, sy, fx, fy, fz):
    """Trilinear value in cell ``b`` at fractions ``(fx, fy, fz)`` and its d/dc along x, y, z."""
    g000, g001 = np.float64(flat[b]), np.float64(flat[b + 1])
    g010, g011 = np.float64(flat[b + sy]), np.float64(flat[b + sy + 1])
    g100, g101 = np.float64(flat[b + sx]), np.float64(flat[b + sx + 1])
    g110, g111 = np.float64(flat[b + sx + sy]), np.float64(flat[b + sx + sy + 1])
    # contract z (value h, slope e), then y, then x
    e00, e01, e10, e11 = g001 - g000, g011 - g010, g101 - g100, g111 - g110
    h00, h01, h10, h11 = g000 + fz * e00, g010 + fz * e01, g100 + fz * e10, g110 + fz * e11
    hy0, hy1 = h01 - h00, h11 - h10
    h0, h1 = h00 + fy * hy0, h10 + fy * hy1
    ez0, ez1 = e00 + fy * (e01 - e00), e10 + fy * (e11 - e10)
    return h0 + fx * (h1 - h0), h1 - h0, hy0 + fx * (hy1 - hy0), ez0 + fx * (ez1 - ez0)


@njit(cache=True, fastmath=_FASTMATH)
def _locate_all(points, dt, theta, origin, inv_size, proj, padded, cells, fracs) -> None:
    """Cache every event's cell at ``theta`` in ``padded``'s grid: ``cells[k]`` its flat
    index where all 8 corners are inside, else -1 (outside, or at the border: located again
    where voted); ``fracs[k]`` its fractions. The weights play no part, so the cache serves
    any memberships at the same velocity (:meth:`VolumeObjective.p_step`)."""
    _, shape, sx, sy = _layout(padded)
    for k in range(dt.size):
        inside, b, ax, ay, az = _locate(points, dt, k, theta, origin, inv_size, proj, shape, sx, sy)
        whole = ax[1] * ax[2] * ay[1] * ay[2] * az[1] * az[2] == 1.0  # all 8 corners inside
        cells[k] = b if inside and whole else -1
        fracs[k, 0], fracs[k, 1], fracs[k, 2] = ax[0], ay[0], az[0]


@njit(cache=True, fastmath=_FASTMATH)
def _vote_located(points, dt, weights, theta, origin, inv_size, proj, padded, cells, fracs):
    """Vote every weighted event into ``padded`` (zero on entry) from its cached cell
    (:func:`_locate_all`), the border's events located again; return the in-grid mass."""
    flat, shape, sx, sy = _layout(padded)
    mass = 0.0
    for k in range(dt.size):
        w = np.float64(weights[k])
        if w == 0.0:
            continue
        b = cells[k]
        if b >= 0:
            fx, fy, fz = fracs[k, 0], fracs[k, 1], fracs[k, 2]
            mass += _splat(flat, b, sx, sy, w, (fx, 1.0, 1.0), (fy, 1.0, 1.0), (fz, 1.0, 1.0))
        else:
            inside, b, ax, ay, az = _locate(
                points, dt, k, theta, origin, inv_size, proj, shape, sx, sy
            )
            if inside:
                mass += _splat(flat, b, sx, sy, w, ax[:3], ay[:3], az[:3])
    return mass


@njit(cache=True, fastmath=_FASTMATH)
def _scatter(points, dt, weights, theta, origin, inv_size, proj, padded, cells, fracs) -> float:
    """Vote every event into ``padded`` (zero on entry); return the in-grid mass ``sum V``.

    Caches each event's cell and fractions in ``cells``/``fracs`` for the passes that follow
    at the same theta (:func:`_locate_all`); those passes skip the events of weight 0.

    Decision: two loops, locating every event first and then voting, because the first,
    without the votes' scattered writes, vectorises: a quarter less time than one loop.
    """
    _locate_all(points, dt, theta, origin, inv_size, proj, padded, cells, fracs)
    return _vote_located(points, dt, weights, theta, origin, inv_size, proj, padded, cells, fracs)


@njit(cache=True, fastmath=_FASTMATH)
def _clear(points, dt, weights, theta, origin, inv_size, proj, padded, cells) -> None:
    """Zero ``padded`` after :func:`_scatter`: by the events' cells when cheaper than a memset."""
    flat, shape, sx, sy = _layout(padded)
    if 8 * dt.size >= flat.size:
        flat[:] = 0
        return
    for k in range(dt.size):
        if weights[k] == 0:
            continue
        b = cells[k]
        if b < 0:
            inside, b, _, _, _ = _locate(
                points, dt, k, theta, origin, inv_size, proj, shape, sx, sy
            )
            if not inside:
                continue
        for corner in (b, b + 1, b + sy, b + sy + 1):
            flat[corner] = 0
            flat[corner + sx] = 0


@njit(cache=True, fastmath=_FASTMATH)
def _weighted_sample_sum(
    points, dt, weights, theta, origin, inv_size, proj, padded, cells, fracs
) -> float:
    """``sum_k w_k V(x'_k)`` after :func:`_scatter`: it equals ``sum V^2``, without a grid pass."""
    flat, shape, sx, sy = _layout(padded)
    total = 0.0
    for k in range(dt.size):
        w = np.float64(weights[k])
        if w == 0.0:
            continue
        b = cells[k]
        if b >= 0:  # cached cell; kept a separate branch, or LLVM warps every event
            value = _interpolate(flat, b, sx, sy, fracs[k, 0], fracs[k, 1], fracs[k, 2])[0]
        else:
            inside, b, ax, ay, az = _locate(
                points, dt, k, theta, origin, inv_size, proj, shape, sx, sy
            )
            if not inside:
                continue
            value = _interpolate(flat, b, sx, sy, ax[0], ay[0], az[0])[0]
        total += w * value
    return total


@njit(cache=True, fastmath=_FASTMATH)
def _gather_grad(points, dt, weights, theta, origin, inv_size, proj, padded, cells, fracs):
    """One gather pass over ``G`` (padded, zero halo) after :func:`_scatter`: ``(S, A, B)``.

    ``S = sum_k w_k G(x'_k)``, ``A = sum_k w_k dt_k J_k^T grad_c G(x'_k)`` with ``J_k`` the
    derivative of the voxel coordinates along the warped point (:func:`_to_theta`), and
    ``B`` the same for the in-grid mass of each event (non-zero only at the border), so that
    for ``dO/dV = slope V + offset`` the gradient is ``-(slope A + offset B)``.
    """
    flat, shape, sx, sy = _layout(padded)
    s = ax_ = ay_ = az_ = bx_ = by_ = bz_ = 0.0
    for k in range(dt.size):
        w = np.float64(weights[k])
        if w == 0.0:
            continue
        b = cells[k]
        wdt = w * dt[k]
        kx = ky = kz = 1.0
        if b >= 0:  # interior cell: all corners in the grid, mass constant
            fx, fy, fz = fracs[k, 0], fracs[k, 1], fracs[k, 2]
        else:
            inside, b, ax, ay, az = _locate(
                points, dt, k, theta, origin, inv_size, proj, shape, sx, sy
            )
            if not inside:
                continue
            (fx, mx0, mx1, kx), (fy, my0, my1, ky), (fz, mz0, mz1, kz) = ax, ay, az
            ex = (1.0 - fx) * mx0 + fx * mx1
            ey = (1.0 - fy) * my0 + fy * my1
            ez = (1.0 - fz) * mz0 + fz * mz1
            mass = _to_theta(
                points,
                dt,
                k,
                theta,
                proj,
                inv_size,
                kx * (mx1 - mx0) * ey * ez,
                ky * (my1 - my0) * ex * ez,
                kz * (mz1 - mz0) * ex * ey,
            )
            bx_ += wdt * mass[0]
            by_ += wdt * mass[1]
            bz_ += wdt * mass[2]
        # one interpolation for both kinds of event, so S rounds as in _weighted_sample_sum
        value, dx, dy, dz = _interpolate(flat, b, sx, sy, fx, fy, fz)
        s += w * value
        jx, jy, jz = _to_theta(points, dt, k, theta, proj, inv_size, kx * dx, ky * dy, kz * dz)
        ax_ += wdt * jx
        ay_ += wdt * jy
        az_ += wdt * jz
    return s, np.array([ax_, ay_, az_]), np.array([bx_, by_, bz_])


@njit(cache=True, fastmath=_FASTMATH)
def _sample(points, dt, theta, origin, inv_size, proj, padded, cells, fracs, out) -> None:
    """``out[k]``: the padded volume interpolated trilinearly at event ``k``'s warped position."""
    flat, shape, sx, sy = _layout(padded)
    for k in range(dt.size):
        b = cells[k]
        if b >= 0:
            out[k] = _interpolate(flat, b, sx, sy, fracs[k, 0], fracs[k, 1], fracs[k, 2])[0]
        else:
            inside, b, ax, ay, az = _locate(
                points, dt, k, theta, origin, inv_size, proj, shape, sx, sy
            )
            out[k] = _interpolate(flat, b, sx, sy, ax[0], ay[0], az[0])[0] if inside else 0.0


@njit(cache=True, parallel=True)
def _batch_moments(points, dt, weights, thetas, origin, inv_size, proj, padded, cells, fracs, out):
    """``out[i] = (sum V, sum V^2)`` at each ``thetas[i]``; one workspace per parallel chunk."""
    n = thetas.shape[0]
    chunks = padded.shape[0]
    for c in prange(chunks):
        for i in range(c, n, chunks):
            theta = (thetas[i, 0], thetas[i, 1], thetas[i, 2])
            args = (points, dt, weights, theta, origin, inv_size, proj, padded[c])
            out[i, 0] = _scatter(*args, cells[c], fracs[c])
            out[i, 1] = _weighted_sample_sum(*args, cells[c], fracs[c])
            _clear(*args, cells[c])


@njit(cache=True, parallel=True)
def _group_moments(
    points, dt, weights, starts, thetas, origin, inv_size, proj, padded, cells, fracs, out
):
    """``out[g, i] = (sum V, sum V^2)`` of group ``g``'s events (``starts[g]:starts[g + 1]``)
    alone at ``thetas[i]``; one workspace per parallel chunk of groups."""
    chunks = padded.shape[0]
    for c in prange(chunks):
        for g in range(c, starts.size - 1, chunks):
            a, b = starts[g], starts[g + 1]
            for i in range(thetas.shape[0]):
                theta = (thetas[i, 0], thetas[i, 1], thetas[i, 2])
                args = (points[a:b], dt[a:b], weights[a:b], theta, origin, inv_size, proj)
                out[g, i, 0] = _scatter(*args, padded[c], cells[c], fracs[c])
                out[g, i, 1] = _weighted_sample_sum(*args, padded[c], cells[c], fracs[c])
                _clear(*args, padded[c], cells[c])


def _stable_order(keys: np.ndarray, n_keys: int) -> np.ndarray:
    """``np.argsort(keys, kind="stable")`` of integer ``keys`` in ``[0, n_keys)``: by counting
    (time ``N + n_keys``) where the keys' range is at most 32 times their count, else
    numpy's comparison sort (250,000 events on a 106,000-voxel grid: 1.5 ms against 21).
    The same order either way."""
    if n_keys > 32 * len(keys):
        return np.argsort(keys, kind="stable")
    return counting_sort(keys.astype(np.int64, copy=False), n_keys)[0]


@njit(cache=True)
def counting_sort(keys: np.ndarray, n_keys: int) -> tuple[np.ndarray, np.ndarray]:
    """The stable order of integer ``keys`` (in ``[0, n_keys)``) by one counting sort, and
    where each key's run starts in it (``order[starts[key]:starts[key + 1]]``)."""
    starts = np.zeros(n_keys + 1, dtype=np.int64)
    for key in keys:
        starts[key + 1] += 1
    for key in range(n_keys):
        starts[key + 1] += starts[key]
    filled = starts[:-1].copy()
    order = np.empty(keys.size, dtype=np.intp)
    for i in range(keys.size):
        order[filled[keys[i]]] = i
        filled[keys[i]] += 1
    return order, starts


def _ranks(values: np.ndarray) -> np.ndarray:
    """Each of the distinct ``values``' rank among them (0 for the smallest)."""
    ranks = np.empty(len(values), dtype=np.intp)
    ranks[np.argsort(values)] = np.arange(len(values))
    return ranks


def _floats(values: np.ndarray) -> tuple[float, ...]:
    """``values`` as a tuple of floats, the form the kernels take a velocity and the grid's
    constants in: an array passed on into their inlined helpers is reference-counted once per
    event, which doubled the cost of a vote (docs/volume.md)."""
    return tuple(float(v) for v in values)


def _finite_array(
    name: str, value: object, shape: tuple[int | None, ...], dtype, hint: str = ""
) -> np.ndarray:
    """``value`` as an array of ``dtype`` with ``shape`` (None: any length), all finite."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array: {exc}") from None
    if arr.ndim != len(shape) or any(
        s is not None and a != s for a, s in zip(arr.shape, shape, strict=True)
    ):
        want = " x ".join("N" if s is None else str(s) for s in shape)
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        first = np.unravel_index(int(np.flatnonzero(bad)[0]), arr.shape)
        raise ValueError(
            f"{name} has {int(bad.sum())} NaN/inf values (first at index "
            f"{tuple(map(int, first))}){hint}"
        )
    return arr.astype(dtype, copy=False)


def check_p_step_blur(
    sigma_xy: float,
    stride: int,
    given: object,
    keys: tuple[str, str] = ("clustering.p_step_sigma", "clustering.p_step_stride"),
) -> None:
    """Raise unless a P-step grid ``stride`` times coarser in x and y fits in a smoothing of
    ``sigma_xy`` voxels there: its voting and sampling tents alone blur by
    ``(stride^2 - 1) / 3`` voxels squared (``given`` and ``keys``: the settings, for the
    message)."""
    if sigma_xy**2 < (stride**2 - 1) / 3:
        raise ValueError(
            f"a P-step stride of {stride} needs a smoothing sigma of at least "
            f"{np.sqrt((stride**2 - 1) / 3):.2f} voxels in x and y, got {given}; lower "
            f"{keys[1]} or raise {keys[0]}"
        )


#: Bytes of located cells one objective keeps for its P-steps (:meth:`VolumeObjective.p_step`):
#: a few clusters' velocities on the fine and the P-step grid for a fitted window (32 bytes
#: per event and grid in float64); an objective whose one velocity needs more keeps none.
LOCATED_BYTES = 1 << 27


@dataclass
class _Located:
    """Every event's cell and fractions at one velocity on one grid (:func:`_locate_all`),
    filled by the first vote at that velocity (``ready`` from then on)."""

    cells: np.ndarray
    fracs: np.ndarray
    ready: bool = False


class VolumeObjective:
    """The objective ``O(V(theta))`` of one cluster's VWE, its gradient, and P-step sampling.

    ``points`` (N x 3) and ``dt`` (N) are the events' 3-D points and ``t_k - t_ref``;
    ``weights`` (N, default 1) their memberships ``p_kj``; ``objective`` an
    :class:`~spatialseg.objectives.Objective` or a registered name; ``dtype`` the storage
    type of points and volumes (float32 or float64); ``groups`` (N integers, optional) a
    partition of the events whose parts :meth:`group_values` judges each alone. Inputs are
    validated here, once.
    """

    def __init__(
        self,
        points: np.ndarray,
        dt: np.ndarray,
        grid: VoxelGrid,
        objective: Objective | str,
        weights: np.ndarray | None = None,
        dtype: npt.DTypeLike = np.float64,
        groups: np.ndarray | None = None,
    ) -> None:
        if not isinstance(grid, VoxelGrid):
            raise ValueError(f"grid must be a VoxelGrid, got {type(grid).__name__}")
        if isinstance(objective, str):
            objective = make_objective(objective)
        if not isinstance(objective, Objective):
            raise ValueError(f"objective must be an Objective or a name, got {objective!r}")
        try:
            dtype = np.dtype(dtype)
        except TypeError:
            raise ValueError(f"dtype must be float32 or float64, got {dtype!r}") from None
        if dtype not in [np.dtype(d) for d in DTYPES]:
            raise ValueError(f"dtype must be float32 or float64, got {dtype}")
        hint = "; drop events without depth before building the volume"
        pts = _finite_array("points", points, (None, 3), np.float64, hint)
        times = _finite_array("dt", dt, (pts.shape[0],), np.float64, hint)
        self.grid = grid
        self.objective = objective
        self.dtype = np.dtype(dtype)
        group = None if groups is None else self._groups(groups, pts.shape[0])
        self._order = self._locality_order(pts, grid, group)
        changes = [] if group is None else np.flatnonzero(np.diff(group[self._order])) + 1
        self._group_starts = np.concatenate([[0], changes, [pts.shape[0]]]).astype(np.int64)
        self._points = np.ascontiguousarray(pts[self._order], dtype=self.dtype)
        self._dt = np.ascontiguousarray(times[self._order], dtype=self.dtype)
        self._weights = np.ones(len(self._dt), dtype=self.dtype)
        self._origin = _floats(grid.origin)
        self._inv_size = _floats(1.0 / grid.voxel_size)
        self._proj = None if grid.projection is None else _floats(grid.projection)
        self._padded, self._cells, self._fracs = self._workspace()
        self._fused = isinstance(objective, MomentObjective) and not objective.smooths
        self._scratch: tuple[np.ndarray, np.ndarray] | None = None
        self._pstep: tuple | None = None
        self._batch: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._lender: VolumeObjective | None = None  # whose zero volumes it votes into
        self._located: OrderedDict[tuple, tuple[_Located, _Located]] = OrderedDict()
        if weights is not None:
            self.set_weights(weights)

    @staticmethod
    def _groups(groups: np.ndarray, n: int) -> np.ndarray:
        """The events' group numbers (N,), checked."""
        group = np.asarray(groups)
        if group.shape != (n,) or not np.issubdtype(group.dtype, np.integer):
            raise ValueError(f"groups must be {n} integers, got {group.dtype} {group.shape}")
        return group.astype(np.int64, copy=False)

    @staticmethod
    def _locality_order(
        points: np.ndarray, grid: VoxelGrid, groups: np.ndarray | None
    ) -> np.ndarray:
        """Event order by group (if given), then by nearest unwarped voxel (C order), then as
        given: the kernels walk V sequentially, and each group's events are contiguous."""
        if not len(points):
            return np.zeros(0, dtype=np.intp)
        shape = np.array(grid.shape)
        index = np.nan_to_num(grid.continuous_index(points))  # NaN: behind the camera
        nearest = np.clip(np.rint(index), 0, shape - 1).astype(np.intp)
        voxel = np.ravel_multi_index(nearest.T, grid.shape)
        if groups is None:
            return _stable_order(voxel, grid.n_voxels)
        return np.lexsort((voxel, groups))

    def _zero_padded(self, *count: int) -> np.ndarray:
        """A zero volume with a one-voxel halo per side (``count`` of them stacked, if given)."""
        return np.zeros((*count, *(n + 2 for n in self.grid.shape)), dtype=self.dtype)

    def _workspace(
        self, *count: int, padded: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A zero padded volume (``padded`` if given) and the per-event cell cache (``count``
        of each, if given)."""
        cells = np.empty((*count, self.n_events), dtype=np.int64)
        fracs = np.empty((*count, self.n_events, 3), dtype=self.dtype)
        return self._zero_padded(*count) if padded is None else padded, cells, fracs

    @staticmethod
    def _interior(padded: np.ndarray) -> np.ndarray:
        """The grid part of a padded volume (a view)."""
        return padded[1:-1, 1:-1, 1:-1]

    @property
    def n_events(self) -> int:
        """Number of events N."""
        return len(self._dt)

    @property
    def order(self) -> np.ndarray:
        """The kernels' event order (N,): their i-th event is input event ``order[i]``.
        Weights set and responses returned ``ordered`` are in it, saving a gather and a
        scatter over every event per call."""
        return self._order

    def set_weights(self, weights: np.ndarray, *, ordered: bool = False) -> None:
        """Replace the memberships ``p_kj`` (N values, finite), e.g. after a P-step; in the
        input order, or in :attr:`order` if ``ordered``."""
        w = _finite_array("weights", weights, (self.n_events,), np.float64)
        self._weights[:] = w if ordered else w[self._order]

    def _args(self, theta: np.ndarray) -> tuple:
        """The kernels' event and grid arguments at ``theta`` (validated: finite 3-vector)."""
        theta = _finite_array("theta", theta, (3,), np.float64)
        return (
            self._points,
            self._dt,
            self._weights,
            _floats(theta),
            self._origin,
            self._inv_size,
            self._proj,
        )

    def _scratch_volumes(self) -> tuple[np.ndarray, np.ndarray]:
        """Two padded buffers (zero halo) for the smoothed volume and ``G``, made once."""
        if self._scratch is None:
            self._scratch = (self._zero_padded(), self._zero_padded())
        return self._scratch

    def _smoothed(self) -> np.ndarray:
        """The volume the objective sees (interior view): ``K V`` with a blur, else ``V``."""
        volume = self._interior(self._padded)
        if not self.objective.smooths:
            return volume
        return self.objective.smooth(volume, out=self._interior(self._scratch_volumes()[0]))

    def _vote(
        self, args: tuple, padded: np.ndarray, located: _Located | None
    ) -> tuple[float, np.ndarray, np.ndarray]:
        """Vote the events at ``args``' velocity into ``padded`` (zero on entry): the in-grid
        mass and the cells and fractions the passes after it read, ``located``'s (located
        at the first vote) or else this objective's own, located anew."""
        if located is None:
            return _scatter(*args, padded, self._cells, self._fracs), self._cells, self._fracs
        if not located.ready:
            _locate_all(*args[:2], *args[3:], padded, located.cells, located.fracs)
            located.ready = True
        mass = _vote_located(*args, padded, located.cells, located.fracs)
        return mass, located.cells, located.fracs

    @contextmanager
    def _voted(
        self, args: tuple, located: _Located | None = None
    ) -> Iterator[tuple[float, np.ndarray, np.ndarray]]:
        """Vote ``V(theta)`` (``args``: :meth:`_args`) into the buffer; yield ``sum V`` and
        the cells and fractions (:meth:`_vote`); clear."""
        cells = self._cells if located is None else located.cells
        try:
            mass, cells, fracs = self._vote(args, self._padded, located)
            yield mass, cells, fracs
        finally:
            _clear(*args, self._padded, cells)

    def _voted_value(self, args: tuple, mass: float, cells: np.ndarray, fracs: np.ndarray) -> float:
        """The objective of the volume now in the buffer (inside :meth:`_voted`)."""
        if self._fused:
            total_sq = _weighted_sample_sum(*args, self._padded, cells, fracs)
            return self.objective.from_moments(mass, total_sq, self.grid.n_voxels)[0]
        return float(self.objective.value(self._smoothed()))

    def value(self, theta: np.ndarray) -> float:
        """The objective at ``theta``."""
        args = self._args(theta)
        with self._voted(args) as voted:
            return self._voted_value(args, *voted)

    def value_and_grad(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """The objective at ``theta`` and its analytic gradient ``dO/dtheta`` (3,)."""
        args = self._args(theta)
        with self._voted(args) as (mass, cells, fracs):
            if self._fused:
                total_sq, slopes, mass_slopes = _gather_grad(*args, self._padded, cells, fracs)
                value, slope, offset = self.objective.from_moments(
                    mass, total_sq, self.grid.n_voxels
                )
                return value, -(slope * slopes + offset * mass_slopes)
            smoothed, derivative = self._smoothed(), self._scratch_volumes()[1]
            value = self.objective.value_and_derivative(smoothed, self._interior(derivative))
            if self.objective.smooths:
                blurred = self._scratch_volumes()[0]
                self.objective.smooth(self._interior(derivative), out=self._interior(blurred))
                derivative = blurred
            slopes = _gather_grad(*args, derivative, cells, fracs)[1]
            return float(value), -slopes

    def grad(self, theta: np.ndarray) -> np.ndarray:
        """The analytic gradient ``dO/dtheta`` (3,)."""
        return self.value_and_grad(theta)[1]

    def batch_value(self, thetas: np.ndarray) -> np.ndarray:
        """The objective at each row of ``thetas`` (n x 3), in parallel; equal to :meth:`value`."""
        thetas = _finite_array("thetas", thetas, (None, 3), np.float64)
        if not self._fused:
            return np.array([self.value(theta) for theta in thetas])
        moments = np.zeros((len(thetas), 2))
        chunks = min(numba.get_num_threads(), len(thetas))
        if chunks:
            events = (self._points, self._dt, self._weights)
            _batch_moments(*events, thetas, *self._batch_args(chunks), moments)
        return self._values(moments)

    def group_values(self, thetas: np.ndarray) -> np.ndarray:
        """The objective of each group's events alone (``groups``, in increasing group
        number) at each row of ``thetas`` (n x 3): G x n, equal to :meth:`batch_value` of a
        volume built on that group's events. One volume serves every group, so judging many
        small groups costs their events, not a grid each."""
        thetas = _finite_array("thetas", thetas, (None, 3), np.float64)
        starts = self._group_starts
        if not self._fused:
            return np.array([self.group(g).batch_value(thetas) for g in range(len(starts) - 1)])
        moments = np.zeros((len(starts) - 1, len(thetas), 2))
        chunks = min(numba.get_num_threads(), len(starts) - 1)
        if chunks and len(thetas):
            events = (self._points, self._dt, self._weights, starts, thetas)
            _group_moments(*events, *self._batch_args(chunks), moments)
        return self._values(moments)

    def _batch_args(self, chunks: int) -> tuple:
        """The batch kernels' grid arguments with ``chunks`` workspaces (made once, kept)."""
        if self._batch is None or len(self._batch[0]) < chunks:
            lent = None if self._lender is None else self._lender._batch_args(chunks)[3]
            self._batch = self._workspace(chunks, padded=lent)
        padded, cells, fracs = (a[:chunks] for a in self._batch)
        return self._origin, self._inv_size, self._proj, padded, cells, fracs

    def _values(self, moments: np.ndarray) -> np.ndarray:
        """The objective of each ``(sum V, sum V^2)`` pair in ``moments`` (... x 2)."""
        value, n_voxels = self.objective.from_moments, self.grid.n_voxels
        flat = [value(m, q, n_voxels)[0] for m, q in moments.reshape(-1, 2)]
        return np.array(flat).reshape(moments.shape[:-1])

    def group(self, g: int) -> VolumeObjective:
        """Group ``g``'s events alone (``groups``, in increasing group number; the events in
        the order given, with their weights) as an objective that votes into this one's zero
        volumes: use the two one at a time, never side by side.

        Decision: a new objective's first calls write into a grid-sized volume of fresh
        memory; on a 698 x 306 x 21 grid that cost 23 ms against 0.3 ms for a batch of ten
        velocities over a 230-event tile, so judging a window's thousand tiles in turn
        (:mod:`spatialseg.hypotheses`) cost their grid, not their events. The part takes
        its events as views in this one's order (by group, then voxel, then as given: the
        order a volume of them alone would sort them into), not checked and sorted again."""
        count = len(self._group_starts) - 1
        if not 0 <= g < count:
            raise ValueError(f"group must be in [0, {count}), got {g}")
        a, b = self._group_starts[g], self._group_starts[g + 1]
        part = copy.copy(self)  # the grid, objective, constants and zero volumes shared
        part._order = _ranks(self._order[a:b])
        part._group_starts = np.array([0, b - a], dtype=np.int64)
        part._points, part._dt = self._points[a:b], self._dt[a:b]
        part._weights = self._weights[a:b].copy()
        part._cells, part._fracs = part._workspace(padded=self._padded)[1:]
        part._scratch = part._pstep = part._batch = None
        part._located = OrderedDict()
        part._lender = self
        return part

    def volume(self, theta: np.ndarray) -> np.ndarray:
        """A copy of the raw VWE ``V(theta)`` (before any blur), shape ``grid.shape``."""
        with self._voted(self._args(theta)):
            return self._interior(self._padded).copy()

    def _p_step_buffers(
        self, stride: int
    ) -> tuple[VoxelGrid, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The P-step's grid (:meth:`VoxelGrid.coarsened` by ``stride``), two padded buffers
        with a zero halo (the coarse votes, zero between calls; the smoothed volume that is
        sampled, its inside overwritten each call), and its raw and smoothed volumes; made
        once per stride."""
        if self._pstep is None or self._pstep[0] != stride:
            grid = self.grid.coarsened(stride)
            padded = tuple(np.zeros(tuple(n + 2 for n in grid.shape), self.dtype) for _ in "ab")
            volumes = (np.empty(grid.shape, self.dtype), np.empty(grid.shape, self.dtype))
            self._pstep = (stride, grid, *padded, *volumes)
        return self._pstep[1:]

    def _p_step_blur(
        self, coarse: VoxelGrid, sigma: float | Sequence[float], stride: int
    ) -> tuple[np.ndarray, float]:
        """The Gaussian's sigmas (3,) on the P-step's grid ``coarse`` (``stride`` times
        coarser) for ``sigma`` fine voxels (:meth:`p_step`), checked to fit, 0 on one-voxel
        axes; and the fine voxels per coarse one."""
        strides = coarse.voxel_size / self.grid.voxel_size
        requested = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (3,))
        if np.any(strides > 1):
            check_p_step_blur(float(requested[strides > 1].min()), stride, sigma)
        fine_sigma = np.sqrt(requested**2 - (strides**2 - 1) / 3)
        sigmas = np.where(np.array(self.grid.shape) > 1, fine_sigma / strides, 0.0)
        return sigmas, float(np.prod(strides))

    def p_step(
        self,
        theta: np.ndarray,
        sigma: float | Sequence[float],
        stride: int = 1,
        *,
        ordered: bool = False,
    ) -> tuple[np.ndarray, float]:
        """``V(theta)`` smoothed by a Gaussian of ``sigma`` voxels (one number, or one per axis
        x, y, depth; axes with one voxel left alone; mirrored at the grid's border) and
        interpolated at each warped event (N, in the input order, or in :attr:`order` if
        ``ordered``): the P-step's ``c_j(x'_kj)``; and the objective of ``V(theta)``. In
        buffers reused from call to call.

        ``stride`` > 1 votes, smooths and samples on a grid that many times coarser in x and
        y, per fine voxel's area; the Gaussian there is narrowed so that it and the coarser
        voting and sampling tents keep the fine total variance (``sigma^2 - (stride^2-1)/3``
        fine voxels squared). Depth keeps its bins: on its dozen or so, a coarser axis moves
        the mirrored border by a sizeable share of the blur.

        Decision: mirrored rather than zero beyond the border, so a cluster whose events
        crowd the border is not diluted there against one in the middle (zero boundaries
        cost 6 % accuracy on a 4,000-event interior window).
        """
        value, events, grid_args, sampled_from, per_voxel, located = self._p_step_volume(
            theta, sigma, stride
        )
        sampled = np.empty(self.n_events)
        _sample(*events[:2], *events[3:], *grid_args, sampled_from, *located, sampled)
        sampled /= per_voxel
        if ordered:
            return sampled, value
        out = np.empty_like(sampled)
        out[self._order] = sampled
        return out, value

    def p_step_at(
        self,
        theta: np.ndarray,
        sigma: float | Sequence[float],
        stride: int,
        points: np.ndarray,
        dt: np.ndarray,
    ) -> np.ndarray:
        """:meth:`p_step`'s smoothed ``V(theta)`` of this objective's events (their
        weights voting) at other events (``points``, M x 3, and ``dt``, M), each warped by
        ``theta``: a fit's volumes read where the events left out of the fit fall. Equal to
        the P-step of an objective holding both, the others with weight 0, without voting
        or locating the others in it."""
        _, events, grid_args, sampled_from, per_voxel, _ = self._p_step_volume(theta, sigma, stride)
        hint = "; drop events without depth first"
        pts = _finite_array("points", points, (None, 3), np.float64, hint).astype(self.dtype)
        times = _finite_array("dt", dt, (len(pts),), np.float64, hint).astype(self.dtype)
        cells = np.empty(len(pts), dtype=self._cells.dtype)
        fracs = np.empty((len(pts), 3), dtype=self._fracs.dtype)
        others = (pts, times, events[3], *grid_args, sampled_from, cells, fracs)
        _locate_all(*others)  # as a P-step's events are: the fractions in the volume's dtype
        sampled = np.empty(len(pts))
        _sample(*others, sampled)
        return sampled / per_voxel

    def _p_step_volume(
        self, theta: np.ndarray, sigma: float | Sequence[float], stride: int
    ) -> tuple[float, tuple, tuple, np.ndarray, float, tuple[np.ndarray, np.ndarray]]:
        """Vote ``V(theta)`` on the P-step's grid and smooth it (:meth:`p_step`): the
        objective of ``V(theta)``, the kernels' event arguments, the P-step grid's, the
        padded smoothed volume, the fine voxels per P-step voxel, and the events' cells and
        fractions in the P-step's grid.

        Decision: the loop's P-steps revisit each cluster's velocity with new memberships
        (the theta-step rarely moves it), so the events are located once per velocity and
        grid (:meth:`_located_at`) and only voted again: a third of a P-step."""
        coarse, votes, sampled_from, raw, smooth = self._p_step_buffers(stride)
        sigmas, per_voxel = self._p_step_blur(coarse, sigma, stride)
        args = self._args(theta)
        fine_at, coarse_at = self._located_at(args[3], stride)
        with self._voted(args, fine_at) as (mass, *located):
            value = self._voted_value(args, mass, *located)
            if stride == 1:  # the vote is the P-step's, and so are its cells
                raw[...] = self._interior(self._padded)
        events, grid_args = args[:4], (self._origin, _floats(1.0 / coarse.voxel_size), self._proj)
        if stride > 1:
            located = self._vote((*events, *grid_args), votes, coarse_at)[1:]
            try:
                raw[...] = self._interior(votes)
            finally:
                _clear(*events, *grid_args, votes, located[0])
        gaussian_smooth(raw, sigmas, out=smooth, work=raw, mode="reflect")
        self._interior(sampled_from)[...] = smooth
        return value, events, grid_args, sampled_from, per_voxel, tuple(located)

    def _located_at(
        self, theta: tuple[float, ...], stride: int
    ) -> tuple[_Located | None, _Located | None]:
        """The cell caches of the events at ``theta`` on the fine grid and on the P-step's
        grid of ``stride``, kept from call to call: beyond :data:`LOCATED_BYTES` the least
        recently used velocity's arrays are taken over (more velocities than fit cost a
        locating each, as without the cache, and no new memory); (None, None) when one
        velocity's would exceed it."""
        key = (theta, stride)
        if key in self._located:
            self._located.move_to_end(key)
            return self._located[key]
        size = 2 * (self._cells.nbytes + self._fracs.nbytes)
        if size > LOCATED_BYTES:
            return None, None
        taken = None
        while (len(self._located) + 1) * size > LOCATED_BYTES:
            taken = self._located.popitem(last=False)[1]
        if taken is None:
            entry = tuple(_Located(*self._workspace(padded=self._padded)[1:]) for _ in "fc")
        else:
            entry = tuple(_Located(old.cells, old.fracs) for old in taken)
        self._located[key] = entry
        return entry

    def sample(self, theta: np.ndarray, volume: np.ndarray | None = None) -> np.ndarray:
        """``volume`` (default: the raw ``V(theta)``) interpolated at each warped event (N,).

        Corners outside the grid count 0. This is ``c_j(x'_kj)`` of the P-step.
        """
        sampled = np.empty(self.n_events)
        if volume is None:
            args = self._args(theta)
            with self._voted(args) as (_, cells, fracs):
                _sample(*args[:2], *args[3:], self._padded, cells, fracs, sampled)
        else:
            args = self._args(theta)
            padded = self._scratch_volumes()[0]
            self._interior(padded)[...] = _finite_array(
                "volume", volume, self.grid.shape, self.dtype
            )
            self._cells.fill(-1)  # no cached cells: locate every event
            _sample(*args[:2], *args[3:], padded, self._cells, self._fracs, sampled)
        out = np.empty_like(sampled)
        out[self._order] = sampled
        return out
