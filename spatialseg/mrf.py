"""Spatially coherent labels: a Potts Markov random field over the events' space-time
neighbours, minimised by graph cuts (one exact cut for two labels, alpha-expansion for more:
Boykov, Veksler and Zabih, 2001), the labelling EMSGC (Zhou et al., 2021) gives event
motion segmentation.

Arrays in, labels out: each event's memberships (N x K) and its position in space-time
(N x 3, time already scaled to pixels, :func:`space_time`) give the labels (N,) that
minimise ``sum_i -log p_i(l_i) + weight * #{neighbouring pairs with different labels}``.
An event's own memberships ignore that an object is a connected blob; the pairwise term
lets its neighbours outvote a weak membership, not a confident one.
"""

from __future__ import annotations

import maxflow
import numpy as np
from numba import njit, prange

from spatialseg.neighbours import agreeing_labels, nearest_neighbours

__all__ = ["NEIGHBOURS", "conditional_labels", "neighbour_pairs", "potts_labels", "space_time"]

#: Each event is joined to this many nearest events in space-time (pairs made symmetric).
NEIGHBOURS = 8
#: Memberships are floored here before their logarithm: a cost of at most 9.2 per event.
FLOOR = 1e-4
#: Alpha-expansion sweeps over every label at most (it stops once a sweep changes nothing).
MAX_SWEEPS = 4


def space_time(xy: np.ndarray, t: np.ndarray, speed: float) -> np.ndarray:
    """Events as points (N x 3) in pixels: ``x, y`` and the time scaled by ``speed``
    (pixels per second, the events' typical image speed), so an edge's events a moment apart
    are as near as events a pixel apart along it."""
    return np.column_stack([xy, (t - t.min()) * speed]).astype(np.float64)


def neighbour_pairs(points: np.ndarray, k: int = NEIGHBOURS) -> tuple[np.ndarray, np.ndarray]:
    """The undirected pairs (i < j, each once, in order of i then j) of every point and its
    ``k`` nearest others (:func:`spatialseg.neighbours.nearest_neighbours`)."""
    n = len(points)
    if n < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    k = min(k, n - 1)
    others = nearest_neighbours(points, k)
    keep = _own_pairs(others)
    a = np.repeat(np.arange(n, dtype=np.int64), k)[keep.reshape(-1)]
    b = others[keep]
    return np.divmod(np.sort(np.minimum(a, b) * n + np.maximum(a, b)), n)


@njit(cache=True, parallel=True)
def _own_pairs(others: np.ndarray) -> np.ndarray:
    """``keep[i, m]``: whether point ``i`` and its ``m``-th neighbour ``others[i, m]`` make a
    pair listed from ``i``: not when a lower-numbered point lists ``i`` too (the pair is kept
    from there). A per-pair check in one parallel pass, several times faster than
    deduplicating with ``np.unique``."""
    n, k = others.shape
    keep = np.ones((n, k), dtype=np.bool_)
    for i in prange(n):
        for m in range(k):
            j = others[i, m]
            if j < i:
                for q in range(k):
                    if others[j, q] == i:
                        keep[i, m] = False
                        break
    return keep


def potts_labels(
    probabilities: np.ndarray, first: np.ndarray, second: np.ndarray, weight: float
) -> np.ndarray:
    """The labels (N,) minimising the Potts energy of ``probabilities`` (N x K) on the pairs
    (``first``, ``second``) with ``weight`` per differing pair: with two labels the minimum
    itself (one cut, :func:`_binary_labels`); with more, alpha-expansion from the likeliest
    labels, one minimum cut per label in turn, until every label's last expansion is of the
    labels as they are now."""
    p = np.asarray(probabilities, dtype=np.float64)
    if p.ndim != 2 or not np.all(np.isfinite(p)):
        raise ValueError("memberships must be a finite N x K array")
    if weight < 0:
        raise ValueError(f"the smoothness weight must be >= 0, got {weight}")
    labels = p.argmax(axis=1) if p.size else np.zeros(len(p), dtype=np.int64)
    if p.shape[1] < 2 or len(first) == 0 or weight == 0:
        return labels
    cost = -np.log(np.maximum(p, FLOOR))
    if p.shape[1] == 2:
        return _binary_labels(cost, first, second, weight)
    k, unchanged = p.shape[1], 0
    for step in range(MAX_SWEEPS * k):
        if step >= k and unchanged >= k - 1:  # the next label's expansion would repeat itself
            break
        moved = _expand(cost, labels, first, second, weight, step % k)
        unchanged = unchanged + 1 if np.array_equal(moved, labels) else 0
        labels = moved
    return labels


def _binary_labels(
    cost: np.ndarray, first: np.ndarray, second: np.ndarray, weight: float
) -> np.ndarray:
    """Two labels: the labels of least energy, from one minimum cut (label 1 on the sink
    side; each pair an edge of ``weight`` both ways, each event's cheaper label's cost
    taken off both of its terminal edges).

    Decision: with two labels the Potts energy is submodular as it stands, so one cut finds
    its global minimum (Greig, Porteous and Seheult, 1989), where alpha-expansion took two
    or three cuts to a labelling that no single expansion improves."""
    cheaper = cost.min(axis=1)
    graph = maxflow.Graph[float](len(cost), len(first))
    nodes = graph.add_nodes(len(cost))
    graph.add_grid_tedges(nodes, cost[:, 1] - cheaper, cost[:, 0] - cheaper)
    both_ways = np.full(len(first), float(weight))
    graph.add_edges(first, second, both_ways, both_ways)
    graph.maxflow()
    return graph.get_grid_segments(nodes).astype(np.int64)


