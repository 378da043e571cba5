"""Reading events window by window: chunks equal the whole read for every format, and
streaming a few-million-event file holds a fraction of the memory of reading it whole."""

from __future__ import annotations

import gc
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from spatialseg.events import EventStream
from spatialseg.io import (
    iter_event_chunks,
    read_any,
    write_events,
    write_prophesee,
    write_recording,
)
from spatialseg.recording import Camera, Recording

W, H = 346, 260
CAMERA = Camera(200.0, 200.0, 172.5, 129.5, W, H)
WRITERS = {".txt": write_events, ".h5": write_events, ".npz": write_events}


def _events(n: int, seed: int = 0) -> EventStream:
    """Random sorted events with whole-microsecond times (all formats store them exactly)."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 10 * n, n)) / 1e6
    return EventStream(
        rng.integers(0, W, n), rng.integers(0, H, n), t, rng.choice([-1, 1], n), W, H
    )


def _write(events: EventStream, path: Path) -> Path:
    """Write ``events`` in the format ``path``'s suffix names."""
    if path.suffix in (".raw", ".dat"):
        write_prophesee(events, path)
    else:
        write_events(events, path)
    return path


@pytest.mark.parametrize("suffix", [".txt", ".h5", ".npz", ".raw", ".dat"])
@pytest.mark.parametrize("chunk", [1, 7, 150, 1000])
def test_chunks_join_to_the_whole_read(tmp_path: Path, suffix: str, chunk: int) -> None:
    events = _events(400)
    path = _write(events, tmp_path / f"e{suffix}")
    chunks = list(iter_event_chunks(path, chunk, width=W, height=H))
    assert [len(c) for c in chunks[:-1]] == [chunk] * (len(chunks) - 1)
    assert 0 < len(chunks[-1]) <= chunk
    whole = read_any(path, camera=CAMERA).events
    for name in ("t", "x", "y", "p"):
        joined = np.concatenate([getattr(c, name) for c in chunks])
        np.testing.assert_array_equal(joined, getattr(whole, name), err_msg=name)


def test_recording_directory_streams_its_events_file(tmp_path: Path) -> None:
    events = _events(1000)
    write_recording(Recording(events, CAMERA), tmp_path / "r", events_format="npz")
    chunks = list(iter_event_chunks(tmp_path / "r", 300))
    assert [len(c) for c in chunks] == [300, 300, 300, 100]
    np.testing.assert_array_equal(np.concatenate([c.t for c in chunks]), events.t)


def test_bad_txt_line_is_named_with_its_line_number(tmp_path: Path) -> None:
    lines = [f"{i * 1e-3!r} 1 2 1" for i in range(50)]
    lines[37] = "0.037 1 400 1"  # y outside the 260-row sensor
    (tmp_path / "e.txt").write_text("# t x y p\n" + "\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"e\.txt line 39: y=400 is outside the sensor"):
        list(iter_event_chunks(tmp_path / "e.txt", 10, width=W, height=H))


def test_polarity_conventions_cannot_mix_across_chunks(tmp_path: Path) -> None:
    """A text file's mix is named by its lines however the file is cut; a binary one's by the
    polarity that changed convention from one chunk to the next."""
    (tmp_path / "e.txt").write_text("0.1 1 1 0\n0.2 1 1 1\n0.3 1 1 -1\n")
    for chunk in (1, 2, 3):
        with pytest.raises(ValueError, match=r"e\.txt line 3: polarity -1 but line 1 has 0; use"):
            list(iter_event_chunks(tmp_path / "e.txt", chunk, width=W, height=H))
    np.savez(tmp_path / "e.npz", t=[0.1, 0.2, 0.3], x=[1, 1, 1], y=[1, 1, 1], p=[0, 1, -1])
    with pytest.raises(ValueError, match="polarity -1 after 0 earlier; use 0/1 or -1/"):
        list(iter_event_chunks(tmp_path / "e.npz", 2, width=W, height=H))


def test_bad_chunk_size_and_missing_size(tmp_path: Path) -> None:
    path = _write(_events(10), tmp_path / "e.txt")
    with pytest.raises(ValueError, match="chunk_events=0; give a positive integer"):
        iter_event_chunks(path, 0, width=W, height=H)
    with pytest.raises(ValueError, match="sensor size unknown"):
        iter_event_chunks(path, 5)


def _peak(task: Callable[[], object]) -> tuple[int, object]:
    """Peak memory traced by tracemalloc (numpy arrays included) while ``task`` runs, and
    what it returned (the whole read is dropped before the streaming run starts)."""
    gc.collect()
    tracemalloc.start()
    try:
        result = task()
        return tracemalloc.get_traced_memory()[1], result
    finally:
        tracemalloc.stop()


def _stream_through(path: Path, chunk: int) -> int:
    """Stream every chunk (as a consumer would), keeping only a count."""
    return sum(len(c) for c in iter_event_chunks(path, chunk))


@pytest.mark.parametrize(("suffix", "n"), [(".h5", 2_000_000), (".raw", 1_000_000)])
def test_streaming_holds_a_fraction_of_the_whole_read(tmp_path: Path, suffix: str, n: int) -> None:
    path = _write(_events(n, seed=1), tmp_path / f"big{suffix}")
    whole, _ = _peak(lambda: len(read_any(path, camera=CAMERA).events))
    streamed, count = _peak(lambda: _stream_through(path, 100_000))
    assert count == n
    assert whole > 17 * n  # t, x, y, p alone take 17 bytes per event
    assert streamed < whole / 4, (streamed, whole)


@pytest.mark.parametrize(
    ("n", "sizes"), [(2300, [1000, 1300]), (2600, [1000, 1000, 600]), (300, [300])]
)
def test_stream_scene_joins_a_short_last_chunk(tmp_path: Path, n: int, sizes: list[int]) -> None:
    """A last chunk under half a window joins the one before it (as in-memory windows do),
    so no streamed window is a handful of events; every event is kept, in order."""
    from spatialseg.scenes import stream_scene

    events = _events(n)
    path = _write(events, tmp_path / "e.npz")
    scene = {"kind": "recording", "path": str(path), "fov_deg": 60.0, "camera": None}
    windows = list(stream_scene(scene, window_events=1000))
    assert [len(w.events) for w in windows] == sizes
    joined = np.concatenate([w.events.t for w in windows])
    np.testing.assert_array_equal(joined, events.t)
