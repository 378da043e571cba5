"""The shared integer check every count in a config goes through."""

from __future__ import annotations

import numpy as np
import pytest

from spatialseg.checks import integer_setting, is_integer, optional_positive, unknown_key
from spatialseg.recording import check_window_context


@pytest.mark.parametrize(
    ("value", "minimum", "expected"),
    [
        (3, 1, True),
        (np.int64(3), 1, True),
        (0, 0, True),
        (0, 1, False),
        (-1, 0, False),
        (True, 0, False),
        (np.bool_(True), 0, False),
        (3.0, 1, False),
        ("3", 1, False),
        (None, 0, False),
    ],
)
def test_is_integer_takes_python_and_numpy_integers_not_bools_or_floats(value, minimum, expected):
    assert is_integer(value, minimum) is expected


def test_a_numpy_integer_is_a_valid_count_wherever_a_python_one_is():
    """Keys checked through is_integer accept both kinds alike (here window.context)."""
    check_window_context(np.int32(1))
    with pytest.raises(ValueError, match=r"window\.context must be an integer >= 0, got True"):
        check_window_context(True)


def test_optional_positive_is_a_float_or_none_and_names_the_key():
    assert optional_positive(None, "k") is None
    assert optional_positive(2, "k") == 2.0 and optional_positive(np.float32(0.5), "k") == 0.5
    for bad in (0, -1.0, float("nan"), float("inf"), True, "5"):
        with pytest.raises(ValueError, match=r"^a\.b must be a positive number or null, got"):
            optional_positive(bad, "a.b")


def test_integer_setting_names_the_key_its_range_and_the_hint():
    assert integer_setting(3, "window.context", 0) == 3
    assert integer_setting(None, "clustering.step_events", 1, optional=True) is None
    for value in (2.5, None, True, -1):
        with pytest.raises(ValueError) as info:
            integer_setting(value, "window.context", 0, hint="0: off")
        assert str(info.value) == (
            f"window.context must be an integer >= 0 (0: off), got {value!r}"
        )
    with pytest.raises(ValueError, match=r"must be an integer >= 1 or null, got 0"):
        integer_setting(0, "clustering.step_events", 1, optional=True)


@pytest.mark.parametrize(
    ("key", "known", "expected"),
    [
        ("scnee", ["model", "scene"], "unknown config key 'scnee'; did you mean 'scene'?"),
        (
            "clustering.max_iteration",
            ["tol", "max_iterations"],
            "unknown config key 'clustering.max_iteration'; did you mean "
            "'clustering.max_iterations'?",
        ),
        (
            "output.figures",
            ["plots", "h5", "progress"],
            "unknown config key 'output.figures'; 'output' has: h5, plots, progress",
        ),
        ("zzz", ["model", "scene"], "unknown config key 'zzz'; the top level has: model, scene"),
    ],
)
def test_unknown_key_names_the_closest_key_or_the_section_keys(key, known, expected):
    assert unknown_key(key, known) == expected
