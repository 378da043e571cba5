"""SSA-Gradient Ascent: SSA for the global search, gradient ascent (Eq. 25) to refine.

``refine='each_generation'`` gives the best remembered sparrow ``refine_steps`` ascent steps
after every SSA generation; ``refine='end'`` runs SSA on all but ``refine_fraction`` of the
budget and then ascends from the best point SSA found until converged or out of budget.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from optimizers.base import check_range, register
from optimizers.gradient_ascent import (
    AscentHyperparameters,
    ascend_until_converged,
    ascent_step,
)
from optimizers.problem import BudgetExhausted, Problem
from optimizers.ssa import SSA, Frame, SSAHyperparameters

__all__ = ["SSAGradientAscent", "SSAGradientAscentHyperparameters"]


@dataclass(frozen=True)
class SSAGradientAscentHyperparameters(AscentHyperparameters, SSAHyperparameters):
    """SSA's and gradient ascent's hyperparameters, plus when to refine.

    refine: 'each_generation' or 'end' (see the module docstring).
    refine_steps: ascent steps given to the best sparrow per generation ('each_generation').
    refine_fraction: share of the budget kept for the final ascent ('end'), in [0, 1).
    starving: SSA's, but 'uniform' by default: the ascent refines the best sparrow, so the
        flock keeps re-sampling the box (the paper's optimiser as measured in Table 1).
    """

    starving: Literal["spread", "uniform", "origin"] = "uniform"
    line_search: bool = True
    refine: Literal["each_generation", "end"] = "each_generation"
    refine_steps: int = 3
    refine_fraction: float = 0.2

    def __post_init__(self) -> None:
        SSAHyperparameters.__post_init__(self)
        AscentHyperparameters.__post_init__(self)
        check_range("refine_steps", self.refine_steps, 1)
        check_range("refine_fraction", self.refine_fraction, 0.0, 1.0, open_high=True)


class _BestSparrowRefiner:
    """Gives the best remembered sparrow a few ascent steps after each generation."""

    def __init__(self, problem: Problem, hp: SSAGradientAscentHyperparameters) -> None:
        self._problem, self._hp = problem, hp
        self._step = hp.mu
        self._converged_at: np.ndarray | None = None

    def __call__(
        self, u: np.ndarray, values: np.ndarray, frame: Frame
    ) -> tuple[np.ndarray, np.ndarray]:
        """Refine ``u[argmax(values)]`` in place, keeping the result only if it is better."""
        b = int(np.argmax(values))
        if self._converged_at is not None and np.array_equal(u[b], self._converged_at):
            return u, values
        z, value = frame.to_problem(u[b]), values[b]
        converged = False
        for _ in range(self._hp.refine_steps):
            z, value, self._step, converged = ascent_step(
                self._problem, z, value, self._step, self._hp
            )
            if converged:
                break
        if value > values[b]:
            u[b], values[b] = frame.to_frame(z), value
        self._converged_at = u[b].copy() if converged else None
        return u, values


@register("ssa_ga")
class SSAGradientAscent(SSA):
    """SSA-Gradient Ascent (the paper's optimiser); x0, when given, is the first sparrow."""

    Hyperparameters = SSAGradientAscentHyperparameters

    def _evaluations_per_generation(self, problem: Problem) -> int:
        """SSA's cost per generation plus the refinement's (a gradient and a value per step)."""
        base = super()._evaluations_per_generation(problem)
        if self.hp.refine == "end":
            return base
        gradient_cost = 1 if problem.has_grad else 2 * problem.dim
        return base + self.hp.refine_steps * (gradient_cost + 1)

    def _search(self, problem: Problem, x0: np.ndarray | None) -> str:
        """SSA with per-generation refinement, or SSA then a final ascent."""
        if self.hp.refine == "each_generation":
            self._evolve(problem, x0, refine=_BestSparrowRefiner(problem, self.hp))
        ssa_share = max(1, problem.max_evals - round(self.hp.refine_fraction * problem.max_evals))
        try:
            with problem.capped(ssa_share):
                self._evolve(problem, x0, refine=None)
        except BudgetExhausted:
            pass
        return ascend_until_converged(problem, problem.best_point(), problem.best_value, self.hp)
