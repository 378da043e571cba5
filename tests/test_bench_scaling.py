"""Smoke tests of the scaling, end-to-end and window benchmarks' helpers (no timing asserted)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

import bench_end_to_end
import bench_scaling
import bench_window


def test_events_are_deterministic_and_fill_a_sensor_sized_grid() -> None:
    """Same seed, same events; the image grid spans about the 346 x 260 sensor in 2-px voxels."""
    a = bench_scaling.make_events(2000, seed=3)
    b = bench_scaling.make_events(2000, seed=3)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    grid = bench_scaling.build_grid(a[0], "image")
    assert 150 < grid.shape[0] < 230 and 110 < grid.shape[1] < 180
    assert bench_scaling.build_grid(a[0], "metric").projection is None


def test_time_point_matches_the_reference() -> None:
    """A tiny run times both dtypes and agrees with the numpy reference."""
    args = bench_scaling.parse_args(["--sizes", "300", "--repeats", "1", "--batch", "2"])
    rows = bench_scaling.time_point(300, "image", args)
    assert [r["impl"] for r in rows] == ["numpy", "kernel", "kernel"]
    assert rows[1]["vg_rel_error"] < 1e-9 and rows[2]["vg_rel_error"] < 1e-3


@pytest.mark.parametrize("flag", [["--sizes", "0"], ["--sizes", "1e4", "--max-events", "10"]])
def test_bad_flags_are_one_line_errors(flag: list[str]) -> None:
    """Bad sizes are rejected by argparse (exit status 2)."""
    with pytest.raises(SystemExit) as exc:
        bench_scaling.parse_args(flag)
    assert exc.value.code == 2


def test_end_to_end_rejects_unknown_optimizers_and_scales_dense_windows() -> None:
    """Unknown optimiser names exit 2; windows over --dense-above get a lower threshold."""
    with pytest.raises(SystemExit):
        bench_end_to_end.parse_args(["--optimizers", "ssa_ga", "no_such"])
    with pytest.raises(SystemExit):
        bench_end_to_end.parse_args(["--optimizers", "no_such:+preset=fast"])
    ok = bench_end_to_end.parse_args(["--optimizers", "default", "default:+preset=fast"])
    assert ok.optimizers == ["default", "default:+preset=fast"]
    assert bench_end_to_end.sensor_overrides(100000, 100000) == []
    assert "scene.sensor.threshold_mean=0.02" in bench_end_to_end.sensor_overrides(10**6, 10**5)


def test_window_benchmark_times_a_config_and_reports_its_run() -> None:
    config = "+preset=fast,volume.depth_error=0"  # interior's depth is exact: 0.56 with the floor
    row = bench_window.time_config("interior", 2000, config, 1)
    assert row["config"] == config and row["events"] == 2000
    assert row["cold_s"] > 0 and row["warm_s"] > 0
    assert row["accuracy"] > 0.8  # both carts found (0.89 measured; one cluster scores ~0.5)
    assert 1 <= row["iterations"] <= 20 and row["evaluations"] > 0


def test_window_benchmark_configs_are_checked_before_any_timing() -> None:
    """A config may join ``default`` with overrides; a bad override exits 2 at the start."""
    assert bench_window.config_overrides("default,+preset=fast") == ["+preset=fast"]
    assert bench_window.config_overrides("default") == []
    ok = bench_window.parse_args(["--configs", "default,+preset=fast", "default"])
    assert ok.configs == ["default,+preset=fast", "default"]
    for bad in ("clustering.no_such_key=1", "+preset=no_such"):
        with pytest.raises(SystemExit) as exc:
            bench_window.parse_args(["--configs", "default", bad])
        assert exc.value.code == 2
