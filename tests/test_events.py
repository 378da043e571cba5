"""The event data model: coercion and validation with errors naming index and fix."""

from __future__ import annotations

import numpy as np
import pytest

from spatialseg.events import EventStream, normalise_polarity


def _stream(**overrides):
    arrays = {
        "x": [0, 1, 2],
        "y": [0, 1, 2],
        "t": [0.0, 0.1, 0.2],
        "p": [1, -1, 1],
        "width": 3,
        "height": 3,
    }
    arrays.update(overrides)
    return EventStream(**arrays, source="ev.txt")


def test_coerces_dtypes_and_length():
    ev = _stream()
    assert len(ev) == 3
    assert ev.x.dtype == np.int32 and ev.t.dtype == np.float64 and ev.p.dtype == np.int8
    assert ev.duration == pytest.approx(0.2)


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"t": [0.0, 0.2, 0.1]}, r"ev.txt: timestamps not sorted at event 2"),
        ({"t": [0.0, np.nan, 0.2]}, r"event 1 has a non-finite timestamp"),
        ({"x": [0, 3, 1]}, r"event 1 has x=3 outside the sensor"),
        ({"y": [0, -1, 1]}, r"event 1 has y=-1 outside the sensor"),
        ({"p": [1, 0, 1]}, r"event 1 has polarity 0"),
        ({"x": [0, 1]}, r"differ in length"),
        ({"x": [0.0, 1.5, 2.0]}, r"event 1 has non-integer x=1.5"),
        ({"t": [[0.0, 0.1, 0.2]]}, r"must be 1-D"),
        ({"width": 0}, r"must be positive"),
    ],
)
def test_invalid_streams_name_the_problem(overrides, match):
    with pytest.raises(ValueError, match=match):
        _stream(**overrides)


def test_empty_stream_is_valid():
    ev = _stream(x=[], y=[], t=[], p=[])
    assert len(ev) == 0 and ev.duration == 0.0


def test_select_and_between_keep_order():
    ev = _stream(t=[0.0, 0.1, 0.2])
    assert ev.select(np.array([True, False, True])).t.tolist() == [0.0, 0.2]
    assert ev.between(0.05, 0.2).t.tolist() == [0.1, 0.2]


@pytest.mark.parametrize(
    ("given", "expected"),
    [([0, 1, 1], [-1, 1, 1]), ([-1, 1], [-1, 1]), ([True, False], [1, -1])],
)
def test_normalise_polarity(given, expected):
    assert normalise_polarity(np.array(given)).tolist() == expected


def test_normalise_polarity_rejects_other_values():
    with pytest.raises(ValueError, match="polarity must be 0/1 or -1/\\+1"):
        normalise_polarity(np.array([0, 2]))
