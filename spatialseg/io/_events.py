"""Bare event files: the ``.h5``/``.hdf5`` (DSEC layout) and ``.npz`` decoders, and the writer
of ``.txt`` (RPG), ``.h5`` and ``.npz`` files.

HDF5: datasets ``events/x``, ``events/y``, ``events/t``, ``events/p``; a float ``t`` is in
seconds, an integer ``t`` in microseconds (DSEC) plus the root dataset ``t_offset`` (µs)
when present; the sensor size is stored as attributes ``width``/``height`` of ``events``.
DSEC compresses its datasets with Blosc/zstd: importing ``hdf5plugin`` registers those
filters with h5py, so such files read like any other.
npz: arrays ``t`` (seconds), ``x``, ``y``, ``p`` and optionally 0-d ``width``, ``height``.
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import h5py
import hdf5plugin  # noqa: F401  (registers Blosc, zstd, LZ4 ... filters with h5py on import)
import numpy as np

from spatialseg.events import EventStream
from spatialseg.io._atomic import atomic_file
from spatialseg.io._decode import Block, damaged, decoding
from spatialseg.io._text import write_events_txt

__all__ = [
    "PathLike",
    "agreed_size",
    "events_kind",
    "h5_blocks",
    "h5_sensor_size",
    "npz_blocks",
    "npz_sensor_size",
    "save_events",
    "size_pair",
    "write_events",
]

PathLike = str | os.PathLike[str]
Size = tuple[int, int]

#: Events file kind by (lower-case) suffix.
_KINDS = {".txt": "txt", ".h5": "h5", ".hdf5": "h5", ".npz": "npz"}
_FIELDS = ("t", "x", "y", "p")


def events_kind(path: Path) -> str:
    """``"txt"``, ``"h5"`` or ``"npz"`` from the file's suffix (ValueError for any other)."""
    kind = _KINDS.get(path.suffix.lower())
    if kind is None:
        raise ValueError(
            f"{path}: unknown events file type {path.suffix!r}; use .txt, .h5, .hdf5 or .npz"
        )
    return kind


def agreed_size(candidates: Sequence[tuple[str, Size | None]]) -> Size | None:
    """The sensor size ``(width, height)`` the known sources give; they must all agree."""
    known = [(source, size) for source, size in candidates if size is not None]
    for source, size in known[1:]:
        if size != known[0][1]:
            raise ValueError(
                f"{source}: sensor size {size[0]}x{size[1]} differs from "
                f"{known[0][1][0]}x{known[0][1][1]} given by {known[0][0]}; make them agree"
            )
    return known[0][1] if known else None


def size_pair(source: str, width: object, height: object) -> Size | None:
    """A ``(width, height)`` given as both or neither, each a positive integer."""
    if width is None and height is None:
        return None
    if width is None or height is None:
        raise ValueError(f"{source}: give both width and height or neither")
    w, h = np.asarray(width), np.asarray(height)
    if not (w.shape == h.shape == () and w.dtype.kind in "iu" and h.dtype.kind in "iu"):
        raise ValueError(f"{source}: width={width!r} height={height!r} must be integers")
    if w <= 0 or h <= 0:
        raise ValueError(f"{source}: sensor size {w}x{h} must be positive")
    return int(w), int(h)


def _open_h5(path: Path) -> h5py.File:
    """Open an HDF5 file for reading, or a ValueError naming it."""
    with decoding(path, "HDF5"):
        return h5py.File(path, "r")


def _h5_events(f: h5py.File, path: Path) -> h5py.Group:
    """The ``events`` group holding datasets x, y, t, p, or a ValueError naming what is missing."""
    with decoding(path, "HDF5", "group events"):
        group = f.get("events")
        missing = [k for k in _FIELDS if not isinstance(group, h5py.Group) or k not in group]
    if missing:
        raise ValueError(
            f"{path}: missing {', '.join('events/' + k for k in missing)}; "
            "expected datasets events/x, events/y, events/t, events/p (the DSEC layout)"
        )
    return group


def _open_npz(path: Path) -> np.lib.npyio.NpzFile:
    """Open an ``.npz`` archive (no pickles), or a ValueError naming it."""
    with decoding(path, ".npz"):
        archive = np.load(path, allow_pickle=False)
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise ValueError(f"{path}: holds a single array, not an .npz archive of t, x, y, p")
    return archive


def h5_sensor_size(path: Path) -> Size | None:
    """The sensor size stored as attributes ``width``/``height`` of ``events`` (None without)."""
    with _open_h5(path) as f:
        group = _h5_events(f, path)
        with decoding(path, "HDF5", "attributes of events"):
            width, height = group.attrs.get("width"), group.attrs.get("height")
        return size_pair(f"{path} (attributes of events)", width, height)


def npz_sensor_size(path: Path) -> Size | None:
    """The sensor size stored as 0-d arrays ``width``, ``height`` (None without)."""
    with _open_npz(path) as archive:
        width, height = (_npz_member(archive, path, k) for k in ("width", "height"))
        return size_pair(str(path), width, height)


def _h5_dataset(f: h5py.File, path: Path, name: str, part: slice | tuple[()] = ()) -> np.ndarray:
    """``part`` (default: all) of dataset ``name``, e.g. ``events/t``; a failure names it."""
    with decoding(path, "HDF5", f"dataset {name}"):
        return f[name][part]


