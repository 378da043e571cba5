"""Damaged files: every reader either reads a mutated file into valid events or ends in one
``ValueError`` naming the file, never another exception, a Rust panic or an abort (a
listing whose damaged line names a missing file: ``FileNotFoundError``, as for any).

Each format's small valid file (written by the project's writers; AEDAT4: the shipped
recording's header and first packets) gets a few hundred seeded mutations: bytes flipped,
the file cut short, header bytes overwritten, a block zeroed. Each mutation is read whole
(``read_any``) and streamed (``iter_event_chunks``).
"""

from __future__ import annotations

import ast
import struct
import subprocess
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

import spatialseg.io._text as text_io
from spatialseg.events import EventStream
from spatialseg.io import (
    iter_event_chunks,
    read_any,
    write_events,
    write_prophesee,
    write_recording,
)
from spatialseg.io._aedat import read_aedat_header
from spatialseg.io._decode import decoding
from spatialseg.recording import Camera, DepthMap, GroundTruth, Keyframe, Recording
from spatialseg.scenes import packaged_data

from .conftest import REPO
from .helpers import run_module

W, H = 64, 48
CAMERA = Camera(60.0, 60.0, 31.5, 23.5, W, H)
AEDAT = packaged_data("road_cars/davis346-road-cars.aedat4")
AEDAT_PACKETS = 14  # events, IMU and trigger packets and one APS frame
KINDS = ("flip", "truncate", "header", "zero")
#: Listings whose damaged paths name files that do not exist: FileNotFoundError, as for
#: any listed file that is missing (``test_io_recording.test_missing_depth_map``).
LISTINGS = ("depthmaps.txt", "images.txt")
Maker = Callable[[Path], Path]


def _events(n: int = 150, seed: int = 0) -> EventStream:
    """Random sorted events with whole-microsecond times (every format stores them exactly)."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 50_000, n)) / 1e6
    return EventStream(
        rng.integers(0, W, n), rng.integers(0, H, n), t, rng.choice([-1, 1], n), W, H
    )


def _events_file(suffix: str, encoding: str = "evt3") -> Maker:
    """A maker of a bare events file ``e<suffix>`` written by the project's own writer."""

    def make(folder: Path) -> Path:
        path = folder / f"e{suffix}"
        if suffix in (".raw", ".dat"):
            write_prophesee(_events(), path, encoding=encoding)
        else:
            write_events(_events(), path)
        return path

    return make


def _aedat_prefix(folder: Path) -> Path:
    """The shipped AEDAT4 recording's header and first packets (LZ4), about 110 kB.

    Its header's file data table position becomes -1 (none, as in an unfinished
    recording), so the packets end where the file does.
    """
    data = AEDAT.read_bytes()
    header = read_aedat_header(AEDAT)
    end = header.data_start
    for _ in range(AEDAT_PACKETS):
        end += 8 + struct.unpack_from("<I", data, end + 4)[0]
    table = struct.pack("<q", header.packets_end)
    head = data[: header.data_start]
    assert head.count(table) == 1
    path = folder / "e.aedat4"
    path.write_bytes(head.replace(table, struct.pack("<q", -1)) + data[header.data_start : end])
    return path


def _directory(folder: Path) -> Path:
    """A recording directory: npz events, two depth maps, a keyframe and ground truth."""
    events = _events()
    depth = np.full((H, W), 2.0, np.float32)
    image = np.arange(W * H, dtype=np.uint8).reshape(H, W)
    truth = GroundTruth(np.arange(len(events)) % 2, {0: [0.1, 0, 0], 1: [0, 0.2, 0]}, {0: "a"})
    maps = (DepthMap(0.0, depth), DepthMap(0.05, depth * 2))
    recording = Recording(events, CAMERA, maps, (Keyframe(0.01, image),), truth)
    write_recording(recording, folder / "rec", events_format="npz")
    return folder / "rec"


#: Format -> (maker, bytes at the start that count as its header, mutations).
FORMATS: dict[str, tuple[Maker, int, int]] = {
    "npz": (_events_file(".npz"), 64, 300),
    "h5": (_events_file(".h5"), 1024, 300),
    "txt": (_events_file(".txt"), 64, 300),
    "evt2": (_events_file(".raw", "evt2"), 96, 300),
    "evt3": (_events_file(".raw", "evt3"), 96, 300),
    "dat": (_events_file(".dat"), 96, 300),
    "directory": (_directory, 64, 300),
    "aedat4": (_aedat_prefix, 3126, 200),  # the magic, the header's length and its 3108 bytes
}


