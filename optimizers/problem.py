"""The bounded, counted and budgeted view of an objective that every search runs on.

:class:`Problem` is the single place where ``fun``, ``grad`` and ``batch_fun`` are called.
It removes zero-width dimensions (searches only see the free ones), projects every point
into the box, counts evaluations against the hard budget (raising :class:`BudgetExhausted`
instead of evaluating past it), treats non-finite values as ``-inf`` and keeps the best
point and the per-iteration history that become the :class:`OptimizeResult`.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np

from optimizers.result import OptimizeResult

__all__ = [
    "BudgetExhausted",
    "Problem",
    "finite_difference_gradient",
    "parse_bounds",
    "parse_budget",
    "parse_x0",
]

Fun = Callable[[np.ndarray], Any]
BatchFun = Callable[[np.ndarray], Any]
Callback = Callable[[int, np.ndarray, float], None]


class BudgetExhausted(Exception):
    """Signals that the evaluation budget is used; ``Optimizer.maximize`` catches it."""


def parse_bounds(bounds: Sequence[Sequence[float]]) -> tuple[np.ndarray, np.ndarray]:
    """Validate ``bounds`` as finite (low, high) pairs and return the lower and upper arrays."""
    try:
        pairs = np.asarray(bounds, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"bounds must be a sequence of numeric (low, high) pairs, got {bounds!r}"
        ) from exc
    if pairs.size == 0:
        raise ValueError("bounds is empty; pass one (low, high) pair per dimension")
    if pairs.ndim != 2 or pairs.shape[1] != 2:
        raise ValueError(
            f"bounds must have shape (n_dims, 2), got {pairs.shape}; pass [(low, high), ...]"
        )
    lower, upper = pairs[:, 0].copy(), pairs[:, 1].copy()
    infinite = np.flatnonzero(~(np.isfinite(lower) & np.isfinite(upper)))
    if infinite.size:
        i = infinite[0]
        raise ValueError(
            f"bounds of dimension {i} are ({lower[i]}, {upper[i]}); every dimension needs "
            "finite bounds"
        )
    inverted = np.flatnonzero(lower > upper)
    if inverted.size:
        i = inverted[0]
        raise ValueError(
            f"bounds of dimension {i} are inverted (low {lower[i]} > high {upper[i]}); "
            "swap them so that low <= high"
        )
    return lower, upper


def parse_x0(x0: Any, lower: np.ndarray, upper: np.ndarray) -> np.ndarray | None:
    """Validate the optional start point: right length, finite and inside the bounds."""
    if x0 is None:
        return None
    point = np.asarray(x0, dtype=float).reshape(-1)
    if point.shape != lower.shape:
        raise ValueError(
            f"x0 has {point.size} values but bounds have {lower.size} dimensions; "
            "pass one value per dimension"
        )
    outside = np.flatnonzero(~((point >= lower) & (point <= upper)))
    if outside.size:
        i = outside[0]
        raise ValueError(
            f"x0[{i}] = {point[i]} lies outside its bounds [{lower[i]}, {upper[i]}]; "
            "clip x0 into the bounds or widen them"
        )
    return point


def parse_budget(max_evals: Any) -> int:
    """Validate ``max_evals`` as a positive integer."""
    if isinstance(max_evals, bool) or not isinstance(max_evals, numbers.Integral):
        raise ValueError(f"max_evals must be a positive integer, got {max_evals!r}")
    if max_evals < 1:
        raise ValueError(f"max_evals must be at least 1, got {max_evals}")
    return int(max_evals)


def _as_value(raw: Any) -> float:
    """Convert what ``fun`` returned into one float, rejecting arrays of several values."""
    if type(raw) is float:
        return raw
    value = np.asarray(raw, dtype=float)
    if value.size != 1:
        raise ValueError(f"fun must return one float, got an array of shape {value.shape}")
    return float(value.item())


def finite_difference_gradient(
    evaluate_many: Callable[[np.ndarray], np.ndarray],
    z: np.ndarray,
    value: float,
    lower: np.ndarray,
    upper: np.ndarray,
    rel_step: float,
) -> np.ndarray:
    """Gradient of a function at ``z`` by differences that never leave the box.

    The step of dimension j is ``rel_step * (upper[j] - lower[j])``; the difference is
    central where both neighbours fit in the box, one-sided otherwise, and taken only over
    finite neighbours (a component with no finite neighbour is 0). ``value`` is f(z).
    """
    h = rel_step * (upper - lower)
    plus_fits = z + h <= upper
    minus_fits = z - h >= lower
    eye = np.diag(h)
    stencil = np.vstack([(z + eye)[plus_fits], (z - eye)[minus_fits]])
    values = evaluate_many(stencil)
    f_plus = np.full(z.size, np.nan)
    f_minus = np.full(z.size, np.nan)
    n_plus = int(plus_fits.sum())
    f_plus[plus_fits] = values[:n_plus]
    f_minus[minus_fits] = values[n_plus:]
    f_plus[~np.isfinite(f_plus)] = np.nan
    f_minus[~np.isfinite(f_minus)] = np.nan
    centre = value if np.isfinite(value) else np.nan
    central = (f_plus - f_minus) / (2.0 * h)
    forward = (f_plus - centre) / h
    backward = (centre - f_minus) / h
    gradient = np.where(np.isnan(central), np.where(np.isnan(forward), backward, forward), central)
    return np.nan_to_num(gradient, nan=0.0)


class Problem:
    """The objective as a search sees it: free dimensions only, bounded, counted, recorded."""

    def __init__(
        self,
        fun: Fun,
        lower: np.ndarray,
        upper: np.ndarray,
        *,
        grad: Fun | None,
        batch_fun: BatchFun | None,
        callback: Callback | None,
        max_evals: int,
        rng: np.random.Generator,
    ) -> None:
        for name, value in (("fun", fun), ("grad", grad), ("batch_fun", batch_fun)):
            if value is not None and not callable(value):
                raise ValueError(f"{name} must be callable, got {type(value).__name__}")
        if callback is not None and not callable(callback):
            raise ValueError(f"callback must be callable, got {type(callback).__name__}")
        self._fun, self._grad, self._batch_fun, self._callback = fun, grad, batch_fun, callback
        self.free = upper > lower
        self._template = lower.copy()
        self.lower, self.upper = lower[self.free], upper[self.free]
        self.dim = int(self.free.sum())
        self.rng = rng
        self.max_evals = max_evals
        self._cap = max_evals
        self.n_fun_evals = 0
        self.n_grad_evals = 0
        self.best_x: np.ndarray | None = None
        self.best_value = -np.inf
        self.history: list[float] = []
        self._evals_at_last_iteration = 0

    @property
    def n_evals(self) -> int:
        """Evaluations charged so far: calls of ``fun`` (or rows of ``batch_fun``) plus ``grad``."""
        return self.n_fun_evals + self.n_grad_evals

    @property
    def remaining(self) -> int:
        """Evaluations still allowed under the current cap."""
        return max(0, self._cap - self.n_evals)

    @property
    def has_grad(self) -> bool:
        """Whether an analytic gradient was given (else gradients are finite differences)."""
        return self._grad is not None

    def uniform(self, n: int) -> np.ndarray:
        """``n`` points drawn uniformly in the box of free dimensions."""
        return self.rng.uniform(self.lower, self.upper, size=(n, self.dim))

    def initial_population(self, n: int, x0: np.ndarray | None) -> np.ndarray:
        """``n`` uniform points in the box, the first replaced by ``x0`` when given."""
        points = self.uniform(n)
        if x0 is not None:
            points[0] = x0
        return points

    def best_point(self) -> np.ndarray:
        """The best evaluated point, in free-dimension coordinates."""
        assert self.best_x is not None, "best_point() called before any evaluation"
        return self.best_x[self.free].copy()

    def _embed(self, z: np.ndarray) -> np.ndarray:
        """Full-dimensional point for free coordinates ``z``, projected into the box."""
        x = self._template.copy()
        x[self.free] = np.clip(z, self.lower, self.upper)
        return x

    def _charge(self, n: int) -> None:
        """Raise BudgetExhausted unless ``n`` more evaluations fit in the budget."""
        if self.remaining < n:
            raise BudgetExhausted

    def _record(self, x: np.ndarray, value: float) -> float:
        """Keep ``x`` if it is the best so far; return the value as searches see it."""
        seen = value if np.isfinite(value) else -np.inf
        if self.best_x is None or seen > self.best_value:
            self.best_x, self.best_value = x, seen
        return seen

    def evaluate(self, z: np.ndarray) -> float:
        """f at the free coordinates ``z`` (one evaluation); non-finite values become -inf."""
        self._charge(1)
        x = self._embed(z)
        self.n_fun_evals += 1
        return self._record(x, _as_value(self._fun(x.copy())))

    def evaluate_many(self, points: np.ndarray) -> np.ndarray:
        """f at each row of ``points`` in order, through ``batch_fun`` when given.

        When fewer evaluations remain than rows, the leading rows that fit are evaluated
        and recorded, then BudgetExhausted is raised, exactly as row-by-row calls would.
        """
        n_fit = min(len(points), self.remaining)
        if n_fit == 0 and len(points):
            raise BudgetExhausted
        if self._batch_fun is None:
            values = np.array([self.evaluate(z) for z in points[:n_fit]], dtype=float)
        else:
            values = self._evaluate_batch(points[:n_fit])
        if n_fit < len(points):
            raise BudgetExhausted
        return values

    def _evaluate_batch(self, points: np.ndarray) -> np.ndarray:
        """Evaluate rows through ``batch_fun`` (one call), recording each row."""
        xs = np.tile(self._template, (len(points), 1))
        xs[:, self.free] = np.clip(points, self.lower, self.upper)
        self.n_fun_evals += len(xs)
        raw = np.asarray(self._batch_fun(xs.copy()), dtype=float)
        if raw.shape != (len(xs),):
            raise ValueError(
                f"batch_fun must return shape ({len(xs)},) for {len(xs)} points, got {raw.shape}"
            )
        return np.array([self._record(x, float(v)) for x, v in zip(xs, raw, strict=True)])

    def gradient(self, z: np.ndarray, value: float, fd_step: float) -> np.ndarray:
        """Gradient at ``z`` (where f = ``value``): ``grad`` (one evaluation) or differences."""
        if self._grad is None:
            return finite_difference_gradient(
                self.evaluate_many, z, value, self.lower, self.upper, fd_step
            )
        self._charge(1)
        x = self._embed(z)
        self.n_grad_evals += 1
        g = np.asarray(self._grad(x.copy()), dtype=float).reshape(-1)
        if g.shape != x.shape:
            raise ValueError(f"grad must return {x.size} values, got shape {g.shape}")
        if not np.all(np.isfinite(g)):
            raise ValueError(
                f"grad returned non-finite values at x={x.tolist()}; fix grad or pass "
                "grad=None to use finite differences"
            )
        return g[self.free]

    def end_iteration(self) -> None:
        """Close an iteration: append the best-so-far value and call the callback.

        Does nothing when no evaluation was made since the last call, so every history
        entry covers at least one evaluation.
        """
        if self.n_evals == self._evals_at_last_iteration or self.best_x is None:
            return
        self._evals_at_last_iteration = self.n_evals
        self.history.append(self.best_value)
        if self._callback is not None:
            self._callback(len(self.history) - 1, self.best_x.copy(), self.best_value)

    @contextmanager
    def capped(self, n_evals: int) -> Iterator[None]:
        """Within the block, raise BudgetExhausted once ``n_evals`` evaluations are spent."""
        outer = self._cap
        self._cap = min(outer, n_evals)
        try:
            yield
        finally:
            self._cap = outer

    def describe_best(self, optimizer: str) -> str:
        """One line on the state of the search, attached to exceptions raised inside it."""
        if self.best_x is None or not np.isfinite(self.best_value):
            best = "no finite value yet"
        else:
            best = f"best so far {self.best_value!r} at x={self.best_x.tolist()}"
        return f"optimizer '{optimizer}' stopped after {self.n_evals} evaluations; {best}"

    def result(self, message: str) -> OptimizeResult:
        """The OptimizeResult of the search, closing a partly done iteration first."""
        self.end_iteration()
        if self.best_x is None or not np.isfinite(self.best_value):
            raise ValueError(
                f"every one of the {self.n_fun_evals} evaluations of fun returned a "
                "non-finite value (NaN or inf); check fun inside the bounds"
            )
        x = self.best_x.copy()
        history = np.array(self.history, dtype=float)
        x.flags.writeable = False
        history.flags.writeable = False
        return OptimizeResult(
            x=x,
            value=float(self.best_value),
            history=history,
            n_evals=self.n_evals,
            n_fun_evals=self.n_fun_evals,
            n_grad_evals=self.n_grad_evals,
            n_iterations=len(history),
            message=message,
        )
