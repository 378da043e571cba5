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


def test_the_approaching_car_gets_an_id_of_its_own(road):
    """It enters in window 1 and drives the other way: one id, moving left, in windows 3
    and 4 beside the others. (The two cars driving the same way share one id since the
    number of motions is chosen from fits of 1, 2, ... motions, session 36; until then they
    had one each: docs/results.md, "`n_clusters=auto` by a sweep".)"""
    cars = _cars_per_window(road)
    leftward = [i for i in range(road.n_objects) if road.velocities[i, 0] < 0]
    assert len(leftward) == 1
    assert all(leftward[0] in cars[w] and len(cars[w]) >= 2 for w in (3, 4)), cars
