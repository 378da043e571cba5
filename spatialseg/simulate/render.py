"""Ray casting with a z-buffer: a scene at time t as depth, object label and log intensity.

Each pixel's ray ``(rx, ry, 1)`` (pixel centres at integer coordinates) is intersected with
the background planes, the static props and the moving boxes; the nearest hit wins. Along
such a ray the ray parameter is the depth Z itself. Rays are separable (rx per column, ry
per row), so slab tests broadcast a row vector against a column vector. With a static
camera the static scene (planes and props) is rendered once and reused bit for bit, so it
can never produce events.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spatialseg.simulate.scene import Body, Scene
from spatialseg.simulate.texture import sample_texture

__all__ = ["STATIC_SCENE", "Frame", "Renderer", "surface_count"]

#: Ground-truth id of the static background ("static scene"); objects are 1..N in YAML order.
STATIC_SCENE = 0


def surface_count(scene: Scene) -> int:
    """The number of textured surfaces (planes, props, objects): one texture key each."""
    return len(scene.background) + len(scene.props) + len(scene.objects)


@dataclass(frozen=True, eq=False)
class Frame:
    """One render: depth (m), label (object id), irradiance and log irradiance, all H x W."""

    t: float
    depth: np.ndarray
    label: np.ndarray
    intensity: np.ndarray
    log_intensity: np.ndarray


@dataclass(frozen=True, eq=False)
class _Layer:
    """Per-pixel depth, surface index (planes, then props, then objects) and reflectance."""

    depth: np.ndarray
    surface: np.ndarray
    reflectance: np.ndarray


def _plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two orthonormal in-plane axes for a plane's texture coordinates."""
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(normal)))] = 1.0
    e1 = np.cross(helper, normal)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)


