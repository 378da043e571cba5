"""Depth sources, attach_depth and the depth config group."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from spatialseg.config import ConfigError, conf_dir, group_options, validate_config
from spatialseg.depth import (
    DEPTH_SOURCES,
    ConstantDepth,
    GroundPlaneDepth,
    attach_depth,
    make_depth_source,
    resize_bilinear,
    with_configured_depth,
)
from spatialseg.edpa import back_project
from spatialseg.events import EventStream
from spatialseg.recording import Camera, DepthMap, Keyframe, Recording
from spatialseg.settings import settings_from

# A 201 x 161 sensor with the principal point on pixel (100, 80).
CAM = Camera(fx=200.0, fy=200.0, cx=100.0, cy=80.0, width=201, height=161)
GROUND = {"name": "ground_plane", "height": 1.5, "pitch": 10.0, "roll": 0.0, "far_depth": None}


def _compose(*overrides: str):
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        return compose("config", overrides=["+scene=interior", *overrides])


# ---------------------------------------------------------------- ground plane and constant


def test_ground_plane_matches_hand_computed_depths():
    """Camera 1.5 m up, pitched 10 degrees down: the principal ray meets the ground at
    1.5 / sin(10 deg) = 8.638 m; the ray 40 rows lower (dy = 40/200 = 0.2) at
    1.5 / (0.2 cos 10 deg + sin 10 deg) = 4.047 m; the horizon is tan(10 deg) * 200 = 35.3
    rows above the principal point, so row 44 is sky and row 45 ground."""
    depth = make_depth_source(GROUND).depth_map(0.5, CAM, None)
    assert isinstance(depth, DepthMap) and depth.t == 0.5
    assert depth.depth.shape == (161, 201) and depth.depth.dtype == np.float32
    assert depth.depth[80, 100] == pytest.approx(8.6382, abs=1e-4)
    assert depth.depth[120, 100] == pytest.approx(4.0474, abs=1e-4)
    # without roll, depth is constant along a row (Z-depth, not range)
    np.testing.assert_allclose(depth.depth[120], 4.0474, atol=1e-4)
    assert np.isnan(depth.depth[:45]).all()  # at or above the horizon: unknown
    assert np.isfinite(depth.depth[45:]).all() and (depth.depth[45:] > 0).all()
    assert depth.depth[45, 100] > 100.0  # just below the horizon: far away


def test_ground_plane_points_lie_on_the_ground():
    """Back-projected, every pixel's point is ``height`` below the camera along the normal."""
    src = GroundPlaneDepth(height=1.2, pitch=7.0, roll=4.0)
    z = src.depth_map(0.0, CAM, None).depth.astype(np.float64)
    v, u = np.nonzero(np.isfinite(z))
    points = back_project(u.astype(float), v.astype(float), z[v, u], CAM)
    pitch, roll = math.radians(7.0), math.radians(4.0)
    normal = [math.sin(roll) * math.cos(pitch), math.cos(roll) * math.cos(pitch), math.sin(pitch)]
    np.testing.assert_allclose(points @ normal, 1.2, rtol=1e-5)


def test_ground_plane_roll_turns_the_ground_to_the_side():
    """Roll 90 degrees, pitch 0: the ground is to the camera's right, Z = h fx / (u - cx)."""
    z = GroundPlaneDepth(height=1.5, pitch=0.0, roll=90.0).depth_map(0.0, CAM, None).depth
    assert z[30, 150] == pytest.approx(1.5 * 200 / 50, rel=1e-5)  # 6.0 m, any row
    assert z[140, 150] == pytest.approx(6.0, rel=1e-5)
    assert np.isnan(z[:, :101]).all()  # the principal column and left of it: no ground


def test_ground_plane_far_depth_fills_the_sky_and_caps_the_ground():
    cfg = {**GROUND, "far_depth": 30.0}
    z = make_depth_source(cfg).depth_map(0.0, CAM, None).depth
    np.testing.assert_array_equal(z[:45], 30.0)
    assert z.max() == 30.0 and z[46, 100] == 30.0  # 1.5 / (-34 / 200 cos + sin) = 237 m
    assert z[80, 100] == pytest.approx(8.6382, abs=1e-4)


