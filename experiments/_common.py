"""Helpers shared by the experiment scripts: compose the project's config, write results."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from spatialseg.config import conf_dir, group_options

__all__ = ["compose_config", "simulated_scenes", "write_json"]


def compose_config(*overrides: str) -> dict[str, Any]:
    """The composed run config (as the command line would build it) as a plain dict."""
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose("config", overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=True)


def simulated_scenes() -> list[str]:
    """Names of the shipped scenes that the simulator produces."""
    root = conf_dir() / "scene"
    return [
        s for s in group_options("scene") if "kind: simulated" in (root / f"{s}.yaml").read_text()
    ]


def write_json(path: Path, payload: Any) -> None:
    """Write the experiment's results as JSON (creating the directory)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2))
