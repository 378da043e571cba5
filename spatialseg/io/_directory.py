"""Recording directories: the RPG Event Camera Dataset layout, extended with depth maps.

``events.txt`` | ``events.h5`` | ``events.hdf5`` | ``events.npz`` (exactly one), ``calib.txt``,
optional ``sensor.txt``, ``depthmaps.txt`` (+ ``.npy`` files), ``images.txt`` (+ PNGs) and
``ground_truth/`` (``event_labels.npy``, ``motions.json``). See ``docs/formats.md``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from spatialseg.io._atomic import atomic_directory
from spatialseg.io._decode import decoding
from spatialseg.io._events import PathLike, Size, agreed_size, save_events
from spatialseg.io._formats import read_whole, stored_size
from spatialseg.io._text import (
    read_calib,
    read_sensor,
    read_timed_paths,
    write_lines,
)
from spatialseg.recording import (
    MILLIMETRES_FIX,
    Camera,
    DepthMap,
    GroundTruth,
    Keyframe,
    Recording,
)

if TYPE_CHECKING:
    import PIL.Image

__all__ = ["EVENT_FILES", "read_recording", "write_recording"]

#: Accepted events files of a recording directory, in the order they are looked for.
EVENT_FILES = ("events.txt", "events.h5", "events.hdf5", "events.npz")
_WRITE_FORMATS = ("txt", "h5", "npz")
_MOTIONS_SCHEMA = '{"objects": [{"id": 0, "name": "cart", "velocity": [vx, vy, vz]}, ...]}'


def _events_file(root: Path) -> Path:
    """The recording's single events file."""
    found = [root / name for name in EVENT_FILES if (root / name).is_file()]
    if not found:
        raise FileNotFoundError(f"{root}: no events file; expected one of {', '.join(EVENT_FILES)}")
    if len(found) > 1:
        names = " and ".join(p.name for p in found)
        raise ValueError(f"{root}: found {names}; keep exactly one events file")
    return found[0]


def _load_npy(path: Path, mmap: bool = False) -> np.ndarray:
    """One array from a ``.npy`` file (no pickles; memory-mapped if ``mmap``), or a ValueError."""
    with decoding(path, ".npy"):
        array = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    if not isinstance(array, np.ndarray):
        raise ValueError(f"{path}: is an .npz archive; save a single array with np.save")
    return array


def listed_files(listing: Path, what: str) -> Iterator[tuple[int, float, Path]]:
    """``(line number, time, existing file)`` for each ``t path`` line of an optional listing."""
    if not listing.is_file():
        return
    for number, t, relative in read_timed_paths(listing):
        file = listing.parent / relative
        if not file.is_file():
            raise FileNotFoundError(f"{listing} line {number}: {what} {relative!r} not found")
        yield number, t, file


def depth_array(file: Path, mmap: bool = False) -> np.ndarray:
    """A depth map's float (H, W) array from its ``.npy`` file (memory-mapped if ``mmap``)."""
    depth = _load_npy(file, mmap)
    if depth.ndim != 2:
        raise ValueError(f"{file}: expected a 2-D (H, W) depth map, got shape {depth.shape}")
    if depth.dtype.kind != "f":
        fix = MILLIMETRES_FIX if depth.dtype.kind in "iu" else "save float32 metres"
        raise ValueError(f"{file}: dtype {depth.dtype}, expected float32 metres; {fix}")
    return depth


def _read_depth_maps(root: Path) -> list[DepthMap]:
    """The depth maps of ``depthmaps.txt``: time-sorted float (H, W) arrays of one shape."""
    listing = root / "depthmaps.txt"
    maps: list[DepthMap] = []
    for number, t, file in listed_files(listing, "depth map"):
        if maps and t < maps[-1].t:
            raise ValueError(
                f"{listing} line {number}: times not sorted ({t!r} < {maps[-1].t!r}); "
                "sort the file by time"
            )
        depth = depth_array(file)
        if maps and depth.shape != maps[0].depth.shape:
            raise ValueError(
                f"{file}: shape {depth.shape} differs from the first depth map "
                f"{maps[0].depth.shape}"
            )
        maps.append(DepthMap(t, depth, source=str(file)))
    return maps


def _read_image(file: Path) -> np.ndarray:
    """A keyframe image as uint8: (H, W) if its colour channels are equal, else (H, W, 3)."""
    from PIL import Image  # Pillow alone: matplotlib's reader costs 0.2 s of imports

    with decoding(file, "an image"), Image.open(file) as opened:
        image = _eight_bit(opened)
    if image.ndim == 3:
        rgb = image[..., :3]
        image = rgb[..., 0] if np.all(rgb == rgb[..., :1]) else rgb
    return np.ascontiguousarray(image)


