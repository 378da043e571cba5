"""experiments/ego_velocity.py on a short window: the static scene's contrast and its peak."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))  # the experiments import _common as a sibling module
import ego_velocity  # noqa: E402

EVENTS = 4000


def test_moving_camera_scenes_are_the_ego_scenes() -> None:
    scenes = ego_velocity.moving_camera_scenes()
    assert {"ego_street", "ego_forward"} <= set(scenes)
    assert "interior" not in scenes and "approach" not in scenes


def test_compensating_the_camera_sharpens_the_static_scene() -> None:
    """At minus the camera's velocity the static events are sharper than unmoved or
    warped the wrong way: the sign convention and the label selection hold."""
    objective, truth, duration = ego_velocity.static_objective("ego_street", 0, EVENTS, [])
    assert np.allclose(truth, [-2.0, 0.0, 0.0]) and 0 < duration < 0.1
    at_truth = objective.value(truth)
    assert at_truth > objective.value(np.zeros(3))
    assert at_truth > objective.value(-truth)


def test_row_reports_the_maximum_and_the_peak() -> None:
    row = ego_velocity.run_one("ego_street", 0, EVENTS, [])
    assert row["contrast_rel"]["1.0"] == 1.0
    assert set(row["contrast_rel"]) == {str(s) for s in ego_velocity.SCALES}
    expected = np.linalg.norm(np.subtract(row["maximum"], row["truth"])) / 2.0
    assert row["maximum_error_rel"] == pytest.approx(expected)
    table = ego_velocity.markdown([row])
    assert table.count("\n") == 2 and f"| ego_street | {EVENTS} |" in table


def test_a_static_camera_scene_is_refused() -> None:
    with pytest.raises(ValueError, match="static camera"):
        ego_velocity.static_objective("interior", 0, 2000, [])
