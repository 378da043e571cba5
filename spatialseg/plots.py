"""Figures written as PNG files.

Figures are built with :class:`matplotlib.figure.Figure` and saved through its Agg canvas,
never through pyplot, so plotting works headless and leaves a user's pyplot backend alone.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib as mpl
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from spatialseg.events import EventStream
from spatialseg.io._atomic import atomic_file
from spatialseg.recording import Recording

if TYPE_CHECKING:
    from spatialseg.pipeline import SegmentationResult
    from spatialseg.window import WindowResult

__all__ = [
    "cluster_image",
    "event_image",
    "figure_count",
    "label_shares",
    "object_colours",
    "object_legend",
    "save_result_figures",
    "save_scene_preview",
    "shown_windows",
]

#: Object colours (tab10, by object id); unassigned events are drawn grey.
_UNASSIGNED = np.array([0.6, 0.6, 0.6])

#: A result figure's margins (inches: left for tick and axis labels, right, bottom for
#: tick and axis labels, top for a title) and the gap between panels (a share of a panel's
#: width); room for a legend right of the axes is added on the right where there is one.
_MARGINS = (0.75, 0.25, 0.6, 0.45)
_PANEL_GAP = 0.3
_LEGEND_WIDTH = 1.3

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


def object_colours(ids: Iterable[int]) -> np.ndarray:
    """RGB colours (n x 3) of object ids (tab10, cycled), the same in every figure."""
    cmap = mpl.colormaps["tab10"]
    return np.array([cmap(int(i) % 10)[:3] for i in ids]).reshape(-1, 3)


def object_legend(ax: Axes, ids: Iterable[int], *, unassigned: bool) -> None:
    """A legend beside an events-by-object image naming each colour's object id (and grey
    for unassigned events)."""
    ids = list(ids)
    handles = [
        Patch(color=colour, label=f"object {i}")
        for i, colour in zip(ids, object_colours(ids), strict=True)
    ]
    if unassigned:
        handles.append(Patch(color=_UNASSIGNED, label="unassigned"))
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small")


def cluster_image(events: EventStream, labels: np.ndarray, n_clusters: int) -> np.ndarray:
    """Events coloured by label (an object id, 0..n_clusters-1) on white (H x W x 3 uint8):
    each pixel takes the colour of its most frequent label; unassigned (-1) events are grey."""
    colours = np.vstack([_UNASSIGNED, object_colours(range(n_clusters))])
    index = events.y.astype(np.int64) * events.width + events.x
    counts = np.zeros((events.width * events.height, n_clusters + 1))
    np.add.at(counts, (index, labels + 1), 1.0)
    hit = counts.sum(axis=1) > 0
    rgb = np.ones((counts.shape[0], 3))
    rgb[hit] = colours[counts[hit].argmax(axis=1)]
    return np.round(rgb.reshape(events.height, events.width, 3) * 255).astype(np.uint8)


def _projected_volumes(window: WindowResult) -> list[np.ndarray]:
    """Each cluster's motion applied to ALL usable events, summed over depth (Y x X images)."""
    from spatialseg.volume import VolumeObjective

    prep = window.prepared
    volume = VolumeObjective(prep.points, prep.t - window.t_ref, prep.grid, "variance")
    images = []
    for theta in window.clustering.thetas:
        full = np.zeros(3)
        full[: theta.size] = theta
        images.append(volume.volume(full).sum(axis=2).T)
    return images


def _result_figure(width: float, height: float, *, legend: bool = False) -> Figure:
    """A result figure of ``width`` x ``height`` inches with fixed margins (:data:`_MARGINS`;
    ``legend``: with room for a legend right of the axes).

    Decision: a layout engine (constrained, tight) draws each figure twice to measure its
    text; a run draws four figures per window, and fixed margins suit their fixed texts."""
    left, right, bottom, top = _MARGINS
    right += _LEGEND_WIDTH if legend else 0.0
    fig = Figure(figsize=(width, height))
    fig.subplots_adjust(
        left=left / width,
        right=1 - right / width,
        bottom=bottom / height,
        top=1 - top / height,
        wspace=_PANEL_GAP,
    )
    return fig


def _save(fig: Figure, path: Path) -> Path:
    """Save a figure as PNG (atomically: a killed run leaves no half-written image)."""
    with atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    return path


#: The figures of each window (:func:`_window_figures`): warped volumes, contrast, theta.
WINDOW_FIGURES = 3