def _eight_bit(image: PIL.Image.Image) -> np.ndarray:
    """An opened image's pixels as uint8: grey, RGB or RGBA as stored, 16-bit grey scaled to
    8 bits, bilevel as 0/255, any other mode (palette, grey with alpha) as RGBA."""
    if image.mode in ("L", "RGB", "RGBA"):
        return np.asarray(image)
    if image.mode == "I" or image.mode.startswith("I;16"):
        scaled = np.round(np.asarray(image, dtype=np.float64) * (255 / 65535))
        return np.clip(scaled, 0, 255).astype(np.uint8)
    if image.mode == "1":
        return np.asarray(image.convert("L"))
    return np.asarray(image.convert("RGBA"))


def _read_keyframes(root: Path) -> list[Keyframe]:
    """The keyframes of ``images.txt``, in file order."""
    return [
        Keyframe(t, _read_image(file), source=str(file))
        for _, t, file in listed_files(root / "images.txt", "image")
    ]


def _motion_object(entry: object, where: str) -> tuple[int, list[float], str | None]:
    """``(id, velocity, name)`` of one ``motions.json`` object, or a ValueError showing it."""
    velocity = entry.get("velocity") if isinstance(entry, dict) else None
    valid = (
        isinstance(entry, dict)
        and type(entry.get("id")) is int
        and isinstance(velocity, list)
        and len(velocity) == 3
        and all(type(v) in (int, float) and math.isfinite(v) for v in velocity)
        and isinstance(entry.get("name", ""), str)
    )
    if not valid:
        raise ValueError(
            f'{where}: expected {{"id": <int>, "name": <str, optional>, '
            f'"velocity": [vx, vy, vz]}} with finite numbers, got {json.dumps(entry)[:80]}'
        )
    return entry["id"], velocity, entry.get("name")


def _read_motions(path: Path) -> tuple[dict[int, list[float]], dict[int, str]]:
    """Each object's velocity and name from ``motions.json``."""
    with decoding(path, "UTF-8 text"):
        text = path.read_text(encoding="utf-8")
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} line {exc.lineno}: {exc.msg}; fix the JSON") from None
    objects = document.get("objects") if isinstance(document, dict) else None
    if not isinstance(objects, list):
        raise ValueError(f"{path}: expected {_MOTIONS_SCHEMA}")
    motions: dict[int, list[float]] = {}
    names: dict[int, str] = {}
    for index, entry in enumerate(objects):
        key, velocity, name = _motion_object(entry, f"{path} objects[{index}]")
        if key in motions:
            raise ValueError(f"{path} objects[{index}]: object id {key} appears twice")
        motions[key] = velocity
        if name is not None:
            names[key] = name
    return motions, names


def _read_ground_truth(folder: Path, n_events: int) -> GroundTruth | None:
    """The optional ``ground_truth/``: one integer label per event and each object's motion."""
    if not folder.exists():
        return None
    labels_path, motions_path = folder / "event_labels.npy", folder / "motions.json"
    for path in (labels_path, motions_path):
        if not path.is_file():
            raise FileNotFoundError(
                f"{path}: not found; ground_truth/ needs event_labels.npy and motions.json"
            )
    labels = _load_npy(labels_path)
    if labels.dtype.kind not in "iu" or labels.shape != (n_events,):
        raise ValueError(
            f"{labels_path}: expected {n_events} integer labels (one per event), "
            f"got {labels.dtype} of shape {labels.shape}"
        )
    motions, names = _read_motions(motions_path)
    try:
        return GroundTruth(labels, motions, names)
    except ValueError as exc:  # labels naming objects that motions.json lacks
        raise ValueError(f"{labels_path}: {exc}") from None


def _sensor_size(root: Path, maps: Sequence[DepthMap], events_path: Path) -> Size:
    """The sensor size from the depth maps, ``sensor.txt`` or the events file (which agree)."""
    candidates: list[tuple[str, Size | None]] = []
    if maps:
        height, width = maps[0].depth.shape
        candidates.append((f"depth map {maps[0].source}", (width, height)))
    sensor_txt = root / "sensor.txt"
    if sensor_txt.is_file():
        candidates.append((str(sensor_txt), read_sensor(sensor_txt)))
    candidates.append((str(events_path), stored_size(events_path)))
    size = agreed_size(candidates)
    if size is None:
        raise ValueError(
            f"{root}: sensor size unknown (no depth maps, no sensor.txt, and "
            f"{events_path.name} does not store it); add sensor.txt with one line 'width height'"
        )
    return size


