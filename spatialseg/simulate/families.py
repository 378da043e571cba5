"""Scene families: seeded generators of whole scenes, the yardstick's data.

The scenes in ``conf/scene`` are fixed points that the defaults were chosen on; a family
is a distribution. Each family draws every free choice from its seed: the sensor, the
objects' sizes, textures, depths, directions and speeds, the camera's motion, the window
length, and the modifiers every family shares (:class:`Modifiers`: depth error of both
kinds, unknown-depth holes, background noise). Geometry is drawn in image terms, where a
user meets it (how large an object looks, how far it moves per window), then turned into
metres by its depth.

:func:`draw_scene` returns a :class:`FamilyScene`, whose ``scene`` is a mapping in the
``conf/scene`` schema (the simulator, the CLI and a user can all read it);
:func:`simulate_family` simulates it into a :class:`~spatialseg.recording.Recording`
whose ground truth has one id per 3-D motion: objects that share a velocity share an id.
Families live in :data:`FAMILIES`, one generator each (``docs/scenes.md`` says what each
tests and why a user meets it).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from spatialseg.events import EventStream
from spatialseg.recording import DepthMap, GroundTruth, Keyframe, Recording
from spatialseg.simulate.render import Renderer
from spatialseg.simulate.scene import parse_scene
from spatialseg.simulate.simulator import simulate_scene, texture_keys

__all__ = [
    "FAMILIES",
    "SENSORS",
    "FamilyScene",
    "Modifiers",
    "draw_scene",
    "merge_equal_motions",
    "simulate_family",
    "with_noise",
    "with_time_offset",
]

#: Sensor sizes a scene is drawn on: DAVIS240, DAVIS346, VGA (DVXplorer, Prophesee Gen3)
#: and HD (Prophesee IMX636).
SENSORS: tuple[tuple[int, int], ...] = ((240, 180), (346, 260), (640, 480), (1280, 720))

#: Each modifier's largest value; a scene draws it as 0 with probability one half, else
#: uniformly up to this.
MODIFIER_LIMITS = {"depth_bias": 0.15, "depth_flicker": 0.15, "holes": 0.05, "noise": 0.3}


@dataclass(frozen=True)
class Modifiers:
    """What every family draws on top of its scene.

    ``depth_bias``: std of one smooth relative depth error that every depth map shares (a
    miscalibrated or biased depth source); ``depth_flicker``: std of an error drawn anew
    for each map (a depth network run per frame); ``holes``: share of pixels with unknown
    depth; ``noise``: share of all events that are background noise (label -1).
    """

    depth_bias: float = 0.0
    depth_flicker: float = 0.0
    holes: float = 0.0
    noise: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value, limit = getattr(self, f.name), 0.95 if f.name != "holes" else 0.5
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"modifier {f.name} must be a number, got {value!r}")
            if not 0 <= value <= limit:
                raise ValueError(f"modifier {f.name} must be in [0, {limit}], got {value}")


@dataclass(frozen=True)
class FamilyScene:
    """One draw of a family: the scene mapping, how it is cut into windows, its motions.

    ``windows``: windows of equal event counts over the simulated duration (each between
    two depth maps); ``n_motions``: distinct 3-D motions (the static scene counts when the
    camera moves); ``time_offset``: seconds added to every timestamp; ``summary``: the
    drawn quantities a reader wants at a glance (sensor, motions per window, ...).
    """

    family: str
    seed: int
    scene: dict[str, Any]
    windows: int
    n_motions: int
    modifiers: Modifiers
    time_offset: float = 0.0
    summary: dict[str, Any] = field(default_factory=dict)


@dataclass
class _Thing:
    """A box drawn in image terms at the middle of the recording.

    ``size`` (w, h) and ``centre`` (u, v) in pixels, ``depth`` of its front face and
    ``thickness`` in metres, ``velocity`` relative to the camera (m/s), ``cell`` the
    texture's lattice in pixels at its depth, ``contrast`` the texture's (low, high).
    """

    name: str
    size: np.ndarray
    depth: float
    velocity: np.ndarray
    cell: float
    contrast: tuple[float, float]
    thickness: float = 0.1
    centre: np.ndarray = field(default_factory=lambda: np.zeros(2))


@dataclass
class _Layout:
    """What a family generator draws: moving objects, the static scene, the timing."""

    things: list[_Thing]
    half: float  # half the simulated duration (s); objects are placed at that time
    windows: int
    background: list[dict[str, Any]]
    props: list[_Thing] = field(default_factory=list)
    ego: np.ndarray = field(default_factory=lambda: np.zeros(3))
    time_offset: float = 0.0


@dataclass(frozen=True)
class _Pinhole:
    """The drawn camera: focal length (px, square pixels), principal point and size."""

    f: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def scale(self) -> float:
        """Sensor width over DAVIS346's: textures and speeds in pixels grow with it."""
        return self.width / 346.0

    def metres(self, pixels: float, depth: float) -> float:
        """A length of ``pixels`` at ``depth`` in metres."""
        return pixels * depth / self.f

    def ray(self, uv: np.ndarray) -> np.ndarray:
        """The normalised image coordinates (x/z, y/z) of pixel ``uv``."""
        return (np.asarray(uv, float) - [self.cx, self.cy]) / self.f

    def image_velocity(self, uv: np.ndarray, depth: float, velocity: np.ndarray) -> np.ndarray:
        """Pixels per second of a point at pixel ``uv`` and ``depth`` moving at ``velocity``."""
        return (
            self.f * velocity[:2] - (np.asarray(uv, float) - [self.cx, self.cy]) * velocity[2]
        ) / depth


