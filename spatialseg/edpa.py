"""EDPA: give every event a depth and lift it from pixels (x, y, t) to metres (X, Y, Z, t).

Section 1 of METHOD.md. The depth of an event is the linear interpolation in time of the
two depth maps bracketing it, read at the event's pixel (the printed Eq. 1 of the paper
drops the ``Z1`` term and is not implemented). Pixels are back-projected with the
full pinhole model. Depths that are non-finite or <= 0 are unknown.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spatialseg.events import EventStream
from spatialseg.recording import Camera, DepthMap, Recording

__all__ = [
    "UNKNOWN_DEPTH_POLICIES",
    "Lifted",
    "back_project",
    "event_depth",
    "fill_depth",
    "lift",
    "voxel_size",
]

#: What to do with an event whose depth is unknown in both maps (see :func:`lift`).
UNKNOWN_DEPTH_POLICIES = ("drop", "fill")


@dataclass(frozen=True, eq=False)
class Lifted:
    """A window's events in metres: ``points`` and ``t`` of the ``valid`` events only.

    ``valid`` (N,) marks the window's events that have a depth; ``depth`` (N,) is each
    event's depth in metres, NaN where unknown. ``points`` (M, 3) and ``t`` (M,) hold the
    M = ``valid.sum()`` valid events in their original (time) order. ``on_edge`` (N,) marks
    events at an occlusion edge (:func:`occlusion_edges`), whose depth is a guess.
    """

    points: np.ndarray
    t: np.ndarray
    valid: np.ndarray
    depth: np.ndarray
    on_edge: np.ndarray


def _known(z: np.ndarray) -> np.ndarray:
    """True where a depth value is usable (finite and positive)."""
    return np.isfinite(z) & (z > 0)


def _time_fraction(t: np.ndarray, t1: float, t2: float) -> np.ndarray:
    """``(t - T1) / (T2 - T1)`` clamped to [0, 1]; 0 everywhere when ``T2 == T1``.

    Decision: events before ``T1`` or after ``T2`` take the depth of the nearer map
    (clamping) rather than an extrapolation, which could run negative or explode.
    """
    if t2 < t1:
        raise ValueError(f"depth maps out of order: T1={t1} > T2={t2}; pass the earlier map first")
    if t2 == t1:
        return np.zeros_like(t, dtype=np.float64)
    return np.clip((np.asarray(t, dtype=np.float64) - t1) / (t2 - t1), 0.0, 1.0)


def occlusion_edges(z1: np.ndarray, z2: np.ndarray, edge_ratio: float | None) -> np.ndarray:
    """Where two known depths of a pixel differ by more than ``edge_ratio`` times the nearer
    one: an occlusion edge passed the pixel between the maps (None: nowhere)."""
    z1 = np.asarray(z1, dtype=np.float64)
    z2 = np.asarray(z2, dtype=np.float64)
    if edge_ratio is None:
        return np.zeros(z1.shape, dtype=bool)
    both = _known(z1) & _known(z2)
    near = np.where(both, np.minimum(z1, z2), 1.0)
    return both & (np.abs(z2 - z1) > edge_ratio * near)


def _interpolate(
    z1: np.ndarray, z2: np.ndarray, s: np.ndarray, edge_ratio: float | None = None
) -> np.ndarray:
    """``Z1 + s (Z2 - Z1)`` where both are known, the known one where one is, else NaN.

    Decision (``edge_ratio``): where the two maps disagree by more than ``edge_ratio`` times
    the nearer depth, the pixel saw an occlusion edge pass (object, then background or the
    reverse). The event belongs to the moving edge, i.e. to the occluder, so it takes the
    nearer depth; interpolating would give a depth between object and background that
    drifts linearly in time and mimics a spurious motion along Z. ``None`` interpolates
    everywhere (the paper's reading).
    """
    z1 = np.asarray(z1, dtype=np.float64)
    z2 = np.asarray(z2, dtype=np.float64)
    k1, k2 = _known(z1), _known(z2)
    z = np.full(z1.shape, np.nan)
    both = k1 & k2
    z[both] = z1[both] + s[both] * (z2[both] - z1[both])
    edge = occlusion_edges(z1, z2, edge_ratio)
    z[edge] = np.minimum(z1, z2)[edge]
    z[k1 & ~k2] = z1[k1 & ~k2]
    z[k2 & ~k1] = z2[k2 & ~k1]
    return z


def _check_map(depth_map: DepthMap, events: EventStream) -> None:
    """Raise if a depth map does not cover the events' sensor."""
    if depth_map.depth.shape != (events.height, events.width):
        raise ValueError(
            f"{depth_map.source}: depth map shape {depth_map.depth.shape} does not match the "
            f"events' sensor (H, W) = ({events.height}, {events.width})"
        )


def event_depth(
    events: EventStream, first: DepthMap, second: DepthMap, *, edge_ratio: float | None = None
) -> np.ndarray:
    """Depth (N,) of each event: ``Z1 + (t - T1)/(T2 - T1) (Z2 - Z1)`` at its pixel.

    A depth unknown in one map is taken from the other; unknown in both gives NaN. Times
    outside [T1, T2] are clamped to the nearer map; ``T2 == T1`` uses Z1 (Z2 where Z1 is
    unknown). Occlusion edges (``edge_ratio``, see :func:`_interpolate`) take the nearer depth.
    """
    z1, z2 = _pixel_depths(events, first, second)
    return _interpolate(z1, z2, _time_fraction(events.t, first.t, second.t), edge_ratio)


def _pixel_depths(
    events: EventStream, first: DepthMap, second: DepthMap
) -> tuple[np.ndarray, np.ndarray]:
    """Each event's depth in the first and in the second map (maps checked against the
    events' sensor)."""
    _check_map(first, events)
    _check_map(second, events)
    return first.depth[events.y, events.x], second.depth[events.y, events.x]


def fill_depth(depth: np.ndarray, x: np.ndarray, y: np.ndarray, *, radius: int) -> np.ndarray:
    """Median of the known depths in the ``(2 radius + 1)^2`` window around each pixel (x, y).

    Used by the "fill" policy for events without depth in either map: a depth map from a
    network is smooth, so a neighbour's depth is the best guess. NaN where the window holds
    no known depth; pixels beyond the border are ignored.
    """
    d = np.asarray(depth, dtype=np.float64)
    x = np.asarray(x, dtype=np.int64)
    y = np.asarray(y, dtype=np.int64)
    if d.ndim != 2:
        raise ValueError(f"depth must be a 2-D map, got shape {d.shape}")
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"x and y must be 1-D of equal length, got {x.shape} and {y.shape}")
    if int(radius) != radius or radius < 0:
        raise ValueError(f"fill radius must be an integer >= 0, got {radius}")
    h, w = d.shape
    if x.size and (x.min() < 0 or x.max() >= w or y.min() < 0 or y.max() >= h):
        raise ValueError(f"pixels outside the {w}x{h} depth map")
    values = _neighbourhood(d, x, y, int(radius))
    values = np.where(_known(values), values, np.nan)
    out = np.full(len(x), np.nan)
    some = np.isfinite(values).any(axis=1)
    out[some] = np.nanmedian(values[some], axis=1)
    return out


