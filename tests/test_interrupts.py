"""A stop request hidden behind a clean-up error still ends the run as stopped."""

from __future__ import annotations

import pytest

from spatialseg.cli import guarded
from spatialseg.interrupts import interruption


def _stopped_mid_clean_up(stop: BaseException) -> None:
    """A library stopped by ``stop`` whose clean-up then fails (OmegaConf, seen in CI)."""
    try:
        raise stop
    finally:
        raise KeyError("half-way state")  # replaces the stop, as a failed clean-up does


@pytest.mark.parametrize("stop", [SystemExit(143), KeyboardInterrupt()])
def test_the_stop_is_found_behind_the_clean_up_error(stop):
    with pytest.raises(KeyError) as caught:
        _stopped_mid_clean_up(stop)
    assert interruption(caught.value) is stop


def test_an_ordinary_error_is_no_stop():
    try:
        try:
            raise ValueError("first")
        except ValueError as first:
            raise RuntimeError("second") from first
    except RuntimeError as exc:
        assert interruption(exc) is None


def test_a_terminated_job_exits_143_without_a_traceback(capsys):
    with pytest.raises(SystemExit) as caught:
        guarded(lambda cfg: _stopped_mid_clean_up(SystemExit(143)))(None)
    assert caught.value.code == 143
    assert caught.value.__context__ is None or caught.value.__suppress_context__
    assert capsys.readouterr().err == ""  # SIGTERM's handler prints the one line itself


def test_an_interrupted_job_exits_130_in_one_line(capsys):
    with pytest.raises(SystemExit) as caught:
        guarded(lambda cfg: _stopped_mid_clean_up(KeyboardInterrupt()))(None)
    assert caught.value.code == 130
    assert capsys.readouterr().err == "error: interrupted by SIGINT\n"
