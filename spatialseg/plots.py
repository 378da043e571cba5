"""Figures written as PNG files.

Figures are built with :class:`matplotlib.figure.Figure` and saved through its Agg canvas,
never through pyplot, so plotting works headless and leaves a user's pyplot backend alone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from spatialseg.events import EventStream
from spatialseg.recording import Recording

__all__ = ["event_image", "label_shares", "save_scene_preview"]

#: Red for positive events, blue for negative ones; a pixel with both mixes towards purple.
_POSITIVE_INK = np.array([0.0, 1.0, 1.0])
_NEGATIVE_INK = np.array([1.0, 1.0, 0.0])


def event_image(events: EventStream, *, saturation: float = 0.99) -> np.ndarray:
    """Polarity-coloured event counts on white (H x W x 3 uint8): red positive, blue negative.

    Counts are scaled so that the ``saturation`` quantile of the non-empty pixels' total
    counts is full colour; busier pixels saturate.
    """
    if not 0 < saturation <= 1:
        raise ValueError(f"saturation must be in (0, 1], got {saturation}")
    n_pixels = events.width * events.height
    index = events.y.astype(np.int64) * events.width + events.x
    positive = np.bincount(index[events.p > 0], minlength=n_pixels).astype(np.float64)
    negative = np.bincount(index[events.p < 0], minlength=n_pixels).astype(np.float64)
    total = positive + negative
    scale = max(float(np.quantile(total[total > 0], saturation)), 1.0) if total.any() else 1.0
    ink = (
        np.clip(positive / scale, 0, 1)[:, None] * _POSITIVE_INK
        + np.clip(negative / scale, 0, 1)[:, None] * _NEGATIVE_INK
    )
    rgb = np.clip(1.0 - ink, 0.0, 1.0).reshape(events.height, events.width, 3)
    return np.round(rgb * 255).astype(np.uint8)


def label_shares(recording: Recording) -> dict[str, float]:
    """Each ground-truth object's share of the events by name ('noise' for label -1)."""
    gt, n = recording.ground_truth, len(recording.events)
    if gt is None or not n:
        return {}
    ids, counts = np.unique(gt.labels, return_counts=True)
    return {
        ("noise" if i < 0 else gt.names.get(i, str(i))): c / n
        for i, c in zip(ids.tolist(), counts.tolist(), strict=True)
    }


def save_scene_preview(recording: Recording, path: str | Path) -> Path:
    """Write a PNG with the event image beside the first depth map (with a colour bar)."""
    if not recording.depth_maps:
        raise ValueError(f"{recording.name}: no depth map to preview")
    events, depth = recording.events, recording.depth_maps[0]
    fig = Figure(figsize=(11, 4.4), layout="constrained")
    left, right = fig.subplots(1, 2)
    left.imshow(event_image(events), interpolation="nearest")
    left.set_title(f"{len(events)} events over {1e3 * events.duration:.1f} ms")
    left.set_xlabel("red: positive, blue: negative")
    shown = right.imshow(depth.depth, cmap="viridis_r", interpolation="nearest")
    right.set_title(f"depth at t = {1e3 * depth.t:.1f} ms")
    fig.colorbar(shown, ax=right, label="depth (m)")
    shares = ", ".join(f"{k} {100 * v:.0f}%" for k, v in label_shares(recording).items())
    fig.suptitle(f"{recording.name}: {shares}" if shares else recording.name)
    out = Path(path)
    fig.savefig(out, dpi=100)
    return out
