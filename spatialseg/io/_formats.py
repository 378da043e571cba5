"""The event-file formats, one registry entry each: its suffixes, its sensor size and its one
decoder, from which both the whole-file read and the streamed read come.

A decoder yields the events of a file in bounded :class:`~spatialseg.io._decode.Block`\\ s;
:func:`read_whole` concatenates them (``read_any``, ``read_events``, ``read_recording``) and
``iter_event_chunks`` regroups them into chunks, so the two reads cannot disagree. Adding a
format is one :func:`register_format`; the built-in ones are registered at the end of this
module, in the order error messages list them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spatialseg.events import EventStream, normalise_polarity
from spatialseg.io._aedat import aedat_blocks, aedat_sensor_size
from spatialseg.io._decode import Block
from spatialseg.io._events import h5_blocks, h5_sensor_size, npz_blocks, npz_sensor_size
from spatialseg.io._prophesee import prophesee_blocks, prophesee_sensor_size
from spatialseg.io._text import txt_blocks
from spatialseg.recording import Keyframe

__all__ = [
    "Decoder",
    "EventFormat",
    "event_formats",
    "format_for",
    "read_whole",
    "register_format",
    "signed_polarity",
    "stored_size",
    "supported",
]

Size = tuple[int, int]
#: A decoder: ``(path, size, block_events)`` -> the file's events in file order, in blocks of
#: at most about ``block_events`` (an AEDAT4 packet, a block of Prophesee words). A whole read
#: asks for up to ``2**24`` at a time: read what the file holds, do not allocate that many.
Decoder = Callable[[Path, Size, int], Iterator[Block]]
#: The sensor size ``(width, height)`` a file stores, or None if it stores none.
SensorSize = Callable[[Path], Size | None]
#: Events per block of a whole-file read: files up to 16.8M events (0.3 GB as an EventStream)
#: come in one block, so joining blocks costs no copy; decoders bound their own further
#: (text lines, Prophesee words).
_WHOLE_BLOCK = 1 << 24
_NO_EVENTS = (np.empty(0), np.empty(0, np.int32), np.empty(0, np.int32), np.empty(0, np.int8))


def signed_polarity(p: np.ndarray, source: str) -> np.ndarray:
    """``p`` as int8 -1/+1 (:func:`normalise_polarity`), at once if it is so already (as the
    camera formats' decoders give it: normalising costs a sort)."""
    if p.dtype == np.int8 and np.all((p == 1) | (p == -1)):
        return p
    return normalise_polarity(p, source)


def _not_stored(path: Path) -> None:
    """The sensor size of a format that does not store it: none (the caller gives it)."""
    return None


@dataclass(frozen=True)
class EventFormat:
    """One registered event-file format (see :func:`register_format`)."""

    name: str
    suffixes: tuple[str, ...]
    decode: Decoder
    sensor_size: SensorSize = _not_stored
    description: str = ""

    @property
    def label(self) -> str:
        """The suffixes and description, as messages list them: ``.raw (Prophesee EVT 2.0/3.0)``."""
        suffixes = "/".join(self.suffixes)
        return f"{suffixes} ({self.description})" if self.description else suffixes


_FORMATS: dict[str, EventFormat] = {}


def register_format(
    name: str,
    suffixes: Sequence[str],
    *,
    sensor_size: SensorSize | None = None,
    description: str = "",
) -> Callable[[Decoder], Decoder]:
    """Decorator: read files ending in ``suffixes`` with the decorated :data:`Decoder`, whole
    (:func:`~spatialseg.io.read_any`) and streamed (:func:`~spatialseg.io.iter_event_chunks`);
    nothing else is needed::

        @register_format("toy", [".toy"], sensor_size=lambda path: (64, 48))
        def toy_blocks(path, size, block_events):
            rows = np.loadtxt(path, ndmin=2)  # t x y p per line
            for start in range(0, len(rows), block_events):
                yield Block(*rows[start : start + block_events].T)

    ``sensor_size`` reads the size the file stores (None: the caller must give it);
    ``description`` follows the suffixes in messages, e.g. ``.aedat4 (iniVation DV)``."""
    keys = tuple(str(s).lower() for s in suffixes)
    if not name or not keys or not all(k.startswith(".") and len(k) > 1 for k in keys):
        raise ValueError(f"format {name!r}: give a name and suffixes like '.txt', got {suffixes!r}")

    def register(decode: Decoder) -> Decoder:
        entry = EventFormat(name, keys, decode, sensor_size or _not_stored, description)
        for other in _FORMATS.values():
            taken = set(keys) & set(other.suffixes)
            if other.name != name and taken:
                raise ValueError(f"format {name!r}: {sorted(taken)} already read as {other.name!r}")
        if name in _FORMATS and _FORMATS[name] != entry:
            raise ValueError(f"format {name!r} is already registered by {_FORMATS[name].decode}")
        _FORMATS[name] = entry
        return decode

    return register


def event_formats() -> tuple[EventFormat, ...]:
    """The registered formats, in the order they were registered."""
    return tuple(_FORMATS.values())


def supported() -> str:
    """What :func:`~spatialseg.io.read_any` reads, for messages: directories and each format."""
    return ", ".join(["a recording directory", *(f.label for f in event_formats())])


def format_for(path: Path) -> EventFormat:
    """The format ``path``'s suffix names; one line naming the supported ones otherwise."""
    suffix = path.suffix.lower()
    for entry in _FORMATS.values():
        if suffix in entry.suffixes:
            return entry
    raise ValueError(f"{path}: unknown file type {path.suffix!r}; supported: {supported()}")


def stored_size(path: Path) -> Size | None:
    """The sensor size an events file stores (its header or attributes), or None."""
    return format_for(path).sensor_size(path)


def read_whole(path: Path, size: Size) -> tuple[EventStream, tuple[Keyframe, ...]]:
    """All events of an events file (validated together) and its keyframes, by its decoder."""
    blocks = list(format_for(path).decode(path, size, _WHOLE_BLOCK))
    columns = [block[:4] for block in blocks if len(block.t)] or [_NO_EVENTS]
    t, x, y, p = (c[0] if len(c) == 1 else np.concatenate(c) for c in zip(*columns, strict=True))
    events = EventStream(x, y, t, signed_polarity(p, str(path)), *size, source=str(path))
    return events, tuple(k for block in blocks for k in block.keyframes)


register_format("txt", [".txt"])(txt_blocks)
register_format("h5", [".h5", ".hdf5"], sensor_size=h5_sensor_size)(h5_blocks)
register_format("npz", [".npz"], sensor_size=npz_sensor_size)(npz_blocks)
register_format("aedat4", [".aedat4"], sensor_size=aedat_sensor_size, description="iniVation DV")(
    aedat_blocks
)
register_format(
    "raw", [".raw"], sensor_size=prophesee_sensor_size, description="Prophesee EVT 2.0/3.0"
)(prophesee_blocks)
register_format("dat", [".dat"], sensor_size=prophesee_sensor_size, description="Prophesee DAT")(
    prophesee_blocks
)
