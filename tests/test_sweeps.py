"""Sweeps at scale: the multirun exit status, the sweep report, the Figures 6-7 command."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import QUICK_LOOP
from tests.test_cli import spatialseg

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))  # the experiments import _common as a sibling module
import paper_figures  # noqa: E402
import sweep_report  # noqa: E402
from _common import split_overrides  # noqa: E402

TINY = ("window.events=2000", "output.plots=false", "output.progress=false", *QUICK_LOOP)


def _client(db: Path):
    from mlflow.tracking import MlflowClient

    return MlflowClient(f"sqlite:///{db}")


def _children(db: Path) -> list:
    """The child runs of the only sweep parent in ``db``."""
    client = _client(db)
    experiment = client.get_experiment_by_name("spatialseg").experiment_id
    return [r for r in client.search_runs([experiment]) if "mlflow.parentRunId" in r.data.tags]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """Four parallel jobs into a fresh store: n_clusters=0 fails (a user error), 2 runs."""
    root = tmp_path_factory.mktemp("sweep")
    res = spatialseg(
        "-m",
        "+scene=interior",
        "n_clusters=0,2",
        "seed=0,1",
        *TINY,
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        f"hydra.sweep.dir={root / 'sweep'}",
        cwd=root,
    )
    return root, res


def test_failed_jobs_make_the_multirun_exit_1(sweep):
    root, res = sweep
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stderr
    last = res.stderr.strip().splitlines()[-1]
    parent = json.loads((root / "sweep" / "mlflow_parent.json").read_text())["run_id"]
    assert last == (
        f"error: 2 of 4 jobs failed; see {root / 'sweep' / 'jobs'}/*.failed; "
        f"MLflow parent run {parent}"
    )
    failed = sorted((root / "sweep" / "jobs").glob("*.failed"))
    assert len(failed) == 2 and len(list((root / "sweep" / "jobs").glob("*.ok"))) == 2
    for path in failed:
        info = json.loads(path.read_text())
        assert "n_clusters=0" in info["overrides"]
        assert info["error"] == (
            "ValueError: n_clusters must be an integer >= 1 "
            "(or auto: the number found per window), got 0"
        )
    run = _client(root / "mlflow.db").get_run(parent)
    assert run.data.tags["jobs_failed"] == "2" and run.data.tags["jobs_total"] == "4"
    assert sorted(r.info.status for r in _children(root / "mlflow.db")) == [
        "FAILED",
        "FAILED",
        "FINISHED",
        "FINISHED",
    ]


def test_tracking_none_counts_failures_and_a_rerun_counts_only_its_own(tmp_path):
    sweep_dir = tmp_path / "sweep"
    common = ("tracking=none", *TINY, f"hydra.sweep.dir={sweep_dir}")
    res = spatialseg("-m", "+scene=interior,recording", *common, cwd=tmp_path)
    assert res.returncode == 1, res.stderr
    assert res.stderr.strip().splitlines()[-1] == (
        f"error: 1 of 2 jobs failed; see {sweep_dir / 'jobs'}/*.failed"
    )
    assert not (tmp_path / "mlflow.db").exists()
    res = spatialseg("-m", "+scene=recording", *common, cwd=tmp_path)
    assert res.returncode == 1
    assert "error: 1 of 1 jobs failed" in res.stderr.strip().splitlines()[-1]


def _report(capsys, *args: str) -> tuple[int, str, str]:
    """Run the report in-process; (exit status, stdout, stderr)."""
    code = 0
    try:
        sweep_report.main(list(args))
    except SystemExit as exc:
        code = int(exc.code or 0)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_report_matches_the_store(sweep, capsys):
    root, _ = sweep
    db = root / "mlflow.db"
    code, out, err = _report(
        capsys, "--tracking-uri", f"sqlite:///{db}", "--by", "n_clusters", "--out-dir", str(root)
    )
    assert code == 0, err
    children = _children(db)
    parent = children[0].data.tags["mlflow.parentRunId"]
    finished = [r for r in children if r.info.status == "FINISHED"]
    rows = {
        line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
        for line in out.splitlines()
        if line.startswith("| ") and not line.startswith("| n_clusters")
    }
    assert rows["0"][:3] == ["2", "0", "2"] and rows["0"][3:] == ["-", "-", "-"]
    assert rows["2"][:3] == ["2", "2", "0"]
    accuracy = [r.data.metrics["accuracy"] for r in finished]
    q1, median, q3 = np.percentile(accuracy, [25, 50, 75])
    assert rows["2"][4] == f"{median:.4g} [{q1:.4g}, {q3:.4g}]"

    with open(root / f"{parent}.csv") as f:
        table = {row["n_clusters"]: row for row in csv.DictReader(f)}
    assert table["0"]["failed"] == "2" and table["0"]["variance_median"] == ""
    for metric in ("variance", "accuracy", "time_total"):
        values = [r.data.metrics[metric] for r in finished]
        assert int(table["2"][f"{metric}_n"]) == 2
        assert float(table["2"][f"{metric}_median"]) == pytest.approx(np.median(values))
        assert float(table["2"][f"{metric}_q1"]) == pytest.approx(np.percentile(values, 25))
    assert (root / f"{parent}.png").stat().st_size > 0

    code, out, _ = _report(capsys, "--tracking-uri", f"sqlite:///{db}", "--out-dir", str(root))
    assert code == 0
    assert "| ssa_ga | interior | 2 | 2 | 2 | 0 |" in out  # the preset's name
    # failed jobs log their params when they start, so they group under their optimiser
    assert "| ssa_ga | interior | 0 | 2 | 0 | 2 | - | - | - |" in out


def test_sweep_parent_holds_the_summary_files(sweep, tmp_path):
    """The parent's ``sweep_summary.md/.csv/.png``: a row per swept n_clusters and seed."""
    root, _ = sweep
    parent = json.loads((root / "sweep" / "mlflow_parent.json").read_text())["run_id"]
    client = _client(root / "mlflow.db")
    sizes = {a.path: a.file_size for a in client.list_artifacts(parent)}
    assert {"sweep_summary.md", "sweep_summary.csv", "sweep_summary.png"} <= set(sizes)
    assert sizes["sweep_summary.png"] > 0
    table = Path(client.download_artifacts(parent, "sweep_summary.md", str(tmp_path))).read_text()
    assert "| n_clusters | seed | runs | finished | failed | accuracy median [IQR] |" in table
    for seed in ("0", "1"):
        assert f"| 0 | {seed} | 1 | 0 | 1 | - |" in table
        assert f"| 2 | {seed} | 1 | 1 | 0 | " in table
    with open(client.download_artifacts(parent, "sweep_summary.csv", str(tmp_path))) as f:
        rows = list(csv.DictReader(f))
    assert [(r["n_clusters"], r["seed"], r["runs"]) for r in rows] == [
        ("0", "0", "1"),
        ("0", "1", "1"),
        ("2", "0", "1"),
        ("2", "1", "1"),
    ]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--experiment", "nope"), "experiment 'nope' not found"),
        (("--by", "no_such_key"), "unknown --by key 'no_such_key'"),
        (("--parent", "0123abc"), "run '0123abc' not found"),
        (("--metrics", "nope"), "no finished run logged nope; final metrics: accuracy,"),
    ],
)
def test_report_user_mistakes_are_one_line(sweep, capsys, args, message):
    root, _ = sweep
    uri = f"sqlite:///{root / 'mlflow.db'}"
    code, _, err = _report(capsys, "--tracking-uri", uri, "--out-dir", str(root), *args)
    assert code == 2
    assert err.startswith("error: ") and message in err and err.count("\n") == 1


