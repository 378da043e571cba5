"""Small input checks shared by the config readers, so every key is judged alike."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["is_integer"]


def is_integer(value: Any, minimum: int) -> bool:
    """Whether ``value`` is an integer >= ``minimum``: a Python or NumPy integer, not a bool
    (YAML's ``true`` is an ``int`` to Python, and never a count)."""
    integer = isinstance(value, int | np.integer) and not isinstance(value, bool)
    return integer and bool(value >= minimum)
