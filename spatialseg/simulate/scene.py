"""A simulated scene, parsed and validated from a ``conf/scene/NAME.yaml`` mapping.

Coordinates: the camera does not rotate, so world axes are camera axes (X right, Y down,
Z forward along the optical axis); the camera's centre is at the origin at t = 0 and moves
with ``camera.ego_velocity``. Positions and velocities in the YAML are in this world frame,
in metres and m/s. Every mapping is checked for unknown keys so a typo fails loudly.

The background is the static scene: infinite planes plus optional static ``props`` (boxes or
patches at rest in the world, e.g. parked cars and posts), all one motion (ground-truth id 0).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from spatialseg.checks import is_integer
from spatialseg.recording import Camera

__all__ = [
    "NO_DEPTH_ERROR",
    "Body",
    "DepthError",
    "Lighting",
    "Plane",
    "Scene",
    "SensorModel",
    "Texture",
    "parse_scene",
]

TEXTURE_KINDS = {
    "uniform": ("level",),
    "noise": ("cell", "low", "high", "octaves"),
    "checker": ("cell", "low", "high"),
}
SHAPES = {"patch": 2, "box": 3}


@dataclass(frozen=True)
class Texture:
    """A procedural reflectance in [0, 1] over a surface's own 2-D coordinates (metres).

    ``uniform``: constant ``level``. ``noise``: bilinear value noise on a lattice of ``cell``
    metres, ``octaves`` finer layers of half weight, values spread over [low, high].
    ``checker``: squares of ``cell`` metres alternating between ``low`` and ``high``.
    """

    kind: str
    level: float = 0.0
    cell: float = 0.0
    low: float = 0.0
    high: float = 0.0
    octaves: int = 1


@dataclass(frozen=True)
class Plane:
    """A static infinite textured plane through ``point`` with normal ``normal`` (background)."""

    name: str
    normal: np.ndarray
    point: np.ndarray
    texture: Texture


@dataclass(frozen=True)
class Body:
    """A moving axis-aligned box (or a fronto-parallel ``patch``, a box of zero Z extent)."""

    name: str
    shape: str
    size: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    texture: Texture


@dataclass(frozen=True)
class DepthError:
    """Corruption of the output depth maps (what EDPA reads); the renderer's truth stays exact.

    Each map becomes ``scale * depth * exp(e)`` with ``e`` a smooth Gaussian random field of
    standard deviation ``sigma`` and correlation length ``correlation`` pixels; then the top
    ``holes`` share of a second smooth field (correlation ``hole_size`` px) becomes unknown
    (NaN) in blobs. ``shared``: both maps get the same field and holes (a fixed bias) instead
    of independent draws. ``bias``: the std of one more smooth field that every map shares,
    added to ``e``, so a map can carry a fixed bias and its own flicker at once (a depth
    network run per frame). ``seed_offset`` picks another draw for the same run seed.
    """

    sigma: float
    correlation: float
    holes: float
    hole_size: float
    scale: float
    shared: bool
    seed_offset: int
    bias: float = 0.0

    @property
    def active(self) -> bool:
        """False when every setting is neutral: the depth maps are then left untouched."""
        return self.sigma > 0 or self.bias > 0 or self.holes > 0 or self.scale != 1.0


#: No corruption: a scene without a ``depth_error`` block (the two lengths are then unused).
NO_DEPTH_ERROR = DepthError(
    sigma=0.0, correlation=1.0, holes=0.0, hole_size=1.0, scale=1.0, shared=False, seed_offset=0
)

#: Keys of a ``depth_error`` block, in YAML order.
DEPTH_ERROR_KEYS = (
    "sigma",
    "correlation",
    "holes",
    "hole_size",
    "scale",
    "shared",
    "bias",
    "seed_offset",
)


@dataclass(frozen=True)
class SensorModel:
    """ESIM-style pixel model: log(I + log_eps) crossings of per-pixel thresholds, plus noise."""

    threshold_mean: float
    threshold_std: float
    threshold_min: float
    refractory: float
    noise_rate: float
    log_eps: float


@dataclass(frozen=True)
class Lighting:
    """Irradiance ``gain * reflectance ** gamma``: gamma < 1 flattens contrast, > 1 hardens it."""

    gain: float
    gamma: float


@dataclass(frozen=True)
class Scene:
    """Everything the simulator needs: camera, ego-motion, sensor, lighting and surfaces.

    ``background`` holds the static planes and ``props`` the static boxes and patches; both
    are the static scene. ``objects`` move. ``depth_error`` corrupts the output depth maps.
    """

    name: str
    description: str
    camera: Camera
    ego_velocity: np.ndarray
    duration: float
    max_pixel_step: float
    sensor: SensorModel
    lighting: Lighting
    background: tuple[Plane, ...]
    objects: tuple[Body, ...]
    props: tuple[Body, ...] = ()
    depth_error: DepthError = NO_DEPTH_ERROR


class _Reader:
    """Reads typed, validated values from one mapping, naming the key path in errors."""

    def __init__(self, data: Any, where: str, scene: str) -> None:
        if not isinstance(data, Mapping):
            raise ValueError(f"scene '{scene}': {where} must be a mapping, got {data!r}")
        self.data, self.where, self.scene = data, where, scene

    def _fail(self, key: str, message: str) -> ValueError:
        path = f"{self.where}.{key}" if self.where else key
        return ValueError(f"scene '{self.scene}': {path} {message}")

    def only(self, keys: tuple[str, ...]) -> None:
        """Reject keys outside ``keys`` (typos) and require all of them."""
        for key in self.data:
            if key not in keys:
                raise self._fail(str(key), f"is not a known key; valid: {', '.join(keys)}")
        for key in keys:
            if key not in self.data:
                raise self._fail(key, "is missing")

    def raw(self, key: str) -> Any:
        """The value at ``key``."""
        return self.data[key]

    def number(self, key: str, *, low: float | None = None, positive: bool = False) -> float:
        """A finite float, optionally ``>= low`` or ``> 0``."""
        value = self.data[key]
        if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
            raise self._fail(key, f"must be a finite number, got {value!r}")
        if positive and value <= 0:
            raise self._fail(key, f"must be > 0, got {value}")
        if low is not None and value < low:
            raise self._fail(key, f"must be >= {low}, got {value}")
        return float(value)

    def integer(self, key: str, *, low: int) -> int:
        """An integer ``>= low``."""
        value = self.data[key]
        if not is_integer(value, low):
            raise self._fail(key, f"must be an integer >= {low}, got {value!r}")
        return int(value)

    def vector(self, key: str, length: int = 3) -> np.ndarray:
        """A list of ``length`` finite numbers as a float64 array."""
        value = self.data[key]
        if not isinstance(value, list | tuple) or len(value) != length:
            raise self._fail(key, f"must be a list of {length} numbers, got {value!r}")
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self._fail(key, f"must be a list of {length} numbers, got {value!r}") from None
        if not np.all(np.isfinite(array)):
            raise self._fail(key, f"must be finite, got {value!r}")
        return array

    def flag(self, key: str) -> bool:
        """A boolean (true or false, not 0 or 1)."""
        value = self.data[key]
        if not isinstance(value, bool):
            raise self._fail(key, f"must be true or false, got {value!r}")
        return value

    def text(self, key: str) -> str:
        """A non-empty string."""
        value = self.data[key]
        if not isinstance(value, str) or not value:
            raise self._fail(key, f"must be a non-empty string, got {value!r}")
        return value

    def sub(self, key: str) -> _Reader:
        """A reader for the nested mapping at ``key``."""
        path = f"{self.where}.{key}" if self.where else key
        return _Reader(self.data[key], path, self.scene)


def _texture(r: _Reader) -> Texture:
    """Parse a texture mapping; its keys depend on its ``kind``."""
    kind = r.data.get("kind")
    if kind not in TEXTURE_KINDS:
        raise r._fail("kind", f"must be one of {', '.join(TEXTURE_KINDS)}, got {kind!r}")
    r.only(("kind", *TEXTURE_KINDS[kind]))
    if kind == "uniform":
        level = r.number("level", low=0.0)
        if level > 1:
            raise r._fail("level", f"must be in [0, 1], got {level}")
        return Texture(kind, level=level)
    low, high = r.number("low", low=0.0), r.number("high", low=0.0)
    if not low <= high <= 1:
        raise r._fail("high", f"must satisfy low <= high <= 1, got low={low} high={high}")
    octaves = 1
    if kind == "noise":
        octaves = r.integer("octaves", low=1)
    return Texture(kind, cell=r.number("cell", positive=True), low=low, high=high, octaves=octaves)


def _plane(r: _Reader) -> Plane:
    """Parse one background plane."""
    r.only(("name", "normal", "point", "texture"))
    normal = r.vector("normal")
    length = float(np.linalg.norm(normal))
    if length == 0:
        raise r._fail("normal", "must not be the zero vector")
    return Plane(r.text("name"), normal / length, r.vector("point"), _texture(r.sub("texture")))


def _body(r: _Reader, *, moving: bool = True) -> Body:
    """Parse one object: a patch (size [w, h]) or a box (size [w, h, d]).

    A static prop (``moving=False``, a ``background`` entry with a ``shape``) has no
    ``velocity`` key: it rests in the world, so it moves with the static scene.
    """
    keys = ("name", "shape", "size", "position", "velocity", "texture")
    r.only(keys if moving else tuple(k for k in keys if k != "velocity"))
    shape = r.raw("shape")
    if shape not in SHAPES:
        raise r._fail("shape", f"must be one of {', '.join(SHAPES)}, got {shape!r}")
    size = r.vector("size", SHAPES[shape])
    if np.any(size <= 0):
        raise r._fail("size", f"must be positive, got {size.tolist()}")
    size = np.append(size, 0.0) if shape == "patch" else size
    position = r.vector("position")
    velocity = r.vector("velocity") if moving else np.zeros(3)
    return Body(r.text("name"), shape, size, position, velocity, _texture(r.sub("texture")))


def _background(r: _Reader, name: str) -> tuple[tuple[Plane, ...], tuple[Body, ...]]:
    """Split ``background`` into infinite planes and static props (entries with a ``shape``)."""
    entries = r.raw("background")
    if not isinstance(entries, list) or not entries:
        raise r._fail("background", "must be a non-empty list of planes (and static props)")
    planes, props = [], []
    for i, entry in enumerate(entries):
        item = _Reader(entry, f"background[{i}]", name)
        if "shape" in item.data:
            props.append(_body(item, moving=False))
        else:
            planes.append(_plane(item))
    if not planes:
        raise r._fail("background", "needs at least one plane (props alone cannot fill the view)")
    return tuple(planes), tuple(props)


def _depth_error(r: _Reader) -> DepthError:
    """Parse the ``depth_error`` block (every key required, as everywhere in a scene)."""
    r.only(DEPTH_ERROR_KEYS)
    holes = r.number("holes", low=0.0)
    if holes >= 1:
        raise r._fail("holes", f"must be a share of the pixels in [0, 1), got {holes}")
    return DepthError(
        sigma=r.number("sigma", low=0.0),
        correlation=r.number("correlation", positive=True),
        holes=holes,
        hole_size=r.number("hole_size", positive=True),
        scale=r.number("scale", positive=True),
        shared=r.flag("shared"),
        seed_offset=r.integer("seed_offset", low=0),
        bias=r.number("bias", low=0.0),
    )


def _camera(r: _Reader) -> tuple[Camera, np.ndarray]:
    """Parse the camera's intrinsics, size and ego-velocity."""
    r.only(("width", "height", "fx", "fy", "cx", "cy", "ego_velocity"))
    camera = Camera(
        fx=r.number("fx", positive=True),
        fy=r.number("fy", positive=True),
        cx=r.number("cx"),
        cy=r.number("cy"),
        width=r.integer("width", low=1),
        height=r.integer("height", low=1),
    )
    return camera, r.vector("ego_velocity")