Generator = Callable[[np.random.Generator, _Pinhole, "_Tools"], _Layout]

#: The families by name, in the order the yardstick reports them.
FAMILIES: dict[str, Generator] = {}


def _family(name: str) -> Callable[[Generator], Generator]:
    """Register a generator in :data:`FAMILIES` under ``name``."""

    def register(generator: Generator) -> Generator:
        FAMILIES[name] = generator
        return generator

    return register


# --- drawing helpers -----------------------------------------------------------------------


def _unit(angle: float) -> np.ndarray:
    """The image direction at ``angle`` radians (x right, y down)."""
    return np.array([np.cos(angle), np.sin(angle)])


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """The angle (radians) between two 2-D directions."""
    cos = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.arccos(np.clip(cos, -1.0, 1.0)))


def _sideways(direction: np.ndarray, speed: float, depth: float, cam: _Pinhole) -> np.ndarray:
    """The 3-D velocity (m/s, no depth component) of ``speed`` px/s along ``direction`` at
    ``depth``."""
    return np.append(direction / np.linalg.norm(direction) * cam.metres(speed, depth), 0.0)


def _texture(thing: _Thing, cam: _Pinhole) -> dict[str, Any]:
    """A two-octave value-noise texture whose lattice is ``thing.cell`` px at its depth."""
    low, high = thing.contrast
    cell = cam.metres(thing.cell, thing.depth)
    return {"kind": "noise", "cell": cell, "low": low, "high": high, "octaves": 2}


class _Tools:
    """The draws every family shares, on one generator (so a family is one seeded stream)."""

    def __init__(self, rng: np.random.Generator, cam: _Pinhole, threshold: float) -> None:
        self.rng, self.cam, self.threshold = rng, cam, threshold

    def speed(self) -> float:
        """The fastest image speed (px/s): 100-300 px/s on a DAVIS346, more on larger sensors."""
        return float(self.rng.uniform(100.0, 300.0) * self.cam.scale)

    def displacement(self, low: float = 8.0, high: float = 20.0) -> float:
        """How far the fastest motion moves per window (px): the window's length."""
        return float(self.rng.uniform(low, high))

    def windows(self) -> int:
        """Two or three windows (three or four depth maps)."""
        return int(self.rng.integers(2, 4))

    def contrast(
        self, low: tuple[float, float] = (0.05, 0.3), spread: tuple[float, float] = (0.3, 0.7)
    ) -> tuple[float, float]:
        """A texture's (low, high) reflectance: a ``spread`` above a dark ``low`` level."""
        lo = float(self.rng.uniform(*low))
        return lo, float(min(lo + self.rng.uniform(*spread), 1.0))

    def cell(self, low: float = 4.0, high: float = 8.0) -> float:
        """A texture lattice in pixels, scaled with the sensor (the same world detail)."""
        return float(self.rng.uniform(low, high) * self.cam.scale)

    def size(self, low: float, high: float) -> np.ndarray:
        """A box's (w, h) in pixels: w a share of the sensor's width, h = w x 0.6-1.5."""
        w = self.rng.uniform(low, high) * self.cam.width
        return np.array([w, w * self.rng.uniform(0.6, 1.5)])

    def thing(self, name: str, size: np.ndarray, depth: float, velocity: np.ndarray) -> _Thing:
        """A textured box with a thickness of 10-40 % of its width."""
        width = self.cam.metres(float(size[0]), depth)
        return _Thing(
            name,
            size,
            depth,
            velocity,
            self.cell(),
            self.contrast(),
            thickness=float(width * self.rng.uniform(0.1, 0.4)),
        )

    def depths(self, n: int, first: tuple[float, float], ratio: tuple[float, float]) -> list[float]:
        """``n`` depths, the nearest drawn in ``first`` and each next one ``ratio`` farther,
        in random order (so the nearest is not always the first object)."""
        depths = [float(self.rng.uniform(*first))]
        for _ in range(n - 1):
            depths.append(depths[-1] * float(self.rng.uniform(*ratio)))
        return [depths[i] for i in self.rng.permutation(n)]

    def static_background(self, things: list[_Thing]) -> list[dict[str, Any]]:
        """One low-contrast plane 1.5-3x behind the farthest object (a static camera's
        background: it shows only where objects uncover it)."""
        far = max(t.depth + t.thickness for t in things) * float(self.rng.uniform(1.5, 3.0))
        wall = _Thing(
            "background",
            np.ones(2),
            far,
            np.zeros(3),
            self.cell(5.0, 10.0),
            self.contrast((0.2, 0.4)),
        )
        return [_plane("background", [0.0, 0.0, 1.0], [0.0, 0.0, far], _texture(wall, self.cam))]

    def place(
        self,
        things: list[_Thing],
        half: float,
        *,
        occlude: bool = False,
        backdrop: np.ndarray | None = None,
    ) -> None:
        """Centre each thing (at the middle of the recording) so that its path stays on the
        sensor and, unless ``occlude``, clear of the others; with ``occlude`` at least one
        pair overlaps at some time. With a ``backdrop`` (the static scene's depth map at the
        middle) each thing is also moved to 50-85 % of the backdrop's depth where it is
        drawn (its size in metres kept) and must stay in front of it (a moving camera's
        facades and props). Redraws up to 300 times, then keeps the last draw."""
        cam = self.cam
        low = np.array([0.15 * cam.width, 0.15 * cam.height])
        high = np.array([0.85 * cam.width, 0.85 * cam.height])
        for _ in range(300):
            for thing in things:
                thing.centre = self.rng.uniform(low, high)
                if backdrop is not None:
                    self._stand_before(thing, backdrop)
            if _paths_fit(things, cam, half, occlude) and _in_front(things, cam, backdrop):
                return

    def _stand_before(self, thing: _Thing, backdrop: np.ndarray) -> None:
        """Move ``thing`` to 50-85 % of the backdrop's depth at its centre (at least 1 m, and
        no nearer than keeps it within 25 % of the sensor's width and half its height), its
        size in metres kept."""
        cam = self.cam
        u, v = np.clip(thing.centre.astype(int), 0, [cam.width - 1, cam.height - 1])
        metres = thing.size * thing.depth / cam.f
        fits = cam.f * max(metres[0] / (0.25 * cam.width), metres[1] / (0.5 * cam.height))
        depth = max(float(backdrop[v, u]) * float(self.rng.uniform(0.5, 0.85)), fits, 1.0)
        thing.size, thing.depth = metres * cam.f / depth, depth


