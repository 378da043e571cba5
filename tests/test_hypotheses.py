"""The tile initialisation: tiling, the greedy cover, and two motions recovered from tiles."""

from __future__ import annotations

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import optimizers
from spatialseg.config import conf_dir
from spatialseg.grid import grid_around
from spatialseg.hypotheses import (
    Tiles,
    distinct_motions,
    greedy_cover,
    image_tiles,
    tile_motions,
    widest_cover,
)
from spatialseg.metrics import segmentation_metrics
from spatialseg.objectives import make_objective
from spatialseg.points import ModelEvaluator
from spatialseg.scenes import load_scene
from spatialseg.settings import settings_from
from spatialseg.volume import VolumeObjective
from spatialseg.window import segment_window

from .test_clustering import _two_motion_cloud


def test_image_tiles_number_dense_tiles_and_drop_sparse_ones():
    xy = np.array([[1.0, 1.0], [2.0, 3.0], [5.0, 1.0], [17.0, 1.0], [18.0, 2.0], [40.0, 40.0]])
    tile, counts = image_tiles(xy, 16.0, 2)
    assert tile.tolist() == [0, 0, 0, 1, 1, -1] and counts.tolist() == [3, 2]
    with pytest.raises(ValueError, match=r"init\.tiles\.size must be > 0"):
        image_tiles(xy, 0.0, 2)


def test_image_tiles_are_numbered_in_row_order_of_their_cells():
    """Tiles numbered as the cells' rows sort (x, then y), negative cells and none too."""
    xy = np.random.default_rng(0).uniform(-40, 300, (5000, 2))
    tile, counts = image_tiles(xy, 16.0, 3)
    cells = np.floor(xy / 16.0).astype(np.int64)
    rows, inverse, every = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    dense = every >= 3
    np.testing.assert_array_equal(counts, every[dense])
    kept = tile >= 0
    np.testing.assert_array_equal(kept, dense[inverse.reshape(-1)])
    np.testing.assert_array_equal(cells[kept], rows[dense][tile[kept]])
    assert image_tiles(np.zeros((0, 2)), 16.0, 3)[0].shape == (0,)


def test_greedy_cover_prefers_distinct_explanations():
    """Tiles 0-2 are explained by hypothesis 0 or 1 (near duplicates), tiles 3-4 only by 2."""
    scores = np.array(
        [
            [1.0, 0.98, 0.2],
            [1.0, 0.99, 0.1],
            [0.97, 1.0, 0.3],
            [0.2, 0.2, 1.0],
            [0.3, 0.1, 1.0],
        ]
    )
    assert greedy_cover(scores, np.ones(5), 2) == [0, 2]
    assert greedy_cover(scores, np.ones(5), 5) == [0, 2, 1]  # at most one pick per column


def test_explained_tiles_keep_a_small_object():
    """Many static tiles a bit better under hypothesis 1 than 0; one small object tile that
    only hypothesis 2 explains: the graded sum picks 1 second, the explained count 2."""
    static = np.tile([0.9, 1.0, 0.3], (20, 1))
    static[:, 0] = 1.0
    static[10:, 1] = 0.8  # 1 is better on half the static tiles only...
    static[:10, 0] = 0.88  # ... and 0 on the other half
    obj = np.array([[0.2, 0.3, 1.0]])
    scores = np.vstack([static, obj])
    weights = np.ones(21)
    assert greedy_cover(scores, weights, 2)[1] == 1
    assert greedy_cover(scores, weights, 2, explained=0.85)[1] == 2


def test_widest_cover_picks_the_set_that_explains_more_tiles():
    """Two proposal sets over four tiles: the one whose two picks explain three tiles wins
    over one whose best two explain two, whatever the order; on a tie the first."""
    weights = np.ones(4)
    narrow = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    wide = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])
    assert widest_cover([narrow, wide], weights, 2, 0.85) == 1
    assert widest_cover([wide, narrow], weights, 2, 0.85) == 0
    assert widest_cover([wide, wide.copy()], weights, 2, 0.85) == 0
    assert widest_cover([narrow], weights, 2, 0.85) == 0
    assert widest_cover([narrow * 0.5, wide * 0.5], weights, 2, None) == 1


