"""The tracking worker's process (:mod:`spatialseg.tracking_worker`), started when the command
starts, before its own imports and the config's composition.

The worker spends about two seconds importing MLflow and opening the store before a job's
run exists; started by the job (:class:`spatialseg.tracking.LiveRun`) that time ran past the
end of a short segmentation, which then waited for it. Started from the entry point
(:func:`start_early`), its imports overlap the command's own. The first job with tracking
takes it (:func:`take`); a job without tracking stops it (:func:`stop_early`), as does the
command's exit if no job took it. This module imports nothing of the package, so the entry
point can start the worker at once.
"""

from __future__ import annotations

import atexit
import subprocess
import sys
from collections.abc import Sequence

__all__ = ["start", "start_early", "stop_early", "take", "tracking_wanted"]

#: Command-line arguments after which the command runs no job (Hydra's help, config and
#: completion flags).
NO_JOB_FLAGS = frozenset(
    ("--help", "-h", "--hydra-help", "--cfg", "-c", "--info", "-i", "--shell-completion", "-sc")
)
#: Overrides that turn tracking off.
TRACKING_OFF = frozenset(("tracking=none", "~tracking", "tracking.enabled=false"))

_early: subprocess.Popen | None = None


def start() -> subprocess.Popen:
    """A new worker process, its requests on stdin and answers on stdout (OSError if it
    cannot start)."""
    command = [sys.executable, "-m", "spatialseg.tracking_worker"]
    return subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE)


def tracking_wanted(argv: Sequence[str]) -> bool:
    """Whether a command with these arguments may run a tracked job: not when it asks for
    help or a config, nor when an override turns tracking off. A config that turns it off
    otherwise is seen only once composed (the job then stops the worker)."""
    return not any(arg in NO_JOB_FLAGS or arg.lower() in TRACKING_OFF for arg in argv)


def start_early(argv: Sequence[str]) -> None:
    """Start a worker now for the command's first tracked job, if ``argv`` may run one;
    stopped at exit if no job takes it. A worker that cannot start is left to the job,
    which starts its own and warns."""
    global _early
    if _early is not None or not tracking_wanted(argv):
        return
    try:
        _early = start()
    except OSError:
        return
    atexit.register(stop_early)


def take() -> subprocess.Popen:
    """The worker started early if it still runs, else a new one (OSError if it cannot
    start)."""
    global _early
    early, _early = _early, None
    if early is not None and early.poll() is None:
        return early
    _stop(early)
    return start()


def stop_early() -> None:
    """Stop the worker started early if no job took it: it holds no run yet."""
    global _early
    early, _early = _early, None
    _stop(early)


def _stop(worker: subprocess.Popen | None) -> None:
    """Kill ``worker`` (it ignores SIGINT and SIGTERM, which are the job's), reap it, close
    its pipes."""
    if worker is None:
        return
    worker.kill()
    worker.wait()
    for pipe in (worker.stdin, worker.stdout):
        if pipe is not None:
            pipe.close()