#: The most windows :func:`_save_windows` shows, evenly spaced over a longer recording.
MAX_WINDOW_PANELS = 24

#: Panels per row of :func:`_save_windows`, and each panel's width (inches).
_PANELS_PER_ROW = 4
_PANEL_WIDTH = 3.6
#: Room above each panel of :func:`_save_windows` for its title (inches).
_WINDOW_TITLE = 0.3


def figure_count(windows: int, *, every_window: bool = False) -> int:
    """How many figures :func:`save_result_figures` draws for ``windows`` windows."""
    if windows == 1:
        return 1 + WINDOW_FIGURES
    return 3 + (windows * (WINDOW_FIGURES + 1) if every_window else 0)


def save_result_figures(
    out_dir: Path, recording: Recording, seg: SegmentationResult, *, every_window: bool = False
) -> list[Path]:
    """Write the run's figures, one colour per object id throughout: the events by object.
    One window: its volume warped by each cluster's motion (one object sharp, the others
    blurred) and its contrast and theta curves (the paper's Figures 6-7). Several windows:
    each window's events by object on one page and each object's velocity over the windows;
    ``every_window`` adds each window's own four figures (``NAME_wN.png``).

    Decision: per-window figures grow with the recording (four per window, about 0.1 s
    each), so a long recording gets two summary figures and the rest on request."""
    k, windows = seg.n_objects, seg.windows
    if len(windows) == 1:
        paths = [_save_clusters(out_dir / "clusters.png", recording, seg.labels, k, recording.name)]
        return paths + _window_figures(out_dir, windows[0], "")
    title = f"{recording.name}, all {len(windows)} windows"
    paths = [
        _save_clusters(out_dir / "clusters.png", recording, seg.labels, k, title),
        _save_windows(out_dir / "windows.png", recording, seg),
        _save_objects(out_dir / "objects.png", recording, seg),
    ]
    for w, window in enumerate(windows if every_window else []):
        part = recording.select(seg.indices[w])
        labels = seg.labels[seg.indices[w]]
        name = f"{recording.name}, window {w}"
        paths.append(_save_clusters(out_dir / f"clusters_w{w}.png", part, labels, k, name))
        paths += _window_figures(out_dir, window, f"_w{w}")
    return paths


def shown_windows(n_windows: int) -> np.ndarray:
    """The windows :func:`_save_windows` draws: all, or :data:`MAX_WINDOW_PANELS` evenly
    spaced from the first to the last."""
    count = min(n_windows, MAX_WINDOW_PANELS)
    return np.unique(np.round(np.linspace(0, n_windows - 1, count)).astype(int))


def _window_span(recording: Recording, indices: np.ndarray) -> tuple[float, float]:
    """The first and last event time (s) of a window's events (0, 0 when it has none)."""
    t = recording.events.t[indices]
    return (float(t.min()), float(t.max())) if len(t) else (0.0, 0.0)


