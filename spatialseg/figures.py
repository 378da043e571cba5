"""The paper's Figures 6-7 as one PNG per scene, rebuilt from a finished run's outputs.

A run directory holds the labels and ``result.json`` (final thetas, reference time and the
per-iteration history) but not the warped volumes; those are recomputed from the window's
points (``points.prepare``, deterministic) and the final thetas, so the figure shows
exactly the run that MLflow recorded. Panels, as in the paper: (a) the window's first
keyframe and (b) its depth map (the paper's Fig. 6a/7a), (c) events by object, (d)-(e) the
volume warped by each cluster's motion summed over depth (that cluster's object sharp, the
others blurred), (f)-(g) each cluster's contrast per iteration, (h)-(i) each cluster's theta
per iteration.

Built with :class:`matplotlib.figure.Figure` (no pyplot), like :mod:`spatialseg.plots`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib as mpl
import numpy as np
from matplotlib.figure import Figure

from spatialseg.plots import object_colours, object_legend
from spatialseg.points import Prepared
from spatialseg.recording import DepthMap
from spatialseg.volume import VolumeObjective

__all__ = ["paper_figure", "save_figure", "warped_images"]

AXES = "xyz"
PANEL_WIDTH = 4.0  # inches per panel
PANEL_HEIGHT = 3.6
#: Depth colour map, near bright; unknown depth (NaN or <= 0) is left blank.
DEPTH_CMAP = mpl.colormaps["viridis_r"].with_extremes(bad=(1.0, 1.0, 1.0, 0.0))


def warped_images(prepared: Prepared, t_ref: float, thetas: np.ndarray) -> list[np.ndarray]:
    """Each theta (K x 3) applied to ALL usable events, the volume summed over depth (Y x X).

    All events, not only the cluster's: the paper's Fig. 6-7 b-c show the whole scene warped
    by one motion, so the object moving that way is sharp and the other one smeared.
    """
    volume = VolumeObjective(prepared.points, prepared.t - t_ref, prepared.grid, "variance")
    images = []
    for theta in np.atleast_2d(thetas):
        full = np.zeros(3)
        full[: theta.size] = theta
        images.append(volume.volume(full).sum(axis=2).T)
    return images


def _letters(start: int, count: int) -> list[str]:
    """Panel labels ``(a)``, ``(b)``, ... starting at letter number ``start``."""
    return [f"({chr(ord('a') + start + i)})" for i in range(count)]


def paper_figure(
    title: str,
    scene_image: np.ndarray,
    scene_caption: str,
    depth: DepthMap,
    clusters_rgb: np.ndarray,
    warped: Sequence[np.ndarray],
    history: Mapping[str, Any],
    units: str,
    ids: Sequence[int] | None = None,
) -> Figure:
    """The Figure 6/7 layout for K clusters: top row (a) the scene image (a keyframe, grey),
    (b) its depth map, (c) events by object (with a legend) and K warped images; bottom row
    K contrast curves and K theta curves (the paper's panels for K = 2).

    ``scene_caption`` titles panel (a) (e.g. ``keyframe at t = 0.0 ms``); ``depth`` is the
    window's depth map, drawn in metres with unknown pixels (NaN or <= 0) blank. ``history``
    is a window's ``result.json`` history: ``per_cluster`` (iterations x K) and ``thetas``
    (iterations x K x 3), iteration 1 first. ``ids``: each cluster's object id, the labels
    ``clusters_rgb`` is coloured by (None: 0..K-1).
    """
    per_cluster = np.asarray(history["per_cluster"], dtype=np.float64)
    thetas = np.asarray(history["thetas"], dtype=np.float64)
    k = len(warped)
    if per_cluster.ndim != 2 or per_cluster.shape[1] != k or thetas.shape[:2] != per_cluster.shape:
        raise ValueError(
            f"history holds {per_cluster.shape} contrasts and {thetas.shape} thetas "
            f"for {k} clusters; is result.json from the same run?"
        )
    iterations = np.arange(1, per_cluster.shape[0] + 1)
    ids = list(range(k)) if ids is None else [int(i) for i in ids]
    colours = object_colours(ids)
    columns = max(3 + k, 2 * k)
    fig = Figure(figsize=(PANEL_WIDTH * columns, 2 * PANEL_HEIGHT + 0.6), layout="constrained")
    fig.suptitle(title)
    top, bottom = fig.subfigures(2, 1)
    letters = _letters(0, 3 + 3 * k)

    image_axes = np.atleast_1d(top.subplots(1, 3 + k))
    scene_ax, depth_ax, cluster_ax = image_axes[:3]
    if scene_image.ndim == 2:
        scene_ax.imshow(scene_image, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    else:
        scene_ax.imshow(scene_image, interpolation="nearest")
    scene_ax.set_title(f"{letters[0]} {scene_caption}")
    metres = np.where(depth.depth > 0, depth.depth, np.nan)
    known = np.isfinite(metres)
    shown = depth_ax.imshow(np.ma.masked_invalid(metres), cmap=DEPTH_CMAP, interpolation="nearest")
    depth_ax.set_title(
        f"{letters[1]} depth at t = {1e3 * depth.t:.1f} ms\n"
        f"(blank: unknown, {100 * (1 - known.mean()):.0f}% of pixels)"
    )
    top.colorbar(shown, ax=depth_ax, label="depth (m)", shrink=0.8)
    cluster_ax.imshow(clusters_rgb, interpolation="nearest")
    cluster_ax.set_title(f"{letters[2]} events by object")
    object_legend(cluster_ax, ids, unassigned=True)
    for j, (ax, image) in enumerate(zip(image_axes[3:], warped, strict=True)):
        ax.imshow(image, cmap="gray_r", interpolation="nearest")
        speed = ", ".join(f"{v:+.3f}" for v in thetas[-1, j])
        ax.set_title(f"{letters[3 + j]} warped by object {ids[j]}\n[{speed}] {units}")
    for ax in image_axes:
        ax.set_xticks([])
        ax.set_yticks([])

    curve_axes = np.atleast_1d(bottom.subplots(1, 2 * k))
    for j in range(k):
        ax = curve_axes[j]
        ax.plot(iterations, per_cluster[:, j], "o-", color=colours[j])
        ax.set(xlabel="iteration", ylabel="contrast (variance of the VWE)")
        ax.set_title(f"{letters[3 + k + j]} contrast, object {ids[j]}")
    for j in range(k):
        ax = curve_axes[k + j]
        for a in range(thetas.shape[2]):
            ax.plot(iterations, thetas[:, j, a], "o-", label=f"theta_{AXES[a]}")
        ax.set(xlabel="iteration", ylabel=f"theta ({units})")
        ax.set_title(f"{letters[3 + 2 * k + j]} theta, object {ids[j]}")
        ax.legend(fontsize="small")
    return fig


def save_figure(fig: Figure, path: Path, dpi: int) -> Path:
    """Write ``fig`` as a PNG (creating the directory) and return the path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path
