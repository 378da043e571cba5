"""The paper's Figures 6 (exterior) and 7 (interior): one command, tracked like any run.

    python experiments/paper_figures.py [--scenes exterior interior] [--seed 0]
        [--events 15000] [--out docs/images] [--runs-dir outputs/paper_figures]
        [--tracking mlflow|none] [--tracking-uri URI] [--set KEY=VALUE ...] [--dpi 100]

The scenes are segmented by the command line itself, as one Hydra multirun
(``python -m spatialseg -m +scene=exterior,interior ...`` with the default optimiser), so
each scene is an ordinary MLflow run under one sweep parent (default store
``sqlite:///mlflow.db`` in the working directory, ``--tracking none`` for no store) with its
outputs in ``--runs-dir/<job>``. Then, per scene, the figure is rebuilt from that run's
``labels.npy`` and ``result.json``; the warped volumes are recomputed from the window's
points (``points.prepare``, deterministic) and the run's final thetas, and the grid shape
is checked against the run's. Panels: (a) the window's first keyframe (an event image if
the window has none) and (b) its depth map in metres (unknown depth blank), as in the
paper's Fig. 6a/7a, (c) events by cluster, (d)-(e) the volume warped by each cluster's
motion (one object sharp, the other blurred), (f)-(g) contrast and (h)-(i) theta per
iteration. The PNGs are also logged as artifacts of the scene's MLflow run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
from _common import compose_config
from omegaconf import OmegaConf

from spatialseg.depth import with_configured_depth
from spatialseg.figures import paper_figure, save_figure, warped_images
from spatialseg.plots import cluster_image, event_image
from spatialseg.points import prepare
from spatialseg.scenes import load_scene
from spatialseg.settings import settings_from
from spatialseg.tracking import JOBS_DIR, PARENT_FILE, tracking_uri

#: The paper's figure number per scene; other scenes get ``figure_<scene>.png``.
PAPER_FIGURES = {"exterior": 6, "interior": 7}


class FigureError(Exception):
    """A problem the user can fix (a failed run, a missing output); reported in one line."""


def sweep_overrides(args: argparse.Namespace) -> list[str]:
    """The multirun's command-line overrides (Hydra syntax) for the requested scenes."""
    overrides = [
        f"+scene={','.join(args.scenes)}",
        f"seed={args.seed}",
        f"window.events={args.events}",
        f"hydra.sweep.dir={args.runs_dir.resolve()}",
    ]
    if args.tracking == "none":
        overrides.append("tracking=none")
    elif args.tracking_uri:
        overrides.append(f"tracking.uri={args.tracking_uri}")
    return overrides + list(args.set)


def run_sweep(overrides: list[str]) -> None:
    """Segment the scenes with ``python -m spatialseg -m``; its log goes to the console."""
    command = [sys.executable, "-m", "spatialseg", "-m", *overrides]
    code = subprocess.run(command, check=False).returncode
    if code != 0:
        raise FigureError(f"the segmentation runs failed (exit status {code}); see the log above")


def scene_jobs(runs_dir: Path) -> dict[str, dict[str, Any]]:
    """Each finished job's record (``overrides``, run ``dir``) by scene name."""
    jobs = {}
    for path in sorted((runs_dir / JOBS_DIR).glob("*.ok")):
        info = json.loads(path.read_text())
        scene = next(o.split("=", 1)[1] for o in info["overrides"] if o.startswith("+scene="))
        jobs[scene] = info
    return jobs


def mlflow_runs(runs_dir: Path, uri: str) -> tuple[str, dict[str, str]]:
    """The sweep's parent run id and its children's run ids by scene (empty if untracked)."""
    parent_file = runs_dir / PARENT_FILE
    if not parent_file.is_file():
        return "", {}
    from mlflow.tracking import MlflowClient

    parent = json.loads(parent_file.read_text())["run_id"]
    client = MlflowClient(uri)
    experiment = client.get_run(parent).info.experiment_id
    children = client.search_runs(
        [experiment], filter_string=f"tags.mlflow.parentRunId = '{parent}'"
    )
    by_scene = {}
    for run in children:
        for override in run.data.tags.get("spatialseg.overrides", "").split():
            if override.startswith("+scene="):
                by_scene[override.split("=", 1)[1]] = run.info.run_id
    return parent, by_scene


