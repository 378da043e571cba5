"""Benchmark the event simulator: ``python experiments/bench_simulate.py``.

For every shipped simulated scene, times :func:`spatialseg.simulate.simulate_scene` (seed 0)
for the paper's 15,000-event window and for 100,000 events (median of ``--repeat`` runs,
after one warm-up run that also loads or compiles the numba kernel), reports events per
second and each object's share of the window, prints a table and writes the numbers as JSON.
The target is 100,000 events in under 10 s.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np
from _common import write_json
from omegaconf import OmegaConf

from spatialseg.config import conf_dir
from spatialseg.plots import label_shares
from spatialseg.recording import Recording
from spatialseg.simulate import simulate_scene

SCENES = ("interior", "exterior", "approach", "three", "night", "noon")
TARGET_S = 10.0


def timed(cfg: dict, events: int, repeat: int) -> tuple[float, Recording]:
    """Median wall time of ``repeat`` simulations of ``events`` events, and the last result."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        recording = simulate_scene(cfg, seed=0, max_events=events)
        times.append(time.perf_counter() - start)
    return statistics.median(times), recording


def run(window: int, total: int, repeat: int) -> dict[str, object]:
    """Benchmark every scene; return the results as a JSON-ready dict."""
    rows = {}
    for name in SCENES:
        cfg = OmegaConf.to_container(OmegaConf.load(conf_dir() / "scene" / f"{name}.yaml"))
        start = time.perf_counter()
        simulate_scene(cfg, seed=0, max_events=window)
        first = time.perf_counter() - start
        window_s, rec = timed(cfg, window, repeat)
        total_s, big = timed(cfg, total, repeat)
        rows[name] = {
            "first_call_s": first,
            "window_s": window_s,
            "window_ms": 1e3 * rec.events.duration,
            "window_shares": label_shares(rec),
            "total_events": len(big.events),
            "total_s": total_s,
            "events_per_s": len(big.events) / total_s,
        }
    return {
        "window_events": window,
        "total_events": total,
        "repeat": repeat,
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "cpus": os.cpu_count(),
        "numpy": np.__version__,
        "target_s": TARGET_S,
        "scenes": rows,
    }


def print_table(result: dict) -> None:
    """Print the timings as a plain-text table."""
    window, total = result["window_events"], result["total_events"]
    print(f"median of {result['repeat']} runs, seed 0, {result['cpus']} CPUs")
    print(
        f"{'scene':9} {'1st call s':>10} {f'{window:,} ev s':>11} {'window ms':>9} "
        f"{f'{total:,} ev s':>12} {'events/s':>10}  shares of the window"
    )
    for name, row in result["scenes"].items():
        share = ", ".join(f"{k} {100 * v:.0f}%" for k, v in row["window_shares"].items())
        print(
            f"{name:9} {row['first_call_s']:10.2f} {row['window_s']:11.2f} "
            f"{row['window_ms']:9.1f} {row['total_s']:12.2f} {row['events_per_s']:10,.0f}  {share}"
        )
    slowest = max(row["total_s"] for row in result["scenes"].values())
    verdict = "meets" if slowest < result["target_s"] else "MISSES"
    print(f"slowest {total:,}-event run: {slowest:.2f} s; {verdict} the < {TARGET_S:.0f} s target")


def main() -> None:
    """Parse arguments, run the benchmark, print the table and write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--window", type=int, default=15_000, help="events per window")
    parser.add_argument("--events", type=int, default=100_000, help="events of the long run")
    parser.add_argument("--repeat", type=int, default=3, help="runs per measurement")
    parser.add_argument(
        "--out", type=Path, default=Path("outputs/bench_simulate.json"), help="JSON results file"
    )
    args = parser.parse_args()
    result = run(args.window, args.events, args.repeat)
    print_table(result)
    write_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
