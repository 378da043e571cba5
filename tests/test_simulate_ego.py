"""Ego-motion: static props, the static scene as one motion, and the shipped ego scenes."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from spatialseg.config import conf_dir
from spatialseg.simulate import simulate_scene

FX = 100.0
WALL, PROP = 3.0, 1.0  # depths (m) of the background wall and the static prop's front face
EGO = [0.3, 0.0, 0.1]
NOISE = {"kind": "noise", "cell": 0.1, "low": 0.1, "high": 0.9, "octaves": 1}


def _scene(ego=EGO) -> dict:
    """A 64 x 24 camera translating past a wall at 3 m and a static prop (box) at 1 m, with a
    small patch rising at 2 m; every surface textured, no noise events."""
    return {
        "name": "tiny ego",
        "kind": "simulated",
        "description": "a wall and a prop at two depths, a rising patch, a moving camera",
        "camera": {
            "width": 64,
            "height": 24,
            "fx": FX,
            "fy": FX,
            "cx": 31.5,
            "cy": 11.5,
            "ego_velocity": list(ego),
        },
        "duration": 1.0,
        "sensor": {
            "threshold_mean": 0.2,
            "threshold_std": 0.0,
            "threshold_min": 0.05,
            "refractory": 0.0,
            "noise_rate": 0.0,
            "log_eps": 0.001,
        },
        "render": {"max_pixel_step": 0.25},
        "lighting": {"gain": 1.0, "gamma": 1.0},
        "background": [
            {"name": "wall", "normal": [0, 0, 1], "point": [0, 0, WALL], "texture": NOISE},
            {
                "name": "crate",
                "shape": "box",
                "size": [0.2, 0.4, 0.2],
                "position": [-0.15, 0.0, PROP + 0.1],
                "texture": NOISE,
            },
        ],
        "objects": [
            {
                "name": "patch",
                "shape": "patch",
                "size": [0.3, 0.2],
                "position": [0.4, 0.0, 2.0],
                "velocity": [0.0, -0.3, 0.0],
                "texture": NOISE,
            }
        ],
    }


def _row(depth: np.ndarray, row: int) -> np.ndarray:
    """One row of a depth map as float64."""
    return depth[row].astype(np.float64)


def test_static_scene_is_one_object_moving_at_minus_ego_with_planes_and_props():
    rec = simulate_scene(_scene(), seed=0, max_events=3000)
    gt = rec.ground_truth
    assert gt.names == {0: "static scene", 1: "patch"}
    assert np.allclose(gt.motions[0], -np.asarray(EGO))
    assert np.allclose(gt.motions[1], np.array([0.0, -0.3, 0.0]) - EGO)
    assert set(np.unique(gt.labels).tolist()) == {0, 1}
    depth = rec.depth_maps[0].depth[rec.events.y, rec.events.x]
    static = gt.labels == 0
    assert np.any(static & (depth < 1.5)), "the prop (1 m) gives no static-scene events"
    assert np.any(static & (depth > 2.5)), "the wall (3 m) gives no static-scene events"


def test_prop_rests_in_the_world_so_it_slides_against_the_camera():
    rec = simulate_scene(_scene(ego=[0.3, 0.0, 0.0]), seed=0, max_events=1000)
    row = 11
    columns = []
    for depth_map in rec.depth_maps:
        front = np.flatnonzero(np.abs(_row(depth_map.depth, row) - PROP) < 1e-6)
        # the front face's right edge at X = -0.05 m, 1 m away, seen from X = 0.3 t
        edge = 31.5 + FX * (-0.05 - 0.3 * depth_map.t) / PROP
        assert front.max() == int(np.floor(edge))
        columns.append(front.max())
    assert columns[1] < columns[0]


def test_props_with_a_static_camera_never_fire_and_are_not_objects():
    cfg = _scene(ego=[0.0, 0.0, 0.0])
    cfg["objects"] = []
    rec = simulate_scene(cfg, seed=0, max_events=None)
    assert len(rec.events) == 0
    assert rec.ground_truth.motions == {}
    assert rec.depth_maps[0].depth[11, 20] == pytest.approx(PROP)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda c: c["background"][1].update(velocity=[1, 0, 0]),
            r"background\[1\].velocity is not a known key",
        ),
        (lambda c: c.update(background=[c["background"][1]]), r"needs at least one plane"),
        (
            lambda c: c["camera"].update(ego_velocity=[0, 0, 2.0]),
            r"prop 'crate' reaches the camera plane",
        ),
        (lambda c: c["background"][1].update(shape="ball"), r"shape must be one of"),
    ],
)
def test_bad_prop_raises_one_line_value_error(edit, message):
    cfg = _scene()
    edit(cfg)
    with pytest.raises(ValueError, match=message) as info:
        simulate_scene(cfg, seed=0, max_events=None)
    assert "\n" not in str(info.value)


# The shipped ego scenes: depth bands (m) of their static layers, each must fire.
LAYERS = {
    "ego_street": {"lamp post": (1.5, 1.8), "parked car": (2.45, 3.2), "building": (7.9, 8.1)},
    "ego_forward": {"near walls": (1.5, 3.0), "middle": (3.0, 5.0), "end wall": (5.8, 6.1)},
}
WINDOW = 15000


@pytest.fixture(scope="module")
def ego_windows() -> dict:
    """Each shipped ego scene simulated once (seed 0, a 15,000-event window)."""
    return {
        name: simulate_scene(
            OmegaConf.load(conf_dir() / "scene" / f"{name}.yaml"), seed=0, max_events=WINDOW
        )
        for name in LAYERS
    }


@pytest.mark.parametrize("name", sorted(LAYERS))
def test_shipped_ego_scene_has_a_dominant_static_scene_and_well_represented_objects(
    name, ego_windows
):
    rec, cfg = ego_windows[name], OmegaConf.load(conf_dir() / "scene" / f"{name}.yaml")
    ego = np.asarray(cfg.camera.ego_velocity)
    gt = rec.ground_truth
    assert len(rec.events) == WINDOW and 0.02 <= rec.events.duration <= 0.3
    assert sorted(gt.motions) == list(range(len(cfg.objects) + 1))
    assert np.allclose(gt.motions[0], -ego)
    shares = np.bincount(gt.labels[gt.labels >= 0], minlength=len(cfg.objects) + 1) / WINDOW
    assert shares[0] >= 0.5, shares
    assert shares[1:].min() >= 0.1, shares
    for i, body in enumerate(cfg.objects, start=1):
        assert np.allclose(gt.motions[i], np.asarray(body.velocity) - ego)


@pytest.mark.parametrize("name", sorted(LAYERS))
def test_every_static_depth_layer_of_a_shipped_ego_scene_fires(name, ego_windows):
    rec = ego_windows[name]
    ev, gt = rec.events, rec.ground_truth
    depth = rec.depth_maps[0].depth[ev.y, ev.x]
    for layer, (near, far) in LAYERS[name].items():
        share = np.mean((gt.labels == 0) & (depth >= near) & (depth <= far))
        assert share >= 0.03, f"{layer}: {share:.3f} of the events"
