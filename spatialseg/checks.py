"""Small input checks shared by the config readers, so every key is judged alike; and the
one plural wording the log lines share."""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from typing import Any

import numpy as np

__all__ = [
    "boolean_setting",
    "integer_setting",
    "is_integer",
    "is_number",
    "number_setting",
    "optional_positive",
    "plural",
    "unknown_key",
]


def is_integer(value: Any, minimum: int) -> bool:
    """Whether ``value`` is an integer >= ``minimum``: a Python or NumPy integer, not a bool
    (YAML's ``true`` is an ``int`` to Python, and never a count)."""
    integer = isinstance(value, int | np.integer) and not isinstance(value, bool)
    return integer and bool(value >= minimum)


def is_number(value: Any) -> bool:
    """True for a finite real number (not a bool, which Python counts as an int)."""
    real = isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)
    return real and bool(np.isfinite(value))


def boolean_setting(value: Any, key: str) -> bool:
    """``value`` if it is true or false; else a one-line ValueError that names the setting
    ``key`` (a string such as 'no' or 'off' would read as true)."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"{key} must be true or false, got {value!r}")
    return bool(value)


def optional_positive(value: Any, key: str) -> float | None:
    """``value`` as a positive finite float, None for null; else a one-line ValueError that
    names the setting ``key``."""
    if value is None:
        return None
    if not is_number(value) or not value > 0:
        raise ValueError(f"{key} must be a positive number or null, got {value!r}")
    return float(value)


def integer_setting(
    value: Any, key: str, minimum: int, *, optional: bool = False, hint: str = ""
) -> int | None:
    """``value`` as an int >= ``minimum`` (None for null when ``optional``); else a one-line
    ValueError that names the setting ``key`` (``hint``, e.g. "0: off", in brackets)."""
    if optional and value is None:
        return None
    if not is_integer(value, minimum):
        expected = f"an integer >= {minimum}" + (" or null" if optional else "")
        note = f" ({hint})" if hint else ""
        raise ValueError(f"{key} must be {expected}{note}, got {value!r}")
    return int(value)


def number_setting(
    value: Any, key: str, minimum: float | None = None, *, optional: bool = False, hint: str = ""
) -> float | None:
    """``value`` as a finite float (>= ``minimum`` if given; None for null when ``optional``);
    else a one-line ValueError that names the setting ``key`` (``hint``, e.g. "0: off", in
    brackets)."""
    if optional and value is None:
        return None
    if not is_number(value) or (minimum is not None and not value >= minimum):
        expected = "a number" + ("" if minimum is None else f" >= {minimum:g}")
        expected += " or null" if optional else ""
        note = f" ({hint})" if hint else ""
        raise ValueError(f"{key} must be {expected}{note}, got {value!r}")
    return float(value)


def unknown_key(key: str, known: Iterable[str], kind: str = "config key") -> str:
    """One line for a dotted ``key`` whose last part is not among ``known`` (its section's
    keys), worded alike by every reader: the closest known key if one is close (a typo),
    else all of them."""
    section, dot, leaf = key.rpartition(".")
    names = sorted(str(k) for k in known)
    close = difflib.get_close_matches(leaf, names, n=1)
    if close:
        return f"unknown {kind} '{key}'; did you mean '{section}{dot}{close[0]}'?"
    place = f"'{section}'" if section else "the top level"
    return f"unknown {kind} '{key}'; {place} has: {', '.join(names)}"


def plural(n: int, word: str) -> str:
    """``1 window``, ``3 windows``: a count with its noun, for log lines."""
    return f"{n} {word}" if n == 1 else f"{n} {word}s"
