"""Locating ``conf/`` and validating a composed configuration against it.

Hydra accepts ``+anything=value`` and silently adds the key, so a misspelt ``+scnee=interior``
would run without a scene. :func:`validate_config` compares every key of the composed config
with the keys the shipped YAML files define and rejects the unknown ones, listing the valid.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

__all__ = ["ConfigError", "conf_dir", "group_options", "validate_config"]

#: Hydra's own and launcher keys that never appear in our YAML files.
_HYDRA_KEYS = {"hydra"}


class ConfigError(ValueError):
    """A configuration mistake a user can fix on the command line."""


def conf_dir() -> Path:
    """The project's ``conf/`` directory (a checkout or an editable install)."""
    here = Path(__file__).resolve().parent
    for candidate in (here / "conf", here.parent / "conf"):
        if (candidate / "config.yaml").is_file():
            return candidate
    raise ConfigError(
        f"spatialseg cannot find its conf/ directory next to {here}; "
        "install it from a checkout with: pip install -e ."
    )


def group_options(group: str) -> list[str]:
    """Sorted option names of a config group (the YAML files in ``conf/<group>/``)."""
    return sorted(p.stem for p in (conf_dir() / group).glob("*.yaml"))


def _groups() -> list[str]:
    """The project's config groups (``conf/hydra/`` holds Hydra's own launcher configs)."""
    return sorted(p.name for p in conf_dir().iterdir() if p.is_dir() and p.name != "hydra")


def _check_keys(composed: Any, reference: Any, path: str) -> None:
    """Raise ConfigError for any mapping key in ``composed`` absent from ``reference``."""
    if not isinstance(composed, DictConfig | Mapping) or not isinstance(
        reference, DictConfig | Mapping
    ):
        return
    for key in composed:
        where = f"{path}.{key}" if path else str(key)
        if key not in reference:
            valid = ", ".join(sorted(str(k) for k in reference))
            raise ConfigError(
                f"unknown config key '{where}'; valid keys here: {valid}"
                + (f". Config groups: {', '.join(_groups())}" if not path else "")
            )
        if not isinstance(composed[key], ListConfig):
            _check_keys(composed[key], reference[key], where)


def validate_config(
    cfg: DictConfig, choices: Mapping[str, str | None], primary: str = "config.yaml"
) -> None:
    """Check ``cfg`` against the primary ``conf/<primary>`` and each chosen group option's YAML.

    ``choices`` maps group name to the selected option (Hydra's ``runtime.choices``).
    Keys a group option does not define (e.g. ``optimizer.typo``) are rejected too, except
    in groups whose options declare ``_open_: true`` (free-form sections).
    """
    root = conf_dir()
    reference = OmegaConf.to_container(OmegaConf.load(root / primary), resolve=False)
    assert isinstance(reference, dict)
    reference.pop("defaults", None)
    groups = _groups()
    for group in groups:
        if group != "hydra":
            reference.setdefault(group, {})
    for key in _HYDRA_KEYS:
        reference[key] = {}
    for key in cfg:
        if key not in reference:
            raise ConfigError(
                f"unknown config key '{key}'; valid top-level keys: "
                f"{', '.join(sorted(k for k in reference if k not in _HYDRA_KEYS))}. "
                f"Did you mean one of the groups ({', '.join(groups)}) with + for scene?"
            )
    if "scene" not in cfg:
        raise ConfigError(
            "no scene selected; add +scene=NAME with NAME one of: "
            + ", ".join(group_options("scene"))
        )
    for key, value in cfg.items():
        if key in _HYDRA_KEYS:
            continue
        if key in groups:
            option = choices.get(str(key))
            if option is None:
                continue
            option_ref = OmegaConf.load(root / str(key) / f"{option}.yaml")
            if isinstance(option_ref, DictConfig) and not option_ref.get("_open_", False):
                _check_keys(value, option_ref, str(key))
        else:
            _check_keys(value, reference[key], str(key))
