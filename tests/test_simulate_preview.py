"""Scene pictures: the polarity-coloured event image and the preview PNG."""

from __future__ import annotations

import matplotlib.image
import numpy as np
import pytest
from omegaconf import OmegaConf

from spatialseg.config import conf_dir
from spatialseg.events import EventStream
from spatialseg.plots import event_image, save_scene_preview
from spatialseg.simulate import simulate_scene


def test_event_image_colours_polarities_on_white():
    events = EventStream([0, 1], [0, 0], [0.0, 0.1], [1, -1], 3, 1)
    image = event_image(events)
    assert image.shape == (1, 3, 3) and image.dtype == np.uint8
    assert image[0, 0].tolist() == [255, 0, 0]
    assert image[0, 1].tolist() == [0, 0, 255]
    assert image[0, 2].tolist() == [255, 255, 255]


def test_event_image_rejects_bad_saturation():
    events = EventStream([0], [0], [0.0], [1], 1, 1)
    with pytest.raises(ValueError, match="saturation must be in"):
        event_image(events, saturation=0.0)


def test_scene_preview_is_a_png_with_events_and_depth(tmp_path):
    cfg = OmegaConf.load(conf_dir() / "scene" / "exterior.yaml")
    rec = simulate_scene(cfg, seed=0, max_events=1000)
    path = save_scene_preview(rec, tmp_path / "preview.png")
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[1] > image.shape[0] > 200
