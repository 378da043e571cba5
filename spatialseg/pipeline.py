"""The recording runner: a recording's windows segmented in order, their objects linked.

A :class:`~spatialseg.recording.Recording` (events, depth maps) in; a
:class:`SegmentationResult` out: an object id (N,) and memberships (N x objects) per event,
each window's :class:`~spatialseg.window.WindowResult`, and a :class:`Handover` that
continues a stream. The stages below it: points, starts, window.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from spatialseg.checks import plural
from spatialseg.compilation import announce_compilation
from spatialseg.executors import map_in_order
from spatialseg.identities import Boundary, boundary, link_clusters
from spatialseg.progress import progress_bar
from spatialseg.recording import Recording, check_depth_maps, check_event_times
from spatialseg.settings import Settings, settings_from
from spatialseg.window import WindowResult, segment_window

__all__ = [
    "ChunkTask",
    "Handover",
    "SegmentationResult",
    "WindowTask",
    "chunk_seed",
    "linked_windows",
    "segment_loaded",
    "segment_recording",
    "segment_stream",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Handover:
    """What a recording's last window hands the next chunk of a stream: its final
    velocities (the ``previous`` start) and its last events with their object ids."""

    velocities: np.ndarray
    boundary: Boundary


@dataclass(frozen=True, eq=False)
class SegmentationResult:
    """All windows of a recording; ``labels`` (object ids, one identity per object across
    the windows; -1 unassigned) and ``probabilities`` (N x objects, column = object id)
    cover every event in order; ``handover`` continues the recording in a next chunk."""

    labels: np.ndarray
    probabilities: np.ndarray
    windows: list[WindowResult] = field(default_factory=list)
    indices: list[np.ndarray] = field(default_factory=list)
    handover: Handover | None = None

    @property
    def n_objects(self) -> int:
        """Object ids in use (0 .. n_objects - 1; a stream's earlier chunks count)."""
        return self.probabilities.shape[1]


def segment_recording(
    recording: Recording,
    settings: Settings | Mapping[str, Any],
    optimizer: Any,
    *,
    seed: int,
    on_iteration: Any = None,
    handover: Handover | None = None,
    progress: bool = True,
    first_window: int | None = None,
    on_window: Callable[[np.ndarray, WindowResult], None] | None = None,
) -> SegmentationResult:
    """Segment every window (each pair of consecutive depth maps); labels cover all events.
    ``settings``: the method's (a mapping is read by :func:`~spatialseg.settings.settings_from`).

    ``progress`` (``output.progress``): an INFO line as each window ends and a DEBUG line
    per iteration (:func:`_window_name` names the window; ``first_window``: in a stream,
    the index of this chunk's first window, as the stream's count is unknown).
    ``on_window(event_indices, result)`` is called as each window ends, its object ids
    linked (a live MLflow run logs it).

    With ``window.context`` = c > 0 each window is clustered together with up to c
    neighbouring windows on each side (EDPA between each event's own pair of maps) and
    keeps the labels of its own events. Decision: a longer span pins the velocities down
    (a moving camera's static scene) while each event is still labelled once, by the span
    centred on its window (docs/method.md, "Context windows"). Each window after the first
    is handed the one before's final velocities (the ``previous`` start of ``init.auto``),
    and its clusters are linked to the objects of the window before
    (:func:`spatialseg.identities.link_clusters`), so an object keeps one id;
    ``handover`` continues a stream's previous chunk (None: a recording's start).
    Events outside every window (before the first or after the last depth map) are -1.
    """
    settings = settings_from(settings)
    windows = _segmented_windows(
        recording.spans(settings.window.context),
        len(recording.depth_maps) - 1,
        settings,
        optimizer,
        seed=seed,
        previous=None if handover is None else handover.velocities,
        on_iteration=on_iteration,
        first_window=first_window,
        progress=progress,
    )
    own = (
        (index, replace(res, labels=res.labels[inner], probabilities=res.probabilities[inner]))
        for index, inner, res in windows
    )
    return linked_windows(recording, own, handover, on_window)


def linked_windows(
    recording: Recording,
    windows: Iterable[tuple[np.ndarray, WindowResult]],
    handover: Handover | None,
    on_window: Callable[[np.ndarray, WindowResult], None] | None = None,
) -> SegmentationResult:
    """A recording's segmented windows, in order (``(event_indices, result)``, the result's
    labels and memberships those of the window's own events), with each window's clusters
    linked to the objects of the window before (``handover``: a stream's previous chunk)
    and ``on_window`` called as each is linked. Why apart: windows segmented on workers are
    linked here afterwards, in order, as the serial run links them."""
    n = len(recording.events)
    labels = np.full(n, -1, dtype=np.int64)
    results, indices = [], []
    previous = None if handover is None else handover.velocities
    edge = None if handover is None else handover.boundary
    next_id = 0 if edge is None else edge.next_id
    xy = np.column_stack([recording.events.x, recording.events.y])
    for index, res in windows:
        previous = res.clustering.thetas
        own = res.labels
        ids, next_id = link_clusters(edge, xy[index], own, res.clustering.thetas.shape[0])
        res = replace(res, ids=ids)
        labels[index] = np.where(own >= 0, ids[np.maximum(own, 0)], -1)
        edge = boundary(xy[index], labels[index], next_id)
        results.append(res)
        indices.append(index)
        if on_window is not None:
            on_window(index, res)
    probabilities = np.zeros((n, max(next_id, 1)), dtype=np.float32)
    for res, index in zip(results, indices, strict=True):
        probabilities[index[:, None], res.ids[None, :]] = res.probabilities
    carry = None if edge is None or previous is None else Handover(previous, edge)
    return SegmentationResult(labels, probabilities, results, indices, carry)


@dataclass(frozen=True)
class WindowTask:
    """One window's work for a worker: :func:`~spatialseg.window.segment_window`'s arguments
    (no previous window's velocities and no per-iteration hook: windows on other workers are
    independent)."""

    span: Recording
    inner: np.ndarray
    settings: Settings
    optimizer: Any
    seed: int


def _run_task(task: WindowTask) -> tuple[WindowResult, float]:
    """The task's window segmented, and the seconds it took (a module-level function, so a
    process pool can pickle it)."""
    start = time.perf_counter()
    result = segment_window(
        task.span, task.settings, task.optimizer, seed=task.seed, inner=task.inner
    )
    return result, time.perf_counter() - start


def _segmented_windows(
    spans: Iterator[tuple[np.ndarray, Recording, np.ndarray]],
    count: int,
    settings: Settings,
    optimizer: Any,
    *,
    seed: int,
    previous: np.ndarray | None,
    on_iteration: Any,
    first_window: int | None,
    progress: bool,
) -> Iterator[tuple[np.ndarray, np.ndarray, WindowResult]]:
    """The ``count`` spans (``(event_indices, span, inner)`` of :meth:`Recording.spans`,
    made one at a time) segmented, in order, each as ``(event_indices, inner, result)``:
    one after the other, each handed the one before's velocities (the ``previous`` start),
    or with ``window.parallel`` on workers that see no other window
    (:mod:`spatialseg.executors`; every span is then made up front). With ``progress``, an
    INFO line as each ends (``first_window`` not None: a stream's chunk, count unknown) and,
    on a terminal, a bar over two windows or more (:mod:`spatialseg.progress`)."""
    engine, workers = settings.window.parallel, settings.window.workers
    seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=max(count, 1))
    total = count if first_window is None else None
    names = [_window_name((first_window or 0) + w, total) for w in range(count)]
    if engine == "none":
        hooks = names if progress else [None] * count  # DEBUG lines per iteration
        done = _serial_windows(spans, settings, optimizer, seeds, previous, on_iteration, hooks)
    else:
        spans = list(spans)
        tasks = [
            WindowTask(span, inner, settings, optimizer, int(s))
            for (_, span, inner), s in zip(spans, seeds, strict=False)
        ]
        runs = map_in_order(_run_task, tasks, engine=engine, workers=workers)
        done = ((window, *run) for window, run in zip(spans, runs, strict=True))
    with progress_bar(count, "window", enabled=progress and total is not None and count > 1) as bar:
        for name, ((index, span, inner), res, seconds) in zip(names, done, strict=True):
            if progress:
                _log_window(name, len(index), len(span.events), res, seconds)
            bar(1)
            yield index, inner, res


