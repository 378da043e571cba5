"""Accuracy of the spatial and planar models on every shipped simulated scene.

    python experiments/segment_scenes.py [--seeds 3] [--events 15000] [--windows 1]
        [--out FILE.json] [--models spatial planar spatial:volume.coordinates=metric]

For each scene, model and seed: simulate ``--windows`` windows of ``--events`` events
(seeded), segment them with the default configuration, and report per-event accuracy,
mean IoU, the relative velocity error of matched clusters (spatial model, m/s; the mean
over objects, and, where the camera moves, the static scene's alone: its target is minus
the camera's velocity), each a mean over the windows, and wall time; the JSON also holds
each run's worst window.
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


def window_metrics(seg, gt, w: int, k: int, spatial: bool) -> dict:
    """One window's accuracy, mean IoU and velocity errors, its clusters matched within it."""
    res, index = seg.windows[w], seg.indices[w]
    thetas = np.zeros((k, 3))
    thetas[:, : res.clustering.thetas.shape[1]] = res.clustering.thetas
    return segmentation_metrics(
        res.labels,
        gt.labels[index],
        pred_velocities=thetas if spatial else None,
        true_motions=gt.motions if spatial else None,
    )


def _mean(values: list[float | None]) -> float | None:
    """Mean over windows of a metric, None when no window has it."""
    v = [x for x in values if x is not None]
    return float(np.mean(v)) if v else None


def run_one(scene: str, variant: str, seed: int, events: int, windows: int = 1) -> dict:
    """Simulate and segment one scene with one model variant; return its metrics (means
    over the ``windows`` windows) and time."""
    k = N_CLUSTERS.get(scene, 2)
    model, _, extra = variant.partition(":")
    overrides = split_overrides(extra)
    cfg = compose_config(
        f"+scene={scene}", f"model={model}", f"n_clusters={k}", f"seed={seed}", *overrides
    )
    rec = load_scene(cfg["scene"], seed=seed, window_events=events, windows=windows)
    start = time.perf_counter()
    rec, seg = segment_loaded(rec, cfg, instantiate(cfg["optimizer"]), seed=seed)
    seconds = time.perf_counter() - start
    spatial = model == "spatial"
    ms = [window_metrics(seg, rec.ground_truth, w, k, spatial) for w in range(len(seg.windows))]
    static = [m.get("velocity_error", {}).get(str(STATIC_SCENE), {}).get("rel") for m in ms]
    return {
        "scene": scene,
        "model": variant,
        "seed": seed,
        "accuracy": _mean([m["accuracy"] for m in ms]),
        "mean_iou": _mean([m["mean_iou"] for m in ms]),
        "velocity_error_rel": _mean([m.get("velocity_error_rel") for m in ms]),
        "static_velocity_error_rel": _mean(static),
        "worst_window_accuracy": min(m["accuracy"] for m in ms),
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--events", type=positive_count, default=15000)
    parser.add_argument("--windows", type=positive_count, default=1)
    parser.add_argument("--models", nargs="+", default=["spatial", "planar"])
    parser.add_argument("--scenes", nargs="+", default=None)
    parser.add_argument("--out", type=Path, default=Path("outputs/segment_scenes.json"))
    args = parser.parse_args()
    if args.seeds < 1:
        parser.error(f"--seeds must be >= 1, got {args.seeds}")
    rows = [
        run_one(scene, model, seed, args.events, args.windows)
        for scene in (args.scenes or simulated_scenes())
        for model in args.models
        for seed in range(args.seeds)
    ]
    write_json(
        args.out,
        {"events": args.events, "windows": args.windows, "seeds": args.seeds, "runs": rows},
    )
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