def _expand(
    cost: np.ndarray,
    labels: np.ndarray,
    first: np.ndarray,
    second: np.ndarray,
    weight: float,
    alpha: int,
) -> np.ndarray:
    """One expansion move: every event keeps its label or takes ``alpha``, whichever set of
    choices lowers the energy most, found as one minimum cut (an event on the sink side takes
    ``alpha``). The pairwise term of a pair is written as linear terms on each event and a
    directed edge (Kolmogorov and Zabih, 2004).

    Only events not labelled ``alpha`` enter the graph, with the pairs among them: an event
    labelled ``alpha`` has both terminal weights and every pair's edge zero (its two choices
    are one label), so it would sit alone in the graph; left out, the cut is the same and
    costs half the time with two labels."""
    n = len(labels)
    free = labels != alpha
    if not free.any():
        return labels
    node = np.cumsum(free) - 1  # each free event's node in the graph
    into_first, into_second, a, b, cut = _pair_terms(labels, first, second, weight, alpha, node)
    delta = cost[:, alpha] - cost[np.arange(n), labels]
    delta += into_first
    delta -= into_second
    graph = maxflow.Graph[float](int(node[-1]) + 1, len(a))
    nodes = graph.add_nodes(int(node[-1]) + 1)
    graph.add_grid_tedges(nodes, np.maximum(delta[free], 0.0), np.maximum(-delta[free], 0.0))
    graph.add_edges(a, b, cut, np.zeros_like(cut))
    graph.maxflow()
    moved = np.zeros(n, dtype=np.bool_)
    moved[free] = graph.get_grid_segments(nodes)
    return np.where(moved, alpha, labels)


@njit(cache=True)
def _pair_terms(
    labels: np.ndarray,
    first: np.ndarray,
    second: np.ndarray,
    weight: float,
    alpha: int,
    node: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An expansion's pairwise terms in one pass over the pairs, summed in pair order: the
    linear term added on each pair's first event (E10 - E00) and the one subtracted on its
    second (E10), and the edge (node of first, node of second, E01 + E10 - E00) of each
    pair whose events are both free (neither labelled ``alpha``). E00: both keep, E01: the
    first keeps, E10: the second keeps; each ``weight`` where the two labels differ."""
    into_first = np.zeros(len(labels))
    into_second = np.zeros(len(labels))
    a = np.empty(len(first), dtype=np.int64)
    b = np.empty(len(first), dtype=np.int64)
    cut = np.empty(len(first))
    m = 0
    for e in range(len(first)):
        i, j = first[e], second[e]
        both_kept = weight * (labels[i] != labels[j])
        first_kept = weight * (labels[i] != alpha)
        second_kept = weight * (labels[j] != alpha)
        into_first[i] += second_kept - both_kept
        into_second[j] += second_kept
        if labels[i] != alpha and labels[j] != alpha:
            a[m], b[m] = node[i], node[j]
            cut[m] = first_kept + second_kept - both_kept  # > 0: the Potts term is a metric
            m += 1
    return into_first, into_second, a[:m], b[:m], cut[:m]


def conditional_labels(
    probabilities: np.ndarray,
    points: np.ndarray,
    fixed_points: np.ndarray,
    fixed_labels: np.ndarray,
    weight: float,
    k: int = NEIGHBOURS,
) -> np.ndarray:
    """The labels (Q,) of the events at ``points`` (Q x 3, :func:`space_time`) with
    memberships ``probabilities`` (Q x K) that minimise the Potts energy with the labels
    of their ``k`` nearest events of ``fixed_points`` (M x 3, labels ``fixed_labels``)
    held: each event's own cost plus ``weight`` per neighbour of another label.

    Decision: the events a dense window's motions were not fitted on
    (:func:`spatialseg.points.fit_sample`) are most of its events, and each is told by
    its neighbours rather than telling them; with the fitted events' labels held their
    energy splits into one independent choice per event, exact and linear in their
    number, where one cut over every event of a dense window was its longest stage."""
    p = np.asarray(probabilities, dtype=np.float64)
    labels = p.argmax(axis=1) if p.size else np.zeros(len(p), dtype=np.int64)
    if len(p) == 0 or len(fixed_points) == 0 or weight == 0 or p.shape[1] < 2:
        return labels
    k = min(k, len(fixed_points))
    held = np.asarray(fixed_labels, dtype=np.int64)
    cost = -np.log(np.maximum(p, FLOOR))
    shared = agreeing_labels(fixed_points, held, k, points)
    # an event whose k neighbours all hold one label disagrees with k of them in any other
    labels = np.argmin(cost + weight * (k * (np.arange(p.shape[1]) != shared[:, None])), axis=1)
    ask = np.flatnonzero(shared < 0)
    if len(ask):
        neighbours = nearest_neighbours(fixed_points, k, points[ask])
        labels[ask] = _held_choice(cost[ask], neighbours, held, float(weight))
    return labels


@njit(cache=True, parallel=True)
def _held_choice(
    cost: np.ndarray, neighbours: np.ndarray, held: np.ndarray, weight: float
) -> np.ndarray:
    """Each event's label minimising ``cost[i, l] + weight * #{m: held[neighbours[i, m]] !=
    l}`` (the first such label on a tie), in one parallel pass: numpy's count of each
    label's disagreements, without its Q x k temporaries per label, which took 0.46 of
    1.47 s for the 921,595 events a 1,000,000-event window left out of its fit."""
    n, labels = cost.shape
    chosen = np.zeros(n, dtype=np.int64)
    for i in prange(n):
        best = np.inf
        for label in range(labels):
            disagree = 0
            for m in range(neighbours.shape[1]):
                if held[neighbours[i, m]] != label:
                    disagree += 1
            value = cost[i, label] + weight * disagree
            if value < best:
                best = value
                chosen[i] = label
    return chosen
