"""Typed settings (issue 26, item 2): defaults in code, one check per key, no Hydra needed."""

from __future__ import annotations

import dataclasses

import pytest

from spatialseg.settings import (
    ClusteringSettings,
    Settings,
    default_tree,
    settings_from,
    smoothing,
)


def test_the_defaults_need_no_config_file():
    settings = settings_from({})
    assert settings == Settings()
    assert settings.window.events == 15000 and settings.clustering.p_step_sigma == (1.5, 4.0)
    assert settings.init.auto == ("image_flow", "tiles", "previous", "planar")
    assert (
        settings.cluster_count == 2 and settings_from({"n_clusters": "auto"}).cluster_count is None
    )


def test_a_partial_mapping_overrides_only_its_keys():
    settings = settings_from({"clustering": {"refit": {"evals": 0}}, "model": {"name": "planar"}})
    assert settings.clustering.refit.evals == 0
    assert settings.clustering.refit.optimizer == "nlopt_bobyqa"
    assert settings.clustering.max_iterations == 10
    assert settings.model.voxel_scale == 1.0 and Settings().model.voxel_scale == 2.0


def test_app_sections_are_not_the_methods():
    settings = settings_from({"scene": {"name": "interior"}, "output": {}, "seed": 3})
    assert settings == Settings()


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ({"n_clusters": 2.5}, "n_clusters must be an integer or one of 'auto', got 2.5"),
        ({"n_clusters": True}, "n_clusters must be an integer or one of 'auto', got True"),
        ({"n_clusters": 0}, "n_clusters must be an integer >= 1"),
        ({"clustering": {"tol": "x"}}, "clustering.tol must be a number, got 'x'"),
        ({"clustering": {"tol": -1}}, "clustering.tol must be a number >= 0, got -1"),
        ({"clustering": {"label_tol": 1}}, "clustering.label_tol must be a number in [0, 1) or"),
        (
            {"clustering": {"fit_per_voxel": 0}},
            "clustering.fit_per_voxel must be a positive number or null, got 0",
        ),
        ({"clustering": {"fooo": 1}}, "clustering.fooo is not a setting; valid clustering: "),
        ({"nonsense": 1, "window": {"events": 0}}, "window.events must be an integer >= 1"),
        ({"window": {"parallel": "gpu"}}, "window.parallel must be one of 'none', 'processes'"),
        ({"window": 3}, "window must be a section of settings (a mapping), got 3"),
        ({"clustering": {"p_step_sigma": [1, 2, 3]}}, "clustering.p_step_sigma must be"),
        ({"clustering": {"p_step_stride": 3, "p_step_sigma": 0.5}}, "lower clustering.p_step_"),
        ({"clustering": {"refit": {"radius": 2}}}, "clustering.refit.radius must be a number in"),
        ({"clustering": {"refit": {"optimizer": "nope"}}}, "clustering.refit.optimizer"),
        ({"init": {"tiles": {"refit": "nope"}}}, "init.tiles.refit"),
        ({"init": {"auto": "tiles"}}, "init.auto must be a list of strings, got 'tiles'"),
        ({"objective": {"name": "nope"}}, "objective=nope is unknown; choose one of:"),
        ({"denoise": {"enabled": "no"}}, "denoise.enabled must be true or false, got 'no'"),
        ({"depth": {"name": 3}}, "depth.name must be a depth source's name, got 3"),
    ],
)
def test_a_bad_value_is_refused_in_one_line_naming_its_key(given, message):
    with pytest.raises(ValueError) as caught:
        settings_from(given)
    text = str(caught.value)
    assert message in text and "\n" not in text


def test_settings_are_frozen_and_checked_when_built_in_code():
    with pytest.raises(dataclasses.FrozenInstanceError):
        Settings().window.events = 5  # type: ignore[misc]
    with pytest.raises(ValueError, match=r"clustering\.max_iterations must be an integer >= 1"):
        ClusteringSettings(max_iterations=0)


def test_smoothing_is_one_number_or_an_image_depth_pair():
    assert smoothing(2, "k") == (2.0, 2.0, 2.0)
    assert smoothing((1.5, 1.0), "k") == (1.5, 1.5, 1.0)
    for bad in (-1, (1, 2, 3), True, ("a",)):
        with pytest.raises(ValueError, match="k must be a number >= 0 or a pair"):
            smoothing(bad, "k")


def test_the_default_tree_builds_the_defaults_back():
    tree = default_tree()
    assert tree["clustering"]["p_step_sigma"] == [1.5, 4.0]
    assert tree["depth"] == {"name": "recording"}
    assert settings_from(tree) == Settings()
