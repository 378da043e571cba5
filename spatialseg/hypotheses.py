"""Initial motions from local contrast maximisation: each image tile proposes the velocity
that sharpens its own events best, and a greedy cover keeps the K proposals that explain
most tiles (``init.method=tiles``).

Decision: with a moving camera the flow-based initialisation fails where motions differ
only in depth, e.g. a camera walking forward past a person crossing (``ego_forward``): in
short windows forward and sideways translation look alike in any small neighbourhood, so
per-event flows do not cluster, and the best single velocity of all events is a blend of
the static scene and the person. A tile's own contrast maximum is sharp for the motion that
dominates the tile, and its contrast under the other tiles' velocities says which of those
explain it too. Measured in docs/method.md ("Initial velocities").
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from spatialseg.clustering import ClusterEvaluator, Maximizer, maximize_contrast

__all__ = [
    "GroupedEvaluator",
    "Tiles",
    "distinct_motions",
    "greedy_cover",
    "image_tiles",
    "tile_motions",
    "widest_cover",
]


def image_tiles(xy: np.ndarray, size: float, min_events: int) -> tuple[np.ndarray, np.ndarray]:
    """Square tiles of ``size`` pixels over the events' image positions ``xy`` (M x 2):
    each event's tile index (-1 in tiles with fewer than ``min_events`` events) and the
    event count of every kept tile."""
    if size <= 0 or min_events < 1:
        raise ValueError(
            f"init.tiles.size must be > 0 and init.tiles.min_events >= 1, got {size}, {min_events}"
        )
    cells = np.floor(np.asarray(xy, dtype=np.float64) / size).astype(np.int64)
    _, tile, counts = np.unique(_row_keys(cells), return_inverse=True, return_counts=True)
    dense = counts >= min_events
    renumber = np.where(dense, np.cumsum(dense) - 1, -1)
    return renumber[tile], counts[dense]


def _row_keys(cells: np.ndarray) -> np.ndarray:
    """One integer per row of ``cells`` (M x 2 integers), ordered as the rows are
    (lexicographically), so a 1-D ``np.unique`` numbers them as ``np.unique(axis=0)`` would,
    several times faster (it sorts numbers, not rows)."""
    if not len(cells):
        return np.zeros(0, dtype=np.int64)
    low = cells.min(axis=0)
    span = int(cells[:, 1].max() - low[1]) + 1
    return (cells[:, 0] - low[0]) * span + (cells[:, 1] - low[1])


class GroupedEvaluator(Protocol):
    """One objective over every tile's events, grouped by tile (tile number = group)."""

    def group_values(self, thetas: np.ndarray) -> np.ndarray:
        """Each tile's contrast alone under each velocity (T x H)."""
        ...

    def group(self, g: int) -> ClusterEvaluator:
        """Tile ``g``'s objective alone, sharing this one's volumes (used one at a time)."""
        ...


class Tiles:
    """The events of each tile (``members``, ``counts``), the objective of any of them built
    on demand by ``evaluator_for(indices)`` (one at a time: each holds a volume the size of
    the grid), and ``grouped``: every tile's contrast under each velocity
    (:meth:`contrasts`, T x H) and each tile's own objective."""

    def __init__(
        self,
        evaluator_for: Callable[[np.ndarray], ClusterEvaluator],
        event_tile: np.ndarray,
        n_tiles: int,
        grouped: GroupedEvaluator,
    ) -> None:
        self._evaluator_for = evaluator_for
        self._grouped = grouped
        order = np.argsort(event_tile, kind="stable")
        ids = event_tile[order]
        starts = np.searchsorted(ids, np.arange(n_tiles))
        ends = np.searchsorted(ids, np.arange(n_tiles), side="right")
        self.members = [order[s:e] for s, e in zip(starts, ends, strict=True)]
        self.counts = ends - starts

    def objective(self, events: np.ndarray) -> ClusterEvaluator:
        """The objective over the given events."""
        return self._evaluator_for(events)

    def contrasts(self, velocities: np.ndarray) -> np.ndarray:
        """Every tile's contrast under each velocity (T x H)."""
        return self._grouped.group_values(velocities)

    def events_of(self, tiles: np.ndarray) -> np.ndarray:
        """The events of the given tiles, sorted."""
        return np.sort(np.concatenate([self.members[t] for t in tiles] or [np.zeros(0, int)]))

    def own_maxima(
        self, optimizer: Maximizer, bounds: np.ndarray, *, evals: int, seed: int
    ) -> np.ndarray:
        """Each tile's contrast maximised from zero velocity within ``bounds`` (T x dim)."""
        seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=len(self.members))
        x0 = np.zeros(bounds.shape[0])  # clipped into the box by maximize_contrast
        return np.array(
            [
                maximize_contrast(self._grouped.group(t), optimizer, x0, bounds, evals, int(s))[0]
                for t, s in enumerate(seeds)
            ]
        )


