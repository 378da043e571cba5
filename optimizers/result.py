"""The one result type every optimiser returns."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["OptimizeResult"]


@dataclass(frozen=True)
class OptimizeResult:
    """Outcome of one ``maximize`` call; ``x`` and ``history`` are read-only arrays.

    ``value == fun(x)`` exactly and is the best finite value of every evaluation made;
    ``history[k]`` is the best-so-far value after iteration ``k`` (non-decreasing, ending at
    ``value``); ``n_evals == n_fun_evals + n_grad_evals`` never exceeds ``max_evals``.
    """

    x: np.ndarray
    value: float
    history: np.ndarray
    n_evals: int
    n_fun_evals: int
    n_grad_evals: int
    n_iterations: int
    message: str
