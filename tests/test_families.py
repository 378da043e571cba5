"""The scene families: deterministic draws that keep each family's promise, and ground truth
consistent with the drawn motions."""

from __future__ import annotations

import functools
import itertools
from dataclasses import asdict

import numpy as np
import pytest

from spatialseg.events import EventStream
from spatialseg.recording import Camera, DepthMap, GroundTruth, Recording
from spatialseg.simulate.families import (
    FAMILIES,
    MODIFIER_LIMITS,
    SENSORS,
    draw_scene,
    merge_equal_motions,
    simulate_family,
    with_noise,
    with_time_offset,
)
from spatialseg.simulate.render import Renderer
from spatialseg.simulate.scene import parse_scene
from spatialseg.simulate.simulator import simulate_scene, texture_keys

#: The draws each promise is checked on (a moving-camera draw simulates a pilot: seconds).
SEEDS = range(4)


def _relative(scene: dict) -> list[np.ndarray]:
    """Each object's velocity relative to the camera."""
    ego = np.asarray(scene["camera"]["ego_velocity"])
    return [np.asarray(o["velocity"]) - ego for o in scene["objects"]]


def _image_velocity(scene: dict, body: dict, t: float) -> np.ndarray:
    """The image velocity (px/s) of a box's front-face centre at time ``t``."""
    cam, ego = scene["camera"], np.asarray(scene["camera"]["ego_velocity"])
    v = np.asarray(body["velocity"]) - ego
    p = np.asarray(body["position"]) + v * t - [0, 0, body["size"][2] / 2]
    focal = np.array([cam["fx"], cam["fy"]])
    return focal * (v[:2] - p[:2] / p[2] * v[2]) / p[2]


@functools.cache
def _drawn(family: str, seed: int):
    """``draw_scene(family, seed)``, drawn once per test module (a draw renders frames)."""
    return draw_scene(family, seed)


@functools.cache
def _middle_render(family: str, seed: int):
    """The drawn scene rendered at the middle of its duration, once per test module."""
    scene = _drawn(family, seed).scene
    parsed = parse_scene(scene)
    return Renderer(parsed, texture_keys(parsed, 0)).render(scene["duration"] / 2)


@pytest.mark.parametrize("family", list(FAMILIES))
def test_a_draw_is_deterministic_per_seed_and_differs_between_seeds(family):
    first, again, other = _drawn(family, 1), draw_scene(family, 1), _drawn(family, 2)
    assert first.scene == again.scene and first.modifiers == again.modifiers
    assert first.windows == again.windows and first.time_offset == again.time_offset
    assert first.scene != other.scene


@pytest.mark.parametrize("family", list(FAMILIES))
def test_every_draw_is_a_valid_scene_with_visible_motions_and_modifiers_in_range(family):
    for seed in SEEDS:
        drawn = _drawn(family, seed)
        cam = drawn.scene["camera"]
        assert (cam["width"], cam["height"]) in SENSORS
        for name, value in asdict(drawn.modifiers).items():
            assert 0 <= value <= MODIFIER_LIMITS[name]
        frame = _middle_render(family, seed)
        for k in range(1, len(drawn.scene["objects"]) + 1):
            assert np.count_nonzero(frame.label == k) >= 20, (seed, k)
        velocities = _relative(drawn.scene)
        if np.any(cam["ego_velocity"]):
            velocities.append(-np.asarray(cam["ego_velocity"]))
        distinct = {tuple(np.round(v, 9)) for v in velocities}
        assert drawn.n_motions == len(distinct)


def test_opposite_directions_differ_by_more_than_90_degrees():
    for seed in SEEDS:
        scene = _drawn("opposite", seed).scene
        a, b = (_image_velocity(scene, o, scene["duration"] / 2) for o in scene["objects"])
        assert a @ b / (np.linalg.norm(a) * np.linalg.norm(b)) < 0


def test_same_direction_objects_share_a_direction_at_different_speeds_and_depths():
    for seed in SEEDS:
        scene = _drawn("same_direction", seed).scene
        assert len(scene["objects"]) in (2, 3)
        flows = [_image_velocity(scene, o, 0.0) for o in scene["objects"]]
        speeds = sorted(np.linalg.norm(f) for f in flows)
        for i, a in enumerate(flows):
            for b in flows[i + 1 :]:
                angle = np.degrees(np.arccos(a @ b / (np.linalg.norm(a) * np.linalg.norm(b))))
                assert angle <= 20.5
        ratios = [b / a for a, b in itertools.pairwise(speeds)]
        assert min(ratios) >= 1.29 and speeds[-1] / speeds[0] <= 3.05
        depths = sorted(o["position"][2] - o["size"][2] / 2 for o in scene["objects"])
        assert all(b / a >= 1.2 for a, b in itertools.pairwise(depths))


