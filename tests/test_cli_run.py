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
    # window.count=3: three 4,000-event windows, each clustered with its neighbours
    assert labels.shape == (12000,) and probs.shape == (12000, 2) and probs.dtype == np.float32
    assert len(result["windows"]) == 3
    assert set(np.unique(labels)) <= {-1, 0, 1}
    assert [c["id"] for c in result["clusters"]] == [0, 1]
    assert all(len(c["theta"]) == 3 and np.isfinite(c["variance"]) for c in result["clusters"])
    assert result["metrics"]["accuracy"] > 0.9
    assert {"load", "segment", "total"} <= set(result["timings"])
    assert (out / "clusters.png").stat().st_size > 1000
    for w in range(3):  # per window, suffixed
        for png in ("clusters", "warped_volumes", "variance", "theta"):
            assert (out / f"{png}_w{w}.png").stat().st_size > 1000
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


def test_denoised_run_labels_every_input_event_in_order(recording_dir, tmp_path):
    """denoise.enabled: the events the filter rejects are left out of the fit, not dropped:
    labels.npy labels them at their input positions, from the fitted motions."""
    from spatialseg.denoise import denoise_mask
    from spatialseg.io import read_recording

    out = tmp_path / "run"
    res = spatialseg(
        "+scene=recording",
        f"scene.path={recording_dir}",
        "denoise.enabled=true",
        "denoise.window=0.002",
        "tracking=none",
        "output.plots=false",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    events = read_recording(recording_dir).events
    labels = np.load(out / "labels.npy")
    assert labels.shape == (len(events),)
    rejected = ~denoise_mask(events, radius=1, window=0.002)
    assert rejected.any() and np.all(labels[rejected] >= 0)
    probabilities = np.load(out / "probabilities.npy")
    np.testing.assert_allclose(probabilities[rejected].sum(axis=1), 1.0, rtol=1e-5)
    assert (labels >= 0).mean() > 0.99


def test_streamed_run_segments_window_by_window(recording_dir, tmp_path):
    """scene.stream=true: windows of window.events read one at a time, each handed the one
    before's velocities; outputs cover all."""
    from spatialseg.io import read_recording

    out = tmp_path / "run"
    common = ("+scene=recording", f"scene.path={recording_dir}", "scene.stream=true")
    res = spatialseg(
        *common,
        "scene.fov_deg=60",
        "depth=constant",
        "window.events=1000",
        "tracking=none",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    n = len(read_recording(recording_dir).events)
    result = json.loads((out / "result.json").read_text())
    assert result["stream"] and result["n_events"] == n
    sizes = [w["n_events"] for w in result["windows"]]
    tail = n % 1000
    expected = [1000] * (n // 1000) + ([tail] if tail else [])
    if 0 < tail < 500:  # a short last chunk joins the window before it
        expected = [*expected[:-2], 1000 + tail]
    assert sizes == expected
    # each window after the first also starts from the velocities the one before ended with
    assert (out / "cli.log").read_text().count("start previous:") == len(sizes) - 1
    labels, probabilities = np.load(out / "labels.npy"), np.load(out / "probabilities.npy")
    assert labels.shape == (n,) and probabilities.shape == (n, max(labels.max() + 1, 2))
    known = labels >= 0  # one column per object id, linked across the streamed windows
    np.testing.assert_array_equal(probabilities[known].argmax(axis=1), labels[known])
    ids = {c["id"] for w in result["windows"] for c in w["clusters"]}
    assert ids == set(range(probabilities.shape[1]))
    assert not list(out.glob(".*.raw"))
    bad = spatialseg(*common, "scene.fov_deg=60", f"hydra.run.dir={tmp_path / 'bad'}", cwd=tmp_path)
    assert bad.returncode == 2 and "use depth=constant or depth=ground_plane" in bad.stderr
    assert not (tmp_path / "bad" / "labels.npy").exists()
    nocam = spatialseg(*common, "depth=constant", f"hydra.run.dir={tmp_path / 'c'}", cwd=tmp_path)
    assert nocam.returncode == 2 and "needs the camera" in nocam.stderr
