"""The command line: help works anywhere, user mistakes give one line and exit status 2."""

from __future__ import annotations

from functools import partial

import pytest

from tests.helpers import run_module

spatialseg = partial(run_module, "spatialseg")


def test_help_works_outside_the_checkout(tmp_path):
    res = spatialseg("--help", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "spatialseg" in res.stdout and "optimizer" in res.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((), "no scene selected; add +scene=NAME"),
        (("+scnee=interior",), "unknown config key 'scnee'"),
        (
            ("+scene=interior", "+clustering.tolerance=1"),
            "unknown config key 'clustering.tolerance'",
        ),
        (
            ("+scene=interior", "clustering.max_iteration=3"),
            "unknown config key 'clustering.max_iteration'; did you mean "
            "'clustering.max_iterations'?",
        ),
        (("+scene=interior", "output.figures=false"), "'output' has: h5, plots, progress"),
        (("+scene=interior", "clustering.tol=[1"), "cannot parse an override"),
        (("+scene=recording",), "scene=recording needs a path"),
        (("+scene=interior", "init.tiles.refit=nope"), "init.tiles.refit: unknown optimizer"),
        (("+scene=interior", "seed=abc"), "seed must be an integer >= 0, got 'abc'"),
        (("+scene=interior", "seed=-1"), "seed must be an integer >= 0, got -1"),
    ],
)
def test_user_mistakes_give_one_line(tmp_path, args, message):
    """Without tracking (test_tracking covers a mistake with an MLflow run open)."""
    res = spatialseg(*args, "tracking=none", f"hydra.run.dir={tmp_path / 'out'}", cwd=tmp_path)
    assert res.returncode == 2
    assert message in res.stderr
    assert "Traceback" not in res.stderr
    assert res.stderr.strip().count("\n") == 0


def test_unknown_config_name_lists_the_options(tmp_path):
    res = spatialseg("+scene=interior", "optimizer=nosuch", "tracking=none", cwd=tmp_path)
    assert res.returncode != 0
    assert "Could not find 'optimizer/nosuch'" in res.stderr
    assert "Traceback" not in res.stderr


def test_missing_recording_directory_is_one_line(tmp_path):
    res = spatialseg(
        "+scene=recording",
        f"scene.path={tmp_path / 'nope'}",
        "tracking=none",
        f"hydra.run.dir={tmp_path}",
        cwd=tmp_path,
    )
    assert res.returncode == 2
    assert "nope" in res.stderr and "Traceback" not in res.stderr
