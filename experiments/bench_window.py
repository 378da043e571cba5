"""In-process segmentation time of one window, as a program that segments window after window
sees it (no interpreter start, imports or JIT cache loading in the figure).

    python experiments/bench_window.py [--events 15000 100000] [--repeats 3]
        [--configs default +preset=fast] [--scene interior]

Simulates the scene once per size (seed 0), then for each config (``default``, or Hydra
overrides joined by commas, ``default`` among them standing for none) times
``pipeline.segment_loaded`` once cold (the first call in the process after the kernels
were loaded by a warm-up on another config) and ``--repeats`` times warm; prints the
median warm time, the cold time, iterations, evaluations and the accuracy, and writes
JSON. Run on a quiet machine: times are wall clock.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from _common import compose_config, positive_count, split_overrides, write_json
from hydra.errors import HydraException
from hydra.utils import instantiate

from spatialseg.metrics import segmentation_metrics
from spatialseg.pipeline import segment_loaded
from spatialseg.scenes import load_scene

DEFAULT = "default"


def config_overrides(config: str) -> list[str]:
    """The Hydra overrides of one ``--configs`` entry: its comma-joined parts, ``default``
    (the defaults, no override) left out."""
    return [part for part in split_overrides(config) if part != DEFAULT]


def time_config(scene: str, events: int, config: str, repeats: int) -> dict:
    """Cold and warm times of one config on one simulated window."""
    overrides = config_overrides(config)
    cfg = compose_config(f"+scene={scene}", f"window.events={events}", *overrides)
    rec = load_scene(cfg["scene"], seed=0, window_events=events)
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        out, seg = segment_loaded(rec, cfg, instantiate(cfg["optimizer"]), seed=0)
        times.append(time.perf_counter() - start)
    window = seg.windows[0].clustering
    return {
        "scene": scene,
        "events": events,
        "config": config,
        "cold_s": times[0],
        "warm_s": float(np.median(times[1:])),
        "iterations": window.iterations,
        "evaluations": int(sum(r.n_evals for r in window.history)),
        "accuracy": segmentation_metrics(seg.labels, out.ground_truth.labels)["accuracy"],
    }


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, checked: ``--repeats`` at least 1, and every config composed once
    with the scene, so a bad override is one line (exit status 2) before any timing."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=positive_count, nargs="+", default=[15000, 100000])
    parser.add_argument("--configs", nargs="+", default=[DEFAULT, "+preset=fast"])
    parser.add_argument("--scene", default="interior")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("outputs/bench_window.json"))
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    for config in args.configs:
        try:
            compose_config(f"+scene={args.scene}", *config_overrides(config))
        except HydraException as exc:
            parser.error(f"--configs {config}: {str(exc).splitlines()[0]}")
    return args


def main() -> None:
    """Warm the kernels, time every size and config, print the table, write JSON."""
    args = parse_args()
    time_config(args.scene, 2000, DEFAULT, 1)  # load the numba kernels
    rows = [
        time_config(args.scene, n, config, args.repeats)
        for n in args.events
        for config in args.configs
    ]
    write_json(args.out, rows)
    print("| events | config | warm (s) | cold (s) | iterations | evaluations | accuracy |")
    print("|---:|---|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['events']:,} | {r['config']} | {r['warm_s']:.2f} | {r['cold_s']:.2f} | "
            f"{r['iterations']} | {r['evaluations']} | {r['accuracy']:.4f} |"
        )


if __name__ == "__main__":
    main()