def test_constant_depth_everywhere():
    z = make_depth_source({"name": "constant", "value": 3.5}).depth_map(1.0, CAM, None)
    assert z.depth.shape == (161, 201)
    np.testing.assert_array_equal(z.depth, 3.5)


@pytest.mark.parametrize(
    ("cfg", "message"),
    [
        ({"name": "lidar"}, "unknown depth source 'lidar'; .*constant, ground_plane, onnx, rec"),
        ({}, "unknown depth source None"),
        ({**GROUND, "height": -1.5}, "depth.height must be a positive number"),
        ({**GROUND, "height": 0}, "depth.height must be a positive number"),
        ({**GROUND, "height": "1.5"}, "depth.height must be a positive number"),
        ({**GROUND, "pitch": 90.0}, r"depth.pitch must be in \(-90, 90\)"),
        ({**GROUND, "pitch": float("nan")}, "depth.pitch must be a finite number"),
        ({**GROUND, "far_depth": 0.0}, "depth.far_depth must be a positive number"),
        ({**GROUND, "hieght": 1.0}, "depth=ground_plane has no parameter 'hieght'"),
        ({"name": "constant", "value": -2.0}, "depth.value must be a positive number"),
        ({"name": "constant"}, "depth.value must be a positive number"),
        ({"name": "onnx", "model": None}, "depth=onnx needs a model"),
    ],
)
def test_bad_configs_are_one_line_errors(cfg, message):
    with pytest.raises(ValueError, match=message) as info:
        make_depth_source(cfg)
    assert "\n" not in str(info.value)


def test_recording_source_makes_no_maps():
    with pytest.raises(ValueError, match="depth=recording makes no depth maps"):
        make_depth_source({"name": "recording"}).depth_map(0.0, CAM, None)


# ---------------------------------------------------------------- ONNX


def _onnx_model(path: Path, *, size=(8, 8), gain=2.0, offset=0.5, channels=3) -> Path:
    """A tiny network: output (1 x H x W) = offset + gain * mean over channels of the input."""
    import onnx
    from onnx import TensorProto, helper

    h, w = size
    image = helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, channels, h, w])
    out = helper.make_tensor_value_info("inverse_depth", TensorProto.FLOAT, [1, h, w])
    nodes = [
        helper.make_node("ReduceMean", ["image"], ["m"], axes=[1], keepdims=0),
        helper.make_node("Mul", ["m", "gain"], ["g"]),
        helper.make_node("Add", ["g", "offset"], ["inverse_depth"]),
    ]
    constants = [
        helper.make_tensor("gain", TensorProto.FLOAT, [], [gain]),
        helper.make_tensor("offset", TensorProto.FLOAT, [], [offset]),
    ]
    graph = helper.make_graph(nodes, "tiny_depth", [image], [out], constants)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


@pytest.fixture
def model(tmp_path) -> Path:
    return _onnx_model(tmp_path / "tiny.onnx")


def _onnx_cfg(model: Path, **overrides) -> dict:
    cfg = OmegaConf.to_container(OmegaConf.load(conf_dir() / "depth" / "onnx.yaml"))
    cfg.update({"model": str(model), "mean": [0.0] * 3, "std": [1.0] * 3, **overrides})
    return cfg


SMALL = Camera(fx=20.0, fy=20.0, cx=11.5, cy=7.5, width=24, height=16)


def _grey(level: int) -> np.ndarray:
    return np.full((SMALL.height, SMALL.width), level, dtype=np.uint8)


def test_onnx_metric_output_passes_through(model):
    """output=depth, affine 1/0: the map is the network's output, 0.5 + 2 * 102/255 = 1.3 m."""
    src = make_depth_source(_onnx_cfg(model, output="depth", scaling="affine"))
    z = src.depth_map(2.0, SMALL, _grey(102)).depth
    assert z.shape == (16, 24)
    np.testing.assert_allclose(z, 0.5 + 2.0 * 102 / 255, rtol=1e-6)