def _save_windows(path: Path, recording: Recording, seg: SegmentationResult) -> Path:
    """Each window's events coloured by object id, a panel per window (at most
    :data:`MAX_WINDOW_PANELS`), with one legend: where each object is, window by window."""
    shown = shown_windows(len(seg.windows))
    cols = min(len(shown), _PANELS_PER_ROW)
    rows = -(-len(shown) // cols)
    panel = _PANEL_WIDTH * recording.camera.height / recording.camera.width
    width = cols * _PANEL_WIDTH + 0.4 + _LEGEND_WIDTH
    height = rows * (panel + _WINDOW_TITLE) + _MARGINS[3]
    fig = Figure(figsize=(width, height))
    fig.subplots_adjust(
        left=0.2 / width,
        right=1 - (0.2 + _LEGEND_WIDTH) / width,
        bottom=0.1 / height,
        top=1 - (_MARGINS[3] + _WINDOW_TITLE) / height,
        wspace=0.05,
        hspace=_WINDOW_TITLE / panel,
    )
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    for ax, w in zip(axes, shown, strict=False):
        part = recording.select(seg.indices[w])
        ax.imshow(cluster_image(part.events, seg.labels[seg.indices[w]], seg.n_objects))
        start, end = _window_span(recording, seg.indices[w])
        # a fixed y skips matplotlib's title placement, which measures every axis's ticks
        ax.set_title(f"window {w}: {start:.2f}-{end:.2f} s", fontsize="small", y=1.0)
    for ax in axes:
        ax.set_axis_off()
    labels = seg.labels
    object_legend(
        axes[cols - 1], np.unique(labels[labels >= 0]), unassigned=bool((labels < 0).any())
    )
    some = "" if len(shown) == len(seg.windows) else f" ({len(shown)} of {len(seg.windows)})"
    fig.suptitle(f"{recording.name}: events by object, window by window{some}")
    return _save(fig, path)


def _save_objects(path: Path, recording: Recording, seg: SegmentationResult) -> Path:
    """Each object's velocity component by component over the windows (a point per window
    it is found in, at the window's mid-time): one identity per object across windows."""
    units = seg.windows[0].prepared.units
    components = len(seg.windows[0].clustering.thetas[0])
    fig = _result_figure(4 * components, 3.6, legend=True)
    axes = np.atleast_1d(fig.subplots(1, components))
    tracks: dict[int, list[tuple[float, np.ndarray]]] = {}
    for w, window in enumerate(seg.windows):
        mid = float(np.mean(_window_span(recording, seg.indices[w])))
        for j, theta in enumerate(window.clustering.thetas):
            tracks.setdefault(_object_id(window, j), []).append((mid, np.asarray(theta)))
    ids = sorted(tracks)
    for obj, colour in zip(ids, object_colours(ids), strict=True):
        times = [t for t, _ in tracks[obj]]
        values = np.array([theta for _, theta in tracks[obj]])
        for a, ax in enumerate(axes):
            ax.plot(times, values[:, a], "o-", color=colour, label=f"object {obj}")
    for a, ax in enumerate(axes):
        ax.set(xlabel="time (s)", ylabel=f"v{'xyz'[a]} ({units})")
    axes[-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small")
    fig.suptitle(f"{recording.name}: velocity of each object over the windows")
    return _save(fig, path)


def _save_clusters(
    path: Path, recording: Recording, labels: np.ndarray, k: int, title: str
) -> Path:
    """The events coloured by object id (grey: unassigned) with a legend, as a PNG."""
    fig = _result_figure(7.2 + _LEGEND_WIDTH, 4.8, legend=True)
    ax = fig.subplots()
    ax.imshow(cluster_image(recording.events, labels, k), interpolation="nearest")
    ax.set_title(f"{title}: events by object")
    object_legend(ax, np.unique(labels[labels >= 0]), unassigned=bool(np.any(labels < 0)))
    return _save(fig, path)


def _object_id(window: WindowResult, cluster: int) -> int:
    """The object id of a window's cluster (the cluster index before linking)."""
    return cluster if window.ids is None else int(window.ids[cluster])


def _window_figures(out_dir: Path, window: WindowResult, suffix: str) -> list[Path]:
    """The warped-volume panels and the contrast and theta curves of one window."""
    c, units = window.clustering, window.prepared.units
    images = _projected_volumes(window)
    fig = _result_figure(5 * len(images), 4.4)
    for j, (ax, image) in enumerate(
        zip(np.atleast_1d(fig.subplots(1, len(images))), images, strict=True)
    ):
        ax.imshow(image, cmap="gray_r", interpolation="nearest", origin="upper")
        theta = ", ".join(f"{v:+.3f}" for v in c.thetas[j])
        ax.set_title(f"warped by object {_object_id(window, j)}: [{theta}] {units}")
    paths = [_save(fig, out_dir / f"warped_volumes{suffix}.png")]

    iterations = [r.iteration for r in c.history]
    fig = _result_figure(6, 4)
    ax = fig.subplots()
    per_cluster = np.array([r.per_cluster for r in c.history])
    ids = [_object_id(window, j) for j in range(per_cluster.shape[1])]
    colours = object_colours(ids)
    for j, obj in enumerate(ids):
        ax.plot(iterations, per_cluster[:, j], "o-", color=colours[j], label=f"object {obj}")
    ax.set(xlabel="iteration", ylabel="contrast (variance of the VWE)", title="contrast per object")
    ax.legend()
    paths.append(_save(fig, out_dir / f"variance{suffix}.png"))

    thetas = np.array([r.thetas for r in c.history])
    fig = _result_figure(4 * thetas.shape[2], 3.6)
    for a, ax in enumerate(np.atleast_1d(fig.subplots(1, thetas.shape[2]))):
        for j, obj in enumerate(ids):
            ax.plot(iterations, thetas[:, j, a], "o-", color=colours[j], label=f"object {obj}")
        ax.set(xlabel="iteration", ylabel=f"theta_{'xyz'[a]} ({units})")
    ax.legend()
    paths.append(_save(fig, out_dir / f"theta{suffix}.png"))
    return paths
