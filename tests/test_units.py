"""Units a recording must be in (times in seconds, depths in metres, one clock for events and
depth maps) and the events a window needs per cluster: each mistake is one line with its fix."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

import spatialseg
from spatialseg.depth import with_configured_depth
from spatialseg.events import EventStream
from spatialseg.io import read_recording, write_recording
from spatialseg.recording import (
    MILLIMETRES_FIX,
    Camera,
    DepthMap,
    Recording,
    check_depth_maps,
    check_event_times,
)
from spatialseg.scenes import load_scene
from spatialseg.settings import settings_from
from spatialseg.window import check_events_per_cluster
from tests.test_cli import spatialseg as run_cli

W, H = 32, 24
REPO = Path(__file__).resolve().parents[1]


def _recording(
    start: float,
    span: float,
    *,
    maps: tuple[float, float] | None = None,
    depth: np.ndarray | None = None,
    n: int = 400,
) -> Recording:
    """``n`` events over ``[start, start + span]`` and two depth maps (at ``maps``, else at
    the first and last event) of ``depth`` (else 2 m everywhere)."""
    rng = np.random.default_rng(0)
    t = np.linspace(start, start + span, n)
    events = EventStream(rng.integers(0, W, n), rng.integers(0, H, n), t, np.ones(n), W, H)
    t0, t1 = maps or (t[0], t[-1])
    d = np.full((H, W), 2.0) if depth is None else depth
    depth_maps = (DepthMap(t0, d, source="d0.npy"), DepthMap(t1, d, source="d1.npy"))
    return Recording(events, Camera(30.0, 30.0, W / 2, H / 2, W, H), depth_maps, name="rec")


@pytest.mark.parametrize(
    ("span", "message"),
    [
        (3.2e6, r"rec: events span 3\.2e\+06 s; timestamps look like microseconds; divide by 1e6"),
        (2.4e12, r"rec: events span 2\.4e\+12 s; timestamps look like nanoseconds; divide by 1e9"),
    ],
)
def test_event_times_in_microseconds_or_nanoseconds_are_refused(span, message):
    with pytest.raises(ValueError, match=message):
        check_event_times(_recording(0.0, span))


def test_a_recording_without_events_is_refused_as_such():
    rec = _recording(0.0, 2.0)
    empty = replace(rec, events=rec.events.select(np.zeros(len(rec.events), dtype=bool)))
    with pytest.raises(ValueError, match="rec: the recording holds no events, nothing to segment"):
        check_event_times(empty)


def test_depth_map_times_in_microseconds_are_refused():
    rec = _recording(0.0, 2.0, maps=(0.0, 2.4e6))
    check_event_times(rec)
    with pytest.raises(ValueError, match=r"rec: depth maps span 2\.4e\+06 s; .* microseconds"):
        check_depth_maps(rec)


def test_unix_times_in_seconds_with_a_short_span_pass():
    rec = _recording(1.7e9, 2.0)
    check_event_times(rec)
    check_depth_maps(rec)


def test_events_on_another_clock_than_the_depth_maps_are_refused_with_both_spans():
    rec = _recording(0.0, 2.36, maps=(1612345678.0, 1612345680.4))
    message = (
        "rec: events span 0.000-2.360 s but the depth maps 1612345678.000-1612345680.400 s: "
        "no event falls between them, the two clocks differ (an offset or a unit); give both "
        "in the same seconds"
    )
    with pytest.raises(ValueError) as exc:
        check_depth_maps(rec)
    assert str(exc.value) == message


def test_most_events_outside_the_depth_maps_is_one_warning(caplog):
    with caplog.at_level(logging.WARNING, logger="spatialseg.recording"):
        check_depth_maps(_recording(0.0, 2.0, maps=(1.5, 2.0)))  # the last quarter inside
    (record,) = caplog.records
    assert "300 of 400 events fall outside them and are labelled -1" in record.getMessage()
    assert "\n" not in record.getMessage()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="spatialseg.recording"):
        check_depth_maps(_recording(0.0, 2.0, maps=(0.5, 2.0)))  # three quarters inside
    assert not caplog.records


def test_float_depth_in_millimetres_is_refused_naming_the_map():
    mm = np.full((H, W), 2500.0)
    mm[:4] = np.nan  # unknown depth does not count
    with pytest.raises(ValueError) as exc:
        check_depth_maps(_recording(0.0, 2.0, depth=mm))
    assert str(exc.value) == (
        "d0.npy (depth map at t=0.000000 s): median depth 2500 m; depths look like "
        "millimetres; divide by 1000 (spatialseg depths are metres)"
    )


def test_depths_of_half_a_metre_to_80_metres_pass():
    depth = np.linspace(0.5, 80.0, H * W).reshape(H, W)
    depth[0, :5] = [np.nan, 0.0, -1.0, np.inf, 1e6]  # unknown, and one far outlier
    check_depth_maps(_recording(0.0, 2.0, depth=depth))


def test_integer_depth_files_give_the_same_millimetres_fix(tmp_path):
    write_recording(_recording(0.0, 2.0), tmp_path / "rec", events_format="npz")
    first = sorted((tmp_path / "rec").rglob("*.npy"))[0]
    np.save(first, np.full((H, W), 2000, dtype=np.uint16))
    with pytest.raises(ValueError, match=r"dtype uint16, expected float32 metres; ") as exc:
        read_recording(tmp_path / "rec")
    assert str(exc.value).endswith(MILLIMETRES_FIX)


def test_the_api_checks_units_before_segmenting():
    mm = _recording(0.0, 2.0, depth=np.full((H, W), 3000.0))
    with pytest.raises(ValueError, match="depths look like millimetres"):
        spatialseg.segment(mm, 2)
    with pytest.raises(ValueError, match="timestamps look like microseconds"):
        spatialseg.segment(_recording(0.0, 2e6), 2, depth="constant")


def test_the_shipped_road_recording_passes():
    scene = OmegaConf.to_container(OmegaConf.load(REPO / "conf/scene/road_cars.yaml"))
    rec = load_scene(scene, seed=0, window_events=15_000)
    check_event_times(rec)
    depth = OmegaConf.to_container(OmegaConf.load(REPO / "conf/depth/ground_plane.yaml"))
    settings = settings_from({"depth": depth, "window": {"events": 15_000}})
    used = with_configured_depth(rec, settings)
    check_depth_maps(used)
    assert len(used.depth_maps) == 6


def test_under_ten_events_per_cluster_are_refused():
    with pytest.raises(ValueError) as exc:
        check_events_per_cluster(19, 2, "rec")
    assert str(exc.value) == (
        "rec: 19 usable events for 2 clusters (under 10 per cluster); use fewer clusters or a "
        "longer window"
    )


@pytest.mark.parametrize(("n_events", "warned"), [(20, True), (399, True), (400, False)])
def test_under_200_events_per_cluster_are_one_warning(caplog, n_events, warned):
    with caplog.at_level(logging.WARNING, logger="spatialseg.pipeline"):
        check_events_per_cluster(n_events, 2, "rec")
    expected = (
        f"rec: {n_events} usable events for 2 clusters (under 200 per cluster); use fewer "
        "clusters or a longer window: its velocities are poorly determined"
    )
    assert [r.getMessage() for r in caplog.records] == ([expected] if warned else [])


def test_command_line_refuses_microseconds_in_one_line(tmp_path):
    rec = _recording(0.0, 3.2e6)
    rec = replace(rec, depth_maps=tuple(replace(d, t=d.t / 1e6) for d in rec.depth_maps))
    write_recording(rec, tmp_path / "rec", events_format="npz")
    out = tmp_path / "run"
    res = run_cli(
        "+scene=recording",
        f"scene.path={tmp_path / 'rec'}",
        "tracking=none",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr
    assert lines[0].startswith("error: ") and "events.npz: events span 3.2e+06 s" in lines[0]
    assert lines[0].endswith(
        "divide by 1e6, or by 1e9 if they are nanoseconds (spatialseg times are seconds)"
    )
