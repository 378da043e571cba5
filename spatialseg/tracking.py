"""MLflow tracking: each run (or multirun job) becomes one MLflow run, jobs under a parent.

A job's run opens when the job starts (:func:`live_run`), stamped with that time and
created by a separate process (:mod:`spatialseg.tracking_worker`) while the job works, so a
long job shows as RUNNING with its composed config (flattened params and ``config.yaml``)
and its code version (tags ``spatialseg.version`` and, in a git checkout,
``mlflow.source.git.commit``). Each window's metrics, its per-iteration curves as stepped
metrics, are logged as the window ends; the whole run's metrics and its output files at its
end. The run ends FINISHED, FAILED on an error (its message as the tag ``error``) or KILLED
on SIGTERM, Ctrl-C or a job that vanished (SIGKILL). The outputs are on disk before they
are sent, and a tracking failure only logs one warning line: tracking never loses a
result. In a multirun, :class:`SweepCallback` creates the store, the
experiment and a parent run before the jobs start and writes the parent's id to
``mlflow_parent.json`` in the sweep directory, where each job finds it; after the jobs it
logs the sweep's summary to the parent.

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
import pickle
import queue
import shlex
import statistics
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from spatialseg import sweeps, tracking_process
from spatialseg.interrupts import interruption, raise_pending, stopped

__all__ = [
    "LiveRun",
    "SweepCallback",
    "SweepTally",
    "browse_hint",
    "git_commit",
    "last_sweep",
    "live_run",
    "mark_job",
]

log = logging.getLogger("spatialseg")

PARENT_FILE = "mlflow_parent.json"
JOBS_DIR = "jobs"  # in the sweep dir: <job num>.ok / <job num>.failed, one per finished job
AXES = "xyz"
MAX_BATCH = 1000  # metrics per log_batch call (MLflow's limit)
MAX_PARAMS = 100  # params per log_batch call (MLflow's limit)
MAX_PARAM_CHARS = 6000  # MLflow's limit on a param value
GIT_TIMEOUT = 2.0  # seconds per git call for the commit tag
WORKER_EXIT_TIMEOUT = 30.0  # seconds the job waits for the tracking process to exit


def _settings(cfg: DictConfig) -> DictConfig | None:
    """The ``tracking`` section when tracking is enabled, else None."""
    settings = cfg.get("tracking")
    return settings if settings is not None and settings.get("enabled", False) else None


def tracking_uri(settings: Mapping[str, Any], cwd: str) -> str:
    """``tracking.uri``, else ``$MLFLOW_TRACKING_URI``, else ``sqlite:///<cwd>/mlflow.db``."""
    if settings["uri"]:
        return str(settings["uri"])
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{Path(cwd) / 'mlflow.db'}"


def store_client(settings: Mapping[str, Any], cwd: str) -> Any:
    """An MlflowClient (``settings``: the ``tracking`` section) with bounded HTTP retries and
    quiet store migrations."""
    os.environ["MLFLOW_HTTP_REQUEST_MAX_RETRIES"] = str(settings["http_retries"])
    os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] = str(settings["http_timeout"])
    from mlflow.tracking import MlflowClient

    for name in ("alembic", "mlflow", "urllib3.connectionpool"):
        logging.getLogger(name).setLevel(logging.ERROR)
    return MlflowClient(tracking_uri=tracking_uri(settings, cwd))


def experiment_id(client: Any, name: str) -> str:
    """The experiment's id, creating it (artifacts beside a SQLite file) if missing."""
    found = client.get_experiment_by_name(name)
    if found is not None:
        return str(found.experiment_id)
    uri = str(client.tracking_uri)
    location = None
    if uri.startswith("sqlite:///"):
        location = (Path(uri.removeprefix("sqlite:///")).parent / "mlartifacts").as_uri()
    return str(client.create_experiment(name, artifact_location=location))