def test_equal_motion_objects_share_one_velocity_at_different_depths():
    for seed in SEEDS:
        drawn = _drawn("equal_motion", seed)
        velocities = _relative(drawn.scene)
        shared = [o for o, v in zip(drawn.scene["objects"], velocities, strict=True)
                  if np.allclose(v, velocities[0])]  # fmt: skip
        assert len(shared) >= 2 and drawn.n_motions == 2
        depths = sorted(o["position"][2] for o in shared)
        assert depths[-1] / depths[0] >= 1.5


def test_looming_has_one_object_moving_mostly_along_the_optical_axis():
    for seed in SEEDS:
        velocities = _relative(_drawn("looming", seed).scene)
        along = [v for v in velocities if abs(v[2]) > 2 * np.linalg.norm(v[:2])]
        assert len(along) == 1 and len(velocities) in (2, 3)


def test_many_has_three_or_four_motions_whose_paths_cross():
    for seed in SEEDS:
        drawn = _drawn("many", seed)
        assert drawn.n_motions in (3, 4)
        assert _any_overlap(drawn.scene), seed


def _any_overlap(scene: dict) -> bool:
    """Whether two objects' image boxes overlap at some time (an occlusion)."""
    cam = scene["camera"]

    def box(body: dict, t: float) -> np.ndarray:
        v = np.asarray(body["velocity"])
        lo = np.asarray(body["position"]) + v * t - np.asarray(body["size"]) / 2
        hi = lo + np.asarray(body["size"])
        z = lo[2]
        return np.array([cam["fx"] * lo[0] / z, cam["fy"] * lo[1] / z,
                         cam["fx"] * hi[0] / z, cam["fy"] * hi[1] / z])  # fmt: skip

    for t in np.linspace(0, scene["duration"], 9):
        boxes = [box(o, t) for o in scene["objects"]]
        for i, a in enumerate(boxes):
            for b in boxes[i + 1 :]:
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    return True
    return False


def test_moving_camera_families_spread_the_static_scene_over_depth():
    for family in ("ego_sideways", "ego_forward"):
        for seed in SEEDS:
            drawn = _drawn(family, seed)
            assert np.linalg.norm(drawn.scene["camera"]["ego_velocity"]) >= 0.5
            frame = _middle_render(family, seed)
            depth = frame.depth[frame.label == 0]
            low, high = np.percentile(depth, [5, 95])
            assert low < 5.0 < high and high / low >= 1.7, (family, seed, low, high)


def test_moving_camera_families_draw_motions_a_segmentation_can_tell_apart():
    # seed 6 drew two objects 1.7 % apart in velocity before the rule (issue #25's dev run)
    for family in ("ego_sideways", "ego_forward"):
        for seed in [*SEEDS, 6]:
            scene = _drawn(family, seed).scene
            motions = [-np.asarray(scene["camera"]["ego_velocity"]), *_relative(scene)]
            for i, a in enumerate(motions):
                for b in motions[i + 1 :]:
                    larger = max(np.linalg.norm(a), np.linalg.norm(b))
                    assert np.linalg.norm(a - b) >= 0.25 * larger, (family, seed)


def test_long_is_one_window_of_many_events_with_a_clock_that_does_not_start_at_zero():
    for seed in SEEDS:
        drawn = _drawn("long", seed)
        assert drawn.windows == 1 and drawn.time_offset >= 1.0
        assert drawn.scene["camera"]["width"] >= 640


def test_fixed_modifiers_replace_the_draw_and_leave_the_scene_alone():
    drawn, fixed = draw_scene("opposite", 2), draw_scene("opposite", 2, depth_flicker=0.1, noise=0)
    assert fixed.modifiers.depth_flicker == 0.1 and fixed.modifiers.noise == 0
    assert fixed.modifiers.holes == drawn.modifiers.holes
    assert fixed.scene["objects"] == drawn.scene["objects"]
    assert fixed.scene["depth_error"]["sigma"] == 0.1


def test_density_divides_the_sensors_thresholds_and_records_more_events_of_one_scene():
    drawn, dense = (
        draw_scene("ego_sideways", 2, noise=0),
        draw_scene("ego_sideways", 2, 3.0, noise=0),
    )
    assert dense.scene["objects"] == drawn.scene["objects"]
    for key in ("threshold_mean", "threshold_std", "threshold_min", "refractory"):
        assert dense.scene["sensor"][key] == pytest.approx(drawn.scene["sensor"][key] / 3)
    sparse_events = simulate_scene(drawn.scene, seed=2, max_events=None, windows=1).events
    dense_events = simulate_scene(dense.scene, seed=2, max_events=None, windows=1).events
    assert len(dense_events) > 3 * len(sparse_events)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="density must be a finite number > 0"):
            draw_scene("opposite", 2, bad)


