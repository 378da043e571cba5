"""Turn a ``scene`` config into a :class:`Recording`: simulate it, or read it from disk.

``kind: recording`` reads any type :func:`spatialseg.io.read_any` supports (a recording
directory, ``.txt``/``.h5``/``.npz`` events, AEDAT4, Prophesee ``.raw``/``.dat``) from
``path``, or from ``packaged`` (a file shipped in ``spatialseg/data/``) when ``path`` is
null. Files without intrinsics take ``camera`` (fx, fy, cx, cy, width, height) or a
nominal pinhole of ``fov_deg``.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from spatialseg.events import EventStream
from spatialseg.recording import Camera, Recording, is_short_tail

__all__ = ["load_scene", "packaged_data", "read_scene", "stream_scene"]

_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height")
_DATA_DIR = Path(__file__).resolve().parent / "data"


def packaged_data(relative: str) -> Path:
    """The path of a data file shipped in ``spatialseg/data/`` (FileNotFoundError if absent)."""
    file = _DATA_DIR / relative
    if not file.exists():
        raise FileNotFoundError(
            f"{file}: packaged data not found; reinstall spatialseg (pip install -e .) "
            "or give scene.path=FILE"
        )
    return file


def _scene_path(scene: Mapping[str, Any]) -> Path:
    """``scene.path`` (user paths expand ``~``), else the packaged file ``scene.packaged``."""
    path = scene.get("path")
    if path:
        return Path(str(path)).expanduser()
    if scene.get("packaged"):
        return packaged_data(str(scene["packaged"]))
    raise ValueError("scene=recording needs a path: add scene.path=DIR")


def _scene_camera(scene: Mapping[str, Any]) -> Camera | None:
    """The camera ``scene.camera`` gives (all of fx, fy, cx, cy, width, height), or None."""
    cam = scene.get("camera")
    if cam is None:
        return None
    missing = [k for k in _CAMERA_KEYS if cam.get(k) is None]
    if missing:
        raise ValueError(
            f"scene.camera lacks {', '.join(missing)}; give fx, fy, cx, cy, width, height "
            "or set scene.camera=null"
        )
    try:
        return Camera(
            *(float(cam[k]) for k in _CAMERA_KEYS[:4]), int(cam["width"]), int(cam["height"])
        )
    except ValueError as exc:
        raise ValueError(f"scene.camera: {exc}") from None


def load_scene(
    scene: Mapping[str, Any], *, seed: int, window_events: int, windows: int = 1
) -> Recording:
    """The recording a scene config describes (``kind: simulated``: ``windows`` windows of
    ``window_events`` events; ``kind: recording``: the file), as stored: denoising and depth
    sources come after (:func:`spatialseg.depth.with_configured_depth`).
    """
    kind = scene.get("kind")
    if kind == "simulated":
        from spatialseg.simulate import simulate_scene

        return simulate_scene(scene, seed=seed, max_events=window_events, windows=windows)
    if kind == "recording":
        return read_scene(scene)
    raise ValueError(f"scene kind {kind!r} is not 'simulated' or 'recording'; fix the scene YAML")


def read_scene(scene: Mapping[str, Any]) -> Recording:
    """A ``kind: recording`` scene's file or directory (``path``, else ``packaged``), as
    stored; a file without intrinsics takes ``camera`` or a nominal pinhole of ``fov_deg``."""
    from spatialseg.io import read_any

    fov = scene.get("fov_deg")
    return read_any(
        _scene_path(scene), camera=_scene_camera(scene), fov_deg=None if fov is None else float(fov)
    )


def stream_scene(scene: Mapping[str, Any], *, window_events: int) -> Iterator[Recording]:
    """A ``kind: recording`` scene's file as recordings of ``window_events`` events each
    (the last one up to 1.5 times that), read one after the other
    (:func:`spatialseg.io.iter_event_chunks`), so a file larger than memory can be
    segmented window by window. They carry no depth maps and no
    keyframes; the camera is ``scene.camera`` or a nominal pinhole of ``scene.fov_deg``."""
    from spatialseg.io import iter_event_chunks, nominal_camera

    if scene.get("kind") != "recording":
        raise ValueError("scene.stream=true reads a file: it needs a kind: recording scene")
    camera, fov = _scene_camera(scene), scene.get("fov_deg")
    if camera is None and fov is None:
        raise ValueError(
            "scene.stream=true needs the camera: give scene.camera={fx, fy, cx, cy, width, "
            "height} or scene.fov_deg"
        )
    path = _scene_path(scene)
    size = {} if camera is None else {"width": camera.width, "height": camera.height}
    chunks = iter_event_chunks(path, int(window_events), **size)
    for chunk in _merge_short_tail(chunks, int(window_events), str(path)):
        if camera is None:
            camera = nominal_camera(chunk.width, chunk.height, float(fov))
        yield Recording(chunk, camera, name=path.stem)


def _merge_short_tail(
    chunks: Iterator[EventStream], window_events: int, source: str
) -> Iterator[EventStream]:
    """The chunks one behind, a final chunk too short to stand alone (:func:`is_short_tail`)
    joined to the one before it, as :func:`spatialseg.recording.event_boundaries` does in
    memory."""
    held: EventStream | None = None
    for chunk in chunks:
        if held is not None and is_short_tail(len(chunk), window_events):
            chunk = EventStream(
                *(np.concatenate([getattr(held, a), getattr(chunk, a)]) for a in "xytp"),
                held.width,
                held.height,
                source=f"{source} (the last {len(held) + len(chunk)} events)",
            )
        elif held is not None:
            yield held
        held = chunk
    if held is not None:
        yield held
