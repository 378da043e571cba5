"""Prophesee event files: EVT 2.0 and EVT 3.0 ``.raw`` streams and ``.dat`` CD files.

Decoded with numpy, block by block, carrying the decoder state (time base, row, vector
base) from one block to the next, so a file of any size streams in bounded memory. Layouts
(Prophesee's published specs, little-endian only):

* ``.raw`` header: ``% key value`` lines up to ``% end``; ``% evt 2.0|3.0`` or
  ``% format EVT2|EVT3;height=H;width=W`` names the encoding, ``% geometry WxH`` or the
  format's ``width``/``height`` the sensor size.
* EVT 2.0: 32-bit words, type in bits 31..28: CD_OFF 0x0 / CD_ON 0x1 (timestamp bits 5..0
  in 27..22, x in 21..11, y in 10..0), EVT_TIME_HIGH 0x8 (timestamp bits 33..6 in 27..0).
* EVT 3.0: 16-bit words, type in bits 15..12: EVT_ADDR_Y 0x0 (y in 10..0), EVT_ADDR_X 0x2
  (polarity 11, x 10..0), VECT_BASE_X 0x3 (polarity 11, x 10..0), VECT_12 0x4 / VECT_8 0x5
  (a bit mask of events at base x + i; the base then advances by 12 / 8), EVT_TIME_LOW 0x6
  and EVT_TIME_HIGH 0x8 (timestamp bits 11..0 and 23..12); a TIME_HIGH that changes the
  time base sets bits 11..0 to 0 until the next TIME_LOW.
* ``.dat``: ``% Key value`` lines (``% Width W``, ``% Height H``), one byte event type
  (0 Event2d or 12 EventCD), one byte event size (8), then 8-byte records: uint32
  timestamp, uint32 with x in bits 13..0, y in 27..14, polarity in 31..28.

Timestamps are microseconds; a counter wrap-around (a drop of more than half its range)
adds one full range. Words before the decoder knows the time and row are skipped (a
recording may start mid-stream); reserved word types raise ``ValueError``.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from spatialseg.events import EventStream
from spatialseg.io._atomic import atomic_file
from spatialseg.io._decode import Block, damaged

__all__ = [
    "ProphHeader",
    "iter_prophesee_arrays",
    "prophesee_blocks",
    "prophesee_sensor_size",
    "read_prophesee_header",
    "write_prophesee",
]

#: Most words decoded per block (bounds the decoder's temporaries to a few tens of MB).
_BLOCK_WORDS = 1 << 18
_MIN_BLOCK_WORDS = 4096  # decode at least this many words per block (speed)
_EVT3_TYPES = np.isin(np.arange(16), [0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x8, 0xA, 0xE, 0xF])
_EVT2_TYPES = np.isin(np.arange(16), [0x0, 0x1, 0x8, 0xA, 0xE, 0xF])
_DAT_TYPES = {0, 12}
_DAT_RECORD = 8
_RAW_SUFFIX, _DAT_SUFFIX = ".raw", ".dat"
_MAX_HEADER_LINES = 10_000  # a header longer than this is not a header: a corrupt file

Arrays = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # t [us] int64, x, y, p (+1/-1)


@dataclass(frozen=True)
class ProphHeader:
    """What a Prophesee header says: encoding, sensor size (or None) and where data starts."""

    encoding: str  # "evt2", "evt3" or "dat"
    size: tuple[int, int] | None
    data_offset: int
    dat_type: int | None = None


def _header_lines(f: BinaryIO, path: Path) -> list[str]:
    """The ``%`` lines at the start of a file, leaving ``f`` at the first data byte."""
    lines: list[str] = []
    while len(lines) < _MAX_HEADER_LINES:
        start = f.tell()
        if f.read(1) != b"%":
            f.seek(start)
            return lines
        raw = f.readline()
        if not raw.endswith(b"\n"):
            raise damaged(path, f"truncated header (no end of line after '%{raw[:40]!r}')")
        text = raw.decode("ascii", errors="replace").strip()
        if text == "end":
            return lines
        lines.append(text)
    raise damaged(path, f"more than {_MAX_HEADER_LINES} '%' header lines")


def _header_size(path: Path, lines: list[str]) -> tuple[int, int] | None:
    """The sensor size from ``geometry WxH``, ``format ...;width=W;height=H`` or Width/Height."""
    keys: dict[str, str] = {}
    for line in lines:
        key, _, value = line.partition(" ")
        keys[key.lower()] = value.strip()
        for name, number in re.findall(r"(width|height)=(\d+)", line.lower()):
            keys[name] = number
    if "geometry" in keys:
        match = re.fullmatch(r"(\d+)x(\d+)", keys["geometry"])
        if match is None:
            raise ValueError(f"{path}: header geometry {keys['geometry']!r} is not 'WxH'")
        return int(match[1]), int(match[2])
    if "width" in keys and "height" in keys:
        try:
            return int(keys["width"]), int(keys["height"])
        except ValueError:
            raise ValueError(
                f"{path}: header width/height {keys['width']!r}/{keys['height']!r} are not integers"
            ) from None
    return None


def _raw_encoding(path: Path, lines: list[str]) -> str:
    """``"evt2"`` or ``"evt3"`` from the ``% evt`` or ``% format`` header line."""
    for line in lines:
        key, _, value = line.partition(" ")
        value = value.strip().upper()
        if key.lower() == "evt" and value in ("2.0", "3.0"):
            return "evt2" if value == "2.0" else "evt3"
        if key.lower() == "format":
            name = value.split(";", 1)[0]
            if name in ("EVT2", "EVT3"):
                return name.lower()
            raise ValueError(f"{path}: encoding {name!r} not supported; use EVT2 or EVT3")
    raise ValueError(f"{path}: header names no encoding; add '% evt 3.0' (or 2.0) to the header")


def read_prophesee_header(path: Path) -> ProphHeader:
    """Parse the header of a ``.raw`` or ``.dat`` file (ValueError if it is malformed)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: events file not found")
    with path.open("rb") as f:
        lines = _header_lines(f, path)
        if path.suffix.lower() == _RAW_SUFFIX:
            return ProphHeader(_raw_encoding(path, lines), _header_size(path, lines), f.tell())
        pair = f.read(2)
        if len(pair) < 2:
            raise damaged(path, "truncated after the header (no event type and size bytes)")
        kind, size = pair[0], pair[1]
        if kind not in _DAT_TYPES or size != _DAT_RECORD:
            raise ValueError(
                f"{path}: event type {kind}, size {size}; only CD events "
                f"(type 0 or 12, size {_DAT_RECORD}) are supported"
            )
        return ProphHeader("dat", _header_size(path, lines), f.tell(), kind)


