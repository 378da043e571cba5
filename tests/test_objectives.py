"""The objective registry: definitions, derivatives w.r.t. V, the blur's symmetry, configs."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from spatialseg import reference as ref
from spatialseg.config import conf_dir, group_options
from spatialseg.objectives import (
    MomentObjective,
    Objective,
    make_objective,
    objective_names,
    register_objective,
    volume_moments,
)
from spatialseg.settings import settings_from


def _volume(seed: int = 0, shape=(7, 6, 5)) -> np.ndarray:
    """A sparse, non-negative random volume."""
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, 3.0, shape) * (rng.random(shape) < 0.3)


def test_builtin_objectives_are_registered():
    assert {"variance", "sum_of_squares"} <= set(objective_names())
    assert isinstance(make_objective("variance"), MomentObjective)


def test_definitions_match_numpy():
    v = _volume()
    assert make_objective("variance").value(v) == pytest.approx(np.var(v), rel=1e-12)
    assert make_objective("sum_of_squares").value(v) == pytest.approx(np.mean(v**2), rel=1e-12)
    for name, plain in ref.OBJECTIVES.items():
        assert make_objective(name).value(v) == pytest.approx(plain(v)[0], rel=1e-12)


@pytest.mark.parametrize("name", objective_names())
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_derivative_matches_finite_differences(name, dtype):
    """``value_and_derivative`` writes dO/dV; check every voxel by central differences."""
    objective = make_objective(name)
    v = _volume(1, shape=(4, 3, 3))
    out = np.empty_like(v, dtype=dtype)
    value = objective.value_and_derivative(v.astype(dtype), out)
    assert value == pytest.approx(objective.value(v), rel=1e-6)
    step = 1e-6
    numeric = np.zeros_like(v)
    for i in np.ndindex(v.shape):
        e = np.zeros_like(v)
        e[i] = step
        numeric[i] = (objective.value(v + e) - objective.value(v - e)) / (2 * step)
    np.testing.assert_allclose(out, numeric, rtol=1e-5, atol=1e-8 * np.abs(numeric).max())


def test_blur_is_symmetric_and_skips_single_voxel_axes():
    objective = make_objective("variance", blur_sigma=1.3)
    a, b = _volume(2), _volume(3)
    ka, kb = objective.smooth(a, np.empty_like(a)), objective.smooth(b, np.empty_like(b))
    assert np.vdot(ka, b) == pytest.approx(np.vdot(a, kb), rel=1e-12)
    flat = _volume(4, shape=(9, 8, 1))
    blurred = objective.smooth(flat, np.empty_like(flat))
    assert blurred.sum() <= flat.sum() and blurred[..., 0].max() < flat.max()
    assert make_objective("variance").smooths is False and objective.smooths is True


def test_moments_accumulate_in_float64():
    v = np.full((100, 100, 10), 0.1, dtype=np.float32)
    total, total_sq = volume_moments(v)
    assert total == pytest.approx(float(np.float32(0.1)) * v.size, rel=1e-10)
    assert total_sq == pytest.approx(float(np.float32(0.1)) ** 2 * v.size, rel=1e-10)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"name": "entropy"}, "unknown objective 'entropy'; choose one of: "),
        ({"name": "variance", "blur_sigma": -1.0}, "blur_sigma must be a finite number >= 0"),
        ({"name": "variance", "blur_sigma": float("nan")}, "blur_sigma must be a finite"),
        ({"name": "variance", "blur_sigma": "wide"}, "blur_sigma must be a finite"),
        ({"name": "variance", "sigma": 1.0}, "objective 'variance': bad parameters"),
    ],
)
def test_make_objective_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_objective(**kwargs)


def test_register_rejects_a_name_clash_and_a_missing_name():
    class Clash(Objective):
        name = "variance"

    with pytest.raises(ValueError, match="already registered"):
        register_objective(Clash)

    class Nameless(Objective):
        pass

    with pytest.raises(TypeError, match="needs a class attribute name"):
        register_objective(Nameless)


def test_every_objective_has_a_config_and_every_config_an_objective():
    assert set(group_options("objective")) == set(objective_names())
    for name in objective_names():
        cfg = OmegaConf.load(conf_dir() / "objective" / f"{name}.yaml")
        assert cfg.name == name  # the option selects; the settings hold the defaults
        section = settings_from({"objective": OmegaConf.to_container(cfg)}).objective
        objective = make_objective(name=section.name, blur_sigma=section.blur_sigma)
        assert objective.name == name and objective.blur_sigma == section.blur_sigma == 0.0
