"""A bar over a sweep's jobs (a Hydra callback), when they run in this process one by one.

The basic launcher runs the jobs here, so the bar sees each end; other launchers (joblib,
Submitit, Ray) end their jobs in other processes, which log their own lines.
"""

from __future__ import annotations

import contextlib
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from spatialseg.progress import logs_above_bars, shows_bar, terminal_bar

__all__ = ["SweepProgress", "sweep_size"]

IN_PROCESS_LAUNCHER = "hydra._internal.core_plugins.basic_launcher.BasicLauncher"
BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"


def sweep_size(config: DictConfig) -> int | None:
    """How many jobs the basic sweeper will launch for ``config`` (None for another sweeper,
    or when the overrides cannot be counted)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    sweeper = config.hydra.sweeper
    if sweeper.get("_target_") != BASIC_SWEEPER:
        return None
    params = [f"{key}={value}" for key, value in (sweeper.get("params") or {}).items()]
    try:
        overrides = OverridesParser.create().parse_overrides(
            [*params, *config.hydra.overrides.task]
        )
        batches = BasicSweeper.split_arguments(overrides, None)
    except Exception:  # a sweep Hydra itself will refuse, with its own message
        return None
    return sum(len(batch) for batch in batches)


class SweepProgress(Callback):
    """A bar over a sweep's jobs on a terminal, when they run in this process one by one.

    The bar shows while a job runs (its log lines above it) and is cleared between jobs,
    where Hydra's launcher logs the next job's overrides."""

    def __init__(self) -> None:
        self._shown = False
        self._total: int | None = None
        self._bar: Any = None
        self._job_logs = contextlib.ExitStack()

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Decide whether to draw (the basic launcher, on a terminal) and count the jobs."""
        launcher = config.hydra.launcher.get("_target_")
        self._shown = launcher == IN_PROCESS_LAUNCHER and shows_bar()
        self._total = sweep_size(config) if self._shown else None

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Draw the bar; the job's log lines (its logging is set up by now) go above it."""
        if not self._shown:
            return
        if self._bar is None:
            self._bar = terminal_bar(self._total, "job")
        else:
            self._bar.refresh()
        self._job_logs.enter_context(logs_above_bars())

    def on_job_end(self, config: DictConfig, job_return: Any, **kwargs: Any) -> None:
        """Advance the bar by one job, then clear it for the launcher's lines."""
        if self._bar is None:
            return
        self._job_logs.close()
        self._bar.update(1)
        self._bar.clear()

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Close the bar."""
        self._job_logs.close()
        if self._bar is not None:
            self._bar.close()
            self._bar = None