def test_unknown_family_and_bad_seed_and_modifier_are_refused_in_one_line():
    with pytest.raises(ValueError, match="unknown scene family 'nope'; choose from opposite"):
        draw_scene("nope", 0)
    with pytest.raises(ValueError, match="seed must be an integer >= 0"):
        draw_scene("opposite", -1)
    with pytest.raises(ValueError, match="modifier noise must be in"):
        draw_scene("opposite", 0, noise=2.0)


@pytest.mark.parametrize("family", list(FAMILIES))
def test_ground_truth_labels_follow_the_drawn_boxes(family):
    """Each object's events lie where its box projects at the event's time, and its ground
    truth motion is its drawn velocity relative to the camera."""
    drawn = draw_scene(family, 1, depth_bias=0, depth_flicker=0, holes=0, noise=0)
    recording = simulate_scene(drawn.scene, seed=drawn.seed, max_events=20000)
    truth, ev, cam = recording.ground_truth, recording.events, drawn.scene["camera"]
    ego = np.asarray(cam["ego_velocity"])
    for k, body in enumerate(drawn.scene["objects"], start=1):
        np.testing.assert_allclose(truth.motions[k], np.asarray(body["velocity"]) - ego)
        mine = truth.labels == k
        if not mine.any():
            continue
        t = ev.t[mine][:, None]
        lo = np.asarray(body["position"]) + (np.asarray(body["velocity"]) - ego) * t
        lo, hi = lo - np.asarray(body["size"]) / 2, lo + np.asarray(body["size"]) / 2
        inside = np.ones(len(t), bool)
        for axis, (pixel, focal, centre) in enumerate(
            ((ev.x[mine], cam["fx"], cam["cx"]), (ev.y[mine], cam["fy"], cam["cy"]))
        ):
            near, far = lo[:, axis] / lo[:, 2], lo[:, axis] / hi[:, 2]
            first = centre + focal * np.minimum(near, far)
            near, far = hi[:, axis] / lo[:, 2], hi[:, axis] / hi[:, 2]
            last = centre + focal * np.maximum(near, far)
            inside &= (pixel >= first - 2) & (pixel <= last + 2)
        assert inside.mean() >= 0.99, (family, k, inside.mean())
    if np.any(ego):
        np.testing.assert_allclose(truth.motions[0], -ego)


def test_simulate_family_cuts_windows_adds_noise_and_merges_equal_motions():
    drawn = draw_scene("equal_motion", 1, noise=0.2)
    recording = simulate_family(drawn)
    assert len(recording.depth_maps) == drawn.windows + 1
    counts = [len(index) for index, _ in recording.windows()]
    assert max(counts) / min(counts) <= 1.03  # equal before the noise, spread uniformly
    labels = recording.ground_truth.labels
    assert np.mean(labels == -1) == pytest.approx(0.2, abs=0.02)
    assert len(recording.ground_truth.motions) == drawn.n_motions == 2


def test_small_object_holds_two_to_five_percent_of_the_events():
    for seed in (0, 2):
        recording = simulate_family(draw_scene("small_object", seed, noise=0))
        labels = recording.ground_truth.labels
        share = np.mean(labels[labels >= 0] == 2)
        assert 0.015 <= share <= 0.06, (seed, share)


def _tiny(n: int = 100) -> Recording:
    """A recording of ``n`` events on a 20 x 10 sensor between two depth maps, labelled 1."""
    events = EventStream(
        np.arange(n) % 20, np.arange(n) % 10, np.linspace(0, 1, n), np.ones(n), 20, 10
    )
    maps = (DepthMap(0.0, np.ones((10, 20))), DepthMap(1.0, np.ones((10, 20))))
    truth = GroundTruth(np.ones(n), {1: np.array([1.0, 0, 0])})
    return Recording(events, Camera(10, 10, 10, 5, 20, 10), maps, ground_truth=truth)


def test_noise_and_time_offset_keep_events_sorted_and_labelled():
    noisy = with_noise(_tiny(), 0.25, np.random.default_rng(0))
    assert len(noisy.events) == 133 and np.all(np.diff(noisy.events.t) >= 0)
    assert np.count_nonzero(noisy.ground_truth.labels == -1) == 33
    later = with_time_offset(noisy, 1.7e9)
    assert later.events.t[0] == pytest.approx(1.7e9) and later.depth_maps[1].t == 1.7e9 + 1.0
    assert [len(i) for i, _ in later.windows()] == [133]


def test_equal_motions_merge_into_the_smallest_id():
    truth = GroundTruth(
        np.array([1, 2, 3, -1, 2]),
        {1: np.array([1.0, 0, 0]), 2: np.array([0.0, 1, 0]), 3: np.array([1.0, 0, 0])},
        {1: "a", 2: "b", 3: "c"},
    )
    merged = merge_equal_motions(truth)
    np.testing.assert_array_equal(merged.labels, [1, 2, 1, -1, 2])
    assert sorted(merged.motions) == [1, 2] and merged.names[1] == "a + c"
