"""A stop request (SIGTERM's SystemExit, Ctrl-C's KeyboardInterrupt) behind another exception.

A signal's exception raised inside a library's ``try``/``finally`` can leave it half-way, so
that its clean-up raises an ordinary exception instead (OmegaConf, stopped while loading a
config, raised ``ConfigKeyError``); Python keeps the stop request in that exception's
``__context__``, where :func:`interruption` finds it, so the run still ends as stopped.
"""

from __future__ import annotations

__all__ = ["interruption"]


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
