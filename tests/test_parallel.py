"""Windows segmented in parallel (spatialseg.executors): a local process pool and a local Ray
instance give the serial run's labels, ids and velocities; bad settings are refused."""

from __future__ import annotations

import numpy as np
import pytest

import spatialseg
from spatialseg.executors import ENGINES, check_parallel, map_in_order

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