def test_distinct_motions_keep_the_heaviest_of_alike_velocities():
    """Hypotheses 0 and 2 shift every point alike (under a quarter voxel apart), 1 and 3
    differ from both; 0 is dropped for the heavier 2. Alike means alike at every point: 3
    differs from 1 at one of three points only, by half a voxel, and is kept."""
    shifts = np.zeros((4, 3, 3))
    shifts[1, :, 0] = 4.0
    shifts[2, :, 1] = 0.2
    shifts[3, :, 0] = 4.0
    shifts[3, 0, 2] = 0.5
    assert distinct_motions(shifts, np.array([5.0, 1.0, 9.0, 2.0])).tolist() == [2, 3, 1]
    shifts[3, 0, 2] = 0.1  # now alike to 1 everywhere: the lighter of the two goes
    assert distinct_motions(shifts, np.array([5.0, 1.0, 9.0, 2.0])).tolist() == [2, 3]
    assert distinct_motions(shifts, np.array([5.0, 3.0, 9.0, 2.0])).tolist() == [2, 1]


@pytest.mark.parametrize("alike", ["kept", "merged", "all"])
def test_tiles_group_events_and_recover_two_motions(alike):
    """With the tiles' alike velocities merged (``shifts``) or not, the two motions; when
    fewer than K proposals are distinct (``all``: every one alike), the cover uses all."""
    rng = np.random.default_rng(0)
    points, dt, labels, truth = _two_motion_cloud(rng)
    grid = grid_around(points, np.array([0.005, 0.005, 0.02]), 0.1, 10**7)
    event_tile, counts = image_tiles(points[:, :2], 0.05, 30)

    def evaluator_for(index: np.ndarray) -> ModelEvaluator:
        return ModelEvaluator(VolumeObjective(points[index], dt[index], grid, "variance"), 3)

    in_tiles = np.flatnonzero(event_tile >= 0)
    grouped = VolumeObjective(
        points[in_tiles], dt[in_tiles], grid, "variance", groups=event_tile[in_tiles]
    )
    tiles = Tiles(evaluator_for, event_tile, len(counts), grouped)
    assert (
        sorted(np.concatenate(tiles.members).tolist()) == np.flatnonzero(event_tile >= 0).tolist()
    )
    bounds = np.array([[-1.0, 1.0], [-1.0, 1.0], [-0.1, 0.1]])
    assert tiles.counts.tolist() == counts.tolist()
    probes, half = points[::50], 0.5 * float(np.ptp(dt))

    def shifts(velocities: np.ndarray) -> np.ndarray:
        return np.stack([grid.continuous_index(probes - half * v) for v in velocities])

    velocities, tile_label = tile_motions(
        tiles,
        2,
        optimizers.create("ssa_ga"),
        bounds,
        optimizers.preset("nlopt_bobyqa"),
        evals=60,
        rounds=2,
        explained=0.85,
        seed=0,
        shifts={"kept": None, "merged": shifts, "all": lambda v: np.zeros((len(v), 1, 3))}[alike],
        flatten=lambda v: np.zeros_like(v),  # one velocity for every tile: the maxima win
    )
    order = np.argsort(velocities[:, 0])[::-1]  # truth: +0.3 then -0.2 in vx
    np.testing.assert_allclose(velocities[order, :2], truth[:, :2], atol=0.03)
    event_label = np.where(event_tile >= 0, tile_label[np.maximum(event_tile, 0)], -1)
    kept = event_label >= 0
    assert np.mean(order[event_label[kept]] == labels[kept]) > 0.95


def test_grouped_contrasts_equal_one_volume_per_tile():
    """One volume judging every tile alone gives each tile's own volume's values, bit for
    bit, with the variance (fused kernel) and with a blurred objective (a volume per tile)."""
    rng = np.random.default_rng(1)
    points, dt, _, _ = _two_motion_cloud(rng)
    grid = grid_around(points, np.array([0.005, 0.005, 0.02]), 0.1, 10**7)
    event_tile, counts = image_tiles(points[:, :2], 0.05, 30)
    in_tiles = np.flatnonzero(event_tile >= 0)
    velocities = rng.normal(0.0, 0.3, (7, 3))
    for objective in (make_objective("variance"), make_objective("variance", blur_sigma=1.0)):
        one = VolumeObjective(
            points[in_tiles], dt[in_tiles], grid, objective, groups=event_tile[in_tiles]
        )
        grouped = one.group_values(velocities)
        assert grouped.shape == (len(counts), 7)
        for tile in range(len(counts)):
            index = np.flatnonzero(event_tile == tile)
            alone = VolumeObjective(points[index], dt[index], grid, objective)
            assert np.array_equal(grouped[tile], alone.batch_value(velocities))


