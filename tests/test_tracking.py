"""MLflow tracking: a live run (RUNNING, FINISHED, FAILED, KILLED) with its code version, a
parallel multirun with a failing job and the sweep's summary, no tracking, no store."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

import spatialseg as package
from spatialseg.settings import Settings
from spatialseg.tracking import SweepCallback, browse_hint, git_commit
from tests.helpers import QUICK_LOOP
from tests.test_cli import spatialseg

FAST = ("window.events=3000", "output.plots=false", *QUICK_LOOP)
REPO = Path(__file__).resolve().parents[1]


def _head() -> str:
    """The checkout's commit, as git itself names it."""
    done = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True
    )
    return done.stdout.strip()


def _expected_commit() -> str | None:
    """The commit a run's tag holds: the checkout's HEAD when the package is imported from
    the checkout (an editable install), none for a wheel installed into a venv (CI's)."""
    from_checkout = Path(package.__file__).resolve().parent == REPO / "spatialseg"
    return _head() if from_checkout else None


def _runs(db: Path) -> list:
    """Every run of the spatialseg experiment in the SQLite store ``db``."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{db}")
    experiment = client.get_experiment_by_name("spatialseg")
    return client.search_runs([experiment.experiment_id])


def test_single_run_is_one_mlflow_run(tmp_path):
    from mlflow.tracking import MlflowClient

    db = tmp_path / "mlflow.db"
    out = tmp_path / "run"
    res = spatialseg(
        "+scene=interior",
        *FAST,
        f"tracking.uri=sqlite:///{db}",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    (run,) = _runs(db)
    assert run.info.status == "FINISHED"
    # stamped when the job started, though a separate process creates it, and closed after
    # the outputs: the run's real duration
    assert f"MLflow: RUNNING run {run.info.run_id}; " in res.stdout
    seconds = (run.info.end_time - run.info.start_time) / 1000
    assert seconds >= json.loads((out / "result.json").read_text())["timings"]["total"]
    assert run.data.tags["spatialseg.version"] == package.__version__
    assert run.data.tags.get("mlflow.source.git.commit") == _expected_commit()
    default = Settings().clustering.evals_per_step
    assert run.data.params["clustering.evals_per_step"] == str(default)
    assert run.data.params["window.events"] == "3000"
    result = json.loads((out / "result.json").read_text())
    windows, metrics = result["windows"], run.data.metrics
    assert len(windows) == 3  # window.count=3: each window's values by its prefix
    # the run's values are the whole run's, not its first window's
    assert metrics["iterations"] == result["iterations"] == sum(w["iterations"] for w in windows)
    contrast = [sum(c["variance"] for c in w["clusters"]) for w in windows]
    assert metrics["variance"] == pytest.approx(sum(contrast))
    assert metrics["converged"] == float(all(w["converged"] for w in windows))
    assert metrics["n_objects"] == result["n_objects"]
    assert metrics["time_cluster"] == pytest.approx(sum(w["timings"]["cluster"] for w in windows))
    assert metrics["accuracy"] == pytest.approx(result["metrics"]["accuracy"])
    client = MlflowClient(f"sqlite:///{db}")
    for i, window in enumerate(windows):
        assert metrics[f"window{i}/iterations"] == window["iterations"]
        assert metrics[f"window{i}/variance"] == pytest.approx(contrast[i])
        for c in window["clusters"]:
            assert metrics[f"window{i}/variance_object{c['id']}"] == pytest.approx(c["variance"])
        history = client.get_metric_history(run.info.run_id, f"window{i}/iter/variance_total")
        assert [m.value for m in history] == pytest.approx(window["history"]["total"])
        assert [m.step for m in history] == list(range(1, len(history) + 1))
        thetas = client.get_metric_history(run.info.run_id, f"window{i}/iter/theta1_z")
        assert len(thetas) == len(history)
    # each window's metrics, its accuracy too, were logged as the window ended
    stamps = [
        client.get_metric_history(run.info.run_id, f"window{i}/variance")[0].timestamp
        for i in range(len(windows))
    ]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(windows)
    for i, window in enumerate(windows):
        assert metrics[f"window{i}/accuracy"] == pytest.approx(window["metrics"]["accuracy"])
    artifacts = {a.path for a in client.list_artifacts(run.info.run_id)}
    assert {"result.json", "labels.npy", "config.yaml"} <= artifacts
    end = res.stdout.strip().splitlines()[-2:]  # the run directory, then how to open the run
    assert end[0].endswith(f"run directory {out}")
    assert end[1].endswith(
        f"MLflow: run {run.info.run_id}; to browse: mlflow ui --backend-store-uri sqlite:///{db}"
    )


def test_parallel_multirun_has_a_parent_and_a_failed_child(tmp_path):
    res = spatialseg(
        "-m",
        "+scene=interior,recording",
        *FAST,
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        f"hydra.sweep.dir={tmp_path / 'sweep'}",
        cwd=tmp_path,
    )
    assert res.returncode == 1, res.stderr
    assert "error: scene=recording needs a path" in res.stderr
    runs = _runs(tmp_path / "mlflow.db")
    (parent,) = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    children = [r for r in runs if r is not parent]
    assert parent.info.status == "FINISHED" and len(children) == 2
    assert {r.data.tags["mlflow.parentRunId"] for r in children} == {parent.info.run_id}
    assert sorted(r.info.status for r in children) == ["FAILED", "FINISHED"]
    failed = next(r for r in children if r.info.status == "FAILED")
    assert "needs a path" in failed.data.tags["error"]
    assert (tmp_path / "sweep" / "0" / "result.json").is_file()
    finished = next(r for r in children if r.info.status == "FINISHED")
    summary = parent.data.metrics
    assert (summary["jobs"], summary["jobs_finished"], summary["jobs_failed"]) == (2, 1, 1)
    accuracy = finished.data.metrics["accuracy"]
    assert summary["accuracy_median"] == summary["accuracy_max"] == pytest.approx(accuracy)
    assert parent.data.tags["best_job"].endswith(f"({finished.info.run_id})")
    assert parent.data.tags.get("mlflow.source.git.commit") == _expected_commit()
    assert f"sweep: 2 jobs, 1 failed; MLflow parent run {parent.info.run_id}; " in res.stdout


def test_tracking_none_creates_no_store(tmp_path):
    out = tmp_path / "run"
    res = spatialseg(
        "+scene=interior", *FAST, "tracking=none", f"hydra.run.dir={out}", cwd=tmp_path
    )
    assert res.returncode == 0, res.stderr
    assert (out / "result.json").is_file()
    assert not (tmp_path / "mlflow.db").exists()


def test_unreachable_store_keeps_the_result(tmp_path):
    out = tmp_path / "run"
    res = spatialseg(
        "+scene=interior",
        *FAST,
        "tracking.uri=http://127.0.0.1:9",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    assert (out / "result.json").is_file() and (out / "labels.npy").is_file()
    lines = (res.stdout + res.stderr).splitlines()
    warnings = [line for line in lines if "WARNING" in line]
    assert len(warnings) == 1 and "tracking" in warnings[0], warnings
    assert "MLflow:" not in res.stdout  # no run to open


@pytest.mark.parametrize(
    ("uri", "hint"),
    [
        ("sqlite:////data/my runs/mlflow.db", "mlflow ui --backend-store-uri 'sqlite:////data/my"),
        ("file:///data/mlruns", "mlflow ui --backend-store-uri file:///data/mlruns"),
        ("http://host:5000", "open http://host:5000"),
    ],
)
def test_browse_hint_names_the_store(uri, hint):
    assert browse_hint(uri, "abc").startswith("run abc; ") and hint in browse_hint(uri, "abc")


SWEEP_DIES = """
import sys
from omegaconf import OmegaConf
from spatialseg.tracking import SweepCallback

