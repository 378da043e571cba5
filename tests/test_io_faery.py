"""The Prophesee reader and writer (``spatialseg.io._prophesee``) against an independent
implementation: faery (Neuromorphic Systems group, Rust core). EVT 2.0 and EVT 3.0 ``.raw``
and ``.dat`` files written by faery decode in spatialseg into the events faery was given, and
files spatialseg writes decode in faery into the events spatialseg was given.

faery's times are integer microseconds, spatialseg's float64 seconds: they are compared in
whole microseconds. faery writes with ``zero_t0=False``: its default shifts the times to
start at 0 and records the shift in a ``% t0`` header line, faery's own extension that
spatialseg does not read. The expected events are the ones handed to the writer, not faery's
re-reading of its own file: faery 0.7.1 reads its own EVT 3.0 files wrongly after a gap
that crosses the 24-bit time base's wrap-around (its encoder steps TIME_HIGH by 0x400, its
decoder counts a wrap only on a drop from 0xFFF to 0x000).
"""

from __future__ import annotations

from pathlib import Path

import faery
import numpy as np
import pytest

from spatialseg.events import EventStream
from spatialseg.io import read_any, write_prophesee
from spatialseg.io._prophesee import iter_prophesee_arrays, read_prophesee_header

W, H = 640, 480  # a Prophesee VGA sensor (Gen3/Gen4)
BURST = 200  # events per burst
#: Gaps before each burst after the first, in us: a time-low step in each encoding (EVT 2.0
#: keeps 6 bits in each CD word, EVT 3.0 12 bits in TIME_LOW); seconds, below, near and past
#: EVT 3.0's 24-bit (16.8 s) time base, so it wraps after gaps of every size; half-hours,
#: past ``.dat``'s 32-bit counter (71.6 min) and, in all, EVT 2.0's 34-bit time base (4.8 h).
#: ``.dat`` stores no time-high words: a gap must stay under half its counter (35.8 min).
GAPS_US = [1, 64, 4096, 12_289, 250_000, 5_000_000, 9_000_000, 20_000_000, 40_000_000]
GAPS_US += [1_800_000_000] * 10
#: (faery's version, spatialseg's encoding, file name); the suffix picks .dat for both.
FORMATS = [("evt2", "evt2", "e.raw"), ("evt3", "evt3", "e.raw"), ("dat2", "evt3", "e.dat")]


def _faery_events(gaps_us: list[int], burst: int, seed: int) -> np.ndarray:
    """Bursts of events with repeated times and 0-3 us steps, from t = 0, separated by gaps.

    The first event at t = 0 is faery's EVT 3.0 special case: a TIME_HIGH and no TIME_LOW.
    """
    rng = np.random.default_rng(seed)
    steps = rng.choice([0, 0, 1, 2, 3], burst * (len(gaps_us) + 1))
    steps[0] = 0
    steps[burst::burst] += gaps_us
    events = np.zeros(steps.size, faery.EVENTS_DTYPE)
    events["t"] = np.cumsum(steps)
    events["x"] = rng.integers(0, W, steps.size)
    events["y"] = rng.integers(0, H, steps.size)
    events["on"] = rng.random(steps.size) < 0.5
    events["x"][:2], events["y"][:2] = [0, W - 1], [0, H - 1]  # both corners of the sensor
    return events


EVENTS = _faery_events(GAPS_US, BURST, seed=28)


def _to_stream(events: np.ndarray) -> EventStream:
    """faery's events as spatialseg's (seconds, polarity +1/-1)."""
    x, y = events["x"].astype(np.int64), events["y"].astype(np.int64)
    return EventStream(x, y, events["t"] / 1e6, np.where(events["on"], 1, -1), W, H)


def _assert_same(decoded: EventStream, expected: np.ndarray) -> None:
    """Same sensor size, count, and per event the same time (to the us), x, y and polarity."""
    assert (decoded.width, decoded.height) == (W, H)
    assert len(decoded) == len(expected)
    t_us = np.round(decoded.t * 1e6).astype(np.int64)
    np.testing.assert_array_equal(t_us, expected["t"].astype(np.int64), err_msg="t [us]")
    np.testing.assert_array_equal(decoded.x, expected["x"], err_msg="x")
    np.testing.assert_array_equal(decoded.y, expected["y"], err_msg="y")
    np.testing.assert_array_equal(decoded.p, np.where(expected["on"], 1, -1), err_msg="p")


def _faery_read(path: Path) -> tuple[tuple[int, int], np.ndarray]:
    decoder = faery.events_stream_from_file(path)
    return decoder.dimensions(), decoder.to_array()