def _plane(name: str, normal: list[float], point: list[float], texture: dict) -> dict[str, Any]:
    """A background plane mapping."""
    return {"name": name, "normal": normal, "point": point, "texture": texture}


def _image_box(thing: _Thing, cam: _Pinhole, dt: float) -> np.ndarray:
    """The thing's front face in the image ``dt`` s after the middle: (u0, v0, u1, v1)."""
    x, y = cam.ray(thing.centre) * thing.depth
    centre = np.array([x, y, thing.depth]) + thing.velocity * dt
    depth = max(centre[2], 1e-3)
    uv = cam.f * centre[:2] / depth + [cam.cx, cam.cy]
    half = thing.size / 2 * thing.depth / depth
    return np.concatenate([uv - half, uv + half])


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two image boxes (u0, v0, u1, v1) overlap."""
    return bool(a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3])


def _in_front(things: list[_Thing], cam: _Pinhole, backdrop: np.ndarray | None) -> bool:
    """Whether every thing is nearer than the ``backdrop`` depth map (None: no check) at
    its centre and at its box's corners, at the middle of the recording."""
    if backdrop is None:
        return True
    for thing in things:
        box = _image_box(thing, cam, 0.0)
        us = np.clip([box[0], box[2], (box[0] + box[2]) / 2], 0, cam.width - 1).astype(int)
        vs = np.clip([box[1], box[3], (box[1] + box[3]) / 2], 0, cam.height - 1).astype(int)
        if np.any(backdrop[np.ix_(vs, us)] <= thing.depth + thing.thickness):
            return False
    return True


def _paths_fit(things: list[_Thing], cam: _Pinhole, half: float, occlude: bool) -> bool:
    """Every centre stays inside the sensor's middle 90 %; the boxes overlap (``occlude``)
    or not."""
    times = np.linspace(-half, half, 9)
    boxes = [[_image_box(t, cam, dt) for dt in times] for t in things]
    for path in boxes:
        for box in (path[0], path[-1]):
            u, v = (box[:2] + box[2:]) / 2
            if not (0.05 * cam.width < u < 0.95 * cam.width):
                return False
            if not (0.05 * cam.height < v < 0.95 * cam.height):
                return False
    crossed = any(
        _overlap(boxes[i][k], boxes[j][k])
        for i in range(len(things))
        for j in range(i + 1, len(things))
        for k in range(len(times))
    )
    return crossed if occlude else not crossed


def _fastest(cam: _Pinhole, things: list[_Thing]) -> float:
    """The largest image speed (px/s) of the things, taken at the image centre."""
    middle = np.array([cam.cx, cam.cy])
    return max(
        float(np.linalg.norm(cam.image_velocity(middle, t.depth, t.velocity))) for t in things
    )


def _timing(tools: _Tools, things: list[_Thing], displacement: float, windows: int) -> float:
    """Half the duration such that the fastest thing moves ``displacement`` px per window."""
    return 0.5 * windows * displacement / _fastest(tools.cam, things)


def _distinct(velocities: list[np.ndarray], share: float) -> bool:
    """Whether every two velocities differ by at least ``share`` of the larger speed."""
    return all(
        np.linalg.norm(a - b) >= share * max(np.linalg.norm(a), np.linalg.norm(b))
        for i, a in enumerate(velocities)
        for b in velocities[i + 1 :]
    )


# --- the families --------------------------------------------------------------------------


@_family("opposite")
def _opposite(rng: np.random.Generator, cam: _Pinhole, tools: _Tools) -> _Layout:
    """Two objects whose image directions differ by more than 90 degrees."""
    first = rng.uniform(0, 2 * np.pi)
    second = first + rng.choice([-1.0, 1.0]) * rng.uniform(np.pi / 2 + 0.05, np.pi)
    top = tools.speed()
    speeds = [top, top * rng.uniform(0.5, 1.0)]
    things = []
    for i, (angle, speed) in enumerate(zip((first, second), speeds, strict=True)):
        depth = float(rng.uniform(0.8, 4.0))
        velocity = _sideways(_unit(angle), speed, depth, cam)
        things.append(tools.thing(f"object {i + 1}", tools.size(0.12, 0.25), depth, velocity))
    return _static_layout(tools, things)


