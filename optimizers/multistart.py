"""Random multi-start L-BFGS-B: the strong simple baseline for every swarm method.

Each round draws ``candidates`` uniform points (one batch), starts SciPy's L-BFGS-B from the
best of them and runs it until it converges; rounds repeat until the budget is used. The
first round starts from ``x0`` when given. Gradients come from ``grad`` or from finite
differences, both counted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NoReturn

import numpy as np
from scipy.optimize import minimize

from optimizers.base import Optimizer, check_range, register
from optimizers.problem import Problem

__all__ = ["MultistartLBFGS", "MultistartLBFGSHyperparameters"]


@dataclass(frozen=True)
class MultistartLBFGSHyperparameters:
    """Hyperparameters of multi-start L-BFGS-B.

    candidates: uniform points drawn per round; L-BFGS-B starts from the best one.
    local_maxiter: most L-BFGS-B iterations of one local run.
    ftol, gtol: L-BFGS-B's relative-decrease and projected-gradient stopping tolerances.
    fd_step: finite-difference step, relative to the box width, when no grad is given.
    """

    candidates: int = 10
    local_maxiter: int = 200
    ftol: float = 2.220446049250313e-09
    gtol: float = 1e-05
    fd_step: float = 1e-06

    def __post_init__(self) -> None:
        check_range("candidates", self.candidates, 1)
        check_range("local_maxiter", self.local_maxiter, 1)
        check_range("ftol", self.ftol, 0.0)
        check_range("gtol", self.gtol, 0.0)
        check_range("fd_step", self.fd_step, 0.0, 0.5, open_low=True)


@register("multistart_lbfgs")
class MultistartLBFGS(Optimizer):
    """Multi-start L-BFGS-B; one iteration per L-BFGS-B iteration and per candidate batch."""

    Hyperparameters = MultistartLBFGSHyperparameters

    def _search(self, problem: Problem, x0: np.ndarray | None) -> NoReturn:
        """Local runs from x0, then from the best of fresh candidates, until out of budget."""
        hp = self.hp
        bounds = list(zip(problem.lower, problem.upper, strict=True))

        def negated(z: np.ndarray) -> tuple[float, np.ndarray]:
            value = problem.evaluate(z)
            return -value, -problem.gradient(z, value, hp.fd_step)

        start = x0
        while True:
            if start is None:
                candidates = problem.uniform(hp.candidates)
                start = candidates[np.argmax(problem.evaluate_many(candidates))]
                problem.end_iteration()
            minimize(
                negated,
                start,
                jac=True,
                method="L-BFGS-B",
                bounds=bounds,
                callback=lambda _x: problem.end_iteration(),
                options={"maxiter": hp.local_maxiter, "ftol": hp.ftol, "gtol": hp.gtol},
            )
            problem.end_iteration()
            start = None
