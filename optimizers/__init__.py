"""A small generic library of box-constrained maximisers behind one registry.

>>> import optimizers
>>> opt = optimizers.create("ssa_ga", population=20)
>>> res = opt.maximize(lambda x: -float(x @ x), [(-1, 1)] * 3, max_evals=300, seed=0)

Every optimiser shares one ``maximize`` (see :class:`Optimizer`): a hard evaluation budget,
points always inside the bounds, non-finite values treated as the worst, determinism from
``seed``. :func:`preset` names an optimiser with chosen hyperparameters (every registered
name, and variants such as ``"nlopt_bobyqa"``). ``docs/optimizers.md`` describes each
optimiser and its measured benchmark.
"""

from optimizers.base import Optimizer, available, create, register
from optimizers.gradient_ascent import GradientAscent
from optimizers.multistart import MultistartLBFGS
from optimizers.nlopt_backend import NLopt
from optimizers.presets import preset, preset_hyperparameters, preset_names
from optimizers.problem import finite_difference_gradient
from optimizers.pso import PSO
from optimizers.result import OptimizeResult
from optimizers.ssa import SSA
from optimizers.ssa_ga import SSAGradientAscent

__all__ = [
    "PSO",
    "SSA",
    "GradientAscent",
    "MultistartLBFGS",
    "NLopt",
    "OptimizeResult",
    "Optimizer",
    "SSAGradientAscent",
    "available",
    "create",
    "finite_difference_gradient",
    "preset",
    "preset_hyperparameters",
    "preset_names",
    "register",
]