def _serial_windows(
    spans: Iterator[tuple[np.ndarray, Recording, np.ndarray]],
    settings: Settings,
    optimizer: Any,
    seeds: np.ndarray,
    previous: np.ndarray | None,
    on_iteration: Any,
    names: list[str | None],
) -> Iterator[tuple[tuple[np.ndarray, Recording, np.ndarray], WindowResult, float]]:
    """The spans segmented here, one after the other, each from the one before's velocities
    too (the ``previous`` start); each span with its result and seconds."""
    for name, window, window_seed in zip(names, spans, seeds, strict=False):
        _, span, inner = window
        start = time.perf_counter()
        res = segment_window(
            span,
            settings,
            optimizer,
            seed=int(window_seed),
            on_iteration=on_iteration,
            previous=previous,
            progress=name,
            inner=inner,
        )
        previous = res.clustering.thetas
        yield window, res, time.perf_counter() - start


def segment_loaded(
    recording: Recording,
    settings: Settings | Mapping[str, Any],
    optimizer: Any,
    *,
    seed: int,
    on_iteration: Any = None,
    handover: Handover | None = None,
    progress: bool = True,
    first_window: int | None = None,
    on_window: Callable[[np.ndarray, WindowResult], None] | None = None,
) -> tuple[Recording, SegmentationResult]:
    """A loaded recording through the ``depth`` source and :func:`segment_recording`
    (``settings``: the method's, a mapping read by :func:`~spatialseg.settings.settings_from`,
    checked before any work; ``handover``: a stream's previous chunk; ``progress``,
    ``first_window``: its progress lines); the result covers every input event. Also
    returns the recording the result describes: the input with the depth maps used.

    Every run (command line, :func:`spatialseg.segment`, experiments) comes through here,
    so the units are checked here, before any work: times in seconds, depths in metres,
    events and depth maps on one clock (:func:`spatialseg.recording.check_depth_maps`).
    A process's first segmentation announces the kernels' compilation on a fresh install
    (:func:`spatialseg.compilation.announce_compilation`)."""
    from spatialseg.depth import with_configured_depth

    settings = settings_from(settings)
    check_event_times(recording)  # before a depth source spends work on the events
    recording = with_configured_depth(recording, settings)
    check_depth_maps(recording)
    with announce_compilation():
        seg = segment_recording(
            recording,
            settings,
            optimizer,
            seed=seed,
            on_iteration=on_iteration,
            handover=handover,
            progress=progress,
            first_window=first_window,
            on_window=on_window,
        )
    return recording, seg


