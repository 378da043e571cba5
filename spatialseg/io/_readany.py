"""One entry point for every supported recording type: :func:`read_any`; and
:func:`read_events` for the bare events files spatialseg also writes.

The reader is picked by what ``path`` is: a recording directory (events, ``calib.txt``,
depth maps, keyframes, ground truth) or a bare events file of a registered format, by suffix
(``spatialseg.io._formats``). Bare files carry no intrinsics, so the camera comes from the
caller: an explicit :class:`Camera`, or a nominal pinhole of a given horizontal field of
view (principal point at the image centre, square pixels).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

from spatialseg.events import EventStream
from spatialseg.io._directory import read_recording
from spatialseg.io._events import PathLike, agreed_size, events_kind, size_pair
from spatialseg.io._formats import read_whole, stored_size
from spatialseg.io._stream import recording_kind, resolve_size
from spatialseg.recording import Camera, Recording

__all__ = ["nominal_camera", "read_any", "read_events"]


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


def read_any(
    path: PathLike, *, camera: Camera | None = None, fov_deg: float | None = None
) -> Recording:
    """Read a recording directory or an events file of any supported type into a Recording.

    ``camera`` replaces the file's intrinsics (a directory's ``calib.txt``) and gives the
    sensor size of files that do not store it (``.txt``); without it, files lacking
    intrinsics get :func:`nominal_camera` of ``fov_deg``. AEDAT4 frames become keyframes.
    """
    path = Path(path)
    if recording_kind(path) == "directory":
        recording = read_recording(path)
        if camera is None:
            return recording
        size = (recording.camera.width, recording.camera.height)
        return replace(recording, camera=_camera_for(path, size, camera, None))
    given = None if camera is None else (int(camera.width), int(camera.height))
    events, keyframes = read_whole(path, resolve_size(path, stored_size(path), given))
    cam = _camera_for(path, (events.width, events.height), camera, fov_deg)
    return Recording(events, cam, keyframes=keyframes, name=path.stem)


def read_events(
    path: PathLike, *, width: int | None = None, height: int | None = None
) -> EventStream:
    """Read a bare ``.txt``/``.h5``/``.hdf5``/``.npz`` events file; size from the file or args."""
    path = Path(path)
    events_kind(path)  # the types write_events writes (read_any reads every registered one)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: events file not found")
    size = agreed_size(
        [
            ("width=/height=", size_pair("width=/height=", width, height)),
            (str(path), stored_size(path)),
        ]
    )
    if size is None:
        raise ValueError(
            f"{path}: sensor size unknown (the file does not store it); pass width= and height="
        )
    return read_whole(path, size)[0]