def _h5_time_offset(f: h5py.File, path: Path) -> np.int64:
    """The root dataset ``t_offset`` (DSEC, microseconds), 0 without it."""
    with decoding(path, "HDF5", "dataset t_offset"):
        present = "t_offset" in f
    return np.int64(_h5_dataset(f, path, "t_offset")) if present else np.int64(0)


def _npz_member(archive: np.lib.npyio.NpzFile, path: Path, name: str) -> np.ndarray | None:
    """Array ``name`` of an open ``.npz`` archive (None if absent); a decoding failure names it."""
    with decoding(path, ".npz", f"member '{name}.npy'"):
        return archive[name] if name in archive.files else None


def _require_npz_arrays(path: Path, names: Sequence[str]) -> None:
    """Raise a ValueError naming the arrays t, x, y, p missing from ``names``."""
    missing = [k for k in _FIELDS if k not in names]
    if missing:
        raise ValueError(
            f"{path}: missing array(s) {', '.join(missing)}; "
            "expected t, x, y, p (and optionally width, height)"
        )


def h5_blocks(path: Path, size: Size, block_events: int) -> Iterator[Block]:
    """Slices of ``events/{t,x,y,p}``; integer t is microseconds plus ``t_offset`` (DSEC)."""
    with _open_h5(path) as f:
        group = _h5_events(f, path)
        offset = _h5_time_offset(f, path)
        lengths = {}
        for k in _FIELDS:
            with decoding(path, "HDF5", f"dataset events/{k}"):
                lengths[k] = group[k].shape
        if len(set(lengths.values())) != 1 or len(lengths["t"]) != 1:
            raise ValueError(f"{path}: events datasets differ in shape {lengths}; give 1-D arrays")
        for start in range(0, lengths["t"][0], block_events):
            part = slice(start, start + block_events)
            t, x, y, p = (_h5_dataset(f, path, f"events/{k}", part) for k in _FIELDS)
            if t.dtype.kind in "iu":
                t = (t.astype(np.int64) + offset) / 1e6
            yield Block(t, x, y, p)


def _npy_member(archive: zipfile.ZipFile, name: str, path: Path) -> tuple[object, np.dtype, int]:
    """An open member ``name.npy`` of an ``.npz``, positioned at its data, its dtype and length."""
    with decoding(path, ".npz", f"member '{name}.npy'"):
        stream = archive.open(f"{name}.npy")
        version = np.lib.format.read_magic(stream)
        read_header = (
            np.lib.format.read_array_header_1_0
            if version == (1, 0)
            else np.lib.format.read_array_header_2_0
        )
        shape, _, dtype = read_header(stream)
    if len(shape) != 1 or dtype.hasobject:
        raise ValueError(f"{path}: array {name!r} has shape {shape} {dtype}; expected 1-D numbers")
    return stream, dtype, int(shape[0])


def npz_blocks(path: Path, size: Size, block_events: int) -> Iterator[Block]:
    """``block_events`` elements at a time of each of ``t, x, y, p``, read out of the archive
    incrementally (no need to unzip or load it)."""
    with decoding(path, ".npz"):
        archive = zipfile.ZipFile(path)
    with archive:
        _require_npz_arrays(path, [name.removesuffix(".npy") for name in archive.namelist()])
        members = {k: _npy_member(archive, k, path) for k in _FIELDS}
        lengths = {k: m[2] for k, m in members.items()}
        if len(set(lengths.values())) != 1:
            raise ValueError(f"{path}: arrays differ in length {lengths}; give one per event")
        for start in range(0, lengths["t"], block_events):
            count = min(block_events, lengths["t"] - start)
            block = []
            for name, (stream, dtype, _) in members.items():
                where = f"member '{name}.npy'"
                with decoding(path, ".npz", where):
                    data = stream.read(count * dtype.itemsize)
                if len(data) != count * dtype.itemsize:
                    raise damaged(path, f"array data ends before event {start + count}", where)
                block.append(np.frombuffer(data, dtype=dtype))
            yield Block(*block)


def _disk_arrays(events: EventStream) -> dict[str, np.ndarray]:
    """Compact on-disk arrays: t float64 seconds, x/y smallest unsigned type, p 0/1 uint8."""
    pixel = np.min_scalar_type(max(events.width, events.height) - 1)
    return {
        "t": events.t,
        "x": events.x.astype(pixel),
        "y": events.y.astype(pixel),
        "p": (events.p > 0).astype(np.uint8),
    }


def save_events(events: EventStream, path: Path, kind: str) -> None:
    """Write events to a new file of ``kind`` (``"txt"``, ``"h5"``, ``"npz"``), not atomically."""
    if kind == "txt":
        write_events_txt(events, path)
    elif kind == "h5":
        with h5py.File(path, "w-") as f:
            group = f.create_group("events")
            for name, array in _disk_arrays(events).items():
                group.create_dataset(name, data=array)
            group.attrs["width"], group.attrs["height"] = events.width, events.height
    else:
        with path.open("xb") as f:
            np.savez(f, **_disk_arrays(events), width=events.width, height=events.height)


def write_events(events: EventStream, path: PathLike) -> None:
    """Write events to ``path`` atomically, in the format its suffix names (.txt, .h5, .npz)."""
    path = Path(path)
    kind = events_kind(path)
    with atomic_file(path) as tmp:
        save_events(events, tmp, kind)