def test_the_stream_needs_the_time_high_words_and_wraps() -> None:
    t = EVENTS["t"].astype(np.int64)
    assert len(EVENTS) == 4000 and t[0] == 0 and (np.diff(t) >= 0).all()
    assert (np.diff(t) == 0).sum() > 500  # repeated times
    assert t[-1] > 1 << 34  # past EVT 2.0's time base, so past .dat's and EVT 3.0's too
    assert np.diff(t).max() > 1 << 24  # a gap longer than EVT 3.0's whole time base
    assert set(np.unique(EVENTS["on"]).tolist()) == {False, True}


@pytest.mark.parametrize(("version", "encoding", "name"), FORMATS)
def test_files_faery_writes_read_as_its_events(
    tmp_path: Path, version: str, encoding: str, name: str
) -> None:
    path = tmp_path / name
    faery.events_stream_from_array(EVENTS, (W, H)).to_file(path, version=version, zero_t0=False)
    _assert_same(read_any(path, fov_deg=70.0).events, EVENTS)
    # Blocks of 97 words: the decoder's state (time base, wraps, row) carried across blocks.
    blocks = list(iter_prophesee_arrays(path, read_prophesee_header(path), block_words=97))
    assert len(blocks) > 40
    t_us, x, y, p = (np.concatenate(column) for column in zip(*blocks, strict=True))
    _assert_same(EventStream(x, y, t_us / 1e6, p, W, H), EVENTS)


@pytest.mark.parametrize(("version", "encoding", "name"), FORMATS)
def test_files_spatialseg_writes_read_in_faery_as_its_events(
    tmp_path: Path, version: str, encoding: str, name: str
) -> None:
    path = tmp_path / name
    write_prophesee(_to_stream(EVENTS), path, encoding=encoding)
    size, decoded = _faery_read(path)
    assert size == (W, H)
    _assert_same(_to_stream(decoded), EVENTS)


@pytest.mark.parametrize(("version", "encoding", "name"), FORMATS[:2])
def test_raw_files_keep_gaps_of_hours_both_ways(
    tmp_path: Path, version: str, encoding: str, name: str
) -> None:
    """Gaps of 3, 6 and 10 h, past EVT 2.0's 34-bit time base (4.8 h); .dat cannot hold them."""
    hour = 3_600_000_000
    events = _faery_events([3 * hour, 6 * hour, 10 * hour], burst=100, seed=29)
    faery.events_stream_from_array(events, (W, H)).to_file(
        tmp_path / "faery.raw", version=version, zero_t0=False
    )
    _assert_same(read_any(tmp_path / "faery.raw", fov_deg=70.0).events, events)
    write_prophesee(_to_stream(events), tmp_path / name, encoding=encoding)
    size, decoded = _faery_read(tmp_path / name)
    assert size == (W, H)
    _assert_same(_to_stream(decoded), events)
    _assert_same(read_any(tmp_path / name, fov_deg=70.0).events, events)


def test_a_new_time_high_restarts_the_time_low_as_in_faery(tmp_path: Path) -> None:
    """EVT 3.0 words by hand: an event may follow a new TIME_HIGH without a TIME_LOW."""
    words = [
        0x8000,  # TIME_HIGH 0: t = 0 (no TIME_LOW yet)
        0x0007,  # ADDR_Y 7
        0x2805,  # ADDR_X 5, ON: t = 0
        0x6123,  # TIME_LOW 0x123: t = 291
        0x2006,  # ADDR_X 6, OFF: t = 291
        0x8001,  # TIME_HIGH 1: t = 4096, not 4096 + 291
        0x2807,  # ADDR_X 7, ON: t = 4096
        0x8001,  # the same TIME_HIGH again: the time low stays
        0x6002,  # TIME_LOW 2: t = 4098
        0x8001,
        0x2008,  # ADDR_X 8, OFF: t = 4098
    ]
    path = tmp_path / "w.raw"
    header = f"% evt 3.0\n% format EVT3;width={W};height={H}\n% geometry {W}x{H}\n% end\n"
    path.write_bytes(header.encode() + np.array(words, "<u2").tobytes())
    size, expected = _faery_read(path)
    assert size == (W, H)
    np.testing.assert_array_equal(expected["t"], [0, 291, 4096, 4098])  # faery's reading
    _assert_same(read_any(path, fov_deg=70.0).events, expected)
    for words_per_block in (1, 2, 3):  # whether a TIME_HIGH is new is carried across blocks
        blocks = iter_prophesee_arrays(path, read_prophesee_header(path), words_per_block)
        t_us, x, y, p = (np.concatenate(column) for column in zip(*blocks, strict=True))
        _assert_same(EventStream(x, y, t_us / 1e6, p, W, H), expected)
