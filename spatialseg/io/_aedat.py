"""AEDAT4 files (iniVation DV) decoded with the ``aedat`` package: events and APS frames.

The file's first ``events`` stream gives the events and the sensor size; its first
``frame`` stream, if any, the keyframes (grayscale; colour frames are kept as RGB). IMU and
trigger packets are skipped. AEDAT4 stores Unix time in microseconds; spatialseg times are
seconds since the file's first event (a float64 of Unix seconds would keep only ~0.2 us).

The Rust decoder trusts the header's flatbuffer and panics, or aborts the interpreter, on
some damaged ones: the header (offsets, compression, UTF-8 description, where the packets
end) is checked here first, and each packet is checked to fit in the file before it is
decoded. What the decoder still raises, a Rust panic included, becomes one ValueError.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from spatialseg.io._decode import Block, damaged, decoding
from spatialseg.recording import Keyframe

__all__ = [
    "AedatHeader",
    "aedat_blocks",
    "aedat_info",
    "aedat_sensor_size",
    "read_aedat_header",
]

_MAGIC = b"#!AER-DAT4.0\r\n"
_PREFIX = len(_MAGIC) + 4  # the magic, then the header's length (uint32)
_COMPRESSIONS = range(5)  # none, LZ4, LZ4 high, Zstd, Zstd high
_MIN_PACKET = 12  # size prefix, root offset and identifier of a packet's flatbuffer

AedatInfo = tuple[int, tuple[int, int], int | None]  # events stream id, (W, H), frame stream id


@dataclass(frozen=True)
class AedatHeader:
    """An AEDAT4 header, checked so the decoder can trust it: where the packets lie."""

    data_start: int  # byte of the first packet
    packets_end: int  # byte after the last packet (the file data table, or the file's end)
    compression: int  # 0 none, 1-2 LZ4, 3-4 Zstd


def _scalar(path: Path, header: bytes, fmt: str, at: int, what: str) -> int:
    """A little-endian number of the header's flatbuffer at byte ``at``, bounds-checked."""
    if not 0 <= at <= len(header) - struct.calcsize(fmt):
        raise damaged(
            path, f"{what} at byte {at} lies outside the {len(header)}-byte header", "header"
        )
    return struct.unpack_from(fmt, header, at)[0]


def _table_fields(path: Path, header: bytes) -> dict[int, int]:
    """Where each present field of the header's root flatbuffer table lies, by field number."""
    table = _scalar(path, header, "<I", 0, "the root table offset")
    vtable = table - _scalar(path, header, "<i", table, "the root table")
    size = _scalar(path, header, "<H", vtable, "the vtable")
    if size < 4 or size % 2:
        raise damaged(path, f"the header's vtable claims {size} bytes", "header")
    slots = [_scalar(path, header, "<H", vtable + at, "the vtable") for at in range(4, size, 2)]
    return {field: table + slot for field, slot in enumerate(slots) if slot}


def _description(path: Path, header: bytes, at: int | None) -> str:
    """The header's XML description (a flatbuffer string at ``at``), checked to be UTF-8."""
    if at is None:
        raise damaged(path, "the header has no stream description", "header")
    start = at + _scalar(path, header, "<I", at, "the description offset")
    length = _scalar(path, header, "<I", start, "the description")
    text = header[start + 4 : start + 4 + length]
    if len(text) != length:
        raise damaged(path, f"the {length}-byte description runs past the header", "header")
    try:
        return text.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise damaged(path, f"the description is not UTF-8 text ({exc})", "header") from None


def _header_bytes(path: Path, f: BinaryIO, size: int) -> bytes:
    """The IOHeader flatbuffer after the magic and its length, checked to fit in ``size``."""
    if f.read(len(_MAGIC)) != _MAGIC:
        raise damaged(path, "not an AEDAT4 file (it does not start with #!AER-DAT4.0)")
    raw = f.read(4)
    length = struct.unpack("<I", raw)[0] if len(raw) == 4 else -1
    if not 0 <= length <= size - _PREFIX:
        raise damaged(path, f"the header ({length} bytes) ends past the end of the file", "header")
    return f.read(length)


