"""Any NLopt algorithm by name, under this package's hard budget and error handling.

NLopt's ``maxeval`` is only a hint here: the evaluator refuses the evaluation past
``max_evals``, the objective then asks NLopt to stop and the run ends with the best point
of the evaluator (the same path carries exceptions raised by ``fun``). Local
algorithms (``LN_*``, ``LD_*``) restart from a uniform random point when they converge early
(``restart``), so the whole budget is used; global ones run once. NLopt's own exceptions
become ValueError (rejected problem) or RuntimeError (failure) with a readable message.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import nlopt
import numpy as np

from optimizers.base import Optimizer, check_range, register
from optimizers.problem import Problem

__all__ = ["NLopt", "NLoptHyperparameters", "algorithm_names"]

#: Algorithms that need a local optimiser (set from ``local_algorithm``).
_NEEDS_LOCAL = ("AUGLAG", "MLSL")
#: Algorithms whose points do not depend on the seed or on x0 (unless named ..._RAND...).
_DETERMINISTIC = ("GN_DIRECT", "GN_ORIG_DIRECT", "GN_AGS", "GD_STOGO")
#: NLopt result codes that end a run normally, with their meaning.
_STOP_REASONS = {
    nlopt.SUCCESS: "success",
    nlopt.STOPVAL_REACHED: "stopval reached",
    nlopt.FTOL_REACHED: "ftol_rel reached",
    nlopt.XTOL_REACHED: "xtol_rel reached",
    nlopt.MAXEVAL_REACHED: "NLopt's maxeval reached",
    nlopt.MAXTIME_REACHED: "maxtime reached",
}


def _nlopt_exceptions(*names: str) -> tuple[type[BaseException], ...]:
    """The NLopt exception classes of these names that the installed NLopt defines."""
    return tuple(getattr(nlopt, name) for name in names if hasattr(nlopt, name))


#: Exceptions NLopt raises for a run that stopped on rounding errors (a normal stop).
_ROUNDOFF = _nlopt_exceptions("RoundoffLimited", "roundoff_limited")
#: NLopt's generic failure (NLOPT_FAILURE); L-BFGS raises it when its line search gives up,
#: as it does at a kink of a non-smooth objective (stevengj/nlopt#40).
_FAILURE = _nlopt_exceptions("runtime_error")
#: Exceptions NLopt raises for arguments it rejects (older versions raise ValueError).
_INVALID = (ValueError, *_nlopt_exceptions("invalid_argument"))


def algorithm_names() -> list[str]:
    """Algorithm names NLopt's Python module defines (e.g. 'LN_BOBYQA').

    An algorithm left out of the NLopt build (e.g. LD_LBFGS_NOCEDAL) is rejected when run.
    """
    return sorted(
        name
        for name in dir(nlopt)
        if name.split("_")[0] in {"GN", "GD", "LN", "LD", "G", "AUGLAG"}
        and isinstance(getattr(nlopt, name), int)
        and getattr(nlopt, name) < nlopt.NUM_ALGORITHMS
    )


def _is_local(name: str) -> bool:
    """Whether the algorithm is a local one (LN_* or LD_*)."""
    return name.startswith(("LN_", "LD_"))


@dataclass(frozen=True)
class NLoptHyperparameters:
    """Hyperparameters of the NLopt wrapper.

    algorithm: NLopt algorithm name, e.g. LN_BOBYQA, GN_DIRECT_L, LD_MMA.
    local_algorithm: local optimiser for the algorithms that need one (MLSL, AUGLAG).
    population: population of the stochastic global algorithms (0 = NLopt's default).
    xtol_rel, ftol_rel: NLopt's relative stopping tolerances (0 disables one).
    restart: restart local algorithms from a random point when they stop early.
    fd_step: finite-difference step, relative to the box width, for LD_* without grad.
    """

    algorithm: str = "LN_BOBYQA"
    local_algorithm: str = "LN_BOBYQA"
    population: int = 0
    xtol_rel: float = 1e-8
    ftol_rel: float = 0.0
    restart: bool = True
    fd_step: float = 1e-6

    def __post_init__(self) -> None:
        names = algorithm_names()
        for field, value in (
            ("algorithm", self.algorithm),
            ("local_algorithm", self.local_algorithm),
        ):
            if value not in names:
                raise ValueError(
                    f"hyperparameter '{field}' is '{value}', not an NLopt algorithm; "
                    f"valid: {', '.join(names)}"
                )
        if not _is_local(self.local_algorithm):
            raise ValueError(
                f"hyperparameter 'local_algorithm' must be an LN_* or LD_* algorithm, "
                f"got '{self.local_algorithm}'"
            )
        check_range("population", self.population, 0)
        check_range("xtol_rel", self.xtol_rel, 0.0)
        check_range("ftol_rel", self.ftol_rel, 0.0)
        check_range("fd_step", self.fd_step, 0.0, 0.5, open_low=True)


@register("nlopt")
class NLopt(Optimizer):
    """An NLopt algorithm chosen by name (hyperparameter ``algorithm``)."""

    Hyperparameters = NLoptHyperparameters

    @property
    def uses_seed(self) -> bool:
        """DIRECT, AGS and StoGO (not their _RAND variants) ignore the seed and x0."""
        name = self.hp.algorithm
        return "RAND" in name or not name.startswith(_DETERMINISTIC)

    def _build(
        self, problem: Problem, objective: Callable[[np.ndarray, np.ndarray], float]
    ) -> nlopt.opt:
        """An nlopt.opt for the free dimensions with bounds, tolerances and local optimiser."""
        hp = self.hp
        opt = nlopt.opt(getattr(nlopt, hp.algorithm), problem.dim)
        opt.set_lower_bounds(problem.lower)
        opt.set_upper_bounds(problem.upper)
        opt.set_max_objective(objective)
        opt.set_xtol_rel(hp.xtol_rel)
        opt.set_ftol_rel(hp.ftol_rel)
        if hp.population:
            opt.set_population(hp.population)
        if any(tag in hp.algorithm for tag in _NEEDS_LOCAL):
            local = nlopt.opt(getattr(nlopt, hp.local_algorithm), problem.dim)
            local.set_xtol_rel(hp.xtol_rel)
            local.set_ftol_rel(hp.ftol_rel)
            opt.set_local_optimizer(local)
        return opt

    def _search(self, problem: Problem, x0: np.ndarray | None) -> str:
        """Run NLopt (one iteration per objective call), restarting local algorithms.

        The objective never raises into NLopt (some algorithms keep calling it after an
        exception, which corrupts the interpreter state): it keeps the first exception,
        asks NLopt to stop and evaluates nothing more; the exception is re-raised after.
        Non-finite values reach NLopt as the lowest finite value seen so far.
        """
        hp = self.hp
        raised: list[BaseException] = []
        running: list[nlopt.opt] = []  # the opt that calls objective, for its force_stop
        lowest = np.inf
        gave_infinity = False

        def objective(z: np.ndarray, gradient_out: np.ndarray) -> float:
            nonlocal lowest, gave_infinity
            if raised:
                return lowest
            try:
                value = problem.evaluate(z)
                if gradient_out.size:
                    gradient_out[:] = problem.gradient(z, value, hp.fd_step)
                problem.end_iteration()
            except BaseException as exc:
                raised.append(exc)
                running[0].force_stop()
                return lowest
            if np.isfinite(value):
                lowest = min(lowest, value)
                return value
            gave_infinity = gave_infinity or not np.isfinite(lowest)
            return lowest

        opt = self._build(problem, objective)
        running.append(opt)
        try:
            start = problem.uniform(1)[0] if x0 is None else x0
            while True:
                nlopt.srand(int(problem.rng.integers(2**31)))
                opt.set_maxeval(problem.remaining)
                try:
                    opt.optimize(start)
                except Exception as exc:
                    if raised:
                        raise raised[0] from None
                    if isinstance(exc, _ROUNDOFF):
                        reason = "stopped by NLopt: roundoff limited"
                    elif gave_infinity:
                        reason = (
                            "stopped by NLopt: it failed after fun returned only non-finite values"
                        )
                    elif isinstance(exc, _FAILURE) and np.isfinite(lowest):
                        reason = (
                            "stopped by NLopt: generic failure (a gradient method's line "
                            "search gave up, e.g. on a non-smooth objective); the best point "
                            "so far is kept"
                        )
                    else:
                        raise _translate(exc, hp.algorithm) from exc
                else:
                    if raised:
                        raise raised[0]
                    reason = (
                        f"stopped by NLopt: {_STOP_REASONS.get(opt.last_optimize_result(), 'done')}"
                    )
                if not (hp.restart and _is_local(hp.algorithm)):
                    return reason
                start = problem.uniform(1)[0]
        finally:
            # NLopt holds ``objective``, whose closure reaches ``opt`` (``running``) and the
            # traceback of the exception that stopped it (``raised``): cycles through a C
            # object the garbage collector cannot see, which kept every problem (and the
            # arrays its function holds, a whole voxel grid each) alive. Emptying both
            # breaks them.
            raised.clear()
            running.clear()


def _translate(exc: BaseException, algorithm: str) -> Exception:
    """A clear ValueError or RuntimeError for an exception raised by NLopt itself."""
    if isinstance(exc, _INVALID):
        return ValueError(
            f"NLopt rejected {algorithm} for this problem (invalid argument: "
            f"{str(exc) or 'no detail'}); this NLopt build may lack it or it may not suit a "
            "bound-constrained problem: choose another algorithm"
        )
    if isinstance(exc, MemoryError):
        return MemoryError(f"NLopt ran out of memory running {algorithm}")
    return RuntimeError(f"NLopt failed running {algorithm} ({type(exc).__name__}: {exc})")