cfg = OmegaConf.create({{
    "tracking": {{"enabled": True, "uri": "sqlite:///{db}", "experiment": "spatialseg",
                  "http_retries": 0, "http_timeout": 5}},
    "hydra": {{"runtime": {{"cwd": "{cwd}"}}, "sweep": {{"dir": "{cwd}/sweep"}}}},
}})
SweepCallback().on_multirun_start(cfg)
{death}
"""
#: How the sweep's process dies: an error, or a scheduler's SIGTERM during a job.
DEATHS = {
    "FAILED": 'raise SystemExit("sweep died")',
    "KILLED": (
        "import os, signal, time\n"
        "from spatialseg.interrupts import stop_on_signals\n"
        "with stop_on_signals():\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    time.sleep(30)"
    ),
}


@pytest.mark.parametrize("status", ["FAILED", "KILLED"])
def test_parent_run_is_failed_or_killed_when_the_sweep_dies(tmp_path, status):
    db = tmp_path / "mlflow.db"
    code = SWEEP_DIES.format(db=db, cwd=tmp_path, death=DEATHS[status])
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    if status == "FAILED":
        assert res.returncode == 1 and "sweep died" in res.stderr
    else:
        assert res.returncode == 143 and "terminated by SIGTERM" in res.stderr
    (parent,) = _runs(db)
    assert parent.info.status == status
    assert (tmp_path / "sweep" / "mlflow_parent.json").is_file()


def test_user_error_ends_the_run_failed(tmp_path):
    """A mistake found after the run opened: exit 2 with one line, the run FAILED (not
    missing, not RUNNING) with its params and the error."""
    db = tmp_path / "mlflow.db"
    res = spatialseg(
        "+scene=recording",
        f"tracking.uri=sqlite:///{db}",
        f"hydra.run.dir={tmp_path / 'run'}",
        cwd=tmp_path,
    )
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0, res.stderr
    (run,) = _runs(db)
    assert run.info.status == "FAILED"
    assert "ValueError: scene=recording needs a path" in run.data.tags["error"]
    assert run.data.params["scene.name"] == "recording"
    assert f"MLflow: FAILED run {run.info.run_id}; to browse: mlflow ui" in res.stdout


#: A job whose run opens seconds before its end (twelve windows; three end about a second
#: after the run opens), so that a signal sent once it is RUNNING finds it at work.
LONG_JOB = ("+scene=interior", "window.count=12", "output.plots=false")


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signalled_job_is_running_then_killed(tmp_path, signum):
    """A job is RUNNING in the store, with its params and code version, while it works; a
    SIGTERM (a scheduler's kill) or Ctrl-C ends it KILLED, in one line."""
    from mlflow.tracking import MlflowClient

    db = tmp_path / "mlflow.db"
    args = (*LONG_JOB, f"tracking.uri=sqlite:///{db}")
    command = [sys.executable, "-m", "spatialseg", *args, f"hydra.run.dir={tmp_path / 'run'}"]
    with subprocess.Popen(
        command,
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # not a shell's SIG_IGN
    ) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:  # the run is open; most of the job is ahead
            if "MLflow: RUNNING run " in line:
                break
        run_id = line.split("RUNNING run ")[1].split(";")[0]
        running = MlflowClient(f"sqlite:///{db}").get_run(run_id)
        proc.send_signal(signum)
        stdout, stderr = proc.communicate(timeout=120)
    assert running.info.status == "RUNNING"
    assert running.data.params["window.events"] == "15000"
    assert running.data.tags.get("mlflow.source.git.commit") == _expected_commit()
    assert proc.returncode == 128 + signum, stderr
    how = "terminated" if signum == signal.SIGTERM else "interrupted"
    assert stderr.strip() == f"error: {how} by {signal.Signals(signum).name}"
    (run,) = _runs(db)
    assert run.info.status == "KILLED"
    assert f"MLflow: KILLED run {run_id}; to browse: mlflow ui" in stdout


def test_a_run_stopped_while_it_logged_its_end_still_says_killed(caplog):
    """Ctrl-C while :meth:`LiveRun.finish` waited for the worker's hint leaves that hint
    unread: ending the run KILLED skips it and still says so, with the run's id."""
    from spatialseg.tracking import LiveRun

    class Worker:
        def wait(self, timeout):
            return 0

    run = LiveRun()
    run._worker, run.run_id, run._uri = Worker(), "abc", "sqlite:///mlflow.db"
    run._answers.put(("hint", "mlflow ui"))  # the interrupted finish's answer
    run._answers.put(("ended", True))
    with caplog.at_level("INFO", logger="spatialseg"):
        run.end("KILLED")
    assert [r.getMessage() for r in caplog.records] == [
        "MLflow: KILLED run abc; to browse: mlflow ui --backend-store-uri sqlite:///mlflow.db"
    ]


def test_a_job_killed_outright_leaves_its_run_killed(tmp_path):
    """SIGKILL gives the job no chance to end its run: the tracking process sees the job's
    pipe close and ends the run KILLED, not RUNNING forever."""
    import time

    from mlflow.tracking import MlflowClient

    db = tmp_path / "mlflow.db"
    args = (*LONG_JOB, f"tracking.uri=sqlite:///{db}")
    command = [sys.executable, "-m", "spatialseg", *args, f"hydra.run.dir={tmp_path / 'run'}"]
    with subprocess.Popen(command, cwd=tmp_path, stdout=subprocess.PIPE, text=True) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:
            if "MLflow: RUNNING run " in line:
                break
        run_id = line.split("RUNNING run ")[1].split(";")[0]
        proc.kill()
    client = MlflowClient(f"sqlite:///{db}")
    for _ in range(300):  # the tracking process ends it within a moment
        if client.get_run(run_id).info.status != "RUNNING":
            break
        time.sleep(0.1)
    assert client.get_run(run_id).info.status == "KILLED"


def test_git_commit_is_the_checkouts_head_or_none(tmp_path):
    """The package's commit where git tracks it; none outside a checkout or in a repository
    that does not track the package (a virtualenv inside someone's project)."""
    assert git_commit() == _expected_commit()
    assert git_commit(REPO / "spatialseg") == _head()
    (tmp_path / "__init__.py").write_text("")
    assert git_commit(tmp_path) is None
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    assert git_commit(tmp_path) is None


def _fake_sweep(tmp_path, monkeypatch, jobs: list[tuple[str, float | None]]):
    """A parent run opened by the callback over hand-made jobs ``(overrides, accuracy)``
    (accuracy None: a failed job), each with its outcome file; (callback, cfg, client, id)."""
    from mlflow.tracking import MlflowClient

    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")  # set by the callback
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "5")
    db = tmp_path / "mlflow.db"
    cfg = OmegaConf.create(
        {
            "tracking": {
                "enabled": True,
                "uri": f"sqlite:///{db}",
                "experiment": "spatialseg",
                "http_retries": 0,
                "http_timeout": 5,
            },
            "hydra": {"runtime": {"cwd": str(tmp_path)}, "sweep": {"dir": str(tmp_path / "s")}},
        }
    )
    callback = SweepCallback()
    callback.on_multirun_start(cfg)
    parent = json.loads((tmp_path / "s" / "mlflow_parent.json").read_text())["run_id"]
    client = MlflowClient(f"sqlite:///{db}")
    experiment = client.get_run(parent).info.experiment_id
    folder = tmp_path / "s" / "jobs"
    folder.mkdir()
    for num, (chosen, accuracy) in enumerate(jobs):
        tags = {"mlflow.parentRunId": parent, "spatialseg.overrides": chosen}
        child = client.create_run(experiment, tags=tags, run_name=f"seed={num}").info.run_id
        if accuracy is not None:
            client.log_metric(child, "accuracy", accuracy)
        client.set_terminated(child, "FINISHED" if accuracy is not None else "FAILED")
        (folder / f"{num}.{'ok' if accuracy is not None else 'failed'}").write_text("{}")
    return callback, cfg, client, parent