def _mutate(data: bytes, kind: str, head: int, rng: np.random.Generator) -> bytes:
    """``data`` with one mutation of ``kind`` (flip, truncate, header, zero) drawn from ``rng``."""
    out = bytearray(data)
    if kind == "truncate":
        return bytes(out[: int(rng.integers(0, len(out)))])
    if kind == "zero":
        start = int(rng.integers(0, len(out)))
        stop = min(len(out), start + int(rng.integers(1, 65)))
        out[start:stop] = bytes(stop - start)
        return bytes(out)
    span = min(head, len(out)) if kind == "header" else len(out)
    for at in rng.integers(0, span, int(rng.integers(1, 9))):
        out[at] = out[at] ^ int(rng.integers(1, 256)) if kind == "flip" else int(rng.integers(256))
    return bytes(out)


def _put(file: Path, data: bytes) -> None:
    """Replace ``file`` by a new one holding ``data`` (truncating it in place costs a flush
    to disk on ext4, which made the writes most of this module's time)."""
    file.unlink()
    file.write_bytes(data)


def mutations(name: str, folder: Path, seed: int = 0) -> Iterator[tuple[int, str, Path, Path]]:
    """Write each seeded mutation of format ``name`` in place: (index, kind, target, file).

    ``target`` is what a reader opens (the file, or the recording directory), ``file`` the
    file mutated; it is restored before the next mutation.
    """
    make, head, count = FORMATS[name]
    target = make(folder)
    files = sorted(p for p in target.rglob("*") if p.is_file()) if target.is_dir() else [target]
    originals = {p: p.read_bytes() for p in files}
    rng = np.random.default_rng(seed)
    for index in range(count):
        file = files[int(rng.integers(0, len(files)))]
        kind = KINDS[index % len(KINDS)]
        _put(file, _mutate(originals[file], kind, head, rng))
        yield index, kind, target, file
        _put(file, originals[file])


def _valid(events: EventStream) -> None:
    """Finite sorted times, pixels inside the sensor, polarity -1/+1."""
    assert np.all(np.isfinite(events.t)) and np.all(np.diff(events.t) >= 0)
    assert np.all((events.x >= 0) & (events.x < events.width))
    assert np.all((events.y >= 0) & (events.y < events.height))
    assert np.all(np.abs(events.p) == 1)


def read_whole(path: Path) -> None:
    """Read ``path`` with read_any and check the events, depth maps and keyframes."""
    recording = read_any(path, camera=CAMERA if path.suffix == ".txt" else None, fov_deg=60.0)
    _valid(recording.events)
    shape = (recording.camera.height, recording.camera.width)
    for depth in recording.depth_maps:
        assert depth.depth.shape == shape and depth.depth.dtype.kind == "f"
    for keyframe in recording.keyframes:
        assert keyframe.image.dtype == np.uint8 and np.isfinite(keyframe.t)


def read_streamed(path: Path) -> None:
    """Stream ``path`` with iter_event_chunks and check each chunk and their order."""
    size = {"width": W, "height": H} if path.suffix == ".txt" else {}
    last = -np.inf
    for chunk in iter_event_chunks(path, 64, **size):
        _valid(chunk)
        assert len(chunk) and chunk.t[0] >= last
        last = chunk.t[-1]


def outcome(read: Callable[[Path], None], target: Path, file: Path) -> str:
    """``"read"``, or the name of the one-line error naming ``file`` that the read raised."""
    expected = (ValueError, FileNotFoundError) if file.name in LISTINGS else ValueError
    try:
        read(target)
    except expected as exc:
        message = str(exc)
        assert "\n" not in message and str(file) in message, message
        return type(exc).__name__
    return "read"


def fuzz(name: str, folder: Path) -> Counter[str]:
    """Outcomes of reading and streaming every mutation of format ``name``; raises on others."""
    counts: Counter[str] = Counter()
    for index, kind, target, file in mutations(name, folder):
        for read in (read_whole, read_streamed):
            try:
                counts[outcome(read, target, file)] += 1
            except (KeyboardInterrupt, SystemExit):
                raise
            except BaseException as exc:  # a pyo3 PanicException is a BaseException
                raise AssertionError(
                    f"{name} mutation {index} ({kind} of {file.name}), {read.__name__}: "
                    f"{type(exc).__name__}: {exc}"
                ) from exc
    return counts