def _warn(problem: BaseException | str) -> None:
    """The one warning line of an unavailable tracking store (``problem``: the error, or
    its first line)."""
    if isinstance(problem, BaseException):
        problem = first_line(problem)
    log.warning("tracking: MLflow unavailable, outputs kept on disk only (%s)", problem)


def first_line(exc: BaseException) -> str:
    """An error's first line (at most 300 characters), or its type's name."""
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0][:300]


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
    """``(key, value)`` of one window's final contrast per object, iterations, convergence
    and, with ground truth, accuracy."""
    yield f"{prefix}variance", _contrast(window)
    for c in window["clusters"]:
        yield f"{prefix}variance_object{c['id']}", c["variance"]
    yield f"{prefix}iterations", window["iterations"]
    yield f"{prefix}converged", float(window["converged"])
    accuracy = window.get("metrics", {}).get("accuracy")
    if accuracy is not None:
        yield f"{prefix}accuracy", accuracy


def _window_metrics(
    window: Mapping[str, Any], index: int, *, prefixed: bool
) -> Iterator[tuple[str, float, int]]:
    """Window ``index``'s curves (under ``window<i>/`` if ``prefixed``) and final values."""
    yield from _curves(window, f"window{index}/" if prefixed else "")
    for key, value in _window_finals(window, f"window{index}/"):
        yield key, value, 0


def _timing_key(key: str) -> str:
    """A ``timings`` entry's metric name: ``time_<stage>`` for seconds, a rate as it is."""
    return key if key == "real_time_factor" else f"time_{key}"


def _finals(summary: Mapping[str, Any]) -> Iterator[tuple[str, float]]:
    """``(key, value)`` of the whole run's final metrics (``variance``: the total contrast
    summed over the windows; ``iterations``: all windows'; ``converged``: every window),
    accuracy, IoU and times."""
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
        yield _timing_key(key), seconds


def now_ms() -> int:
    """The time now, in MLflow's milliseconds."""
    return int(time.time() * 1000)


def log_metrics(
    client: Any, run_id: str, points: Iterable[tuple[str, float, int]], stamp: int
) -> None:
    """Log ``(key, value, step)`` points stamped ``stamp`` (ms; when the job measured them,
    not when the tracking process sends them), in batches of MLflow's limit."""
    from mlflow.entities import Metric

    metrics = [Metric(key, float(value), stamp, step) for key, value, step in points]
    for i in range(0, len(metrics), MAX_BATCH):
        client.log_batch(run_id, metrics=metrics[i : i + MAX_BATCH])


def log_params(
    client: Any, run_id: str, params: Sequence[tuple[str, str]], config_yaml: str
) -> None:
    """The composed config as flattened params (:func:`flatten`) and as ``config.yaml``."""
    from mlflow.entities import Param

    entries = [Param(k, v) for k, v in params]
    for i in range(0, len(entries), MAX_PARAMS):
        client.log_batch(run_id, params=entries[i : i + MAX_PARAMS])
    client.log_text(run_id, config_yaml, "config.yaml")


def log_outputs(client: Any, run_id: str, out: Path) -> None:
    """The run directory's output files (labels, result.json, figures) as artifacts."""
    for path in sorted(out.iterdir()):
        if path.is_file() and path.suffix in {".npy", ".json", ".png"}:
            client.log_artifact(run_id, str(path))


