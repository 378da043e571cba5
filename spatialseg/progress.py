"""Progress bars on a terminal: over a run's windows, over a stream, over a sweep's jobs
(:mod:`spatialseg.sweep_progress`).

A bar is drawn only when its stream is a terminal; in a log file (a Slurm job's output, a
pipe) the INFO line each window logs as it ends is the progress. While a bar is drawn, the
console's log lines are printed above it (tqdm's logging redirection), so lines and bar do
not overwrite each other.

Decision: tqdm, the field's usual progress bar (a small pure-Python package), rather than
a bar of our own.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TextIO

__all__ = ["logs_above_bars", "progress_bar", "shows_bar", "terminal_bar"]


def shows_bar(stream: TextIO | None = None) -> bool:
    """Whether a bar would be drawn on ``stream`` (stderr by default): a terminal, not a
    ``TERM=dumb`` one."""
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty()) and os.environ.get("TERM") != "dumb"


def logs_above_bars() -> contextlib.AbstractContextManager[Any]:
    """While the block runs, the console's log lines are printed above the bars."""
    from tqdm.contrib.logging import logging_redirect_tqdm

    return logging_redirect_tqdm(loggers=[logging.getLogger()])


def terminal_bar(total: int | None, unit: str, stream: TextIO | None = None) -> Any:
    """A tqdm bar of ``total`` steps (None: a count) on ``stream`` (stderr by default), every
    step drawn (steps are windows and jobs, seconds apart); cleared when closed."""
    from tqdm import tqdm

    return tqdm(
        total=total,
        unit=unit,
        file=sys.stderr if stream is None else stream,
        leave=False,
        dynamic_ncols=True,
        mininterval=0,
        miniters=1,
    )


@contextmanager
def progress_bar(
    total: int | None, unit: str, *, enabled: bool = True, stream: TextIO | None = None
) -> Iterator[Callable[[int], Any]]:
    """A bar of ``total`` steps (None: a count) over the block, the log lines above it;
    yields its ``update(n)``. With ``enabled`` False, or ``stream`` (stderr by default) not
    a terminal, no bar is drawn and ``update`` does nothing."""
    if not (enabled and shows_bar(stream)):
        yield lambda n=1: None
        return
    with terminal_bar(total, unit, stream) as bar, logs_above_bars():
        yield bar.update
