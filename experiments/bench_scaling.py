"""How the volume objective scales with the number of events: time per call and peak memory.

    python experiments/bench_scaling.py                          # 1e4 .. 1e7 events, ~4 min
    python experiments/bench_scaling.py --sizes 1e4 1e5 --no-memory --plot none   # quick look

Events are synthetic but shaped like the pipeline's input for a 346 x 260 sensor (the
interior scene's camera): two carts' worth of events on boxes 0.93 m away plus events on the
table at 1 m and uniform noise, over a 0.13 s window; the grids are built exactly as
``points.prepare`` builds them (``edpa.voxel_size`` + ``grid_around``, xy_scale 2, 16
depth bins, margin 0.1), once metric (``volume.coordinates=metric``) and once over pixels and
inverse depth (``image``, the default). For each size N, grid and dtype it measures

* time: ``value_and_grad`` per call and ``batch_value`` per candidate (a batch of
  ``--batch`` candidates, ``--threads`` numba threads), median CPU and wall time, against
  the numpy reference (:mod:`spatialseg.reference`, float64) in the same run up to
  ``--reference-max`` events, with the largest relative difference;
* memory (in a fresh subprocess per point): the peak RSS increase (Linux ``VmHWM`` reset
  through ``/proc/self/clear_refs``, else ``ru_maxrss``) and the peak of numpy's traced
  allocations (``tracemalloc``) while building a VolumeObjective over N events and
  evaluating ``value_and_grad`` and ``batch_value``; the caller's inputs are not counted.

Prints tables, writes the numbers to ``--json`` and a log-log figure to ``--plot``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import platform
import resource
import subprocess
import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
import numpy as np
from _common import positive_count

from spatialseg import reference as ref
from spatialseg.edpa import voxel_size
from spatialseg.grid import VoxelGrid, grid_around
from spatialseg.recording import Camera
from spatialseg.volume import VolumeObjective

#: The interior scene's DAVIS346 camera (conf/scene/interior.yaml).
CAMERA = {"width": 346, "height": 260, "fx": 300.0, "fy": 300.0, "cx": 172.5, "cy": 129.5}
#: A cart-like velocity (m/s) with a small depth component, so every axis is exercised.
THETA = np.array([0.26, -0.16, 0.05])
WINDOW_S = 0.13
GRIDS = ("metric", "image")
DTYPES = ("float64", "float32")
LIMIT_BYTES = 1 << 30  # the budget: 1e7 events in < 1 GB


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line; bad values end in one argparse error line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--sizes", type=positive_count, nargs="+", default=[10**4, 10**5, 10**6, 10**7]
    )
    parser.add_argument("--max-events", type=positive_count, default=10**7, help="skip larger N")
    parser.add_argument("--reference-max", type=float, default=1e6, help="largest N for numpy")
    parser.add_argument("--grids", nargs="+", choices=GRIDS, default=list(GRIDS))
    parser.add_argument("--dtypes", nargs="+", choices=DTYPES, default=list(DTYPES))
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per measurement")
    parser.add_argument("--budget", type=float, default=3.0, help="s per measurement, >= 2 calls")
    parser.add_argument("--batch", type=int, default=20, help="candidates per batch_value call")
    parser.add_argument("--threads", type=int, default=1, help="numba threads")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-memory", action="store_true", help="skip the memory subprocesses")
    parser.add_argument("--json", type=Path, default=Path("outputs/bench_scaling.json"))
    parser.add_argument("--plot", default="docs/images/scaling.png", help="PNG path or 'none'")
    parser.add_argument("--child", nargs=3, metavar=("N", "GRID", "DTYPE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    for name in ("repeats", "batch", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.budget <= 0:
        parser.error(f"--budget must be > 0, got {args.budget}")
    if args.threads > numba.config.NUMBA_NUM_THREADS:
        parser.error(f"--threads {args.threads} exceeds numba's {numba.config.NUMBA_NUM_THREADS}")
    args.sizes = sorted({n for n in args.sizes if n <= args.max_events})
    if not args.sizes and args.child is None:
        parser.error(f"no size is <= --max-events {args.max_events}")
    return args


def camera() -> Camera:
    """The benchmark's camera (the interior scene's)."""
    return Camera(**CAMERA)


def make_events(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` events shaped like a window of the interior scene: points (N x 3, metres), dt
    (s, around the window's middle) and memberships in [0.5, 1].

    45 % on each of two cart tops (boxes at 0.945-0.95 m, pixels inside a rectangle, a little
    depth spread) and 10 % anywhere on the sensor at the table's depth (1 m: table texture and
    noise, which EDPA gives the table's depth).
    """
    rng = np.random.default_rng(seed)
    cam = CAMERA
    kind = rng.choice(3, size=n, p=[0.45, 0.45, 0.10])
    boxes = np.array(  # u0, u1, v0, v1 (pixels), depth (m)
        [[60.0, 140.0, 40.0, 95.0, 0.945], [200.0, 255.0, 145.0, 180.0, 0.95]]
    )
    u = rng.uniform(0.0, cam["width"] - 1.0, n)
    v = rng.uniform(0.0, cam["height"] - 1.0, n)
    z = np.ones(n)
    for j, (u0, u1, v0, v1, depth) in enumerate(boxes):
        on = kind == j
        u[on] = rng.uniform(u0, u1, on.sum())
        v[on] = rng.uniform(v0, v1, on.sum())
        z[on] = depth + rng.normal(0.0, 0.002, on.sum())
    points = np.column_stack([(u - cam["cx"]) * z / cam["fx"], (v - cam["cy"]) * z / cam["fy"], z])
    dt = rng.uniform(-0.5 * WINDOW_S, 0.5 * WINDOW_S, n)
    return points, dt, rng.uniform(0.5, 1.0, n)


