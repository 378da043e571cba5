"""End-to-end segmentation time from a recording on disk, as a user runs it.

    python experiments/bench_end_to_end.py [--events 15000 100000] [--repeats 3]
    python experiments/bench_end_to_end.py --optimizers ssa_ga pso gradient_ascent \\
        nlopt_bobyqa multistart_lbfgs --events 15000 100000 --repeats 1      # ~3 min
    python experiments/bench_end_to_end.py --optimizers ssa_ga multistart_lbfgs \\
        --events 1e6 --repeats 1                                             # large, ~3 min
    python experiments/bench_end_to_end.py --optimizers default default:+preset=fast

Simulates the interior scene with N events, writes it as a recording directory, then
times ``python -m spatialseg +scene=recording scene.path=DIR`` (2 clusters, default
optimiser or each of ``--optimizers``, each optionally followed by ``:`` and comma-separated
overrides, figures and MLflow tracking off) as a subprocess:
process start, imports, reading, EDPA, initialisation, clustering and writing the outputs.
Reports the median wall time, the run's own stage timings from result.json (medians over
the repeats), the evaluations spent, the accuracy, and the child process's peak RSS; the
clustering time of each optimiser is also given as a ratio to the first one's at the same
size, measured in the same run.

The interior scene yields only about 140,000 events in its 1 s at the default contrast
threshold; windows larger than ``--dense-above`` events are simulated with the sensor's
threshold, its spread and floor and the refractory period scaled by ``dense_above / N``
(1e6 events: threshold 0.02, a 0.47 s window), so the carts move about as far as in a
100,000-event window.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import positive_count, split_overrides, write_json

from spatialseg.config import group_options

#: The interior scene's sensor defaults (conf/scene/interior.yaml), scaled for dense windows.
SENSOR = {"threshold_mean": 0.2, "threshold_std": 0.03, "threshold_min": 0.05, "refractory": 1e-4}
DEFAULT = "default"


def sensor_overrides(events: int, dense_above: int) -> list[str]:
    """Scene overrides that make a window of ``events`` events as short in time as one of
    ``dense_above`` events (none when ``events <= dense_above``)."""
    if events <= dense_above:
        return []
    scale = dense_above / events
    return [f"scene.sensor.{key}={value * scale:.6g}" for key, value in SENSOR.items()]


def _simulate(out: Path, events: int, dense_above: int) -> float:
    """Simulate the interior scene into the recording ``out``; return the wall time (s)."""
    cmd = [
        sys.executable,
        "-m",
        "spatialseg.simulate",
        "+scene=interior",
        f"out={out}",
        f"window.events={events}",
        "preview=false",
        f"hydra.run.dir={out.parent / ('sim_' + out.name)}",
        *sensor_overrides(events, dense_above),
    ]
    start = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, cwd=out.parent)
    return time.perf_counter() - start


def _run_child(cmd: list[str], cwd: Path, log: Path, timeout: float) -> tuple[float, int]:
    """Run ``cmd`` (output to ``log``); return its wall time (s) and peak RSS (bytes, from
    ``wait4``: the child's own maximum resident set size). Killed after ``timeout`` s."""
    with open(log, "wb") as out:
        start = time.perf_counter()
        proc = subprocess.Popen(cmd, cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
        timer = threading.Timer(timeout, proc.kill)
        timer.start()
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        finally:
            timer.cancel()
        wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        tail = log.read_text(errors="replace").strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"{' '.join(cmd[2:5])} failed ({proc.returncode}): {tail[0]}")
    return wall, usage.ru_maxrss * (1 if sys.platform == "darwin" else 1024)


def _segment(rec: Path, run: Path, optimizer: str, timeout: float) -> tuple[float, int, dict]:
    """Segment the recording ``rec`` into ``run``: wall time, peak RSS, result.json."""
    cmd = [
        sys.executable,
        "-m",
        "spatialseg",
        "+scene=recording",
        f"scene.path={rec}",
        "n_clusters=2",
        "output.plots=false",
        "output.progress=false",
        "tracking=none",
        f"hydra.run.dir={run}",
    ]
    name, _, overrides = optimizer.partition(":")
    if name != DEFAULT:
        cmd.append(f"optimizer={name}")
    cmd.extend(split_overrides(overrides))
    run.parent.mkdir(parents=True, exist_ok=True)
    wall, peak = _run_child(cmd, run.parent, run.parent / f"{run.name}.log", timeout)
    return wall, peak, json.loads((run / "result.json").read_text())


def summarise_runs(
    n: int, optimizer: str, runs: list[tuple[float, int, dict]], sim_s: float
) -> dict[str, Any]:
    """One row: medians of the times over the repeats; counts and metrics of the last run."""
    results = [r for _, _, r in runs]
    window = results[-1]["windows"][0]
    stages = {
        key: float(np.median([r["windows"][0]["timings"][key] for r in results]))
        for key in ("prepare", "init", "cluster")
    }
    metrics = results[-1].get("metrics", {})
    return {
        "events": n,
        "optimizer": optimizer,
        "wall_s": [w for w, _, _ in runs],
        "total_s": float(np.median([r["timings"]["total"] for r in results])),
        "load_s": float(np.median([r["timings"]["load"] for r in results])),
        **{f"{key}_s": value for key, value in stages.items()},
        "evaluations": int(sum(window["history"]["n_evals"])),
        "iterations": int(window["iterations"]),
        "accuracy": metrics.get("accuracy"),
        "velocity_error_rel": metrics.get("velocity_error_rel"),
        "peak_rss_bytes": max(p for _, p, _ in runs),
        "simulate_s": sim_s,
        "grid_shape": window.get("grid_shape"),
        # kept for the earlier JSON layout
        "cluster_s": stages["cluster"],
    }


HEADER = (
    "| events | optimizer | wall, median (s) | load (s) | prepare (s) | init (s) | "
    "clustering (s) | clustering vs first | evaluations | iterations | accuracy | "
    "velocity error (rel.) | peak RSS (MB) |"
)


def format_row(row: dict[str, Any], first_cluster_s: float) -> str:
    """One Markdown table line."""
    acc = "-" if row["accuracy"] is None else f"{row['accuracy']:.4f}"
    vel = "-" if row["velocity_error_rel"] is None else f"{row['velocity_error_rel']:.2f}"
    return (
        f"| {row['events']:,} | {row['optimizer']} | {np.median(row['wall_s']):.2f} | "
        f"{row['load_s']:.2f} | {row['prepare_s']:.2f} | {row['init_s']:.2f} | "
        f"{row['cluster_s']:.2f} | {row['cluster_s'] / first_cluster_s:.2f} | "
        f"{row['evaluations']} | {row['iterations']} | {acc} | {vel} | "
        f"{row['peak_rss_bytes'] / 1e6:.0f} |"
    )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line; unknown optimisers and bad numbers end in one error line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=positive_count, nargs="+", default=[15000, 100000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--optimizers",
        nargs="+",
        default=[DEFAULT],
        metavar="NAME",
        help=f"conf/optimizer names ('{DEFAULT}': the config's), each optionally with "
        "':override,override'; the first is the ratio base",
    )
    parser.add_argument(
        "--dense-above",
        type=positive_count,
        default=100000,
        help="larger windows get a proportionally lower sensor threshold",
    )
    parser.add_argument("--timeout", type=float, default=1800.0, help="s per segmentation run")
    parser.add_argument("--out", type=Path, default=Path("outputs/bench_end_to_end.json"))
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    known = group_options("optimizer")
    names = [o.partition(":")[0] for o in args.optimizers]
    unknown = [o for o in names if o != DEFAULT and o not in known]
    if unknown:
        parser.error(f"unknown optimizer {unknown[0]!r}; choose from {', '.join(known)}")
    return args


def main(argv: list[str] | None = None) -> None:
    """Simulate each size once, segment it with every optimiser, print the table, write JSON."""
    args = parse_args(argv)
    rows = []
    print(HEADER)
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.events:
            rec = Path(tmp) / f"interior_{n}"
            sim_s = _simulate(rec, n, args.dense_above)
            first = None
            for k, optimizer in enumerate(args.optimizers):
                runs = [
                    _segment(rec, Path(tmp) / f"run_{n}_{k}" / str(i), optimizer, args.timeout)
                    for i in range(args.repeats)
                ]
                row = summarise_runs(n, optimizer, runs, sim_s)
                row["sensor_overrides"] = sensor_overrides(n, args.dense_above)
                first = first or row["cluster_s"]
                rows.append(row)
                print(format_row(row, first), flush=True)
            print(f"<!-- simulated {n:,} events in {sim_s:.1f} s -->", flush=True)
    write_json(args.out, rows)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
