"""Recording directories: round trips per events format, atomic writes, malformed files."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import spatialseg.io._directory as io_directory
from spatialseg.events import EventStream
from spatialseg.io import read_recording, write_events, write_recording
from spatialseg.recording import Camera, DepthMap, GroundTruth, Keyframe, Recording
from tests.helpers import assert_same_recording

W, H = 6, 4


def _recording(*, truth: bool = True, keyframes: bool = True, depth: bool = True) -> Recording:
    """A small recording with every optional part: NaN depth, grey and RGB keyframes, labels."""
    rng = np.random.default_rng(3)
    n = 30
    events = EventStream(
        rng.integers(0, W, n),
        rng.integers(0, H, n),
        np.sort(rng.uniform(0.0, 1.0, n)),
        rng.choice([-1, 1], n),
        W,
        H,
    )
    maps = [DepthMap(t, rng.uniform(0.5, 3.0, (H, W)).astype(np.float32)) for t in (0.0, 0.5, 1.0)]
    maps[1].depth[0, 0] = np.nan
    frames = (
        Keyframe(0.25, rng.integers(0, 256, (H, W), dtype=np.uint8)),
        Keyframe(0.75, rng.integers(0, 256, (H, W, 3), dtype=np.uint8)),
    )
    gt = GroundTruth(
        rng.integers(-1, 2, n),
        {0: np.array([0.1, 0.0, -0.2]), 1: np.array([1 / 3, 2.5, 0.0])},
        {0: "cart_left"},
    )
    return Recording(
        events,
        Camera(fx=120.5, fy=119.25, cx=2.9, cy=1.7, width=W, height=H),
        tuple(maps) if depth else (),
        frames if keyframes else (),
        gt if truth else None,
        name="scene",
    )


@pytest.mark.parametrize("events_format", ["txt", "h5", "npz"])
def test_round_trip(tmp_path: Path, events_format: str) -> None:
    rec = _recording()
    path = tmp_path / "scene"
    write_recording(rec, path, events_format=events_format)
    back = read_recording(path)
    assert_same_recording(rec, back)
    assert back.name == "scene"
    assert (path / f"events.{events_format}").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]  # no temporary left behind


def test_round_trip_minimal(tmp_path: Path) -> None:
    rec = _recording(truth=False, keyframes=False, depth=False)
    write_recording(rec, tmp_path / "r")
    back = read_recording(tmp_path / "r")
    assert_same_recording(rec, back)
    assert back.ground_truth is None
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == [
        "calib.txt",
        "events.txt",
        "sensor.txt",
    ]


@pytest.mark.parametrize("events_format", ["h5", "npz"])
def test_size_from_event_file_attributes(tmp_path: Path, events_format: str) -> None:
    path = tmp_path / "r"
    write_recording(_recording(depth=False), path, events_format=events_format)
    (path / "sensor.txt").unlink()
    camera = read_recording(path).camera
    assert (camera.width, camera.height) == (W, H)


def test_txt_without_any_size_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "r"
    write_recording(_recording(depth=False), path)
    (path / "sensor.txt").unlink()
    with pytest.raises(ValueError, match=r"sensor size unknown .*; add sensor\.txt with one line"):
        read_recording(path)


def test_refuses_to_overwrite_unless_asked(tmp_path: Path) -> None:
    path = tmp_path / "r"
    write_recording(_recording(), path)
    with pytest.raises(FileExistsError, match="already exists; pass overwrite=True"):
        write_recording(_recording(truth=False), path)
    write_recording(_recording(truth=False), path, events_format="npz", overwrite=True)
    assert read_recording(path).ground_truth is None
    assert not (path / "events.txt").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["r"]


@pytest.mark.parametrize("existing", [False, True])
def test_crash_mid_write_leaves_nothing_half_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, existing: bool
) -> None:
    path = tmp_path / "r"
    if existing:
        write_recording(_recording(truth=False), path)

    def crash(truth: GroundTruth, folder: Path) -> None:
        folder.mkdir()
        raise OSError("disk full")

    monkeypatch.setattr(io_directory, "_write_ground_truth", crash)
    with pytest.raises(OSError, match="disk full"):
        write_recording(_recording(), path, overwrite=True)
    assert [p.name for p in tmp_path.iterdir()] == (["r"] if existing else [])
    if existing:
        assert read_recording(path).ground_truth is None


KILLED_WRITER = """
import os, signal, sys
sys.path[:0] = [sys.argv[2], os.path.dirname(sys.argv[2])]  # the tests and their package
import spatialseg.io._directory as io_directory
from spatialseg.io import write_recording
from test_io_recording import _recording
io_directory._write_ground_truth = lambda truth, folder: os.kill(os.getpid(), signal.SIGKILL)
write_recording(_recording(), sys.argv[1], overwrite=True)
"""


@pytest.mark.parametrize("existing", [False, True])
def test_killed_writer_never_leaves_a_readable_half(tmp_path: Path, existing: bool) -> None:
    path = tmp_path / "r"
    if existing:
        write_recording(_recording(truth=False), path)
    tests = str(Path(__file__).parent)
    done = subprocess.run([sys.executable, "-c", KILLED_WRITER, str(path), tests], check=False)
    assert done.returncode == -signal.SIGKILL
    if existing:
        assert read_recording(path).ground_truth is None  # the old recording, intact
    else:
        with pytest.raises(FileNotFoundError, match="recording directory not found"):
            read_recording(path)
    leftovers = [p.name for p in tmp_path.iterdir() if p.name != "r"]
    assert len(leftovers) == 1 and leftovers[0].startswith(".r.") and leftovers[0].endswith(".tmp")


def test_bad_keyframe_or_format_fails_before_writing(tmp_path: Path) -> None:
    rec = _recording()
    bad = Recording(rec.events, rec.camera, keyframes=(Keyframe(0.0, np.zeros((H, W))),))
    with pytest.raises(ValueError, match=r"keyframe 0 .*uint8 \(H, W\) or \(H, W, 3\)"):
        write_recording(bad, tmp_path / "r")
    with pytest.raises(ValueError, match="events_format='csv'; use 'txt', 'h5' or 'npz'"):
        write_recording(rec, tmp_path / "r", events_format="csv")
    assert list(tmp_path.iterdir()) == []


@pytest.fixture
def rec_dir(tmp_path: Path) -> Path:
    """A valid recording directory (txt events) to break in one place."""
    path = tmp_path / "rec"
    write_recording(_recording(), path)
    return path


def test_missing_depth_map(rec_dir: Path) -> None:
    (rec_dir / "depth" / "000001.npy").unlink()
    message = f"{rec_dir / 'depthmaps.txt'} line 2: depth map 'depth/000001.npy' not found"
    with pytest.raises(FileNotFoundError, match=re.escape(message)):
        read_recording(rec_dir)


def test_depth_maps_of_different_shapes(rec_dir: Path) -> None:
    np.save(rec_dir / "depth" / "000002.npy", np.ones((3, 5), dtype=np.float32))
    message = "000002.npy: shape (3, 5) differs from the first depth map (4, 6)"
    with pytest.raises(ValueError, match=re.escape(message)):
        read_recording(rec_dir)


def test_integer_depth_map(rec_dir: Path) -> None:
    np.save(rec_dir / "depth" / "000000.npy", np.ones((H, W), dtype=np.uint16))
    with pytest.raises(ValueError, match=r"000000.npy: dtype uint16, expected float32 metres"):
        read_recording(rec_dir)


def test_depthmaps_listing_errors(rec_dir: Path) -> None:
    listing = rec_dir / "depthmaps.txt"
    listing.write_text("0.0 depth/000000.npy\n0.5\n")
    with pytest.raises(ValueError, match=re.escape(f"{listing} line 2: expected 't path'")):
        read_recording(rec_dir)
    listing.write_text("0.5 depth/000000.npy\n0.2 depth/000001.npy\n")
    with pytest.raises(ValueError, match=r"line 2: times not sorted \(0.2 < 0.5\)"):
        read_recording(rec_dir)


def test_sensor_txt_must_agree_with_depth_maps(rec_dir: Path) -> None:
    (rec_dir / "sensor.txt").write_text("8 4\n")
    with pytest.raises(ValueError, match=r"sensor.txt: sensor size 8x4 differs from 6x4 given by"):
        read_recording(rec_dir)


def test_event_outside_the_depth_maps_sensor(rec_dir: Path) -> None:
    events = rec_dir / "events.txt"
    events.write_text(events.read_text() + "5.0 6 0 1\n")
    with pytest.raises(ValueError, match=re.escape(f"{events} line 31: x=6 is outside the sensor")):
        read_recording(rec_dir)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("100 100 2\n", " line 1: expected 'fx fy cx cy', got '100 100 2'"),
        ("100 a 2 1\n", " line 1: expected 'fx fy cx cy', got '100 a 2 1'"),
        ("100 100 2 1\n100 100 2 1\n", ": expected one line 'fx fy cx cy', got 2 lines"),
        ("-100 100 2 1\n", " line 1: camera intrinsics fx=-100.0"),
    ],
)
def test_malformed_calib(rec_dir: Path, text: str, message: str) -> None:
    (rec_dir / "calib.txt").write_text(text)
    with pytest.raises(ValueError, match=re.escape(f"{rec_dir / 'calib.txt'}{message}")):
        read_recording(rec_dir)


def test_calib_distortion_is_ignored_with_a_warning(rec_dir: Path) -> None:
    (rec_dir / "calib.txt").write_text("# RPG layout\n120.5 119.25 2.9 1.7 -0.3 0.1 0 0 0\n")
    with pytest.warns(UserWarning, match=r"ignoring distortion coefficients \[-0.3, 0.1"):
        assert read_recording(rec_dir).camera.fx == 120.5


def test_events_files(rec_dir: Path) -> None:
    write_events(read_recording(rec_dir).events, rec_dir / "events.npz")
    with pytest.raises(ValueError, match=r"found events\.txt and events\.npz; keep exactly one"):
        read_recording(rec_dir)
    (rec_dir / "events.txt").unlink()
    (rec_dir / "events.npz").unlink()
    with pytest.raises(FileNotFoundError, match=r"no events file; expected one of events\.txt"):
        read_recording(rec_dir)


def test_missing_directory_or_calib(rec_dir: Path) -> None:
    with pytest.raises(FileNotFoundError, match="recording directory not found"):
        read_recording(rec_dir / "nope")
    with pytest.raises(NotADirectoryError, match="use read_events for a bare events file"):
        read_recording(rec_dir / "events.txt")
    (rec_dir / "calib.txt").unlink()
    with pytest.raises(FileNotFoundError, match=r"calib\.txt: not found"):
        read_recording(rec_dir)


def test_missing_keyframe_image(rec_dir: Path) -> None:
    (rec_dir / "images" / "000001.png").unlink()
    message = f"{rec_dir / 'images.txt'} line 2: image 'images/000001.png' not found"
    with pytest.raises(FileNotFoundError, match=re.escape(message)):
        read_recording(rec_dir)


def test_ground_truth_errors(rec_dir: Path) -> None:
    gt = rec_dir / "ground_truth"
    np.save(gt / "event_labels.npy", np.zeros(29, dtype=np.int64))
    with pytest.raises(ValueError, match=r"event_labels.npy: expected 30 integer labels"):
        read_recording(rec_dir)
    np.save(gt / "event_labels.npy", np.full(30, 7))
    with pytest.raises(ValueError, match=r"event_labels\.npy: .*objects \[7\] with no motion"):
        read_recording(rec_dir)
    motions = gt / "motions.json"
    motions.write_text('{"objects": [\n  {"id": 7, "velocity": [1, 2, 3],}\n]}\n')
    with pytest.raises(ValueError, match=r"motions.json line 2: .*; fix the JSON"):
        read_recording(rec_dir)
    motions.write_text(json.dumps({"objects": [{"id": 7, "velocity": [1, 2]}]}))
    with pytest.raises(ValueError, match=r"motions.json objects\[0\]: expected \{\"id\""):
        read_recording(rec_dir)
    motions.write_text(json.dumps({"objects": [{"id": 7, "velocity": [1, float("nan"), 3]}]}))
    with pytest.raises(ValueError, match=r"objects\[0\]: .*with finite numbers, got .*NaN"):
        read_recording(rec_dir)
    motions.write_text(json.dumps({"objects": [{"id": 7, "velocity": [1, 2, 3]}] * 2}))
    with pytest.raises(ValueError, match=r"objects\[1\]: object id 7 appears twice"):
        read_recording(rec_dir)
    motions.unlink()
    with pytest.raises(FileNotFoundError, match=r"motions\.json: not found; ground_truth/ needs"):
        read_recording(rec_dir)


def _matplotlib_pixels(file: Path) -> np.ndarray:
    """The reader's pixels as matplotlib's ``imread`` gives them (its reader until session
    51): PNG as floats in [0, 1] rounded back to 8 bits, alpha and equal channels dropped."""
    import matplotlib.image

    image = matplotlib.image.imread(file)
    if image.dtype.kind == "f":
        image = np.round(image * 255)
    image = image.astype(np.uint8)
    if image.ndim == 3:
        rgb = image[..., :3]
        image = rgb[..., 0] if np.all(rgb == rgb[..., :1]) else rgb
    return image


@pytest.mark.parametrize(
    ("mode", "suffix"),
    [
        ("L", ".png"),
        ("RGB", ".png"),
        ("RGBA", ".png"),
        ("P", ".png"),
        ("LA", ".png"),
        ("1", ".png"),
        ("I;16", ".png"),
        ("L", ".jpg"),
        ("RGB", ".jpg"),
    ],
)
def test_keyframe_pixels_as_matplotlib_read_them(tmp_path: Path, mode: str, suffix: str) -> None:
    """Every image mode a keyframe file may hold reads to the pixels matplotlib gave."""
    from PIL import Image

    rng = np.random.default_rng(7)
    if mode == "I;16":
        image = Image.fromarray(rng.integers(0, 65536, (H, W), dtype=np.uint16))
    else:
        image = Image.fromarray(rng.integers(0, 256, (H, W, 3), dtype=np.uint8)).convert(mode)
    file = tmp_path / f"frame{suffix}"
    image.save(file)
    got = io_directory._read_image(file)
    assert got.dtype == np.uint8
    np.testing.assert_array_equal(got, _matplotlib_pixels(file))