def build_grid(points: np.ndarray, kind: str) -> VoxelGrid:
    """The grid ``points.prepare`` builds for these points with the default config."""
    cam = camera()
    size = voxel_size(points, cam, xy_scale=2.0, z_bins=16, coordinates=kind)
    projection = cam.intrinsics if kind == "image" else None
    return grid_around(points, size, 0.1, 20_000_000, projection)


def candidates(count: int, seed: int) -> np.ndarray:
    """``count`` velocities around :data:`THETA`, as a swarm would propose them (count x 3)."""
    rng = np.random.default_rng(seed + 1)
    return THETA + rng.normal(0.0, 0.1, (count, 3)) * np.array([1.0, 1.0, 0.2])


def timed(fn: Callable[[], object], repeats: int, budget: float, warm: bool = True) -> dict:
    """Median CPU and wall ms of up to ``repeats`` calls (stopping after ``budget`` s, at
    least 2 calls), after one warm-up call when ``warm``; and the last result."""
    result = fn() if warm else None
    cpu, wall = [], []
    begin = time.perf_counter()
    while len(cpu) < repeats and (len(cpu) < 2 or time.perf_counter() - begin < budget):
        cpu_start, wall_start = time.process_time(), time.perf_counter()
        result = fn()
        wall.append(time.perf_counter() - wall_start)
        cpu.append(time.process_time() - cpu_start)
    return {
        "cpu_ms": 1e3 * float(np.median(cpu)),
        "wall_ms": 1e3 * float(np.median(wall)),
        "calls": len(cpu),
        "result": result,
    }


def _flat(result: object) -> np.ndarray:
    """A value, a (value, gradient) pair or an array as one float64 vector."""
    parts = result if isinstance(result, tuple) else (result,)
    return np.concatenate([np.ravel(np.asarray(p, dtype=np.float64)) for p in parts])