def test_onnx_inverse_depth_with_scale_and_shift(model):
    """depth = 1 / (scale * output + shift) = 1 / (4 (0.5 + 2 * 51/255) - 1) = 1 / 2.6 m."""
    cfg = _onnx_cfg(model, output="inverse_depth", scaling="affine", scale=4.0, shift=-1.0)
    z = make_depth_source(cfg).depth_map(0.0, SMALL, _grey(51)).depth
    np.testing.assert_allclose(z, 1.0 / (4.0 * (0.5 + 2.0 * 51 / 255) - 1.0), rtol=1e-6)


def test_onnx_normalises_like_the_network_was_trained(model):
    """mean 0.5 and std 0.25 on every channel: (204/255 - 0.5) / 0.25 = 1.2 enters the net."""
    cfg = _onnx_cfg(model, output="depth", scaling="affine", mean=[0.5] * 3, std=[0.25] * 3)
    z = make_depth_source(cfg).depth_map(0.0, SMALL, _grey(204)).depth
    np.testing.assert_allclose(z, 0.5 + 2.0 * 1.2, rtol=1e-6)
    colour = np.repeat(_grey(204)[..., None], 3, axis=2)
    np.testing.assert_array_equal(make_depth_source(cfg).depth_map(0.0, SMALL, colour).depth, z)


def test_onnx_median_scaling_and_near_is_bright(model):
    """Relative inverse depth: brighter (larger output) is nearer; the median is median_depth."""
    ramp = np.tile(np.linspace(0, 255, SMALL.width).astype(np.uint8), (SMALL.height, 1))
    cfg = _onnx_cfg(model, scaling="median", median_depth=4.0)
    z = make_depth_source(cfg).depth_map(0.0, SMALL, ramp).depth
    assert np.median(z) == pytest.approx(4.0, rel=1e-6)
    assert np.all(np.diff(z[8]) <= 0) and z[8, 0] > z[8, -1] * 1.5


def test_onnx_resizes_input_and_output(tmp_path):
    """A 4 x 6 network on a 16 x 24 sensor: a left/right split image comes back split."""
    model = _onnx_model(tmp_path / "m.onnx", size=(4, 6))
    image = _grey(0)
    image[:, 12:] = 255
    cfg = _onnx_cfg(model, output="depth", scaling="affine")
    z = make_depth_source(cfg).depth_map(0.0, SMALL, image).depth
    assert z.shape == (16, 24)
    np.testing.assert_allclose(z[:, :4], 0.5, rtol=1e-6)
    np.testing.assert_allclose(z[:, -4:], 2.5, rtol=1e-6)
    assert np.all(np.diff(z[5]) >= 0)


def test_onnx_max_depth_marks_far_pixels_unknown(model):
    cfg = _onnx_cfg(model, output="depth", scaling="affine", max_depth=1.0)
    image = _grey(0)
    image[:8] = 255  # top: 2.5 m (beyond max_depth), bottom: 0.5 m
    z = make_depth_source(cfg).depth_map(0.0, SMALL, image).depth
    assert np.isnan(z[:3]).all() and np.allclose(z[-3:], 0.5)


def test_onnx_dynamic_input_needs_an_input_size(tmp_path):
    model = _onnx_model(tmp_path / "dyn.onnx", size=("height", "width"))
    with pytest.raises(ValueError, match=r"input size is not fixed .*set depth.input_size"):
        make_depth_source(_onnx_cfg(model))
    src = make_depth_source(_onnx_cfg(model, input_size=[5, 7], output="depth", scaling="affine"))
    np.testing.assert_allclose(src.depth_map(0.0, SMALL, _grey(255)).depth, 2.5, rtol=1e-6)


def test_onnx_errors(model, tmp_path):
    with pytest.raises(ValueError, match=r"nope.onnx: no such file"):
        make_depth_source(_onnx_cfg(tmp_path / "nope.onnx"))
    broken = tmp_path / "broken.onnx"
    broken.write_bytes(b"not a network")
    with pytest.raises(ValueError, match="onnxruntime cannot load it"):
        make_depth_source(_onnx_cfg(broken))
    with pytest.raises(ValueError, match=r"takes 8 x 8 but depth.input_size is \[4, 4\]"):
        make_depth_source(_onnx_cfg(model, input_size=[4, 4]))
    with pytest.raises(
        ValueError, match=re.escape("depth.output must be one of inverse_depth, depth")
    ):
        make_depth_source(_onnx_cfg(model, output="disparity"))
    with pytest.raises(ValueError, match=re.escape("depth.std must be positive")):
        make_depth_source(_onnx_cfg(model, std=[1.0, 0.0, 1.0]))
    src = make_depth_source(_onnx_cfg(model))
    with pytest.raises(ValueError, match="depth=onnx needs a keyframe image"):
        src.depth_map(0.0, SMALL, None)
    with pytest.raises(
        ValueError, match=re.escape("keyframe at t=0.000000 is 12x16 but the sensor is 24x16")
    ):
        src.depth_map(0.0, SMALL, np.zeros((16, 12), np.uint8))


