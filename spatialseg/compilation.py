"""The numba kernels' first compilation, announced: a fresh install compiles them on first
use (``cache=True`` keeps them for later runs), tens of seconds without a word otherwise.

Decision: the cache counts as cold when no kernel has a cache index yet (numba's
``<module>.<function>-<line>.pyXY.nbi``, in ``NUMBA_CACHE_DIR`` or next to the module);
inlined helpers and kernels a run never calls have none, so "any index" and not "every
index" tells a used install from a fresh one. The compile time is numba's own
``numba:compile`` events, so the line after it counts compiling, not segmenting.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from numba.core import event
from numba.core.dispatcher import Dispatcher

__all__ = ["announce_compilation", "cache_is_cold", "compile_seconds", "index_paths"]

log = logging.getLogger(__name__)

#: The modules whose ``cache=True`` kernels a segmentation calls.
KERNEL_MODULES = (
    "spatialseg.volume",
    "spatialseg.clustering",
    "spatialseg.objectives",
    "spatialseg.smoothing",
    "spatialseg.denoise",
    "spatialseg.mrf",
)

#: About how long a cold cache takes to compile (seconds; 13 s measured for a run of
#: ``+scene=interior``, whose first window compiles every kernel it calls).
EXPECTED_SECONDS = 15

_announced = {"checked": False}  # one check per process: later runs find the kernels loaded


def index_paths(modules: Iterable[str] = KERNEL_MODULES) -> list[Path]:
    """Where numba keeps (or will keep) the cache index of each kernel of ``modules``."""
    paths = []
    for name in modules:
        for value in vars(importlib.import_module(name)).values():
            cache_file = getattr(getattr(value, "_cache", None), "_cache_file", None)
            if isinstance(value, Dispatcher) and cache_file is not None:
                paths.append(Path(cache_file._index_path))
    return paths


def cache_is_cold(modules: Iterable[str] = KERNEL_MODULES) -> bool:
    """Whether the kernels' first use will compile them: none has a cache index yet."""
    paths = index_paths(modules)
    return bool(paths) and not any(path.exists() for path in paths)


def compile_seconds(records: list[tuple[float, event.Event]]) -> float:
    """The wall time numba spent compiling: its outermost ``numba:compile`` spans, summed
    (a kernel compiles the functions it calls inside its own span)."""
    total, depth, began = 0.0, 0, 0.0
    for stamp, ev in records:
        if ev.is_start:
            depth += 1
            began = stamp if depth == 1 else began
        elif ev.is_end and depth > 0:
            depth -= 1
            total += stamp - began if depth == 0 else 0.0
    return total


@contextmanager
def announce_compilation() -> Iterator[None]:
    """Around a process's first segmentation: with a cold cache, one line before it and
    one with the compile time after it; nothing otherwise."""
    if _announced["checked"]:
        yield
        return
    _announced["checked"] = True
    if not cache_is_cold():
        yield
        return
    log.info("compiling the numba kernels (once per install, about %d s) ...", EXPECTED_SECONDS)
    start = time.perf_counter()
    with event.install_recorder("numba:compile") as recorder:
        yield
    log.info(
        "compiled in %.1f s (of the first segmentation's %.1f s)",
        compile_seconds(recorder.buffer),
        time.perf_counter() - start,
    )
