"""Summarise one sweep (a Hydra multirun) from the MLflow store: a table, a CSV and a box plot.

    python experiments/sweep_report.py [--tracking-uri sqlite:///mlflow.db]
        [--experiment spatialseg] [--parent RUN_ID] [--by optimizer scene n_clusters]
        [--metrics variance accuracy time_total] [--out-dir outputs/sweep_report]

The sweep is the parent run ``--parent`` or, by default, the most recently started run
that has children (every multirun opens one parent; its jobs are child runs). The children
are grouped by the ``--by`` keys; a key K is read from the run's param K (the flattened
config, e.g. ``n_clusters``, ``seed``, ``clustering.evals_per_step``), else K.name
(``scene`` -> ``scene.name``), else the job's command-line override ``K=V`` (how a config
group such as ``optimizer=pso`` was chosen), else K._target_ (the optimiser's class when the
sweep did not choose it). A job logs its params as it starts, so failed jobs have them too.

Per group: runs, finished, failed, and for each metric (the final values a run logs:
``variance`` = total contrast, ``accuracy``, ``mean_iou``, ``time_total`` = seconds from
loading to the end of segmentation, ...) the median and interquartile range over the
finished runs. Prints a Markdown table and writes ``<parent>.csv`` and ``<parent>.png``
(one box plot per metric, a box per group) into ``--out-dir``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from spatialseg.sweeps import (
    PARENT_TAG,
    ReportError,
    group_runs,
    markdown,
    search_all,
    write_csv,
    write_plot,
)


def open_store(uri: str) -> Any:
    """An MlflowClient on ``uri``; a SQLite file must exist (MLflow would create an empty one)."""
    if uri.startswith("sqlite:///"):
        path = Path(uri.removeprefix("sqlite:///"))
        if not path.is_file():
            raise ReportError(
                f"no MLflow store at {path}; run a sweep first "
                "(python -m spatialseg -m ...) or pass --tracking-uri"
            )
    for name in ("alembic", "mlflow"):
        logging.getLogger(name).setLevel(logging.ERROR)
    from mlflow.tracking import MlflowClient

    return MlflowClient(uri)


def experiment_id(client: Any, name: str, uri: str) -> str:
    """The id of experiment ``name``, or an error listing the experiments in the store."""
    found = client.get_experiment_by_name(name)
    if found is None:
        names = sorted(e.name for e in client.search_experiments())
        raise ReportError(
            f"experiment {name!r} not found in {uri}; experiments there: "
            + (", ".join(names) or "none")
        )
    return str(found.experiment_id)


def latest_parent(runs: Sequence[Any], experiment_name: str) -> str:
    """The id of the most recently started run that has child runs (the latest sweep)."""
    if not runs:
        raise ReportError(f"experiment {experiment_name!r} has no runs; run a sweep first")
    parents = {r.data.tags[PARENT_TAG] for r in runs if PARENT_TAG in r.data.tags}
    if not parents:
        raise ReportError(
            f"experiment {experiment_name!r} holds only single runs, no sweep; "
            "run one with python -m spatialseg -m ..."
        )
    start = {r.info.run_id: r.info.start_time or 0 for r in runs}
    for r in runs:  # a parent missing from the list (deleted): date it by its children
        parent = r.data.tags.get(PARENT_TAG)
        if parent is not None and parent not in start:
            start[parent] = max(start.get(parent, 0), r.info.start_time or 0)
    return max(parents, key=lambda p: start[p])


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--tracking-uri",
        default=os.environ.get("MLFLOW_TRACKING_URI", "sqlite:///mlflow.db"),
        help="default: $MLFLOW_TRACKING_URI, else sqlite:///mlflow.db",
    )
    parser.add_argument("--experiment", default="spatialseg")
    parser.add_argument("--parent", default=None, help="the sweep's parent run id (default latest)")
    parser.add_argument("--by", nargs="+", default=["optimizer", "scene", "n_clusters"])
    parser.add_argument("--metrics", nargs="+", default=["variance", "accuracy", "time_total"])
    parser.add_argument("--out-dir", type=Path, default=Path("outputs/sweep_report"))
    return parser.parse_args(argv)


def logged_metrics(children: Sequence[Any], wanted: Sequence[str]) -> list[str]:
    """The wanted metrics some finished run logged (``accuracy`` needs ground truth)."""
    finished = [r for r in children if r.info.status == "FINISHED"]
    logged = {m for r in finished for m in r.data.metrics}
    kept = [m for m in wanted if m in logged]
    if not kept:
        final = sorted(m for m in logged if "/" not in m)
        raise ReportError(
            f"no finished run logged {', '.join(wanted)}; final metrics: {', '.join(final)}"
        )
    return kept


def report(args: argparse.Namespace) -> tuple[str, Path, Path]:
    """Build the report of one sweep: the Markdown text and the CSV and PNG paths."""
    client = open_store(args.tracking_uri)
    experiment = experiment_id(client, args.experiment, args.tracking_uri)
    if args.parent:
        from mlflow.exceptions import MlflowException

        try:
            client.get_run(args.parent)
        except MlflowException as exc:
            raise ReportError(f"run {args.parent!r} not found in {args.tracking_uri}") from exc
        parent = args.parent
    else:
        parent = latest_parent(search_all(client, experiment), args.experiment)
    children = search_all(client, experiment, f"tags.{PARENT_TAG} = '{parent}'")
    if not children:
        raise ReportError(f"run {parent} has no child runs in experiment {args.experiment!r}")
    failed = sum(r.info.status == "FAILED" for r in children)
    if not any(r.info.status == "FINISHED" for r in children):
        raise ReportError(
            f"sweep {parent} has no finished runs ({failed} of {len(children)} failed; "
            "see their 'error' tags)"
        )
    metrics = logged_metrics(children, args.metrics)
    groups = group_runs(children, args.by, metrics)
    csv_path = args.out_dir / f"{parent}.csv"
    png_path = args.out_dir / f"{parent}.png"
    write_csv(csv_path, groups, args.by, metrics)
    title = f"sweep {parent}: {len(children)} jobs, {failed} failed"
    write_plot(png_path, groups, args.by, metrics, title)
    return f"{title}\n\n{markdown(groups, args.by, metrics)}", csv_path, png_path


def main(argv: list[str] | None = None) -> None:
    """Print the table and the written paths; a user mistake is one ``error:`` line, exit 2."""
    args = parse_args(argv)
    try:
        text, csv_path, png_path = report(args)
    except ReportError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    print(text)
    print(f"\nwrote {csv_path} and {png_path}")


if __name__ == "__main__":
    main()
