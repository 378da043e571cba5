"""Full command-line runs: a simulated scene and a recording on disk, with their outputs."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from spatialseg.results import is_output
from spatialseg.window import PREVIOUS_MARGIN
from tests.test_cli import spatialseg

#: A log line of the final object table: id, events, first-last window, velocity.
OBJECT_ROW = re.compile(r"\]\[spatialseg\]\[INFO\] -\s+(\d+)\s+(\d+)\s+(\d+)-(\d+)\s+\[")


def _stale_run_dir(out: Path) -> None:
    """A run directory an earlier run (killed mid-way) left, with a user's own file."""
    (out / ".hydra").mkdir(parents=True)
    (out / "result.json").write_text('{"scene": "earlier"}')
    for name in ("labels.npy", "clusters_w7.png", ".labels.npy.raw", ".result.json.tmp"):
        (out / name).write_bytes(b"earlier")
    (out / "notes.txt").write_text("mine")
    (out / "cli.log").write_text("STALE LOG LINE\n")


def _object_table(stdout: str) -> dict[int, tuple[int, int, int]]:
    """The final table's rows: object id -> (events, first window, last window)."""
    rows = [tuple(map(int, m.groups())) for m in map(OBJECT_ROW.search, stdout.splitlines()) if m]
    return {obj: (n, first, last) for obj, n, first, last in rows}


