"""Stop requests (SIGTERM, Ctrl-C) that end a run as stopped, however the stack unwinds.

While a task runs under :func:`stop_on_signals`, SIGTERM raises :class:`SystemExit` (exit
status 143) and Ctrl-C :class:`KeyboardInterrupt`, so ``finally`` blocks and atomic writes
remove their temporary files. Two ways a stop can go astray are covered:

- raised inside a library's ``try``/``finally``, the stop can leave it half-way so that its
  clean-up raises an ordinary exception instead (OmegaConf, stopped while loading a config,
  raised ``ConfigKeyError``); Python keeps the stop in that exception's ``__context__``, where
  :func:`interruption` finds it;
- raised while a garbage-collector callback runs (SQLAlchemy's, inside MLflow), the stop is
  lost (Python prints it as "Exception ignored"); the handler records it first,
  :func:`raise_pending` raises it again at the next checkpoint (a window's end, a run's end),
  and the printout is silenced so the user sees one line.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["interruption", "raise_pending", "stop_on_signals", "stopped"]

#: The stop a signal handler raised in this process and no checkpoint has re-raised yet.
_pending: BaseException | None = None
#: Whether a stop signal was handled in this process (a sweep's parent run ends KILLED).
_stopped = False


def stopped() -> bool:
    """Whether SIGTERM or Ctrl-C stopped a task in this process."""
    return _stopped


def interruption(exc: BaseException) -> BaseException | None:
    """The SystemExit or KeyboardInterrupt in ``exc``'s chain of causes and contexts (``exc``
    itself included), or None."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, SystemExit | KeyboardInterrupt):
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


def raise_pending() -> None:
    """Raise again a stop that a signal handler raised where it was swallowed (a checkpoint)."""
    global _pending
    stop, _pending = _pending, None
    if stop is not None:
        raise type(stop)(*stop.args)


def _terminate(signum: int, frame: object) -> None:
    """SIGTERM's handler: record the stop and unwind (exit status 128 + 15); a second SIGTERM
    ends the process at once."""
    global _pending, _stopped
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    print(f"error: terminated by {signal.Signals(signum).name}", file=sys.stderr)
    _pending, _stopped = SystemExit(128 + signum), True
    raise SystemExit(128 + signum)


def _interrupt(signum: int, frame: object) -> None:
    """Ctrl-C's handler: record the stop and raise :class:`KeyboardInterrupt`, as Python's does."""
    global _pending, _stopped
    _pending, _stopped = KeyboardInterrupt(), True
    raise KeyboardInterrupt


def _quiet_swallowed_stop(previous: object) -> object:
    """An unraisable-exception hook that drops the recorded stop and passes anything else on."""

    def hook(unraisable: sys.UnraisableHookArgs) -> None:
        if _pending is None or not isinstance(unraisable.exc_value, type(_pending)):
            previous(unraisable)  # type: ignore[operator]

    return hook


@contextmanager
def stop_on_signals() -> Iterator[None]:
    """While the block runs, SIGTERM and Ctrl-C raise recorded stops (see the module).

    Only Python's default handlers are replaced, and only in the main thread: a handler a
    launcher installed (Submitit's) is left alone."""
    global _pending
    _pending = None
    main = threading.current_thread() is threading.main_thread()
    ours = {
        signal.SIGTERM: (signal.SIG_DFL, _terminate),
        signal.SIGINT: (signal.default_int_handler, _interrupt),
    }
    installed = [s for s, (default, _) in ours.items() if main and signal.getsignal(s) is default]
    for signum in installed:
        signal.signal(signum, ours[signum][1])
    previous_hook, sys.unraisablehook = (
        sys.unraisablehook,
        _quiet_swallowed_stop(sys.unraisablehook),
    )
    try:
        yield
    finally:
        for signum in installed:
            signal.signal(signum, ours[signum][0])
        sys.unraisablehook, _pending = previous_hook, None
