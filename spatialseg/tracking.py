"""MLflow tracking: each run (or multirun job) becomes one MLflow run, jobs under a parent.

A run records the composed config (flattened params and ``config.yaml``), the
per-iteration curves as stepped metrics, the final metrics and its output files. The
outputs are on disk before anything is sent, and a tracking failure only logs one warning
line: tracking never loses a result. In a multirun, :class:`SweepCallback` creates the
store, the experiment and a parent run before the jobs start and writes the parent's id to
``mlflow_parent.json`` in the sweep directory, where each job finds it.

Each multirun job also leaves its outcome as a file in ``<sweep dir>/jobs/`` (tracking on or
off, any launcher: joblib and Submitit jobs run in other processes); after the sweep,
:class:`SweepCallback` counts them so the command can exit non-zero when a job failed.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import logging
import os
import shlex
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

__all__ = [
    "SweepCallback",
    "SweepTally",
    "browse_hint",
    "last_sweep",
    "mark_job",
    "record",
    "record_failure",
]

log = logging.getLogger("spatialseg")

PARENT_FILE = "mlflow_parent.json"
JOBS_DIR = "jobs"  # in the sweep dir: <job num>.ok / <job num>.failed, one per finished job
AXES = "xyz"
MAX_BATCH = 1000  # metrics per log_batch call (MLflow's limit)
MAX_PARAMS = 100  # params per log_batch call (MLflow's limit)
MAX_PARAM_CHARS = 6000  # MLflow's limit on a param value


def _settings(cfg: DictConfig) -> DictConfig | None:
    """The ``tracking`` section when tracking is enabled, else None."""
    settings = cfg.get("tracking")
    return settings if settings is not None and settings.get("enabled", False) else None


def tracking_uri(settings: DictConfig, cwd: str) -> str:
    """``tracking.uri``, else ``$MLFLOW_TRACKING_URI``, else ``sqlite:///<cwd>/mlflow.db``."""
    if settings.uri:
        return str(settings.uri)
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{Path(cwd) / 'mlflow.db'}"


def _client(settings: DictConfig, cwd: str) -> Any:
    """An MlflowClient with bounded HTTP retries and quiet store migrations."""
    os.environ["MLFLOW_HTTP_REQUEST_MAX_RETRIES"] = str(settings.http_retries)
    os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] = str(settings.http_timeout)
    from mlflow.tracking import MlflowClient

    for name in ("alembic", "mlflow", "urllib3.connectionpool"):
        logging.getLogger(name).setLevel(logging.ERROR)
    return MlflowClient(tracking_uri=tracking_uri(settings, cwd))


def _experiment_id(client: Any, name: str) -> str:
    """The experiment's id, creating it (artifacts beside a SQLite file) if missing."""
    found = client.get_experiment_by_name(name)
    if found is not None:
        return str(found.experiment_id)
    uri = str(client.tracking_uri)
    location = None
    if uri.startswith("sqlite:///"):
        location = (Path(uri.removeprefix("sqlite:///")).parent / "mlartifacts").as_uri()
    return str(client.create_experiment(name, artifact_location=location))


def _warn(exc: BaseException) -> None:
    """The one warning line of an unavailable tracking store."""
    first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:300]
    log.warning("tracking: MLflow unavailable, outputs kept on disk only (%s)", first)


def flatten(tree: Any, prefix: str = "") -> Iterator[tuple[str, str]]:
    """``(dotted.key, text)`` pairs of a nested mapping; lists stay whole, as JSON."""
    if isinstance(tree, Mapping):
        for key, value in tree.items():
            yield from flatten(value, f"{prefix}{key}.")
    else:
        text = tree if isinstance(tree, str) else json.dumps(tree)
        yield prefix.rstrip("."), text[:MAX_PARAM_CHARS]


def _curves(window: Mapping[str, Any], prefix: str) -> Iterator[tuple[str, float, int]]:
    """``(key, value, step)`` of one window's per-iteration curves."""
    history = window["history"]
    for step, total in enumerate(history["total"], start=1):
        yield f"{prefix}iter/variance_total", total, step
    for step, values in enumerate(history["per_cluster"], start=1):
        for j, value in enumerate(values):
            yield f"{prefix}iter/variance_cluster{j}", value, step
    for step, thetas in enumerate(history["thetas"], start=1):
        for j, theta in enumerate(thetas):
            for axis, value in zip(AXES, theta, strict=False):
                yield f"{prefix}iter/theta{j}_{axis}", value, step


def _contrast(window: Mapping[str, Any]) -> float:
    """A window's total contrast: the sum of its clusters' final variances."""
    return float(sum(c["variance"] for c in window["clusters"]))


