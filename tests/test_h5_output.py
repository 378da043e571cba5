"""segmentation.h5: a run's events, labels, memberships, objects and settings in one HDF5
file, read back here with plain h5py."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

import spatialseg
from spatialseg.events import EventStream
from spatialseg.io import read_recording
from spatialseg.segmentation_h5 import SegmentationH5
from tests.test_cli import spatialseg as run_cli

#: A small whole-file run of the recording: no MLflow, no figures.
QUIET = ("+scene=recording", "tracking=none", "output.plots=false")

#: A streamed run of the recording (as tests/test_cli_run.py streams it), windows of 1,000.
STREAM = ("scene.stream=true", "scene.fov_deg=60", "depth=constant", "window.events=1000")


def _stale(out: Path) -> None:
    """An earlier run's segmentation.h5 and a temporary of one in the run directory."""
    out.mkdir(parents=True)
    (out / "segmentation.h5").write_bytes(b"earlier")
    (out / ".segmentation.h5.0123456789ab.tmp").write_bytes(b"earlier")


def _read_h5(path: Path) -> dict[str, Any]:
    """Every dataset of ``path`` by its full name, and the root and group attributes."""
    found: dict[str, Any] = {}

    def dataset(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset):
            found.update({name: obj[()], f"{name}.dtype": obj.dtype})

    with h5py.File(path, "r") as f:
        f.visititems(dataset)
        found["attrs"] = dict(f.attrs)
        found["events.attrs"] = dict(f["events"].attrs)
        found["units"] = f["objects/velocity"].attrs["units"]
        found["filters"] = {(d.compression, d.shuffle) for d in (f["events/t"], f["labels"])}
        found["probabilities.filters"] = f["probabilities"].compression
    return found


def _check_h5(out: Path, events: EventStream) -> dict[str, Any]:
    """Assert the run's segmentation.h5 holds ``events`` and what labels.npy,
    probabilities.npy and result.json hold; return its settings attribute, parsed."""
    h5 = _read_h5(out / "segmentation.h5")
    labels, probabilities = np.load(out / "labels.npy"), np.load(out / "probabilities.npy")
    result = json.loads((out / "result.json").read_text())
    for name, dtype in (("t", np.float64), ("x", np.uint16), ("y", np.uint16), ("p", np.int8)):
        np.testing.assert_array_equal(h5[f"events/{name}"], getattr(events, name))
        assert h5[f"events/{name}.dtype"] == dtype
    assert h5["events.attrs"] == {"width": events.width, "height": events.height}
    assert h5["labels.dtype"] == np.int64 and h5["probabilities.dtype"] == np.float32
    np.testing.assert_array_equal(h5["labels"], labels)
    np.testing.assert_array_equal(h5["probabilities"], probabilities)
    n_objects = probabilities.shape[1]
    assert h5["objects/id"].tolist() == list(range(n_objects))
    counts = np.bincount(labels[labels >= 0], minlength=n_objects)
    assert h5["objects/n_events"].tolist() == counts.tolist() and counts.sum() > 0
    assert h5["objects/velocity"].shape == (n_objects, 3) and h5["units"] == result["units"]
    for field in ("velocity", "first_window", "last_window", "n_windows"):
        np.testing.assert_allclose(h5[f"objects/{field}"], [o[field] for o in result["objects"]])
    attrs = h5["attrs"]
    assert attrs["n_events"] == len(events) == len(labels) and attrs["n_objects"] == n_objects
    assert attrs["scene"] == result["scene"]
    assert attrs["spatialseg_version"] == spatialseg.__version__
    assert h5["filters"] == {("gzip", True)} and h5["probabilities.filters"] is None
    assert not [p.name for p in out.glob(".*") if p.name != ".hydra"]
    return json.loads(attrs["settings"])


def test_a_run_writes_segmentation_h5_beside_labels_npy(recording_dir, tmp_path):
    """Into a reused run directory: the earlier file is replaced by this run's."""
    out = tmp_path / "run"
    _stale(out)
    res = run_cli(*QUIET, f"scene.path={recording_dir}", f"hydra.run.dir={out}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    settings = _check_h5(out, read_recording(recording_dir).events)
    assert settings["scene"]["name"] == "recording"
    assert settings["scene"]["path"] == str(recording_dir) and settings["output"]["h5"] is True


def test_a_streamed_run_writes_the_same_layout(recording_dir, tmp_path):
    """scene.stream=true: the events appended window by window, the rest copied at the end."""
    out = tmp_path / "run"
    res = run_cli(
        *QUIET, *STREAM, f"scene.path={recording_dir}", f"hydra.run.dir={out}", cwd=tmp_path
    )
    assert res.returncode == 0, res.stderr
    settings = _check_h5(out, read_recording(recording_dir).events)
    assert settings["scene"]["stream"] is True and settings["window"]["events"] == 1000
    assert json.loads((out / "result.json").read_text())["n_windows"] == 3


def test_output_h5_false_writes_none_and_removes_an_earlier_one(recording_dir, tmp_path):
    """output.h5=false: labels.npy as ever, no segmentation.h5 (an earlier run's goes);
    output.h5=no is refused before any work."""
    out = tmp_path / "run"
    _stale(out)
    args = (*QUIET, *STREAM, f"scene.path={recording_dir}", f"hydra.run.dir={out}")
    res = run_cli(*args, "output.h5=false", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in out.iterdir() if p.name not in (".hydra", "cli.log")) == [
        "labels.npy",
        "probabilities.npy",
        "result.json",
    ]
    bad = run_cli(*args, "output.h5=no", cwd=tmp_path)
    assert bad.returncode == 2 and bad.stderr.strip() == (
        "error: output.h5 must be true or false, got 'no'"
    )


def test_segmentation_h5_left_by_an_error_removes_its_temporary(tmp_path):
    """Events appended, then the run fails: neither the file nor its temporary stays."""
    events = EventStream(np.arange(5), np.zeros(5), np.arange(5) * 1e-3, np.ones(5), 8, 2)
    with pytest.raises(RuntimeError), SegmentationH5(tmp_path / "segmentation.h5") as h5:
        h5.append_events(events)
        h5.append_events(events.select(slice(0, 2)))
        assert h5.rows == 7 and [p.name[:17] for p in tmp_path.iterdir()] == [".segmentation.h5."]
        raise RuntimeError("window 2 failed")
    assert list(tmp_path.iterdir()) == []
