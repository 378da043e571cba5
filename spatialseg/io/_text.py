"""The plain-text files of a recording: ``events.txt``, ``calib.txt``, ``sensor.txt`` and the
``t path`` listings (``depthmaps.txt``, ``images.txt``).

Every text file may hold blank lines and ``#`` comments (from ``#`` to the end of the line).
Events files are parsed a block of lines at a time at C speed by ``np.loadtxt``; only a block
that fails is scanned again line by line, to name the first bad line and say how to fix it.
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path

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
#: Most lines parsed per block when reading (a list of Python strings: bounds its memory).
_READ_LINES = 1 << 16


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


def txt_blocks(path: Path, size: tuple[int, int], block_events: int) -> Iterator[Block]:
    """The events of a ``t x y p`` file, ``block_events`` lines (at most ``_READ_LINES``) at a
    time, each block checked; a bad block is scanned line by line to name its bad line."""
    negative: tuple[float, int] | None = None  # the first polarity other than 1, and its line
    previous, first = -math.inf, 1
    with path.open(encoding="utf-8", errors="replace") as f:
        while lines := list(itertools.islice(f, min(block_events, _READ_LINES))):
            try:
                t, x, y, p = _table(lines).T
                events = EventStream(x, y, t, normalise_polarity(p, str(path)), *size, str(path))
                other = np.flatnonzero(p != 1)
                if t.size and t[0] < previous:
                    raise ValueError("timestamps not sorted")
                if other.size and negative is not None and p[other[0]] != negative[0]:
                    raise ValueError("polarity 0/1 and -1/+1 mixed")
            except ValueError as exc:
                _name_bad_line(path, lines, first, size, previous, negative)
                raise ValueError(f"{path} lines {first}..{first + len(lines) - 1}: {exc}") from None
            if other.size and negative is None:
                line = next(itertools.islice(_numbered(lines, first), int(other[0]), None))[0]
                negative = (float(p[other[0]]), line)
            previous, first = (float(t[-1]) if t.size else previous), first + len(lines)
            yield Block(events.t, events.x, events.y, events.p)


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
