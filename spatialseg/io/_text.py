"""The plain-text files of a recording: ``events.txt``, ``calib.txt``, ``sensor.txt`` and the
``t path`` listings (``depthmaps.txt``, ``images.txt``).

Every text file may hold blank lines and ``#`` comments (from ``#`` to the end of the line).
Events files are read in chunks of whole lines and parsed at C speed: a large chunk of plain
lines by Arrow's CSV reader, any other by ``np.loadtxt``; only a block that fails its checks
is scanned again line by line, to name the first bad line and say how to fix it.
"""

from __future__ import annotations

import functools
import io
import itertools
import math
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from spatialseg.events import EventStream, normalise_polarity
from spatialseg.io._decode import Block
from spatialseg.recording import Camera

__all__ = [
    "data_lines",
    "read_calib",
    "read_sensor",
    "read_timed_paths",
    "txt_blocks",
    "write_events_txt",
    "write_lines",
]

#: Events formatted per ``write`` call when writing ``events.txt`` (bounds the memory used).
_WRITE_CHUNK = 1_000_000
#: Most lines parsed per block by ``np.loadtxt`` (a list of Python strings: bounds its memory).
_READ_LINES = 1 << 16
#: Bytes read at a time, in whole lines (about 550,000 events of 30 bytes; as Python strings
#: for ``np.loadtxt``, some 50 MB).
_CHUNK_BYTES = 1 << 24
#: The smallest chunk parsed by Arrow: importing pyarrow (0.1 s) costs more than it saves on
#: fewer than about 130,000 lines (``np.loadtxt``: 0.85 s a million).
_ARROW_BYTES = 1 << 22
#: The columns of an events file, as Arrow parses them.
_TXYP = {name: np.dtype(kind) for name, kind in zip("txyp", ("f8", "i4", "i4", "i1"), strict=True)}


def _numbered(lines: Iterable[str], first: int) -> Iterator[tuple[int, str]]:
    """``(line number, text)`` of the non-blank ``lines``, numbered from ``first``, comments cut."""
    for number, line in enumerate(lines, start=first):
        text = line.split("#", 1)[0].strip()
        if text:
            yield number, text


def data_lines(path: Path) -> Iterator[tuple[int, str]]:
    """Yield ``(line number, text)`` of non-blank lines, ``#`` comments cut, bad bytes as U+FFFD."""
    with path.open(encoding="utf-8", errors="replace") as f:
        yield from _numbered(f, 1)


def read_timed_paths(path: Path) -> list[tuple[int, float, str]]:
    """``(line number, time, relative path)`` of each ``t path`` line of a listing file."""
    entries = []
    for number, text in data_lines(path):
        fields = text.split(maxsplit=1)
        if len(fields) != 2:
            raise ValueError(f"{path} line {number}: expected 't path', got {text!r}")
        try:
            t = float(fields[0])
        except ValueError:
            raise ValueError(
                f"{path} line {number}: time {fields[0]!r} is not a number; expected 't path'"
            ) from None
        if not math.isfinite(t):
            raise ValueError(f"{path} line {number}: time {fields[0]!r} is not finite")
        entries.append((number, t, fields[1]))
    return entries


def _parse_numbers(path: Path, number: int, fields: list[str], expected: str) -> list[float]:
    """At least as many floats as ``expected`` names, or a ValueError naming line and layout."""
    try:
        values = [float(f) for f in fields]
    except ValueError:
        values = []
    if len(values) < len(expected.split()):
        raise ValueError(f"{path} line {number}: expected {expected!r}, got {' '.join(fields)!r}")
    return values


def _single_line(path: Path, expected: str) -> tuple[int, list[str]]:
    """The one data line of a one-line file (``calib.txt``, ``sensor.txt``), split."""
    lines = list(data_lines(path))
    if len(lines) != 1:
        raise ValueError(f"{path}: expected one line {expected!r}, got {len(lines)} lines")
    number, text = lines[0]
    return number, text.split()


def read_calib(path: Path, width: int, height: int) -> Camera:
    """The pinhole camera of ``calib.txt``: ``fx fy cx cy`` [distortion: warned, ignored]."""
    number, fields = _single_line(path, "fx fy cx cy")
    values = _parse_numbers(path, number, fields, "fx fy cx cy")
    if any(values[4:]):
        warnings.warn(
            f"{path}: ignoring distortion coefficients {values[4:]}; "
            "spatialseg assumes undistorted (rectified) events",
            stacklevel=3,
        )
    fx, fy, cx, cy = values[:4]
    try:
        return Camera(fx, fy, cx, cy, width, height)
    except ValueError as exc:
        raise ValueError(f"{path} line {number}: {exc}") from None