def test_resize_bilinear_keeps_constants_and_linear_ramps():
    a = np.full((3, 5), 7.0)
    np.testing.assert_array_equal(resize_bilinear(a, 9, 4), 7.0)
    ramp = np.arange(4.0)[None, :].repeat(2, axis=0)  # centres 0..3
    up = resize_bilinear(ramp, 2, 8)  # new centres at (j + 0.5) / 2 - 0.5
    np.testing.assert_allclose(up[0], [0, 0.25, 0.75, 1.25, 1.75, 2.25, 2.75, 3])


# ---------------------------------------------------------------- attach_depth


def _recording(t: np.ndarray, keyframes=(), depth_maps=(), camera=SMALL) -> Recording:
    n = len(t)
    x = np.arange(n) % camera.width
    y = np.arange(n) % camera.height
    events = EventStream(x, y, t, np.ones(n), camera.width, camera.height)
    return Recording(events, camera, depth_maps, keyframes)


def test_attach_depth_without_keyframes_every_n_events():
    t = np.linspace(0.0, 1.0, 100)
    rec = attach_depth(_recording(t), ConstantDepth(2.0), window_events=50)
    assert [m.t for m in rec.depth_maps] == [t[0], t[50], t[99]]
    assert [len(w.events) for _, w in rec.windows()] == [50, 50]
    np.testing.assert_array_equal(rec.depth_maps[1].depth, 2.0)


def test_attach_depth_merges_a_short_last_window():
    """100 events every 30: windows of 30, 30, 30 and 10; the 10 join the window before."""
    t = np.linspace(0.0, 1.0, 100)
    rec = attach_depth(_recording(t), ConstantDepth(2.0), window_events=30)
    assert [m.t for m in rec.depth_maps] == [t[0], t[30], t[60], t[99]]
    assert [len(w.events) for _, w in rec.windows()] == [30, 30, 40]
    one = attach_depth(_recording(t), ConstantDepth(2.0), window_events=1000)
    assert [m.t for m in one.depth_maps] == [t[0], t[99]]


def test_attach_depth_at_keyframes_with_their_images(model):
    """Maps at the keyframes bounding the events (0.0 .. 1.0 for events in 0.1 .. 0.9); each
    map is computed from its own image (level L gives 0.5 + 2 L / 255 m)."""
    levels = {0.0: 0, 0.2: 51, 0.5: 102, 0.8: 153, 1.0: 204, 1.2: 255}
    frames = [Keyframe(tk, _grey(level)) for tk, level in reversed(levels.items())]
    rec = _recording(np.linspace(0.1, 0.9, 40), keyframes=frames)
    src = make_depth_source(_onnx_cfg(model, output="depth", scaling="affine"))
    out = attach_depth(rec, src, window_events=10)
    assert [m.t for m in out.depth_maps] == [0.0, 0.2, 0.5, 0.8, 1.0]
    for m in out.depth_maps:
        np.testing.assert_allclose(m.depth, 0.5 + 2 * levels[m.t] / 255, rtol=1e-6)
    assert sum(len(w.events) for _, w in out.windows()) == 40
    # a source without images keeps the user's window length (every 10 events)
    ground = attach_depth(rec, make_depth_source(GROUND | {"far_depth": 9.0}), window_events=10)
    assert [m.t for m in ground.depth_maps] == [rec.events.t[i] for i in (0, 10, 20, 30, 39)]


def test_attach_depth_with_one_keyframe_falls_back_to_event_counts():
    t = np.linspace(0.0, 1.0, 20)
    rec = _recording(t, keyframes=[Keyframe(0.5, _grey(0))])
    out = attach_depth(rec, ConstantDepth(1.0), window_events=10)
    assert [m.t for m in out.depth_maps] == [t[0], t[10], t[19]]


