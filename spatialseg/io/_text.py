"""The plain-text files of a recording: ``events.txt``, ``calib.txt``, ``sensor.txt`` and the
``t path`` listings (``depthmaps.txt``, ``images.txt``).

Every text file may hold blank lines and ``#`` comments (from ``#`` to the end of the line).
``events.txt`` is parsed at C speed by ``np.loadtxt``; only when that fails is it scanned
again line by line, to name the first bad line and say how to fix it.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from spatialseg.events import EventStream, normalise_polarity
from spatialseg.recording import Camera

__all__ = [
    "data_lines",
    "read_calib",
    "read_events_txt",
    "read_sensor",
    "read_timed_paths",
    "write_events_txt",
    "write_lines",
]

#: Events formatted per ``write`` call when writing ``events.txt`` (bounds the memory used).
_WRITE_CHUNK = 1_000_000


def data_lines(path: Path) -> Iterator[tuple[int, str]]:
    """Yield ``(line number, text)`` of non-blank lines, ``#`` comments cut, bad bytes as U+FFFD."""
    with path.open(encoding="utf-8", errors="replace") as f:
        for number, line in enumerate(f, start=1):
            text = line.split("#", 1)[0].strip()
            if text:
                yield number, text


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


def read_events_txt(path: Path, width: int, height: int) -> EventStream:
    """The events of a ``t x y p`` file, parsed at C speed; on failure, the bad line is named."""
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "loadtxt: input contained no data")
            table = np.loadtxt(path, dtype=np.float64, comments="#", ndmin=2, encoding="utf-8")
        if table.size == 0:
            table = np.empty((0, 4))
        if table.shape[1] != 4:
            raise ValueError(f"expected 4 columns 't x y p', got {table.shape[1]}")
        t, x, y, p = table.T
        return EventStream(x, y, t, normalise_polarity(p, str(path)), width, height, str(path))
    except ValueError as exc:  # includes UnicodeDecodeError
        _find_bad_event_line(path, width, height)
        raise ValueError(f"{path}: {exc}") from exc


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


def _find_bad_event_line(path: Path, width: int, height: int) -> None:
    """Scan ``events.txt`` line by line and raise a ValueError naming the first bad line."""
    previous_t = -math.inf
    negative: tuple[float, int] | None = None  # first polarity other than 1, and its line
    for number, text in data_lines(path):
        where = f"{path} line {number}"
        t, p = _parse_event_line(where, text.split(), width, height)
        if t < previous_t:
            raise ValueError(
                f"{where}: timestamps not sorted ({t!r} < {previous_t!r}); sort the file by time"
            )
        if p != 1.0:
            if negative is None:
                negative = (p, number)
            elif p != negative[0]:
                raise ValueError(
                    f"{where}: polarity {p:g} but line {negative[1]} has {negative[0]:g}; "
                    "use 0/1 or -1/+1, not a mix"
                )
        previous_t = t


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
