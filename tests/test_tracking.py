"""MLflow tracking: a run, a parallel multirun with a failing job, no tracking, no store."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from spatialseg.config import conf_dir
from spatialseg.tracking import browse_hint
from tests.test_cli import spatialseg

FAST = ("window.events=3000", "output.plots=false")


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
    default = OmegaConf.load(conf_dir() / "config.yaml").clustering.evals_per_step
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
raise SystemExit("sweep died")
"""


def test_parent_run_is_failed_when_the_sweep_dies(tmp_path):
    db = tmp_path / "mlflow.db"
    code = SWEEP_DIES.format(db=db, cwd=tmp_path)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 1 and "sweep died" in res.stderr
    (parent,) = _runs(db)
    assert parent.info.status == "FAILED"
    assert (tmp_path / "sweep" / "mlflow_parent.json").is_file()
