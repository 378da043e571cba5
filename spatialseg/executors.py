"""Independent jobs mapped in order, here, over local processes or on Ray.

The recording's windows (or a stream's, as the file is read) are independent work once
identities are linked after the fact (:func:`spatialseg.identities.link_clusters`), so
:func:`map_in_order` runs them on the engine ``window.parallel`` names and hands the
results back in the windows' order:

- ``none``: one after the other in this process;
- ``processes``: a local pool of ``spawn`` processes (a fork would copy numba's thread
  pool mid-state), one numba thread each, so the workers share the cores;
- ``ray``: tasks of one CPU each on the Ray instance ``ray.init()`` finds (``RAY_ADDRESS``,
  a cluster's head) or starts locally, for recordings too long for one machine.
"""

from __future__ import annotations

import multiprocessing
import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from functools import partial
from typing import Any, TypeVar

from spatialseg.checks import integer_setting

__all__ = ["ENGINES", "check_parallel", "map_in_order"]

#: The engines ``window.parallel`` names.
ENGINES = ("none", "processes", "ray")

#: Items submitted per worker ahead of the result being handed back: enough to keep every
#: worker busy while the caller handles a result, few enough to bound the memory.
AHEAD = 2

T = TypeVar("T")
R = TypeVar("R")
F = TypeVar("F")


def check_parallel(engine: Any, workers: Any) -> tuple[str, int | None]:
    """``window.parallel`` and ``window.workers`` (None: one per core, or Ray's CPUs),
    checked; a one-line error naming the setting otherwise."""
    if engine not in ENGINES:
        raise ValueError(f"window.parallel must be one of {ENGINES}, got {engine!r}")
    return str(engine), integer_setting(workers, "window.workers", 1, optional=True)


def _one_thread() -> None:
    """Run each worker's kernels on one thread, so the workers do not oversubscribe cores."""
    import numba

    numba.set_num_threads(1)


def _call_on_one_thread(fn: Callable[[T], R], item: T) -> R:
    """``fn(item)`` on one numba thread (a Ray task holds one CPU)."""
    _one_thread()
    return fn(item)


def _bounded(
    submit: Callable[[T], F], result: Callable[[F], R], items: Iterable[T], ahead: int
) -> Iterator[R]:
    """Each item submitted as it is drawn, at most ``ahead`` waiting at a time, results in
    the items' order. Why: a stream's windows are read while earlier ones run, and only
    ``ahead`` of them are held in memory at once."""
    pending: deque[F] = deque()
    for item in items:
        pending.append(submit(item))
        if len(pending) >= ahead:
            yield result(pending.popleft())
    while pending:
        yield result(pending.popleft())


def _processes(fn: Callable[[T], R], items: Iterable[T], workers: int | None) -> Iterator[R]:
    """``fn`` over ``items`` on a local pool of spawned processes (started as work arrives),
    results in order."""
    count = workers or os.cpu_count() or 1
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(count, mp_context=context, initializer=_one_thread) as pool:
        yield from _bounded(partial(pool.submit, fn), Future.result, items, AHEAD * count)


def _ray(fn: Callable[[T], R], items: Iterable[T], workers: int | None) -> Iterator[R]:
    """``fn`` over ``items`` as Ray tasks of one CPU each, results in order; starts a local
    Ray instance (``workers`` CPUs) unless one is running or ``RAY_ADDRESS`` names one."""
    try:
        import ray
    except ImportError:
        raise ValueError(
            "window.parallel=ray needs Ray; install it with pip install 'spatialseg[ray]'"
        ) from None
    if not ray.is_initialized():
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    task = ray.remote(num_cpus=1)(_call_on_one_thread)
    shared = ray.put(fn)
    cpus = workers or max(int(ray.cluster_resources().get("CPU", 1)), 1)
    yield from _bounded(partial(task.remote, shared), ray.get, items, AHEAD * cpus)


def map_in_order(
    fn: Callable[[T], R], items: Iterable[T], *, engine: str = "none", workers: int | None = None
) -> Iterator[R]:
    """``fn(item)`` for each item, in the items' order, on ``engine`` (:data:`ENGINES`;
    ``fn`` and the items must pickle for any engine but ``none``). The items are drawn as
    the work proceeds, at most :data:`AHEAD` per worker ahead of the result being handed
    back, so an endless iterator (a stream) runs in bounded memory."""
    engine, workers = check_parallel(engine, workers)
    if engine == "none":
        return map(fn, items)
    run = _processes if engine == "processes" else _ray
    return run(fn, items, workers)
