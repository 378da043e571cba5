"""Standard test problems for maximisers and a runner that summarises one over many seeds.

Sphere, Rosenbrock and Rastrigin on the box [-5, 5]^d, negated so that the maximum is 0,
each plain and shifted and rotated: f(x) = -g(R (x - o) + z*), whose maximiser is o.
The plain sphere and Rastrigin have their optimum at the box centre, so comparing them
with their shifted versions probes an optimiser for a centre bias.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from optimizers.base import Optimizer

__all__ = [
    "BenchmarkFunction",
    "RunSummary",
    "benchmark_functions",
    "centre_bias",
    "make_function",
    "run_seeds",
]

#: Half-width of the search box [-BOX, BOX]^d.
BOX = 5.0
#: A run succeeds when its error (optimum minus best value) is at most this.
SUCCESS_TOLERANCE = 1e-6
#: Errors below this count as exact when forming the centre-bias ratio.
ERROR_FLOOR = 1e-12
#: Seed of the fixed shifts and rotations (not of any optimiser).
_TRANSFORM_SEED = 2022


def sphere(z: np.ndarray) -> np.ndarray:
    """Sum of squares over the last axis."""
    return np.sum(z * z, axis=-1)


def sphere_gradient(z: np.ndarray) -> np.ndarray:
    """Gradient of :func:`sphere`."""
    return 2.0 * z


def rosenbrock(z: np.ndarray) -> np.ndarray:
    """Rosenbrock's valley, minimum 0 at (1, ..., 1)."""
    head, tail = z[..., :-1], z[..., 1:]
    return np.sum(100.0 * (tail - head**2) ** 2 + (1.0 - head) ** 2, axis=-1)


def rosenbrock_gradient(z: np.ndarray) -> np.ndarray:
    """Gradient of :func:`rosenbrock`."""
    head, tail = z[..., :-1], z[..., 1:]
    inner = tail - head**2
    gradient = np.zeros_like(z)
    gradient[..., :-1] = -400.0 * head * inner - 2.0 * (1.0 - head)
    gradient[..., 1:] += 200.0 * inner
    return gradient


def rastrigin(z: np.ndarray) -> np.ndarray:
    """Rastrigin's egg box, minimum 0 at the origin, a local minimum near every integer point."""
    return 10.0 * z.shape[-1] + np.sum(z * z - 10.0 * np.cos(2.0 * np.pi * z), axis=-1)


def rastrigin_gradient(z: np.ndarray) -> np.ndarray:
    """Gradient of :func:`rastrigin`."""
    return 2.0 * z + 20.0 * np.pi * np.sin(2.0 * np.pi * z)


#: name -> (value, gradient, minimiser coordinate) of each base function.
_BASES: dict[str, tuple[Callable, Callable, float]] = {
    "sphere": (sphere, sphere_gradient, 0.0),
    "rosenbrock": (rosenbrock, rosenbrock_gradient, 1.0),
    "rastrigin": (rastrigin, rastrigin_gradient, 0.0),
}


@dataclass(frozen=True)
class BenchmarkFunction:
    """f(x) = -g(R (x - o) + z*) on [-BOX, BOX]^d, with maximum 0 at x = o.

    Shifted optima have every coordinate between 0.3 and 0.7 box half-widths off-centre.
    """

    name: str
    base: str
    optimum: np.ndarray
    rotation: np.ndarray

    @property
    def bounds(self) -> list[tuple[float, float]]:
        """The search box."""
        return [(-BOX, BOX)] * self.optimum.size

    def _inner(self, x: np.ndarray) -> np.ndarray:
        """The base function's argument for the point(s) x."""
        return (x - self.optimum) @ self.rotation.T + _BASES[self.base][2]

    def fun(self, x: np.ndarray) -> float:
        """The objective at one point."""
        return -float(_BASES[self.base][0](self._inner(np.asarray(x, dtype=float))))

    def batch_fun(self, points: np.ndarray) -> np.ndarray:
        """The objective at each row of ``points``."""
        return -_BASES[self.base][0](self._inner(np.asarray(points, dtype=float)))

    def grad(self, x: np.ndarray) -> np.ndarray:
        """The objective's gradient at one point."""
        return -(_BASES[self.base][1](self._inner(np.asarray(x, dtype=float))) @ self.rotation)


def make_function(base: str, dim: int = 3, transformed: bool = False) -> BenchmarkFunction:
    """The plain base function, or its shifted and rotated version (fixed o and R)."""
    if base not in _BASES:
        raise ValueError(f"unknown test function '{base}'; valid: {', '.join(_BASES)}")
    if not transformed:
        return BenchmarkFunction(base, base, np.full(dim, _BASES[base][2]), np.eye(dim))
    rng = np.random.default_rng([_TRANSFORM_SEED, dim])
    q, r = np.linalg.qr(rng.standard_normal((dim, dim)))
    rotation = q * np.sign(np.diag(r))
    optimum = rng.uniform(0.3 * BOX, 0.7 * BOX, dim) * rng.choice((-1.0, 1.0), dim)
    return BenchmarkFunction(f"{base}_shifted_rotated", base, optimum, rotation)


def benchmark_functions(dim: int = 3) -> list[BenchmarkFunction]:
    """The six standard problems: each base function plain, then shifted and rotated."""
    return [make_function(b, dim, t) for b in _BASES for t in (False, True)]


@dataclass(frozen=True)
class RunSummary:
    """An optimiser on one function over several seeds."""

    errors: tuple[float, ...]
    seconds: tuple[float, ...]

    @property
    def median_error(self) -> float:
        """Median of (optimum - best value) over the seeds."""
        return float(np.median(self.errors))

    @property
    def success_rate(self) -> float:
        """Fraction of seeds whose error is at most SUCCESS_TOLERANCE."""
        return float(np.mean(np.array(self.errors) <= SUCCESS_TOLERANCE))

    @property
    def seconds_per_run(self) -> float:
        """Mean wall time of one run."""
        return float(np.mean(self.seconds))


def run_seeds(
    optimizer: Optimizer, function: BenchmarkFunction, seeds: Sequence[int], max_evals: int
) -> RunSummary:
    """Run ``optimizer`` on ``function`` once per seed (random start, grad and batch_fun given)."""
    errors, seconds = [], []
    for seed in seeds:
        started = time.perf_counter()
        result = optimizer.maximize(
            function.fun,
            function.bounds,
            grad=function.grad,
            max_evals=max_evals,
            seed=seed,
            batch_fun=function.batch_fun,
        )
        seconds.append(time.perf_counter() - started)
        errors.append(-result.value)
    return RunSummary(tuple(errors), tuple(seconds))


def centre_bias(shifted: RunSummary, plain: RunSummary) -> float:
    """Median error with the optimum shifted over median error with it at the box centre."""
    return max(shifted.median_error, ERROR_FLOOR) / max(plain.median_error, ERROR_FLOOR)