def test_a_groups_own_objective_equals_a_volume_of_its_events_and_leaves_the_shared_one_zero():
    """``group(g)`` judges tile ``g``'s events (in the order given, with their weights) as a
    volume of its own would, bit for bit, although it votes into the grouped volume's
    buffers; the grouped volume's values are unchanged after it."""
    rng = np.random.default_rng(2)
    points, dt, _, _ = _two_motion_cloud(rng)
    grid = grid_around(points, np.array([0.005, 0.005, 0.02]), 0.1, 10**7)
    event_tile, counts = image_tiles(points[:, :2], 0.05, 30)
    in_tiles = np.flatnonzero(event_tile >= 0)
    weights = rng.uniform(0.2, 1.0, len(in_tiles))
    one = VolumeObjective(
        points[in_tiles], dt[in_tiles], grid, "variance", weights, groups=event_tile[in_tiles]
    )
    velocities = rng.normal(0.0, 0.3, (5, 3))
    before = one.batch_value(velocities), one.value_and_grad(velocities[0])
    for tile in (0, len(counts) // 2, len(counts) - 1):
        mine = event_tile[in_tiles] == tile
        alone = VolumeObjective(points[in_tiles][mine], dt[in_tiles][mine], grid, "variance")
        alone.set_weights(weights[mine])
        part = one.group(tile)
        assert np.array_equal(part.order, alone.order)
        assert np.array_equal(part.batch_value(velocities), alone.batch_value(velocities))
        assert part.value(velocities[1]) == alone.value(velocities[1])
        value, grad = part.value_and_grad(velocities[2])
        assert value == alone.value_and_grad(velocities[2])[0]
        assert np.array_equal(grad, alone.grad(velocities[2]))
        found, expected = part.p_step(velocities[3], 1.5, 2), alone.p_step(velocities[3], 1.5, 2)
        assert np.array_equal(found[0], expected[0]) and found[1] == expected[1]
    after = one.batch_value(velocities), one.value_and_grad(velocities[0])
    assert np.array_equal(after[0], before[0]) and after[1][0] == before[1][0]
    with pytest.raises(ValueError, match=r"group must be in \[0, "):
        one.group(len(counts))


def test_volume_refuses_groups_that_are_not_one_integer_per_event():
    points = np.zeros((3, 3)) + 0.5
    grid = grid_around(points, np.array([0.1, 0.1, 0.1]), 0.1, 10**5)
    with pytest.raises(ValueError, match="groups must be 3 integers"):
        VolumeObjective(points, np.zeros(3), grid, "variance", groups=np.array([0.0, 1.0, 1.0]))


def _config(*overrides: str) -> dict:
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["+scene=interior", *overrides])
    return OmegaConf.to_container(cfg, resolve=True)


def test_tile_init_segments_the_interior_window():
    cfg = _config("init.method=tiles")
    _, window = next(load_scene(cfg["scene"], seed=0, window_events=4000).windows())
    res = segment_window(window, settings_from(cfg), optimizers.create("ssa_ga"), seed=0)
    assert segmentation_metrics(res.labels, window.ground_truth.labels)["accuracy"] > 0.95


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("init.method=kmeans", "init.method must be one of"),
        ("init.tiles.refit=no_such", "init.tiles.refit: unknown optimizer 'no_such'"),
    ],
)
def test_bad_init_settings_name_the_choices(override, message):
    cfg = _config("init.method=tiles", override)
    _, window = next(load_scene(cfg["scene"], seed=0, window_events=2000).windows())
    with pytest.raises(ValueError, match=message):
        segment_window(window, settings_from(cfg), optimizers.create("ssa_ga"), seed=0)