@_family("same_direction")
def _same_direction(rng: np.random.Generator, cam: _Pinhole, tools: _Tools) -> _Layout:
    """Two or three objects within 20 degrees of one image direction, image speeds 1.3-3x
    apart (every pair), at different depths, with 3-D speeds at least 25 % apart."""
    n = int(rng.integers(2, 4))
    base = rng.uniform(0, 2 * np.pi)
    speed = tools.speed()
    ratios = [float(rng.uniform(1.3, 3.0 / 1.3))]
    if n == 3:
        ratios.append(float(rng.uniform(1.3, 3.0 / ratios[0])))
    speeds = [speed / float(np.prod(ratios[:i])) for i in range(n)]
    angles = base + rng.uniform(-np.radians(10), np.radians(10), n)
    for _ in range(100):
        depths = tools.depths(n, (0.8, 2.0), (1.25, 2.0))
        velocities = [
            _sideways(_unit(a), s, z, cam) for a, s, z in zip(angles, speeds, depths, strict=True)
        ]
        if _distinct(velocities, 0.25):
            break
    things = [
        tools.thing(f"object {i + 1}", tools.size(0.1, 0.2), z, v)
        for i, (z, v) in enumerate(zip(depths, velocities, strict=True))
    ]
    slowest = max(speeds) / min(speeds)
    return _static_layout(
        tools, things, displacement=min(max(tools.displacement(), 4 * slowest), 36)
    )


@_family("equal_motion")
def _equal_motion(rng: np.random.Generator, cam: _Pinhole, tools: _Tools) -> _Layout:
    """Two or three objects at different depths sharing one 3-D velocity (one motion whose
    image speed differs by depth), and one independent object."""
    n = int(rng.integers(2, 4))
    depths = sorted(tools.depths(n, (0.8, 1.5), (1.6, 2.2)))
    angle = rng.uniform(0, 2 * np.pi)
    shared = _sideways(_unit(angle), tools.speed(), depths[0], cam)
    shared[2] = rng.uniform(-0.1, 0.1) * np.linalg.norm(shared)
    things = [
        tools.thing(f"shared motion {i + 1}", tools.size(0.1, 0.2), z, shared)
        for i, z in enumerate(depths)
    ]
    other_angle = angle + rng.choice([-1.0, 1.0]) * rng.uniform(np.radians(60), np.pi)
    depth = float(rng.uniform(0.8, 4.0))
    speed = rng.uniform(0.5, 1.0) * cam.f * np.linalg.norm(shared[:2]) / depths[0]
    velocity = _sideways(_unit(other_angle), speed, depth, cam)
    things.append(tools.thing("independent", tools.size(0.1, 0.2), depth, velocity))
    spread = depths[-1] / depths[0]
    return _static_layout(
        tools, things, displacement=min(max(tools.displacement(), 4 * spread), 36)
    )


@_family("looming")
def _looming(rng: np.random.Generator, cam: _Pinhole, tools: _Tools) -> _Layout:
    """One object moving mostly along the optical axis (approaching or receding: its depth
    changes 5-12 % per window), one or two others sideways."""
    others = []
    speed = tools.speed()
    for i in range(int(rng.integers(1, 3))):
        depth = float(rng.uniform(0.8, 4.0))
        v = _sideways(_unit(rng.uniform(0, 2 * np.pi)), speed * rng.uniform(0.5, 1.0), depth, cam)
        others.append(tools.thing(f"sideways {i + 1}", tools.size(0.1, 0.2), depth, v))
    displacement, windows = tools.displacement(), tools.windows()
    half = 0.5 * windows * displacement / speed  # the sideways objects set the window
    depth = float(rng.uniform(1.0, 3.0))
    change = rng.uniform(0.05, 0.12) * rng.choice([-1.0, 1.0])  # per window; < 0 approaches
    vz = change * depth / (2 * half / windows)
    lateral = _unit(rng.uniform(0, 2 * np.pi)) * abs(vz) * rng.uniform(0.0, 0.3)
    looming = tools.thing("looming", tools.size(0.18, 0.3), depth, np.append(lateral, vz))
    things = [looming, *others]
    tools.place(things, half)
    return _Layout(things, half, windows, tools.static_background(things))


@_family("many")
def _many(rng: np.random.Generator, cam: _Pinhole, tools: _Tools) -> _Layout:
    """Three or four motions at different depths whose paths cross (occlusions)."""
    n = int(rng.integers(3, 5))
    speed = tools.speed()
    for _ in range(100):
        angles = rng.uniform(0, 2 * np.pi, n)
        speeds = speed * np.r_[1.0, rng.uniform(0.4, 1.0, n - 1)]
        images = [_unit(a) * s for a, s in zip(angles, speeds, strict=True)]
        if _distinct(images, 0.4):
            break
    depths = tools.depths(n, (0.8, 1.5), (1.15, 1.6))
    things = [
        tools.thing(
            f"object {i + 1}", tools.size(0.12, 0.22), z, _sideways(d, np.linalg.norm(d), z, cam)
        )
        for i, (z, d) in enumerate(zip(depths, images, strict=True))
    ]
    windows = tools.windows()
    half = 0.5 * windows * tools.displacement() / speed
    tools.place(things, half, occlude=True)
    return _Layout(things, half, windows, tools.static_background(things))


