"""Windows segmented in parallel (spatialseg.executors): a local process pool and a local Ray
instance give the serial run's labels, ids and velocities, of a recording and of a stream;
items are drawn as the work proceeds; bad settings are refused."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import optimizers
import spatialseg
from spatialseg.executors import AHEAD, ENGINES, check_parallel, map_in_order
from spatialseg.pipeline import segment_stream
from spatialseg.recording import Recording
from spatialseg.settings import settings_from

#: Starts every engine shares: the previous window's velocities exist only one after another.
INDEPENDENT = {"init": {"auto": ["image_flow", "tiles"]}}


def _square(x: int) -> int:
    """A picklable job whose result names its input."""
    return x * x


@pytest.fixture(scope="module")
def ray_instance():
    """A local Ray instance of two CPUs for this module, shut down after it."""
    import ray  # the test extra installs it

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def two_windows():
    """A two-window interior recording and its serial segmentation."""
    recording = spatialseg.simulate("interior", seed=3, window_events=3000, windows=2)
    return recording, spatialseg.segment(recording, 2, seed=5, **INDEPENDENT)


@pytest.mark.parametrize("engine", ["none", "processes"])
def test_map_in_order_keeps_the_order(engine):
    assert list(map_in_order(_square, range(7), engine=engine, workers=2)) == [
        x * x for x in range(7)
    ]


def test_map_in_order_draws_items_as_the_work_proceeds():
    drawn = []

    def endless():
        for x in itertools.count():
            drawn.append(x)
            yield x

    results = map_in_order(_square, endless(), engine="processes", workers=2)
    assert list(itertools.islice(results, 5)) == [0, 1, 4, 9, 16]
    assert len(drawn) <= 5 + AHEAD * 2  # never more than AHEAD per worker ahead
    results.close()


def test_map_in_order_on_ray(ray_instance):
    assert list(map_in_order(_square, range(5), engine="ray")) == [0, 1, 4, 9, 16]


@pytest.mark.parametrize(
    ("engine", "workers", "message"),
    [
        ("threads", None, "window.parallel must be one of"),
        ("processes", 0, "window.workers must be an integer >= 1"),
        ("ray", 1.5, "window.workers must be an integer >= 1"),
    ],
)
def test_bad_settings_are_named(engine, workers, message):
    with pytest.raises(ValueError, match=message):
        check_parallel(engine, workers)


def test_every_engine_is_accepted():
    assert [check_parallel(e, None)[0] for e in ENGINES] == list(ENGINES)


def _assert_same(a: spatialseg.Segmentation, b: spatialseg.Segmentation) -> None:
    assert np.array_equal(a.labels, b.labels)
    assert np.allclose(a.probabilities, b.probabilities)
    assert len(a.windows) == len(b.windows) == 2
    for wa, wb in zip(a.windows, b.windows, strict=True):
        assert np.array_equal(wa.clustering.thetas, wb.clustering.thetas)
        assert np.array_equal(wa.ids, wb.ids)


def test_process_pool_gives_the_serial_labels(two_windows):
    recording, serial = two_windows
    assert len(np.unique(serial.labels[serial.labels >= 0])) >= 2  # a real segmentation
    pooled = spatialseg.segment(
        recording, 2, seed=5, window={"parallel": "processes", "workers": 2}, **INDEPENDENT
    )
    _assert_same(serial, pooled)


def test_ray_gives_the_serial_labels(two_windows, ray_instance):
    recording, serial = two_windows
    on_ray = spatialseg.segment(recording, 2, seed=5, window={"parallel": "ray"}, **INDEPENDENT)
    _assert_same(serial, on_ray)


@pytest.fixture(scope="module")
def stream():
    """Three depth-less 3,000-event chunks of an interior recording (a file read by
    scene.stream=true), their settings, and the serial stream's segmentations."""
    recording = spatialseg.simulate("interior", seed=4, window_events=3000, windows=3)
    ev = recording.events
    chunks = [
        Recording(ev.select(slice(i, i + 3000)), recording.camera, name=f"chunk {i // 3000}")
        for i in range(0, len(ev), 3000)
    ]
    config = {**INDEPENDENT, "depth": {"name": "constant", "value": 3.0}}
    config["window"] = {"events": 3000}
    serial = list(
        segment_stream(chunks, settings_from(config), optimizers.create("ssa_ga"), seed=2)
    )
    return chunks, config, serial


@pytest.mark.parametrize("engine", ["processes", "ray"])
def test_a_stream_on_workers_gives_the_serial_labels_and_ids(stream, engine, request):
    if engine == "ray":
        request.getfixturevalue("ray_instance")
    chunks, config, serial = stream
    assert len(serial) == 3
    ids = np.concatenate([seg.labels for _, seg in serial])
    assert len(np.unique(ids[ids >= 0])) >= 2  # a real segmentation
    linked = [w.ids.tolist() for _, seg in serial for w in seg.windows]
    assert any(i != sorted(i) for i in linked)  # a chunk's clusters come out in another order
    settings = settings_from({**config, "window": {**config["window"], "parallel": engine}})
    pooled = list(segment_stream(chunks, settings, optimizers.create("ssa_ga"), seed=2))
    assert len(pooled) == len(serial)
    for (used_a, a), (used_b, b) in zip(serial, pooled, strict=True):
        assert len(used_a.depth_maps) == len(used_b.depth_maps) == 2
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_allclose(a.probabilities, b.probabilities)
        assert a.handover.boundary.next_id == b.handover.boundary.next_id
        for wa, wb in zip(a.windows, b.windows, strict=True):
            np.testing.assert_array_equal(wa.clustering.thetas, wb.clustering.thetas)
            np.testing.assert_array_equal(wa.ids, wb.ids)
