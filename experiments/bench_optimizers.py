"""Benchmark every optimiser config on the standard 3-D test functions and print a table.

    python experiments/bench_optimizers.py                       # 30 seeds, 2000 evaluations
    python experiments/bench_optimizers.py --seeds 10 --max-evals 500 \\
        --record tests/optimizers_recorded.json                  # the conformance thresholds

Each config is an optimiser preset (``optimizers.preset(NAME)``), as ``optimizer=NAME``
builds it. Every run starts at random (x0=None) with the analytic
gradient and the vectorised objective given. BLAS is limited to one thread so that times
measure the optimiser rather than thread contention on small matrices.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import platform
from pathlib import Path

import numpy as np

import optimizers
from optimizers.benchmark import (
    SUCCESS_TOLERANCE,
    RunSummary,
    benchmark_functions,
    centre_bias,
    run_seeds,
)


def run_config(name: str, seeds: list[int], max_evals: int, dim: int) -> dict[str, RunSummary]:
    """Summaries of one config on every test function."""
    optimizer = optimizers.preset(name)
    return {f.name: run_seeds(optimizer, f, seeds, max_evals) for f in benchmark_functions(dim)}


def markdown_table(results: dict[str, dict[str, RunSummary]]) -> str:
    """One row per config: median best value and success rate per function, time, centre bias."""
    functions = list(next(iter(results.values())))
    header = ["optimizer", *functions, "ms / run", "centre bias"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name, summaries in results.items():
        # 0.0 - error: the median best value, written without a "-0.00e+00".
        cells = [
            f"{0.0 - s.median_error:.2e} ({100 * s.success_rate:.0f}%)" for s in summaries.values()
        ]
        ms = 1000 * np.mean([s.seconds_per_run for s in summaries.values()])
        bias = centre_bias(summaries["sphere_shifted_rotated"], summaries["sphere"])
        lines.append("| " + " | ".join([name, *cells, f"{ms:.1f}", f"{bias:.2g}"]) + " |")
    return "\n".join(lines)


def recorded(results: dict[str, dict[str, RunSummary]], args: argparse.Namespace) -> dict:
    """The JSON the conformance suite compares against."""
    return {
        "command": "python experiments/bench_optimizers.py "
        f"--seeds {args.seeds} --max-evals {args.max_evals} --dim {args.dim} --record PATH",
        "seeds": list(range(args.seeds)),
        "max_evals": args.max_evals,
        "dim": args.dim,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "results": {
            name: {
                fname: {"median_error": s.median_error, "success_rate": s.success_rate}
                for fname, s in summaries.items()
            }
            for name, summaries in results.items()
        },
    }


def main() -> None:
    """Parse arguments, run every config, print the table, optionally record the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=30, help="seeds 0..N-1 per function")
    parser.add_argument("--max-evals", type=int, default=2000, help="budget of each run")
    parser.add_argument("--dim", type=int, default=3, help="dimension of the test functions")
    parser.add_argument("--configs", nargs="*", default=None, help="config names (default all)")
    parser.add_argument("--record", type=Path, help="write the results as JSON to this path")
    args = parser.parse_args()
    seeds = list(range(args.seeds))
    results = {}
    for name in args.configs or optimizers.preset_names():
        results[name] = run_config(name, seeds, args.max_evals, args.dim)
        print(f"done {name}", flush=True)
    print(
        f"\n{args.seeds} seeds, {args.max_evals} evaluations, {args.dim}-D; cell = median best "
        f"value (optimum 0) and success rate (error <= {SUCCESS_TOLERANCE:g})\n"
    )
    print(markdown_table(results))
    if args.record:
        args.record.write_text(json.dumps(recorded(results, args), indent=1) + "\n")
        print(f"\nrecorded {args.record}")


if __name__ == "__main__":
    main()
