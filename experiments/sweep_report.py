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
import csv
import logging
import os
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

OVERRIDES_TAG = "spatialseg.overrides"
PARENT_TAG = "mlflow.parentRunId"
PAGE = 1000  # runs per search request
NOT_SET = "n/a"  # a run without the --by key (param, name, override or target)


class ReportError(Exception):
    """A problem the user can fix (no store, unknown experiment or key); one line."""


@dataclass
class Group:
    """The child runs that share one value per ``--by`` key."""

    key: tuple[str, ...]
    runs: int = 0
    finished: int = 0
    failed: int = 0
    values: dict[str, list[float]] = field(default_factory=dict)


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


def search_all(client: Any, experiment: str, filter_string: str = "") -> list[Any]:
    """Every run of ``experiment`` matching ``filter_string``, following MLflow's pages."""
    runs: list[Any] = []
    token = None
    while True:
        page = client.search_runs(
            [experiment], filter_string=filter_string, max_results=PAGE, page_token=token
        )
        runs.extend(page)
        token = page.token
        if not token:
            return runs


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


def overrides(run: Any) -> dict[str, str]:
    """The job's command-line overrides as ``{key: value}`` (``+`` and ``~`` stripped)."""
    pairs = (o.split("=", 1) for o in run.data.tags.get(OVERRIDES_TAG, "").split() if "=" in o)
    return {k.lstrip("+~"): v for k, v in pairs}


def group_value(run: Any, key: str) -> str | None:
    """The run's value for ``--by`` key ``key`` (param, .name, override, ._target_)."""
    params = run.data.params
    for candidate in (key, f"{key}.name"):
        if candidate in params:
            return str(params[candidate])
    chosen = overrides(run)
    if key in chosen:
        return chosen[key]
    return params.get(f"{key}._target_")


def group_runs(children: Sequence[Any], by: Sequence[str], metrics: Sequence[str]) -> list[Group]:
    """Children grouped by the ``by`` keys, with each finished run's metric values."""
    for key in by:
        if all(group_value(r, key) is None for r in children):
            known = sorted({p for r in children for p in r.data.params})
            raise ReportError(
                f"unknown --by key {key!r}: no run has it as a param or override; "
                f"params include: {', '.join(known[:40])}"
            )
    groups: dict[tuple[str, ...], Group] = {}
    for run in children:
        key = tuple(group_value(run, k) or NOT_SET for k in by)
        group = groups.setdefault(key, Group(key, values={m: [] for m in metrics}))
        group.runs += 1
        if run.info.status == "FINISHED":
            group.finished += 1
            for m in metrics:
                if m in run.data.metrics:
                    group.values[m].append(float(run.data.metrics[m]))
        elif run.info.status == "FAILED":
            group.failed += 1
    return [groups[k] for k in sorted(groups, key=_sort_key)]


def _sort_key(key: tuple[str, ...]) -> tuple[tuple[int, float, str], ...]:
    """Numbers in numeric order, before text."""

    def one(v: str) -> tuple[int, float, str]:
        try:
            return (0, float(v), "")
        except ValueError:
            return (1, 0.0, v)

    return tuple(one(v) for v in key)


def quartiles(values: Iterable[float]) -> tuple[float, float, float] | None:
    """(median, first quartile, third quartile), or None without values."""
    data = np.asarray(list(values), dtype=np.float64)
    if data.size == 0:
        return None
    q1, median, q3 = np.percentile(data, [25, 50, 75])
    return float(median), float(q1), float(q3)


def _cell(stats: tuple[float, float, float] | None) -> str:
    """``median [q1, q3]`` with 4 significant digits, or ``-``."""
    if stats is None:
        return "-"
    median, q1, q3 = stats
    return f"{median:.4g} [{q1:.4g}, {q3:.4g}]"


def markdown(groups: Sequence[Group], by: Sequence[str], metrics: Sequence[str]) -> str:
    """The report as a Markdown table: one row per group."""
    head = [*by, "runs", "finished", "failed", *(f"{m} median [IQR]" for m in metrics)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for g in groups:
        cells = [*g.key, str(g.runs), str(g.finished), str(g.failed)]
        cells += [_cell(quartiles(g.values[m])) for m in metrics]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_csv(
    path: Path, groups: Sequence[Group], by: Sequence[str], metrics: Sequence[str]
) -> None:
    """One row per group: keys, counts, and per metric n, median, q1, q3 (blank if none)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    stats_cols = [f"{m}_{s}" for m in metrics for s in ("n", "median", "q1", "q3")]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow([*by, "runs", "finished", "failed", *stats_cols])
        for g in groups:
            row: list[Any] = [*g.key, g.runs, g.finished, g.failed]
            for m in metrics:
                stats = quartiles(g.values[m])
                row += [len(g.values[m]), *(stats if stats else ("", "", ""))]
            writer.writerow(row)


def write_plot(
    path: Path, groups: Sequence[Group], by: Sequence[str], metrics: Sequence[str], title: str
) -> None:
    """One box plot per metric with values, a box per group (finished runs only)."""
    shown = [m for m in metrics if any(g.values[m] for g in groups)]
    fig = Figure(
        figsize=(max(4.0, 0.9 * len(groups) + 1.5) * len(shown), 4.2), layout="constrained"
    )
    axes = np.atleast_1d(fig.subplots(1, len(shown)))
    labels = ["\n".join(g.key) for g in groups]
    for ax, m in zip(axes, shown, strict=True):
        data = [g.values[m] for g in groups]
        ax.boxplot([d if d else [np.nan] for d in data])
        ax.set_xticks(range(1, len(labels) + 1), labels)
        ax.set(title=m, xlabel=" / ".join(by))
        ax.tick_params(axis="x", labelsize="small")
    fig.suptitle(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


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
