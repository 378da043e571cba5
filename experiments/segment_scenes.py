"""Accuracy of the spatial and planar models on every shipped simulated scene.

    python experiments/segment_scenes.py [--seeds 3] [--events 15000] [--out FILE.json]
        [--models spatial planar spatial:volume.coordinates=metric]

For each scene, model and seed: simulate the window (seeded), segment it with the default
configuration, and report per-event accuracy, mean IoU, the relative velocity error of
matched clusters (spatial model, m/s; the mean over objects, and, where the camera moves,
the static scene's alone: its target is minus the camera's velocity), and wall time.
Prints a Markdown table of medians (min-max over seeds). A model may carry config
overrides after a colon, comma-separated
(``spatial:volume.coordinates=metric,clustering.max_iterations=20``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from _common import (
    compose_config,
    median_range,
    positive_count,
    simulated_scenes,
    split_overrides,
    write_json,
)
from hydra.utils import instantiate

from spatialseg.metrics import segmentation_metrics
from spatialseg.pipeline import segment_loaded
from spatialseg.scenes import load_scene
from spatialseg.simulate.render import STATIC_SCENE

N_CLUSTERS = {"three": 3}


def run_one(scene: str, variant: str, seed: int, events: int) -> dict:
    """Simulate and segment one scene with one model variant; return its metrics and time."""
    k = N_CLUSTERS.get(scene, 2)
    model, _, extra = variant.partition(":")
    overrides = split_overrides(extra)
    cfg = compose_config(
        f"+scene={scene}", f"model={model}", f"n_clusters={k}", f"seed={seed}", *overrides
    )
    rec = load_scene(cfg["scene"], seed=seed, window_events=events)
    start = time.perf_counter()
    rec, seg = segment_loaded(rec, cfg, instantiate(cfg["optimizer"]), seed=seed)
    seconds = time.perf_counter() - start
    w = seg.windows[0]
    thetas = np.zeros((k, 3))
    thetas[:, : w.clustering.thetas.shape[1]] = w.clustering.thetas
    gt = rec.ground_truth
    m = segmentation_metrics(
        seg.labels,
        gt.labels,
        pred_velocities=thetas if model == "spatial" else None,
        true_motions=gt.motions if model == "spatial" else None,
    )
    static = m.get("velocity_error", {}).get(str(STATIC_SCENE), {})
    return {
        "scene": scene,
        "model": variant,
        "seed": seed,
        "accuracy": m["accuracy"],
        "mean_iou": m["mean_iou"],
        "velocity_error_rel": m.get("velocity_error_rel"),
        "static_velocity_error_rel": static.get("rel"),
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--events", type=positive_count, default=15000)
    parser.add_argument("--models", nargs="+", default=["spatial", "planar"])
    parser.add_argument("--scenes", nargs="+", default=None)
    parser.add_argument("--out", type=Path, default=Path("outputs/segment_scenes.json"))
    args = parser.parse_args()
    if args.seeds < 1:
        parser.error(f"--seeds must be >= 1, got {args.seeds}")
    rows = [
        run_one(scene, model, seed, args.events)
        for scene in (args.scenes or simulated_scenes())
        for model in args.models
        for seed in range(args.seeds)
    ]
    write_json(args.out, {"events": args.events, "seeds": args.seeds, "runs": rows})
    print(
        "| scene | model | accuracy | mean IoU | velocity error (rel.) "
        "| static scene's velocity error (rel.) | time (s) |"
    )
    print("|---|---|---|---|---|---|---|")
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for model in args.models:
            sel = [r for r in rows if r["scene"] == scene and r["model"] == model]
            print(
                f"| {scene} | {model} | {median_range([r['accuracy'] for r in sel], '.4f')} | "
                f"{median_range([r['mean_iou'] for r in sel], '.3f')} | "
                f"{median_range([r['velocity_error_rel'] for r in sel], '.2f')} | "
                f"{median_range([r['static_velocity_error_rel'] for r in sel], '.2f')} | "
                f"{median_range([r['seconds'] for r in sel], '.2f')} |"
            )


if __name__ == "__main__":
    main()
