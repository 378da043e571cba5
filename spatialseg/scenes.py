"""Turn a ``scene`` config into a :class:`Recording`: simulate it, or read it from disk."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from spatialseg.recording import Recording

__all__ = ["load_scene"]


def load_scene(scene: Mapping[str, Any], *, seed: int, window_events: int) -> Recording:
    """The recording a scene config describes (``kind: simulated`` or ``kind: recording``)."""
    kind = scene.get("kind")
    if kind == "simulated":
        from spatialseg.simulate import simulate_scene

        return simulate_scene(scene, seed=seed, max_events=window_events)
    if kind == "recording":
        from spatialseg.io import read_recording

        path = scene.get("path")
        if not path:
            raise ValueError("scene=recording needs a path: add scene.path=DIR")
        return read_recording(Path(str(path)).expanduser())
    raise ValueError(f"scene kind {kind!r} is not 'simulated' or 'recording'; fix the scene YAML")