def scene_figure(scene: str, job: dict[str, Any]) -> Any:
    """The Figure 6/7 panels of one finished run, rebuilt from its outputs."""
    run_dir = Path(job["dir"])
    result_path = run_dir / "result.json"
    if not result_path.is_file():
        raise FigureError(f"{scene}: no result.json in {run_dir}; rerun the command")
    result = json.loads(result_path.read_text())
    labels = np.load(run_dir / "labels.npy")
    cfg = compose_config(*job["overrides"])
    recording = load_scene(
        cfg["scene"],
        seed=int(cfg["seed"]),
        window_events=int(cfg["window"]["events"]),
        windows=int(cfg["window"]["count"]),
    )
    # The run's own preparation (denoising, depth source), so labels.npy lines up, and its
    # first window's span (the window with its window.context neighbours), as clustered.
    settings = settings_from(cfg)
    recording = with_configured_depth(recording, settings)
    index, span, inner = next(iter(recording.spans(settings.window.context)))
    window = span.select(inner)
    prepared = prepare(span, settings)
    first = result["windows"][0]
    if list(prepared.grid.shape) != list(first["grid_shape"]):
        raise FigureError(
            f"{scene}: recomputed grid {list(prepared.grid.shape)} differs from the run's "
            f"{first['grid_shape']}; the code changed since the run, rerun the command"
        )
    thetas = np.array([c["theta"] for c in first["clusters"]])
    warped = warped_images(prepared, float(first["t_ref"]), thetas)
    ids = [int(c["id"]) for c in first["clusters"]]  # labels.npy holds these object ids
    clusters = cluster_image(window.events, labels[index], max(ids) + 1)
    accuracy = first.get("metrics", {}).get("accuracy")
    title = f"{scene}: {len(window.events)} events, {first['iterations']} iterations" + (
        f", accuracy {accuracy:.4f}" if accuracy is not None else ""
    )
    depth = window.depth_maps[0]
    if window.keyframes:
        keyframe = window.keyframes[0]
        scene_image = keyframe.image
        caption = f"keyframe at t = {1e3 * keyframe.t:.1f} ms"
    else:
        scene_image = event_image(window.events)
        caption = "events (no keyframe in the window)"
    return paper_figure(
        title,
        scene_image,
        caption,
        depth,
        clusters,
        warped,
        first["history"],
        first["units"],
        ids,
    )


def figure_name(scene: str) -> str:
    """``figure6_exterior.png``, ``figure7_interior.png``, else ``figure_<scene>.png``."""
    number = PAPER_FIGURES.get(scene, "")
    return f"figure{number}_{scene}.png" if number else f"figure_{scene}.png"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options; the defaults reproduce the paper's two figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(PAPER_FIGURES))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--events", type=int, default=15000, help="events per window")
    parser.add_argument("--out", type=Path, default=Path("docs/images"), help="PNG directory")
    parser.add_argument(
        "--runs-dir", type=Path, default=Path("outputs/paper_figures"), help="Hydra sweep dir"
    )
    parser.add_argument("--tracking", choices=["mlflow", "none"], default="mlflow")
    parser.add_argument(
        "--tracking-uri", default=None, help="default: $MLFLOW_TRACKING_URI or ./mlflow.db"
    )
    parser.add_argument(
        "--set", nargs="*", default=[], metavar="KEY=VALUE", help="more spatialseg overrides"
    )
    parser.add_argument("--dpi", type=int, default=100)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    """Run the scenes, write one PNG per scene, print the paths and the MLflow run ids."""
    args = parse_args(argv)
    try:
        run_sweep(sweep_overrides(args))
        jobs = scene_jobs(args.runs_dir)
        missing = sorted(set(args.scenes) - set(jobs))
        if missing:
            raise FigureError(f"no finished run for {', '.join(missing)} in {args.runs_dir}")
        uri = ""
        if args.tracking == "mlflow":
            settings = OmegaConf.create({"uri": args.tracking_uri})
            uri = tracking_uri(settings, str(Path.cwd()))
        parent, run_ids = mlflow_runs(args.runs_dir, uri) if uri else ("", {})
        for scene in args.scenes:
            path = save_figure(
                scene_figure(scene, jobs[scene]), args.out / figure_name(scene), args.dpi
            )
            print(f"{scene}: {path}  (run dir {jobs[scene]['dir']})")
            if scene in run_ids:
                from mlflow.tracking import MlflowClient

                MlflowClient(uri).log_artifact(run_ids[scene], str(path))
                print(f"{scene}: MLflow run {run_ids[scene]}")
        if parent:
            print(f"MLflow sweep parent run {parent} in {uri}")
    except FigureError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