def _stage_times(windows: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """Each stage's seconds (prepare, init, cluster, ...) summed over the windows."""
    totals: dict[str, float] = {}
    for window in windows:
        for key, seconds in window["timings"].items():
            totals[key] = totals.get(key, 0.0) + seconds
    return totals


def _window_finals(window: Mapping[str, Any], prefix: str) -> Iterator[tuple[str, float]]:
    """``(key, value)`` of one window's final contrast per object, iterations, convergence."""
    yield f"{prefix}variance", _contrast(window)
    for c in window["clusters"]:
        yield f"{prefix}variance_object{c['id']}", c["variance"]
    yield f"{prefix}iterations", window["iterations"]
    yield f"{prefix}converged", float(window["converged"])


def _finals(summary: Mapping[str, Any]) -> Iterator[tuple[str, float]]:
    """``(key, value)`` of the final metrics of the whole run (``variance``: the total
    contrast summed over the windows; ``iterations``: all windows'; ``converged``: every
    window), accuracy, IoU and times, then each window's under ``window<i>/``."""
    windows = summary["windows"]
    yield "variance", sum(_contrast(w) for w in windows)
    yield "iterations", summary["iterations"]
    yield "converged", float(summary["converged"])
    yield "n_objects", summary["n_objects"]
    metrics = summary.get("metrics", {})
    for key in ("accuracy", "mean_iou", "unassigned_share"):
        if metrics.get(key) is not None:
            yield key, metrics[key]
    for obj, iou in (metrics.get("iou") or {}).items():
        yield f"iou_object{obj}", iou
    for key, seconds in {**summary["timings"], **_stage_times(windows)}.items():
        yield f"time_{key}", seconds
    for i, window in enumerate(windows):
        yield from _window_finals(window, f"window{i}/")


def _metrics(summary: Mapping[str, Any]) -> list[Any]:
    """Every metric point of a run as MLflow ``Metric`` objects."""
    from mlflow.entities import Metric

    now = int(time.time() * 1000)
    windows = summary["windows"]
    points = [
        Metric(key, float(value), now, step)
        for i, window in enumerate(windows)
        for key, value, step in _curves(window, f"window{i}/" if len(windows) > 1 else "")
    ]
    return points + [Metric(key, float(value), now, 0) for key, value in _finals(summary)]


def _log_run(
    client: Any, run_id: str, cfg: DictConfig, summary: Mapping[str, Any], out: Path
) -> None:
    """Params, config.yaml, metrics in batches, and the output files of one run."""
    from mlflow.entities import Param

    plain = OmegaConf.to_container(cfg, resolve=True)
    params = [Param(k, v) for k, v in flatten(plain)]
    for i in range(0, len(params), MAX_PARAMS):
        client.log_batch(run_id, params=params[i : i + MAX_PARAMS])
    client.log_text(run_id, OmegaConf.to_yaml(cfg, resolve=True), "config.yaml")
    metrics = _metrics(summary)
    for i in range(0, len(metrics), MAX_BATCH):
        client.log_batch(run_id, metrics=metrics[i : i + MAX_BATCH])
    for path in sorted(out.iterdir()):
        if path.is_file() and path.suffix in {".npy", ".json", ".png"}:
            client.log_artifact(run_id, str(path))


def _parent_id() -> str | None:
    """The sweep's parent run id when this is a multirun job with a parent file."""
    hc = HydraConfig.get()
    if hc.mode != RunMode.MULTIRUN:
        return None
    path = Path(hc.sweep.dir) / PARENT_FILE
    return json.loads(path.read_text())["run_id"] if path.is_file() else None


def _start_run(cfg: DictConfig, settings: DictConfig) -> tuple[Any, str]:
    """Create this job's MLflow run (a child of the sweep's parent, if any)."""
    hc = HydraConfig.get()
    client = _client(settings, hc.runtime.cwd)
    tags = {"spatialseg.overrides": " ".join(hc.overrides.task)[:MAX_PARAM_CHARS]}
    parent = _parent_id()
    if parent is not None:
        tags["mlflow.parentRunId"] = parent
    name = ",".join(hc.overrides.task)[:250] or None
    run = client.create_run(_experiment_id(client, settings.experiment), tags=tags, run_name=name)
    return client, run.info.run_id


def browse_hint(uri: str, run_id: str) -> str:
    """How to look at run ``run_id`` of the store at ``uri``: a server's address to open,
    else the ``mlflow ui`` command that serves the store."""
    if uri.startswith(("http://", "https://")):
        return f"run {run_id}; open {uri}"
    return f"run {run_id}; to browse: mlflow ui --backend-store-uri {shlex.quote(uri)}"


def record(cfg: DictConfig, summary: Mapping[str, Any], out_dir: Path) -> str | None:
    """Record a finished run in MLflow and return how to open it (:func:`browse_hint`);
    None when tracking is off, or the store is unavailable (a one-line warning)."""
    settings = _settings(cfg)
    if settings is None:
        return None
    log.info("logging to MLflow ...")  # the store's logging takes seconds at a run's end
    try:
        client, run_id = _start_run(cfg, settings)
        try:
            _log_run(client, run_id, cfg, summary, out_dir)
        except Exception:
            with contextlib.suppress(Exception):
                client.set_terminated(run_id, "FAILED")
            raise
        client.set_terminated(run_id, "FINISHED")
    except Exception as exc:
        _warn(exc)
        return None
    return browse_hint(str(client.tracking_uri), run_id)


def record_failure(cfg: DictConfig, error: BaseException) -> None:
    """Record a run that raised ``error`` as a FAILED MLflow run with the error as a tag."""
    settings = _settings(cfg)
    if settings is None:
        return
    try:
        client, run_id = _start_run(cfg, settings)
        client.set_tag(run_id, "error", f"{type(error).__name__}: {error}"[:MAX_PARAM_CHARS])
        client.set_terminated(run_id, "FAILED")
    except Exception as exc:
        _warn(exc)


@dataclass(frozen=True)
class SweepTally:
    """How many jobs of a finished sweep failed, and where their error files are."""

    failed: int
    total: int
    jobs_dir: Path
    parent_run_id: str


_last_sweep: SweepTally | None = None


def last_sweep() -> SweepTally | None:
    """The tally of the multirun this process launched (None before or without one)."""
    return _last_sweep


def mark_job(error: BaseException | None) -> None:
    """In a multirun, leave this job's outcome in ``<sweep dir>/jobs/<num>.ok|failed``.

    A file, because the job may run in another process or on another machine (joblib,
    Submitit); the sweep's callback counts them afterwards. A failure file holds the job's
    overrides and error, so the user can see which job failed and why.
    """
    hc = HydraConfig.get()
    if hc.mode != RunMode.MULTIRUN:
        return
    folder = Path(hc.sweep.dir) / JOBS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    status = "ok" if error is None else "failed"
    info = {"num": hc.job.num, "overrides": list(hc.overrides.task), "dir": hc.runtime.output_dir}
    if error is not None:
        info["error"] = f"{type(error).__name__}: {error}"
    (folder / f"{hc.job.num}.{status}").write_text(json.dumps(info) + "\n")


def _tally(sweep_dir: Path, parent_run_id: str) -> SweepTally:
    """Count the job outcome files of a sweep."""
    folder = sweep_dir / JOBS_DIR
    failed = len(list(folder.glob("*.failed")))
    total = failed + len(list(folder.glob("*.ok")))
    return SweepTally(failed, total, folder, parent_run_id)


class SweepCallback(Callback):
    """Open the sweep's parent run before the jobs, close it after (FAILED if the sweep dies)."""

    def __init__(self) -> None:
        self._client: Any = None
        self._run_id = ""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Clear old job outcomes; create the store, experiment and parent run for the jobs."""
        global _last_sweep
        _last_sweep = None
        jobs = Path(str(config.hydra.sweep.dir)) / JOBS_DIR
        for stale in [*jobs.glob("*.ok"), *jobs.glob("*.failed")]:
            stale.unlink()  # a rerun into the same sweep dir counts only its own jobs
        settings = _settings(config)
        if settings is None:
            return
        try:
            client = _client(settings, config.hydra.runtime.cwd)
            experiment = _experiment_id(client, settings.experiment)
            sweep_dir = Path(str(config.hydra.sweep.dir))
            run = client.create_run(experiment, run_name=f"sweep {sweep_dir.name}")
        except Exception as exc:
            _warn(exc)
            return
        self._client, self._run_id = client, run.info.run_id
        sweep_dir.mkdir(parents=True, exist_ok=True)
        (sweep_dir / PARENT_FILE).write_text(json.dumps({"run_id": self._run_id}))
        atexit.register(self._close, "FAILED")

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Count the failed jobs (for the exit status), tag and finish the parent run."""
        global _last_sweep
        _last_sweep = _tally(Path(str(config.hydra.sweep.dir)), self._run_id)
        if self._run_id:
            atexit.unregister(self._close)
            with contextlib.suppress(Exception):
                self._client.set_tag(self._run_id, "jobs_failed", str(_last_sweep.failed))
                self._client.set_tag(self._run_id, "jobs_total", str(_last_sweep.total))
            self._close("FINISHED")

    def _close(self, status: str) -> None:
        """Terminate the parent run with ``status``, warning if the store is gone."""
        try:
            self._client.set_terminated(self._run_id, status)
        except Exception as exc:
            _warn(exc)
