"""The simulator against analytic cases, its determinism, ground truth and input checks."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from spatialseg.config import conf_dir
from spatialseg.simulate import simulate_scene

LOG_EPS = 0.001
BG_LEVEL, PATCH_LEVEL = 0.2, 0.8
FX = 100.0
EDGE_X0, DEPTH, SPEED = -0.2, 1.0, 0.2  # patch's right edge (m), its depth (m), speed (m/s)
STEP = 0.25  # max_pixel_step


@pytest.fixture
def interior() -> dict:
    """The shipped interior scene as a plain dict (a fresh copy per test)."""
    return OmegaConf.to_container(OmegaConf.load(conf_dir() / "scene" / "interior.yaml"))


def _scene(**sensor) -> dict:
    """A 64 x 16 camera, a uniform wall at 2 m and a wide uniform patch whose right edge
    sweeps to the right over the image at a known speed."""
    return {
        "name": "edge",
        "kind": "simulated",
        "description": "a straight edge at known speed and contrast",
        "camera": {
            "width": 64,
            "height": 16,
            "fx": FX,
            "fy": FX,
            "cx": 31.5,
            "cy": 7.5,
            "ego_velocity": [0.0, 0.0, 0.0],
        },
        "duration": 1.0,
        "sensor": {
            "threshold_mean": 0.3,
            "threshold_std": 0.0,
            "threshold_min": 0.05,
            "refractory": 0.0,
            "noise_rate": 0.0,
            "log_eps": LOG_EPS,
            **sensor,
        },
        "render": {"max_pixel_step": STEP},
        "lighting": {"gain": 1.0, "gamma": 1.0},
        "background": [
            {
                "name": "wall",
                "normal": [0, 0, 1],
                "point": [0, 0, 2.0],
                "texture": {"kind": "uniform", "level": BG_LEVEL},
            }
        ],
        "objects": [
            {
                "name": "patch",
                "shape": "patch",
                "size": [2.0, 1.0],
                "position": [EDGE_X0 - 1.0, 0.0, DEPTH],
                "velocity": [SPEED, 0.0, 0.0],
                "texture": {"kind": "uniform", "level": PATCH_LEVEL},
            }
        ],
    }


def _per_pixel_counts(rec) -> np.ndarray:
    """Event counts per pixel (H x W)."""
    ev = rec.events
    counts = np.zeros((ev.height, ev.width), dtype=np.int64)
    np.add.at(counts, (ev.y, ev.x), 1)
    return counts


@pytest.mark.parametrize("threshold", [0.2, 0.3, 0.5])
def test_moving_edge_gives_predicted_events_per_pixel_at_predicted_times(threshold):
    rec = simulate_scene(_scene(threshold_mean=threshold), seed=0, max_events=None)
    ev = rec.events
    contrast = np.log(PATCH_LEVEL + LOG_EPS) - np.log(BG_LEVEL + LOG_EPS)
    u_edge0 = 31.5 + FX * EDGE_X0 / DEPTH
    speed_px = FX * SPEED / DEPTH
    u_end = u_edge0 + speed_px * 1.0
    swept = (np.arange(64) > u_edge0) & (np.arange(64) <= u_end)
    counts = _per_pixel_counts(rec)
    assert np.all(np.abs(counts[:, swept] - contrast / threshold) <= 1)
    assert not counts[:, ~swept].any()
    assert np.all(ev.p == 1)
    crossing = (ev.x - u_edge0) / speed_px
    assert np.all(np.abs(ev.t - crossing) <= STEP / speed_px)
    assert np.all(rec.ground_truth.labels == 1)


def test_refractory_period_suppresses_repeated_crossings():
    rec = simulate_scene(_scene(refractory=0.5), seed=0, max_events=None)
    counts = _per_pixel_counts(rec)
    assert counts.max() == 1


def test_noise_events_are_labelled_minus_one_at_the_configured_rate():
    cfg = _scene(noise_rate=20.0)
    cfg["objects"] = []
    rec = simulate_scene(cfg, seed=0, max_events=None)
    expected = 20.0 * 64 * 16 * 1.0
    assert abs(len(rec.events) - expected) < 5 * np.sqrt(expected)
    assert np.all(rec.ground_truth.labels == -1)
    assert set(np.unique(rec.events.p).tolist()) == {-1, 1}


def test_static_scene_without_noise_gives_no_events(interior):
    cfg = interior
    for body in cfg["objects"]:
        body["velocity"] = [0.0, 0.0, 0.0]
    cfg["sensor"]["noise_rate"] = 0.0
    rec = simulate_scene(cfg, seed=0, max_events=1000)
    assert len(rec.events) == 0
    assert [d.t for d in rec.depth_maps] == [0.0, cfg["duration"]]


def test_same_seed_gives_identical_events_and_another_seed_does_not(interior):
    a, b, c = (simulate_scene(interior, seed=s, max_events=3000) for s in (7, 7, 8))
    for name in ("x", "y", "t", "p"):
        assert np.array_equal(getattr(a.events, name), getattr(b.events, name))
    assert np.array_equal(a.ground_truth.labels, b.ground_truth.labels)
    assert np.array_equal(a.depth_maps[1].depth, b.depth_maps[1].depth)
    assert not np.array_equal(a.events.t, c.events.t)


def test_window_ends_at_max_events_with_depth_maps_and_keyframes_at_its_ends(interior):
    rec = simulate_scene(interior, seed=0, max_events=2000)
    ev = rec.events
    assert len(ev) == 2000
    assert [d.t for d in rec.depth_maps] == [ev.t[0], ev.t[-1]]
    assert [k.t for k in rec.keyframes] == [ev.t[0], ev.t[-1]]
    for d, k in zip(rec.depth_maps, rec.keyframes, strict=True):
        assert d.depth.dtype == np.float32 and np.all(np.isfinite(d.depth) & (d.depth > 0))
        assert k.image.dtype == np.uint8 and k.image.shape == (260, 346)
    assert rec.depth_maps[0].depth.max() == pytest.approx(1.0)
    assert rec.depth_maps[0].depth.min() == pytest.approx(0.965 - 0.03)
    gt = rec.ground_truth
    assert set(gt.motions) == {1, 2} and gt.names == {1: "silver cart", 2: "red cart"}
    assert np.allclose(gt.motions[1], interior["objects"][0]["velocity"])


def test_windows_put_a_depth_map_and_keyframe_every_window_of_events(interior):
    rec = simulate_scene(interior, seed=0, max_events=1000, windows=3)
    ev = rec.events
    assert len(ev) == 3000
    expected = [ev.t[0], ev.t[1000], ev.t[2000], ev.t[-1]]
    assert [d.t for d in rec.depth_maps] == expected
    assert [k.t for k in rec.keyframes] == expected
    one = simulate_scene(interior, seed=0, max_events=1000)
    np.testing.assert_array_equal(one.events.t, ev.t[:1000])
    assert [len(i) for i, _ in rec.windows()] == [1000, 1000, 1000]


def test_a_whole_duration_splits_into_windows_of_equal_event_counts(interior):
    rec = simulate_scene({**interior, "duration": 0.05}, seed=0, max_events=None, windows=3)
    counts = [len(index) for index, _ in rec.windows()]
    assert len(counts) == 3 and max(counts) - min(counts) <= 2
    assert rec.events.t[-1] <= 0.05


@pytest.mark.parametrize(
    ("events", "windows", "message"),
    [
        (1000, 0, "window.count must be a positive integer"),
        (1000, True, "window.count must be a positive integer"),
    ],
)
def test_bad_window_counts_are_refused(interior, events, windows, message):
    with pytest.raises(ValueError, match=message):
        simulate_scene(interior, seed=0, max_events=events, windows=windows)


@pytest.mark.parametrize("near_first", [True, False])
def test_zbuffer_shows_the_nearer_object_whatever_the_order(near_first):
    cfg = _scene()
    near = {**cfg["objects"][0], "name": "near", "size": [0.04, 0.04], "position": [0, 0, 0.5]}
    far = {**cfg["objects"][0], "name": "far", "size": [0.4, 0.4], "position": [0, 0, 1.5]}
    for body in (near, far):
        body["velocity"] = [0.0, 0.0, 0.0]
    cfg["objects"] = [near, far] if near_first else [far, near]
    depth = simulate_scene(cfg, seed=0, max_events=None).depth_maps[0].depth
    assert depth[7, 31] == pytest.approx(0.5)
    assert depth[7, 39] == pytest.approx(1.5)
    assert depth[7, 0] == pytest.approx(2.0)


def test_ego_velocity_makes_the_static_scene_object_zero():
    cfg = _scene()
    cfg["camera"]["ego_velocity"] = [0.3, 0.0, 0.2]
    cfg["background"][0]["texture"] = {
        "kind": "noise",
        "cell": 0.05,
        "low": 0.1,
        "high": 0.9,
        "octaves": 1,
    }
    body = cfg["objects"][0]
    body.update(size=[0.3, 0.3], position=[0.0, 0.0, 1.0], velocity=[0.0, 0.2, 0.0])
    body["texture"] = cfg["background"][0]["texture"]
    rec = simulate_scene(cfg, seed=0, max_events=2000)
    gt = rec.ground_truth
    assert gt.names[0] == "static scene"
    assert np.allclose(gt.motions[0], [-0.3, 0.0, -0.2])
    assert np.allclose(gt.motions[1], [-0.3, 0.2, -0.2])
    assert {0, 1} <= set(np.unique(gt.labels).tolist()) <= {0, 1}
    t0, t1 = (d.t for d in rec.depth_maps)
    corner = [d.depth[0, 0] for d in rec.depth_maps]
    assert corner[1] - corner[0] == pytest.approx(-0.2 * (t1 - t0), rel=1e-4)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda c: c["sensor"].update(typo=1), r"sensor.typo is not a known key"),
        (lambda c: c.update(kind="recording"), r"kind must be 'simulated'"),
        (
            lambda c: c["objects"][0].update(size=[1, 1, 1]),
            r"objects\[0\].size must be a list of 2",
        ),
        (lambda c: c["objects"][0]["texture"].update(kind="wood"), r"texture.kind must be one of"),
        (lambda c: c["render"].update(max_pixel_step=2), r"max_pixel_step must be a fraction"),
        (lambda c: c["sensor"].update(threshold_mean=0), r"threshold_mean must be > 0"),
        (
            lambda c: c["background"][0].update(point=[0, 0, -1]),
            r"no background plane is seen at pixel",
        ),
        (
            lambda c: c["objects"][0].update(velocity=[0, 0, -2.0]),
            r"object 'patch' reaches the camera plane",
        ),
        (
            lambda c: (c["camera"].update(ego_velocity=[0, 0, 3.0]), c.update(objects=[])),
            r"the camera reaches background plane 'wall'",
        ),
    ],
)
def test_bad_scene_raises_one_line_value_error(edit, message):
    cfg = _scene()
    edit(cfg)
    with pytest.raises(ValueError, match=message) as info:
        simulate_scene(cfg, seed=0, max_events=None)
    assert "\n" not in str(info.value)


def test_max_events_must_be_positive():
    with pytest.raises(ValueError, match="max_events must be a positive integer"):
        simulate_scene(_scene(), seed=0, max_events=0)
