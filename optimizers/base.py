"""The optimiser base class, its hyperparameter checking and the name registry.

A subclass declares a frozen dataclass of hyperparameters (``Hyperparameters``) and
implements only ``_search``; ``maximize`` (validation, counting, budget, best-so-far,
non-finite values, the result) is written once, here.
"""

from __future__ import annotations

import abc
import dataclasses
import numbers
import typing
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, Literal

import numpy as np

from optimizers.problem import (
    BatchFun,
    BudgetExhausted,
    Callback,
    Fun,
    Problem,
    parse_bounds,
    parse_budget,
    parse_x0,
)
from optimizers.result import OptimizeResult

__all__ = ["Optimizer", "available", "check_range", "create", "register"]

_REGISTRY: dict[str, type[Optimizer]] = {}


def register(name: str) -> Callable[[type[Optimizer]], type[Optimizer]]:
    """Class decorator adding an Optimizer subclass to the registry under ``name``."""

    def decorate(cls: type[Optimizer]) -> type[Optimizer]:
        if name in _REGISTRY:
            raise ValueError(
                f"optimizer name '{name}' is already registered by {_REGISTRY[name].__name__}; "
                "choose another name"
            )
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return decorate


def available() -> list[str]:
    """Sorted names of the registered optimisers."""
    return sorted(_REGISTRY)


def create(name: str, **hyperparameters: Any) -> Optimizer:
    """Build the optimiser registered as ``name`` with the given hyperparameters."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown optimizer '{name}'; valid names: {', '.join(available())}")
    return _REGISTRY[name](**hyperparameters)


def check_range(
    name: str,
    value: float,
    low: float | None = None,
    high: float | None = None,
    *,
    open_low: bool = False,
    open_high: bool = False,
) -> None:
    """Raise ValueError unless ``low <= value <= high`` (strict on the open ends)."""
    too_low = low is not None and (value <= low if open_low else value < low)
    too_high = high is not None and (value >= high if open_high else value > high)
    if too_low or too_high:
        left = "(" if open_low else "["
        right = ")" if open_high else "]"
        low_text = "-inf" if low is None else f"{low:g}"
        high_text = "inf" if high is None else f"{high:g}"
        raise ValueError(
            f"hyperparameter '{name}' must be in {left}{low_text}, {high_text}{right}, got {value}"
        )


def _coerce(name: str, value: Any, hint: Any) -> Any:
    """Check ``value`` against the annotation ``hint`` (int, float, bool, str or Literal)."""
    if typing.get_origin(hint) is Literal:
        choices = typing.get_args(hint)
        if value not in choices:
            raise ValueError(
                f"hyperparameter '{name}' must be one of {', '.join(map(repr, choices))}, "
                f"got {value!r}"
            )
        return value
    if hint is bool:
        if not isinstance(value, bool | np.bool_):
            raise ValueError(f"hyperparameter '{name}' must be true or false, got {value!r}")
        return bool(value)
    numeric = {int: numbers.Integral, float: numbers.Real}.get(hint)
    if numeric is not None:
        if isinstance(value, bool | np.bool_) or not isinstance(value, numeric):
            raise ValueError(
                f"hyperparameter '{name}' must be a{'n int' if hint is int else ' number'}, "
                f"got {value!r}"
            )
        return hint(value)
    if not isinstance(value, hint):
        raise ValueError(f"hyperparameter '{name}' must be a {hint.__name__}, got {value!r}")
    return value


class Optimizer(abc.ABC):
    """Maximises a function over a box within a hard evaluation budget.

    Subclasses set ``Hyperparameters`` (a frozen dataclass whose ``__post_init__`` checks
    ranges) and implement :meth:`_search`; they are registered with :func:`register`.
    """

    name: ClassVar[str] = ""
    Hyperparameters: ClassVar[type]

    def __init__(self, **hyperparameters: Any) -> None:
        hints = typing.get_type_hints(self.Hyperparameters)
        unknown = sorted(set(hyperparameters) - set(hints))
        if unknown:
            raise ValueError(
                f"unknown hyperparameter {', '.join(map(repr, unknown))} for optimizer "
                f"'{self.name}'; valid: {', '.join(sorted(hints)) or 'none'}"
            )
        try:
            checked = {k: _coerce(k, v, hints[k]) for k, v in hyperparameters.items()}
            self.hp = self.Hyperparameters(**checked)
        except ValueError as exc:
            raise ValueError(f"optimizer '{self.name}': {exc}") from None

    @classmethod
    def hyperparameter_names(cls) -> list[str]:
        """Names of the accepted hyperparameters, in declaration order."""
        return [f.name for f in dataclasses.fields(cls.Hyperparameters)]

    @property
    def uses_seed(self) -> bool:
        """Whether the sequence of evaluated points depends on ``seed``."""
        return True

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.hp})"

    def maximize(
        self,
        fun: Fun,
        bounds: Sequence[Sequence[float]],
        x0: Sequence[float] | np.ndarray | None = None,
        grad: Fun | None = None,
        max_evals: int = 2000,
        seed: int | np.random.SeedSequence | None = 0,
        *,
        batch_fun: BatchFun | None = None,
        callback: Callback | None = None,
    ) -> OptimizeResult:
        """Maximise ``fun`` over ``bounds`` with at most ``max_evals`` evaluations.

        ``grad`` calls count one evaluation each; ``batch_fun(X)`` (rows of points, one
        value per row, equal to ``fun`` row by row) counts one per row. Non-finite values
        are the worst possible; an exception from ``fun`` propagates with a note giving the
        best point so far.
        """
        lower, upper = parse_bounds(bounds)
        start = parse_x0(x0, lower, upper)
        problem = Problem(
            fun,
            lower,
            upper,
            grad=grad,
            batch_fun=batch_fun,
            callback=callback,
            max_evals=parse_budget(max_evals),
            rng=np.random.default_rng(seed),
        )
        try:
            message = self._run(problem, start)
        except BudgetExhausted:
            message = f"stopped: the budget of {problem.max_evals} evaluations is used"
        except BaseException as exc:
            exc.add_note(problem.describe_best(self.name))
            raise
        return problem.result(message)

    def _run(self, problem: Problem, start: np.ndarray | None) -> str:
        """Search the free dimensions, or evaluate the one point when none is free."""
        if problem.dim == 0:
            problem.evaluate(np.empty(0))
            return "every dimension is fixed by its bounds: evaluated the only feasible point"
        return self._search(problem, None if start is None else start[problem.free])

    @abc.abstractmethod
    def _search(self, problem: Problem, x0: np.ndarray | None) -> str:
        """Run the search on ``problem`` (free dimensions) from optional ``x0``; return a message.

        May return early (e.g. converged) or run until ``problem`` raises BudgetExhausted.
        """
