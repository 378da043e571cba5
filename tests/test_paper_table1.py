"""experiments/paper_table1.py on a tiny setting: structure, PSO as the 0 % reference."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))  # the experiments import _common as a sibling module
import paper_table1  # noqa: E402


def test_convergence_iteration_definition() -> None:
    """First 1-based iteration after which best-so-far stays within 0.1 % of the final."""
    assert paper_table1.convergence_iteration(np.array([1.0])) == 1
    assert paper_table1.convergence_iteration(np.array([1.0, 1.0, 1.0])) == 1
    assert paper_table1.convergence_iteration(np.array([0.5, 0.9995, 1.0])) == 2
    assert paper_table1.convergence_iteration(np.array([0.5, 0.99, 1.0])) == 3
    assert paper_table1.convergence_iteration(np.array([-2.0, -1.0005, -1.0])) == 2


@pytest.fixture(scope="module")
def result() -> dict:
    return paper_table1.run_experiment(["interior"], seeds=1, events=3000, max_evals=60)


def test_structure(result: dict) -> None:
    runs = result["runs"]
    for flow in range(paper_table1.N_FLOWS):
        names = [r["optimizer"] for r in runs if r["flow"] == flow]
        assert sorted(names) == sorted(paper_table1.OPTIMIZERS)
        starts = {tuple(r["x0"]) for r in runs if r["flow"] == flow}
        assert len(starts) == 1  # every optimiser from the same initial theta
    for r in runs:
        assert r["n_evals"] <= 60
        assert 1 <= r["convergence_iteration"] <= r["n_iterations"] == len(r["history"])
        assert r["convergence_evals"] <= r["n_evals"]
        assert r["history"][-1] == r["value"]
        if r["optimizer"] == paper_table1.REFERENCE:
            assert r["value_vs_pso_pct"] == 0.0
            assert r["iteration_vs_pso_pct"] == 0.0
    summary = result["summary"]
    assert len(summary) == paper_table1.N_FLOWS * len(paper_table1.OPTIMIZERS)
    pso = [s for s in summary if s["optimizer"] == paper_table1.REFERENCE]
    assert all(s["value_vs_pso_pct"]["median"] == 0.0 for s in pso)
    table = paper_table1.markdown(result)
    assert all(name in table for name in paper_table1.OPTIMIZERS)
