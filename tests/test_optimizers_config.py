"""Every registered optimiser has a config in conf/optimizer/, and configs build optimisers
through Hydra exactly as ``optimizer=NAME optimizer.PARAM=VALUE`` does on the command line."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf

import optimizers
from spatialseg.config import ConfigError, conf_dir, group_options, validate_config

CONFIGS = group_options("optimizer")


def load(name: str) -> dict:
    """conf/optimizer/NAME.yaml as a plain dict."""
    return OmegaConf.to_container(OmegaConf.load(conf_dir() / "optimizer" / f"{name}.yaml"))


def composed(*overrides: str):
    """The composed job config for these command-line overrides, checked by the validator."""
    with initialize_config_dir(version_base="1.3", config_dir=str(conf_dir())):
        cfg = compose("config", overrides=["+scene=interior", *overrides])
    choice = next(o.split("=")[1] for o in overrides if o.startswith("optimizer="))
    validate_config(cfg, {"optimizer": choice, "scene": "interior"})
    return cfg


@pytest.mark.parametrize("name", optimizers.available())
def test_registered_name_has_a_config_holding_its_defaults(name):
    assert name in CONFIGS
    config = load(name)
    target = get_class(config.pop("_target_"))
    assert target is type(optimizers.create(name))
    assert config == {
        field: getattr(optimizers.create(name).hp, field) for field in target.hyperparameter_names()
    }


@pytest.mark.parametrize("name", CONFIGS)
def test_config_lists_every_hyperparameter_of_its_target(name):
    config = load(name)
    target = get_class(config.pop("_target_"))
    assert list(config) == target.hyperparameter_names()
    assert isinstance(
        instantiate(OmegaConf.load(conf_dir() / "optimizer" / f"{name}.yaml")), target
    )


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
