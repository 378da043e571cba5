"""The shipped scenes: each simulates a paper-like window with balanced objects."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from spatialseg.config import conf_dir
from spatialseg.simulate import simulate_scene

SCENES = ["interior", "exterior", "approach", "three", "night", "noon"]
WINDOW = 15000


def _load(name: str):
    """A shipped scene config as Hydra would hand it over (a DictConfig)."""
    return OmegaConf.load(conf_dir() / "scene" / f"{name}.yaml")


@pytest.fixture(scope="module")
def windows() -> dict:
    """Every shipped scene simulated once (seed 0, the paper's 15,000-event window)."""
    return {name: simulate_scene(_load(name), seed=0, max_events=WINDOW) for name in SCENES}


@pytest.mark.parametrize("name", SCENES)
def test_scene_fills_a_window_in_tens_of_milliseconds_with_every_object_well_represented(
    name, windows
):
    rec = windows[name]
    cfg = _load(name)
    assert rec.name == name == cfg.name
    assert len(rec.events) == WINDOW
    assert 0.02 <= rec.events.duration <= 0.3
    gt = rec.ground_truth
    assert sorted(gt.motions) == list(range(1, len(cfg.objects) + 1))
    shares = np.bincount(gt.labels[gt.labels >= 0], minlength=len(cfg.objects) + 1)[1:] / WINDOW
    assert shares.min() >= 0.2, dict(zip([o.name for o in cfg.objects], shares, strict=True))


def _image_corners(cam, body, t: float) -> np.ndarray:
    """Image positions (8 x 2) of a (static-camera) box's corners at time t."""
    centre = np.asarray(body.position) + np.asarray(body.velocity) * t
    size = np.append(body.size, 0.0)[:3]
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)])
    corners = centre + signs * size / 2
    return np.stack(
        [
            cam.cx + cam.fx * corners[:, 0] / corners[:, 2],
            cam.cy + cam.fy * corners[:, 1] / corners[:, 2],
        ],
        axis=1,
    )


@pytest.mark.parametrize("name", SCENES)
def test_objects_move_several_pixels_within_the_window(name, windows):
    rec, cfg = windows[name], _load(name)
    t0, t1 = (d.t for d in rec.depth_maps)
    for body in cfg.objects:
        moved = _image_corners(rec.camera, body, t1) - _image_corners(rec.camera, body, t0)
        assert np.hypot(*moved.T).max() >= 4.0, body.name


def test_night_is_noisier_and_noon_has_stronger_contrast_than_the_exterior(windows):
    def noise_share(name):
        return np.mean(windows[name].ground_truth.labels == -1)

    assert noise_share("night") > 5 * noise_share("exterior")
    assert windows["noon"].events.duration < windows["exterior"].events.duration
    assert windows["night"].events.duration > windows["exterior"].events.duration
