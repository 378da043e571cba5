"""Algorithm 1: memberships, stopping rules, and recovery of two known motions."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import optimizers
from spatialseg.clustering import (
    ConvergenceRules,
    IterationRecord,
    StepStage,
    _step_rows,
    _stop_reason,
    cluster_responses,
    initial_memberships,
    iterative_clustering,
    p_step,
    repaired_memberships,
    squarem_step,
    update_memberships,
)
from spatialseg.config import conf_dir
from spatialseg.grid import grid_around
from spatialseg.metrics import segmentation_metrics
from spatialseg.points import ModelEvaluator
from spatialseg.scenes import load_scene
from spatialseg.settings import settings_from
from spatialseg.volume import VolumeObjective
from spatialseg.window import segment_window


def test_update_memberships_normalises_and_guards_zero_rows():
    p = update_memberships(np.array([[1.0, 3.0], [0.0, 0.0], [-1.0, 2.0]]))
    assert np.allclose(p, [[0.25, 0.75], [0.5, 0.5], [0.0, 1.0]])


@pytest.mark.parametrize("k", [1, 2, 3, 5, 7])
def test_update_memberships_is_eq_26_to_the_last_bit(k):
    """The kernel gives numpy's normalisation exactly (negative responses as 0, all-zero
    rows uniform) over responses of every magnitude, for up to 7 clusters."""
    rng = np.random.default_rng(k)
    responses = rng.random((3000, k)) * 10.0 ** rng.uniform(-300, 300, (3000, k))
    responses[rng.random((3000, k)) < 0.1] = 0.0
    responses[rng.random((3000, k)) < 0.05] *= -1.0
    responses[:5] = 0.0
    clipped = np.maximum(responses, 0.0)
    total = clipped.sum(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        expected = np.where(total > 0, clipped / np.where(total > 0, total, 1.0), 1.0 / k)
    np.testing.assert_array_equal(update_memberships(responses), expected)


def test_initial_memberships_flow_and_uniform():
    points = np.array([[0.0, 0, 0], [0.1, 0, 0], [5.0, 0, 0], [5.1, 0, 0]])
    labels = np.array([0, -1, 1, -1])
    p = initial_memberships(points, np.ones(3), labels, 2, mode="flow", confidence=0.9)
    assert np.allclose(p, [[0.9, 0.1], [0.9, 0.1], [0.1, 0.9], [0.1, 0.9]])
    twins = initial_memberships(
        points[[0, 0]], np.ones(3), np.array([0, 1]), 2, mode="flow", confidence=0.9
    )
    assert np.allclose(twins, [[0.9, 0.1], [0.1, 0.9]])  # a labelled event keeps its own label
    u = initial_memberships(points, np.ones(3), labels, 2, mode="uniform", confidence=0.9)
    assert np.allclose(u, 0.5)
    with pytest.raises(ValueError, match="init_memberships must be"):
        initial_memberships(points, np.ones(3), labels, 2, mode="kmeans", confidence=0.9)


def test_convergence_rules_validate():
    with pytest.raises(ValueError, match="max_iterations"):
        ConvergenceRules(max_iterations=0, tol=1e-3, patience=1)
    with pytest.raises(ValueError, match="label_tol must be in"):
        ConvergenceRules(max_iterations=5, tol=1e-3, patience=1, label_tol=1.5)


def _history(totals: list[float], changed: list[float]) -> list[IterationRecord]:
    """Iteration records with the given total contrasts and shares of changed labels."""
    return [
        IterationRecord(i + 1, np.array([t]), np.zeros((1, 3)), 1, 0.0, c)
        for i, (t, c) in enumerate(zip(totals, changed, strict=True))
    ]


def test_stable_labels_stop_the_loop_while_the_contrast_still_rises():
    rules = ConvergenceRules(max_iterations=20, tol=1e-3, patience=2, label_tol=0.005)
    rising = [1.0, 1.1, 1.2, 1.3]
    assert _stop_reason(_history(rising, [0.3, 0.01, 0.004, 0.02]), rules) == ""
    assert "labels changed < 0.005" in _stop_reason(
        _history(rising, [0.3, 0.01, 0.004, 0.001]), rules
    )
    off = ConvergenceRules(max_iterations=20, tol=1e-3, patience=2)
    assert _stop_reason(_history(rising, [0.3, 0.01, 0.004, 0.001]), off) == ""


def _two_motion_cloud(rng: np.random.Generator):
    """Textured points on two planes translating with known 3-D velocities."""
    truth = np.array([[0.3, 0.1, 0.0], [-0.2, 0.25, 0.0]])
    n = 3000
    seeds = [rng.uniform(-0.1, 0.1, size=(60, 2)) + c for c in ([-0.2, 0.0], [0.2, 0.0])]
    points, labels, t = [], [], rng.uniform(0.0, 0.2, size=2 * n)
    for j in range(2):
        base = seeds[j][rng.integers(0, 60, n)] + rng.normal(0, 0.002, size=(n, 2))
        xyz = np.column_stack([base, np.full(n, 1.0 + 0.2 * j)])
        tj = t[j * n : (j + 1) * n]
        points.append(xyz + (tj - 0.1)[:, None] * truth[j])
        labels.append(np.full(n, j))
    return np.vstack(points), t - 0.1, np.concatenate(labels), truth


def test_clustering_recovers_two_known_motions():
    rng = np.random.default_rng(0)
    points, dt, labels, truth = _two_motion_cloud(rng)
    grid = grid_around(points, np.array([0.005, 0.005, 0.02]), 0.1, 10**7)
    evaluator = ModelEvaluator(VolumeObjective(points, dt, grid, "variance"), 3)
    start = truth + np.array([[0.05, -0.04, 0.0], [-0.04, 0.05, 0.0]])
    p0 = initial_memberships(points, grid.voxel_size, labels, 2, mode="flow", confidence=0.9)
    bounds = np.array([[-1.0, 1.0], [-1.0, 1.0], [-0.1, 0.1]])
    result = iterative_clustering(
        evaluator,
        optimizers.create("ssa_ga"),
        start,
        p0,
        bounds,
        rules=ConvergenceRules(max_iterations=5, tol=1e-3, patience=1),
        evals_per_step=200,
        p_step_sigma=2.0,
        seed=0,
    )
    assert np.all(np.abs(result.thetas[:, :2] - truth[:, :2]) < 0.03)
    assert np.mean(result.probabilities.argmax(axis=1) == labels) > 0.95
    totals = [r.total for r in result.history]
    assert len(totals) == result.iterations and all(np.isfinite(totals))


def test_p_step_prior_weight_scales_responses_by_the_cluster_shares():
    """prior_weight 0 is the paper's P-step; 1 multiplies each event's responses by the
    clusters' shares (mean memberships), which moves events towards the larger cluster."""
    rng = np.random.default_rng(0)
    points, dt, labels, truth = _two_motion_cloud(rng)
    grid = grid_around(points, np.array([0.005, 0.005, 0.02]), 0.1, 10**7)
    evaluator = ModelEvaluator(VolumeObjective(points, dt, grid, "variance"), 3)
    p = np.where(labels[:, None] == np.arange(2), 0.8, 0.2)
    p[: len(p) // 4] = [0.9, 0.1]  # cluster 0 the larger
    plain = p_step(evaluator, truth, p, 2.0, 1)
    none = p_step(evaluator, truth, p, 2.0, 1, np.zeros(len(p)))
    full = p_step(evaluator, truth, p, 2.0, 1, np.ones(len(p)))
    np.testing.assert_allclose(none, plain, atol=1e-12)
    responses = cluster_responses(evaluator, truth, p, 2.0, 1)[0]
    np.testing.assert_allclose(full, update_memberships(responses * p.mean(axis=0)), atol=1e-12)
    assert p.mean(axis=0)[0] > 0.5 and np.all(full[:, 0] >= plain[:, 0] - 1e-12)
    for bad in (np.ones(3), np.full(len(p), 1.5)):
        with pytest.raises(ValueError, match=r"prior_weight must be \d+ numbers in \[0, 1\]"):
            p_step(evaluator, truth, p, 2.0, 1, bad)


def test_repaired_memberships_give_an_emptied_cluster_back_its_events():
    """Issue #25: the P-step weighted by the memberships leaves a cluster with none of them
    empty even at its object's velocity; the repair (every event in every volume, then
    weighted P-steps until the labels settle) gives it that object's events back."""
    rng = np.random.default_rng(0)
    points, dt, labels, truth = _two_motion_cloud(rng)
    grid = grid_around(points, np.array([0.005, 0.005, 0.02]), 0.1, 10**7)
    evaluator = ModelEvaluator(VolumeObjective(points, dt, grid, "variance"), 3)
    emptied = np.column_stack([np.ones(len(points)), np.zeros(len(points))])
    assert np.all(p_step(evaluator, truth, emptied, 2.0, 1).argmax(axis=1) == 0)
    repaired = repaired_memberships(evaluator, truth, 2.0, max_steps=20)
    assert repaired.shape == emptied.shape
    np.testing.assert_allclose(repaired.sum(axis=1), 1.0)
    assert np.mean(repaired.argmax(axis=1) == labels) > 0.95


def test_theta_step_on_a_subset_labels_every_event():
    """clustering.step_events: velocities from a sample, memberships and contrasts for all."""
    overrides = ["+scene=interior", "clustering.step_events=1500"]
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = OmegaConf.to_container(compose("config", overrides=overrides), resolve=True)
    rec = load_scene(cfg["scene"], seed=0, window_events=4000)
    _, window = next(rec.windows())
    res = segment_window(window, settings_from(cfg), optimizers.create("ssa_ga"), seed=0)
    assert res.probabilities.shape == (len(window.events), 2)
    assert segmentation_metrics(res.labels, window.ground_truth.labels)["accuracy"] > 0.95
    # one iteration from uniform memberships: the recorded contrast is the full volume's
    one = {**cfg, "clustering": {**cfg["clustering"], "max_iterations": 1}}
    one["clustering"]["init_memberships"] = "uniform"
    res = segment_window(window, settings_from(one), optimizers.create("ssa_ga"), seed=0)
    full = ModelEvaluator(
        VolumeObjective(
            res.prepared.points, res.prepared.t - res.t_ref, res.prepared.grid, "variance"
        ),
        3,
    )
    full.set_weights(np.full(full.n_events, 0.5))
    last = res.clustering.history[-1]  # the loop's velocities (thetas are the refit's)
    assert last.per_cluster[0] == pytest.approx(full.value(last.thetas[0]), rel=1e-9)


def test_fast_preset_is_one_window_with_an_earlier_stop():
    """+preset=fast is +preset=one_window with only the stopping rule changed."""
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        base = OmegaConf.to_container(
            compose("config", overrides=["+scene=interior", "+preset=one_window"])
        )
        fast = OmegaConf.to_container(
            compose("config", overrides=["+scene=interior", "+preset=fast"])
        )
    assert fast["clustering"]["label_tol"] == 0.005
    changed = {k for k in base["clustering"] if base["clustering"][k] != fast["clustering"][k]}
    assert changed == {"label_tol"}
    assert {k: v for k, v in fast.items() if k != "clustering"} == {
        k: v for k, v in base.items() if k != "clustering"
    }


def test_one_window_preset_clusters_each_window_alone_from_the_flow_start():
    """+preset=one_window: the image-flow start alone, no neighbouring windows (so the
    P-step takes clustering.p_step_alone), edge events out of the theta-step, one window."""
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        base = compose("config", overrides=["+scene=ego_street"])
        cfg = compose("config", overrides=["+scene=ego_street", "+preset=one_window"])
    assert base.init.method == "auto" and base.window.context == 1 and base.window.count == 3
    assert cfg.init.method == "image_flow" and cfg.clustering.step_edges is False
    assert cfg.window.context == 0 and cfg.window.count == 1


class _Stub:
    """An optimiser that spends ``cost`` evaluations and moves ``theta`` by ``shift`` per call."""

    def __init__(self, cost: int, shift: float) -> None:
        self.cost, self.shift = cost, shift

    def maximize(self, fun, bounds, x0=None, grad=None, max_evals=2000, seed=0, **kwargs):
        return SimpleNamespace(x=np.asarray(x0) + self.shift, n_evals=self.cost)


@pytest.mark.parametrize("shift, searched", [(0.0, 2), (1e-4, 6)])
def test_the_theta_steps_stop_once_patience_of_them_moved_no_velocity(shift, searched):
    """A theta-step that keeps every velocity twice (patience 2) ends the search: the loop
    then runs P-steps only; one that moves a velocity each time runs every iteration."""
    rng = np.random.default_rng(0)
    points, dt, labels, truth = _two_motion_cloud(rng)
    grid = grid_around(points, np.array([0.005, 0.005, 0.02]), 0.1, 10**7)
    evaluator = ModelEvaluator(VolumeObjective(points, dt, grid, "variance"), 3)
    p0 = initial_memberships(points, grid.voxel_size, labels, 2, mode="flow", confidence=0.6)
    result = iterative_clustering(
        evaluator,
        _Stub(cost=7, shift=shift),
        truth,
        p0,
        np.array([[-1.0, 1.0], [-1.0, 1.0], [-0.1, 0.1]]),
        rules=ConvergenceRules(max_iterations=6, tol=0.0, patience=2),
        evals_per_step=7,
        p_step_sigma=2.0,
        seed=0,
    )
    assert [r.n_evals for r in result.history] == [14] * searched + [0] * (6 - searched)
    changed = [r.labels_changed for r in result.history]
    assert changed[0] > 0  # the P-steps go on: the flow start's soft memberships harden
    assert np.mean(result.probabilities.argmax(axis=1) == labels) > 0.95


@pytest.mark.parametrize("subset", [slice(None), np.array([7, 2, 9, 4, 0, 5])])
def test_the_theta_steps_rows_are_its_events_in_its_own_order(subset):
    """The loop keeps memberships in the P-step evaluator's order; the theta-step's evaluator
    (of a subset of the events, in its own order) reads its events' rows from them."""
    rng = np.random.default_rng(5)
    memberships = rng.uniform(size=(10, 2))
    order = rng.permutation(10)
    size = len(np.arange(10)[subset])
    step = StepStage(SimpleNamespace(order=rng.permutation(size)), None, 1, subset)
    rows = _step_rows(step, order)
    expected = memberships[subset][step.evaluator.order]
    assert np.array_equal(memberships[order][rows], expected)


def test_squarem_lands_on_the_fixed_point_of_a_uniform_contraction():
    """For ``F(p) = p* + c (p - p*)`` two steps determine ``p*``, and SQUAREM's extrapolation
    returns it exactly, where a third plain step is still ``c^3`` of the way off."""
    rng = np.random.default_rng(4)
    target = rng.dirichlet(np.ones(3), 200)
    p0 = rng.dirichlet(np.ones(3), 200)
    step = lambda p: target + 0.8 * (p - target)  # noqa: E731
    p1, p2 = step(p0), step(step(p0))
    assert np.allclose(squarem_step(p0, p1, p2), target, atol=1e-12)
    assert np.abs(step(p2) - target).max() > 0.1 * np.abs(p0 - target).max()
    assert squarem_step(p0, p0, p0) is p0  # no movement: nothing to extrapolate


def test_squarem_keeps_every_row_on_the_simplex():
    """An extrapolation that overshoots (steps of 0.3 then 0.15 towards label 0: the
    unfloored step lands at 1.1 and -0.1) is floored and renormalised: memberships stay
    probabilities, here the hard label the steps head for."""
    p0 = np.tile([0.5, 0.5], (5, 1))
    p1 = np.tile([0.8, 0.2], (5, 1))
    p2 = np.tile([0.95, 0.05], (5, 1))
    q = squarem_step(p0, p1, p2)
    assert np.all(q > 0) and np.allclose(q.sum(axis=1), 1.0)
    assert np.allclose(q, [1.0, 0.0], atol=1e-9)
    rng = np.random.default_rng(5)
    p0, p1, p2 = (rng.dirichlet(np.ones(4), 300) for _ in range(3))
    q = squarem_step(p0, p1, p2)
    assert np.all(q > 0) and np.allclose(q.sum(axis=1), 1.0)
