"""Reading events window by window, so a recording larger than memory can be processed.

:func:`iter_event_chunks` yields :class:`EventStream` chunks of exactly ``chunk_events``
events (the last may be shorter) from any registered format (``spatialseg.io._formats``):
its decoder gives blocks of about ``chunk_events`` events, regrouped here, so only about one
chunk (plus one block of the underlying file) is held at a time.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from spatialseg.checks import is_integer
from spatialseg.events import EventStream
from spatialseg.io._events import PathLike, Size, agreed_size, size_pair
from spatialseg.io._formats import format_for, signed_polarity, stored_size
from spatialseg.io._text import read_sensor

__all__ = ["iter_event_chunks", "recording_kind", "resolve_size"]

Columns = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # t [s], x, y, p (+1/-1)


def recording_kind(path: Path) -> str:
    """``directory``, or the name of the registered format of ``path``'s suffix."""
    if path.is_dir():
        return "directory"
    if not path.exists():
        raise FileNotFoundError(f"{path}: not found")
    return format_for(path).name


def resolve_size(path: Path, stored: Size | None, given: Size | None) -> Size:
    """The sensor size the file stores and/or the caller gives (they must agree)."""
    if stored is not None and given is not None and stored != given:
        raise ValueError(
            f"{path}: the sensor is {stored[0]}x{stored[1]} but the camera given is "
            f"{given[0]}x{given[1]}; fix the camera's width/height"
        )
    size = stored or given
    if size is None:
        raise ValueError(
            f"{path}: sensor size unknown (the file does not store it); "
            "give width and height (command line: scene.camera.width/height; Python: "
            "read(path, camera={...}) with width and height)"
        )
    return size


class _Polarity:
    """Polarity normalised block by block, rejecting 0/1 in one block and -1/+1 in another."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.negative: float | None = None

    def __call__(self, p: np.ndarray) -> np.ndarray:
        """``p`` as int8 -1/+1, checking it uses the same convention as earlier blocks."""
        out = signed_polarity(p, self.source)
        first = int(np.argmin(out)) if out.size else 0  # the first -1, if any
        if p.dtype != bool and out.size and out[first] < 0:
            value = p[first].item()  # 0 or -1: a block holds one convention
            if self.negative is None:
                self.negative = value
            elif value != self.negative:
                raise ValueError(
                    f"{self.source}: polarity {value:g} after {self.negative:g} earlier; "
                    "use 0/1 or -1/+1, not a mix"
                )
        return out


def _first_depth_shape(root: Path) -> tuple[str, Size] | None:
    """``(source, (W, H))`` of a directory's first listed depth map, memory-mapped (not loaded)."""
    from spatialseg.io._directory import depth_array, listed_files

    first = next(listed_files(root / "depthmaps.txt", "depth map"), None)
    if first is None:
        return None
    height, width = depth_array(first[2], mmap=True).shape
    return str(first[2]), (width, height)


def _directory_source(root: Path, given: Size | None) -> tuple[Path, Size]:
    """A recording directory's events file and sensor size (depth map, sensor.txt, file)."""
    from spatialseg.io._directory import _events_file

    events_path = _events_file(root)
    sensor = root / "sensor.txt"
    candidates = [
        ("the given sensor size", given),
        _first_depth_shape(root) or ("depth maps", None),
        (str(sensor), read_sensor(sensor) if sensor.is_file() else None),
        (str(events_path), stored_size(events_path)),
    ]
    size = agreed_size(candidates)
    if size is None:
        raise ValueError(
            f"{root}: sensor size unknown; add sensor.txt with one line 'width height'"
        )
    return events_path, size


def _rebatch(
    blocks: Iterable[Columns], chunk_events: int, size: Size, source: str
) -> Iterator[EventStream]:
    """Regroup blocks into EventStreams of exactly ``chunk_events`` events (the last shorter)."""
    pending: list[Columns] = []
    count, start, last_t = 0, 0, -math.inf

    def emit(n: int) -> EventStream:
        nonlocal pending, count, start, last_t
        merged = [np.concatenate(c) for c in zip(*pending, strict=True)]
        head = [a[:n] for a in merged]
        pending = [tuple(a[n:] for a in merged)] if n < len(merged[0]) else []
        where = f"{source} (events {start}..{start + n - 1})"
        if head[0][0] < last_t:
            raise ValueError(
                f"{source}: timestamps not sorted at event {start} "
                f"({head[0][0]:.9f} s < {last_t:.9f} s); sort the events by time"
            )
        chunk = EventStream(head[1], head[2], head[0], head[3], *size, source=where)
        count, start, last_t = count - n, start + n, float(chunk.t[-1])
        return chunk

    for block in blocks:
        if not len(block[0]):
            continue
        pending.append(block)
        count += len(block[0])
        while count >= chunk_events:
            yield emit(chunk_events)
    if count:
        yield emit(count)


def iter_event_chunks(
    path: PathLike,
    chunk_events: int,
    *,
    width: int | None = None,
    height: int | None = None,
) -> Iterator[EventStream]:
    """Yield the events of any supported file or recording directory, ``chunk_events`` at a time.

    Each chunk is a validated :class:`EventStream` (times in seconds; AEDAT4 times are
    relative to the first event, as in :func:`read_any`); the chunks together are sorted.
    ``width``/``height`` give the sensor size for files that do not store it (``.txt``).
    """
    path = Path(path)
    if not is_integer(chunk_events, 1):
        raise ValueError(f"chunk_events={chunk_events!r}; give a positive integer")
    given = size_pair("width=/height=", width, height)
    if recording_kind(path) == "directory":
        path, size = _directory_source(path, given)
    else:
        size = resolve_size(path, stored_size(path), given)
    polarity = _Polarity(str(path))
    blocks = format_for(path).decode(path, size, chunk_events)
    ordered = ((b.t, b.x, b.y, polarity(b.p)) for b in blocks)
    return _rebatch(ordered, chunk_events, size, str(path))