@_family("small_object")
def _small_object(rng: np.random.Generator, cam: _Pinhole, tools: _Tools) -> _Layout:
    """A small object holding 2-5 % of the events beside a large one (sized from the
    event rates of a short simulation, :func:`_pilot_rates`)."""
    speed = tools.speed()
    angle = rng.uniform(0, 2 * np.pi)
    depth = float(rng.uniform(1.0, 3.0))
    large = tools.thing(
        "large", tools.size(0.2, 0.35), depth, _sideways(_unit(angle), speed, depth, cam)
    )
    small_angle = angle + rng.choice([-1.0, 1.0]) * rng.uniform(np.radians(45), np.pi)
    small_speed = speed * rng.uniform(0.5, 1.0)
    depth = float(rng.uniform(0.8, 4.0))
    share = float(rng.uniform(0.02, 0.05))
    area = share / (1 - share) * np.prod(large.size) * speed / small_speed
    aspect = rng.uniform(0.7, 1.4)
    size = np.array([np.sqrt(area / aspect), np.sqrt(area * aspect)])
    small = tools.thing(
        "small", size, depth, _sideways(_unit(small_angle), small_speed, depth, cam)
    )
    layout = _static_layout(tools, [large, small])
    for _ in range(2):  # the rates of the drawn scene, and the small box rescaled to the share
        rates = _pilot_rates(tools, layout)
        predicted = rates.get(2, 0.0) / max(sum(rates.values()), 1e-12)
        small.size = small.size * np.sqrt(share / max(predicted, 1e-3))
    tools.place(layout.things, layout.half)
    return layout


def _ego_layout(
    tools: _Tools,
    ego: np.ndarray,
    background: list[dict],
    props: list[_Thing],
    displacement: float,
) -> _Layout:
    """A moving camera's layout: the static scene's median image speed (a render of it)
    sets the window; one or two independent boxes (0.3-0.7 m wide, 0.4-1.2 m tall: bins,
    bicycles, dogs) move across it in front of the static scene (:meth:`_Tools.place`),
    every two motions (the static scene's among them) 25 % apart as in ``same_direction``;
    one holding under :data:`MIN_EGO_SHARE` of a pilot simulation's events is brought
    nearer (at most to a quarter of the sensor wide, half of it tall, and 1 m away)."""
    rng, cam = tools.rng, tools.cam
    speed, backdrop = _static_view(_probe(tools, _Layout([], 0.0, 1, background, props, ego)))
    windows = tools.windows()
    half = 0.5 * windows * displacement / speed
    things: list[_Thing] = []
    for i in range(int(rng.integers(1, 3))):
        metres = np.array([rng.uniform(0.3, 0.7), rng.uniform(0.4, 1.2)])
        depth = 3.0  # placeholder: place() stands it before the static scene
        motions = [-ego] + [t.velocity for t in things]
        world = ego.copy()
        # it must move in the image too, and apart from every motion drawn before it
        while np.linalg.norm(world - ego) < 0.5 or not _distinct([*motions, world - ego], 0.25):
            world = np.array(
                [rng.choice([-1.0, 1.0]) * rng.uniform(0.6, 1.8), 0.0, rng.uniform(-0.3, 0.3)]
            )
        thing = tools.thing(f"object {i + 1}", metres * cam.f / depth, depth, world - ego)
        thing.cell, thing.contrast = _static_cell(tools), tools.contrast((0.1, 0.3), (0.3, 0.6))
        things.append(thing)
    tools.place(things, half, backdrop=backdrop)
    layout = _Layout(things, half, windows, background, props, ego)
    rates = _pilot_rates(tools, layout)  # an object must hold a share a user would see
    total = max(sum(rates.values()), 1e-12)
    limit = np.array([0.25 * cam.width, 0.5 * cam.height])
    for k, thing in enumerate(things, start=1):
        share = rates.get(k, 0.0) / total
        if share < MIN_EGO_SHARE:  # nearer (still in front), so larger and faster in view
            factor = np.sqrt(MIN_EGO_SHARE / max(share, 1e-3))
            factor = min(factor, float(np.min(limit / thing.size)), thing.depth / 1.0)
            thing.size, thing.depth = thing.size * factor, thing.depth / factor
    return layout


def _props(tools: _Tools, n: int, depth: tuple[float, float], ego: np.ndarray) -> list[_Thing]:
    """``n`` static boxes (0.3-1.2 m wide, 0.5-2 m tall) at random places in the view, at
    most a quarter of the sensor wide and half of it tall."""
    rng, cam = tools.rng, tools.cam
    props = []
    for i in range(n):
        metres = np.array([rng.uniform(0.3, 1.2), rng.uniform(0.5, 2.0)])
        fits = cam.f * max(metres[0] / (0.25 * cam.width), metres[1] / (0.5 * cam.height))
        z = max(float(rng.uniform(*depth)), fits)
        prop = tools.thing(f"prop {i + 1}", metres * cam.f / z, z, -ego)
        prop.cell = _static_cell(tools)
        prop.contrast = tools.contrast((0.1, 0.3), (0.3, 0.6))
        prop.centre = rng.uniform(
            [0.1 * cam.width, 0.2 * cam.height], [0.9 * cam.width, 0.8 * cam.height]
        )
        props.append(prop)
    return props


def _static_cell(tools: _Tools) -> float:
    """A static surface's texture lattice (px at its depth): coarser than an object's, as
    a moving camera sees every static pixel move and a street has large plain areas."""
    return tools.cell(6.0, 12.0)


def _wall_texture(tools: _Tools, far: float) -> dict[str, Any]:
    """A static plane's texture: a lattice of 4-7 px at ``far`` (no aliasing at its far end,
    coarse where it is near)."""
    cam = tools.cam
    low, high = tools.contrast((0.1, 0.3), (0.3, 0.6))
    cell = cam.metres(tools.rng.uniform(4.0, 7.0) * cam.scale, far)
    return {"kind": "noise", "cell": cell, "low": low, "high": high, "octaves": 1}


#: The least share of the events an independent object of a moving-camera family holds.
MIN_EGO_SHARE = 0.05