def test_attach_depth_errors(model):
    t = np.linspace(0.0, 1.0, 20)
    onnx_source = make_depth_source(_onnx_cfg(model))
    with pytest.raises(ValueError, match="depth=onnx needs two or more keyframe images"):
        attach_depth(_recording(t), onnx_source, window_events=10)
    with pytest.raises(ValueError, match=r"has 0 depth map\(s\) and depth=recording needs two"):
        attach_depth(_recording(t), make_depth_source({"name": "recording"}), window_events=10)
    with pytest.raises(ValueError, match="all events share one timestamp"):
        attach_depth(_recording(np.zeros(5)), ConstantDepth(1.0), window_events=2)
    with pytest.raises(ValueError, match=re.escape("window.events must be an integer >= 1")):
        attach_depth(_recording(t), ConstantDepth(1.0), window_events=0)


def test_attach_depth_recording_source_keeps_the_recording():
    t = np.linspace(0.0, 1.0, 20)
    maps = (DepthMap(0.0, np.ones((16, 24))), DepthMap(1.0, np.ones((16, 24))))
    rec = _recording(t, depth_maps=maps)
    assert attach_depth(rec, make_depth_source({"name": "recording"}), window_events=5) is rec


def test_configured_depth_replaces_maps_unless_depth_is_recording():
    t = np.linspace(0.0, 1.0, 60)
    maps = (DepthMap(0.0, np.ones((16, 24))), DepthMap(1.0, np.ones((16, 24))))
    rec = _recording(t, depth_maps=maps)
    default = settings_from({"window": {"events": 30}})  # depth=recording
    assert with_configured_depth(rec, default) is rec
    cfg = {"depth": {"name": "constant", "value": 3.0}, "window": {"events": 30}}
    out = with_configured_depth(rec, settings_from(cfg))
    assert [m.t for m in out.depth_maps] == [t[0], t[30], t[59]]
    assert all(np.all(m.depth == 3.0) for m in out.depth_maps)


# ---------------------------------------------------------------- config group


def test_every_shipped_depth_option_is_a_known_source():
    assert set(group_options("depth")) == set(DEPTH_SOURCES)
    for name in group_options("depth"):
        cfg = OmegaConf.load(conf_dir() / "depth" / f"{name}.yaml")
        assert cfg.name == name
        assert set(cfg) - {"name"} == set(DEPTH_SOURCES[name].keys)


@pytest.mark.parametrize("name", ["recording", "constant", "ground_plane"])
def test_composed_depth_config_validates_and_builds(name):
    cfg = _compose(f"depth={name}")
    validate_config(cfg, {"depth": name, "scene": "interior"})
    source = make_depth_source(OmegaConf.to_container(cfg.depth))
    assert source.name == name


def test_composed_config_rejects_a_misspelt_depth_parameter():
    cfg = _compose("depth=ground_plane", "+depth.hieght=2")
    with pytest.raises(ConfigError, match=re.escape("unknown config key 'depth.hieght'")):
        validate_config(cfg, {"depth": "ground_plane", "scene": "interior"})
    cfg = _compose("+denoise.radiu=2")
    with pytest.raises(ConfigError, match=re.escape("unknown config key 'denoise.radiu'")):
        validate_config(cfg, {"depth": "recording", "scene": "interior"})


@pytest.mark.parametrize(
    ("depth", "message"),
    [
        ({"name": "constant", "value": -1}, "depth.value must be a positive number"),
        ({"name": "ground_plane", "pitch": 100}, "depth.pitch must be in (-90, 90) degrees"),
        ({"name": "nope"}, "unknown depth source 'nope'"),
    ],
)
def test_a_bad_depth_source_is_refused_by_the_up_front_check(depth, message):
    """The run's check (before a scene is simulated or a file read) builds the depth source."""
    from spatialseg.window import check_config

    base = {"ground_plane": {"height": 1.5, "pitch": 10.0, "roll": 0.0, "far_depth": None}}
    with pytest.raises(ValueError, match=re.escape(message)):
        check_config({"depth": {**base.get(depth["name"], {}), **depth}})
