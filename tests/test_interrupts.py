"""A stop request hidden behind a clean-up error still ends the run as stopped."""

from __future__ import annotations

import signal
import weakref

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


@pytest.fixture
def python_default_sigint():
    """Python's own SIGINT handler for the test, as a terminal gives the command line: a
    shell starts background jobs with SIGINT ignored, which the job rightly leaves alone."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
@pytest.mark.usefixtures("python_default_sigint")
def test_a_stop_swallowed_by_a_gc_callback_still_stops_the_job(signum, code, capsys):
    """A signal handled while a weakref callback runs (SQLAlchemy's, inside MLflow, seen in a
    test) raises where Python only prints "Exception ignored"; the job still ends stopped,
    and stderr holds the one line, not the printout."""

    class Box:
        pass

    finished = []

    def task(cfg):
        box = Box()
        watch = weakref.ref(box, lambda ref: signal.getsignal(signum)(signum, None))
        del box  # the callback runs here, and the stop it raises is swallowed
        assert watch() is None
        finished.append(True)  # the task went on: the stop was swallowed

    with pytest.raises(SystemExit) as caught:
        guarded(task)(None)
    assert finished and caught.value.code == code
    assert capsys.readouterr().err.count("\n") <= 1
