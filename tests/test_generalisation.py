"""experiments/generalisation.py: seeds per split, modifier flags, rows and the table."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

import generalisation

ROW_KEYS = {
    "family", "seed", "model", "accuracy", "accuracy_per_window", "mean_iou",
    "velocity_error", "unassigned", "time_s", "n_events",
}  # fmt: skip
FAST = "clustering.max_iterations=2,init.method=image_flow,window.context=0"


def test_dev_and_heldout_seeds_never_meet():
    assert generalisation.split_seeds("dev", 3) == [0, 1, 2]
    assert generalisation.split_seeds("heldout", 2) == [1000, 1001]
    with pytest.raises(ValueError, match="the dev split holds seeds 0-999"):
        generalisation.split_seeds("dev", 1001)


def test_fixed_modifiers_are_checked():
    assert generalisation._fixed_modifiers(["depth_flicker=0.1"]) == {"depth_flicker": 0.1}
    with pytest.raises(ValueError, match="unknown modifier; choose from depth_bias"):
        generalisation._fixed_modifiers(["flicker=0.1"])
    with pytest.raises(ValueError, match="'x' is not a number"):
        generalisation._fixed_modifiers(["noise=x"])


def test_a_scene_read_back_from_disk_is_scored_per_model(tmp_path):
    models = [f"spatial:{FAST}", f"planar:{FAST}"]
    rows = generalisation.run_scene(("equal_motion", 1, models, {"noise": 0.1}, tmp_path))
    assert [r["model"] for r in rows] == models
    for row in rows:
        assert set(row) >= ROW_KEYS and row["modifiers"]["noise"] == 0.1
        assert 0 <= row["accuracy"] <= row["accuracy_per_window"] <= 1
        assert row["windows"] == 2 and row["n_motions"] == 2
    assert rows[0]["velocity_error"] is not None and rows[1]["velocity_error"] is None
    assert len(list(tmp_path.iterdir())) == 1  # the cached recording, reused by a rerun
    again = generalisation.run_scene(("equal_motion", 1, models[:1], {"noise": 0.1}, tmp_path))
    assert again[0]["accuracy"] == rows[0]["accuracy"]
    table = generalisation.table(rows + again, models)
    assert "| equal_motion | spatial:" in table and "| 2 |" in table


def test_motions_found_is_the_share_with_as_many_objects_as_motions():
    rows = [
        {"n_motions": 2, "n_clusters_found": 2},
        {"n_motions": 3, "n_clusters_found": 2},
        {"n_motions": 1, "n_clusters_found": 1},
        {"n_motions": 2, "n_clusters_found": 3},
    ]
    assert generalisation.motions_found(rows) == "0.50"
    assert generalisation.motions_found([{"accuracy": 1.0}]) == "-"
