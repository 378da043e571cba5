"""A sweep's summary from its MLflow child runs: groups, a Markdown table, a CSV, a box plot.

The children are grouped by keys; a key K is read from the run's param K (the flattened
config, e.g. ``n_clusters``, ``seed``, ``clustering.evals_per_step``), else K.name
(``scene`` -> ``scene.name``, ``optimizer`` -> its preset's name), else the job's
command-line override ``K=V`` (how a config group was chosen), else K._target_ (an
optimiser a user's own config builds by class). A job logs its params as it starts, so
failed jobs have them too. Per group: runs, finished, failed, and per metric the median
and interquartile range over the finished runs. Used by
:class:`spatialseg.tracking.SweepCallback` (the parent run's ``sweep_summary.*``
artifacts) and by ``experiments/sweep_report.py``.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "Group",
    "ReportError",
    "group_runs",
    "group_value",
    "markdown",
    "overrides",
    "quartiles",
    "search_all",
    "summary_metric",
    "swept_keys",
    "write_csv",
    "write_plot",
    "write_summary",
]

OVERRIDES_TAG = "spatialseg.overrides"
PARENT_TAG = "mlflow.parentRunId"
PAGE = 1000  # runs per search request
NOT_SET = "n/a"  # a run without the key (param, name, override or target)
SUMMARY = "sweep_summary"  # the parent run's artifacts: sweep_summary.md, .csv, .png
ALL_JOBS = "sweep"  # the one grouping key when no override varies across the jobs


class ReportError(Exception):
    """A problem the user can fix (no store, unknown experiment or key); one line."""


@dataclass
class Group:
    """The child runs that share one value per grouping key."""

    key: tuple[str, ...]
    runs: int = 0
    finished: int = 0
    failed: int = 0
    values: dict[str, list[float]] = field(default_factory=dict)


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


def overrides(run: Any) -> dict[str, str]:
    """The job's command-line overrides as ``{key: value}`` (``+`` and ``~`` stripped)."""
    pairs = (o.split("=", 1) for o in run.data.tags.get(OVERRIDES_TAG, "").split() if "=" in o)
    return {k.lstrip("+~"): v for k, v in pairs}


def group_value(run: Any, key: str) -> str | None:
    """The run's value for grouping key ``key`` (param, .name, override, ._target_)."""
    params = run.data.params
    for candidate in (key, f"{key}.name"):
        if candidate in params:
            return str(params[candidate])
    chosen = overrides(run)
    if key in chosen:
        return chosen[key]
    return params.get(f"{key}._target_")


def swept_keys(children: Sequence[Any]) -> list[str]:
    """The override keys whose value differs across the jobs (what the sweep varied)."""
    chosen = [overrides(r) for r in children]
    keys = dict.fromkeys(k for o in chosen for k in o)  # first-seen order, once each
    return [k for k in keys if len({o.get(k) for o in chosen}) > 1]


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
    from matplotlib.figure import Figure  # only a sweep's end draws; keep imports light

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


def summary_metric(children: Sequence[Any]) -> str:
    """The metric a sweep's summary shows: ``accuracy`` if a job has it, else ``variance``."""
    return "accuracy" if any("accuracy" in r.data.metrics for r in children) else "variance"


def write_summary(out_dir: Path, children: Sequence[Any], title: str) -> list[Path]:
    """Write ``sweep_summary.md``, ``.csv`` and ``.png`` (the summary metric against the swept
    keys, one group for the whole sweep when none varies) into ``out_dir``; their paths."""
    by = swept_keys(children)
    metrics = [summary_metric(children)]
    groups = group_runs(children, by, metrics)
    if not by:  # one group, named so the table and the plot have a label
        by, groups[0].key = [ALL_JOBS], ("all",)
    paths = [out_dir / f"{SUMMARY}.{ext}" for ext in ("md", "csv", "png")]
    out_dir.mkdir(parents=True, exist_ok=True)
    paths[0].write_text(f"{title}\n\n{markdown(groups, by, metrics)}\n")
    write_csv(paths[1], groups, by, metrics)
    if not any(g.values[metrics[0]] for g in groups):
        return paths[:2]  # no finished job logged the metric: nothing to plot
    write_plot(paths[2], groups, by, metrics, title)
    return paths
