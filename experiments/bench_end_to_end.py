"""End-to-end segmentation time from a recording on disk, as a user runs it.

    python experiments/bench_end_to_end.py [--events 15000 100000] [--repeats 3]

Simulates the interior scene with N events, writes it as a recording directory, then
times ``python -m spatialseg +scene=recording scene.path=DIR`` (2 clusters, default
optimiser, figures and MLflow tracking off) as a subprocess: process start, imports, reading, EDPA,
initialisation, clustering and writing the outputs. Reports the median wall time and
the run's own stage timings from result.json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import write_json


def _simulate(out: Path, events: int) -> None:
    cmd = [
        sys.executable,
        "-m",
        "spatialseg.simulate",
        "+scene=interior",
        f"out={out}",
        f"window.events={events}",
        "preview=false",
        f"hydra.run.dir={out.parent / 'sim'}",
    ]
    subprocess.run(cmd, check=True, capture_output=True, cwd=out.parent)


def _segment(rec: Path, run: Path) -> tuple[float, dict]:
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
    start = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, cwd=run.parent)
    wall = time.perf_counter() - start
    return wall, json.loads((run / "result.json").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, nargs="+", default=[15000, 100000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("outputs/bench_end_to_end.json"))
    args = parser.parse_args()
    rows = []
    print("| events | wall time, median (s) | in-process total (s) | clustering (s) | accuracy |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.events:
            rec = Path(tmp) / f"interior_{n}"
            _simulate(rec, n)
            runs = [_segment(rec, Path(tmp) / f"run_{n}_{i}") for i in range(args.repeats)]
            walls = [w for w, _ in runs]
            result = runs[-1][1]
            row = {
                "events": n,
                "wall_s": walls,
                "total_s": result["timings"]["total"],
                "cluster_s": result["windows"][0]["timings"]["cluster"],
                "accuracy": result["metrics"]["accuracy"],
            }
            rows.append(row)
            print(
                f"| {n} | {np.median(walls):.2f} | {row['total_s']:.2f} | "
                f"{row['cluster_s']:.2f} | {row['accuracy']:.4f} |"
            )
    write_json(args.out, rows)


if __name__ == "__main__":
    main()
