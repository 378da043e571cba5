"""Bare event files: round trips (.txt, .h5, .hdf5, .npz), DSEC HDF5, and malformed input."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

import spatialseg.io._events as io_events
import spatialseg.io._text as text_io
from spatialseg.events import EventStream
from spatialseg.io import iter_event_chunks, read_events, write_events

W, H = 6, 4


def _stream(n: int = 40, seed: int = 0) -> EventStream:
    """Random events with awkward float times (they must round-trip bit-exact)."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0.0, 1.0, n)) + 1e3 / 3
    return EventStream(
        rng.integers(0, W, n), rng.integers(0, H, n), t, rng.choice([-1, 1], n), W, H
    )


def _same(a: EventStream, b: EventStream) -> None:
    """Equal events, bit for bit, and equal sensor size."""
    assert (a.width, a.height) == (b.width, b.height)
    for name in ("t", "x", "y", "p"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.parametrize("suffix", [".txt", ".h5", ".hdf5", ".npz"])
def test_round_trip(tmp_path: Path, suffix: str) -> None:
    events = _stream()
    path = tmp_path / f"events{suffix}"
    write_events(events, path)
    size = {"width": W, "height": H} if suffix == ".txt" else {}
    back = read_events(path, **size)
    _same(events, back)
    assert back.source == str(path)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary left behind


def test_write_creates_parent_directories(tmp_path: Path) -> None:
    path = tmp_path / "a" / "b" / "events.h5"
    write_events(_stream(), path)
    _same(_stream(), read_events(path))


@pytest.mark.parametrize("suffix", [".txt", ".h5", ".npz"])
def test_round_trip_empty(tmp_path: Path, suffix: str) -> None:
    events = _stream(0)
    write_events(events, tmp_path / f"e{suffix}")
    assert len(read_events(tmp_path / f"e{suffix}", width=W, height=H)) == 0


def test_txt_accepts_comments_blank_lines_and_signed_polarity(tmp_path: Path) -> None:
    path = tmp_path / "events.txt"
    path.write_text("# t x y p\n\n0.1 1 2 -1\n0.5 5 3 1  # inline comment\n7.5e-1 0 0 1\n")
    events = read_events(path, width=W, height=H)
    np.testing.assert_array_equal(events.t, [0.1, 0.5, 0.75])
    np.testing.assert_array_equal(events.p, [-1, 1, 1])
    np.testing.assert_array_equal(events.x, [1, 5, 0])


BAD_TXT = [
    ("0.1 1 2 1\n0.2 1 2\n", 3, "expected 4 columns 't x y p', got 3"),
    ("0.1 1 2\n0.2 1 2\n", 2, "expected 4 columns 't x y p', got 3"),
    ("0.1 1 2 1 7\n", 2, "expected 4 columns 't x y p', got 5"),
    ("0.1 1 abc 1\n", 2, "y='abc' is not a number"),
    ("0.013 1 2 1\n0.012 1 2 1\n", 3, "timestamps not sorted (0.012 < 0.013); sort the file"),
    ("0.1 6 2 1\n", 2, "x=6 is outside the sensor (0..5); check the sensor size or crop"),
    ("0.1 1 -1 1\n", 2, "y=-1 is outside the sensor (0..3)"),
    ("0.1 1.5 2 1\n", 2, "x=1.5 is not an integer pixel coordinate"),
    ("0.1 1 2 2\n", 2, "polarity 2 must be 0/1 or -1/+1"),
    ("0.1 1 2 0\n0.2 1 2 -1\n", 3, "polarity -1 but line 2 has 0; use 0/1 or -1/+1, not a mix"),
    ("nan 1 2 1\n", 2, "timestamp nan is not finite"),
]


@pytest.mark.parametrize(("body", "line", "message"), BAD_TXT)
def test_malformed_txt_names_file_and_line(
    tmp_path: Path, body: str, line: int, message: str
) -> None:
    path = tmp_path / "events.txt"
    path.write_text("# header comment, so line numbers differ from event indices\n" + body)
    with pytest.raises(ValueError, match=re.escape(f"{path} line {line}: {message}")):
        read_events(path, width=W, height=H)


@pytest.fixture
def arrow_chunks(monkeypatch: pytest.MonkeyPatch) -> list[bool]:
    """Every text chunk (of about 256 bytes) offered to Arrow; records whether Arrow took it."""
    taken: list[bool] = []
    parse = text_io._arrow_columns

    def spy(chunk: bytes) -> tuple[np.ndarray, ...] | None:
        columns = parse(chunk)
        taken.append(columns is not None)
        return columns

    monkeypatch.setattr(text_io, "_arrow_columns", spy)
    monkeypatch.setattr(text_io, "_ARROW_BYTES", 1)
    monkeypatch.setattr(text_io, "_CHUNK_BYTES", 256)
    return taken


def test_arrow_reads_the_bits_loadtxt_reads(tmp_path: Path, arrow_chunks: list[bool]) -> None:
    """Times in every notation a writer uses (shortest repr, fixed decimals, exponents,
    integers), chunked, read bit-exact against ``np.loadtxt``; blocks as asked."""
    rng = np.random.default_rng(3)
    values = np.concatenate([rng.uniform(0, 3, 300), 10.0 ** rng.uniform(-9, 2, 300)]).tolist()
    notations = ["{!r}", "{:.9f}", "{:.17e}", "{:.3g}", "{:.0f}"]
    times = sorted((notations[i % 5].format(v) for i, v in enumerate(values)), key=float)
    lines = [f"{t} {i % W} {i % H} {i % 2}" for i, t in enumerate(times)]
    path = tmp_path / "events.txt"
    path.write_text("\n".join(lines))  # the last line without its newline
    expected = np.loadtxt(path)
    events = read_events(path, width=W, height=H)
    assert len(arrow_chunks) > 10 and all(arrow_chunks)
    np.testing.assert_array_equal(events.t, expected[:, 0])
    np.testing.assert_array_equal(events.x, expected[:, 1])
    np.testing.assert_array_equal(events.p, np.where(expected[:, 3] > 0, 1, -1))
    chunks = list(iter_event_chunks(path, 100, width=W, height=H))
    assert [len(c) for c in chunks] == [100] * 6
    np.testing.assert_array_equal(np.concatenate([c.t for c in chunks]), events.t)


@pytest.mark.parametrize(
    "odd",
    ["0.2  1 2 1", "", "0.2 1 2 1 # c", "0.2\t1 2 1", "0.2 1 2 1\r", "0.2 1 2 1 ", " 0.2 1 2 1"],
)
def test_arrow_leaves_comments_and_odd_spacing_to_loadtxt(
    tmp_path: Path, arrow_chunks: list[bool], odd: str
) -> None:
    """A chunk Arrow declines (or would number wrongly) is read by ``np.loadtxt``."""
    path = tmp_path / "events.txt"
    path.write_text(f"0.1 1 2 0\n{odd}\n0.3 1 2 1\n")
    events = read_events(path, width=W, height=H)
    assert arrow_chunks == [False]
    kept = [0.1, 0.3] if odd == "" else [0.1, 0.2, 0.3]
    np.testing.assert_array_equal(events.t, kept)
    np.testing.assert_array_equal(events.p, [-1] + [1] * (len(kept) - 1))


@pytest.mark.parametrize(("body", "line", "message"), BAD_TXT)
def test_arrow_chunks_name_the_bad_line(
    tmp_path: Path, arrow_chunks: list[bool], body: str, line: int, message: str
) -> None:
    """The same messages when the bad line lies in a later chunk than the first."""
    good = "".join(f"{i * 1e-4!r} 1 2 1\n" for i in range(1, 61))
    path = tmp_path / "events.txt"
    path.write_text(good + body)
    moved = message.replace("line 2 has", "line 61 has")  # 60 lines before the body, not one
    with pytest.raises(ValueError, match=re.escape(f"{path} line {line + 59}: {moved}")):
        read_events(path, width=W, height=H)
    assert arrow_chunks[0]


def test_arrow_chunks_name_the_line_of_the_first_polarity(
    tmp_path: Path, arrow_chunks: list[bool]
) -> None:
    """A polarity mix across chunks names both lines (the first 0 inside a later chunk)."""
    p = ["1"] * 40
    p[16], p[34] = "0", "-1"
    path = tmp_path / "events.txt"
    path.write_text("".join(f"{i * 1e-4!r} 1 2 {v}\n" for i, v in enumerate(p)))
    with pytest.raises(
        ValueError, match=re.escape(f"{path} line 35: polarity -1 but line 17 has 0")
    ):
        read_events(path, width=W, height=H)
    assert arrow_chunks[:2] == [True, True]


def test_binary_garbage_in_txt_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "events.txt"
    path.write_bytes(b"0.1 1 2 1\n0.2 \xff\xfe 2 1\n")
    with pytest.raises(ValueError, match=re.escape(f"{path} line 2: x=") + ".*not a number"):
        read_events(path, width=W, height=H)


def test_txt_needs_sensor_size(tmp_path: Path) -> None:
    path = tmp_path / "events.txt"
    write_events(_stream(), path)
    with pytest.raises(ValueError, match=r"sensor size unknown .*; pass width= and height="):
        read_events(path)
    with pytest.raises(ValueError, match="give both width and height or neither"):
        read_events(path, width=W)


def test_stored_size_must_agree_with_arguments(tmp_path: Path) -> None:
    path = tmp_path / "events.npz"
    write_events(_stream(), path)
    with pytest.raises(ValueError, match=r"events.npz: sensor size 6x4 differs from 8x4"):
        read_events(path, width=8, height=4)
    assert len(read_events(path, width=W, height=H)) == 40


def _write_dsec(path: Path, t_us: np.ndarray, offset: int | None, attrs: bool) -> None:
    """An HDF5 file in DSEC's layout: integer microseconds, uint16 pixels, 0/1 polarity."""
    with h5py.File(path, "w") as f:
        group = f.create_group("events")
        group["t"] = t_us.astype(np.uint32)
        group["x"] = np.array([0, 5, 3], dtype=np.uint16)
        group["y"] = np.array([0, 3, 1], dtype=np.uint16)
        group["p"] = np.array([0, 1, 1], dtype=np.uint8)
        if offset is not None:
            f["t_offset"] = np.int64(offset)
        if attrs:
            group.attrs["width"], group.attrs["height"] = W, H


def test_dsec_microseconds_and_t_offset(tmp_path: Path) -> None:
    path = tmp_path / "events.h5"
    _write_dsec(path, np.array([0, 250, 1_000_000]), offset=2_000_000, attrs=False)
    events = read_events(path, width=W, height=H)
    np.testing.assert_array_equal(events.t, [2.0, 2.00025, 3.0])
    np.testing.assert_array_equal(events.p, [-1, 1, 1])
    _write_dsec(path, np.array([0, 250, 1_000_000]), offset=None, attrs=True)
    np.testing.assert_array_equal(read_events(path).t, [0.0, 0.00025, 1.0])


def test_dsec_blosc_zstd_compressed_h5_reads_whole_and_streamed(tmp_path: Path) -> None:
    """DSEC compresses with Blosc/zstd: h5py alone cannot decode it, the readers can."""
    import hdf5plugin

    path = tmp_path / "events.h5"
    t_us = np.arange(0, 3000, 10, dtype=np.uint32)
    with h5py.File(path, "w") as f:
        group = f.create_group("events")
        zstd = hdf5plugin.Blosc(cname="zstd", clevel=5)
        group.create_dataset("t", data=t_us, chunks=(100,), **zstd)
        for name, dtype in (("x", np.uint16), ("y", np.uint16), ("p", np.uint8)):
            group.create_dataset(name, data=(t_us % 2).astype(dtype), chunks=(100,), **zstd)
        group.attrs["width"], group.attrs["height"] = W, H
    plain = "import h5py, sys; h5py.File(sys.argv[1], 'r')['events/t'][:]"
    bare = subprocess.run([sys.executable, "-c", plain, str(path)], capture_output=True)
    assert bare.returncode != 0  # the filter is not built into h5py
    readers = (  # a fresh process: only spatialseg's own imports register the filters
        "import sys, numpy as np; from spatialseg.io import iter_event_chunks, read_events; "
        "whole = read_events(sys.argv[1]).t; "
        "streamed = np.concatenate([c.t for c in iter_event_chunks(sys.argv[1], 128)]); "
        "print(len(whole), float(whole.sum()), float(streamed.sum()))"
    )
    res = subprocess.run([sys.executable, "-c", readers, str(path)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    n, whole, streamed = res.stdout.split()
    assert int(n) == len(t_us) and float(whole) == float(streamed) == pytest.approx(
        t_us.sum() / 1e6
    )


def test_h5_without_size_needs_arguments(tmp_path: Path) -> None:
    path = tmp_path / "events.h5"
    _write_dsec(path, np.array([0, 1, 2]), offset=None, attrs=False)
    with pytest.raises(ValueError, match=r"events\.h5: sensor size unknown"):
        read_events(path)


def test_h5_missing_dataset(tmp_path: Path) -> None:
    path = tmp_path / "events.h5"
    with h5py.File(path, "w") as f:
        for k in "txy":
            f[f"events/{k}"] = np.zeros(2)
    with pytest.raises(ValueError, match=r"events.h5: missing events/p; expected datasets"):
        read_events(path, width=W, height=H)


def test_h5_unsorted_names_file_and_event(tmp_path: Path) -> None:
    path = tmp_path / "events.h5"
    _write_dsec(path, np.array([5, 3, 9]), offset=None, attrs=True)
    with pytest.raises(ValueError, match=re.escape(f"{path}: timestamps not sorted at event 1")):
        read_events(path)


def test_npz_missing_array_and_half_size(tmp_path: Path) -> None:
    path = tmp_path / "events.npz"
    np.savez(path, t=np.zeros(2), x=np.zeros(2), y=np.zeros(2))
    with pytest.raises(ValueError, match=r"events.npz: missing array\(s\) p; expected t, x, y, p"):
        read_events(path, width=W, height=H)
    np.savez(path, t=np.zeros(1), x=np.zeros(1), y=np.zeros(1), p=np.ones(1), width=6)
    with pytest.raises(ValueError, match=r"events\.npz: give both width and height or neither"):
        read_events(path)


@pytest.mark.parametrize("suffix", [".h5", ".npz"])
def test_not_a_container_file(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"events{suffix}"
    path.write_text("0.1 1 2 1\n")
    with pytest.raises(ValueError, match=rf"events\{suffix}: cannot (open|read) as"):
        read_events(path, width=W, height=H)


def test_unknown_suffix_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"unknown events file type '\.csv'; use \.txt"):
        write_events(_stream(), tmp_path / "events.csv")
    with pytest.raises(FileNotFoundError, match=r"events\.npz: events file not found"):
        read_events(tmp_path / "events.npz")


def test_failed_write_keeps_the_old_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "events.npz"
    write_events(_stream(seed=1), path)
    before = path.read_bytes()

    def crash(events: EventStream, tmp: Path, kind: str) -> None:
        tmp.write_bytes(b"half an archive")
        raise OSError("disk full")

    monkeypatch.setattr(io_events, "save_events", crash)
    with pytest.raises(OSError, match="disk full"):
        write_events(_stream(seed=2), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["events.npz"]


def test_benchmark_runs(tmp_path: Path, repo: Path) -> None:
    out = tmp_path / "bench.json"
    command = [sys.executable, str(repo / "experiments" / "bench_io.py"), "--events", "2000"]
    done = subprocess.run(
        [*command, "--repeat", "1", "--out", str(out)], capture_output=True, text=True, check=True
    )
    assert "events.txt:" in done.stdout
    assert json.loads(out.read_text())["formats"][".npz"]["read_s"] > 0
