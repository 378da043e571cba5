"""The sparrow search algorithm (SSA) of Xue and Shen (2020), written for maximisation.

Each generation ranks the remembered positions (rank 1 is the best), then

* producers (the best ``PD`` fraction) shrink by ``exp(-i / (alpha T))`` when the alarm
  value R2 < ST, else take a normal step ``Q L`` (Eq. 3);
* scroungers of rank i > n/2 are starving and fly to ``Q exp((X_worst - X_i) / i^2)`` (or,
  by default, to ``X_P + Q s``, a normal step scaled by the flock's spread ``s`` around the
  best new producer X_P), the others forage around X_P with ``|X_i - X_P| A+ L`` (Eq. 4);
* a random ``SD`` fraction is danger-aware: a sparrow that is not the best jumps to
  ``X_best + beta |X_i - X_best|``, the best one moves by
  ``K |X_i - X_worst| / (|f_i - f_w| + eps)`` (Eq. 5);

and every sparrow keeps the best position it has evaluated (the paper's "if the new location
is better than before, update it"). The known traps of the literal formulas are switches
(:class:`SSAHyperparameters`); ``docs/optimizers.md`` says which is default and why.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, NoReturn

import numpy as np

from optimizers.base import Optimizer, check_range, register
from optimizers.problem import Problem

__all__ = ["SSA", "SSAHyperparameters"]

#: The paper's epsilon, which keeps the danger-aware division finite.
EPS = 1e-50
#: Largest exponent passed to exp in the starving rule (exp(709) is the largest float).
EXP_MAX = 700.0

#: Refinement hook: (remembered positions U, their values F, frame) -> updated (U, F).
Refine = Callable[[np.ndarray, np.ndarray, "Frame"], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class SSAHyperparameters:
    """Hyperparameters of SSA; the last seven are the trap switches (first choice = default).

    population: number of sparrows n.
    PD: fraction of producers (at least one); SD: fraction of danger-aware sparrows.
    ST: safety threshold; producers shrink while the alarm value R2 ~ U(0, 1) is below it.
    coordinates: 'unit_box' runs the formulas in box coordinates mapped to [-1, 1]^d (origin
        = box centre, unit = half width), 'raw' in the problem's own units (the paper).
    starving: starving scroungers fly to X_P + Q s, a normal step around the best new
        producer scaled by the flock's mean distance s from it per coordinate ('spread'),
        to a 'uniform' random point of the box, or to Q exp((X_worst - X_i) / i^2), a point
        near the 'origin' (the paper; a centre bias).
    producer_decay: exp(-i/(alpha T)) with 'rank' i (the paper) or 'iteration' t.
    shrink_towards: the producer shrink contracts towards the current 'best' or the
        'origin' (the paper; a centre bias).
    step_direction: 'per_dimension' draws Q, A, beta and K per coordinate; 'diagonal' uses
        one scalar times the all-ones vector (the paper's Q L and A+ L).
    danger_step: 'normalized' moves the best danger-aware sparrow by K |X_i - X_worst|
        (scale invariant), 'fitness_difference' divides that by |f_i - f_w| + eps (paper).
    bounds_handling: 'clip' to the box (as reference code does) or 'reflect' off its walls.
    """

    population: int = 20
    PD: float = 0.2
    SD: float = 0.2
    ST: float = 0.8
    coordinates: Literal["unit_box", "raw"] = "unit_box"
    starving: Literal["spread", "uniform", "origin"] = "spread"
    producer_decay: Literal["rank", "iteration"] = "rank"
    shrink_towards: Literal["best", "origin"] = "best"
    step_direction: Literal["per_dimension", "diagonal"] = "per_dimension"
    danger_step: Literal["normalized", "fitness_difference"] = "normalized"
    bounds_handling: Literal["clip", "reflect"] = "clip"

    def __post_init__(self) -> None:
        check_range("population", self.population, 2)
        check_range("PD", self.PD, 0.0, 1.0, open_low=True)
        check_range("SD", self.SD, 0.0, 1.0)
        check_range("ST", self.ST, 0.0, 1.0)


@dataclass(frozen=True)
class Frame:
    """Affine map x = offset + scale * u between problem and SSA coordinates, and the box in u."""

    offset: np.ndarray
    scale: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def build(cls, problem: Problem, coordinates: str) -> Frame:
        """The identity ('raw') or the map of the box onto [-1, 1]^d ('unit_box')."""
        if coordinates == "raw":
            return cls(np.zeros(problem.dim), np.ones(problem.dim), problem.lower, problem.upper)
        half = (problem.upper - problem.lower) / 2.0
        ones = np.ones(problem.dim)
        return cls(problem.lower + half, half, -ones, ones)

    def to_problem(self, u: np.ndarray) -> np.ndarray:
        """Problem coordinates of SSA coordinates ``u``."""
        return self.offset + self.scale * u

    def to_frame(self, x: np.ndarray) -> np.ndarray:
        """SSA coordinates of problem coordinates ``x``."""
        return (x - self.offset) / self.scale

    def into_box(self, u: np.ndarray, mode: str) -> np.ndarray:
        """Bring points back into the box by clipping or by reflecting off the walls."""
        if mode == "reflect":
            width = self.upper - self.lower
            folded = np.mod(u - self.lower, 2.0 * width)
            u = self.lower + np.where(folded > width, 2.0 * width - folded, folded)
        return np.clip(u, self.lower, self.upper)


def _coefficients(
    rng: np.random.Generator, n: int, d: int, per_dimension: bool, kind: str
) -> np.ndarray:
    """Random coefficients, shape (n, d) per dimension or (n, 1) as one scalar per sparrow."""
    shape = (n, d if per_dimension else 1)
    if kind == "normal":
        return rng.standard_normal(shape)
    return rng.uniform(-1.0, 1.0, shape)


def _producers(
    rng: np.random.Generator,
    u: np.ndarray,
    ranks: np.ndarray,
    t: int,
    horizon: int,
    best: np.ndarray,
    hp: SSAHyperparameters,
) -> np.ndarray:
    """Eq. 3: shrink while the alarm value is below ST, else a normal step."""
    per_dimension = hp.step_direction == "per_dimension"
    if rng.random() >= hp.ST:
        return u + _coefficients(rng, len(u), u.shape[1], per_dimension, "normal")
    alpha = 1.0 - rng.random((len(u), 1))
    index = ranks[:, None] if hp.producer_decay == "rank" else t
    factor = np.exp(-index / (alpha * horizon))
    anchor = best if hp.shrink_towards == "best" else 0.0
    return anchor + (u - anchor) * factor


def _scroungers(
    rng: np.random.Generator,
    u: np.ndarray,
    ranks: np.ndarray,
    n: int,
    producer_best: np.ndarray,
    worst: np.ndarray,
    frame: Frame,
    hp: SSAHyperparameters,
) -> np.ndarray:
    """Eq. 4: starving sparrows (rank > n/2) fly off, the others forage around X_P."""
    per_dimension = hp.step_direction == "per_dimension"
    d = u.shape[1]
    starving = ranks > n / 2.0
    moved = np.empty_like(u)
    hungry = u[starving]
    if hp.starving == "spread":
        spread = np.abs(u - producer_best).mean(axis=0)
        moved[starving] = producer_best + rng.standard_normal(hungry.shape) * spread
    elif hp.starving == "uniform":
        moved[starving] = rng.uniform(frame.lower, frame.upper, size=hungry.shape)
    else:
        q = _coefficients(rng, len(hungry), d, per_dimension, "normal")
        exponent = (worst - hungry) / (ranks[starving][:, None] ** 2)
        moved[starving] = q * np.exp(np.minimum(exponent, EXP_MAX))
    fed = u[~starving]
    signs = rng.choice((-1.0, 1.0), size=fed.shape)
    terms = signs * np.abs(fed - producer_best) / d
    moved[~starving] = producer_best + (terms if per_dimension else terms.sum(1, keepdims=True))
    return moved


def _danger_aware(
    rng: np.random.Generator,
    u: np.ndarray,
    values: np.ndarray,
    best: np.ndarray,
    best_value: float,
    worst: np.ndarray,
    worst_value: float,
    hp: SSAHyperparameters,
) -> np.ndarray:
    """Eq. 5: sparrows off the best jump near it; the best one moves away from the worst."""
    per_dimension = hp.step_direction == "per_dimension"
    n, d = u.shape
    beta = _coefficients(rng, n, d, per_dimension, "normal")
    k = _coefficients(rng, n, d, per_dimension, "uniform")
    scale: np.ndarray | float = 1.0
    if hp.danger_step == "fitness_difference":
        with np.errstate(invalid="ignore"):
            gap = np.abs(values - worst_value) + EPS
        scale = np.nan_to_num(1.0 / gap, nan=0.0)[:, None]
    away = u + k * np.abs(u - worst) * scale
    toward = best + beta * np.abs(u - best)
    return np.where((values >= best_value)[:, None], away, toward)


def _keep_better(
    u: np.ndarray, values: np.ndarray, rows: np.ndarray, moved: np.ndarray, moved_values: np.ndarray
) -> None:
    """Replace the remembered positions ``u[rows]`` whose new position is strictly better."""
    better = moved_values > values[rows]
    u[rows[better]] = moved[better]
    values[rows[better]] = moved_values[better]


@register("ssa")
class SSA(Optimizer):
    """Sparrow search algorithm; x0, when given, is the first sparrow."""

    Hyperparameters = SSAHyperparameters

    def _sizes(self) -> tuple[int, int]:
        """Numbers of producers and of danger-aware sparrows."""
        n = self.hp.population
        return min(n, max(1, round(self.hp.PD * n))), round(self.hp.SD * n)

    def _evaluations_per_generation(self, problem: Problem) -> int:
        """Evaluations one generation costs, used to estimate the horizon T."""
        return self.hp.population + self._sizes()[1]

    def _search(self, problem: Problem, x0: np.ndarray | None) -> str:
        """Run generations until the budget is used (never returns)."""
        self._evolve(problem, x0, refine=None)

    def _evolve(self, problem: Problem, x0: np.ndarray | None, refine: Refine | None) -> NoReturn:
        """Evaluate the initial flock, then run generations (each an iteration) forever."""
        hp = self.hp
        frame = Frame.build(problem, hp.coordinates)
        flock = problem.initial_population(hp.population, x0)
        values = problem.evaluate_many(flock)
        u = frame.to_frame(flock)
        problem.end_iteration()
        horizon = max(1, problem.remaining // self._evaluations_per_generation(problem))
        for t in itertools.count(1):
            order = np.argsort(-values, kind="stable")
            u, values = self._generation(problem, frame, u[order], values[order], t, horizon)
            if refine is not None:
                u, values = refine(u, values, frame)
            problem.end_iteration()

    def _generation(
        self,
        problem: Problem,
        frame: Frame,
        u: np.ndarray,
        values: np.ndarray,
        t: int,
        horizon: int,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One generation on the ranked flock ``u`` (best first); returns the updated memory."""
        hp, rng = self.hp, problem.rng
        n = len(u)
        n_producers, n_danger = self._sizes()
        ranks = np.arange(1, n + 1)

        def evaluate(moved: np.ndarray) -> np.ndarray:
            return problem.evaluate_many(frame.to_problem(moved))

        producers = frame.into_box(
            _producers(rng, u[:n_producers], ranks[:n_producers], t, horizon, u[0], hp),
            hp.bounds_handling,
        )
        producer_values = evaluate(producers)
        producer_best = producers[np.argmax(producer_values)]
        scroungers = frame.into_box(
            _scroungers(
                rng, u[n_producers:], ranks[n_producers:], n, producer_best, u[-1], frame, hp
            ),
            hp.bounds_handling,
        )
        scrounger_values = evaluate(scroungers)
        u, values = u.copy(), values.copy()
        _keep_better(
            u,
            values,
            ranks - 1,
            np.vstack([producers, scroungers]),
            np.concatenate([producer_values, scrounger_values]),
        )
        alert = rng.choice(n, size=n_danger, replace=False)
        b, w = int(np.argmax(values)), int(np.argmin(values))
        danger = frame.into_box(
            _danger_aware(rng, u[alert], values[alert], u[b], values[b], u[w], values[w], hp),
            hp.bounds_handling,
        )
        _keep_better(u, values, alert, danger, evaluate(danger))
        return u, values
