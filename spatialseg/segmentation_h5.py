"""``segmentation.h5``: a run's events, labels, memberships, objects and settings in one file.

Readable with plain h5py (no spatialseg needed)::

    events/t, events/x, events/y, events/p   the input events (attrs: width, height)
    labels                                   int64 object id per event, -1 unassigned
    probabilities                            float32 events x objects (column = object id)
    objects/id, velocity (units attr), n_events, first_window, last_window, n_windows
    attrs: settings (JSON), spatialseg_version, scene, n_events, n_objects

The file is built under a hidden temporary name (:func:`spatialseg.io._atomic.atomic_file`)
and renamed into place once complete: events are appended as a run reads them (a streamed
run one window at a time), labels and memberships copied from the finished ``labels.npy``
and ``probabilities.npy`` a block at a time, so memory stays bounded by a block.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any, Self

import h5py
import numpy as np

from spatialseg.events import EventStream
from spatialseg.io._atomic import atomic_file

__all__ = ["COMPRESSION", "SegmentationH5", "write_segmentation_h5"]

#: The filters of the per-event datasets: byte shuffle, then gzip at level 1. On a run's own
#: arrays it wrote about as fast as lzf with shuffle and was smaller (0.51 of the raw bytes
#: against 0.56; docs/formats.md), and every HDF5 reader (h5py, h5dump, MATLAB, HDF5.jl)
#: decodes gzip without a plugin, which lzf needs outside h5py.
COMPRESSION: dict[str, Any] = {"compression": "gzip", "compression_opts": 1, "shuffle": True}

#: The per-event datasets stored without filters. Decision: memberships are float32 in
#: [0, 1] whose low bytes are noise; on a 1,000,000-event run gzip took 231 ms to save 19 %
#: of their 12 MB (the events' times: 129 ms for 39 %; labels: 46 ms for 96 %), half of
#: writing the file (docs/formats.md).
UNCOMPRESSED = ("probabilities",)

#: Rows per HDF5 chunk of a per-event dataset (256 KiB of ``events/t``: within h5py's
#: default 1 MiB chunk cache, so appending a window at a time re-compresses no chunk).
CHUNK_ROWS = 1 << 15

#: Rows copied from a finished ``.npy`` at a time: a whole number of chunks.
BLOCK_ROWS = 32 * CHUNK_ROWS

#: Each whole-run object's fields (:func:`spatialseg.results.objects_summary`) and their
#: dtypes, written as ``objects/<field>``.
OBJECT_FIELDS = (
    ("id", np.int64),
    ("velocity", np.float64),
    ("n_events", np.int64),
    ("first_window", np.int64),
    ("last_window", np.int64),
    ("n_windows", np.int64),
)


def _rows_dataset(
    group: h5py.Group, name: str, dtype: Any, width: int | None, *, compressed: bool = True
) -> h5py.Dataset:
    """An empty dataset of ``width`` columns (None: 1-D) that grows by rows, chunked and
    (``compressed``) filtered by :data:`COMPRESSION`."""
    shape = (0,) if width is None else (0, width)
    chunks = (CHUNK_ROWS,) if width is None else (CHUNK_ROWS, max(width, 1))
    return group.create_dataset(
        name,
        shape=shape,
        maxshape=(None,) * len(shape),
        dtype=dtype,
        chunks=chunks,
        **(COMPRESSION if compressed else {}),
    )


def _append(dataset: h5py.Dataset, rows: np.ndarray) -> None:
    """Write ``rows`` after the dataset's last row, growing it."""
    start = dataset.shape[0]
    dataset.resize(start + len(rows), axis=0)
    dataset[start:] = rows


def _pixel_dtype(width: int, height: int) -> np.dtype[Any]:
    """uint16 for the pixel coordinates, wider only for a sensor beyond 65,536 pixels a side."""
    return np.promote_types(np.uint16, np.min_scalar_type(max(width, height) - 1))


