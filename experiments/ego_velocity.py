"""How sharply one window's contrast pins down a moving camera's velocity, labels aside.

    python experiments/ego_velocity.py [--seeds 3] [--events 15000 30000 45000]
        [--scenes ego_forward ego_street] [--set volume.t_ref=start ...] [--out FILE.json]

For each moving-camera scene, window length and seed: the window is simulated, lifted by
EDPA and its static scene's events are taken by their ground-truth labels (perfect
memberships, so the clustering plays no part). The contrast of their volume is then
evaluated at velocities ``s * v`` (``v`` the truth, minus the camera's velocity) and
maximised by Nelder-Mead from ``v``. The maximum's relative distance from ``v`` is the error
the objective itself makes, the floor under the segmentation's static velocity error; the
contrast at ``0.75 v`` and ``1.25 v`` relative to that at ``v`` says how sharp the peak is.
Prints a Markdown table of medians (min-max over seeds).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _common import (
    compose_config,
    median_range,
    positive_count,
    simulated_scenes,
    write_json,
)
from scipy.optimize import minimize

from spatialseg.points import ModelEvaluator, prepare, reference_time, window_objective
from spatialseg.scenes import load_scene
from spatialseg.settings import settings_from
from spatialseg.simulate.render import STATIC_SCENE

#: Multiples of the true velocity at which the contrast is reported.
SCALES = (0.5, 0.75, 1.0, 1.25, 1.5)


def moving_camera_scenes() -> list[str]:
    """The shipped simulated scenes whose camera translates (a static scene that moves)."""
    return [
        s
        for s in simulated_scenes()
        if np.any(compose_config(f"+scene={s}")["scene"]["camera"]["ego_velocity"])
    ]


def static_objective(
    scene: str, seed: int, events: int, overrides: list[str]
) -> tuple[ModelEvaluator, np.ndarray, float]:
    """The contrast of ``scene``'s static events (ground-truth labels) in a window of
    ``events``, the static scene's true velocity and the window's duration (s)."""
    cfg = compose_config(f"+scene={scene}", f"seed={seed}", *overrides)
    rec = load_scene(cfg["scene"], seed=seed, window_events=events)
    if STATIC_SCENE not in rec.ground_truth.motions:
        raise ValueError(f"scene {scene!r} has a static camera; choose a moving-camera scene")
    settings = settings_from(cfg)
    prepared = prepare(rec, settings)
    t_ref = reference_time(prepared.t, settings.volume.t_ref)
    objective = window_objective(prepared, t_ref, settings)
    static = rec.ground_truth.labels[prepared.valid] == STATIC_SCENE
    objective.set_weights(static.astype(np.float64))
    duration = float(prepared.t.max() - prepared.t.min())
    return objective, rec.ground_truth.motions[STATIC_SCENE], duration


def contrast_maximum(objective: ModelEvaluator, start: np.ndarray) -> np.ndarray:
    """The contrast's local maximum nearest ``start`` (Nelder-Mead, to 1 mm/s)."""
    result = minimize(
        lambda theta: -objective.value(theta),
        start,
        method="Nelder-Mead",
        options={"xatol": 1e-3, "fatol": 1e-12, "maxiter": 2000},
    )
    return np.asarray(result.x)


def run_one(scene: str, seed: int, events: int, overrides: list[str]) -> dict:
    """One scene, seed and window length: the maximum's error and the peak's sharpness."""
    objective, truth, duration = static_objective(scene, seed, events, overrides)
    at_truth = objective.value(truth)
    best = contrast_maximum(objective, truth)
    return {
        "scene": scene,
        "seed": seed,
        "events": events,
        "duration": duration,
        "truth": truth.tolist(),
        "maximum": best.tolist(),
        "maximum_error_rel": float(np.linalg.norm(best - truth) / np.linalg.norm(truth)),
        "contrast_rel": {str(s): objective.value(s * truth) / at_truth for s in SCALES},
    }


def markdown(rows: list[dict]) -> str:
    """The table of medians (min-max over seeds) per scene and window length."""
    lines = [
        "| scene | events | window (s) | maximum's error (rel.) | contrast at 0.75 v | "
        "contrast at 1.25 v |",
        "|---|---|---|---|---|---|",
    ]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for events in dict.fromkeys(r["events"] for r in rows):
            sel = [r for r in rows if r["scene"] == scene and r["events"] == events]
            lines.append(
                f"| {scene} | {events} | {median_range([r['duration'] for r in sel], '.3f')} | "
                f"{median_range([r['maximum_error_rel'] for r in sel], '.2f')} | "
                f"{median_range([r['contrast_rel']['0.75'] for r in sel], '.4f')} | "
                f"{median_range([r['contrast_rel']['1.25'] for r in sel], '.4f')} |"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--events", type=positive_count, nargs="+", default=[15000, 30000, 45000])
    parser.add_argument("--scenes", nargs="+", default=None)
    parser.add_argument(
        "--set", nargs="*", default=[], help="config overrides, e.g. volume.z_bins=8"
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/ego_velocity.json"))
    args = parser.parse_args()
    if args.seeds < 1:
        parser.error(f"--seeds must be >= 1, got {args.seeds}")
    choices = moving_camera_scenes()
    unknown = sorted(set(args.scenes or ()) - set(choices))
    if unknown:
        parser.error(
            f"--scenes {' '.join(unknown)}: not a moving-camera scene; choose from {choices}"
        )
    rows = [
        run_one(scene, seed, events, args.set)
        for scene in (args.scenes or choices)
        for events in args.events
        for seed in range(args.seeds)
    ]
    write_json(args.out, {"overrides": args.set, "runs": rows})
    print(markdown(rows))


if __name__ == "__main__":
    main()