@pytest.mark.parametrize("name", [n for n in FORMATS if n != "aedat4"])
def test_damaged_files_read_or_fail_in_one_line(tmp_path: Path, name: str) -> None:
    counts = fuzz(name, tmp_path)
    assert counts.total() == 2 * FORMATS[name][2]
    assert counts["ValueError"] > counts.total() / 3, counts  # the mutations do damage


def test_damaged_text_read_by_arrow_or_fail_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The text reader's Arrow path (chunks of 64 bytes, every one offered to Arrow)."""
    monkeypatch.setattr(text_io, "_ARROW_BYTES", 1)
    monkeypatch.setattr(text_io, "_CHUNK_BYTES", 64)
    counts = fuzz("txt", tmp_path)
    assert counts.total() == 2 * FORMATS["txt"][2]
    assert counts["ValueError"] > counts.total() / 3, counts  # the mutations do damage


def test_damaged_aedat4_never_panics_or_aborts(tmp_path: Path) -> None:
    """Every AEDAT4 mutation in one child process: an abort shows in its exit status."""
    script = (  # -P and append: the installed package, as pytest imports it, and the tests
        f"import sys; sys.path.append({str(REPO)!r}); from pathlib import Path; "
        "from tests.test_reader_fuzz import fuzz; print(dict(fuzz('aedat4', Path(sys.argv[1]))))"
    )
    res = subprocess.run(
        [sys.executable, "-P", "-c", script, str(tmp_path)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0, (res.returncode, res.stderr[-3000:])
    counts = Counter(ast.literal_eval(res.stdout.strip().splitlines()[-1]))
    assert counts.total() == 2 * FORMATS["aedat4"][2]
    assert counts["ValueError"] > counts.total() / 3 and counts["read"] > 0, counts


class PanicException(BaseException):
    """Stands for pyo3's PanicException, which derives from BaseException, not Exception."""


def test_decoding_turns_a_panic_into_one_line_and_lets_interrupts_through(tmp_path: Path) -> None:
    path = tmp_path / "e.aedat4"
    with pytest.raises(ValueError) as exc, decoding(path, "AEDAT4", "packet 3 at byte 40"):
        raise PanicException("index out of bounds:\n the len is 3")
    assert str(exc.value) == (
        f"{path} packet 3 at byte 40: cannot read as AEDAT4 (PanicException: index out of "
        "bounds: the len is 3); the file is damaged or truncated; copy or export it again"
    )
    for interrupt in (KeyboardInterrupt, SystemExit, GeneratorExit):
        with pytest.raises(interrupt), decoding(path, "AEDAT4"):
            raise interrupt()


def test_a_panic_while_decoding_a_packet_names_the_packet(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import aedat

    path = _aedat_prefix(tmp_path)
    real = aedat.Decoder

    class Panicking:
        """The real decoder until its third packet, which panics."""

        def __init__(self, name: str) -> None:
            self.decoder, self.count = real(name), 0

        def id_to_stream(self) -> dict:
            return self.decoder.id_to_stream()

        def __next__(self) -> dict:
            self.count += 1
            if self.count == 3:
                raise PanicException("range end index 9 out of range for slice of length 4")
            return next(self.decoder)

    monkeypatch.setattr(aedat, "Decoder", Panicking)
    data, offset = path.read_bytes(), read_aedat_header(path).data_start
    for _ in range(2):  # past packets 0 and 1: 8 bytes of stream id and length, then the data
        offset += 8 + struct.unpack_from("<I", data, offset + 4)[0]
    for read in (read_whole, read_streamed):
        with pytest.raises(ValueError) as exc:
            read(path)
        assert str(exc.value).startswith(
            f"{path} packet 2 at byte {offset}: cannot read as AEDAT4 (PanicException: range end"
        )


def test_cli_reports_a_damaged_npz_in_one_line(tmp_path: Path) -> None:
    path = _events_file(".npz")(tmp_path)
    data = bytearray(path.read_bytes())
    data[100] ^= 0xFF  # inside member t.npy: the archive opens, its CRC-32 check fails
    path.write_bytes(bytes(data))
    res = run_module(
        "spatialseg",
        "+scene=recording",
        f"scene.path={path}",
        "scene.fov_deg=60",
        f"hydra.run.dir={tmp_path / 'run'}",
        "tracking=none",
        cwd=tmp_path,
    )
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().count("\n") == 0 and "Traceback" not in res.stderr
    assert f"error: {path} member 't.npy': cannot read as .npz (BadZipFile: Bad CRC-32" in (
        res.stderr
    )
    assert "damaged or truncated" in res.stderr