@_family("ego_sideways")
def _ego_sideways(rng: np.random.Generator, cam: _Pinhole, tools: _Tools) -> _Layout:
    """A camera moving sideways (0.5-2 m/s) along a street: a facade seen at 30-50 degrees,
    3-5 m away at its nearest, receding to a back wall at 10-12 m, a floor, 2-4 props at
    1.5-6 m: a static scene spread over 1.5-10 m, one motion; one or two independent
    objects."""
    speed = rng.uniform(0.5, 2.0)
    ego = np.array([rng.choice([-1.0, 1.0]), rng.uniform(-0.1, 0.1), rng.uniform(-0.2, 0.2)])
    ego *= speed
    far = float(rng.uniform(10.0, 12.0))
    angle = rng.choice([-1.0, 1.0]) * rng.uniform(np.radians(30), np.radians(50))
    nearest = float(rng.uniform(3.0, 5.0))
    edge = (cam.width / 2) / cam.f  # the image border's ray, on the facade's near side
    normal = [float(np.sin(angle)), 0.0, float(np.cos(angle))]
    depth_on_axis = nearest * (1 + edge * abs(np.tan(angle)))
    floor = float(rng.uniform(1.0, 1.6))
    background = [
        _plane("facade", normal, [0.0, 0.0, depth_on_axis], _wall_texture(tools, far)),
        _plane("back wall", [0.0, 0.0, 1.0], [0.0, 0.0, far], _wall_texture(tools, far)),
        _plane("floor", [0.0, 1.0, 0.0], [0.0, floor, 0.0], _wall_texture(tools, far)),
    ]
    props = _props(tools, int(rng.integers(2, 5)), (1.5, 6.0), ego)
    return _ego_layout(tools, ego, background, props, tools.displacement(2.0, 6.0))


@_family("ego_forward")
def _ego_forward(rng: np.random.Generator, cam: _Pinhole, tools: _Tools) -> _Layout:
    """A camera walking forward (0.8-2 m/s) down a corridor or street (walls 1.2-2.5 m to
    the sides, a floor, sometimes a ceiling, an end wall at 9-12 m, 1-3 props at 1.8-6 m),
    one motion; one or two independent objects crossing it."""
    forward = rng.uniform(0.8, 2.0)
    ego = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.05, 0.05), 1.0]) * forward
    end = float(rng.uniform(9.0, 12.0))
    left, right = -rng.uniform(1.2, 2.5), rng.uniform(1.2, 2.5)
    floor = rng.uniform(1.1, 1.6)
    background = [
        _plane("left wall", [1.0, 0.0, 0.0], [left, 0.0, 0.0], _wall_texture(tools, end)),
        _plane("right wall", [1.0, 0.0, 0.0], [right, 0.0, 0.0], _wall_texture(tools, end)),
        _plane("floor", [0.0, 1.0, 0.0], [0.0, floor, 0.0], _wall_texture(tools, end)),
        _plane("end wall", [0.0, 0.0, 1.0], [0.0, 0.0, end], _wall_texture(tools, end)),
    ]
    if rng.random() < 0.5:
        ceiling = -rng.uniform(1.2, 2.2)
        background.append(
            _plane("ceiling", [0.0, 1.0, 0.0], [0.0, ceiling, 0.0], _wall_texture(tools, end))
        )
    props = _props(tools, int(rng.integers(1, 4)), (1.8, 6.0), ego)
    return _ego_layout(tools, ego, background, props, tools.displacement(1.5, 4.0))


@_family("long")
def _long(rng: np.random.Generator, cam: _Pinhole, tools: _Tools) -> _Layout:
    """100,000-1,000,000 events between only two depth maps (one window), two large objects
    on a VGA or HD sensor, timestamps starting anywhere from 1 s to 2e9 s (a Unix time)."""
    speed = tools.speed()
    first = rng.uniform(0, 2 * np.pi)
    angles = (first, first + rng.choice([-1.0, 1.0]) * rng.uniform(np.radians(60), np.pi))
    things = []
    for i, angle in enumerate(angles):
        depth = float(rng.uniform(1.0, 4.0))
        v = _sideways(_unit(angle), speed * (1.0 if i == 0 else rng.uniform(0.5, 1.0)), depth, cam)
        thing = tools.thing(f"object {i + 1}", tools.size(0.25, 0.4), depth, v)
        thing.cell = tools.cell(2.0, 3.5)
        things.append(thing)
    target = float(np.exp(rng.uniform(np.log(1e5), np.log(1e6))))
    offset = float(np.exp(rng.uniform(0.0, np.log(2e9))))
    layout = _static_layout(tools, things, windows=1)
    rate = sum(_pilot_rates(tools, layout).values())
    layout.half = 0.5 * target / max(rate, 1.0)
    tools.place(things, layout.half)
    layout.time_offset = offset
    return layout


def _static_layout(
    tools: _Tools,
    things: list[_Thing],
    *,
    displacement: float | None = None,
    windows: int | None = None,
) -> _Layout:
    """A static camera's layout: the window from the fastest thing and ``displacement``
    (drawn when None), things placed clear of each other, a plane behind them."""
    windows = tools.windows() if windows is None else windows
    displacement = tools.displacement() if displacement is None else displacement
    half = _timing(tools, things, displacement, windows)
    tools.place(things, half)
    return _Layout(things, half, windows, tools.static_background(things))


# --- scenes, rates and the simulation -------------------------------------------------------


