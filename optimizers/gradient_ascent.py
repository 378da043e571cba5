"""Gradient ascent ``x <- x + mu * grad f(x)`` (the paper's baseline), optionally with backtracking.

The step routines are shared with SSA-GA, which uses them to refine sparrows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from optimizers.base import Optimizer, check_range, register
from optimizers.problem import Problem

__all__ = ["AscentHyperparameters", "GradientAscent", "ascend_until_converged", "ascent_step"]

#: Sufficient-increase constant of the backtracking (Armijo) test.
ARMIJO = 1e-4
#: Factor applied to the trial step after a rejected trial.
SHRINK = 0.5
#: Factor applied to the next trial step after an accepted one.
GROW = 2.0


@dataclass(frozen=True)
class AscentHyperparameters:
    """Hyperparameters of a gradient-ascent step.

    mu: the step size (fixed), or the first trial step with ``line_search``.
    line_search: backtrack (halve the step until f rises by the Armijo test) and grow the
        next trial step by 2 after a success.
    xtol: stop once a step moves no coordinate by more than xtol times its box width.
    fd_step: finite-difference step, relative to the box width, used when no grad is given.
    """

    mu: float = 0.01
    line_search: bool = False
    xtol: float = 1e-10
    fd_step: float = 1e-6

    def __post_init__(self) -> None:
        check_range("mu", self.mu, 0.0, open_low=True)
        check_range("xtol", self.xtol, 0.0)
        check_range("fd_step", self.fd_step, 0.0, 0.5, open_low=True)


def ascent_step(
    problem: Problem, z: np.ndarray, value: float, step: float, hp: AscentHyperparameters
) -> tuple[np.ndarray, float, float, bool]:
    """One projected ascent step from ``z`` (where f = ``value``) with trial step ``step``.

    Returns the new point, its value, the next trial step and whether the search has
    converged (no move larger than ``xtol``; the point is then unchanged).
    """
    g = problem.gradient(z, value, hp.fd_step)
    width = problem.upper - problem.lower
    while True:
        moved_to = np.clip(z + step * g, problem.lower, problem.upper)
        if np.max(np.abs(moved_to - z) / width) <= hp.xtol:
            return z, value, step, True
        moved_value = problem.evaluate(moved_to)
        if not hp.line_search:
            return moved_to, moved_value, step, False
        if moved_value >= value + ARMIJO * float(g @ (moved_to - z)):
            return moved_to, moved_value, step * GROW, False
        step *= SHRINK


def ascend_until_converged(
    problem: Problem, z: np.ndarray, value: float, hp: AscentHyperparameters
) -> str:
    """Take ascent steps from ``z`` (one iteration each) until converged or out of budget."""
    step = hp.mu
    converged = False
    while not converged:
        z, value, step, converged = ascent_step(problem, z, value, step, hp)
        problem.end_iteration()
    if hp.line_search:
        return "converged: no step along the gradient longer than xtol increases fun"
    return "converged: the step mu * grad moves less than xtol"


@register("gradient_ascent")
class GradientAscent(Optimizer):
    """Gradient ascent from ``x0`` (or a uniform random point when x0 is None)."""

    Hyperparameters = AscentHyperparameters

    def _search(self, problem: Problem, x0: np.ndarray | None) -> str:
        """Evaluate the start, then step until converged or out of budget."""
        z = problem.uniform(1)[0] if x0 is None else x0
        value = problem.evaluate(z)
        problem.end_iteration()
        return ascend_until_converged(problem, z, value, self.hp)
