"""A recording: events plus what the method needs around them (camera, depth, keyframes).

The types here are what readers return, what the simulator produces and what the method
consumes. Construction validates consistency (depth maps match the sensor, sorted times,
one ground-truth label per event) and raises ``ValueError`` naming the problem;
:func:`check_event_times` and :func:`check_depth_maps` check units (seconds, metres) and
that both clocks agree, before segmentation.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from spatialseg.checks import is_integer
from spatialseg.events import EventStream

__all__ = [
    "MAX_MEDIAN_DEPTH",
    "MAX_SPAN",
    "MILLIMETRES_FIX",
    "Camera",
    "DepthMap",
    "GroundTruth",
    "Keyframe",
    "Recording",
    "check_depth_maps",
    "check_depth_units",
    "check_event_times",
    "check_time_units",
    "check_window_context",
    "event_boundaries",
    "is_short_tail",
]

log = logging.getLogger(__name__)

#: Longest plausible span of times, in seconds (over a day): no event recording is that long,
#: so a longer span is microseconds or nanoseconds read as seconds.
MAX_SPAN = 1e5
#: A span over this many "seconds" is over a day even in microseconds: nanoseconds.
_NANOSECONDS_SPAN = 1e11
#: Median known depth (m) above which a depth map is taken for millimetres: an event camera's
#: scene is within tens of metres (a street's median is ~10 m), and a scene in millimetres
#: has a median over 200 unless it is all nearer than 0.2 m.
MAX_MEDIAN_DEPTH = 200.0
#: The fix for depths stored in millimetres, shared by every check that suspects them.
MILLIMETRES_FIX = "depths look like millimetres; divide by 1000 (spatialseg depths are metres)"


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels and the sensor size: ``u = fx X / Z + cx``."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in values) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(
                f"camera intrinsics fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}: "
                "focal lengths must be positive and all values finite"
            )
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera size {self.width}x{self.height} must be positive")

    @property
    def intrinsics(self) -> np.ndarray:
        """``[fx, fy, cx, cy]``, as :func:`spatialseg.grid.project_jacobian` and the image
        grid's projection take them."""
        return np.array([self.fx, self.fy, self.cx, self.cy])


@dataclass(frozen=True, eq=False)
class DepthMap:
    """Per-pixel depth in metres at time ``t`` (float32, H x W); NaN or <= 0 means unknown."""

    t: float
    depth: np.ndarray
    source: str = field(default="<memory>", compare=False)

    def __post_init__(self) -> None:
        d = np.asarray(self.depth)
        if d.ndim != 2:
            raise ValueError(f"{self.source}: depth map must be 2-D (H x W), got shape {d.shape}")
        object.__setattr__(self, "depth", np.ascontiguousarray(d, dtype=np.float32))
        object.__setattr__(self, "t", float(self.t))
        if not np.isfinite(self.t):
            raise ValueError(f"{self.source}: depth map time {self.t} is not finite")


