"""The end-to-end benchmark's pure pieces: its command line, the fused pass's timing, the
targets of issue #27 in the table, the dense-window sensor scaling (no segmentation run)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numba
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

import bench_end_to_end as bench
from _common import compose_config

import spatialseg
from spatialseg.settings import settings_from


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--scenes", "interior", "no_such_scene"], "invalid choice: 'no_such_scene'"),
        (["--events", "0"], "need a positive whole number of events"),
        (["--events", "15000", "1.5e3x"], "not a number"),
        (["--optimizers", "no_such"], "unknown optimizer 'no_such'"),
    ],
)
def test_bad_arguments_end_in_one_error_line(
    flags: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """An unknown scene or optimiser, or a bad size: exit status 2, one line saying why."""
    with pytest.raises(SystemExit) as exc:
        bench.parse_args(flags)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and message in errors[0]
    assert "Traceback" not in err


def test_defaults_cover_the_targets_scenes_and_sizes() -> None:
    """By default: static 2 and 3 motions and a moving camera, at the four sizes of #27."""
    args = bench.parse_args([])
    assert args.events == [15000, 65000, 250000, 1000000]
    assert [bench.scene_motions(s) for s in args.scenes] == [(2, False), (3, False), (2, True)]


def test_scene_motions_come_from_the_scene_files() -> None:
    """Objects, plus the static scene when the camera moves (ego_forward: a person)."""
    assert bench.scene_motions("three") == (3, False)
    assert bench.scene_motions("ego_forward") == (2, True)


def test_sensor_scaling_uses_each_scenes_own_values() -> None:
    """Over --dense-above every threshold key and the refractory period of the scene's own
    sensor are scaled by dense_above / N (night's spread is 0.05, interior's 0.03)."""
    assert bench.sensor_overrides(100000, 100000, "night") == []
    night = bench.sensor_overrides(10**6, 10**5, "night")
    assert night == [
        "scene.sensor.threshold_mean=0.02",
        "scene.sensor.threshold_std=0.005",
        "scene.sensor.threshold_min=0.005",
        "scene.sensor.refractory=1e-05",
    ]
    assert "scene.sensor.threshold_std=0.003" in bench.sensor_overrides(10**6, 10**5)
    assert "scene.sensor.threshold_mean=0.08" in bench.sensor_overrides(250000, 100000, "three")


def test_run_overrides_name_the_optimiser_and_its_extras() -> None:
    """The child's and the pass's config: the recording, K, then the optimiser's overrides."""
    rec = Path("/data/rec")
    assert bench.run_overrides(rec, 3, "default") == [
        "+scene=recording",
        "scene.path=/data/rec",
        "n_clusters=3",
    ]
    tail = bench.run_overrides(rec, 2, "pso:+preset=fast,clustering.p_step_sigma=[2,3]")[3:]
    assert tail == ["optimizer=pso", "+preset=fast", "clustering.p_step_sigma=[2,3]"]


def test_pass_time_is_positive_and_counts_each_event_once() -> None:
    """On a tiny two-window recording the pass takes time, covers at most every event once
    (each window alone, not with its neighbours), every supported one even where the method
    fits a sample, and leaves numba's threads as they were."""
    recording = spatialseg.simulate("interior", seed=0, window_events=1500, windows=2)
    threads = numba.get_num_threads()
    settings = settings_from(compose_config("n_clusters=2"))
    seconds, events = bench.pass_seconds(recording, settings, calls=3)
    assert 0 < seconds < 1
    assert len(recording.events) // 2 < events <= len(recording.events)
    assert numba.get_num_threads() == threads
    # a fit on a sample (clustering.fit_per_voxel) leaves the reference pass over every event
    sampled = settings_from(compose_config("n_clusters=2", "clustering.fit_per_voxel=0.01"))
    assert bench.pass_seconds(recording, sampled, calls=1)[1] == events


def test_stage_seconds_sum_every_stage_over_the_windows() -> None:
    """The segmentation time is every stage of every window in result.json."""
    result = {
        "windows": [
            {"timings": {"prepare": 0.5, "cluster": 1.0}},
            {"timings": {"prepare": 0.25, "cluster": 2.0, "relabel": 0.125}},
        ]
    }
    assert bench.stage_seconds(result) == {"prepare": 0.75, "cluster": 3.0, "relabel": 0.125}


def _result(cluster_s: float) -> dict[str, Any]:
    """A one-window result.json whose segmentation took 0.5 s plus ``cluster_s``."""
    window = {
        "timings": {"prepare": 0.5, "cluster": cluster_s},
        "history": {"n_evals": [30, 30]},
        "iterations": 2,
    }
    return {"timings": {"total": 2.0, "load": 0.25}, "windows": [window]}


