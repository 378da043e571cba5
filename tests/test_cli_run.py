"""Full command-line runs: a simulated scene and a recording on disk, with their outputs."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from tests.helpers import run_module
from tests.test_cli import spatialseg


@pytest.fixture(scope="module")
def recording_dir(tmp_path_factory):
    """A small interior recording written by the simulator's command line."""
    root = tmp_path_factory.mktemp("rec")
    out = root / "interior"
    done = run_module(
        "spatialseg.simulate",
        "+scene=interior",
        f"out={out}",
        "window.events=3000",
        f"hydra.run.dir={root / 'sim'}",
        cwd=root,
    )
    assert done.returncode == 0, done.stderr
    return out


def test_simulated_scene_run_writes_all_outputs(tmp_path):
    out = tmp_path / "run"
    res = spatialseg("+scene=interior", "window.events=4000", f"hydra.run.dir={out}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    result = json.loads((out / "result.json").read_text())
    labels = np.load(out / "labels.npy")
    probs = np.load(out / "probabilities.npy")
    assert labels.shape == (4000,) and probs.shape == (4000, 2) and probs.dtype == np.float32
    assert set(np.unique(labels)) <= {-1, 0, 1}
    assert [c["id"] for c in result["clusters"]] == [0, 1]
    assert all(len(c["theta"]) == 3 and np.isfinite(c["variance"]) for c in result["clusters"])
    assert result["metrics"]["accuracy"] > 0.9
    assert {"load", "segment", "total"} <= set(result["timings"])
    for png in ("clusters.png", "warped_volumes.png", "variance.png", "theta.png"):
        assert (out / png).stat().st_size > 1000
    assert "cluster 0" in res.stderr + res.stdout


def test_recording_without_ground_truth(recording_dir, tmp_path):
    plain = tmp_path / "plain"
    shutil.copytree(recording_dir, plain)
    shutil.rmtree(plain / "ground_truth")
    out = tmp_path / "run"
    res = spatialseg(
        "+scene=recording",
        f"scene.path={plain}",
        "n_clusters=2",
        f"hydra.run.dir={out}",
        "output.plots=false",
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    result = json.loads((out / "result.json").read_text())
    assert "metrics" not in result and len(result["clusters"]) == 2
    assert np.load(out / "labels.npy").shape == (3000,)


def test_recording_with_ground_truth_reports_metrics(recording_dir, tmp_path):
    out = tmp_path / "run"
    res = spatialseg(
        "+scene=recording",
        f"scene.path={recording_dir}",
        "model=planar",
        f"hydra.run.dir={out}",
        "output.plots=false",
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["units"] == "px/s" and 0.0 <= result["metrics"]["accuracy"] <= 1.0