def read_aedat_header(path: Path) -> AedatHeader:
    """Check what the Rust decoder would trust (it panics or aborts on some damaged headers)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: events file not found")
    size = path.stat().st_size
    with path.open("rb") as f:
        header = _header_bytes(path, f, size)
    fields = _table_fields(path, header)
    compression = _scalar(path, header, "<i", fields[0], "compression") if 0 in fields else 0
    end = _scalar(path, header, "<q", fields[1], "the data table position") if 1 in fields else -1
    _description(path, header, fields.get(2))
    start = _PREFIX + len(header)
    if compression not in _COMPRESSIONS:
        raise damaged(path, f"unknown compression {compression}", "header")
    if end != -1 and not start <= end <= size:
        raise damaged(path, f"the packets end at byte {end}, outside {start}..{size}", "header")
    return AedatHeader(start, size if end == -1 else end, compression)


def _decoder(path: Path) -> tuple[Any, AedatHeader]:
    """An ``aedat.Decoder`` for ``path`` (after checking its header) and the header."""
    import aedat

    header = read_aedat_header(path)
    with decoding(path, "AEDAT4", "header"):
        return aedat.Decoder(str(path)), header


def aedat_info(path: Path) -> AedatInfo:
    """The ids of the first events and frame streams and the events' sensor size."""
    decoder, _ = _decoder(path)
    with decoding(path, "AEDAT4", "header"):
        streams = decoder.id_to_stream()
    events = sorted(k for k, s in streams.items() if s.get("type") == "events")
    frames = sorted(k for k, s in streams.items() if s.get("type") == "frame")
    if not events:
        kinds = sorted({str(s.get("type")) for s in streams.values()})
        raise ValueError(f"{path}: no events stream (streams: {', '.join(kinds) or 'none'})")
    stream = streams[events[0]]
    return events[0], (int(stream["width"]), int(stream["height"])), (frames or [None])[0]


def _packet_size(path: Path, f: BinaryIO, offset: int, header: AedatHeader, where: str) -> int:
    """The size of the packet at ``offset`` (its 8-byte head included), checked to fit."""
    left = header.packets_end - offset
    f.seek(offset + 4)
    raw = f.read(4)
    length = struct.unpack("<I", raw)[0] if left >= 8 and len(raw) == 4 else 0
    if left < 8 or 8 + length > left:
        problem = f"the packet needs {8 + length} bytes, only {max(left, 0)} are left"
        raise damaged(path, problem, where)
    if header.compression == 0 and length < _MIN_PACKET:
        raise damaged(path, f"a {length}-byte packet is too short for its flatbuffer", where)
    return 8 + length


def iter_aedat_packets(path: Path) -> Iterator[dict[str, Any]]:
    """The decoded packets of a file, each checked to fit before the decoder reads it."""
    decoder, header = _decoder(path)
    offset, index = header.data_start, 0
    with path.open("rb") as f:
        while offset < header.packets_end:
            where = f"packet {index} at byte {offset}"
            size = _packet_size(path, f, offset, header, where)
            with decoding(path, "AEDAT4", where):
                packet = next(decoder)
            offset, index = offset + size, index + 1
            yield packet


def _packet_events(packet: dict[str, Any]) -> tuple[np.ndarray, ...]:
    """``(t_us, x, y, p)`` of one events packet; polarity ``on`` becomes +1, off -1."""
    e = packet["events"]
    return e["t"].astype(np.int64), e["x"], e["y"], np.where(e["on"], 1, -1).astype(np.int8)


def _frame_image(frame: dict[str, Any]) -> np.ndarray:
    """A frame's pixels as uint8 (H, W) grayscale or (H, W, 3) colour (alpha dropped)."""
    pixels = np.asarray(frame["pixels"])
    if pixels.dtype != np.uint8:  # 16-bit frames: keep the high byte
        pixels = (pixels.astype(np.uint32) >> (8 * (pixels.itemsize - 1))).astype(np.uint8)
    if pixels.ndim == 3:
        pixels = pixels[..., 0] if pixels.shape[2] == 1 else pixels[..., :3]
    return np.ascontiguousarray(pixels)


def aedat_sensor_size(path: Path) -> tuple[int, int]:
    """The sensor size of the file's first events stream."""
    return aedat_info(path)[1]


def _keyframes(frames: list[tuple[int, np.ndarray]], origin: int, path: Path) -> Block:
    """A block of no events carrying ``(t_us, image)`` frames as keyframes, from ``origin``."""
    none = np.empty(0, np.int32)
    found = tuple(Keyframe((t - origin) / 1e6, image, str(path)) for t, image in frames)
    return Block(np.empty(0), none, none, none.astype(np.int8), found)


def aedat_blocks(path: Path, size: tuple[int, int], block_events: int) -> Iterator[Block]:
    """Each events packet, and the frames as keyframes, in one pass; times in seconds since the
    first event (or, in a file without events, the first frame: frames wait for the origin)."""
    events_id, _, frames_id = aedat_info(path)
    origin: int | None = None
    frames: list[tuple[int, np.ndarray]] = []  # (t_us, image) not yet given out
    for packet in iter_aedat_packets(path):
        sid = packet.get("stream_id")
        if sid == events_id and "events" in packet:
            t, x, y, p = _packet_events(packet)
            if origin is None and t.size:
                origin = int(t[0])
            yield Block((t - (origin or 0)) / 1e6, x, y, p)
        elif sid == frames_id and "frame" in packet:
            frames.append((int(packet["frame"]["t"]), _frame_image(packet["frame"])))
        if frames and origin is not None:
            yield _keyframes(frames, origin, path)
            frames = []
    if frames:
        yield _keyframes(frames, frames[0][0], path)