def read_recording(path: PathLike) -> Recording:
    """Read a recording directory (events, camera, depth maps, keyframes, ground truth)."""
    root = Path(path)
    if not root.is_dir():
        if root.exists():
            raise NotADirectoryError(
                f"{root}: not a directory; use read_events for a bare events file"
            )
        raise FileNotFoundError(f"{root}: recording directory not found")
    events_path = _events_file(root)
    depth_maps = _read_depth_maps(root)
    size = _sensor_size(root, depth_maps, events_path)
    calib = root / "calib.txt"
    if not calib.is_file():
        raise FileNotFoundError(f"{calib}: not found; a recording needs 'fx fy cx cy' intrinsics")
    camera = read_calib(calib, *size)
    keyframes = _read_keyframes(root)
    events = read_whole(events_path, size)[0]
    ground_truth = _read_ground_truth(root / "ground_truth", len(events))
    return Recording(
        events, camera, tuple(depth_maps), tuple(keyframes), ground_truth, root.resolve().name
    )


def _keyframe_rgb(index: int, keyframe: Keyframe) -> tuple[float, np.ndarray]:
    """``(t, (H, W, 3) uint8 image)`` of a keyframe to save (grey is repeated per channel)."""
    image = np.asarray(keyframe.image)
    shape_ok = image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)
    if image.dtype != np.uint8 or not shape_ok or not np.isfinite(keyframe.t):
        raise ValueError(
            f"keyframe {index} ({keyframe.source}): expected a finite time and a uint8 (H, W) "
            f"or (H, W, 3) image, got t={keyframe.t} and {image.dtype} {image.shape}"
        )
    rgb = np.repeat(image[..., None], 3, axis=2) if image.ndim == 2 else image
    return float(keyframe.t), rgb


def _save_png(file: Path, rgb: np.ndarray) -> None:
    """Save a (H, W, 3) uint8 image as a PNG file."""
    from PIL import Image

    Image.fromarray(rgb).save(file, format="PNG")


def _write_timed_files(
    root: Path,
    listing: str,
    folder: str,
    suffix: str,
    items: Sequence[tuple[float, np.ndarray]],
    save: Callable[[Path, np.ndarray], None],
) -> None:
    """Save each ``(t, array)`` as ``folder/NNNNNN<suffix>`` and list it in ``listing``."""
    if not items:
        return
    (root / folder).mkdir()
    lines = []
    for index, (t, array) in enumerate(items):
        relative = f"{folder}/{index:06d}{suffix}"
        save(root / relative, array)
        lines.append(f"{float(t)!r} {relative}")
    write_lines(root / listing, lines)


def _write_camera(camera: Camera, root: Path) -> None:
    """Write ``calib.txt`` (``fx fy cx cy``) and ``sensor.txt`` (``width height``)."""
    intrinsics = (camera.fx, camera.fy, camera.cx, camera.cy)
    write_lines(root / "calib.txt", [" ".join(repr(float(v)) for v in intrinsics)])
    write_lines(root / "sensor.txt", [f"{int(camera.width)} {int(camera.height)}"])


def _write_ground_truth(truth: GroundTruth, folder: Path) -> None:
    """Write ``event_labels.npy`` and ``motions.json`` into a new ``ground_truth/`` folder."""
    folder.mkdir()
    np.save(folder / "event_labels.npy", truth.labels)
    objects = [
        {"id": key}
        | ({"name": truth.names[key]} if key in truth.names else {})
        | {"velocity": [float(v) for v in truth.motions[key]]}
        for key in sorted(truth.motions)
    ]
    body = ",\n".join("  " + json.dumps(entry) for entry in objects)
    write_lines(folder / "motions.json", ['{"objects": [', body, "]}"])


def write_recording(
    recording: Recording,
    path: PathLike,
    *,
    events_format: str = "txt",
    overwrite: bool = False,
) -> None:
    """Write a recording directory atomically (temporary sibling, then rename into place)."""
    if events_format not in _WRITE_FORMATS:
        raise ValueError(f"events_format={events_format!r}; use 'txt', 'h5' or 'npz'")
    images = [_keyframe_rgb(i, k) for i, k in enumerate(recording.keyframes)]
    depths = [(d.t, d.depth) for d in recording.depth_maps]
    with atomic_directory(Path(path), overwrite=overwrite) as tmp:
        save_events(recording.events, tmp / f"events.{events_format}", events_format)
        _write_camera(recording.camera, tmp)
        _write_timed_files(tmp, "depthmaps.txt", "depth", ".npy", depths, np.save)
        _write_timed_files(tmp, "images.txt", "images", ".png", images, _save_png)
        if recording.ground_truth is not None:
            _write_ground_truth(recording.ground_truth, tmp / "ground_truth")
