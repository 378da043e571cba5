"""Benchmark the VWE kernels against the numpy reference: events per second, speed-up.

    python experiments/bench_kernels.py                      # 1e4, 1e5, 1e6 events, one core
    python experiments/bench_kernels.py --sizes 1e4 1e7 --dtypes float32 --json out.json

For each size and storage dtype it times ``value`` (objective), ``value_and_grad``
(objective + gradient) and ``p_step`` (P-step: vote V, smooth it by
``--p-step-sigma`` voxels, interpolate it at every event; ``--p-step-stride`` 2 does so on a
grid twice as coarse in x and y, so its error column is that approximation's) of
:class:`spatialseg.volume.VolumeObjective`, and the same three quantities from
:mod:`spatialseg.reference` (smoothing by ``scipy.ndimage.gaussian_filter``) in the same run
(up to ``--reference-max`` events), on random events filling a ``--grid`` volume and warped
by a few voxels. Prints a table, writes JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numba
import numpy as np
from scipy.ndimage import gaussian_filter

from spatialseg import reference as ref
from spatialseg.grid import VoxelGrid
from spatialseg.volume import VolumeObjective

OPERATIONS = ("objective", "objective+gradient", "P-step")


def parse_args() -> argparse.Namespace:
    """The command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[1e4, 1e5, 1e6])
    parser.add_argument("--grid", type=int, nargs=3, default=[200, 150, 32], metavar="N")
    parser.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    parser.add_argument("--objective", default="variance")
    parser.add_argument("--repeats", type=int, default=7, help="timed calls per measurement")
    parser.add_argument("--threads", type=int, default=1, help="numba threads")
    parser.add_argument("--shift", type=float, default=3.0, help="largest warp, in voxels")
    parser.add_argument("--reference-max", type=float, default=1e6, help="largest reference N")
    parser.add_argument("--p-step-sigma", type=float, default=3.0, help="P-step smoothing, voxels")
    parser.add_argument("--p-step-stride", type=int, default=1, help="P-step grid coarsening")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=Path("outputs/bench_kernels.json"))
    return parser.parse_args()


def make_events(n: int, grid: VoxelGrid, shift: float, seed: int):
    """Random events over the grid, ``dt`` in [-1/2, 1/2] s, and a theta warping up to ``shift``
    voxels per axis (so some events leave the grid)."""
    rng = np.random.default_rng(seed)
    extent = (np.array(grid.shape) - 1) * grid.voxel_size
    points = grid.origin + rng.uniform(0.0, 1.0, (n, 3)) * extent
    dt = rng.uniform(-0.5, 0.5, n)
    theta = 2.0 * shift * grid.voxel_size * np.array([0.8, -0.6, 0.5])
    return points, dt, rng.uniform(0.2, 1.0, n), theta


def timed(fn: Callable[[], object], repeats: int) -> tuple[dict[str, float], object]:
    """Median CPU time, median and best wall time (ms) of ``repeats`` calls after a warm-up
    call, and its result. CPU time is the fair figure on a machine shared with other jobs."""
    result = fn()
    cpu, wall = [], []
    for _ in range(repeats):
        cpu_start, wall_start = time.process_time(), time.perf_counter()
        fn()
        wall.append(time.perf_counter() - wall_start)
        cpu.append(time.process_time() - cpu_start)
    times = {"cpu_ms": np.median(cpu), "wall_ms": np.median(wall), "best_wall_ms": np.min(wall)}
    return {key: 1e3 * float(value) for key, value in times.items()}, result