def _body(thing: _Thing, cam: _Pinhole, half: float, ego: np.ndarray, moving: bool) -> dict:
    """The box mapping of a thing: centred at its drawn place at ``half`` s, moving with
    its relative velocity (world velocity = relative + ego); a prop has no velocity."""
    w, h = (cam.metres(float(s), thing.depth) for s in thing.size)
    x, y = cam.ray(thing.centre) * thing.depth
    middle = np.array([x, y, thing.depth + thing.thickness / 2])
    relative = thing.velocity if moving else -ego
    body = {
        "name": thing.name,
        "shape": "box",
        "size": [float(w), float(h), float(thing.thickness)],
        "position": (middle - relative * half).tolist(),
        "texture": _texture(thing, cam),
    }
    if moving:
        body["velocity"] = (thing.velocity + ego).tolist()
    return body


def _scene_mapping(
    name: str,
    cam: _Pinhole,
    layout: _Layout,
    modifiers: Modifiers,
    threshold: float,
    density: float = 1.0,
) -> dict[str, Any]:
    """The ``conf/scene`` mapping of a layout, with pixels of contrast threshold ``threshold``;
    the sensor's thresholds and refractory period divided by ``density``."""
    scale = cam.scale
    return {
        "name": name,
        "kind": "simulated",
        "description": f"drawn by the {name.split('-')[0]} family",
        "camera": {
            "width": cam.width,
            "height": cam.height,
            "fx": cam.f,
            "fy": cam.f,
            "cx": cam.cx,
            "cy": cam.cy,
            "ego_velocity": layout.ego.tolist(),
        },
        "duration": max(2 * layout.half, 1e-6),
        "sensor": {
            "threshold_mean": threshold / density,
            "threshold_std": 0.03 / density,
            "threshold_min": 0.05 / density,
            "refractory": 1.0e-4 / density,
            "noise_rate": 0.05,
            "log_eps": 0.001,
        },
        "render": {"max_pixel_step": 0.2},
        "lighting": {"gain": 1.0, "gamma": 1.0},
        "depth_error": {
            "sigma": modifiers.depth_flicker,
            "correlation": 40.0 * scale,
            "holes": modifiers.holes,
            "hole_size": 15.0 * scale,
            "scale": 1.0,
            "shared": False,
            "bias": modifiers.depth_bias,
            "seed_offset": 0,
        },
        "background": [
            *layout.background,
            *(_body(p, cam, layout.half, layout.ego, False) for p in layout.props),
        ],
        "objects": [_body(t, cam, layout.half, layout.ego, True) for t in layout.things],
    }


def _flow(renderer: Renderer, depth: np.ndarray, label: np.ndarray) -> np.ndarray:
    """Each pixel's image velocity (H x W x 2, px/s) from its surface's relative velocity."""
    cam = renderer.scene.camera
    v = renderer.velocities[label]
    du = cam.fx * (v[..., 0] - renderer.rx[None, :] * v[..., 2]) / depth
    dv = cam.fy * (v[..., 1] - renderer.ry[:, None] * v[..., 2]) / depth
    return np.stack([du, dv], axis=-1)


def _probe(tools: _Tools, layout: _Layout, duration: float = 0.0) -> dict[str, Any]:
    """The scene mapping of ``layout`` starting as it is at the middle of the recording and
    lasting ``duration`` (a pilot simulation, or a single render)."""
    probe = replace(layout, half=0.0)
    scene = _scene_mapping("probe", tools.cam, probe, Modifiers(), tools.threshold)
    return {**scene, "duration": max(duration, 1e-6)}


def _pilot_rates(tools: _Tools, layout: _Layout) -> dict[int, float]:
    """Events per second of each ground-truth id, measured on a short simulation from the
    middle of the recording (the fastest thing moves 16 px; the first 8 px are left out,
    while the pixels' reference levels settle). A render's gradients overestimate it 2-3x:
    texture wiggles smaller than the contrast threshold emit nothing."""
    duration = 16.0 / _fastest(tools.cam, layout.things)
    pilot = simulate_scene(_probe(tools, layout, duration), seed=0, max_events=None)
    assert pilot.ground_truth is not None  # the simulator always gives it
    late = pilot.events.t >= duration / 2
    ids, counts = np.unique(pilot.ground_truth.labels[late], return_counts=True)
    return {int(i): 2 * float(c) / duration for i, c in zip(ids, counts, strict=True) if i >= 0}


def _static_view(scene: dict[str, Any]) -> tuple[float, np.ndarray]:
    """For a moving camera: the static scene's median image speed (px/s) and its depth map
    (H x W, m) at t = 0."""
    parsed = parse_scene(scene)
    renderer = Renderer(parsed, texture_keys(parsed, 0))
    frame = renderer.render(0.0)
    flow = _flow(renderer, frame.depth, frame.label)
    return float(np.median(np.hypot(flow[..., 0], flow[..., 1]))), frame.depth


def _draw_modifiers(rng: np.random.Generator) -> Modifiers:
    """Each modifier 0 with probability one half, else uniform up to its limit."""
    values = {
        name: float(rng.uniform(0, limit)) if rng.random() < 0.5 else 0.0
        for name, limit in MODIFIER_LIMITS.items()
    }
    return Modifiers(**values)


def _generator(family: str, seed: int) -> np.random.Generator:
    """The family's stream for ``seed``: families with the same seed draw independently."""
    return np.random.default_rng([zlib.crc32(family.encode()), seed])


def _check_family(family: str) -> None:
    """A one-line error naming the known families."""
    if family not in FAMILIES:
        raise ValueError(f"unknown scene family {family!r}; choose from {', '.join(FAMILIES)}")


