"""One entry point for every supported recording type: :func:`read_any`.

The reader is picked by what ``path`` is: a recording directory (events, ``calib.txt``,
depth maps, keyframes, ground truth) or a bare events file by suffix (``.txt``, ``.h5``,
``.hdf5``, ``.npz``, ``.aedat4``, ``.raw``, ``.dat``). Bare files carry no intrinsics, so
the camera comes from the caller: an explicit :class:`Camera`, or a nominal pinhole of a
given horizontal field of view (principal point at the image centre, square pixels).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from spatialseg.events import EventStream
from spatialseg.io._directory import read_recording
from spatialseg.io._events import PathLike, load_events
from spatialseg.io._stream import SUPPORTED, _stored_size, recording_kind, resolve_size
from spatialseg.recording import Camera, Keyframe, Recording

__all__ = ["SUPPORTED", "nominal_camera", "read_any"]


def nominal_camera(width: int, height: int, fov_deg: float) -> Camera:
    """A pinhole with horizontal field of view ``fov_deg``, square pixels, centred axis."""
    if not 0 < float(fov_deg) < 180:
        raise ValueError(f"field of view {fov_deg!r} degrees must be between 0 and 180")
    focal = (width / 2) / math.tan(math.radians(float(fov_deg)) / 2)
    return Camera(focal, focal, (width - 1) / 2, (height - 1) / 2, width, height)


def _camera_for(
    path: Path, size: tuple[int, int], camera: Camera | None, fov_deg: float | None
) -> Camera:
    """The given camera (checked against the sensor size) or a nominal one from ``fov_deg``."""
    if camera is not None:
        if (int(camera.width), int(camera.height)) != size:
            raise ValueError(
                f"{path}: the sensor is {size[0]}x{size[1]} but the camera given is "
                f"{camera.width}x{camera.height}; fix the camera's width/height"
            )
        return camera
    if fov_deg is None:
        raise ValueError(
            f"{path}: the file has no camera intrinsics; give a camera (scene.camera: fx, fy, "
            "cx, cy, width, height) or a field of view (scene.fov_deg)"
        )
    return nominal_camera(*size, fov_deg)


def _read_prophesee(path: Path, size: tuple[int, int]) -> EventStream:
    """All events of a Prophesee ``.raw``/``.dat`` file, in seconds."""
    from spatialseg.io._prophesee import iter_prophesee_arrays, read_prophesee_header

    blocks = list(iter_prophesee_arrays(path, read_prophesee_header(path)))
    if blocks:
        t, x, y, p = (np.concatenate(c) for c in zip(*blocks, strict=True))
    else:
        t, x, y, p = np.empty(0), np.empty(0, int), np.empty(0, int), np.empty(0, np.int8)
    return EventStream(x, y, t / 1e6, p, *size, source=str(path))


def read_any(
    path: PathLike, *, camera: Camera | None = None, fov_deg: float | None = None
) -> Recording:
    """Read a recording directory or an events file of any supported type into a Recording.

    ``camera`` replaces the file's intrinsics (a directory's ``calib.txt``) and gives the
    sensor size of files that do not store it (``.txt``); without it, files lacking
    intrinsics get :func:`nominal_camera` of ``fov_deg``. AEDAT4 frames become keyframes.
    """
    path = Path(path)
    kind = recording_kind(path)
    given = None if camera is None else (int(camera.width), int(camera.height))
    if kind == "directory":
        recording = read_recording(path)
        if camera is None:
            return recording
        size = (recording.camera.width, recording.camera.height)
        return replace(recording, camera=_camera_for(path, size, camera, None))
    keyframes: list[Keyframe] = []
    if kind == "aedat4":
        from spatialseg.io._aedat import read_aedat

        events, keyframes = read_aedat(path)
        resolve_size(path, (events.width, events.height), given)
    else:
        size = resolve_size(path, _stored_size(path, kind), given)
        events = _read_prophesee(path, size) if kind == "prophesee" else load_events(path, size)
    cam = _camera_for(path, (events.width, events.height), camera, fov_deg)
    return Recording(events, cam, keyframes=tuple(keyframes), name=path.stem)