def test_report_on_an_empty_or_failed_store(tmp_path, capsys):
    code, _, err = _report(capsys, "--tracking-uri", f"sqlite:///{tmp_path / 'none.db'}")
    assert code == 2 and "no MLflow store at" in err
    assert not (tmp_path / "none.db").exists()

    db = tmp_path / "mlflow.db"
    client = _client(db)
    experiment = client.create_experiment("spatialseg")
    uri = ("--tracking-uri", f"sqlite:///{db}", "--out-dir", str(tmp_path))
    code, _, err = _report(capsys, *uri)
    assert code == 2 and "has no runs" in err
    single = client.create_run(experiment)
    client.set_terminated(single.info.run_id, "FINISHED")
    code, _, err = _report(capsys, *uri)
    assert code == 2 and "only single runs, no sweep" in err
    parent = client.create_run(experiment).info.run_id
    child = client.create_run(experiment, tags={"mlflow.parentRunId": parent}).info.run_id
    client.set_terminated(child, "FAILED")
    code, _, err = _report(capsys, *uri)
    assert code == 2 and f"sweep {parent} has no finished runs (1 of 1 failed" in err


def test_paper_figures_on_a_tiny_budget(tmp_path, monkeypatch, capsys):
    from matplotlib.image import imread

    monkeypatch.chdir(tmp_path)
    paper_figures.main(
        [
            "--events",
            "2000",
            "--out",
            "img",
            "--runs-dir",
            "runs",
            "--set",
            "output.plots=false",
            "output.progress=false",
            "clustering.max_iterations=2",
        ]
    )
    out = capsys.readouterr().out
    for name in ("figure6_exterior.png", "figure7_interior.png"):
        image = imread(tmp_path / "img" / name)
        assert image.shape[0] > 500 and image.shape[1] > 1000
    children = {r.info.run_id: r for r in _children(tmp_path / "mlflow.db")}
    assert len(children) == 2 and all(r.info.status == "FINISHED" for r in children.values())
    for run_id, run in children.items():
        assert f"MLflow run {run_id}" in out
        # window.count=3 windows, each stopped by clustering.max_iterations=2: the run's 6
        assert [run.data.metrics[f"window{i}/iterations"] for i in range(3)] == [2, 2, 2]
        assert run.data.metrics["iterations"] == 6
        artifacts = {a.path for a in _client(tmp_path / "mlflow.db").list_artifacts(run_id)}
        assert {"result.json", "labels.npy"} <= artifacts
        assert artifacts & {"figure6_exterior.png", "figure7_interior.png"}


def test_experiment_overrides_keep_list_values_whole():
    """The experiments' ``model:a=1,b=[2,3]`` overrides split at commas outside brackets."""
    assert split_overrides("a=1,clustering.p_step_sigma=[2,3],+preset=x") == [
        "a=1",
        "clustering.p_step_sigma=[2,3]",
        "+preset=x",
    ]
    assert split_overrides("") == []
    assert split_overrides("x=[1,[2,3]],y=2") == ["x=[1,[2,3]]", "y=2"]