def test_sweep_parent_holds_the_summary(tmp_path, monkeypatch, capsys):
    """The parent's metrics: jobs, finished, failed, the jobs' accuracy median/min/max; its
    best job named; how to open it printed; the table, CSV and plot of accuracy against the
    swept override (``optimizer``; ``+scene`` is the same in every job) as artifacts."""
    jobs = [
        (f"+scene=interior optimizer={optimizer} seed={num}", accuracy)
        for num, (optimizer, accuracy) in enumerate(
            [("pso", 0.6), ("ssa_ga", 0.9), ("pso", 0.7), ("ssa_ga", None)]
        )
    ]
    callback, cfg, client, parent = _fake_sweep(tmp_path, monkeypatch, jobs)
    callback.on_multirun_end(cfg)
    run = client.get_run(parent)
    assert run.info.status == "FINISHED"
    assert run.data.metrics == pytest.approx(
        {
            "jobs": 4,
            "jobs_finished": 3,
            "jobs_failed": 1,
            "accuracy_median": 0.7,
            "accuracy_min": 0.6,
            "accuracy_max": 0.9,
        }
    )
    assert run.data.tags["best_job"].startswith("seed=1 (")
    assert run.data.tags["spatialseg.version"] == package.__version__
    db = tmp_path / "mlflow.db"
    hint = f"MLflow parent run {parent}; to browse: mlflow ui --backend-store-uri sqlite:///{db}"
    assert capsys.readouterr().out.strip() == f"sweep: 4 jobs, 1 failed; {hint}"

    names = {a.path: a.file_size for a in client.list_artifacts(parent)}
    assert set(names) == {"sweep_summary.md", "sweep_summary.csv", "sweep_summary.png"}
    assert names["sweep_summary.png"] > 0
    table = Path(client.download_artifacts(parent, "sweep_summary.md", str(tmp_path))).read_text()
    # seed varies too: one row per job, each its own group
    assert "| optimizer | seed | runs | finished | failed | accuracy median [IQR] |" in table
    assert "| ssa_ga | 3 | 1 | 0 | 1 | - |" in table