@dataclass
class _State:
    """Decoder state carried across blocks (time in us, EVT3 row and vector base)."""

    time_high: int = -1  # unwrapped, in units of the encoding's high part; -1 until known
    last_raw: int = -1  # the last counter value as stored (to detect a wrap-around)
    time_low: int = -1
    wraps: int = 0
    y: int = -1
    base_x: int = -1
    base_p: int = 0
    words: int = 0  # words decoded so far (for error messages)


def _forward_fill(mask: np.ndarray, values: np.ndarray, initial: int) -> np.ndarray:
    """At each position, the value of the last position where ``mask`` holds (else initial)."""
    index = np.where(mask, np.arange(mask.size, dtype=np.int32), np.int32(-1))
    np.maximum.accumulate(index, out=index)
    return np.where(index >= 0, values[np.maximum(index, 0)], initial).astype(np.int64)


def _unwrap(values: np.ndarray, previous: int, wraps: int, period: int) -> tuple[np.ndarray, int]:
    """Counter values plus ``period`` per wrap-around (a drop of more than half the period)."""
    before = np.concatenate(([previous if previous >= 0 else values[:1].max(initial=0)], values))
    drops = np.cumsum(before[:-1] - before[1:] > period // 2) + wraps
    total = int(drops[-1]) if drops.size else wraps
    return values.astype(np.int64) + drops.astype(np.int64) * period, total


def _check_types(
    path: Path, types: np.ndarray, known: np.ndarray, state: _State, what: str
) -> None:
    """Raise a ValueError naming the first word whose type is reserved in this encoding."""
    valid = known[types]
    if not valid.all():
        bad = np.flatnonzero(~valid)
        k = int(bad[0])
        raise ValueError(
            f"{path}: word {state.words + k} has reserved type 0x{int(types[k]):X}; "
            f"not a valid {what} stream (corrupt file, or the header names the wrong encoding)"
        )


def _decode_evt2(path: Path, w: np.ndarray, state: _State) -> Arrays:
    """Events of a block of EVT 2.0 words (32-bit), updating ``state``."""
    types = (w >> 28).astype(np.uint8)
    _check_types(path, types, _EVT2_TYPES, state, "EVT 2.0")
    is_high = types == 0x8
    raw = (w[is_high] & 0x0FFFFFFF).astype(np.int64)
    highs, state.wraps = _unwrap(raw, state.last_raw, state.wraps, 1 << 28)
    full = np.zeros(w.size, np.int64)
    full[is_high] = highs
    high = _forward_fill(is_high, full, state.time_high)
    if highs.size:
        state.time_high, state.last_raw = int(highs[-1]), int(raw[-1])
    cd = (types <= 0x1) & (high >= 0)
    wc = w[cd].astype(np.int64)
    t = (high[cd] << 6) | ((wc >> 22) & 0x3F)
    p = np.where(types[cd] == 1, 1, -1).astype(np.int8)
    return t, (wc >> 11) & 0x7FF, wc & 0x7FF, p


def _evt3_vector_base(types: np.ndarray, payload: np.ndarray, state: _State) -> np.ndarray:
    """The base x of each word's vector (VECT_BASE_X, advanced by 12 / 8 per vector word)."""
    is_base = types == 0x3
    step = np.where(types == 0x4, 12, np.where(types == 0x5, 8, 0)).astype(np.int64)
    before = np.cumsum(step) - step  # advance accumulated before each word
    index = np.where(is_base, np.arange(types.size, dtype=np.int32), np.int32(-1))
    np.maximum.accumulate(index, out=index)
    has_base = index >= 0
    at = np.maximum(index, 0)
    base = np.where(has_base, (payload[at] & 0x7FF) + before - before[at], state.base_x + before)
    if state.base_x < 0:
        base = np.where(has_base, base, -1)
    if types.size:
        end = int(base[-1] + step[-1]) if base[-1] >= 0 else -1
        state.base_x = end
        bases = np.flatnonzero(is_base)
        if bases.size:
            state.base_p = int((payload[bases[-1]] >> 11) & 1)
    return base


def _decode_evt3(path: Path, w: np.ndarray, state: _State) -> Arrays:
    """Events of a block of EVT 3.0 words (16-bit), updating ``state``."""
    types = (w >> 12).astype(np.uint8)
    _check_types(path, types, _EVT3_TYPES, state, "EVT 3.0")
    payload = (w & 0xFFF).astype(np.int32)
    is_high, is_low, is_y = types == 0x8, types == 0x6, types == 0x0
    raw_highs = payload[is_high]
    highs, state.wraps = _unwrap(raw_highs, state.last_raw, state.wraps, 1 << 12)
    full = np.zeros(w.size, np.int64)
    full[is_high] = highs
    high = _forward_fill(is_high, full, state.time_high)
    # A TIME_HIGH that changes the time base restarts the low part at 0 (as Prophesee's and
    # faery's decoders do): an event may follow it without a TIME_LOW.
    new_high = raw_highs != np.concatenate(([state.last_raw], raw_highs[:-1]))
    sets_low = is_low.copy()
    sets_low[np.flatnonzero(is_high)[new_high]] = True
    low = _forward_fill(sets_low, np.where(is_low, payload, 0), state.time_low)
    y = _forward_fill(is_y, payload & 0x7FF, state.y)
    base_p0 = state.base_p
    base = _evt3_vector_base(types, payload, state)
    base_p = _forward_fill(types == 0x3, (payload >> 11) & 1, base_p0)
    if highs.size:
        state.time_high, state.last_raw = int(highs[-1]), int(payload[is_high][-1])
    if w.size:
        state.time_low, state.y = int(low[-1]), int(y[-1])
    single, vec12, vec8 = types == 0x2, types == 0x4, types == 0x5
    rows = np.flatnonzero((single | vec12 | vec8) & (high >= 0) & (low >= 0) & (y >= 0))
    rows = rows[~((vec12[rows] | vec8[rows]) & (base[rows] < 0))]
    masks = np.where(single[rows], 1, np.where(vec8[rows], payload[rows] & 0xFF, payload[rows]))
    bits = np.unpackbits(
        masks.astype("<u2").view(np.uint8).reshape(-1, 2), axis=1, bitorder="little"
    )
    r, bit = np.nonzero(bits[:, :12])
    word = rows[r]
    x = np.where(single[word], payload[word] & 0x7FF, base[word] + bit)
    p = np.where(single[word], (payload[word] >> 11) & 1, base_p[word])
    t = (high[word] << 12) | low[word]
    return t, x, y[word], np.where(p == 1, 1, -1).astype(np.int8)


def _decode_dat(path: Path, records: np.ndarray, state: _State) -> Arrays:
    """Events of a block of ``.dat`` records (uint32 timestamp, uint32 packed address)."""
    stamps, state.wraps = _unwrap(
        records[:, 0].astype(np.int64), state.last_raw, state.wraps, 1 << 32
    )
    if stamps.size:
        state.last_raw = int(records[-1, 0])
    data = records[:, 1].astype(np.int64)
    p = np.where((data >> 28) & 0xF, 1, -1).astype(np.int8)
    return stamps, data & 0x3FFF, (data >> 14) & 0x3FFF, p


def iter_prophesee_arrays(
    path: Path, header: ProphHeader, block_words: int = _BLOCK_WORDS
) -> Iterator[Arrays]:
    """Decoded ``(t_us, x, y, p)`` blocks of ``block_words`` words each, in file order."""
    item = {"evt2": np.dtype("<u4"), "evt3": np.dtype("<u2"), "dat": np.dtype("<u4")}
    dtype = item[header.encoding]
    unit = 2 * dtype.itemsize if header.encoding == "dat" else dtype.itemsize
    total = path.stat().st_size - header.data_offset
    if total % unit:
        raise damaged(
            path,
            f"truncated: {total} data bytes is not a whole number of "
            f"{unit}-byte {'records' if header.encoding == 'dat' else 'words'}",
        )
    state = _State()
    with path.open("rb") as f:
        f.seek(header.data_offset)
        while True:
            block = np.fromfile(f, dtype=dtype, count=block_words * (unit // dtype.itemsize))
            if not block.size:
                return
            if header.encoding == "dat":
                out = _decode_dat(path, block.reshape(-1, 2), state)
            elif header.encoding == "evt2":
                out = _decode_evt2(path, block, state)
            else:
                out = _decode_evt3(path, block, state)
            state.words += block.size
            yield out


def prophesee_sensor_size(path: Path) -> tuple[int, int] | None:
    """The sensor size of a ``.raw``/``.dat`` header (None if it names none)."""
    return read_prophesee_header(path).size


def prophesee_blocks(path: Path, size: tuple[int, int], block_events: int) -> Iterator[Block]:
    """The events of a ``.raw``/``.dat`` file, about ``block_events`` words a block, in seconds."""
    words = min(_BLOCK_WORDS, max(block_events, _MIN_BLOCK_WORDS))
    for t, x, y, p in iter_prophesee_arrays(path, read_prophesee_header(path), words):
        yield Block(t / 1e6, x, y, p)


def _dat_bytes(events: EventStream, t_us: np.ndarray) -> bytes:
    """``.dat`` header, type/size bytes and records for ``events``."""
    header = (
        "% Data file containing CD events\n% Version 2\n"
        f"% Width {events.width}\n% Height {events.height}\n"
    ).encode("ascii")
    records = np.empty((len(events), 2), "<u4")
    records[:, 0] = t_us & 0xFFFFFFFF
    records[:, 1] = events.x | (events.y.astype(np.int64) << 14) | ((events.p > 0) << 28)
    return header + bytes((12, _DAT_RECORD)) + records.tobytes()


def _bridges(high: np.ndarray, period: int) -> tuple[np.ndarray, np.ndarray]:
    """Extra TIME_HIGH values (unwrapped, ascending) across gaps, and the event each precedes.

    Between the events' own values: every quarter ``period`` and the last value before each
    wrap-around (from the start of the first event's period on), so every wrap shows as a
    drop of ``period - 1``, which every decoder counts, whatever the gap (Prophesee's OpenEB
    counts a drop of at least half the period, spatialseg more than half, faery's EVT 3.0
    decoder only a drop of ``period - 1``).
    """
    step = period // 4
    first, last = int(high[0]) - int(high[0]) % period, int(high[-1])
    candidates = np.union1d(
        np.arange(first, last + 1, step, dtype=np.int64),
        np.arange(first + period - 1, last + 1, period, dtype=np.int64),
    )
    before = np.searchsorted(high, candidates)  # the first event at or after each value
    extra = high[before] != candidates
    return candidates[extra], before[extra]


def _interleave(
    columns: list[np.ndarray],
    keep: list[np.ndarray],
    dtype: str,
    extra: tuple[np.ndarray, np.ndarray],
) -> bytes:
    """Words of several columns, row by row, keeping the entries ``keep`` marks, and the
    ``extra`` words ``(row, word)`` before the first word of their row, in the order given."""
    kept = np.stack(keep, axis=1)
    words = np.stack([c.astype(dtype) for c in columns], axis=1)[kept]
    per_row = kept.sum(axis=1)
    first_word = np.cumsum(per_row) - per_row
    rows, extra_words = extra
    return np.insert(words, first_word[rows], extra_words.astype(dtype)).tobytes()


def _evt2_bytes(events: EventStream, t_us: np.ndarray) -> bytes:
    """EVT 2.0 words: a TIME_HIGH whenever bits 33..6 change (and _bridges across gaps),
    then one CD word per event."""
    high = t_us >> 6
    new_high = np.concatenate(([True], high[1:] != high[:-1]))
    cd = (
        ((events.p > 0).astype(np.int64) << 28)
        | ((t_us & 0x3F) << 22)
        | (events.x.astype(np.int64) << 11)
        | events.y
    )
    values, before = _bridges(high, 1 << 28)
    extra = (before, (0x8 << 28) | (values & 0x0FFFFFFF))
    time_high = (0x8 << 28) | (high & 0x0FFFFFFF)
    return _interleave([time_high, cd], [new_high, np.ones_like(new_high)], "<u4", extra)


def _evt3_bytes(events: EventStream, t_us: np.ndarray) -> bytes:
    """EVT 3.0 words: TIME_HIGH (and _bridges across gaps), TIME_LOW, ADDR_Y when they
    change, then one ADDR_X per event."""
    high, low = t_us >> 12, t_us & 0xFFF
    new_high = np.concatenate(([True], high[1:] != high[:-1]))
    new_low = new_high | np.concatenate(([True], low[1:] != low[:-1]))
    new_y = new_high | np.concatenate(([True], events.y[1:] != events.y[:-1]))
    x_word = (0x2 << 12) | ((events.p > 0).astype(np.int64) << 11) | events.x
    columns = [(0x8 << 12) | (high & 0xFFF), (0x6 << 12) | low, events.y.astype(np.int64), x_word]
    keep = [new_high, new_low, new_y, np.ones_like(new_y)]
    values, before = _bridges(high, 1 << 12)
    return _interleave(columns, keep, "<u2", (before, (0x8 << 12) | (values & 0xFFF)))


def write_prophesee(events: EventStream, path: str | Path, *, encoding: str = "evt3") -> None:
    """Write events atomically as ``.raw`` (``encoding`` evt2 or evt3) or ``.dat`` (by suffix).

    Times are rounded to whole microseconds and must be >= 0. Meant for tests and for
    converting recordings; EVT 3.0 is written without vector words (valid, not compact).
    Gaps of any length are kept; the formats store times modulo 2**24 us (EVT 3.0), 2**34 us
    (EVT 2.0) or 2**32 us (``.dat``), so a first event later than that reads back earlier
    by whole periods, and ``.dat`` keeps only gaps shorter than 2**31 us (35.8 min).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (_RAW_SUFFIX, _DAT_SUFFIX) or encoding not in ("evt2", "evt3"):
        raise ValueError(f"{path}: write .raw (encoding 'evt2' or 'evt3') or .dat files")
    t_us = np.round(events.t * 1e6).astype(np.int64)
    if t_us.size and t_us[0] < 0:
        raise ValueError(f"{path}: negative timestamps cannot be written; shift the times")
    if suffix == _DAT_SUFFIX:
        body = _dat_bytes(events, t_us)
    else:
        name = encoding.upper()
        version = "2.0" if encoding == "evt2" else "3.0"
        header = (
            f"% evt {version}\n% format {name};height={events.height};width={events.width}\n"
            f"% geometry {events.width}x{events.height}\n% end\n"
        ).encode("ascii")
        words = _evt2_bytes if encoding == "evt2" else _evt3_bytes
        body = header + (words(events, t_us) if len(events) else b"")
    with atomic_file(path) as tmp, tmp.open("xb") as f:
        f.write(body)
