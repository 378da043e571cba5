"""The Python API (spatialseg.api): simulate, write, read, segment, MotionSegmenter, and the
one-line ValueError every bad argument raises before any work starts."""

from __future__ import annotations

import copy
import importlib
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sklearn.base import clone

import spatialseg
from spatialseg import api, pipeline
from spatialseg.config import compose_config
from spatialseg.io import write_events
from spatialseg.metrics import recording_metrics
from spatialseg.recording import Recording
from spatialseg.simulate import simulator
from tests.helpers import assert_same_recording

#: Cheap settings for runs that check plumbing, not accuracy.
QUICK = {"init": {"method": "image_flow"}, "clustering.max_iterations": 3}


@pytest.fixture(scope="module")
def recording() -> Recording:
    """The interior scene: 2 windows of 3,000 events, seed 0."""
    return spatialseg.simulate("interior", seed=0, window_events=3000, windows=2)


@pytest.fixture(scope="module")
def segmentation(recording: Recording) -> spatialseg.Segmentation:
    """``recording`` segmented with the default settings, seed 0."""
    return spatialseg.segment(recording, 2, seed=0)


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if segmentation or simulation starts."""

    def fail(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("work started before the arguments were checked")

    monkeypatch.setattr(pipeline, "segment_loaded", fail)
    monkeypatch.setattr(pipeline, "segment_recording", fail)
    monkeypatch.setattr(simulator, "simulate_scene", fail)


def test_api_names_survive_importing_the_simulator_package() -> None:
    """``spatialseg.simulate`` stays the function after its namesake subpackage is imported."""
    importlib.import_module("spatialseg.simulate.families")
    assert spatialseg.simulate is api.simulate
    assert {"segment", "simulate", "read", "write", "MotionSegmenter"} <= set(spatialseg.__all__)


def _loaded_before_and_after(first: str, module: str, then: str) -> list[str]:
    """In a fresh interpreter: whether ``module`` is loaded after the imports ``first``,
    then after the statement ``then`` (the words Python prints, 'True' or 'False')."""
    loaded = f"print({module!r} in sys.modules)"
    code = f"import sys; {first}; {loaded}; {then}; {loaded}"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return done.stdout.split()


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ({}, "PASSIVE"),  # not chosen: the threads sleep while they wait
        ({"OMP_WAIT_POLICY": "active"}, "active"),  # the user's choice is kept
        ({"GOMP_SPINCOUNT": "300000"}, None),  # a spin count chosen: no policy added
    ],
)
def test_the_kernels_threads_wait_asleep_unless_the_environment_chooses(given, expected):
    """``import spatialseg`` sets ``OMP_WAIT_POLICY=PASSIVE`` only where neither it nor
    GNU OpenMP's ``GOMP_SPINCOUNT`` is set, before numba's OpenMP threads start."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    code = "import os, spatialseg; print(os.environ.get('OMP_WAIT_POLICY'))"
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env={**env, **given}
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [str(expected)]


def test_importing_the_package_leaves_the_renderer_unloaded() -> None:
    """``import spatialseg`` (every run, and a run on a recording needs no more) does not
    import the simulator's renderer; its names load on first use."""
    then = "from spatialseg.simulate import simulate_scene; assert callable(simulate_scene)"
    loaded = _loaded_before_and_after("import spatialseg", "spatialseg.simulate.simulator", then)
    assert loaded == ["False", "True"]


def test_the_command_line_and_the_api_leave_scikit_learn_unloaded() -> None:
    """Every module a command-line run imports (the pipeline, the outputs, the figures) and
    the Python API's functions work without scikit-learn, whose import takes about a second;
    only the estimator loads it."""
    first = "import spatialseg.cli, spatialseg.results, spatialseg.plots; spatialseg.segment"
    then = "from spatialseg import MotionSegmenter"
    assert _loaded_before_and_after(first, "sklearn", then) == ["False", "True"]


def test_simulate_write_read_round_trip(recording: Recording, tmp_path: Path) -> None:
    """What simulate makes (the windows asked for), write stores and read gives back:
    events, camera, depth maps, keyframes and ground truth."""
    assert len(recording.events) == 6000 and len(recording.depth_maps) == 3
    assert recording.ground_truth is not None
    back = spatialseg.read(spatialseg.write(recording, tmp_path / "interior"))
    assert_same_recording(recording, back)


