"""Every optimiser preset is an option of the ``optimizer`` group, holding all its
hyperparameters, and builds through Hydra exactly as ``optimizer=NAME optimizer.PARAM=VALUE``
does on the command line (the presets live in the optimizers package, not in conf/)."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

import optimizers
from spatialseg.config import ConfigError, conf_dir, group_options, validate_config


def composed(*overrides: str):
    """The composed job config for these command-line overrides, checked by the validator."""
    with initialize_config_dir(version_base="1.3", config_dir=str(conf_dir())):
        cfg = compose("config", overrides=["+scene=interior", *overrides])
    choice = next(o.split("=")[1] for o in overrides if o.startswith("optimizer="))
    validate_config(cfg, {"optimizer": choice, "scene": "interior"})
    return cfg


def test_the_group_offers_every_preset():
    assert set(optimizers.preset_names()) <= set(group_options("optimizer"))
    assert not (conf_dir() / "optimizer").exists()  # no copy of the hyperparameters


@pytest.mark.parametrize("name", optimizers.preset_names())
def test_each_option_lists_every_hyperparameter_and_builds_the_preset(name):
    cfg = composed(f"optimizer={name}")
    listed = {k: v for k, v in cfg.optimizer.items() if k not in ("_target_", "name")}
    assert listed == optimizers.preset_hyperparameters(name)
    built = instantiate(cfg.optimizer)
    assert type(built) is type(optimizers.preset(name))
    assert built.hp == optimizers.preset(name).hp


def test_command_line_selects_the_optimiser_and_its_hyperparameters():
    cfg = composed("optimizer=nlopt", "optimizer.algorithm=LD_MMA", "optimizer.xtol_rel=1e-6")
    opt = instantiate(cfg.optimizer)
    assert isinstance(opt, optimizers.NLopt)
    assert (opt.hp.algorithm, opt.hp.xtol_rel) == ("LD_MMA", 1e-6)
    assert isinstance(
        instantiate(composed("optimizer=ssa_ga").optimizer), optimizers.SSAGradientAscent
    )


def test_command_line_rejects_an_unknown_hyperparameter():
    with pytest.raises(ConfigError, match=r"optimizer\.bogus"):
        composed("optimizer=pso", "+optimizer.bogus=1")
