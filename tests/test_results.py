"""result.json's whole-run objects, and which files of a run directory a run owns."""

from __future__ import annotations

import numpy as np
import pytest

from spatialseg.results import ArrayStream, clear_outputs, is_output, objects_summary


def _window(*clusters: tuple[int, int, list[float]]) -> dict:
    """A window summary holding only what objects_summary reads: (id, events, theta)."""
    return {"clusters": [{"id": i, "n_events": n, "theta": v} for i, n, v in clusters]}


def test_objects_are_summed_over_windows_with_event_weighted_velocities():
    windows = [
        _window((0, 300, [1.0, 0.0, 0.0]), (1, 100, [0.0, 2.0, 0.0])),
        _window((1, 300, [0.0, 4.0, 0.0]), (0, 100, [3.0, 0.0, 0.0])),
        _window((2, 50, [0.0, 0.0, 1.0]), (1, 0, [9.0, 9.0, 9.0])),
    ]
    objects = {o["id"]: o for o in objects_summary(windows)}
    assert sorted(objects) == [0, 1, 2]
    assert [objects[i]["n_events"] for i in range(3)] == [400, 400, 50]
    # 300 events at vx = 1 and 100 at vx = 3; an empty cluster weighs nothing
    np.testing.assert_allclose(objects[0]["velocity"], [1.5, 0.0, 0.0])
    np.testing.assert_allclose(objects[1]["velocity"], [0.0, 3.5, 0.0])
    assert (objects[0]["first_window"], objects[0]["last_window"]) == (0, 1)
    assert (objects[1]["first_window"], objects[1]["last_window"], objects[1]["n_windows"]) == (
        0,
        2,
        3,
    )
    assert (objects[2]["first_window"], objects[2]["last_window"]) == (2, 2)


def test_an_object_without_events_gets_the_plain_mean_of_its_velocities():
    windows = [_window((0, 0, [1.0, 0.0, 0.0])), _window((0, 0, [3.0, 2.0, 0.0]))]
    (only,) = objects_summary(windows)
    assert only["n_events"] == 0
    np.testing.assert_allclose(only["velocity"], [2.0, 1.0, 0.0])


@pytest.mark.parametrize(
    ("name", "owned"),
    [
        ("result.json", True),
        ("labels.npy", True),
        ("probabilities.npy", True),
        ("segmentation.h5", True),
        (".segmentation.h5.0123456789ab.tmp", True),
        ("clusters.png", True),
        ("warped_volumes_w12.png", True),
        ("theta_w0.png", True),
        (".labels.npy.raw", True),
        (".result.json.tmp", True),
        (".probabilities.npy.0123456789ab.tmp", True),
        (".clusters_w3.png.0123456789ab.tmp", True),
        ("cli.log", False),  # Hydra's, truncated by the run instead
        ("notes.txt", False),
        ("clusters_final.png", False),
        ("result.json.bak", False),
        (".notes.txt.tmp", False),
        ("my_labels.npy", False),
    ],
)
def test_a_run_owns_its_outputs_and_their_temporaries_only(name, owned):
    assert is_output(name) is owned


def test_clear_outputs_leaves_other_files_and_directories(tmp_path):
    for name in ("result.json", "clusters_w1.png", ".labels.npy.raw", "notes.txt"):
        (tmp_path / name).write_text("old")
    (tmp_path / ".hydra").mkdir()
    (tmp_path / "theta.png").mkdir()  # a directory by an output's name is not a run's
    removed = clear_outputs(tmp_path)
    assert sorted(p.name for p in removed) == [".labels.npy.raw", "clusters_w1.png", "result.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [".hydra", "notes.txt", "theta.png"]
    assert clear_outputs(tmp_path / "missing") == []


def test_an_array_stream_left_by_an_error_removes_its_temporary_file(tmp_path):
    with pytest.raises(RuntimeError), ArrayStream(tmp_path / "labels.npy", np.int64) as stream:
        stream.append(np.arange(5))
        assert (tmp_path / ".labels.npy.raw").is_file()
        raise RuntimeError("window 2 failed")
    assert list(tmp_path.iterdir()) == []
    with ArrayStream(tmp_path / "labels.npy", np.int64) as stream:
        stream.append(np.arange(5))
        stream.finish()
    assert [p.name for p in tmp_path.iterdir()] == ["labels.npy"]
    np.testing.assert_array_equal(np.load(tmp_path / "labels.npy"), np.arange(5))
