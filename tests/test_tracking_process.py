"""The tracking worker started with the command: taken by the first tracked job, stopped by a
job without tracking or by the command's exit."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from collections.abc import Iterator

import pytest
from omegaconf import OmegaConf

from spatialseg import tracking_process
from spatialseg.tracking import LiveRun


@pytest.fixture(autouse=True)
def _no_early_worker_left() -> Iterator[None]:
    """Each test starts without an early worker and leaves none running."""
    tracking_process.stop_early()
    yield
    tracking_process.stop_early()


@pytest.mark.parametrize(
    ("argv", "wanted"),
    [
        ([], True),
        (["+scene=interior", "optimizer=ssa_ga"], True),
        (["tracking.uri=sqlite:///x.db", "-m", "seed=0,1"], True),
        (["+scene=interior", "tracking=none"], False),
        (["tracking.enabled=False"], False),
        (["~tracking"], False),
        (["--help"], False),
        (["--cfg", "job"], False),
        (["-c", "job", "+scene=interior"], False),
    ],
)
def test_tracking_wanted(argv: list[str], wanted: bool) -> None:
    assert tracking_process.tracking_wanted(argv) is wanted


def test_no_worker_when_the_arguments_turn_tracking_off() -> None:
    tracking_process.start_early(["tracking=none"])
    assert tracking_process._early is None


def test_a_job_without_tracking_stops_the_early_worker() -> None:
    tracking_process.start_early([])
    early = tracking_process._early
    assert early is not None and early.poll() is None
    LiveRun().start(OmegaConf.create({"tracking": {"enabled": False}}))
    assert tracking_process._early is None
    assert early.returncode is not None  # killed and reaped


def test_the_first_job_takes_the_early_worker_and_the_next_starts_its_own() -> None:
    tracking_process.start_early([])
    early = tracking_process._early
    taken = tracking_process.take()
    assert taken is early
    second = tracking_process.take()
    try:
        assert second is not early and second.poll() is None
    finally:
        for worker in (taken, second):
            worker.kill()
            worker.wait()


def test_an_early_worker_that_died_is_replaced() -> None:
    tracking_process.start_early([])
    early = tracking_process._early
    assert early is not None
    early.kill()
    early.wait()
    fresh = tracking_process.take()
    try:
        assert fresh is not early and fresh.poll() is None
    finally:
        fresh.kill()
        fresh.wait()


def test_an_untaken_worker_is_stopped_when_the_command_exits() -> None:
    script = textwrap.dedent(
        """
        from spatialseg import tracking_process
        tracking_process.start_early([])
        print(tracking_process._early.pid, flush=True)
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True
    )
    pid = int(done.stdout.split()[0])
    with pytest.raises(ProcessLookupError):  # reaped by the command, so no process is left
        os.kill(pid, 0)


@pytest.mark.skipif(not hasattr(os, "getpriority"), reason="POSIX process priorities")
def test_the_worker_runs_at_the_lowest_priority() -> None:
    """The worker's MLflow work yields the cores to the job's segmentation."""
    import time

    from spatialseg.tracking_worker import NICENESS

    worker = tracking_process.start()
    try:
        deadline = time.monotonic() + 30  # its imports come first
        while os.getpriority(os.PRIO_PROCESS, worker.pid) != NICENESS:
            assert worker.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
    finally:
        worker.kill()
        worker.wait()