def _rel_error(got: object, want: object) -> float:
    """Largest absolute difference over the largest magnitude of ``want``."""
    a, b = _flat(got), _flat(want)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def time_point(n: int, kind: str, args: argparse.Namespace) -> list[dict[str, Any]]:
    """Timing rows at one size and grid: each dtype, plus the reference when N is small."""
    points, dt, weights = make_events(n, args.seed)
    grid = build_grid(points, kind)
    thetas = candidates(args.batch, args.seed)
    want: dict[str, Any] = {}
    base = {"events": n, "grid": kind, "grid_shape": list(grid.shape)}
    rows = []
    if n <= args.reference_max:
        vg = timed(
            lambda: ref.value_and_grad(points, dt, THETA, grid, weights), 2, args.budget, False
        )
        one = timed(lambda: ref.value(points, dt, thetas[0], grid, weights), 2, args.budget, False)
        want = {"vg": vg.pop("result"), "value": one.pop("result")}
        rows.append({**base, "dtype": "float64", "impl": "numpy", "vg": vg, "per_candidate": one})
    for dtype in args.dtypes:
        start = time.perf_counter()
        ev = VolumeObjective(points, dt, grid, "variance", weights, np.dtype(dtype))
        build_ms = 1e3 * (time.perf_counter() - start)
        vg = timed(lambda ev=ev: ev.value_and_grad(THETA), args.repeats, args.budget)
        batch = timed(lambda ev=ev: ev.batch_value(thetas), args.repeats, args.budget)
        per = {k: batch[k] / args.batch for k in ("cpu_ms", "wall_ms")} | {"calls": batch["calls"]}
        row = {**base, "dtype": dtype, "impl": "kernel", "build_ms": build_ms}
        row |= {"vg": vg, "per_candidate": per}
        if want:
            row["vg_rel_error"] = _rel_error(vg["result"], want["vg"])
            row["value_rel_error"] = _rel_error(batch["result"][0], want["value"])
        vg.pop("result")
        rows.append(row)
        del ev
    return rows


def _peak_bytes() -> int:
    """Peak resident set size of this process so far (bytes)."""
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    scale = 1 if sys.platform == "darwin" else 1024  # ru_maxrss: bytes on macOS, KiB on Linux
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def _reset_peak() -> bool:
    """Reset the peak RSS to the current RSS (Linux >= 4.0); False where unsupported."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def _current_bytes() -> int:
    """Current resident set size (bytes); the peak where the current value is unavailable."""
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return _peak_bytes()


def memory_child(n: int, kind: str, dtype: str, args: argparse.Namespace) -> dict[str, Any]:
    """In this (fresh) process: peak RSS increase and peak traced numpy memory for building a
    VolumeObjective over ``n`` events and evaluating it once each way."""
    warm_points, warm_dt, _ = make_events(1000, args.seed)  # load the cached kernels first
    warm = VolumeObjective(warm_points, warm_dt, build_grid(warm_points, kind), "variance")
    warm.value_and_grad(THETA), warm.batch_value(candidates(2, args.seed))
    del warm
    points, dt, weights = make_events(n, args.seed)
    grid = build_grid(points, kind)
    thetas = candidates(args.batch, args.seed)
    resettable = _reset_peak()
    before = _current_bytes() if resettable else _peak_bytes()
    tracemalloc.start()
    ev = VolumeObjective(points, dt, grid, "variance", weights, np.dtype(dtype))
    _, build_peak = tracemalloc.get_traced_memory()
    ev.value_and_grad(THETA)
    ev.batch_value(thetas)
    retained, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss = _peak_bytes() - before
    return {
        "events": n,
        "grid": kind,
        "dtype": dtype,
        "threads": args.threads,
        "rss_peak_increase": rss,
        "rss_method": "VmHWM after clear_refs" if resettable else "ru_maxrss",
        "traced_peak": peak,
        "traced_build_peak": build_peak,
        "traced_retained": retained,
        "grid_voxels": grid.n_voxels,
    }


def measure_memory(n: int, kind: str, dtype: str, args: argparse.Namespace) -> dict[str, Any]:
    """:func:`memory_child` in a fresh interpreter, so earlier sizes do not set the peak."""
    cmd = [sys.executable, __file__, "--child", str(n), kind, dtype]
    cmd += ["--seed", str(args.seed), "--batch", str(args.batch), "--threads", str(args.threads)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        tail = done.stderr.strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"memory run N={n} {kind} {dtype} failed: {tail[0]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def print_timing(rows: list[dict[str, Any]], batch: int) -> None:
    """The timing table (Markdown), with speed-ups against numpy of the same N and grid."""
    print(
        f"\n| events | grid | dtype | value+grad ms | ns/event | batch ms/candidate "
        f"(of {batch}) | ns/event | numpy v+g ms | speed-up v+g | speed-up batch | rel. diff |"
    )
    print("|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    refs = {(r["events"], r["grid"]): r for r in rows if r["impl"] == "numpy"}
    for r in (r for r in rows if r["impl"] == "kernel"):
        n, vg, per = r["events"], r["vg"]["cpu_ms"], r["per_candidate"]["cpu_ms"]
        ref_row = refs.get((n, r["grid"]))
        tail = "- | - | - | -"
        if ref_row:
            tail = (
                f"{ref_row['vg']['cpu_ms']:.0f} | {ref_row['vg']['cpu_ms'] / vg:.0f}x | "
                f"{ref_row['per_candidate']['cpu_ms'] / per:.0f}x | "
                f"{max(r['vg_rel_error'], r['value_rel_error']):.0e}"
            )
        print(
            f"| {n:,} | {r['grid']} | {r['dtype']} | {vg:.2f} | {1e6 * vg / n:.1f} | {per:.2f} | "
            f"{1e6 * per / n:.1f} | {tail} |"
        )


def image_over_metric(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per size and dtype, the image grid's time over the metric grid's, same run."""
    kernel = {(r["events"], r["dtype"], r["grid"]): r for r in rows if r["impl"] == "kernel"}
    ratios = []
    for (n, dtype, kind), r in sorted(kernel.items()):
        other = kernel.get((n, dtype, "metric"))
        if kind == "image" and other:
            ratios.append(
                {
                    "events": n,
                    "dtype": dtype,
                    "vg": r["vg"]["cpu_ms"] / other["vg"]["cpu_ms"],
                    "per_candidate": r["per_candidate"]["cpu_ms"]
                    / other["per_candidate"]["cpu_ms"],
                }
            )
    return ratios


