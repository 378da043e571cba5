"""Real-camera files: AEDAT4 (the shipped DAVIS346 recording), Prophesee EVT 2.0/3.0/DAT,
the ``read_any`` dispatch, cameras for files without intrinsics, and malformed input."""

from __future__ import annotations

import hashlib
import struct
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from spatialseg.depth import with_configured_depth
from spatialseg.events import EventStream
from spatialseg.io import (
    iter_event_chunks,
    nominal_camera,
    read_any,
    read_recording,
    write_events,
    write_prophesee,
    write_recording,
)
from spatialseg.recording import Camera, DepthMap, Recording
from spatialseg.scenes import load_scene, packaged_data
from spatialseg.settings import settings_from

from .conftest import REPO

PACKAGED = "road_cars/davis346-road-cars.aedat4"
#: The real recording as shipped in the package (its sha256 is checked below), so the
#: tests do not depend on ../shared beside the checkout.
REAL = packaged_data(PACKAGED)
REAL_SHA256 = "b383462d72122c69fd96ebf095c384e3f1a2f092cc1b2681be52ebc1d260cf8a"
W, H = 640, 480
CAMERA = Camera(300.0, 300.0, 319.5, 239.5, W, H)


def _events(n: int = 500, seed: int = 0, span_s: float = 0.5, w: int = W, h: int = H):
    """Random time-sorted events with whole-microsecond times (Prophesee's resolution)."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, int(span_s * 1e6), n)) / 1e6
    return EventStream(
        rng.integers(0, w, n), rng.integers(0, h, n), t, rng.choice([-1, 1], n), w, h
    )


def _same(a: EventStream, b: EventStream) -> None:
    """Equal events (times to 1 ns) and sensor size."""
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose(a.t, b.t, rtol=0, atol=1e-9)
    for name in ("x", "y", "p"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def _raw(path: Path, header: str, words: list[int], dtype: str) -> Path:
    """A ``.raw`` file: ``% ...`` header lines, ``% end``, then little-endian words."""
    path.write_bytes(header.encode() + b"% end\n" + np.array(words, dtype).tobytes())
    return path


def _one_line_error(exc: pytest.ExceptionInfo, *fragments: str) -> None:
    """The message is one line and contains every fragment."""
    message = str(exc.value)
    assert "\n" not in message, message
    for fragment in fragments:
        assert fragment in message, message


# --- the real DAVIS346 recording --------------------------------------------------------------


def test_real_aedat4_matches_its_description() -> None:
    rec = read_any(REAL, camera=Camera(227.0, 227.0, 172.5, 129.5, 346, 260))
    ev = rec.events
    assert (ev.width, ev.height) == (346, 260)
    assert len(ev) == 78_830
    assert ev.t[0] == 0.0 and ev.duration == pytest.approx(2.36, abs=0.005)
    assert set(np.unique(ev.p).tolist()) == {-1, 1}
    assert 0.3 < np.mean(ev.p > 0) < 0.7
    assert len(rec.keyframes) == 59
    times = [k.t for k in rec.keyframes]
    assert times == sorted(times) and times[0] < 0.01 and times[-1] > 2.3
    image = rec.keyframes[0].image
    assert image.shape == (260, 346) and image.dtype == np.uint8 and image.std() > 5
    assert rec.name == "davis346-road-cars" and rec.depth_maps == ()


def test_packaged_copy_is_the_shared_file() -> None:
    shipped = packaged_data(PACKAGED)
    assert hashlib.sha256(shipped.read_bytes()).hexdigest() == REAL_SHA256
    assert (shipped.parent / "davis346-road-cars.LICENSE").read_text().startswith("MIT License")


def test_real_aedat4_streams_in_chunks_equal_to_the_whole() -> None:
    whole = read_any(REAL, fov_deg=70.0).events
    chunks = list(iter_event_chunks(REAL, 10_000))
    assert [len(c) for c in chunks] == [10_000] * 7 + [8_830]
    for name in ("t", "x", "y", "p"):
        joined = np.concatenate([getattr(c, name) for c in chunks])
        np.testing.assert_array_equal(joined, getattr(whole, name), err_msg=name)


def test_road_cars_scene_reads_the_packaged_file_with_its_assumed_camera() -> None:
    scene = OmegaConf.to_container(OmegaConf.load(REPO / "conf/scene/road_cars.yaml"))
    assert scene["defaults"][0] == {"override /depth@_global_.depth": "ground_plane"}
    rec = load_scene(scene, seed=0, window_events=15_000)
    assert len(rec.events) == 78_830 and len(rec.keyframes) == 59
    assert rec.camera == Camera(227.0, 227.0, 172.5, 129.5, 346, 260)


def _with_depth(recording, depth_name: str, window_events: int):
    """``with_configured_depth`` with the shipped settings of ``depth=depth_name``."""
    depth = OmegaConf.to_container(OmegaConf.load(REPO / f"conf/depth/{depth_name}.yaml"))
    cfg = {"depth": depth, "window": {"events": window_events}}
    return with_configured_depth(recording, settings_from(cfg))


def test_loaded_recording_gets_depth_maps_from_the_depth_config(tmp_path: Path) -> None:
    scene = OmegaConf.to_container(OmegaConf.load(REPO / "conf/scene/road_cars.yaml"))
    rec = _with_depth(load_scene(scene, seed=0, window_events=15_000), "ground_plane", 15_000)
    # ground_plane needs no image: windows of 15,000 events, not the 40 ms APS frames
    assert [d.t for d in rec.depth_maps] == [
        rec.events.t[i] for i in (0, 15_000, 30_000, 45_000, 60_000, 78_829)
    ]
    assert rec.depth_maps[0].depth.shape == (260, 346)
    write_prophesee(_events(1000), tmp_path / "e.raw")  # no keyframes: every N events
    plain = {"kind": "recording", "path": str(tmp_path / "e.raw"), "fov_deg": 70.0}
    loaded = load_scene(plain, seed=0, window_events=250)
    assert len(_with_depth(loaded, "constant", 250).depth_maps) == 5
    with pytest.raises(ValueError, match="depth=recording needs two or more"):
        _with_depth(loaded, "recording", 250)


def test_road_cars_scene_selects_ground_plane_depth_unless_overridden() -> None:
    from hydra import compose, initialize_config_dir

    from spatialseg.config import validate_config

    with initialize_config_dir(version_base="1.3", config_dir=str(REPO / "conf")):
        chosen = compose("config", overrides=["+scene=road_cars"], return_hydra_config=True)
        override = compose("config", overrides=["+scene=road_cars", "depth=constant"])
        other = compose("config", overrides=["+scene=interior"])
    assert chosen.depth.name == "ground_plane" and override.depth.name == "constant"
    assert other.depth.name == "recording"
    choices = dict(chosen.hydra.runtime.choices)
    del chosen.hydra
    validate_config(chosen, choices)


def test_recording_scene_reads_any_file_type(tmp_path: Path) -> None:
    events = _events(300)
    write_prophesee(events, tmp_path / "cars.raw")
    scene = {"kind": "recording", "path": str(tmp_path / "cars.raw"), "fov_deg": 90.0}
    rec = load_scene(scene, seed=0, window_events=100)
    _same(rec.events, events)
    assert rec.camera.fx == pytest.approx(W / 2) and rec.camera.cx == (W - 1) / 2
    bad = {"kind": "recording", "path": str(tmp_path / "cars.raw"), "camera": {"fx": 1.0}}
    with pytest.raises(ValueError) as exc:
        load_scene(bad, seed=0, window_events=100)
    _one_line_error(exc, "scene.camera lacks fy, cx, cy, width, height")


# --- Prophesee: words written by hand from the published layouts ------------------------------


def test_evt3_words_decode_as_the_spec_says(tmp_path: Path) -> None:
    words = [
        0x2000 | 9,  # EVT_ADDR_X before any time or row: skipped
        0x8001,  # EVT_TIME_HIGH 1  -> t = 1 << 12 | low
        0x6005,  # EVT_TIME_LOW 5   -> t = 4101 us
        0x0007,  # EVT_ADDR_Y 7
        0x3800 | 100,  # VECT_BASE_X x=100, polarity 1
        0x4000 | 0b101,  # VECT_12: x = 100, 102; base -> 112
        0x5000 | 0x80,  # VECT_8: bit 7 -> x = 119; base -> 120
        0x2000 | 5,  # EVT_ADDR_X x=5, polarity 0
        0xA000,  # EXT_TRIGGER: ignored
        0x6006,  # EVT_TIME_LOW 6 -> t = 4102 us
        0x0800 | 3,  # EVT_ADDR_Y 3 (system type bit set)
        0x4000 | 0x800,  # VECT_12: bit 11 -> x = 120 + 11 = 131
    ]
    path = _raw(tmp_path / "v.raw", "% evt 3.0\n% geometry 640x480\n", words, "<u2")
    ev = read_any(path, camera=CAMERA).events
    np.testing.assert_array_equal(ev.t * 1e6, [4101, 4101, 4101, 4101, 4102])
    np.testing.assert_array_equal(ev.x, [100, 102, 119, 5, 131])
    np.testing.assert_array_equal(ev.y, [7, 7, 7, 7, 3])
    np.testing.assert_array_equal(ev.p, [1, 1, 1, -1, 1])
    for size in (1, 2, 3):  # chunk boundaries inside the vector state give the same events
        chunks = list(iter_event_chunks(path, size))
        np.testing.assert_array_equal(np.concatenate([c.x for c in chunks]), ev.x)


def test_evt2_words_decode_as_the_spec_says(tmp_path: Path) -> None:
    words = [
        (1 << 28) | (1 << 11) | 1,  # CD_ON before any EVT_TIME_HIGH: skipped
        (0x8 << 28) | 5,  # EVT_TIME_HIGH 5 -> t = 5 << 6 | low
        (1 << 28) | (3 << 22) | (10 << 11) | 20,  # CD_ON t=323 x=10 y=20
        (0xA << 28) | 1,  # EXT_TRIGGER: ignored
        (0 << 28) | (4 << 22) | (639 << 11) | 479,  # CD_OFF t=324 at the last pixel
    ]
    path = _raw(tmp_path / "v.raw", "% format EVT2;height=480;width=640\n", words, "<u4")
    ev = read_any(path, camera=CAMERA).events
    np.testing.assert_array_equal(ev.t * 1e6, [323, 324])
    np.testing.assert_array_equal(ev.x, [10, 639])
    np.testing.assert_array_equal(ev.y, [20, 479])
    np.testing.assert_array_equal(ev.p, [1, -1])


def test_dat_records_decode_as_the_spec_says(tmp_path: Path) -> None:
    header = b"% Data file containing CD events\n% Version 2\n% Width 640\n% Height 480\n"
    records = struct.pack("<4I", 100, 5 | (7 << 14) | (1 << 28), 200, 639 | (479 << 14))
    path = tmp_path / "v.dat"
    path.write_bytes(header + bytes((12, 8)) + records)
    ev = read_any(path, fov_deg=60.0).events
    assert (ev.width, ev.height) == (640, 480)
    np.testing.assert_array_equal(ev.t * 1e6, [100, 200])
    np.testing.assert_array_equal(ev.x, [5, 639])
    np.testing.assert_array_equal(ev.y, [7, 479])
    np.testing.assert_array_equal(ev.p, [1, -1])


@pytest.mark.parametrize(
    ("name", "encoding"), [("a.raw", "evt2"), ("a.raw", "evt3"), ("a.dat", "evt3")]
)
def test_prophesee_round_trip(tmp_path: Path, name: str, encoding: str) -> None:
    events = _events(2000, span_s=40.0)  # past EVT 3.0's 24-bit (16.8 s) time wrap-around
    write_prophesee(events, tmp_path / name, encoding=encoding)
    rec = read_any(tmp_path / name, camera=CAMERA)
    _same(rec.events, events)
    assert rec.name == "a" and rec.camera == CAMERA


@pytest.mark.parametrize("suffix", [".txt", ".h5", ".npz", ".raw", ".dat"])
def test_bare_files_read_with_a_given_or_nominal_camera(tmp_path: Path, suffix: str) -> None:
    events = _events(200)
    path = tmp_path / f"e{suffix}"
    (write_prophesee if suffix in (".raw", ".dat") else write_events)(events, path)
    _same(read_any(path, camera=CAMERA).events, events)
    if suffix != ".txt":  # .txt stores no sensor size: only a camera can give it
        assert read_any(path, fov_deg=90.0).camera == nominal_camera(W, H, 90.0)


def test_directory_reads_as_before_and_a_camera_replaces_its_calib(tmp_path: Path) -> None:
    depth = np.full((H, W), 2.0, np.float32)
    rec = Recording(_events(100), CAMERA, (DepthMap(0.0, depth), DepthMap(0.5, depth)))
    write_recording(rec, tmp_path / "r", events_format="h5")
    back = read_any(tmp_path / "r")
    _same(back.events, read_recording(tmp_path / "r").events)
    assert back.camera == CAMERA and len(back.depth_maps) == 2
    other = Camera(500.0, 500.0, 300.0, 200.0, W, H)
    assert read_any(tmp_path / "r", camera=other).camera == other


def test_nominal_camera_from_field_of_view() -> None:
    cam = nominal_camera(346, 260, 90.0)
    assert cam.fx == cam.fy == pytest.approx(173.0)
    assert (cam.cx, cam.cy, cam.width, cam.height) == (172.5, 129.5, 346, 260)
    with pytest.raises(ValueError, match="between 0 and 180"):
        nominal_camera(346, 260, 180.0)


# --- user mistakes: one line naming the file and the problem ----------------------------------


def test_unknown_type_lists_the_supported_ones(tmp_path: Path) -> None:
    (tmp_path / "e.bag").write_bytes(b"x")
    with pytest.raises(ValueError) as exc:
        read_any(tmp_path / "e.bag")
    _one_line_error(exc, "e.bag", "unknown file type '.bag'", ".aedat4", ".raw", ".dat", ".npz")
    with pytest.raises(FileNotFoundError, match=r"nope\.raw: not found"):
        read_any(tmp_path / "nope.raw")


def test_missing_intrinsics_and_size_mismatch(tmp_path: Path) -> None:
    write_prophesee(_events(10), tmp_path / "e.raw")
    with pytest.raises(ValueError) as exc:
        read_any(tmp_path / "e.raw")
    _one_line_error(exc, "e.raw", "no camera intrinsics", "scene.fov_deg")
    with pytest.raises(ValueError) as exc:
        read_any(tmp_path / "e.raw", camera=Camera(200.0, 200.0, 172.5, 129.5, 346, 260))
    _one_line_error(exc, "e.raw", "sensor is 640x480", "camera given is 346x260")
    write_events(_events(10), tmp_path / "e.txt")
    with pytest.raises(ValueError) as exc:
        read_any(tmp_path / "e.txt", fov_deg=70.0)
    _one_line_error(exc, "e.txt", "sensor size unknown", "Python: read(path, camera={...})")


def _truncated_aedat(path: Path) -> Path:
    data = REAL.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


@pytest.mark.parametrize(
    ("name", "content", "fragments"),
    [
        ("half.aedat4", None, ("half.aedat4 header", "packets end at", "damaged or truncated")),
        ("text.aedat4", b"hello world", ("not an AEDAT4 file",)),
        ("empty.aedat4", b"", ("not an AEDAT4 file",)),
        ("noenc.raw", b"% geometry 640x480\n% end\n\x00\x80", ("header names no encoding",)),
        ("evt21.raw", b"% format EVT21;width=640;height=480\n% end\n", ("'EVT21' not supported",)),
        ("odd.raw", b"% evt 3.0\n% geometry 640x480\n% end\n\x01\x80\x05", ("truncated", "3 data")),
        ("type.raw", b"% evt 3.0\n% geometry 640x480\n% end\n\x01\x80\x00\xd0", ("word 1", "0xD")),
        ("geom.raw", b"% evt 3.0\n% geometry 640 by 480\n% end\n", ("geometry '640 by 480'",)),
        ("cut.raw", b"% evt 3.0\n% geometry 640x4", ("truncated header",)),
        ("kind.dat", b"% Width 640\n% Height 480\n\x01\x08", ("event type 1", "only CD")),
        ("short.dat", b"% Width 640\n% Height 480\n\x0c", ("truncated after the header",)),
        ("rec.dat", b"% Width 640\n% Height 480\n\x0c\x08\x01\x02\x03", ("truncated", "8-byte")),
        ("big.dat", b"% Width 4\n% Height 4\n\x0c\x08" + struct.pack("<2I", 1, 9), ("x=9",)),
    ],
)
def test_malformed_files_are_one_line_errors(
    tmp_path: Path, name: str, content: bytes | None, fragments: tuple[str, ...]
) -> None:
    path = tmp_path / name
    if content is None:
        _truncated_aedat(path)
    else:
        path.write_bytes(content)
    with pytest.raises(ValueError) as exc:
        read_any(path, fov_deg=70.0)
    _one_line_error(exc, name, *fragments)
    with pytest.raises(ValueError) as exc:  # streaming reports the same problem
        list(iter_event_chunks(path, 1000))
    _one_line_error(exc, name, *fragments)


def test_unsorted_prophesee_events_are_named(tmp_path: Path) -> None:
    words = [0x8001, 0x6005, 0x0007, 0x2000 | 1, 0x6004, 0x2000 | 2]  # time low goes back
    path = _raw(tmp_path / "u.raw", "% evt 3.0\n% geometry 640x480\n", words, "<u2")
    with pytest.raises(ValueError) as exc:
        read_any(path, camera=CAMERA)
    _one_line_error(exc, "u.raw", "not sorted at event 1", "sort the events by time")


def test_cli_reports_a_bad_file_in_one_line(tmp_path: Path) -> None:
    from .helpers import run_module

    (tmp_path / "bad.raw").write_bytes(b"% geometry 640x480\n% end\n")
    res = run_module(
        "spatialseg",
        "+scene=recording",
        f"scene.path={tmp_path / 'bad.raw'}",
        f"hydra.run.dir={tmp_path / 'run'}",
        "tracking=none",
        cwd=tmp_path,
    )
    assert res.returncode == 2, res.stderr
    assert "bad.raw: header names no encoding" in res.stderr
    assert "Traceback" not in res.stderr
