"""The simulator's command line: writes a readable recording, reports mistakes in one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest


def _simulate(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run ``python -m spatialseg.simulate ARGS`` in ``cwd``."""
    return subprocess.run(
        [sys.executable, "-m", "spatialseg.simulate", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_cli_writes_a_recording_with_preview(tmp_path):
    io = pytest.importorskip("spatialseg.io")
    if not hasattr(io, "read_recording"):
        pytest.skip("spatialseg.io has no reader yet")
    done = _simulate("+scene=interior", "out=rec", "window.events=2000", "seed=1", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("interior: 2000 events over ")
    rec = io.read_recording(tmp_path / "rec")
    assert len(rec.events) == 2000 and len(rec.depth_maps) == 2
    assert set(rec.ground_truth.motions) == {1, 2}
    assert (tmp_path / "rec" / "preview.png").is_file()
    assert (tmp_path / "rec" / "simulate.yaml").is_file()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["+scene=interior", "out=x", "+scene.sensr=1"], "unknown config key 'scene.sensr'"),
        (["+scene=interior"], "no output directory; add out=DIR"),
        (["+scene=interior", "out=x", "window.events=0"], "window.events must be a positive"),
        (["+scene=interior", "out=x", "scene.duration=-1"], "duration must be > 0"),
        (["+scene=recording", "out=x"], "is not simulated"),
    ],
)
def test_cli_user_mistake_is_one_error_line_and_exit_2(tmp_path, args, message):
    done = _simulate(*args, cwd=tmp_path)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0]
    assert not (tmp_path / "x").exists()