def bench_size(n: int, dtype: str, grid: VoxelGrid, args: argparse.Namespace) -> list[dict]:
    """All operations at one size and dtype: kernel and (if small enough) reference rows."""
    points, dt, weights, theta = make_events(n, grid, args.shift, args.seed)
    ev = VolumeObjective(points, dt, grid, args.objective, weights, np.dtype(dtype))
    kernels = {
        "objective": lambda: ev.value(theta),
        "objective+gradient": lambda: ev.value_and_grad(theta),
        "P-step": lambda: ev.p_step(theta, args.p_step_sigma, args.p_step_stride)[0],
    }
    # the reference on the same (rounded) inputs
    p, t, w = (a.astype(dtype).astype(np.float64) for a in (points, dt, weights))
    references = {
        "objective": lambda: ref.value(p, t, theta, grid, w, args.objective),
        "objective+gradient": lambda: ref.value_and_grad(p, t, theta, grid, w, args.objective),
        "P-step": lambda: ref.sample(p, t, theta, grid, smoothed(ref.volume(p, t, theta, grid, w))),
    }
    sigmas = [args.p_step_sigma if n > 1 else 0.0 for n in grid.shape]

    def smoothed(volume: np.ndarray) -> np.ndarray:
        return gaussian_filter(volume, sigmas, mode="reflect")

    rows = []
    for op in OPERATIONS:
        times, result = timed(kernels[op], args.repeats)
        row = {"events": n, "dtype": dtype, "operation": op, **times}
        row["events_per_s"] = n / (1e-3 * times["cpu_ms"])
        if n <= args.reference_max:
            ref_times, expected = timed(references[op], max(1, min(args.repeats, 3)))
            got, want = flatten(result), flatten(expected)
            row |= {
                "reference_cpu_ms": ref_times["cpu_ms"],
                "speedup": ref_times["cpu_ms"] / times["cpu_ms"],
                "max_rel_error": float(np.max(np.abs(got - want)) / np.max(np.abs(want))),
            }
        rows.append(row)
        print(format_row(row), flush=True)
    return rows


def flatten(result: object) -> np.ndarray:
    """A value, a (value, gradient) pair or an array as one float64 vector."""
    parts = result if isinstance(result, tuple) else (result,)
    return np.concatenate([np.ravel(np.asarray(part, dtype=np.float64)) for part in parts])


def format_row(row: dict) -> str:
    """One table line."""
    ref_part = (
        f"{row['reference_cpu_ms']:12.1f} {row['speedup']:8.1f}x {row['max_rel_error']:9.1e}"
        if "reference_cpu_ms" in row
        else f"{'-':>12} {'-':>9} {'-':>9}"
    )
    return (
        f"{row['events']:>10,d} {row['dtype']:>8} {row['operation']:>19} {row['cpu_ms']:9.2f} "
        f"{row['wall_ms']:9.2f} {row['best_wall_ms']:9.2f} {row['events_per_s'] / 1e6:10.1f} "
        f"{ref_part}"
    )


def main() -> None:
    """Run the grid of measurements, print the table and write the JSON."""
    args = parse_args()
    numba.set_num_threads(args.threads)
    grid = VoxelGrid(np.zeros(3), np.array([0.01, 0.01, 0.05]), tuple(args.grid))
    print(
        f"grid {grid.shape} = {grid.n_voxels:,} voxels, objective {args.objective}, "
        f"{args.threads} numba thread(s), median of {args.repeats} calls; Mevents/s and "
        "speed-up from CPU time"
    )
    print(
        f"{'events':>10} {'dtype':>8} {'operation':>19} {'cpu ms':>9} {'wall ms':>9} "
        f"{'best wall':>9} {'Mevents/s':>10} {'numpy cpu ms':>12} {'speed-up':>9} {'rel.err':>9}"
    )
    rows = [
        row
        for n in args.sizes
        for dtype in args.dtypes
        for row in bench_size(int(n), dtype, grid, args)
    ]
    args.json.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "grid": list(grid.shape),
        "objective": args.objective,
        "threads": args.threads,
        "repeats": args.repeats,
        "shift_voxels": args.shift,
        "seed": args.seed,
        "machine": platform.processor() or platform.machine(),
        "numba": numba.__version__,
        "numpy": np.__version__,
    }
    args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
