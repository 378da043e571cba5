"""One identity per object across a recording's windows.

Each window is clustered on its own, so its cluster indices say nothing about the window
before. An object's events at the end of one window and at the start of the next fire at
nearly the same pixels (it moves a pixel or two in between), so the link is the overlap
of the two windows' boundary events: for each of the new window's first events, the
object of the nearest of the previous window's last events within ``radius`` pixels
votes; the Hungarian assignment of clusters to objects maximises the number of agreeing
events (not their shares: a cluster of a hundred events all on an object must not take
its id from the cluster of thousands that continues it). A cluster with too small a
share of its boundary events voting for the object it is assigned (an object entering)
gets a new id; an object left without a cluster (one that stopped or left) keeps its id
retired, and no id is ever reused.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

__all__ = ["Boundary", "boundary", "link_clusters"]

#: Share of a window's events (at least :data:`MIN_BOUNDARY` of them) that form its start
#: and end boundary: a tenth of a window moves an object about a pixel.
BOUNDARY_SHARE = 0.1
MIN_BOUNDARY = 200

#: Pixels within which a previous boundary event votes for a new one.
RADIUS = 3.0

#: A cluster keeps an object's id when at least this share of its boundary events vote for
#: that object; below it the cluster is a new object.
MIN_VOTES = 0.2


@dataclass(frozen=True, eq=False)
class Boundary:
    """A window's last events as the next window sees them: pixel positions (n x 2) and
    object ids (-1: unassigned), and the next unused id."""

    xy: np.ndarray
    ids: np.ndarray
    next_id: int


def _count(n: int) -> int:
    """How many of a window's ``n`` events form a boundary."""
    return min(n, max(MIN_BOUNDARY, int(np.ceil(BOUNDARY_SHARE * n))))


def boundary(xy: np.ndarray, ids: np.ndarray, next_id: int) -> Boundary:
    """The end of a window (its events time-sorted, ``ids`` per event) as a
    :class:`Boundary`."""
    tail = slice(len(ids) - _count(len(ids)), None)
    return Boundary(np.asarray(xy, float)[tail], np.asarray(ids)[tail], int(next_id))


def link_clusters(
    previous: Boundary | None, xy: np.ndarray, labels: np.ndarray, k: int
) -> tuple[np.ndarray, int]:
    """The object id of each of a window's ``k`` clusters, and the next unused id.

    ``xy`` (n x 2) and ``labels`` (n,) are the window's events in time order with their
    cluster (-1: unassigned); its first events are matched against ``previous`` (None: the
    recording's first window, whose clusters become objects 0..k-1).
    """
    if previous is None:
        return np.arange(k), k
    head = slice(0, _count(len(labels)))
    mine = np.asarray(labels)[head]
    votes = _votes(previous, np.asarray(xy, float)[head], mine, k)
    share = votes / np.maximum(np.bincount(mine[mine >= 0], minlength=k), 1)[:, None]
    ids = np.full(k, -1, dtype=np.int64)
    rows, cols = linear_sum_assignment(votes, maximize=True)
    for cluster, obj in zip(rows, cols, strict=True):
        if share[cluster, obj] >= MIN_VOTES:
            ids[cluster] = obj
    next_id = previous.next_id
    for cluster in np.flatnonzero(ids < 0):
        ids[cluster], next_id = next_id, next_id + 1
    return ids, next_id


def _votes(previous: Boundary, xy: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """How many of each cluster's boundary events have their nearest previous boundary event
    within :data:`RADIUS` px on each object (k x previous.next_id)."""
    votes = np.zeros((k, max(previous.next_id, 1)))
    known = previous.ids >= 0
    mine = labels >= 0
    if not known.any() or not mine.any():
        return votes
    distance, nearest = cKDTree(previous.xy[known]).query(xy[mine], distance_upper_bound=RADIUS)
    close = np.isfinite(distance)
    np.add.at(votes, (labels[mine][close], previous.ids[known][nearest[close]]), 1.0)
    return votes
