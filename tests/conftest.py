"""Shared fixtures: paths to the repository and to ../shared beside the checkout, and a small
simulated recording on disk."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers import run_module

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture(scope="session")
def repo() -> Path:
    """The repository root."""
    return REPO


@pytest.fixture(scope="session")
def recording_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small interior recording written by the simulator's command line."""
    root = tmp_path_factory.mktemp("rec")
    out = root / "interior"
    done = run_module(
        "spatialseg.simulate",
        "+scene=interior",
        f"out={out}",
        "window.events=3000",
        f"hydra.run.dir={root / 'sim'}",
        cwd=root,
    )
    assert done.returncode == 0, done.stderr
    return out
