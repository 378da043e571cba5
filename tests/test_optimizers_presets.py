"""Optimiser presets: one name for an optimiser and its hyperparameters, in the optimizers
package (applications name presets; they keep no copy of the hyperparameters)."""

from __future__ import annotations

import pytest

import optimizers
from optimizers.presets import VARIANTS


def test_every_registered_optimiser_is_its_own_preset_at_its_defaults():
    for name in optimizers.available():
        assert name in optimizers.preset_names()
        made, default = optimizers.preset(name), optimizers.create(name)
        assert type(made) is type(default) and made.hp == default.hp


@pytest.mark.parametrize("name", sorted(VARIANTS))
def test_a_variant_is_its_optimiser_with_its_own_values(name):
    registered, chosen = VARIANTS[name]
    made = optimizers.preset(name)
    assert type(made) is type(optimizers.create(registered))
    assert all(getattr(made.hp, key) == value for key, value in chosen.items())
    full = optimizers.preset_hyperparameters(name)
    assert list(full) == type(made).hyperparameter_names()
    assert optimizers.create(registered, **full).hp == made.hp


def test_overrides_apply_over_the_preset_and_are_checked():
    made = optimizers.preset("nlopt_mma", xtol_rel=1e-6)
    assert (made.hp.algorithm, made.hp.xtol_rel) == ("LD_MMA", 1e-6)
    with pytest.raises(ValueError, match=r"unknown optimizer 'nope'; choose from .*ssa_ga"):
        optimizers.preset("nope")
    with pytest.raises(ValueError, match="bogus"):
        optimizers.preset("pso", bogus=1)
