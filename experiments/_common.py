"""Helpers shared by the experiment scripts (``compose_config`` and ``simulated_scenes`` are
:mod:`spatialseg.config`'s, shared with the Python API), write results."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from spatialseg.config import compose_config, simulated_scenes
from spatialseg.events import EventStream

__all__ = [
    "compose_config",
    "median_range",
    "positive_count",
    "simulated_scenes",
    "split_overrides",
    "synthetic_events",
    "write_json",
]


def split_overrides(text: str) -> list[str]:
    """Comma-separated Hydra overrides, split only at commas outside brackets, so a list
    value (``clustering.p_step_sigma=[2,3]``) stays one override."""
    parts, depth, current = [], 0, ""
    for char in text:
        depth += {"[": 1, "]": -1}.get(char, 0)
        if char == "," and depth == 0:
            parts.append(current)
            current = ""
        else:
            current += char
    return [p for p in (*parts, current) if p]


def median_range(values: list[float | None], fmt: str) -> str:
    """Median (min-max) of a metric over seeds, skipping missing values; "-" when none."""
    v = [x for x in values if x is not None]
    if not v:
        return "-"
    return f"{np.median(v):{fmt}} ({min(v):{fmt}}-{max(v):{fmt}})"


def write_json(path: Path, payload: Any) -> None:
    """Write the experiment's results as JSON (creating the directory)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2))


def synthetic_events(n: int, seed: int = 0, width: int = 346, height: int = 260) -> EventStream:
    """``n`` uniformly spread events over 10 s on a sensor (default DAVIS346), at whole
    microseconds as cameras stamp them (so every file format round-trips them exactly)."""
    rng = np.random.default_rng(seed)
    return EventStream(
        rng.integers(0, width, n),
        rng.integers(0, height, n),
        np.sort(rng.integers(0, 10_000_000, n)) / 1e6,
        rng.choice([-1, 1], n),
        width,
        height,
    )


def positive_count(text: str) -> int:
    """An event count such as ``1e6`` or ``250000`` (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (np.isfinite(value) and value >= 1 and value == int(value)):
        raise argparse.ArgumentTypeError(f"need a positive whole number of events, got {text!r}")
    return int(value)
