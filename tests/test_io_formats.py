"""The reader registry (``spatialseg.io._formats``): every registered format reads, whole and
in chunks, the events written to it; an unknown suffix is one line naming the supported ones;
a format registered here is read by ``read_any`` and ``iter_event_chunks`` with no other edit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import faery
import numpy as np
import pytest

import spatialseg.io as sio
from spatialseg.events import EventStream
from spatialseg.io import (
    Block,
    _formats,
    event_formats,
    iter_event_chunks,
    read_any,
    register_format,
    write_events,
    write_prophesee,
)
from spatialseg.recording import Camera

W, H = 64, 48
CAMERA = Camera(60.0, 60.0, 31.5, 23.5, W, H)


def _faery_aedat4(events: EventStream, path: Path) -> None:
    """An AEDAT4 file written by faery (spatialseg writes none), times in whole microseconds."""
    array = np.zeros(len(events), faery.EVENTS_DTYPE)
    array["t"] = np.round(events.t * 1e6).astype(np.uint64)
    array["x"], array["y"], array["on"] = events.x, events.y, events.p > 0
    faery.events_stream_from_array(array, (W, H)).to_file(path, zero_t0=False)


#: A writer for each registered format: a format added to the registry needs one here.
WRITERS: dict[str, Callable[[EventStream, Path], None]] = {
    "txt": write_events,
    "h5": write_events,
    "npz": write_events,
    "aedat4": _faery_aedat4,
    "raw": write_prophesee,
    "dat": write_prophesee,
}


def _events(n: int = 40, seed: int = 0) -> EventStream:
    """Random sorted events from t = 0 (AEDAT4 reads times from its first event) in whole
    microseconds, with repeated times, both polarities and both sensor corners."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 5_000, n))
    t[0] = 0
    x, y = rng.integers(0, W, n), rng.integers(0, H, n)
    x[:2], y[:2] = [0, W - 1], [0, H - 1]
    return EventStream(x, y, t / 1e6, rng.choice([-1, 1], n), W, H)


def _joined(chunks: list[EventStream]) -> EventStream:
    """The chunks as one stream."""
    columns = [np.concatenate([getattr(c, a) for c in chunks]) for a in "xytp"]
    return EventStream(*columns, chunks[0].width, chunks[0].height)


def _same(read: EventStream, written: EventStream) -> None:
    """The same sensor size and, per event, the same time, pixel and polarity."""
    assert (read.width, read.height) == (written.width, written.height)
    for name in ("t", "x", "y", "p"):
        np.testing.assert_array_equal(getattr(read, name), getattr(written, name), err_msg=name)


@pytest.mark.parametrize("entry", event_formats(), ids=lambda entry: entry.name)
def test_every_format_reads_what_was_written_whole_and_in_chunks(
    tmp_path: Path, entry: _formats.EventFormat
) -> None:
    assert entry.name in WRITERS, f"add a writer of format {entry.name!r} to WRITERS"
    events = _events()
    path = tmp_path / f"e{entry.suffixes[0]}"
    WRITERS[entry.name](events, path)
    _same(read_any(path, camera=CAMERA).events, events)
    chunks = list(iter_event_chunks(path, 3, width=W, height=H))
    assert [len(c) for c in chunks] == [3] * 13 + [1]
    _same(_joined(chunks), events)


def test_an_unknown_suffix_is_one_line_naming_every_format(tmp_path: Path) -> None:
    path = tmp_path / "e.bag"
    path.write_bytes(b"x")
    expected = f"{path}: unknown file type '.bag'; supported: {sio.SUPPORTED}"
    for read in (lambda: read_any(path, fov_deg=60.0), lambda: iter_event_chunks(path, 5)):
        with pytest.raises(ValueError) as exc:
            read()
        assert str(exc.value) == expected
    for entry in event_formats():
        assert entry.label in sio.SUPPORTED


def _toy_blocks(path: Path, size: tuple[int, int], block_events: int) -> Iterator[Block]:
    """A ``.toy`` file: uint32 width and height, then float64 rows ``t x y p`` (p 0/1)."""
    rows = np.fromfile(path, "<f8", offset=8).reshape(-1, 4)
    for start in range(0, len(rows), block_events):
        yield Block(*rows[start : start + block_events].T)


def _toy_size(path: Path) -> tuple[int, int]:
    """The toy file's stored sensor size."""
    width, height = np.fromfile(path, "<u4", 2)
    return int(width), int(height)


@pytest.fixture
def toy(monkeypatch: pytest.MonkeyPatch) -> None:
    """The ``.toy`` format registered for one test (the registry is restored after it)."""
    monkeypatch.setattr(_formats, "_FORMATS", dict(_formats._FORMATS))
    register_format("toy", [".toy"], sensor_size=_toy_size, description="a test")(_toy_blocks)


def test_a_registered_format_is_read_with_no_other_edit(tmp_path: Path, toy: None) -> None:
    events = _events(25)
    rows = np.column_stack([events.t, events.x, events.y, events.p > 0]).astype("<f8")
    path = tmp_path / "e.TOY"
    path.write_bytes(np.array([W, H], "<u4").tobytes() + rows.tobytes())
    recording = read_any(path, fov_deg=60.0)
    _same(recording.events, events)
    assert recording.name == "e" and recording.camera.width == W
    chunks = list(iter_event_chunks(path, 4))
    assert [len(c) for c in chunks] == [4] * 6 + [1]
    _same(
        EventStream(*[np.concatenate([getattr(c, a) for c in chunks]) for a in "xytp"], W, H),
        events,
    )
    assert sio.SUPPORTED.endswith(", .toy (a test)")
    with pytest.raises(ValueError, match=r"format 'other': \['\.toy'\] already read as 'toy'"):
        register_format("other", [".toy"])(_toy_blocks)
    with pytest.raises(ValueError, match=r"give a name and suffixes like '\.txt'"):
        register_format("bare", ["toy"])(_toy_blocks)
