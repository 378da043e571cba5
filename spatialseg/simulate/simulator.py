"""The simulation loop: adaptive renders, threshold crossings, ground truth, the Recording."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from spatialseg.checks import is_integer
from spatialseg.events import EventStream
from spatialseg.recording import DepthMap, GroundTruth, Keyframe, Recording, event_boundaries
from spatialseg.simulate.depth_error import corrupt_depth_maps
from spatialseg.simulate.render import STATIC_SCENE, Frame, Renderer, surface_count
from spatialseg.simulate.scene import Scene, parse_scene
from spatialseg.simulate.sensor import EventChunk, Pixels

__all__ = ["simulate_scene", "texture_keys"]

#: Name of the static background when it is an object (camera with ego-velocity).
STATIC_SCENE_NAME = "static scene"


def _interval_labels(before: Frame, after: Frame) -> np.ndarray:
    """Object id per pixel for events between two renders: the nearer of the two surfaces.

    Where the front surface changes (an occlusion edge) the edge moves with the occluder,
    so its events belong to the nearer surface.
    """
    return np.where(before.depth <= after.depth, before.label, after.label)


def _next_time(renderer: Renderer, frame: Frame, end: float) -> float:
    """The next render time: no point moves more than ``max_pixel_step`` pixels, capped at end."""
    speed = renderer.max_image_speed(frame)
    if speed == 0:
        return end
    return min(frame.t + renderer.scene.max_pixel_step / speed, end)


def _run(
    scene: Scene, renderer: Renderer, pixels_rng: np.random.Generator, max_events: int | None
) -> tuple[list[EventChunk], float]:
    """Render and emit until ``max_events`` events exist or ``duration`` is reached."""
    frame = renderer.render(0.0)
    pixels = Pixels(scene.sensor, frame.log_intensity, pixels_rng)
    chunks: list[EventChunk] = []
    count = 0
    while frame.t < scene.duration and (max_events is None or count < max_events):
        following = renderer.render(_next_time(renderer, frame, scene.duration))
        labels = _interval_labels(frame, following)
        chunk = pixels.step(
            frame.log_intensity, following.log_intensity, labels, frame.t, following.t
        )
        chunks.append(chunk)
        count += len(chunk)
        frame = following
    return chunks, frame.t


def _keyframe(frame: Frame) -> Keyframe:
    """An 8-bit grayscale image of the irradiance (clipped to [0, 1])."""
    image = np.round(np.clip(frame.intensity, 0.0, 1.0) * 255).astype(np.uint8)
    return Keyframe(frame.t, image, source=f"simulated keyframe t={frame.t:.6f}")


def _ground_truth(scene: Scene, labels: np.ndarray) -> GroundTruth:
    """Labels plus each object's velocity relative to the camera (camera coordinates, m/s)."""
    motions = {i + 1: b.velocity - scene.ego_velocity for i, b in enumerate(scene.objects)}
    names = {i + 1: b.name for i, b in enumerate(scene.objects)}
    if np.any(scene.ego_velocity):
        motions[STATIC_SCENE] = -scene.ego_velocity
        names[STATIC_SCENE] = STATIC_SCENE_NAME
    return GroundTruth(labels, motions, names)


def texture_keys(scene: Scene, seed: int) -> np.ndarray:
    """One texture key per surface (:func:`surface_count`) for ``seed``: the first stream
    of ``SeedSequence(seed)`` (the second draws the pixels' thresholds)."""
    textures = np.random.default_rng(np.random.SeedSequence(seed).spawn(2)[0])
    return textures.integers(0, 2**62, surface_count(scene))


def simulate_scene(
    scene_cfg: Mapping[str, Any], *, seed: int, max_events: int | None, windows: int = 1
) -> Recording:
    """Simulate a ``conf/scene`` config into a Recording with ground truth, deterministically.

    The recording ends at the ``max_events * windows``-th event or at the scene's
    ``duration``. Depth maps and keyframes are rendered at the first event (0 without
    events) and at the last event (the end of the simulation without events), and with
    ``windows`` > 1 at every ``max_events``-th event between (a last window of fewer than
    half as many events joins the one before; without ``max_events``, the whole duration
    is split into ``windows`` windows of equal event counts); the scene's ``depth_error`` corrupts
    these maps only (labels come from the exact renders). Ground-truth ids: 0 is the static
    scene (planes and props; an object only with a nonzero ego-velocity), 1..N the objects
    in YAML order, -1 noise.
    """
    if max_events is not None and not is_integer(max_events, 1):
        raise ValueError(f"max_events must be a positive integer or None, got {max_events!r}")
    if not is_integer(windows, 1):
        raise ValueError(f"window.count must be a positive integer, got {windows!r}")
    per_window, max_events = max_events, None if max_events is None else max_events * windows
    scene = parse_scene(scene_cfg)
    renderer = Renderer(scene, texture_keys(scene, seed))
    thresholds = np.random.default_rng(np.random.SeedSequence(seed).spawn(2)[1])
    chunks, end = _run(scene, renderer, thresholds, max_events)
    keep = slice(0, max_events)
    pixel = np.concatenate([c.pixel for c in chunks] or [np.zeros(0, np.int64)])[keep]
    width = scene.camera.width
    events = EventStream(
        pixel % width,
        pixel // width,
        np.concatenate([c.t for c in chunks] or [np.zeros(0)])[keep],
        np.concatenate([c.p for c in chunks] or [np.zeros(0, np.int8)])[keep],
        width,
        scene.camera.height,
        source=f"simulated:{scene.name}",
    )
    labels = np.concatenate([c.label for c in chunks] or [np.zeros(0, np.int64)])[keep]
    times = (events.t[0], events.t[-1]) if len(events) else (0.0, end)
    if windows > 1 and len(events):
        times = event_boundaries(events.t, per_window or -(-len(events) // windows))
    frames = [renderer.render(float(t)) for t in times]
    depth_maps = tuple(
        DepthMap(f.t, f.depth, source=f"simulated depth t={f.t:.6f}") for f in frames
    )
    return Recording(
        events=events,
        camera=scene.camera,
        depth_maps=corrupt_depth_maps(depth_maps, scene.depth_error, seed=seed),
        keyframes=tuple(_keyframe(f) for f in frames),
        ground_truth=_ground_truth(scene, labels),
        name=scene.name,
    )
