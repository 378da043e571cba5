"""The MRF smoothness term: an isolated mislabelled event follows its neighbourhood."""

from __future__ import annotations

import numpy as np
import pytest

from spatialseg.coherence import neighbour_graph, smooth_memberships


def _two_blobs() -> tuple[np.ndarray, np.ndarray]:
    """Two 10 x 10 pixel blobs 30 px apart; memberships 0.8 for each blob's own cluster."""
    grid = np.stack(np.meshgrid(np.arange(10), np.arange(10)), axis=-1).reshape(-1, 2)
    xy = np.vstack([grid, grid + np.array([30, 0])]).astype(float)
    p = np.repeat([[0.8, 0.2], [0.2, 0.8]], 100, axis=0)
    return xy, p


def test_an_isolated_mislabelled_event_takes_its_neighbours_label():
    xy, p = _two_blobs()
    p[55] = [0.3, 0.7]  # inside blob 0, but the P-step leans to cluster 1
    smoothed = smooth_memberships(p, neighbour_graph(xy))
    assert smoothed[55].argmax() == 0
    assert np.all(smoothed.argmax(axis=1) == np.repeat([0, 1], 100))


def test_strong_evidence_and_no_smoothness_keep_the_p_step_s_label():
    xy, p = _two_blobs()
    p[55] = [0.02, 0.98]
    assert smooth_memberships(p, neighbour_graph(xy))[55].argmax() == 1
    p[55] = [0.3, 0.7]
    np.testing.assert_allclose(smooth_memberships(p, neighbour_graph(xy), beta=0.0), p)


def test_events_without_evidence_follow_their_neighbours():
    xy, p = _two_blobs()
    p[120] = 0.0
    assert smooth_memberships(p, neighbour_graph(xy))[120].argmax() == 1
    with pytest.raises(ValueError, match="beta must be a finite number >= 0"):
        smooth_memberships(p, neighbour_graph(xy), beta=-1.0)
    assert neighbour_graph(np.zeros((1, 2))).shape == (1, 1)