def _motion_count(layout: _Layout) -> int:
    """Distinct 3-D motions: the objects' relative velocities, plus the static scene's when
    the camera moves."""
    velocities = [t.velocity for t in layout.things]
    if np.any(layout.ego):
        velocities.append(-layout.ego)
    distinct: list[np.ndarray] = []
    for v in velocities:
        if not any(np.allclose(v, d, rtol=0, atol=1e-9) for d in distinct):
            distinct.append(v)
    return len(distinct)


def draw_scene(family: str, seed: int, density: float = 1.0, **fixed: float) -> FamilyScene:
    """Draw one scene of ``family`` from ``seed`` (deterministic); ``fixed`` sets modifiers
    (:class:`Modifiers` field names) instead of drawing them, the rest of the draw unchanged.

    ``density`` (> 0) records the same scene more densely: the sensor's contrast
    thresholds and refractory period are divided by it, as a more sensitive sensor would
    (a texture's weak edges start firing too: 3 gave ``ego_sideways`` seed 2 11.7 times the
    events); the draw is otherwise unchanged."""
    _check_family(family)
    if not isinstance(seed, int | np.integer) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    if not (isinstance(density, int | float) and np.isfinite(density) and density > 0):
        raise ValueError(f"density must be a finite number > 0, got {density!r}")
    rng = _generator(family, int(seed))
    width, height = SENSORS[int(rng.integers(len(SENSORS)))]
    if family == "long":  # a million events need room to move on the sensor
        width, height = SENSORS[int(rng.integers(2, len(SENSORS)))]
    f = width * float(rng.uniform(0.75, 1.1))
    cam = _Pinhole(f, (width - 1) / 2, (height - 1) / 2, width, height)
    tools = _Tools(rng, cam, float(rng.uniform(0.15, 0.3)))
    layout = FAMILIES[family](rng, cam, tools)
    modifiers = replace(_draw_modifiers(rng), **fixed)
    name = f"{family}-{seed}"
    scene = _scene_mapping(name, cam, layout, modifiers, tools.threshold, float(density))
    summary = {
        "sensor": f"{width}x{height}",
        "objects": len(layout.things),
        "window_ms": round(2e3 * layout.half / layout.windows, 3),
    }
    return FamilyScene(
        family,
        int(seed),
        scene,
        layout.windows,
        _motion_count(layout),
        modifiers,
        layout.time_offset,
        summary,
    )


def merge_equal_motions(truth: GroundTruth) -> GroundTruth:
    """Ground truth with one id per 3-D motion: ids whose velocities are equal take the
    smallest of them (names joined), since a segmentation by motion cannot tell them apart."""
    ids = sorted(truth.motions)
    target = {}
    for i in ids:
        same = [
            j
            for j in ids
            if j <= i and np.allclose(truth.motions[j], truth.motions[i], rtol=0, atol=1e-9)
        ]
        target[i] = same[0]
    labels = truth.labels.copy()
    for i, j in target.items():
        labels[truth.labels == i] = j
    kept = sorted(set(target.values()))
    names = {k: " + ".join(truth.names.get(i, str(i)) for i in ids if target[i] == k) for k in kept}
    return GroundTruth(labels, {k: truth.motions[k] for k in kept}, names)


def with_noise(recording: Recording, share: float, rng: np.random.Generator) -> Recording:
    """The recording with background-activity events added (label -1) so that they are
    ``share`` of all events: uniform over the pixels and the events' time span."""
    events = recording.events
    if share <= 0 or not len(events):
        return recording
    n = round(share / (1 - share) * len(events))
    t = np.concatenate([events.t, rng.uniform(events.t[0], events.t[-1], n)])
    order = np.argsort(t, kind="stable")
    noisy = EventStream(
        np.concatenate([events.x, rng.integers(0, events.width, n)])[order],
        np.concatenate([events.y, rng.integers(0, events.height, n)])[order],
        t[order],
        np.concatenate([events.p, rng.choice(np.array([-1, 1], np.int8), n)])[order],
        events.width,
        events.height,
        source=events.source,
    )
    truth = recording.ground_truth
    if truth is not None:
        labels = np.concatenate([truth.labels, np.full(n, -1)])[order]
        truth = replace(truth, labels=labels)
    return replace(recording, events=noisy, ground_truth=truth)


def with_time_offset(recording: Recording, offset: float) -> Recording:
    """The recording with ``offset`` seconds added to every timestamp (events, depth maps,
    keyframes), as a camera's clock that did not start at zero."""
    if offset == 0:
        return recording
    events = replace(recording.events, t=recording.events.t + offset)
    maps = tuple(DepthMap(d.t + offset, d.depth, d.source) for d in recording.depth_maps)
    frames = tuple(Keyframe(k.t + offset, k.image, k.source) for k in recording.keyframes)
    return replace(recording, events=events, depth_maps=maps, keyframes=frames)


def simulate_family(family: str | FamilyScene, seed: int = 0, **fixed: float) -> Recording:
    """Simulate a family's scene (a name and ``seed``, or a :class:`FamilyScene`) into a
    Recording: ``windows`` windows of equal event counts, noise added, timestamps offset,
    ground truth with one id per 3-D motion."""
    drawn = family if isinstance(family, FamilyScene) else draw_scene(family, seed, **fixed)
    recording = simulate_scene(drawn.scene, seed=drawn.seed, max_events=None, windows=drawn.windows)
    assert recording.ground_truth is not None  # the simulator always gives it
    recording = replace(recording, ground_truth=merge_equal_motions(recording.ground_truth))
    noise_rng = np.random.default_rng([zlib.crc32(b"noise"), drawn.seed])
    recording = with_noise(recording, drawn.modifiers.noise, noise_rng)
    return with_time_offset(recording, drawn.time_offset)