def read_sensor(path: Path) -> tuple[int, int]:
    """The sensor size ``(width, height)`` of ``sensor.txt`` (one line ``width height``)."""
    number, fields = _single_line(path, "width height")
    values = _parse_numbers(path, number, fields, "width height")
    if len(values) != 2 or not all(v.is_integer() and v > 0 for v in values):
        raise ValueError(
            f"{path} line {number}: expected 'width height' (two positive integers), "
            f"got {' '.join(fields)!r}"
        )
    return int(values[0]), int(values[1])


def write_lines(path: Path, lines: list[str]) -> None:
    """Write text lines (each ended by a newline) to a new file."""
    with path.open("x", encoding="utf-8") as f:
        f.writelines(line + "\n" for line in lines)


def _parse_event_line(
    where: str, fields: list[str], width: int, height: int
) -> tuple[float, float]:
    """Check one ``t x y p`` line on its own and return its time and polarity."""
    if len(fields) != 4:
        raise ValueError(f"{where}: expected 4 columns 't x y p', got {len(fields)}")
    values = []
    for name, text in zip("txyp", fields, strict=True):
        try:
            values.append(float(text))
        except ValueError:
            raise ValueError(f"{where}: {name}={text!r} is not a number") from None
    t, x, y, p = values
    if not math.isfinite(t):
        raise ValueError(f"{where}: timestamp {fields[0]} is not finite; drop the line")
    for name, value, size in (("x", x, width), ("y", y, height)):
        if not (math.isfinite(value) and value.is_integer()):
            raise ValueError(f"{where}: {name}={value!r} is not an integer pixel coordinate")
        if not 0 <= value < size:
            raise ValueError(
                f"{where}: {name}={int(value)} is outside the sensor (0..{size - 1}); "
                "check the sensor size or crop the events"
            )
    if p not in (-1.0, 0.0, 1.0):
        raise ValueError(f"{where}: polarity {fields[3]} must be 0/1 or -1/+1")
    return t, p


def _name_bad_line(
    path: Path,
    lines: list[str],
    first: int,
    size: tuple[int, int],
    previous: float,
    negative: tuple[float, int] | None,
) -> None:
    """Raise a ValueError naming the first bad ``t x y p`` line of ``lines`` (numbered from
    ``first``), given the time and polarity convention of the lines before them."""
    for number, text in _numbered(lines, first):
        where = f"{path} line {number}"
        t, p = _parse_event_line(where, text.split(), *size)
        if t < previous:
            raise ValueError(
                f"{where}: timestamps not sorted ({t!r} < {previous!r}); sort the file by time"
            )
        if p != 1.0:
            if negative is None:
                negative = (p, number)
            elif p != negative[0]:
                raise ValueError(
                    f"{where}: polarity {p:g} but line {negative[1]} has {negative[0]:g}; "
                    "use 0/1 or -1/+1, not a mix"
                )
        previous = t


def _table(lines: list[str]) -> np.ndarray:
    """The ``(N, 4)`` numbers of ``t x y p`` lines, by ``np.loadtxt`` (C speed)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "loadtxt: input contained no data")
        table = np.loadtxt(lines, comments="#", ndmin=2)
    if table.size == 0:
        return np.empty((0, 4))
    if table.shape[1] != 4:
        raise ValueError(f"expected 4 columns 't x y p', got {table.shape[1]}")
    return table


def _arrow_columns(chunk: bytes) -> tuple[np.ndarray, ...] | None:
    """``t, x, y, p`` of a chunk of plain ``t x y p`` lines (one space apart, ``\\n`` endings, no
    comments or blank lines, so row i is line i) by Arrow's multithreaded CSV reader, or None
    for anything else. Arrow's floats are correctly rounded, as ``np.loadtxt``'s are."""
    if b"#" in chunk or b"\r" in chunk or b"\n\n" in chunk or chunk.startswith(b"\n"):
        return None
    import pyarrow as pa
    from pyarrow import csv

    types = {name: pa.from_numpy_dtype(dtype) for name, dtype in _TXYP.items()}
    try:
        table = csv.read_csv(
            pa.py_buffer(chunk),
            read_options=csv.ReadOptions(column_names=list(types)),
            parse_options=csv.ParseOptions(delimiter=" "),
            convert_options=csv.ConvertOptions(column_types=types),
        )
    except pa.ArrowException:
        return None
    if table.num_rows == 0 or any(column.null_count for column in table.columns):
        return None
    return tuple(_numpy(table.column(name), dtype) for name, dtype in _TXYP.items())


def _numpy(column: Any, dtype: np.dtype) -> np.ndarray:
    """A null-free Arrow column of ``dtype`` as one numpy array, from its buffers (Arrow's
    ``to_numpy`` imports pandas: 0.3 s)."""
    return np.concatenate(
        [
            np.frombuffer(part.buffers()[1], dtype, len(part), part.offset * dtype.itemsize)
            for part in column.chunks
        ]
    )


def _loadtxt_columns(lines: list[str]) -> tuple[np.ndarray, ...]:
    """``t, x, y, p`` of ``t x y p`` lines, by ``np.loadtxt``."""
    return tuple(_table(lines).T)


def _whole_lines(f: BinaryIO, size: int) -> Iterator[bytes]:
    """The bytes of ``f`` in chunks of whole lines, about ``size`` bytes each (the last line
    may lack its newline)."""
    rest = b""
    while data := f.read(size):
        data = rest + data
        cut = data.rfind(b"\n") + 1
        rest = data[cut:]
        if cut:
            yield data[:cut]
    if rest:
        yield rest


def _text_lines(chunk: bytes) -> list[str]:
    """The lines of ``chunk`` as a text-mode read gives them: bad bytes as U+FFFD, any
    newline convention."""
    return io.StringIO(chunk.decode("utf-8", errors="replace"), newline=None).readlines()


@dataclass(frozen=True)
class _Lines:
    """Where a block's events come from: ``text()`` its lines (made only when needed),
    numbered from ``first``; ``plain``: one event per line, none blank or commented."""

    text: Callable[[], list[str]]
    first: int
    plain: bool

    def line_of(self, row: int) -> int:
        """The line number of the block's event ``row``."""
        if self.plain:
            return self.first + row
        return next(itertools.islice(_numbered(self.text(), self.first), row, None))[0]