@dataclass(frozen=True, eq=False)
class Keyframe:
    """A grayscale (H x W) or colour (H x W x 3) uint8 image at time ``t``."""

    t: float
    image: np.ndarray
    source: str = field(default="<memory>", compare=False)


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Evaluation-only truth: an object id per event (-1 for noise) and each object's velocity.

    ``motions`` maps object id to its 3-D velocity (vx, vy, vz) in m/s in camera
    coordinates; ``names`` optionally maps object id to a human-readable name.
    """

    labels: np.ndarray
    motions: Mapping[int, np.ndarray]
    names: Mapping[int, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "labels", np.asarray(self.labels, dtype=np.int64))
        motions = {int(k): np.asarray(v, dtype=np.float64) for k, v in self.motions.items()}
        for k, v in motions.items():
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"ground truth motion of object {k} must be 3 finite numbers")
        object.__setattr__(self, "motions", motions)
        unknown = set(np.unique(self.labels[self.labels >= 0]).tolist()) - set(motions)
        if unknown:
            raise ValueError(
                f"ground truth labels name objects {sorted(unknown)} with no motion; "
                "add them to motions.json"
            )

    def select(self, index: slice | np.ndarray) -> GroundTruth:
        """Ground truth for a subset of events."""
        return replace(self, labels=self.labels[index])


@dataclass(frozen=True, eq=False)
class Recording:
    """Events, camera, time-sorted depth maps, optional keyframes and optional ground truth."""

    events: EventStream
    camera: Camera
    depth_maps: tuple[DepthMap, ...] = ()
    keyframes: tuple[Keyframe, ...] = ()
    ground_truth: GroundTruth | None = None
    name: str = "recording"

    def __post_init__(self) -> None:
        ev, cam = self.events, self.camera
        object.__setattr__(self, "depth_maps", tuple(self.depth_maps))
        object.__setattr__(self, "keyframes", tuple(self.keyframes))
        if (ev.width, ev.height) != (int(cam.width), int(cam.height)):
            raise ValueError(
                f"{self.name}: events are {ev.width}x{ev.height} but the camera is "
                f"{cam.width}x{cam.height}; they must describe the same sensor"
            )
        for d in self.depth_maps:
            if d.depth.shape != (cam.height, cam.width):
                raise ValueError(
                    f"{d.source}: depth map shape {d.depth.shape} does not match the sensor "
                    f"(H, W) = ({cam.height}, {cam.width})"
                )
        times = [d.t for d in self.depth_maps]
        if times != sorted(times):
            raise ValueError(f"{self.name}: depth maps are not sorted by time")
        gt = self.ground_truth
        if gt is not None and gt.labels.shape != (len(ev),):
            raise ValueError(
                f"{self.name}: ground truth has {gt.labels.size} labels for {len(ev)} events; "
                "give exactly one label per event"
            )

    def select(self, index: slice | np.ndarray) -> Recording:
        """The same recording restricted to a subset of its events."""
        gt = self.ground_truth.select(index) if self.ground_truth is not None else None
        return replace(self, events=self.events.select(index), ground_truth=gt)

    def windows(self) -> Iterator[tuple[np.ndarray, Recording]]:
        """Yield ``(event_indices, window)`` for each pair of consecutive depth maps.

        A window holds the events with ``T_i <= t < T_{i+1}`` (the last one also takes
        events at exactly ``T_{i+1}``) and the two depth maps bounding it.
        """
        for index, window, _ in self.spans(0):
            yield index, window

    def spans(self, context: int) -> Iterator[tuple[np.ndarray, Recording, np.ndarray]]:
        """Yield ``(event_indices, span, inner)`` for each window (:meth:`windows`): the span
        is the window with up to ``context`` neighbouring windows on each side (their events,
        depth maps and keyframes); ``inner`` locates the window's own events in the span.
        """
        maps = self.depth_maps
        if len(maps) < 2:
            raise ValueError(
                f"{self.name}: {len(maps)} depth map(s); EDPA needs at least two "
                "(one at the window's start and one at its end)"
            )
        check_window_context(context)
        t, last = self.events.t, len(maps) - 1
        bounds = [int(np.searchsorted(t, m.t, side="left")) for m in maps[:-1]]
        bounds.append(int(np.searchsorted(t, maps[-1].t, side="right")))
        for i in range(last):
            first, end = max(i - context, 0), min(i + 1 + context, last)
            lo, hi = bounds[first], bounds[end]
            index = np.arange(bounds[i], bounds[i + 1])
            span_maps = maps[first : end + 1]
            frames = tuple(k for k in self.keyframes if maps[first].t <= k.t <= maps[end].t)
            span = replace(self.select(slice(lo, hi)), depth_maps=span_maps, keyframes=frames)
            yield index, span, index - lo


def check_time_units(what: str, noun: str, t: np.ndarray) -> None:
    """Raise a one-line error naming ``what`` when the times ``t`` of its ``noun`` span over
    :data:`MAX_SPAN` s; the span, not the values, as Unix times in seconds (1.7e9) are fine."""
    span = float(np.max(t) - np.min(t)) if len(t) else 0.0
    if span <= MAX_SPAN:
        return
    if span > _NANOSECONDS_SPAN:  # over a day in microseconds too
        unit, fix = "nanoseconds", "divide by 1e9"
    else:  # a microsecond span of 0.1 s to a day is also 0.1 ms to 100 s in nanoseconds
        unit, fix = "microseconds", "divide by 1e6, or by 1e9 if they are nanoseconds"
    raise ValueError(
        f"{what}: {noun} span {span:.2g} s; timestamps look like {unit}; {fix} "
        "(spatialseg times are seconds)"
    )


def check_depth_units(depth_map: DepthMap) -> None:
    """Raise a one-line error naming the map when its median known depth is over
    :data:`MAX_MEDIAN_DEPTH` m: millimetres stored as floats would scale every velocity 1000x."""
    d = depth_map.depth
    known = d[np.isfinite(d) & (d > 0)]
    median = float(np.median(known)) if known.size else 0.0
    if median > MAX_MEDIAN_DEPTH:
        raise ValueError(
            f"{depth_map.source} (depth map at t={depth_map.t:.6f} s): median depth "
            f"{median:.4g} m; {MILLIMETRES_FIX}"
        )


def _source(recording: Recording) -> str:
    """The events' file, or the recording's name for events made in memory."""
    source = recording.events.source
    return recording.name if source == "<memory>" else source


def check_event_times(recording: Recording) -> None:
    """Raise a one-line error when the recording holds no events or their times are not
    seconds (:func:`check_time_units`), before a depth source spends any work on them."""
    if not len(recording.events):
        raise ValueError(
            f"{_source(recording)}: the recording holds no events, nothing to segment; "
            "check that its events file is not empty"
        )
    check_time_units(_source(recording), "events", recording.events.t)


def check_depth_maps(recording: Recording) -> None:
    """Raise a one-line error when the depth maps' times are not seconds, their depths not
    metres, or no event falls between the first and last map; warn when most events do not.

    Decision: the two clocks differing (an offset, or units the span check cannot see) leave
    every window empty; most events outside may be a depth sequence shorter than the events,
    so it warns (those events are labelled -1) rather than refuses.
    """
    maps, t = recording.depth_maps, recording.events.t
    check_time_units(recording.name, "depth maps", np.array([m.t for m in maps]))
    for depth_map in maps:
        check_depth_units(depth_map)
    if len(maps) < 2 or not len(t):
        return
    first, last = maps[0].t, maps[-1].t
    inside = int(np.searchsorted(t, last, side="right") - np.searchsorted(t, first, side="left"))
    spans = (
        f"{_source(recording)}: events span {t[0]:.3f}-{t[-1]:.3f} s but the depth maps "
        f"{first:.3f}-{last:.3f} s"
    )
    if inside == 0:
        raise ValueError(
            f"{spans}: no event falls between them, the two clocks differ (an offset or a "
            "unit); give both in the same seconds"
        )
    if inside < len(t) / 2:
        log.warning(
            "%s: %d of %d events fall outside them and are labelled -1; if the two clocks "
            "differ, give both in the same seconds",
            spans,
            len(t) - inside,
            len(t),
        )


def check_window_context(context: Any) -> None:
    """Raise a one-line error unless ``window.context`` is an integer >= 0 (not a bool)."""
    if not is_integer(context, 0):
        raise ValueError(f"window.context must be an integer >= 0, got {context!r}")


def is_short_tail(n_events: int, window_events: int) -> bool:
    """Whether a final window of ``n_events`` is too short to stand alone (under half of
    ``window_events``): it joins the window before it, so no window is a handful of events
    (too few to cluster)."""
    return n_events < window_events / 2


def event_boundaries(t: np.ndarray, window_events: int) -> np.ndarray:
    """Window boundary times every ``window_events`` events, the first and last event included.

    A final window shorter than half of ``window_events`` is merged into the one before it
    (:func:`is_short_tail`).
    """
    starts = np.arange(0, len(t), window_events)
    if len(starts) > 1 and is_short_tail(len(t) - starts[-1], window_events):
        starts = starts[:-1]
    return np.unique(np.r_[t[starts], t[-1]])
