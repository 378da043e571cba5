"""The simulator's command line: writes a readable recording, reports mistakes in one line."""

from __future__ import annotations

from functools import partial

import pytest

from spatialseg.io import read_recording
from tests.helpers import run_module

_simulate = partial(run_module, "spatialseg.simulate")


def test_cli_writes_a_recording_with_preview(tmp_path):
    done = _simulate("+scene=interior", "out=rec", "window.events=2000", "seed=1", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("interior: 2000 events over ")
    rec = read_recording(tmp_path / "rec")
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
        (["+scene=interior", "out=x", "seed=abc"], "seed must be an integer >= 0, got 'abc'"),
    ],
)
def test_cli_user_mistake_is_one_error_line_and_exit_2(tmp_path, args, message):
    done = _simulate(*args, cwd=tmp_path)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0]
    assert not (tmp_path / "x").exists()
