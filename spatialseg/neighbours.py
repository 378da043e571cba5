"""Exact k nearest neighbours of every point among the others (or of query points among
them), on a uniform grid of cells.

Events in space-time (pixels, and time scaled to pixels) fill a box about evenly at the
scale of their neighbours, so a grid whose cells hold a few points each finds a point's
neighbours in the cells around its own, and a ring of cells further out only while a
nearer point could still lie there: about 2.5x faster than scipy's k-d tree over
1,000,000 events, with the same neighbours (docs/performance.md, session 52). The search runs on
numba's threads. Ties in distance go to the lower index, so the answer is one function of
the points, whatever the threads.

Arrays in, indices out: :func:`nearest_neighbours`; labels in, labels out:
:func:`agreeing_labels`, the label a query's nearest points all carry where the grid shows
it without a search.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange
from scipy import ndimage

from spatialseg.volume import counting_sort

__all__ = ["agreeing_labels", "grid_order", "nearest_neighbours"]

#: Points per cell on average over the points' bounding box: fewer cells to visit against
#: fewer points per cell (0.5-1.5 within 5 % of each other on 15,000-1,000,000 events; 3
#: and 6 slower on the larger).
POINTS_PER_CELL = 1.5
#: Cells at most per point: a box whose points crowd into a small part of it gets coarser
#: cells rather than a grid larger than the points.
MAX_CELLS_PER_POINT = 2
#: The search's stopping distances are shrunk by this share of the coordinates' magnitude,
#: so a point that rounding put into the next cell is never missed.
ROUNDING = 1e-9
#: Once the 27 cells around a query's own hold k points, its k nearest are at most
#: 2 sqrt(3) < 4 cell sides away, so within this many cells of its own along every axis.
AGREEING_RING = 4


def nearest_neighbours(points: np.ndarray, k: int, queries: np.ndarray | None = None) -> np.ndarray:
    """The indices (N x k, nearest first) of each point's ``k`` nearest other points in
    Euclidean distance, ties to the lower index; a duplicate point is a neighbour at
    distance 0, the point itself never. ``points`` is N x 3 and finite, ``1 <= k < N``.
    With ``queries`` (Q x 3, finite): each query's ``k`` nearest points (Q x k, ``k <= N``),
    none excluded."""
    points = _finite(points, "points")
    n = len(points)
    top = n - 1 if queries is None else n
    if not 1 <= k <= top:
        raise ValueError(f"k must be at least 1 and at most {top} (of {n} points), got {k}")
    lo, size, shape = _grid(points)
    order, starts = _grouped(points, lo, size, shape)
    grouped = points[order]
    if queries is None:
        margin = ROUNDING * (float(np.abs(points).max()) + size)
        found = np.empty((n, k), np.int64)
        found[order] = _search(grouped, order, starts, grouped, order, k, lo, size, shape, margin)
        return found
    asked = _finite(queries, "queries")
    reach = max(float(np.abs(points).max()), float(np.abs(asked).max(initial=0.0)))
    margin = ROUNDING * (reach + size)
    own = np.full(len(asked), -1, np.int64)  # a query is none of the points
    return _search(grouped, order, starts, asked, own, k, lo, size, shape, margin)


def grid_order(points: np.ndarray) -> np.ndarray:
    """The indices of ``points`` (N x 3, finite) grouped by the cells of
    :func:`nearest_neighbours`' grid, in the cells' order: near points near in the order.

    Why: numbered in this order, a graph over the points' neighbours keeps each node's
    neighbours close in memory, and the minimum cuts of :mod:`spatialseg.mrf` ran 30-45 %
    faster than in the events' time order, with the same labels (docs/performance.md,
    session 57)."""
    points = _finite(points, "points")
    if len(points) == 0:
        return np.zeros(0, np.intp)
    return _grouped(points, *_grid(points))[0]


def agreeing_labels(
    points: np.ndarray, labels: np.ndarray, k: int, queries: np.ndarray
) -> np.ndarray:
    """For each query (Q x 3, finite), the label (of ``labels``, N, >= 0) that all its ``k``
    nearest ``points`` (N x 3, finite, ``1 <= k <= N``) carry, where the grid of
    :func:`nearest_neighbours` shows it without finding them; -1 where they might differ
    (or the query lies beyond the points' box): those need the search.

    Decision: when a query's 27 surrounding cells hold ``k`` points, its ``k`` nearest lie
    within :data:`AGREEING_RING` cells of its own, so one label over that block answers
    for them. Labelling the events a dense window's fit left out asks exactly this of
    most of them (all but 0-20 % on 1,000,000-event windows), and the search was most of
    that stage's time (docs/performance.md, session 55)."""
    points = _finite(points, "points")
    asked = _finite(queries, "queries")
    labels = np.asarray(labels, dtype=np.int64)
    if labels.shape != (len(points),) or (labels.size and labels.min() < 0):
        raise ValueError("labels must be one label >= 0 per point")
    if not 1 <= k <= len(points):
        raise ValueError(f"k must be at least 1 and at most {len(points)}, got {k}")
    lo, size, shape = _grid(points)
    cells = tuple(shape)
    own = np.unravel_index(_cells_of(points, lo, size, shape), cells)
    count = np.zeros(cells, np.int64)
    np.add.at(count, own, 1)
    none = int(labels.max(initial=0)) + 1  # the lowest label of a cell without points
    low = np.full(cells, none, np.int64)
    high = np.full(cells, -1, np.int64)
    np.minimum.at(low, own, labels)
    np.maximum.at(high, own, labels)
    block = 2 * AGREEING_RING + 1
    low = ndimage.minimum_filter(low, size=block, mode="constant", cval=none)
    high = ndimage.maximum_filter(high, size=block, mode="constant", cval=-1)
    near = ndimage.correlate(count, np.ones((3, 3, 3), np.int64), mode="constant")
    known = np.where((low == high) & (near >= k), high, -1).reshape(-1)
    inside = np.all((asked >= lo) & (asked <= lo + shape * size), axis=1)
    return np.where(inside, known[_cells_of(asked, lo, size, shape)], -1)


def _grid(points: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """The search grid over ``points``: its low corner (3,), the cells' side and its shape."""
    lo = points.min(axis=0)
    size, shape = _cells(points.max(axis=0) - lo, len(points))
    return lo, size, shape


def _grouped(
    points: np.ndarray, lo: np.ndarray, size: float, shape: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The points grouped by cell (each cell's in index order) and where each cell's run
    starts in that order."""
    return counting_sort(_cells_of(points, lo, size, shape), int(np.prod(shape)))


def _finite(points: np.ndarray, name: str) -> np.ndarray:
    """``points`` as a C-ordered float64 N x 3 array, refused unless finite."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
        raise ValueError(f"{name} must be a finite N x 3 array")
    return points


def _cells(extent: np.ndarray, n: int) -> tuple[float, np.ndarray]:
    """The cells' side and the grid's shape (3,) for ``n`` points spread over ``extent``:
    :data:`POINTS_PER_CELL` on average, at most :data:`MAX_CELLS_PER_POINT` cells a point."""
    volume = float(np.prod(np.maximum(extent, 1.0)))
    size = (volume * POINTS_PER_CELL / n) ** (1.0 / 3.0)
    while True:
        shape = (extent // size).astype(np.int64) + 1
        if int(np.prod(shape)) <= MAX_CELLS_PER_POINT * n + 8:
            return size, shape
        size *= 1.25


@njit(cache=True, inline="always")
def _cell_of(value: float, lo: float, size: float, count: int) -> int:
    """The cell (0 .. count - 1) of one coordinate; a query beyond the grid, its edge cell."""
    return max(min(int(np.floor((value - lo) / size)), count - 1), 0)


@njit(cache=True)
def _cells_of(points, lo, size, shape):
    """Each point's cell, numbered in C order over the grid's ``shape``."""
    cells = np.empty(points.shape[0], np.int64)
    for i in range(points.shape[0]):
        cx = _cell_of(points[i, 0], lo[0], size, shape[0])
        cy = _cell_of(points[i, 1], lo[1], size, shape[1])
        cz = _cell_of(points[i, 2], lo[2], size, shape[2])
        cells[i] = (cx * shape[1] + cy) * shape[2] + cz
    return cells


@njit(cache=True, inline="always")
def _gap(value: float, low: float, size: float) -> float:
    """The distance along one axis from ``value`` to the cell ``[low, low + size]``."""
    if value < low:
        return low - value
    if value > low + size:
        return value - low - size
    return 0.0


@njit(cache=True, inline="always")
def _insert(best_d, best_i, count, d, j) -> int:
    """Put neighbour ``j`` at squared distance ``d`` into the sorted ``best_*`` (length k)
    if it beats the last; return how many are held."""
    k = len(best_d)
    if count == k and (d > best_d[k - 1] or (d == best_d[k - 1] and j > best_i[k - 1])):
        return count
    m = count if count < k else k - 1
    while m > 0 and (best_d[m - 1] > d or (best_d[m - 1] == d and best_i[m - 1] > j)):
        best_d[m] = best_d[m - 1]
        best_i[m] = best_i[m - 1]
        m -= 1
    best_d[m] = d
    best_i[m] = j
    return count + 1 if count < k else k


@njit(cache=True, inline="always")
def _reach(p, lo, size, shape, home, r) -> float:
    """How far from ``p`` the cube of cells within ``r`` of ``home`` surely reaches: the
    distance to its nearest face beyond which cells remain (infinite when none do)."""
    reach = np.inf
    for a in range(3):
        if home[a] - r > 0:
            reach = min(reach, p[a] - (lo[a] + (home[a] - r) * size))
        if home[a] + r < shape[a] - 1:
            reach = min(reach, lo[a] + (home[a] + r + 1) * size - p[a])
    return reach


@njit(cache=True, parallel=True)
def _search(grouped, order, starts, queries, own, k, lo, size, shape, margin):
    """Each query's k nearest points other than point ``own`` of it (-1: none), Q x k
    (``grouped``: the points in ``order``, so a cell's points lie together in memory): the
    rings of cells around the query's own, ring by ring, until the k-th nearest found is
    nearer than anything beyond the ring; a cell farther than the k-th nearest is skipped."""
    found = np.empty((queries.shape[0], k), np.int64)
    for t in prange(queries.shape[0]):
        i = own[t]
        p = queries[t]
        home = np.empty(3, np.int64)
        for a in range(3):
            home[a] = _cell_of(p[a], lo[a], size, shape[a])
        best_d = np.full(k, np.inf)
        best_i = np.full(k, -1, np.int64)
        count, r = 0, 0
        while True:
            for cx in range(max(home[0] - r, 0), min(home[0] + r, shape[0] - 1) + 1):
                gx = _gap(p[0], lo[0] + cx * size, size)
                x_edge = abs(cx - home[0]) == r
                for cy in range(max(home[1] - r, 0), min(home[1] + r, shape[1] - 1) + 1):
                    gy = _gap(p[1], lo[1] + cy * size, size)
                    # inside the ring in x and y: only its two faces in z are new cells
                    z_step = 1 if x_edge or abs(cy - home[1]) == r else 2 * r
                    for cz in range(home[2] - r, home[2] + r + 1, z_step):
                        if cz < 0 or cz >= shape[2]:
                            continue
                        gz = _gap(p[2], lo[2] + cz * size, size)
                        if count == k:
                            gap = max(np.sqrt(gx * gx + gy * gy + gz * gz) - margin, 0.0)
                            if gap * gap > best_d[k - 1]:
                                continue
                        cell = (cx * shape[1] + cy) * shape[2] + cz
                        for s in range(starts[cell], starts[cell + 1]):
                            j = order[s]
                            if j != i:
                                dx = grouped[s, 0] - p[0]
                                dy = grouped[s, 1] - p[1]
                                dz = grouped[s, 2] - p[2]
                                d = dx * dx + dy * dy + dz * dz
                                count = _insert(best_d, best_i, count, d, j)
            reach = _reach(p, lo, size, shape, home, r) - margin
            if reach == np.inf or (count == k and reach > 0 and best_d[k - 1] < reach * reach):
                break
            r += 1
        found[t] = best_i
    return found