class _TxtChecker:
    """The checks that span blocks of a ``t x y p`` file: times sorted across them, one
    polarity convention (0/1 or -1/+1) throughout."""

    def __init__(self, path: Path, size: tuple[int, int]) -> None:
        self.path, self.size = path, size
        self.previous = -math.inf
        self.negative: tuple[float, int] | None = None  # the first polarity other than 1, its line

    def block(self, parse: Callable[[], tuple[np.ndarray, ...]], lines: _Lines) -> Block:
        """The checked block of the columns ``parse()`` gives (``t, x, y, p``) for ``lines``;
        a bad block's lines are scanned to name the first bad one."""
        try:
            t, x, y, p = parse()
            source = str(self.path)
            events = EventStream(x, y, t, normalise_polarity(p, source), *self.size, source)
            other = np.flatnonzero(p != 1)
            if t.size and t[0] < self.previous:
                raise ValueError("timestamps not sorted")
            if other.size and self.negative is not None and p[other[0]] != self.negative[0]:
                raise ValueError("polarity 0/1 and -1/+1 mixed")
        except ValueError as exc:
            text = lines.text()
            _name_bad_line(self.path, text, lines.first, self.size, self.previous, self.negative)
            last = lines.first + len(text) - 1
            raise ValueError(f"{self.path} lines {lines.first}..{last}: {exc}") from None
        if other.size and self.negative is None:
            self.negative = (float(p[other[0]]), lines.line_of(int(other[0])))
        self.previous = float(t[-1]) if t.size else self.previous
        return Block(events.t, events.x, events.y, events.p)


def txt_blocks(path: Path, size: tuple[int, int], block_events: int) -> Iterator[Block]:
    """The events of a ``t x y p`` file, at most ``block_events`` a block, each checked; a
    bad block is scanned line by line to name its bad line. Plain chunks of at least
    ``_ARROW_BYTES`` are parsed by Arrow (a million lines in 0.13 s against 0.85 s) and
    checked whole; the others by ``np.loadtxt``, ``_READ_LINES`` lines at most at a time."""
    checker, first = _TxtChecker(path, size), 1
    with path.open("rb") as f:
        for chunk in _whole_lines(f, _CHUNK_BYTES):
            columns = _arrow_columns(chunk) if len(chunk) >= _ARROW_BYTES else None
            if columns is not None:
                lines = _Lines(functools.partial(_text_lines, chunk), first, plain=True)
                whole = checker.block(functools.partial(tuple, columns), lines)
                for start in range(0, len(whole.t), block_events):
                    part = slice(start, start + block_events)
                    yield Block(whole.t[part], whole.x[part], whole.y[part], whole.p[part])
                first += chunk.count(b"\n") + (not chunk.endswith(b"\n"))
                continue
            text, step = _text_lines(chunk), min(block_events, _READ_LINES)
            for start in range(0, len(text), step):
                part = text[start : start + step]
                lines = _Lines(functools.partial(list, part), first + start, plain=False)
                yield checker.block(functools.partial(_loadtxt_columns, part), lines)
            first += len(text)


def write_events_txt(events: EventStream, path: Path) -> None:
    """Write ``t x y p`` lines to a new file: t bit-exact (shortest repr), p as 0/1; no size."""
    with path.open("x", encoding="utf-8") as f:
        for start in range(0, len(events), _WRITE_CHUNK):
            part = slice(start, start + _WRITE_CHUNK)
            lines = map(
                "{!r} {} {} {}\n".format,
                events.t[part].tolist(),
                events.x[part].tolist(),
                events.y[part].tolist(),
                (events.p[part] > 0).astype(np.uint8).tolist(),
            )
            f.write("".join(lines))