def test_sweep_summary_groups_jobs_by_the_swept_value(tmp_path, monkeypatch):
    """One row per swept value with its run counts; a summary that fails only warns."""
    jobs = [
        ("+scene=interior optimizer=pso", 0.6),
        ("+scene=interior optimizer=ssa_ga", 0.9),
        ("+scene=interior optimizer=pso", 0.7),
        ("+scene=interior optimizer=ssa_ga", None),
    ]
    callback, cfg, client, parent = _fake_sweep(tmp_path, monkeypatch, jobs)
    callback.on_multirun_end(cfg)
    path = client.download_artifacts(parent, "sweep_summary.csv", str(tmp_path))
    with open(path) as f:
        rows = {row["optimizer"]: row for row in csv.DictReader(f)}
    assert set(rows) == {"pso", "ssa_ga"}
    counts = {k: (r["runs"], r["finished"], r["failed"]) for k, r in rows.items()}
    assert counts == {"pso": ("2", "2", "0"), "ssa_ga": ("2", "1", "1")}
    assert float(rows["pso"]["accuracy_median"]) == pytest.approx(0.65)


def test_a_failing_sweep_summary_only_warns(tmp_path, monkeypatch, caplog):
    """No varying override: one ``all`` row; a plot that fails: one warning, parent FINISHED."""
    from spatialseg import sweeps

    def broken(*args, **kwargs):
        raise RuntimeError("no display\nmore")

    monkeypatch.setattr(sweeps, "write_plot", broken)
    jobs = [("+scene=interior", 0.6), ("+scene=interior", 0.8)]
    callback, cfg, client, parent = _fake_sweep(tmp_path, monkeypatch, jobs)
    with caplog.at_level("WARNING", logger="spatialseg"):
        callback.on_multirun_end(cfg)
    assert client.get_run(parent).info.status == "FINISHED"
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        "tracking: sweep summary files not logged (RuntimeError: no display)"
    ]
    assert client.list_artifacts(parent) == []  # written into a folder, logged only if all made