def _slab(lo: float, hi: float, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth interval where rays from the origin with direction component ``d`` lie in [lo, hi]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = lo / d, hi / d
    inside = lo <= 0 <= hi
    parallel = d == 0
    enter = np.where(parallel, -np.inf if inside else np.inf, np.minimum(a, b))
    leave = np.where(parallel, np.inf if inside else -np.inf, np.maximum(a, b))
    return enter, leave


def _corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The 8 corners (8 x 3) of the box [lo, hi]."""
    grid = np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1).T
    return np.where(grid == 1, hi, lo)


def _face_coordinates(local: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Texture coordinates of box-surface points: the two axes along the face they lie on."""
    with np.errstate(divide="ignore", invalid="ignore"):
        closeness = np.where(half > 0, np.abs(local) / half, np.inf)
    face = np.argmax(closeness, axis=1)
    s = np.where(face == 0, local[:, 2], local[:, 0])
    u = np.where(face == 1, local[:, 2], local[:, 1])
    return s, u


class Renderer:
    """Renders a :class:`Scene` at any time; textures are keyed by ``keys``, one per surface
    in the order planes, props, objects (see :func:`surface_count`)."""

    def __init__(self, scene: Scene, keys: np.ndarray) -> None:
        cam = scene.camera
        if len(keys) != surface_count(scene):
            raise ValueError(
                f"{len(keys)} texture keys for {surface_count(scene)} surfaces; "
                "pass one key per plane, prop and object"
            )
        self.scene = scene
        self.keys = [int(k) for k in keys]
        self.n_static = len(scene.background) + len(scene.props)
        self.rx = (np.arange(cam.width) - cam.cx) / cam.fx
        self.ry = (np.arange(cam.height) - cam.cy) / cam.fy
        self.axes = [_plane_axes(p.normal) for p in scene.background]
        # n . (rx, ry, 1) per pixel: fixed for the recording, since planes do not turn
        self.facing = [
            p.normal[0] * self.rx[None, :] + p.normal[1] * self.ry[:, None] + p.normal[2]
            for p in scene.background
        ]
        relative = [b.velocity - scene.ego_velocity for b in scene.objects]
        self.velocities = np.array([-scene.ego_velocity, *relative]).reshape(-1, 3)
        self.camera_moves = bool(np.any(scene.ego_velocity))
        self._static = None if self.camera_moves else self._background(0.0)

    def _background(self, t: float) -> _Layer:
        """The static scene at time t: the planes (every pixel must hit one), then the props."""
        cam, centre = self.scene.camera, self.scene.ego_velocity * t
        shape = (cam.height, cam.width)
        depth = np.full(shape, np.inf)
        surface = np.zeros(shape, dtype=np.int32)
        for k, plane in enumerate(self.scene.background):
            with np.errstate(divide="ignore", invalid="ignore"):
                z = np.float64(plane.normal @ (plane.point - centre)) / self.facing[k]
            nearer = (z > 0) & (z < depth)
            depth[nearer] = z[nearer]
            surface[nearer] = k
        if np.isinf(depth).any():
            row, col = np.argwhere(np.isinf(depth))[0]
            raise ValueError(
                f"scene '{self.scene.name}': no background plane is seen at pixel "
                f"({col}, {row}) at t={t:.4f} s; add a plane that fills the view"
            )
        reflectance = np.empty(shape)
        for k, plane in enumerate(self.scene.background):
            rows, cols = np.nonzero(surface == k)
            z = depth[rows, cols]
            hit = np.stack([z * self.rx[cols], z * self.ry[rows], z], axis=-1) + centre
            e1, e2 = self.axes[k]
            local = hit - plane.point
            reflectance[rows, cols] = sample_texture(
                plane.texture, self.keys[k], local @ e1, local @ e2
            )
        layer = _Layer(depth, surface, reflectance)
        for index, prop in enumerate(self.scene.props):
            self._draw_box(layer, prop, len(self.scene.background) + index, t)
        return layer

    def _box_bounds(self, body: Body, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The box's near and far corners in camera coordinates at time t (in front: see
        the scene's clearance check)."""
        centre = body.position + (body.velocity - self.scene.ego_velocity) * t
        return centre - body.size / 2, centre + body.size / 2

    def _pixel_window(self, lo: np.ndarray, hi: np.ndarray) -> tuple[slice, slice] | None:
        """Rows and columns covering the projected box, or None if it is off the sensor."""
        cam, corners = self.scene.camera, _corners(lo, hi)
        u = cam.cx + cam.fx * corners[:, 0] / corners[:, 2]
        v = cam.cy + cam.fy * corners[:, 1] / corners[:, 2]
        c0, c1 = max(int(np.floor(u.min())), 0), min(int(np.ceil(u.max())) + 1, cam.width)
        r0, r1 = max(int(np.floor(v.min())), 0), min(int(np.ceil(v.max())) + 1, cam.height)
        if c0 >= c1 or r0 >= r1:
            return None
        return slice(r0, r1), slice(c0, c1)

    def _draw_box(self, layer: _Layer, body: Body, surface: int, t: float) -> None:
        """Z-buffer one box (prop or object, surface index ``surface``) into ``layer`` in place."""
        lo, hi = self._box_bounds(body, t)
        window = self._pixel_window(lo, hi)
        if window is None:
            return
        rows, cols = window
        rx, ry = self.rx[cols], self.ry[rows]
        ex, lx = _slab(lo[0], hi[0], rx)
        ey, ly = _slab(lo[1], hi[1], ry)
        enter = np.maximum(np.maximum(ex[None, :], ey[:, None]), lo[2])
        leave = np.minimum(np.minimum(lx[None, :], ly[:, None]), hi[2])
        depth = layer.depth[window]
        wins = (enter <= leave) & (enter < depth)
        if not wins.any():
            return
        r, c = np.nonzero(wins)
        z = enter[r, c]
        local = np.stack([z * rx[c], z * ry[r], z], axis=-1) - (lo + hi) / 2
        s, u = _face_coordinates(local, body.size / 2)
        depth[r, c] = z
        layer.surface[window][r, c] = surface
        layer.reflectance[window][r, c] = sample_texture(body.texture, self.keys[surface], s, u)

    def render(self, t: float) -> Frame:
        """The scene at time ``t`` (seconds)."""
        base = self._background(t) if self.camera_moves else self._static
        layer = _Layer(base.depth.copy(), base.surface.copy(), base.reflectance.copy())
        for index, body in enumerate(self.scene.objects):
            self._draw_box(layer, body, self.n_static + index, t)
        first = self.n_static  # surface index of object 1
        label = np.where(layer.surface >= first, layer.surface - first + 1, STATIC_SCENE)
        light, eps = self.scene.lighting, self.scene.sensor.log_eps
        intensity = light.gain * layer.reflectance**light.gamma
        return Frame(t, layer.depth, label.astype(np.int32), intensity, np.log(intensity + eps))

    def max_image_speed(self, frame: Frame) -> float:
        """The fastest image motion (px/s): over the static scene's pixels and its props'
        corners when the camera moves, and over each object's corners (visible or not, so
        entering objects and props count)."""
        cam, fastest = self.scene.camera, 0.0
        boxes = [
            (body, self.velocities[index + 1]) for index, body in enumerate(self.scene.objects)
        ]
        if self.camera_moves:
            v = self.velocities[STATIC_SCENE]
            du = cam.fx * (v[0] - self.rx[None, :] * v[2]) / frame.depth
            dv = cam.fy * (v[1] - self.ry[:, None] * v[2]) / frame.depth
            speed = np.where(frame.label == STATIC_SCENE, np.hypot(du, dv), 0.0)
            fastest = float(speed.max())
            boxes += [(prop, v) for prop in self.scene.props]
        for body, vel in boxes:
            corners = _corners(*self._box_bounds(body, frame.t))
            z = corners[:, 2]
            du = cam.fx * (vel[0] - corners[:, 0] / z * vel[2]) / z
            dv = cam.fy * (vel[1] - corners[:, 1] / z * vel[2]) / z
            fastest = max(fastest, float(np.hypot(du, dv).max()))
        return fastest