def test_segment_labels_probabilities_velocities(
    recording: Recording, segmentation: spatialseg.Segmentation
) -> None:
    """One label per event, nearly always the likeliest object of its probabilities row (the
    label smoothing gives some events their neighbours' object), ids one object across
    windows (accuracy with one matching over the recording > 0.8), and each object's
    whole-run velocity as the summary's."""
    seg, n = segmentation, len(recording.events)
    assert seg.labels.shape == (n,) and seg.probabilities.shape == (n, seg.n_objects)
    assert seg.n_objects == 2 and len(seg.windows) == len(seg.window_indices) == 2
    rows = np.flatnonzero(seg.labels >= 0)
    assert len(rows) > 0.9 * n
    likeliest = seg.probabilities[rows, seg.labels[rows]] == seg.probabilities[rows].max(axis=1)
    assert 0.95 < likeliest.mean() < 1.0  # 137 of 6,000 smoothed at the default
    assert recording.ground_truth is not None
    scores = recording_metrics(seg.labels, recording.ground_truth.labels, seg.window_indices)
    assert scores["accuracy"] > 0.8
    assert seg.units == "m/s" and seg.velocities.shape == (2, 3)
    for obj in seg.summary["objects"]:
        np.testing.assert_allclose(seg.velocities[obj["id"]], obj["velocity"])
    assert seg.timings["total"] >= seg.timings["segment"] > 0


def test_motion_segmenter_fit_equals_segment(recording: Recording) -> None:
    """``MotionSegmenter(...).fit`` is ``segment`` with the same seed and settings; its
    parameters, the settings among them, survive scikit-learn's clone."""
    model = spatialseg.MotionSegmenter(2, seed=3, **QUICK)
    fitted = model.fit(recording)
    np.testing.assert_array_equal(
        fitted.labels, spatialseg.segment(recording, 2, seed=3, **QUICK).labels
    )
    assert model.labels_ is fitted.labels and model.segmentation_ is fitted
    twin = clone(spatialseg.MotionSegmenter(3, seed=1, model="planar", **QUICK))
    params = {"n_clusters": 3, "seed": 1, "optimizer": "ssa_ga", "model": "planar", **QUICK}
    assert twin.get_params() == params


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"clustrng": {"tol": 0.1}}, r"unknown setting 'clustrng'; did you mean 'clustering'\?"),
        (
            {"clustering.max_iteratons": 5},
            r"'clustering\.max_iteratons'; did you mean 'clustering\.max_iterations'\?",
        ),
        ({"n_clusters": 2.5}, r"n_clusters must be an integer or one of 'auto', got 2\.5"),
        ({"clustering": {"max_iterations": "x"}}, r"clustering\.max_iterations must be an int"),
        ({"clustering": {"max_iterations": 0}}, r"clustering\.max_iterations must be an int"),
        ({"optimizer": "nope"}, r"optimizer: unknown optimizer 'nope'; choose from .*ssa_ga"),
        ({"model": "planer"}, r"model: unknown model 'planer'; choose from planar, spatial"),
        ({"depth": {"name": "constant", "value": -1.0}}, r"depth\.value must be a positive"),
    ],
)
def test_bad_settings_raise_before_work(
    recording: Recording, no_work: None, arguments: dict[str, Any], message: str
) -> None:
    """A wrong key, type, value or name is one ValueError naming the setting, before any
    segmentation starts."""
    arguments = dict(arguments)
    n_clusters = arguments.pop("n_clusters", 2)
    with pytest.raises(ValueError, match=message):
        spatialseg.segment(recording, n_clusters, **arguments)


def test_unknown_scene_raises_before_simulating(no_work: None) -> None:
    """An unknown or recorded scene name is refused, listing the simulated scenes."""
    with pytest.raises(ValueError, match=r"scene: 'nope' is unknown; .*interior"):
        spatialseg.simulate("nope")
    with pytest.raises(ValueError, match=r"'road_cars' is a recording: read it"):
        spatialseg.simulate("road_cars")


def test_events_without_depth(recording: Recording, tmp_path: Path) -> None:
    """A bare event file has no depth maps: segment says how to give depth, and with
    ``depth="constant"`` it segments every event."""
    path = tmp_path / "events.npz"
    write_events(recording.events, path)
    events_only = spatialseg.read(path, camera=recording.camera)
    assert not events_only.depth_maps
    with pytest.raises(ValueError, match=r"0 depth map\(s\).*depth='constant'"):
        spatialseg.segment(events_only)
    seg = spatialseg.segment(events_only, depth="constant", window={"events": 3000}, **QUICK)
    assert seg.labels.shape == (len(recording.events),) and len(seg.windows) == 2


def test_a_composed_config_is_the_callers_own() -> None:
    """The config is composed once per set of overrides and handed out as a copy: a caller
    that edits its config (as segment does) leaves the next caller's untouched."""
    first = compose_config("n_clusters=3")
    untouched = copy.deepcopy(first)
    first["clustering"]["max_iterations"] = -1
    first["window"].clear()
    assert compose_config("n_clusters=3") == untouched and untouched["n_clusters"] == 3


def test_nullable_settings_are_those_typed_optional() -> None:
    """The API lets null through for the settings whose type admits it, each a key of the
    composed config, whatever its default; a setting typed without None refuses it."""
    cfg = compose_config()
    for key in api._NULLABLE:
        node = cfg
        for part in key.split("."):
            node = node[part]
    assert {"window.count", "clustering.fit_per_voxel", "clustering.relabel_sigma"} <= api._NULLABLE
    assert api._fits("window.count", None, 3) and api._fits("clustering.label_tol", None, None)
    assert not api._fits("clustering.max_iterations", None, 20)