def test_the_tracking_process_stamps_metrics_with_the_jobs_time():
    """A window's metrics carry the moment the job measured them, not the moment the
    tracking process, perhaps still opening the store, got round to sending them."""
    import io

    from spatialseg.tracking_worker import Worker

    class Store:
        def __init__(self):
            self.logged = []

        def log_batch(self, run_id, metrics=()):
            self.logged += [(run_id, m.key, m.value, m.timestamp, m.step) for m in metrics]

    worker = Worker(io.BytesIO())
    worker._client, worker._run_id = Store(), "run"
    measured = 1_000_000  # ms: long before now
    assert worker.handle(("metrics", [("window0/variance", 2.5, 0)], measured))
    assert worker._client.logged == [("run", "window0/variance", 2.5, measured, 0)]


def test_a_job_gone_while_it_is_answered_leaves_its_run_killed(monkeypatch):
    """The job died between sending a request and reading its answer (its pipe closed): the
    tracking process ends the run KILLED, as when the job dies between requests, instead of
    failing on the closed pipe and leaving the run RUNNING."""
    import io
    import pickle

    from spatialseg import tracking_worker

    class Store:
        tracking_uri = "sqlite:///unused.db"

        def __init__(self):
            self.ended = []

        def set_terminated(self, run_id, status):
            self.ended.append((run_id, status))

    class ClosedPipe(io.BytesIO):
        def write(self, data):
            raise BrokenPipeError(32, "Broken pipe")

    store = Store()

    def start(self, job):
        self._client, self._run_id = store, "run"
        self.reply("started", "run", store.tracking_uri)

    monkeypatch.setattr(tracking_worker.Worker, "start", start)
    requests = io.BytesIO(pickle.dumps(("start", {})) + pickle.dumps(("outputs", ".")))
    tracking_worker.serve(requests, ClosedPipe())
    assert store.ended == [("run", "KILLED")]