def chunk_seed(seed: int, chunk: int) -> int:
    """The seed of a stream's chunk ``chunk``: drawn from (``seed``, ``chunk``), so each
    chunk's segmentation is the same whichever worker runs it."""
    return int(np.random.default_rng([int(seed), int(chunk)]).integers(2**31 - 1))


@dataclass(frozen=True)
class ChunkTask:
    """One stream chunk's work for a worker: :func:`segment_loaded`'s arguments, without
    the chunk before's handover (chunks on other workers are independent)."""

    chunk: Recording
    settings: Settings
    optimizer: Any
    seed: int


def _segment_chunk(task: ChunkTask) -> tuple[Recording, SegmentationResult]:
    """The task's chunk through its depth source and segmented, its objects numbered from
    0 (a module-level function, so a process pool can pickle it)."""
    return segment_loaded(task.chunk, task.settings, task.optimizer, seed=task.seed, progress=False)


def segment_stream(
    chunks: Iterable[Recording],
    settings: Settings | Mapping[str, Any],
    optimizer: Any,
    *,
    seed: int,
    progress: bool = True,
) -> Iterator[tuple[Recording, SegmentationResult]]:
    """A stream's chunks (recordings without depth maps, in time order) segmented, in order,
    each as (the chunk with the depth maps used, its segmentation, object ids continuing
    the chunks before): one after the other, each chunk handed the one before's
    :class:`Handover`; or with ``window.parallel`` on workers, at most a few chunks ahead
    of the one being handed back (:func:`~spatialseg.executors.map_in_order`), each chunk's
    objects linked here, in order, to the chunk before's. Chunk ``w`` runs with
    :func:`chunk_seed` (``seed``, w) either way."""
    settings = settings_from(settings)
    handover, first = None, 0
    if settings.window.parallel == "none":
        for w, chunk in enumerate(chunks):
            used, seg = segment_loaded(
                chunk,
                settings,
                optimizer,
                seed=chunk_seed(seed, w),
                handover=handover,
                progress=progress,
                first_window=first,
            )
            handover, first = seg.handover or handover, first + len(seg.windows)
            yield used, seg
        return
    here = replace(settings, window=replace(settings.window, parallel="none"))
    tasks = (ChunkTask(c, here, optimizer, chunk_seed(seed, w)) for w, c in enumerate(chunks))
    engine, workers = settings.window.parallel, settings.window.workers
    for used, alone in map_in_order(_segment_chunk, tasks, engine=engine, workers=workers):
        seg = linked_windows(used, zip(alone.indices, alone.windows, strict=True), handover)
        if progress:
            for w, (index, res) in enumerate(zip(seg.indices, seg.windows, strict=True)):
                seconds = sum(res.timings.values())
                _log_window(_window_name(first + w, None), len(index), len(index), res, seconds)
        handover, first = seg.handover or handover, first + len(seg.windows)
        yield used, seg


def _window_name(index: int, count: int | None) -> str:
    """``window 2/3`` (its index as in result.json, of the recording's count), or
    ``window 2`` in a stream, whose count is unknown."""
    return f"window {index}" if count is None else f"window {index}/{count}"


def _log_window(name: str, events: int, span: int, result: WindowResult, seconds: float) -> None:
    """The INFO line as a window ends: its events (``span``: with its context windows'),
    how many the motions were fitted on where a dense window's were sampled, clusters,
    iterations and time."""
    extra = f" ({span} with its context)" if span > events else ""
    if result.prepared.unsampled is not None:
        extra += f", fitted on a sample of {len(result.prepared.points)}"
    log.info(
        "%s: %d events%s, %s, %d iterations, %.1f s",
        name,
        events,
        extra,
        plural(result.clustering.thetas.shape[0], "cluster"),
        result.clustering.iterations,
        seconds,
    )