def _sensor(r: _Reader) -> SensorModel:
    """Parse the pixel model."""
    r.only(
        (
            "threshold_mean",
            "threshold_std",
            "threshold_min",
            "refractory",
            "noise_rate",
            "log_eps",
        )
    )
    return SensorModel(
        threshold_mean=r.number("threshold_mean", positive=True),
        threshold_std=r.number("threshold_std", low=0.0),
        threshold_min=r.number("threshold_min", positive=True),
        refractory=r.number("refractory", low=0.0),
        noise_rate=r.number("noise_rate", low=0.0),
        log_eps=r.number("log_eps", positive=True),
    )


def _plain(scene_cfg: Mapping[str, Any]) -> Mapping[str, Any]:
    """A plain-Python view of a DictConfig (resolved) or the mapping itself."""
    if isinstance(scene_cfg, DictConfig):
        container = OmegaConf.to_container(scene_cfg, resolve=True)
        assert isinstance(container, dict)
        return container
    return scene_cfg


def _check_clearance(scene: Scene) -> None:
    """Objects stay in front of the camera and the camera on one side of each plane.

    Checked at t = 0 and t = duration (motions are linear, so this covers the whole run);
    an object reaching the camera plane would shrink the adaptive render step towards zero.
    """
    times = (0.0, scene.duration)
    labelled = [("prop", b) for b in scene.props] + [("object", b) for b in scene.objects]
    for kind, body in labelled:
        near = [
            body.position[2] - body.size[2] / 2 + (body.velocity[2] - scene.ego_velocity[2]) * t
            for t in times
        ]
        if min(near) <= 0:
            raise ValueError(
                f"scene '{scene.name}': {kind} '{body.name}' reaches the camera plane (Z <= 0) "
                f"before t={scene.duration} s; shorten duration or start it farther away"
            )
    for plane in scene.background:
        side = [float(plane.normal @ (plane.point - scene.ego_velocity * t)) for t in times]
        if side[0] * side[1] <= 0:
            raise ValueError(
                f"scene '{scene.name}': the camera reaches background plane '{plane.name}' "
                f"before t={scene.duration} s; shorten duration or move the plane"
            )


