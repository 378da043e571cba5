"""Helpers shared by the test modules."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from spatialseg.recording import Recording

#: Overrides for a quick clustering (the image-flow start, a 4-iteration loop), for tests
#: about what surrounds the segmentation (tracking, sweeps), not about its result.
QUICK_LOOP = ("init.method=image_flow", "clustering.max_iterations=4")


def run_module(module: str, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run ``python -m MODULE ARGS`` in ``cwd`` the way a user does, capturing its output."""
    return subprocess.run(
        [sys.executable, "-m", module, *args], cwd=cwd, capture_output=True, text=True, timeout=300
    )


def assert_same_recording(a: Recording, b: Recording) -> None:
    """Everything a recording holds is equal (depth NaN-aware, floats bit-exact)."""
    for name in ("t", "x", "y", "p"):
        np.testing.assert_array_equal(getattr(a.events, name), getattr(b.events, name))
    assert a.camera == b.camera
    assert [d.t for d in a.depth_maps] == [d.t for d in b.depth_maps]
    for da, db in zip(a.depth_maps, b.depth_maps, strict=True):
        np.testing.assert_array_equal(da.depth, db.depth)
        assert db.depth.dtype == np.float32
    assert [k.t for k in a.keyframes] == [k.t for k in b.keyframes]
    for ka, kb in zip(a.keyframes, b.keyframes, strict=True):
        np.testing.assert_array_equal(ka.image, kb.image)
        assert kb.image.dtype == np.uint8
    assert (a.ground_truth is None) == (b.ground_truth is None)
    if a.ground_truth is not None and b.ground_truth is not None:
        np.testing.assert_array_equal(a.ground_truth.labels, b.ground_truth.labels)
        assert a.ground_truth.motions.keys() == b.ground_truth.motions.keys()
        for k, v in a.ground_truth.motions.items():
            np.testing.assert_array_equal(v, b.ground_truth.motions[k])
        assert dict(a.ground_truth.names) == dict(b.ground_truth.names)