def _git(folder: Path, *args: str) -> str | None:
    """``git ARGS``'s output in ``folder``; None when git is missing, fails or hangs."""
    try:
        done = subprocess.run(
            ["git", *args],
            cwd=folder,
            capture_output=True,
            text=True,
            timeout=GIT_TIMEOUT,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip()


def git_commit(folder: Path | None = None) -> str | None:
    """HEAD's commit of the git checkout that tracks the package (``folder``), else None."""
    folder = folder or Path(__file__).parent
    if _git(folder, "ls-files", "--error-unmatch", "__init__.py") is None:
        return None  # not a checkout, or an installed copy inside someone else's repository
    return _git(folder, "rev-parse", "HEAD") or None


def code_tags() -> dict[str, str]:
    """The code version a run ran: the package's version and, in a checkout, its commit."""
    from spatialseg import __version__

    tags = {"spatialseg.version": __version__}
    commit = git_commit()
    if commit is not None:
        tags["mlflow.source.git.commit"] = commit
    return tags


def _parent_id() -> str | None:
    """The sweep's parent run id when this is a multirun job with a parent file."""
    hc = HydraConfig.get()
    if hc.mode != RunMode.MULTIRUN:
        return None
    path = Path(hc.sweep.dir) / PARENT_FILE
    return json.loads(path.read_text())["run_id"] if path.is_file() else None


def browse_hint(uri: str, run_id: str) -> str:
    """How to look at run ``run_id`` of the store at ``uri``: a server's address to open,
    else the ``mlflow ui`` command that serves the store."""
    if uri.startswith(("http://", "https://")):
        return f"run {run_id}; open {uri}"
    return f"run {run_id}; to browse: mlflow ui --backend-store-uri {shlex.quote(uri)}"


class LiveRun:
    """The job's MLflow run while it runs, kept by a worker process
    (:mod:`spatialseg.tracking_worker`) so that importing MLflow and opening the store
    overlap the job instead of delaying it; idle when tracking is off or the store failed.

    Requests go out through a thread (the job never waits on a pipe); a second thread reads
    the answers, says when the run is RUNNING and warns when the store fails. Only
    :meth:`finish` and :meth:`end` wait, for the worker to have logged everything before.
    """

    def __init__(self) -> None:
        self._worker: subprocess.Popen | None = None
        self._outbox: queue.Queue = queue.Queue()
        self._answers: queue.Queue = queue.Queue()
        self._warned = False
        self.run_id = ""
        self._uri = ""
        self._windows = 0  # windows whose metrics are logged

    def start(self, cfg: DictConfig) -> None:
        """Take the worker (started with the command, or now: :mod:`spatialseg.tracking_process`)
        and ask it to create the run, stamped now, with the job's code version and config; the
        run is RUNNING (and says how to open it) once created."""
        settings = _settings(cfg)
        if settings is None:
            tracking_process.stop_early()
            return
        hc = HydraConfig.get()
        job = {
            "settings": OmegaConf.to_container(settings, resolve=True),
            "cwd": hc.runtime.cwd,
            "overrides": list(hc.overrides.task),
            "parent": _parent_id(),
            "start_time": now_ms(),
            "params": list(flatten(OmegaConf.to_container(cfg, resolve=True))),
            "config_yaml": OmegaConf.to_yaml(cfg, resolve=True),
        }
        try:
            self._worker = tracking_process.take()
        except OSError as exc:
            self._warn(exc)
            return
        threading.Thread(target=self._write, daemon=True).start()
        threading.Thread(target=self._read, daemon=True).start()
        self._outbox.put(("start", job))

    def log_windows(self, windows: Sequence[Mapping[str, Any]], *, prefixed: bool = True) -> None:
        """Log windows as they end (a stream's chunk, a recording's window), each under
        ``window<i>/`` (the curves of a recording's only window: unprefixed)."""
        first, self._windows = self._windows, self._windows + len(windows)
        if self._worker is None:
            return
        points = [
            point
            for i, window in enumerate(windows, start=first)
            for point in _window_metrics(window, i, prefixed=prefixed)
        ]
        self._outbox.put(("metrics", points, now_ms()))

    def finish(self, summary: Mapping[str, Any], out_dir: Path) -> str | None:
        """Log the run's final metrics, unlogged windows and files; return how to open it."""
        if self._worker is None or self._warned:
            return None
        log.info("logging to MLflow ...")  # the store's logging takes seconds at a run's end
        windows = summary["windows"]
        prefixed = self._windows > 0 or len(windows) > 1
        points = [(key, value, 0) for key, value in _finals(summary)]
        for i, window in enumerate(windows[self._windows :], start=self._windows):
            points += _window_metrics(window, i, prefixed=prefixed)
        self._windows = len(windows)
        self._outbox.put(("metrics", points, now_ms()))
        self._outbox.put(("outputs", str(out_dir)))
        answer = self._answer("hint")
        return answer[1] if answer[0] == "hint" else None

    def end(self, status: str, error: BaseException | None = None) -> None:
        """End the run as ``status`` (FINISHED, FAILED, KILLED), ``error`` as its tag, and
        wait for the worker to exit."""
        if self._worker is None:
            return
        text = None if error is None else f"{type(error).__name__}: {error}"
        self._outbox.put(("end", status, text))
        self._outbox.put(None)
        answer = self._answer("ended")
        worker, self._worker = self._worker, None
        try:
            worker.wait(timeout=WORKER_EXIT_TIMEOUT)
        except subprocess.TimeoutExpired:
            worker.kill()
        if answer[0] == "ended" and answer[1] and status != "FINISHED":
            self._say(status)  # a finished run's report names it

    def _answer(self, kind: str) -> tuple:
        """The worker's next answer of ``kind`` (``("gone",)`` if it exited without one); an
        earlier answer left unread, as when Ctrl-C stopped :meth:`finish`, is skipped."""
        while (answer := self._answers.get())[0] not in (kind, "gone"):
            pass
        if answer[0] == "gone":
            self._warn("the tracking process exited")
        return answer

    def _write(self) -> None:
        """Send the queued requests to the worker, in order; close its input after the last."""
        assert self._worker is not None and self._worker.stdin is not None
        pipe = self._worker.stdin
        with contextlib.suppress(OSError):  # the worker is gone: the reader says so
            while (request := self._outbox.get()) is not None:
                pickle.dump(request, pipe)
                pipe.flush()
            pipe.close()

    def _read(self) -> None:
        """Take the worker's answers: say RUNNING, warn, pass the rest to :meth:`_answer`."""
        assert self._worker is not None and self._worker.stdout is not None
        pipe = self._worker.stdout
        while True:
            try:
                answer = pickle.load(pipe)
            except (EOFError, OSError, pickle.UnpicklingError):
                self._answers.put(("gone",))
                return
            if answer[0] == "started":
                self.run_id, self._uri = answer[1], answer[2]
                self._say("RUNNING")
            elif answer[0] == "warning":
                self._warn(answer[1])
            else:
                self._answers.put(answer)

    def _warn(self, problem: BaseException | str) -> None:
        """Warn once that tracking failed (:func:`_warn`)."""
        if not self._warned:
            self._warned = True
            _warn(problem)

    def _say(self, status: str) -> None:
        """Log the run's ``status`` and how to open it."""
        log.info("MLflow: %s %s", status, browse_hint(self._uri, self.run_id))


@contextlib.contextmanager
def live_run(cfg: DictConfig) -> Iterator[LiveRun]:
    """This job's MLflow run over the block: FINISHED when it ends, FAILED on an exception,
    KILLED on SIGTERM or Ctrl-C (the :class:`SystemExit` the command line's SIGTERM handler
    raises, Python's :class:`KeyboardInterrupt`, or an exception raised while unwinding
    from either: :func:`spatialseg.interrupts.interruption`)."""
    run = LiveRun()
    try:
        run.start(cfg)
        yield run
        raise_pending()  # a stop that a library swallowed on the way ends the run KILLED
    except Exception as exc:
        run.end("FAILED" if interruption(exc) is None else "KILLED", exc)
        raise
    except BaseException:
        run.end("KILLED")
        raise
    run.end("FINISHED")


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


def _children(client: Any, parent_run_id: str) -> list[Any]:
    """The MLflow runs of a sweep's jobs (every page of the search)."""
    experiment = client.get_run(parent_run_id).info.experiment_id
    return sweeps.search_all(client, experiment, f"tags.mlflow.parentRunId = '{parent_run_id}'")


def _sweep_metrics(tally: SweepTally, children: Sequence[Any]) -> dict[str, float]:
    """The parent run's summary: job counts (outcome files) and the jobs' accuracy spread."""
    summary = {
        "jobs": float(tally.total),
        "jobs_finished": float(tally.total - tally.failed),
        "jobs_failed": float(tally.failed),
    }
    accuracy = [r.data.metrics["accuracy"] for r in children if "accuracy" in r.data.metrics]
    if accuracy:
        summary["accuracy_median"] = statistics.median(accuracy)
        summary["accuracy_min"] = min(accuracy)
        summary["accuracy_max"] = max(accuracy)
    return summary


def _best_job(children: Sequence[Any]) -> str | None:
    """The job run of the highest ``accuracy``, as ``name (run id)``; None without one."""
    scored = [r for r in children if "accuracy" in r.data.metrics]
    if not scored:
        return None
    best = max(scored, key=lambda r: r.data.metrics["accuracy"])
    return f"{best.info.run_name} ({best.info.run_id})"


class SweepCallback(Callback):
    """The sweep's parent run: opened before the jobs, summarised and closed after them."""

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
            client = store_client(settings, config.hydra.runtime.cwd)
            experiment = experiment_id(client, settings.experiment)
            sweep_dir = Path(str(config.hydra.sweep.dir))
            name = f"sweep {sweep_dir.name}"
            run = client.create_run(experiment, tags=code_tags(), run_name=name)
        except Exception as exc:
            _warn(exc)
            return
        self._client, self._run_id = client, run.info.run_id
        sweep_dir.mkdir(parents=True, exist_ok=True)
        (sweep_dir / PARENT_FILE).write_text(json.dumps({"run_id": self._run_id}))
        atexit.register(self._close_at_exit)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Count the failed jobs (for the exit status); log the summary, finish the parent."""
        global _last_sweep
        _last_sweep = _tally(Path(str(config.hydra.sweep.dir)), self._run_id)
        if not self._run_id:
            return
        atexit.unregister(self._close_at_exit)
        try:
            self._summarise(_last_sweep)
        except Exception as exc:
            _warn(exc)
        self._close("FINISHED")
        hint = browse_hint(str(self._client.tracking_uri), self._run_id)
        print(f"sweep: {_last_sweep.total} jobs, {_last_sweep.failed} failed; MLflow parent {hint}")

    def _summarise(self, tally: SweepTally) -> None:
        """Log the sweep's summary metrics (:func:`_sweep_metrics`) and tags to the parent."""
        children = _children(self._client, self._run_id)
        metrics = _sweep_metrics(tally, children)
        points = [(k, v, 0) for k, v in metrics.items()]
        log_metrics(self._client, self._run_id, points, now_ms())
        tags = {"jobs_failed": str(tally.failed), "jobs_total": str(tally.total)}
        best = _best_job(children)
        if best is not None:
            tags["best_job"] = best
        for key, value in tags.items():
            self._client.set_tag(self._run_id, key, value)
        try:
            self._log_summary_files(tally, children)
        except Exception as exc:  # the table and plot are extras: never fail the sweep
            first = (str(exc).strip().splitlines() or [""])[0][:300]
            log.warning(
                "tracking: sweep summary files not logged (%s: %s)", type(exc).__name__, first
            )

    def _log_summary_files(self, tally: SweepTally, children: Sequence[Any]) -> None:
        """Log ``sweep_summary.md``, ``.csv`` and ``.png`` (:func:`sweeps.write_summary`)."""
        if not children:
            return
        title = f"sweep {self._run_id}: {tally.total} jobs, {tally.failed} failed"
        with tempfile.TemporaryDirectory() as folder:
            for path in sweeps.write_summary(Path(folder), children, title):
                self._client.log_artifact(self._run_id, str(path))

    def _close_at_exit(self) -> None:
        """The sweep died before its end: KILLED by SIGTERM or Ctrl-C, else FAILED."""
        self._close("KILLED" if stopped() else "FAILED")

    def _close(self, status: str) -> None:
        """Terminate the parent run with ``status``, warning if the store is gone."""
        try:
            self._client.set_terminated(self._run_id, status)
        except Exception as exc:
            _warn(exc)