def parse_scene(scene_cfg: Mapping[str, Any]) -> Scene:
    """Validate a scene config (dict or DictConfig) and return it as a :class:`Scene`."""
    data = _plain(scene_cfg)
    name = str(data.get("name", "<unnamed>")) if isinstance(data, Mapping) else "<unnamed>"
    r = _Reader(data, "", name)
    keys = ("name", "kind", "description", "camera", "duration", "sensor", "render")
    keys = (*keys, "lighting", "background", "objects")
    # depth_error is optional (absent: no corruption) so older scene files stay valid
    r.only((*keys, "depth_error") if "depth_error" in r.data else keys)
    if r.raw("kind") != "simulated":
        raise r._fail("kind", f"must be 'simulated' to simulate, got {r.raw('kind')!r}")
    camera, ego = _camera(r.sub("camera"))
    render = r.sub("render")
    render.only(("max_pixel_step",))
    step = render.number("max_pixel_step", positive=True)
    if step > 1:
        raise render._fail("max_pixel_step", f"must be a fraction of a pixel (<= 1), got {step}")
    lighting = r.sub("lighting")
    lighting.only(("gain", "gamma"))
    planes, props = _background(r, name)
    bodies = r.raw("objects")
    if not isinstance(bodies, list):
        raise r._fail("objects", f"must be a list (may be empty), got {bodies!r}")
    objects = tuple(_body(_Reader(b, f"objects[{i}]", name)) for i, b in enumerate(bodies))
    names = [o.name for o in objects]
    if len(set(names)) != len(names):
        raise r._fail("objects", f"names must be unique, got {names}")
    error = _depth_error(r.sub("depth_error")) if "depth_error" in r.data else NO_DEPTH_ERROR
    scene = Scene(
        name=r.text("name"),
        description=str(r.raw("description")),
        camera=camera,
        ego_velocity=ego,
        duration=r.number("duration", positive=True),
        max_pixel_step=step,
        sensor=_sensor(r.sub("sensor")),
        lighting=Lighting(
            lighting.number("gain", positive=True), lighting.number("gamma", positive=True)
        ),
        background=planes,
        objects=objects,
        props=props,
        depth_error=error,
    )
    _check_clearance(scene)
    return scene
