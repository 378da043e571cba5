"""AEDAT4 files (iniVation DV) decoded with the ``aedat`` package: events and APS frames.

The file's first ``events`` stream gives the events and the sensor size; its first
``frame`` stream, if any, the keyframes (grayscale; colour frames are kept as RGB). IMU and
trigger packets are skipped. AEDAT4 stores Unix time in microseconds; spatialseg times are
seconds since the file's first event (a float64 of Unix seconds would keep only ~0.2 us).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from spatialseg.events import EventStream
from spatialseg.recording import Keyframe

__all__ = ["aedat_info", "iter_aedat_events", "read_aedat"]

_MAGIC = b"#!AER-DAT4.0"

AedatInfo = tuple[int, tuple[int, int], int | None]  # events stream id, (W, H), frame stream id
_EMPTY = (np.empty(0, np.int64), np.empty(0, np.int32), np.empty(0, np.int32), np.empty(0, np.int8))


def _decoder(path: Path) -> Any:
    """An ``aedat.Decoder`` for ``path``, or a one-line error naming the problem."""
    import aedat

    if not path.is_file():
        raise FileNotFoundError(f"{path}: events file not found")
    with path.open("rb") as f:
        magic = f.read(len(_MAGIC))
    if magic != _MAGIC:
        raise ValueError(f"{path}: not an AEDAT4 file (it does not start with {_MAGIC.decode()})")
    try:
        return aedat.Decoder(str(path))
    except RuntimeError as exc:
        raise ValueError(f"{path}: cannot read as AEDAT4 ({exc}); the file is corrupt") from None


def aedat_info(path: Path) -> AedatInfo:
    """The ids of the first events and frame streams and the events' sensor size."""
    streams = _decoder(path).id_to_stream()
    events = sorted(k for k, s in streams.items() if s.get("type") == "events")
    frames = sorted(k for k, s in streams.items() if s.get("type") == "frame")
    if not events:
        kinds = sorted({str(s.get("type")) for s in streams.values()})
        raise ValueError(f"{path}: no events stream (streams: {', '.join(kinds) or 'none'})")
    stream = streams[events[0]]
    return events[0], (int(stream["width"]), int(stream["height"])), (frames or [None])[0]


def iter_aedat_packets(path: Path) -> Iterator[dict[str, Any]]:
    """The decoded packets of a file; a decoding failure (truncation) becomes a ValueError."""
    decoder = _decoder(path)
    index = 0
    while True:
        try:
            packet = next(decoder)
        except StopIteration:
            return
        except RuntimeError as exc:
            raise ValueError(
                f"{path}: packet {index} cannot be decoded ({exc}); "
                "the file is truncated or corrupt"
            ) from None
        index += 1
        yield packet


def iter_aedat_events(path: Path, stream_id: int) -> Iterator[tuple[np.ndarray, ...]]:
    """``(t_us, x, y, p)`` arrays of each events packet of stream ``stream_id`` (t absolute)."""
    for packet in iter_aedat_packets(path):
        if packet.get("stream_id") == stream_id and "events" in packet:
            yield _packet_events(packet)


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


def read_aedat(path: Path) -> tuple[EventStream, list[Keyframe]]:
    """All events and frames of a file, in one pass; times in seconds since the first event."""
    events_id, (width, height), frames_id = aedat_info(path)
    parts: list[tuple[np.ndarray, ...]] = []
    frames: list[tuple[int, np.ndarray]] = []
    for packet in iter_aedat_packets(path):
        sid = packet.get("stream_id")
        if sid == events_id and "events" in packet:
            parts.append(_packet_events(packet))
        elif sid == frames_id and "frame" in packet:
            frames.append((int(packet["frame"]["t"]), _frame_image(packet["frame"])))
    t, x, y, p = (np.concatenate(c) for c in zip(*parts, strict=True)) if parts else _EMPTY
    origin = int(t[0]) if t.size else (frames[0][0] if frames else 0)
    events = EventStream(x, y, (t - origin) / 1e6, p, width, height, str(path))
    keyframes = [Keyframe((ft - origin) / 1e6, image, str(path)) for ft, image in frames]
    return events, keyframes