def _neighbourhood(d: np.ndarray, x: np.ndarray, y: np.ndarray, radius: int) -> np.ndarray:
    """The values of map ``d`` in the ``(2 radius + 1)^2`` window around each pixel (x, y),
    one row per pixel; NaN beyond the border."""
    h, w = d.shape
    offsets = np.arange(-radius, radius + 1)
    xx = x[:, None, None] + offsets[None, None, :]
    yy = y[:, None, None] + offsets[None, :, None]
    inside = (xx >= 0) & (xx < w) & (yy >= 0) & (yy < h)
    values = d[np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)]
    return np.where(inside, values, np.nan).reshape(len(x), -1)


def back_project(x: np.ndarray, y: np.ndarray, z: np.ndarray, camera: Camera) -> np.ndarray:
    """Pinhole back-projection (N, 3): ``X = (x - cx) Z / fx``, ``Y = (y - cy) Z / fy``, Z."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    if not (x.ndim == 1 and x.shape == y.shape == z.shape):
        raise ValueError(
            f"x, y, z must be 1-D of equal length, got {x.shape}, {y.shape}, {z.shape}"
        )
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y)) and np.all(np.isfinite(z))):
        raise ValueError("x, y or z contains NaN or inf; drop events without depth first")
    return np.column_stack(((x - camera.cx) * z / camera.fx, (y - camera.cy) * z / camera.fy, z))


def _window_maps(window: Recording) -> tuple[DepthMap, ...]:
    """The time-sorted depth maps of a window or span of windows; raise with fewer than two."""
    if len(window.depth_maps) < 2:
        raise ValueError(
            f"{window.name}: a window needs two depth maps (or more for a span of windows), "
            f"got {len(window.depth_maps)}; take windows from Recording.windows()"
        )
    return window.depth_maps


def _bracketing_pair(t: np.ndarray, maps: tuple[DepthMap, ...]) -> np.ndarray:
    """Index i of the maps (i, i + 1) bracketing each time; times outside all maps take the
    first or the last pair (and are clamped there by :func:`_time_fraction`)."""
    times = np.array([m.t for m in maps])
    return np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(maps) - 2)


def lift(
    window: Recording,
    *,
    unknown_depth: str,
    fill_radius: int,
    edge_ratio: float | None = None,
) -> Lifted:
    """Depth and 3-D position of each event of a window, per METHOD.md 1: each event between
    the two of the window's depth maps that bracket its time (a window has two; a span of
    windows, ``window.context``, one more per window).

    ``unknown_depth`` says what happens to an event with no depth in either map: "drop"
    excludes it (``valid`` False; the pipeline labels it -1), "fill" takes, in each map,
    the median known depth within ``fill_radius`` pixels (:func:`fill_depth`) and
    interpolates those; an event still without depth is dropped. NaN never reaches
    ``points``. ``edge_ratio`` is the occlusion-edge rule of :func:`event_depth`.
    """
    if unknown_depth not in UNKNOWN_DEPTH_POLICIES:
        raise ValueError(
            f"unknown_depth must be one of {UNKNOWN_DEPTH_POLICIES}, got {unknown_depth!r}"
        )
    ev = window.events
    if not len(ev):
        raise ValueError(f"{window.name}: the window has no events; check the window bounds")
    maps = _window_maps(window)
    pair = _bracketing_pair(ev.t, maps)
    depth = np.full(len(ev), np.nan)
    on_edge = np.zeros(len(ev), dtype=bool)
    for i in np.unique(pair):
        sel = np.flatnonzero(pair == i)
        first, second = maps[i], maps[i + 1]
        z1, z2 = _pixel_depths(ev.select(sel), first, second)
        s = _time_fraction(ev.t[sel], first.t, second.t)
        depth[sel] = _interpolate(z1, z2, s, edge_ratio)
        edge = occlusion_edges(z1, z2, edge_ratio)
        on_edge[sel] = edge
        missing = ~np.isfinite(depth[sel])
        if unknown_depth == "fill" and missing.any():
            x, y = ev.x[sel][missing], ev.y[sel][missing]
            f1 = fill_depth(first.depth, x, y, radius=fill_radius)
            f2 = fill_depth(second.depth, x, y, radius=fill_radius)
            depth[sel[missing]] = _interpolate(f1, f2, s[missing])
    valid = np.isfinite(depth)
    if not valid.any():
        sources = ", ".join(m.source for m in maps)
        raise ValueError(
            f"{window.name}: all events in the window have unknown depth; check the depth "
            f"maps {sources} (NaN or <= 0 means unknown)"
        )
    points = back_project(ev.x[valid], ev.y[valid], depth[valid], window.camera)
    return Lifted(points=points, t=ev.t[valid].copy(), valid=valid, depth=depth, on_edge=on_edge)


def voxel_size(
    points: np.ndarray,
    camera: Camera,
    *,
    xy_scale: float,
    z_bins: int,
    coordinates: str = "metric",
    depth_error: float = 0.0,
) -> np.ndarray:
    """Voxel size (3,) of the volume of warped events, in the grid's coordinates.

    ``metric`` (metres): X and Y are ``xy_scale`` pixel footprints at the median depth
    (``median(Z)/fx``, ``/fy``), so one voxel is about ``xy_scale`` pixels where most events
    are; Z is the depth extent of the points over ``z_bins``, never finer than the smaller
    lateral size. ``image`` (pixels, pixels, 1/m): ``xy_scale`` pixels, and the inverse-depth
    extent over ``z_bins``, never finer than the inverse-depth step of a lateral voxel at the
    median depth (``xy_scale median(1/Z) / f``). Decision: the floor keeps a flat scene (zero
    extent) valid, and finer depth voxels buy nothing because an estimated depth is far less
    precise than a pixel position; so ``z_bins`` is an upper bound on the number of depth bins.
    ``depth_error``: the depth's relative error; the depth voxel is never finer than it at
    the median depth (``depth_error median(Z)``, or ``depth_error median(1/Z)`` in inverse
    depth), so that events of one object, whose depths scatter by that error, share a
    depth voxel whatever the scene's depth range.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts):
        raise ValueError(f"need a non-empty N x 3 array of points, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points contain NaN or inf; drop events without depth first")
    if np.any(pts[:, 2] <= 0):
        raise ValueError("points must have positive depth Z (in front of the camera)")
    if not (np.isfinite(xy_scale) and xy_scale > 0):
        raise ValueError(f"xy_scale must be a positive number, got {xy_scale}")
    if int(z_bins) != z_bins or z_bins < 1:
        raise ValueError(f"z_bins must be an integer >= 1, got {z_bins}")
    if not (np.isfinite(depth_error) and depth_error >= 0):
        raise ValueError(f"depth_error must be a number >= 0, got {depth_error}")
    if coordinates == "image":
        inverse = 1.0 / pts[:, 2]
        median_inverse = float(np.median(inverse))
        floor = max(xy_scale / max(camera.fx, camera.fy), depth_error) * median_inverse
        step = max(float(inverse.max() - inverse.min()) / int(z_bins), floor)
        return np.array([xy_scale, xy_scale, step])
    if coordinates != "metric":
        raise ValueError(f"volume.coordinates must be 'image' or 'metric', got {coordinates!r}")
    z = pts[:, 2]
    median = float(np.median(z))
    sx = xy_scale * median / camera.fx
    sy = xy_scale * median / camera.fy
    sz = max(float(z.max() - z.min()) / int(z_bins), min(sx, sy), depth_error * median)
    return np.array([sx, sy, sz])