def print_memory(rows: list[dict[str, Any]]) -> None:
    """The memory table (Markdown): peak increases and bytes per event."""
    print(
        "\n| events | grid | dtype | peak RSS increase (MB) | bytes/event (RSS) "
        "| numpy peak (MB) | numpy retained (MB) | bytes/event (retained) |"
    )
    print("|---:|---|---|---:|---:|---:|---:|---:|")
    for r in rows:
        n = r["events"]
        print(
            f"| {n:,} | {r['grid']} | {r['dtype']} | {r['rss_peak_increase'] / 1e6:.1f} | "
            f"{r['rss_peak_increase'] / n:.0f} | {r['traced_peak'] / 1e6:.1f} | "
            f"{r['traced_retained'] / 1e6:.1f} | {r['traced_retained'] / n:.0f} |"
        )


def plot(timing: list[dict[str, Any]], memory: list[dict[str, Any]], path: Path) -> None:
    """Log-log figure: time per call vs N (left) and peak memory vs N (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(12, 4.8))
    styles = {"metric": "tab:blue", "image": "tab:orange"}
    for kind in GRIDS:
        for dtype, mark in (("float64", "-o"), ("float32", "--s"), ("numpy", ":^")):
            impl = "numpy" if dtype == "numpy" else "kernel"
            want = "float64" if impl == "numpy" else dtype
            rows = [
                r for r in timing if r["grid"] == kind and r["impl"] == impl and r["dtype"] == want
            ]
            if not rows:
                continue
            n = [r["events"] for r in rows]
            ax_t.plot(
                n,
                [r["vg"]["cpu_ms"] for r in rows],
                mark,
                color=styles[kind],
                label=f"{kind} {dtype} value+grad",
            )
            if impl == "kernel":
                ax_t.plot(
                    n,
                    [r["per_candidate"]["cpu_ms"] for r in rows],
                    mark,
                    color=styles[kind],
                    alpha=0.4,
                    label=f"{kind} {dtype} batch / cand.",
                )
    _guide(ax_t, [r["events"] for r in timing], [r["vg"]["cpu_ms"] for r in timing], "ms")
    ax_t.set(
        xscale="log",
        yscale="log",
        xlabel="events N",
        ylabel="CPU ms per call",
        title="time per call (one candidate)",
    )
    ax_t.legend(fontsize=7)
    for kind in GRIDS:
        for dtype, mark in (("float64", "-o"), ("float32", "--s")):
            rows = [r for r in memory if r["grid"] == kind and r["dtype"] == dtype]
            if rows:
                ax_m.plot(
                    [r["events"] for r in rows],
                    [r["rss_peak_increase"] / 1e6 for r in rows],
                    mark,
                    color=styles[kind],
                    label=f"{kind} {dtype} peak RSS increase",
                )
    if memory:
        _guide(
            ax_m,
            [r["events"] for r in memory],
            [r["rss_peak_increase"] / 1e6 for r in memory],
            "MB",
        )
        ax_m.axhline(LIMIT_BYTES / 1e6, color="red", lw=0.8, label="1 GiB budget")
    ax_m.set(
        xscale="log",
        yscale="log",
        xlabel="events N",
        ylabel="MB",
        title="peak memory: build + evaluate",
    )
    ax_m.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _guide(ax: Any, n: list[int], y: list[float], unit: str) -> None:
    """A grey line of slope 1 (linear scaling) through the largest measured point."""
    if not n:
        return
    i = int(np.argmax(n))
    xs = np.array([min(n), max(n)], float)
    ax.plot(xs, y[i] * xs / n[i], color="grey", lw=0.8, label=f"linear in N ({unit} ~ N)")


def main(argv: list[str] | None = None) -> None:
    """Time every size and grid, measure memory in subprocesses, print, write JSON and PNG."""
    args = parse_args(argv)
    numba.set_num_threads(args.threads)
    if args.child:
        n, kind, dtype = args.child
        print(json.dumps(memory_child(int(n), kind, dtype, args)))
        return
    print(
        f"{numba.get_num_threads()} numba thread(s), CPU time, median of <= {args.repeats} calls "
        f"(<= {args.budget} s each); batch of {args.batch}; numpy reference up to "
        f"{args.reference_max:.0e} events"
    )
    timing = []
    for n in args.sizes:
        for kind in args.grids:
            rows = time_point(n, kind, args)
            timing += rows
            print(f"  timed N={n:,} {kind} grid {rows[0]['grid_shape']}", flush=True)
    print_timing(timing, args.batch)
    ratios = image_over_metric(timing)
    if ratios:
        print("\n| events | dtype | image / metric, value+grad | image / metric, batch |")
        print("|---:|---|---:|---:|")
        for r in ratios:
            print(f"| {r['events']:,} | {r['dtype']} | {r['vg']:.2f} | {r['per_candidate']:.2f} |")
    memory = []
    if not args.no_memory:
        for n in args.sizes:
            for kind in args.grids:
                for dtype in args.dtypes:
                    memory.append(measure_memory(n, kind, dtype, args))
                    print(f"  memory N={n:,} {kind} {dtype}", flush=True)
        print_memory(memory)
    meta = {
        "camera": CAMERA,
        "theta": THETA.tolist(),
        "window_s": WINDOW_S,
        "batch": args.batch,
        "threads": args.threads,
        "repeats": args.repeats,
        "seed": args.seed,
        "cpus": os.cpu_count(),
        "machine": platform.processor() or platform.machine(),
        "numba": numba.__version__,
        "numpy": np.__version__,
    }
    payload = {"meta": meta, "timing": timing, "image_over_metric": ratios, "memory": memory}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(payload, indent=2))
    print(f"\nwrote {args.json}")
    if args.plot != "none":
        plot(timing, memory, Path(args.plot))
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
