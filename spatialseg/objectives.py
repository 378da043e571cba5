"""Contrast objectives of the volume of warped events (VWE), kept in a registry.

An objective maps a volume ``V`` (``grid.shape``) to a number to *maximise* and gives its
derivative ``G = dO/dV`` (a volume of the same shape); :mod:`spatialseg.volume` turns ``G``
into ``dO/dtheta`` with one gather pass. Each objective optionally smooths ``V`` with a
Gaussian of ``blur_sigma`` voxels first; the blur uses zero padding, so it is a symmetric
linear map ``K`` and the chain rule is ``dO/dV = K (dO/dB)`` with ``B = K V``.

Adding an objective is one class here (or in any module imported before use) plus its
``conf/objective/<name>.yaml``::

    @register_objective
    @dataclass(frozen=True)
    class MeanOfCubes(Objective):
        name: ClassVar[str] = "mean_of_cubes"

        def value(self, volume):
            return float(np.mean(volume.astype(np.float64) ** 3))

        def value_and_derivative(self, volume, out):
            np.multiply(volume, volume, out=out)
            out *= 3.0 / volume.size
            return self.value(volume)

An objective that depends on ``V`` only through ``|Omega|``, ``sum V`` and ``sum V^2``
subclasses :class:`MomentObjective` instead and implements :meth:`MomentObjective.from_moments`;
the evaluator then runs it inside its voting and gather kernels (no whole-volume pass).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numba import njit

from spatialseg.smoothing import gaussian_smooth

__all__ = [
    "MomentObjective",
    "Objective",
    "SumOfSquares",
    "Variance",
    "make_objective",
    "objective_names",
    "register_objective",
    "volume_moments",
]

_REGISTRY: dict[str, type[Objective]] = {}


@njit(cache=True)
def volume_moments(volume: np.ndarray) -> tuple[float, float]:
    """``(sum V, sum V^2)`` of a volume (any dtype or memory layout), accumulated in float64."""
    total = 0.0
    total_sq = 0.0
    for value in volume.flat:
        v = np.float64(value)
        total += v
        total_sq += v * v
    return total, total_sq


@dataclass(frozen=True, kw_only=True)
class Objective(ABC):
    """A contrast objective ``O(K V)`` to maximise; ``K`` is the optional Gaussian blur.

    Subclasses are dataclasses whose fields are their config keys (``blur_sigma`` is
    keyword-only, so a subclass may add fields without defaults).
    """

    name: ClassVar[str]
    blur_sigma: float = 0.0

    def __post_init__(self) -> None:
        try:
            sigma = float(self.blur_sigma)
        except (TypeError, ValueError):
            sigma = float("nan")
        if not np.isfinite(sigma) or sigma < 0:
            raise ValueError(
                f"objective.blur_sigma must be a finite number >= 0 (voxels), got {self.blur_sigma}"
            )
        object.__setattr__(self, "blur_sigma", sigma)

    @property
    def smooths(self) -> bool:
        """Whether the volume is blurred before the objective."""
        return self.blur_sigma > 0

    def smooth(self, volume: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Apply the symmetric blur ``K`` (zero padding; axes of one voxel are left alone)."""
        sigma = [self.blur_sigma if n > 1 else 0.0 for n in volume.shape]
        return gaussian_smooth(volume, sigma, out=out)

    @abstractmethod
    def value(self, volume: np.ndarray) -> float:
        """The objective of an (already smoothed) volume."""

    @abstractmethod
    def value_and_derivative(self, volume: np.ndarray, out: np.ndarray) -> float:
        """The objective of a volume; writes ``dO/dV`` into ``out`` (same shape)."""


@dataclass(frozen=True)
class MomentObjective(Objective):
    """An objective of ``|Omega|``, ``sum V``, ``sum V^2`` only: ``dO/dV = slope V + offset``."""

    @abstractmethod
    def from_moments(
        self, total: float, total_sq: float, n_voxels: int
    ) -> tuple[float, float, float]:
        """``(value, slope, offset)`` from the moments: ``dO/dV[v] = slope * V[v] + offset``."""

    def value(self, volume: np.ndarray) -> float:
        """The objective from the volume's moments."""
        return self.from_moments(*volume_moments(volume), volume.size)[0]

    def value_and_derivative(self, volume: np.ndarray, out: np.ndarray) -> float:
        """The objective; writes the affine derivative ``slope V + offset`` into ``out``."""
        value, slope, offset = self.from_moments(*volume_moments(volume), volume.size)
        np.multiply(volume, slope, out=out)
        out += offset
        return value


def register_objective(cls: type[Objective]) -> type[Objective]:
    """Class decorator: make ``cls`` selectable as ``objective=<cls.name>``."""
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name:
        raise TypeError(f"{cls.__name__} needs a class attribute name: ClassVar[str]")
    if name in _REGISTRY and _REGISTRY[name] is not cls:
        raise ValueError(f"objective '{name}' is already registered by {_REGISTRY[name]}")
    _REGISTRY[name] = cls
    return cls


def objective_names() -> list[str]:
    """The registered objective names, sorted."""
    return sorted(_REGISTRY)


def make_objective(name: str, **params: Any) -> Objective:
    """The objective ``name`` built from its config (``make_objective(**cfg.objective)``)."""
    if name not in _REGISTRY:
        raise ValueError(
            f"unknown objective '{name}'; choose one of: {', '.join(objective_names())}"
        )
    try:
        return _REGISTRY[name](**params)
    except TypeError as exc:
        raise ValueError(f"objective '{name}': bad parameters {sorted(params)}: {exc}") from None


@register_objective
@dataclass(frozen=True)
class Variance(MomentObjective):
    """The paper's contrast (Eq. 19 with its 1/|Omega|): ``mean((V - mean V)^2)``."""

    name: ClassVar[str] = "variance"

    def from_moments(
        self, total: float, total_sq: float, n_voxels: int
    ) -> tuple[float, float, float]:
        """``Var = E[V^2] - mu^2`` and ``dVar/dV = 2 (V - mu) / |Omega|``."""
        mean = total / n_voxels
        slope = 2.0 / n_voxels
        return total_sq / n_voxels - mean * mean, slope, -slope * mean


@register_objective
@dataclass(frozen=True)
class SumOfSquares(MomentObjective):
    """``mean(V^2)``: the variance without the mean, Gallego et al.'s sum of squares / |Omega|."""

    name: ClassVar[str] = "sum_of_squares"

    def from_moments(
        self, total: float, total_sq: float, n_voxels: int
    ) -> tuple[float, float, float]:
        """``mean(V^2)`` and its derivative ``2 V / |Omega|``."""
        return total_sq / n_voxels, 2.0 / n_voxels, 0.0
