"""Global-best particle swarm optimisation (inertia or constriction form, velocity clamping)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from optimizers.base import Optimizer, check_range, register
from optimizers.problem import Problem

__all__ = ["PSO", "PSOHyperparameters"]


@dataclass(frozen=True)
class PSOHyperparameters:
    """Hyperparameters of global-best PSO.

    swarm_size: number of particles.
    form: 'inertia' v <- w v + c1 r1 (p - x) + c2 r2 (g - x), or 'constriction'
        v <- chi (v + c1 r1 (p - x) + c2 r2 (g - x)) with Clerc's chi (needs c1 + c2 > 4).
    inertia: w of the inertia form (unused by the constriction form).
    c1, c2: cognitive and social acceleration coefficients.
    vmax_fraction: each velocity component is clamped to vmax_fraction times the box width.
    """

    swarm_size: int = 20
    form: Literal["inertia", "constriction"] = "inertia"
    inertia: float = 0.7298
    c1: float = 1.49618
    c2: float = 1.49618
    vmax_fraction: float = 0.2

    def __post_init__(self) -> None:
        check_range("swarm_size", self.swarm_size, 1)
        check_range("inertia", self.inertia, 0.0, 1.0)
        check_range("c1", self.c1, 0.0)
        check_range("c2", self.c2, 0.0)
        check_range("vmax_fraction", self.vmax_fraction, 0.0, open_low=True)
        if self.form == "constriction" and self.c1 + self.c2 <= 4.0:
            raise ValueError(
                f"the constriction form needs c1 + c2 > 4, got {self.c1 + self.c2}; "
                "use c1 = c2 = 2.05 or form='inertia'"
            )


def constriction_factor(phi: float) -> float:
    """Clerc and Kennedy's chi = 2 / |2 - phi - sqrt(phi^2 - 4 phi)| for phi = c1 + c2 > 4."""
    return 2.0 / abs(2.0 - phi - math.sqrt(phi * phi - 4.0 * phi))


@register("pso")
class PSO(Optimizer):
    """Global-best PSO; x0, when given, is the first particle; walls stop a particle."""

    Hyperparameters = PSOHyperparameters

    def _search(self, problem: Problem, x0: np.ndarray | None) -> str:
        """Move the swarm generation by generation until the budget is used."""
        hp, rng = self.hp, problem.rng
        n, d = hp.swarm_size, problem.dim
        vmax = hp.vmax_fraction * (problem.upper - problem.lower)
        position = problem.initial_population(n, x0)
        velocity = rng.uniform(-vmax, vmax, size=(n, d))
        values = problem.evaluate_many(position)
        problem.end_iteration()
        personal, personal_values = position.copy(), values.copy()
        chi = constriction_factor(hp.c1 + hp.c2) if hp.form == "constriction" else 1.0
        weight = 1.0 if hp.form == "constriction" else hp.inertia
        while True:
            leader = personal[np.argmax(personal_values)]
            r1, r2 = rng.random((n, d)), rng.random((n, d))
            pull = hp.c1 * r1 * (personal - position) + hp.c2 * r2 * (leader - position)
            velocity = np.clip(chi * (weight * velocity + pull), -vmax, vmax)
            moved = position + velocity
            position = np.clip(moved, problem.lower, problem.upper)
            velocity[moved != position] = 0.0
            values = problem.evaluate_many(position)
            better = values > personal_values
            personal[better], personal_values[better] = position[better], values[better]
            problem.end_iteration()
