"""The real road recording (DAVIS346, shipped in the package): three cars, two driving the
same way at different distances and one approaching, with ``n_clusters=auto`` and the
ground-plane depth of ``+scene=road_cars``."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

import spatialseg
from spatialseg.config import conf_dir
from spatialseg.scenes import load_scene

#: Events an object needs in a window to count as one of the cars there (the smallest car
#: holds about 2,000 of a window's 15,000 events; fragments hold a few hundred).
CAR_EVENTS = 1000


@pytest.fixture(scope="module")
def road() -> spatialseg.Segmentation:
    scene = OmegaConf.to_container(OmegaConf.load(conf_dir() / "scene" / "road_cars.yaml"))
    recording = load_scene(scene, seed=0, window_events=15_000)
    return spatialseg.segment(recording, "auto", depth="ground_plane")


def _cars_per_window(road: spatialseg.Segmentation) -> list[dict[int, int]]:
    """Each window's objects holding at least :data:`CAR_EVENTS` of its events: id -> count."""
    found = []
    for index in road.window_indices:
        ids, counts = np.unique(road.labels[index], return_counts=True)
        found.append(
            {int(i): int(c) for i, c in zip(ids, counts, strict=True) if i >= 0 and c >= CAR_EVENTS}
        )
    return found


def test_the_two_cars_driving_the_same_way_keep_two_ids_in_every_window(road):
    """Before the search box was measured per window (it spanned the context windows), both
    cars' velocities were held at the box's edge and they shared one id from window 2."""
    cars = _cars_per_window(road)
    rightward = [i for i in range(road.n_objects) if road.velocities[i, 0] > 0]
    steady = [i for i in rightward if all(i in window for window in cars)]
    assert len(steady) == 2, cars


def test_the_approaching_car_gets_a_third_id_of_its_own(road):
    """It enters in window 1 and drives the other way: one id, moving left, in windows 3
    and 4 beside the two others."""
    cars = _cars_per_window(road)
    leftward = [i for i in range(road.n_objects) if road.velocities[i, 0] < 0]
    assert len(leftward) == 1
    assert all(leftward[0] in cars[w] and len(cars[w]) == 3 for w in (3, 4)), cars