def test_simulated_scene_run_writes_all_outputs(tmp_path):
    """Into a reused run directory: every file of the earlier run is replaced or gone."""
    out = tmp_path / "run"
    _stale_run_dir(out)
    args = ("+scene=interior", "window.events=4000", "output.plots=windows")
    res = spatialseg(*args, f"hydra.run.dir={out}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    result = json.loads((out / "result.json").read_text())
    labels = np.load(out / "labels.npy")
    probs = np.load(out / "probabilities.npy")
    # window.count=3: three 4,000-event windows, each clustered with its neighbours
    assert labels.shape == (12000,) and probs.shape == (12000, 2) and probs.dtype == np.float32
    assert len(result["windows"]) == 3
    assert set(np.unique(labels)) <= {-1, 0, 1}
    first = result["windows"][0]["clusters"]
    assert [c["id"] for c in first] == [0, 1]
    assert all(len(c["theta"]) == 3 and np.isfinite(c["variance"]) for c in first)
    for window in result["windows"]:  # every start's total; the highest kept, or the
        totals = window["start_totals"]  # previous start's within the margin of it
        kept, highest = totals[window["init_method"]], max(totals.values())
        assert len(totals) >= 3 and kept * (1 + PREVIOUS_MARGIN) >= highest
        assert kept == highest or window["init_method"] == "previous"
    assert result["metrics"]["accuracy"] > 0.9
    assert {"load", "segment", "total"} <= set(result["timings"])
    for png in ("clusters", "windows", "objects"):  # the summary
        assert (out / f"{png}.png").stat().st_size > 1000
    for w in range(3):  # and every window's own, suffixed
        for png in ("clusters", "warped_volumes", "variance", "theta"):
            assert (out / f"{png}_w{w}.png").stat().st_size > 1000
    # the earlier run's outputs are gone, the user's file and Hydra's config stay
    assert result["scene"] == "interior"
    assert not (out / "clusters_w7.png").exists() and (out / "notes.txt").read_text() == "mine"
    assert not [p.name for p in out.glob(".*") if p.name != ".hydra"]
    assert (out / ".hydra" / "config.yaml").is_file()
    assert "STALE LOG LINE" not in (out / "cli.log").read_text()
    assert "removed 5 outputs of an earlier run" in res.stdout
    assert all(is_output(p.name) for p in out.iterdir() if p.suffix in (".png", ".npy", ".json"))


def test_run_summary_and_result_json_describe_the_whole_run(tmp_path):
    """The final table and result.json's top level count every window's events by object
    id, as labels.npy does; the per-window details are under windows."""
    out = tmp_path / "run"
    res = spatialseg(
        "+scene=interior",
        "window.events=2000",
        "tracking=none",
        "output.plots=false",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    labels = np.load(out / "labels.npy")
    counts = np.bincount(labels[labels >= 0])
    result = json.loads((out / "result.json").read_text())
    windows = result["windows"]
    assert result["n_events"] == labels.size == sum(w["n_events"] for w in windows) == 6000
    assert result["n_objects"] == len(result["objects"]) == len(counts) >= 2
    assert [o["id"] for o in result["objects"]] == list(range(len(counts)))
    assert [o["n_events"] for o in result["objects"]] == counts.tolist()
    assert result["n_labelled"] == int(np.sum(labels >= 0)) == sum(counts)
    assert result["iterations"] == sum(w["iterations"] for w in windows) > windows[0]["iterations"]
    assert result["converged"] == all(w["converged"] for w in windows)
    assert "clusters" not in result  # the clusters are per window
    table = _object_table(res.stdout)
    assert {obj: n for obj, (n, _, _) in table.items()} == {
        i: n for i, n in enumerate(counts.tolist()) if n
    }
    for o in result["objects"]:
        assert table[o["id"]][1:] == (o["first_window"], o["last_window"])
    assert sum(n for n, _, _ in table.values()) == result["n_labelled"]
    end = res.stdout.strip().splitlines()[-1]
    assert end.endswith(f"run directory {out}") and "mlflow ui" not in res.stdout
    assert "weighted by its events" in res.stdout and f"{len(windows)} windows" in res.stdout


def test_a_run_that_fails_early_leaves_no_earlier_outputs(tmp_path):
    """A config mistake found after Hydra wrote the new .hydra/ config: no earlier result
    stays beside it."""
    out = tmp_path / "run"
    _stale_run_dir(out)
    res = spatialseg(
        "+scene=interior",
        "init.tiles.refit=nope",
        "tracking=none",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert res.returncode == 2 and "init.tiles.refit: unknown optimizer" in res.stderr
    assert res.stderr.strip().count("\n") == 0 and "Traceback" not in res.stderr
    assert sorted(p.name for p in out.iterdir()) == [".hydra", "cli.log", "notes.txt"]
    assert "nope" in (out / ".hydra" / "overrides.yaml").read_text()
    assert "STALE LOG LINE" not in (out / "cli.log").read_text()


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
        "tracking=none",
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    result = json.loads((out / "result.json").read_text())
    assert "metrics" not in result and len(result["windows"][0]["clusters"]) == 2
    assert np.load(out / "labels.npy").shape == (3000,)


def test_recording_with_ground_truth_reports_metrics(recording_dir, tmp_path):
    out = tmp_path / "run"
    res = spatialseg(
        "+scene=recording",
        f"scene.path={recording_dir}",
        "model=planar",
        f"hydra.run.dir={out}",
        "output.plots=false",
        "tracking=none",
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
        "hydra.verbose=spatialseg.pipeline",  # the per-start lines are DEBUG
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
    log_text = (out / "cli.log").read_text()
    assert log_text.count(", start previous: total contrast") == len(sizes) - 1
    # one INFO line per streamed window, named by its index (a stream's count is unknown)
    for w, size in enumerate(sizes):
        assert f"[INFO] - window {w}: {size} events, " in log_text
    labels, probabilities = np.load(out / "labels.npy"), np.load(out / "probabilities.npy")
    assert labels.shape == (n,) and probabilities.shape == (n, max(labels.max() + 1, 2))
    known = labels >= 0  # one column per object id, linked across the streamed windows
    agree = np.mean(probabilities[known].argmax(axis=1) == labels[known])
    assert agree > 0.8  # the smoothing relabels some (0.94); a swapped column agrees on few
    ids = {c["id"] for w in result["windows"] for c in w["clusters"]}
    assert ids == set(range(probabilities.shape[1]))
    assert not list(out.glob(".*.raw"))
    bad = spatialseg(*common, "scene.fov_deg=60", f"hydra.run.dir={tmp_path / 'bad'}", cwd=tmp_path)
    assert bad.returncode == 2 and "use depth=constant or depth=ground_plane" in bad.stderr
    assert not (tmp_path / "bad" / "labels.npy").exists()
    nocam = spatialseg(*common, "depth=constant", f"hydra.run.dir={tmp_path / 'c'}", cwd=tmp_path)
    assert nocam.returncode == 2 and "needs the camera" in nocam.stderr


STREAM = ("+scene=recording", "scene.stream=true", "scene.fov_deg=60", "depth=constant")


def test_streamed_run_failing_mid_way_leaves_no_temporary_files(recording_dir, tmp_path):
    """A bad line in the file's third window: the rows of the windows before are dropped."""
    bad = tmp_path / "bad"
    shutil.copytree(recording_dir, bad)
    lines = (bad / "events.txt").read_text().splitlines()
    t, x, _, p = lines[2499].split()
    lines[2499] = f"{t} {x} 400 {p}"  # y outside the 260-row sensor
    (bad / "events.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / "run"
    res = spatialseg(
        *STREAM,
        f"scene.path={bad}",
        "window.events=1000",
        "tracking=none",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert res.returncode == 2 and "events.txt line 2500: y=400" in res.stderr
    assert "window 0: 1000 events" in res.stdout  # it failed after a window was written
    assert sorted(p.name for p in out.iterdir()) == [".hydra", "cli.log"]


def test_streamed_run_reports_its_real_time_factor_and_logs_windows_live(recording_dir, tmp_path):
    """A streamed run ends with the recording's duration, its wall time and their ratio (in
    the log and result.json); each window's metrics reach MLflow as the window ends."""
    from mlflow.tracking import MlflowClient

    from spatialseg.io import read_recording

    db, out = tmp_path / "mlflow.db", tmp_path / "run"
    res = spatialseg(
        *STREAM,
        f"scene.path={recording_dir}",
        "window.events=1000",
        f"tracking.uri=sqlite:///{db}",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    result = json.loads((out / "result.json").read_text())
    timings = result["timings"]
    t = read_recording(recording_dir).events.t
    assert timings["recording_s"] == pytest.approx(t.max() - t.min(), abs=1e-6)  # rounded
    assert timings["real_time_factor"] > 0
    ratio = timings["recording_s"] / timings["total"]
    assert timings["real_time_factor"] == pytest.approx(ratio, rel=1e-3)
    line = re.search(
        r"streamed ([\d.]+) s of recording in ([\d.]+) s: real-time factor ([\d.]+)", res.stdout
    )
    assert line is not None, res.stdout
    logged = [float(v) for v in line.groups()]
    expected = [timings[k] for k in ("recording_s", "total", "real_time_factor")]
    assert logged == pytest.approx(expected, abs=0.006)
    client = MlflowClient(f"sqlite:///{db}")
    (run,) = client.search_runs([client.get_experiment_by_name("spatialseg").experiment_id])
    assert run.data.metrics["real_time_factor"] == pytest.approx(timings["real_time_factor"])
    count = len(result["windows"])
    assert count >= 2
    history = [
        client.get_metric_history(run.info.run_id, f"window{w}/variance") for w in range(count)
    ]
    stamps = [points[0].timestamp for points in history]
    assert stamps == sorted(stamps) and len(set(stamps)) == count  # each as its window ended


def test_killed_streamed_run_leaves_no_temporary_files(recording_dir, tmp_path):
    """SIGTERM mid-way (a job scheduler's kill): exit status 143, no hidden .raw files. Small
    windows, so that ten are still ahead (half a second) when the signal is sent."""
    out = tmp_path / "run"
    args = (*STREAM, f"scene.path={recording_dir}", "window.events=250", "tracking=none")
    command = [sys.executable, "-m", "spatialseg", *args, f"hydra.run.dir={out}"]
    with subprocess.Popen(
        command, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    ) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:  # window 1 ended: window 0's rows are in the temporary files
            if "][INFO] - window 1: 250 events" in line:
                break
        assert (out / ".labels.npy.raw").is_file()
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    assert stderr.strip() == "error: terminated by SIGTERM"
    assert sorted(p.name for p in out.iterdir()) == [".hydra", "cli.log"]


def test_summary_table_names_objects_without_events_apart(caplog, tmp_path):
    """An empty cluster's object (a new id, no events) is named on one line, not a row."""
    from spatialseg.cli import _report
    from spatialseg.results import run_summary

    def window(clusters, converged):
        theta = [1.0, 0.0, 0.0]
        return {
            "clusters": [{"id": i, "n_events": n, "theta": theta} for i, n in clusters],
            "units": "m/s",
            "iterations": 20,
            "converged": converged,
            "stop_reason": "converged" if converged else "iteration limit 20 reached",
        }

    cfg = {"n_clusters": 2, "model": {"name": "spatial"}, "objective": {"name": "variance"}}
    windows = [window([(0, 0), (1, 500)], False), window([(2, 0), (1, 480)], True)]
    summary = run_summary("s", 1000, {**cfg, "optimizer": {}}, windows, {"total": 1.0})
    with caplog.at_level("INFO", logger="spatialseg"):
        _report(summary, tmp_path, None)
    lines = caplog.messages
    assert lines[0].startswith("s: 1000 events in 2 windows, 980 labelled as 1 object; 40 ")
    assert lines[0].endswith("1 of 2 windows converged (window 0: iteration limit 20 reached)")
    assert _object_table("\n".join(f"][spatialseg][INFO] - {m}" for m in lines)) == {1: (980, 0, 1)}
    assert "  no events: object 0, 2 (a window's empty cluster)" in lines


def test_an_unknown_plots_value_is_refused_naming_the_choices(tmp_path):
    """output.plots takes true, false or windows; anything else is one line, exit 2."""
    res = spatialseg(
        "+scene=interior",
        "output.plots=all",
        "tracking=none",
        f"hydra.run.dir={tmp_path}",
        cwd=tmp_path,
    )
    assert res.returncode == 2 and res.stderr.strip() == (
        "error: output.plots must be true or false, got 'all' (or windows: every window's "
        "figures too)"
    )
    assert not (tmp_path / "result.json").exists()


def test_a_scene_with_more_motions_than_n_clusters_is_named_on_one_line(tmp_path):
    """The shipped three-motion scene at the default two clusters: one WARNING says so and
    names the fix; with n_clusters=3 nothing is said."""
    common = (
        "+scene=three",
        "window.events=3000",
        "window.count=1",
        "output.plots=false",
        "tracking=none",
    )
    warned = spatialseg(*common, f"hydra.run.dir={tmp_path / 'two'}", cwd=tmp_path)
    assert warned.returncode == 0, warned.stderr
    lines = [line for line in warned.stdout.splitlines() if "[WARNING]" in line]
    assert len(lines) == 1, warned.stdout
    assert lines[0].endswith(
        "the ground truth has 3 motions but n_clusters=2: set n_clusters=3 (or auto) to "
        "segment each apart"
    )
    quiet = spatialseg(*common, "n_clusters=3", f"hydra.run.dir={tmp_path / 'three'}", cwd=tmp_path)
    assert quiet.returncode == 0, quiet.stderr
    assert "[WARNING]" not in quiet.stdout