def _objects(group: h5py.Group, objects: Sequence[Mapping[str, Any]], units: Any) -> None:
    """Write the whole run's objects, one row per object id, into ``group``."""
    for field, dtype in OBJECT_FIELDS:
        values = np.array([o[field] for o in objects], dtype=dtype)
        if field == "velocity":
            values = values.reshape(len(objects), 3)
        group.create_dataset(field, data=values)
    group["velocity"].attrs["units"] = str(units)


def _run_attributes(summary: Mapping[str, Any], settings: Mapping[str, Any]) -> dict[str, Any]:
    """The file's root attributes: the resolved settings as JSON, the version, the scene and
    the counts."""
    from spatialseg import __version__

    return {
        "settings": json.dumps(settings),
        "spatialseg_version": __version__,
        "scene": str(summary["scene"]),
        "n_events": int(summary["n_events"]),
        "n_objects": int(summary["n_objects"]),
    }


class SegmentationH5:
    """``segmentation.h5`` under construction: events appended as they are read, the rest
    written by :meth:`finish`, which renames the file into place.

    Used as a context manager, it removes its temporary file however the block ends without
    :meth:`finish` (an error, Ctrl-C, a SIGTERM turned into an exit).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self._stack = ExitStack()
        temporary = self._stack.enter_context(atomic_file(path))
        self._file = self._stack.enter_context(h5py.File(temporary, "w"))
        self._events = self._file.create_group("events")

    def __enter__(self) -> Self:
        """The file, whose temporary :meth:`__exit__` removes unless finished."""
        return self

    def __exit__(self, *exc: Any) -> None:
        """Close the file and remove its temporary (nothing left to do after :meth:`finish`)."""
        self._stack.__exit__(*exc)

    @property
    def rows(self) -> int:
        """The events appended so far."""
        return int(self._events["t"].shape[0]) if "t" in self._events else 0

    def append_events(self, events: EventStream) -> None:
        """Append events in their order; the first call takes the sensor size from them."""
        if "t" not in self._events:
            pixel = _pixel_dtype(events.width, events.height)
            for name, dtype in (("t", events.t.dtype), ("x", pixel), ("y", pixel), ("p", np.int8)):
                _rows_dataset(self._events, name, dtype, None)
            self._events.attrs.update(width=events.width, height=events.height)
        for name in ("t", "x", "y", "p"):
            _append(self._events[name], getattr(events, name))

    def finish(
        self,
        labels: Path,
        probabilities: Path,
        summary: Mapping[str, Any],
        settings: Mapping[str, Any],
    ) -> Path:
        """Copy the finished ``labels.npy`` and ``probabilities.npy``, write the objects and
        attributes of ``summary`` (``result.json``'s) and ``settings``, rename into place."""
        for name, path in (("labels", labels), ("probabilities", probabilities)):
            self._copy_rows(name, path)
        _objects(self._file.create_group("objects"), summary["objects"], summary["units"])
        self._file.attrs.update(_run_attributes(summary, settings))
        self._stack.close()
        return self.path

    def _copy_rows(self, name: str, npy: Path) -> None:
        """Copy the ``.npy`` file ``npy`` (one row per event, memory-mapped) into the dataset
        ``name`` a block at a time."""
        array = np.load(npy, mmap_mode="r")
        if len(array) != self.rows:
            raise RuntimeError(f"{npy}: {len(array)} rows for {self.rows} events")
        width = int(array.shape[1]) if array.ndim == 2 else None
        dataset = _rows_dataset(
            self._file, name, array.dtype, width, compressed=name not in UNCOMPRESSED
        )
        for start in range(0, len(array), BLOCK_ROWS):
            _append(dataset, array[start : start + BLOCK_ROWS])


def write_segmentation_h5(
    path: Path,
    events: EventStream,
    labels: Path,
    probabilities: Path,
    summary: Mapping[str, Any],
    settings: Mapping[str, Any],
) -> Path:
    """``segmentation.h5`` of a run held in memory: its events at once, labels and
    memberships from the finished ``labels.npy`` and ``probabilities.npy``."""
    with SegmentationH5(path) as h5:
        h5.append_events(events)
        return h5.finish(labels, probabilities, summary, settings)
