"""Reading events window by window, so a recording larger than memory can be processed.

:func:`iter_event_chunks` yields :class:`EventStream` chunks of exactly ``chunk_events``
events (the last may be shorter) from any supported file type. Only about one chunk (plus
one block of the underlying file) is held at a time: text is parsed ``chunk_events``
lines at a time, HDF5 datasets are sliced, ``.npz`` members are read incrementally from
the archive, AEDAT4 packets and Prophesee words are decoded block by block.
"""

from __future__ import annotations

import io
import itertools
import math
import warnings
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from spatialseg.checks import is_integer
from spatialseg.events import EventStream, normalise_polarity
from spatialseg.io._decode import damaged, decoding
from spatialseg.io._events import (
    PathLike,
    Size,
    _h5_events,
    _open_h5,
    _size_pair,
    agreed_size,
    h5_dataset,
    h5_time_offset,
    require_npz_arrays,
    stored_sensor_size,
)
from spatialseg.io._text import _parse_event_line, read_sensor

__all__ = ["SUPPORTED", "iter_event_chunks", "recording_kind", "resolve_size"]

#: File kind by (lower-case) suffix; a directory is a recording directory.
_KINDS = {
    ".txt": "txt",
    ".h5": "h5",
    ".hdf5": "h5",
    ".npz": "npz",
    ".aedat4": "aedat4",
    ".raw": "prophesee",
    ".dat": "prophesee",
}
#: What :func:`recording_kind` accepts, for error messages and docs.
SUPPORTED = (
    "a recording directory, .txt, .h5/.hdf5, .npz, .aedat4 (iniVation DV), "
    ".raw (Prophesee EVT 2.0/3.0), .dat (Prophesee DAT)"
)
_FIELDS = ("t", "x", "y", "p")
_MIN_BLOCK_WORDS = 4096  # decode at least this many Prophesee words per step (speed)
Block = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # t [s], x, y, p


def recording_kind(path: Path) -> str:
    """``directory``, ``txt``, ``h5``, ``npz``, ``aedat4`` or ``prophesee`` for ``path``."""
    if path.is_dir():
        return "directory"
    if not path.exists():
        raise FileNotFoundError(f"{path}: not found")
    kind = _KINDS.get(path.suffix.lower())
    if kind is None:
        raise ValueError(f"{path}: unknown file type {path.suffix!r}; supported: {SUPPORTED}")
    return kind


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
            "give width and height (scene.camera.width/height)"
        )
    return size