def test_the_time_outside_the_segmentation_is_each_tracked_run_s_own() -> None:
    """Outside the segmentation: each tracked run's wall time less its own stages (a run
    with tracking segments at its own speed), the median over the repeats; the stage
    times come from the runs with tracking off."""
    runs = [(3.0, 1, _result(1.0)), (3.5, 1, _result(1.5))]
    tracked = [(4.0, 2, _result(2.0)), (3.0, 2, _result(1.0)), (5.5, 2, _result(3.5))]
    row = bench.summarise_runs(runs, tracked)
    assert row["outside_tracking_s"] == 1.5  # 4 - 2.5, 3 - 1.5, 5.5 - 4
    assert row["segmentation_s"] == 1.75 and row["wall_tracking_median_s"] == 4.0


def _row(**changes: Any) -> dict[str, Any]:
    """A table row as the benchmark builds it, with ``changes``."""
    row = {
        "scene": "interior",
        "events": 250_000,
        "moving_camera": False,
        "optimizer": "default",
        "segmentation_s": 2.0,
        "pass_s": 0.05,
        "passes": 40.0,
        "wall_median_s": 4.0,
        "wall_tracking_median_s": 5.5,
        "outside_tracking_s": 1.6,
        "load_s": 0.1,
        "prepare_s": 0.2,
        "init_s": 0.3,
        "cluster_s": 1.2,
        "stages_s": {
            **{"prepare": 0.2, "init": 0.3, "cluster": 1.2},
            **{"refit": 0.05, "label": 0.05, "smooth": 0.15, "relabel": 0.05},
        },
        "evaluations": 600,
        "iterations": 10,
        "accuracy": 0.99,
        "velocity_error_rel": None,
        "peak_rss_bytes": 400e6,
        "peak_rss_tracking_bytes": 450e6,
        **changes,
    }
    row["targets"] = bench.check_targets(row)
    return row


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        ({}, {"passes": (40.0, True)}),
        ({"passes": 40.5}, {"passes": (40.0, False)}),
        ({"moving_camera": True, "passes": 99.0}, {"passes": (100.0, True)}),
        ({"moving_camera": True, "passes": 101.0}, {"passes": (100.0, False)}),
        ({"events": 249_999, "passes": 500.0}, {}),
        ({"events": 15_000, "segmentation_s": 0.09}, {"window": (0.1, True)}),
        ({"events": 15_000, "segmentation_s": 0.2}, {"window": (0.1, False)}),
        (
            {"events": 65_000, "wall_tracking_median_s": 1.9, "outside_tracking_s": 1.4},
            {"tracking": (2.0, True), "outside": (1.5, True)},
        ),
        (
            {"events": 65_000, "wall_tracking_median_s": 2.1},
            {"tracking": (2.0, False), "outside": (1.5, False)},
        ),
        (
            {"events": 1_000_000, "passes": 30.0, "wall_tracking_median_s": 3.1},
            {"passes": (40.0, True), "tracking": (3.0, False)},
        ),
    ],
)
def test_targets_apply_where_issue_27_sets_them(
    changes: dict[str, Any], expected: dict[str, tuple[float, bool]]
) -> None:
    """Each target's limit and yes/no, only at the sizes and cameras it names."""
    targets = _row(**changes)["targets"]
    assert {name: (t["limit"], t["met"]) for name, t in targets.items()} == expected


def test_the_passes_by_stage_add_up_to_the_rows_passes() -> None:
    """Each stage's seconds over one pass's, the stages the table does not name as one."""
    parts = bench.stage_passes(_row())
    assert len(parts) == len(bench.STAGES) + 1
    assert sum(parts) == pytest.approx(40.0)
    assert parts[-1] == pytest.approx(1.0)  # relabel: 0.05 s over a 0.05 s pass


def test_table_line_states_the_ratio_and_the_targets() -> None:
    """A line has a cell per column: the passes, each target's limit with yes/no or '-'."""
    line = bench.format_row(_row(events=1_000_000, passes=52.4, cluster_s=1.5), 1.2)
    cells = [c.strip() for c in line.strip("|").split("|")]
    column = dict(zip([name for name, _ in bench.COLUMNS], cells, strict=True))
    assert column["events"] == "1,000,000"
    assert column["passes"] == "52"
    assert column["passes target"] == "<= 40: no"
    assert column["15k window target"] == "-"
    assert column["tracking on target"] == "<= 3: no"
    assert column["outside the segmentation, tracking on (s)"] == "1.60"
    assert column["outside target"] == "-"  # set at 65,000 events only
    assert column["clustering vs first"] == "1.25"
    assert column["pass (ms)"] == "50.00"
    assert column["peak RSS off / on (MB)"] == "400 / 450"
    by_stage = column["passes: prepare / starts / loops / refit / label / smoothing / other"]
    assert by_stage == "4 / 6 / 24 / 1 / 1 / 3 / 1"
    assert len(bench.ALIGN.split("|")) == len(bench.HEADER.split("|"))


def test_a_tracked_run_that_missed_mlflow_fails() -> None:
    """A child that fell back to disk only (exit status 0) is an error, not a timing."""
    bench.check_tracked("...\n  MLflow: run 0123abc; to browse: mlflow ui ...\n")
    with pytest.raises(RuntimeError, match=r"tracking failed: .*MLflow unavailable"):
        bench.check_tracked("[WARNING] - tracking: MLflow unavailable, outputs kept on disk\n")