def greedy_cover(
    scores: np.ndarray, weights: np.ndarray, k: int, explained: float | None = None
) -> list[int]:
    """Pick ``k`` columns of ``scores`` (tiles x hypotheses, in [0, 1]) one at a time, each
    maximising ``sum_t weights_t max(covered_t, scores_t,h)``: the hypotheses that together
    explain the most (weighted) tiles. With ``explained``, a tile counts as explained once
    a pick scores at least that, and each pick first maximises the weight it newly explains
    (ties broken by the graded sum).

    Decision (``explained``): with the graded sum alone, a second velocity that makes the
    many tiles of a big static scene slightly better beats one that explains a small moving
    object; on ``ego_street`` one seed in six lost its cyclist that way (0.68).
    """
    chosen: list[int] = []
    covered = np.zeros(scores.shape[0])
    for _ in range(min(k, scores.shape[1])):
        reach = np.maximum(scores, covered[:, None])
        graded = (reach * weights[:, None]).sum(axis=0)
        if explained is None:
            count = np.zeros_like(graded)
        else:
            count = ((reach >= explained) * weights[:, None]).sum(axis=0)
        count[chosen] = graded[chosen] = -np.inf
        best = int(np.lexsort((graded, count))[-1])
        chosen.append(best)
        covered = np.maximum(covered, scores[:, best])
    return chosen


#: Voxels: two velocities that shift every probe point less than this apart are alike.
#: A quarter of a voxel over half the window (a voxel of the image grid is two pixels);
#: at a whole voxel the interior window's two carts were merged.
ALIKE = 0.25


