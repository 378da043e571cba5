"""Recording consistency checks and windowing by depth maps."""

from __future__ import annotations

import numpy as np
import pytest

from spatialseg.events import EventStream
from spatialseg.recording import Camera, DepthMap, GroundTruth, Recording

CAM = Camera(fx=100.0, fy=100.0, cx=2.0, cy=1.5, width=4, height=3)


def _events(t):
    n = len(t)
    return EventStream(np.zeros(n), np.zeros(n), t, np.ones(n), 4, 3)


def _depth(t, shape=(3, 4)):
    return DepthMap(t, np.ones(shape, dtype=np.float32))


def test_depth_map_shape_must_match_sensor():
    with pytest.raises(ValueError, match=r"depth map shape \(4, 4\) does not match"):
        Recording(_events([0.0]), CAM, (_depth(0.0, (4, 4)),))


def test_ground_truth_needs_one_label_per_event():
    gt = GroundTruth(np.array([0]), {0: np.zeros(3)})
    with pytest.raises(ValueError, match="1 labels for 2 events"):
        Recording(_events([0.0, 1.0]), CAM, ground_truth=gt)


def test_ground_truth_labels_need_motions():
    with pytest.raises(ValueError, match=r"objects \[3\] with no motion"):
        GroundTruth(np.array([3, -1]), {0: np.zeros(3)})


def test_camera_rejects_bad_intrinsics():
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        Camera(fx=0.0, fy=1.0, cx=0.0, cy=0.0, width=4, height=3)


def test_windows_split_events_between_consecutive_depth_maps():
    t = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    gt = GroundTruth(np.arange(5) % 2, {0: np.zeros(3), 1: np.ones(3)})
    rec = Recording(_events(t), CAM, (_depth(0.0), _depth(1.0), _depth(2.0)), ground_truth=gt)
    windows = list(rec.windows())
    assert [w.events.t.tolist() for _, w in windows] == [[0.0, 0.5], [1.0, 1.5, 2.0]]
    assert np.concatenate([i for i, _ in windows]).tolist() == list(range(5))
    assert windows[1][1].ground_truth.labels.tolist() == [0, 1, 0]
    assert [d.t for d in windows[1][1].depth_maps] == [1.0, 2.0]


def test_windows_need_two_depth_maps():
    with pytest.raises(ValueError, match="EDPA needs at least two"):
        list(Recording(_events([0.0]), CAM, (_depth(0.0),)).windows())


def test_spans_add_neighbouring_windows_and_locate_the_window_in_them():
    t = np.arange(8) * 0.5  # 0 .. 3.5; maps at 0, 1, 2, 3.5: windows of 2, 2 and 4 events
    rec = Recording(_events(t), CAM, tuple(_depth(x) for x in (0.0, 1.0, 2.0, 3.5)))
    spans = list(rec.spans(1))
    assert [i.tolist() for i, _, _ in spans] == [[0, 1], [2, 3], [4, 5, 6, 7]]
    assert [s.events.t.tolist() for _, s, _ in spans] == [
        t[:4].tolist(),
        t.tolist(),
        t[2:].tolist(),
    ]
    assert [[d.t for d in s.depth_maps] for _, s, _ in spans] == [
        [0.0, 1.0, 2.0],
        [0.0, 1.0, 2.0, 3.5],
        [1.0, 2.0, 3.5],
    ]
    for index, span, inner in spans:
        np.testing.assert_array_equal(span.events.t[inner], t[index])
    alone = [(i.tolist(), s.events.t.tolist()) for i, s, _ in rec.spans(0)]
    assert alone == [(i.tolist(), w.events.t.tolist()) for i, w in rec.windows()]


@pytest.mark.parametrize("context", [-1, 1.5, "abc"])
def test_spans_refuse_a_bad_context(context):
    rec = Recording(_events([0.0, 1.0]), CAM, (_depth(0.0), _depth(1.0)))
    with pytest.raises(ValueError, match=r"window\.context must be an integer >= 0"):
        list(rec.spans(context))
