"""Named presets: a registered optimiser with chosen hyperparameters, by one name.

Every registered optimiser is its own preset at its defaults (``"pso"``); the variants below
name other settings worth comparing (the paper's SSA, NLopt's algorithms one by one).
Applications name optimisers by preset (``preset("nlopt_bobyqa")``), so their config holds
a name, never a copy of the hyperparameters.

>>> import optimizers
>>> optimizers.preset("pso_constriction").hp.form
'constriction'
"""

from __future__ import annotations

from typing import Any

from optimizers.base import Optimizer, available, create

__all__ = ["preset", "preset_hyperparameters", "preset_names"]

#: Preset name -> (registered optimiser, the hyperparameters that differ from its defaults).
VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    # The paper's SSA as printed (raw coordinates, moves towards the origin; docs/optimizers.md).
    "ssa_paper": (
        "ssa",
        {
            "coordinates": "raw",
            "starving": "origin",
            "shrink_towards": "origin",
            "step_direction": "diagonal",
            "danger_step": "fitness_difference",
        },
    ),
    # Clerc's constriction form (needs c1 + c2 > 4).
    "pso_constriction": ("pso", {"form": "constriction", "c1": 2.05, "c2": 2.05}),
    "nlopt_bobyqa": ("nlopt", {"algorithm": "LN_BOBYQA"}),
    "nlopt_neldermead": ("nlopt", {"algorithm": "LN_NELDERMEAD"}),
    "nlopt_crs2_lm": ("nlopt", {"algorithm": "GN_CRS2_LM"}),
    "nlopt_direct_l": ("nlopt", {"algorithm": "GN_DIRECT_L"}),
    "nlopt_lbfgs": ("nlopt", {"algorithm": "LD_LBFGS"}),
    "nlopt_mma": ("nlopt", {"algorithm": "LD_MMA"}),
}


def preset_names() -> list[str]:
    """Sorted names of every preset: each registered optimiser and each variant."""
    return sorted({*available(), *VARIANTS})


def _resolve(name: str) -> tuple[str, dict[str, Any]]:
    """The registered optimiser and hyperparameters preset ``name`` stands for."""
    if name in VARIANTS:
        return VARIANTS[name]
    if name in available():
        return name, {}
    raise ValueError(f"unknown optimizer '{name}'; choose from {', '.join(preset_names())}")


def preset(name: str, **hyperparameters: Any) -> Optimizer:
    """The optimiser preset ``name`` stands for, with ``hyperparameters`` overriding it."""
    registered, chosen = _resolve(name)
    return create(registered, **{**chosen, **hyperparameters})


def preset_hyperparameters(name: str) -> dict[str, Any]:
    """Every hyperparameter of preset ``name`` (its optimiser's defaults, the preset's own
    values over them), in the optimiser's order: what a config file for it would list."""
    opt = preset(name)
    return {key: getattr(opt.hp, key) for key in type(opt).hyperparameter_names()}