def distinct_motions(shifts: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The hypotheses kept, heaviest first (indices): each one whose shifts (H x P x 3,
    :func:`spatialseg.points.voxel_shifts`) differ from those of a heavier kept one by
    under :data:`ALIKE` at every one of the P points is dropped as the same motion."""
    kept: list[int] = []
    for h in np.argsort(-np.asarray(weights), kind="stable"):
        if kept:
            gap = np.linalg.norm(shifts[kept] - shifts[h], axis=2)
            if np.any(np.nanmax(gap, axis=1) < ALIKE):
                continue
        kept.append(int(h))
    return np.array(kept, dtype=np.int64)


def _distinct_proposals(
    velocities: np.ndarray,
    counts: np.ndarray,
    k: int,
    shifts: Callable[[np.ndarray], np.ndarray] | None,
) -> np.ndarray:
    """The tiles' proposals the cover chooses among: the :func:`distinct_motions` (with
    ``shifts``) when at least ``k`` are distinct, else all."""
    if shifts is None:
        return velocities
    distinct = distinct_motions(shifts(velocities), counts)
    return velocities[distinct] if len(distinct) >= k else velocities


def widest_cover(
    raws: list[np.ndarray], weights: np.ndarray, k: int, explained: float | None
) -> int:
    """Which of several proposal sets (their tiles x proposals contrasts ``raws``) a greedy
    cover of ``k`` explains most with: the tile weight explained (:func:`greedy_cover`),
    then the graded sum, each tile's scores relative to its best proposal of any set; the
    first set on a tie (a single set without a cover)."""
    if len(raws) == 1:
        return 0
    best = np.maximum(np.max([raw.max(axis=1) for raw in raws], axis=0), 1e-300)
    reach = []
    for raw in raws:
        scores = raw / best[:, None]
        covered = scores[:, greedy_cover(scores, weights, k, explained)].max(axis=1)
        count = 0.0 if explained is None else float(((covered >= explained) * weights).sum())
        reach.append((count, float((covered * weights).sum())))
    return max(range(len(raws)), key=reach.__getitem__)


def tile_motions(
    tiles: Tiles,
    k: int,
    optimizer: Maximizer,
    bounds: np.ndarray,
    refit: Maximizer,
    *,
    evals: int,
    rounds: int,
    explained: float | None,
    seed: int,
    shifts: Callable[[np.ndarray], np.ndarray] | None = None,
    flatten: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """K velocities (K x dim) and each tile's motion (T,): the greedy cover of the tiles' own
    maxima (``optimizer``), then ``rounds`` of re-fitting each velocity on its tiles' events
    (``refit``, a local optimiser, from the velocity) and re-assigning each tile to the
    velocity it scores best (relative to the tile's best proposal for the cover; the best
    velocity of a tile is the same either way). ``explained``: see :func:`greedy_cover`.
    ``shifts(velocities)``: their :func:`~spatialseg.points.voxel_shifts`; with it, the
    cover chooses among the :func:`distinct_motions` only, the denser tile's of alike ones
    (among all when fewer than ``k`` are distinct, so that it still picks ``k``).
    ``flatten(velocities)``: each tile's velocity with the same image motion and no motion
    in depth; with it, the maxima or their flattened forms, whichever set's cover explains
    more tiles (:func:`widest_cover`).

    Decision: every tile's contrast under every tile's maximum is most of the start's cost
    on a large window (T x T group contrasts), and the tiles of one object propose
    velocities the volume cannot tell apart. ``flatten``: over a tile a motion in depth
    moves the events almost as a sideways one does, so a tile's maximum lies anywhere on a
    ridge in ``vz`` and the tiles of one object propose velocities that each explain part
    of it; flattened, the tiles of an object moving across the view agree, while a
    forward-moving camera's static scene needs its ``vz`` for one velocity to explain its
    tiles together, and the cover's reach tells the two apart (docs/results.md,
    session 64)."""
    own = tiles.own_maxima(optimizer, bounds, evals=evals, seed=seed)
    sets = [own] if flatten is None else [own, np.clip(flatten(own), bounds[:, 0], bounds[:, 1])]
    proposals = [_distinct_proposals(velocities, tiles.counts, k, shifts) for velocities in sets]
    raws = [tiles.contrasts(velocities) for velocities in proposals]
    weights = tiles.counts.astype(np.float64)
    pick = widest_cover(raws, weights, k, explained)
    own, raw = proposals[pick], raws[pick]
    best = np.maximum(raw.max(axis=1), 1e-300)
    chosen = greedy_cover(raw / best[:, None], weights, k, explained)
    velocities = own[chosen].copy()
    label = np.argmax(raw[:, chosen], axis=1)
    seeds = np.random.default_rng(seed + 1).integers(0, 2**31 - 1, size=(rounds, k))
    for r in range(rounds):
        for j in range(k):
            members = tiles.events_of(np.flatnonzero(label == j))
            if len(members):
                ev = tiles.objective(members)
                velocities[j] = maximize_contrast(
                    ev, refit, velocities[j], bounds, evals, int(seeds[r, j])
                )[0]
        label = np.argmax(tiles.contrasts(velocities), axis=1)
    return velocities, label