class _Polarity:
    """Polarity normalised block by block, rejecting 0/1 in one block and -1/+1 in another."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.negative: float | None = None

    def __call__(self, p: np.ndarray) -> np.ndarray:
        """``p`` as int8 -1/+1, checking it uses the same convention as earlier blocks."""
        out = normalise_polarity(p, self.source)
        if p.dtype != bool and p.size:
            seen = set(np.unique(p[p != 1]).tolist())
            for value in seen:
                if self.negative is None:
                    self.negative = value
                elif value != self.negative:
                    raise ValueError(
                        f"{self.source}: polarity {value:g} after {self.negative:g} earlier; "
                        "use 0/1 or -1/+1, not a mix"
                    )
        return out


def _bad_txt_line(path: Path, lines: list[str], first: int, size: Size, previous: float) -> None:
    """Raise a ValueError naming the first bad ``t x y p`` line among ``lines``."""
    for number, line in enumerate(lines, start=first):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        where = f"{path} line {number}"
        t, _ = _parse_event_line(where, text.split(), *size)
        if t < previous:
            raise ValueError(
                f"{where}: timestamps not sorted ({t!r} < {previous!r}); sort the file by time"
            )
        previous = t


def _txt_blocks(path: Path, chunk_events: int, size: Size) -> Iterator[Block]:
    """``chunk_events`` lines at a time of a ``t x y p`` file, parsed by ``np.loadtxt``."""
    polarity, previous, first = _Polarity(str(path)), -math.inf, 1
    with path.open(encoding="utf-8", errors="replace") as f:
        while lines := list(itertools.islice(f, chunk_events)):
            try:
                with warnings.catch_warnings():
                    warnings.filterwarnings("ignore", "loadtxt: input contained no data")
                    table = np.loadtxt(io.StringIO("".join(lines)), comments="#", ndmin=2)
                if table.size == 0:
                    first += len(lines)
                    continue
                if table.shape[1] != 4:
                    raise ValueError(f"expected 4 columns 't x y p', got {table.shape[1]}")
                t, x, y, p = table.T
                events = EventStream(x, y, t, polarity(p), *size, source=str(path))
                if events.t[0] < previous:
                    raise ValueError("timestamps not sorted")
            except ValueError as exc:
                _bad_txt_line(path, lines, first, size, previous)
                last = first + len(lines) - 1
                raise ValueError(f"{path} lines {first}..{last}: {exc}") from None
            previous, first = float(events.t[-1]), first + len(lines)
            yield events.t, events.x, events.y, events.p


def _h5_blocks(path: Path, chunk_events: int) -> Iterator[Block]:
    """Slices of ``events/{t,x,y,p}``; integer t is microseconds plus ``t_offset`` (DSEC)."""
    polarity = _Polarity(str(path))
    with _open_h5(path) as f:
        group = _h5_events(f, path)
        offset = h5_time_offset(f, path)
        with decoding(path, "HDF5", "group events"):
            lengths = {k: group[k].shape for k in _FIELDS}
        if len(set(lengths.values())) != 1 or len(lengths["t"]) != 1:
            raise ValueError(f"{path}: events datasets differ in shape {lengths}; give 1-D arrays")
        for start in range(0, lengths["t"][0], chunk_events):
            part = slice(start, start + chunk_events)
            t, x, y, p = (h5_dataset(f, path, f"events/{k}", part) for k in _FIELDS)
            if t.dtype.kind in "iu":
                t = (t.astype(np.int64) + offset) / 1e6
            yield t, x, y, polarity(p)


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


def _npz_blocks(path: Path, chunk_events: int) -> Iterator[Block]:
    """``chunk_events`` elements at a time of each of ``t, x, y, p`` of an ``.npz`` archive."""
    polarity = _Polarity(str(path))
    with decoding(path, ".npz"):
        archive = zipfile.ZipFile(path)
    with archive:
        require_npz_arrays(path, [name.removesuffix(".npy") for name in archive.namelist()])
        members = {k: _npy_member(archive, k, path) for k in _FIELDS}
        lengths = {k: m[2] for k, m in members.items()}
        if len(set(lengths.values())) != 1:
            raise ValueError(f"{path}: arrays differ in length {lengths}; give one per event")
        for start in range(0, lengths["t"], chunk_events):
            count = min(chunk_events, lengths["t"] - start)
            block = []
            for name, (stream, dtype, _) in members.items():
                where = f"member '{name}.npy'"
                with decoding(path, ".npz", where):
                    data = stream.read(count * dtype.itemsize)
                if len(data) != count * dtype.itemsize:
                    raise damaged(path, f"array data ends before event {start + count}", where)
                block.append(np.frombuffer(data, dtype=dtype))
            t, x, y, p = block
            yield t, x, y, polarity(p)


def _aedat_blocks(path: Path) -> Iterator[Block]:
    """AEDAT4 events packet by packet, in seconds since the first event."""
    from spatialseg.io._aedat import aedat_info, iter_aedat_events

    origin: int | None = None
    for t, x, y, p in iter_aedat_events(path, aedat_info(path)[0]):
        if origin is None and t.size:
            origin = int(t[0])
        yield (t - (origin or 0)) / 1e6, x, y, p


def _prophesee_blocks(path: Path, chunk_events: int) -> Iterator[Block]:
    """Prophesee ``.raw``/``.dat`` events, about ``chunk_events`` words at a time, in seconds."""
    from spatialseg.io._prophesee import (
        _BLOCK_WORDS,
        iter_prophesee_arrays,
        read_prophesee_header,
    )

    words = min(_BLOCK_WORDS, max(chunk_events, _MIN_BLOCK_WORDS))
    for t, x, y, p in iter_prophesee_arrays(path, read_prophesee_header(path), words):
        yield t / 1e6, x, y, p


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
        (str(events_path), stored_sensor_size(events_path)),
    ]
    size = agreed_size(candidates)
    if size is None:
        raise ValueError(
            f"{root}: sensor size unknown; add sensor.txt with one line 'width height'"
        )
    return events_path, size


def _stored_size(path: Path, kind: str) -> Size | None:
    """The sensor size a file records in its header or attributes (None if it does not)."""
    if kind in ("h5", "npz"):
        return stored_sensor_size(path)
    if kind == "aedat4":
        from spatialseg.io._aedat import aedat_info

        return aedat_info(path)[1]
    if kind == "prophesee":
        from spatialseg.io._prophesee import read_prophesee_header

        return read_prophesee_header(path).size
    return None


def _rebatch(
    blocks: Iterable[Block], chunk_events: int, size: Size, source: str
) -> Iterator[EventStream]:
    """Regroup blocks into EventStreams of exactly ``chunk_events`` events (the last shorter)."""
    pending: list[Block] = []
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
    given = _size_pair("width=/height=", width, height)
    kind = recording_kind(path)
    if kind == "directory":
        path, size = _directory_source(path, given)
        kind = _KINDS[path.suffix.lower()]
    else:
        size = resolve_size(path, _stored_size(path, kind), given)
    return _rebatch(_blocks(path, kind, chunk_events, size), chunk_events, size, str(path))


def _blocks(path: Path, kind: str, chunk_events: int, size: Size) -> Iterable[Block]:
    """The raw blocks of an events file of ``kind``, in file order."""
    if kind == "txt":
        return _txt_blocks(path, chunk_events, size)
    if kind == "h5":
        return _h5_blocks(path, chunk_events)
    if kind == "npz":
        return _npz_blocks(path, chunk_events)
    if kind == "aedat4":
        return _aedat_blocks(path)
    return _prophesee_blocks(path, chunk_events)
