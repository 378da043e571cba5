"""Every setting of the method, typed, with its default and its check: one source of truth.

:class:`Settings` holds one frozen dataclass per config section (``window``, ``edpa``,
``denoise``, ``volume``, ``init``, ``clustering``, ``model``, ``objective``, ``depth``).
:func:`settings_from` builds it from a nested mapping (the command line's composed config,
or the keyword settings of :func:`spatialseg.segment`): missing keys take the defaults
below, an unknown key or a value of the wrong type or range raises one ``ValueError`` that
names the key and the fix, before any work starts. The Hydra app registers
:func:`default_tree` as its config's base, so ``conf/config.yaml`` only selects and
overrides; the algorithm reads these objects, never the config dict.

Checks that need a registry (optimiser presets, objectives) look their names up where the
registry lives, so a setting is judged the same wherever it is read.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from spatialseg.checks import integer_setting, is_integer, number_setting, optional_positive

__all__ = [
    "ClusteringSettings",
    "DenoiseSettings",
    "DepthSettings",
    "EdpaSettings",
    "InitSettings",
    "ModelSettings",
    "ObjectiveSettings",
    "PStepAloneSettings",
    "RefitSettings",
    "Settings",
    "TilesSettings",
    "VolumeSettings",
    "WindowSettings",
    "default_tree",
    "settings_from",
    "smoothing",
]

#: A smoothing width in voxels: one number for every axis, or a pair [image, depth].
Sigma = float | tuple[float, float]


def smoothing(value: Sigma, key: str) -> tuple[float, float, float]:
    """A smoothing setting as (x, y, depth) voxels, checked: one number >= 0 for every axis,
    or a pair ``[image, depth]`` (x and y share the first)."""
    parts = [value] if isinstance(value, int | float) else list(value)
    if (
        isinstance(value, bool)
        or len(parts) not in (1, 2)
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in parts)
        or not all(np.isfinite(v) and v >= 0 for v in parts)
    ):
        raise ValueError(
            f"{key} must be a number >= 0 or a pair [image, depth] of them (voxels), got {value!r}"
        )
    return (float(parts[0]), float(parts[0]), float(parts[-1]))


def _check_optimizer_preset(name: str, key: str) -> None:
    """Refuse, in one line naming ``key``, an optimiser preset name nobody defines."""
    import optimizers

    if name not in optimizers.preset_names():
        raise ValueError(
            f"{key}: unknown optimizer {name!r}; choose from {', '.join(optimizers.preset_names())}"
        )


def _in_range(value: float, key: str, low: float, high: float, *, open_low: bool) -> None:
    """Refuse ``value`` outside ``(low, high]`` (``[low, high]`` unless ``open_low``)."""
    if (value <= low if open_low else value < low) or value > high:
        left = "(" if open_low else "["
        raise ValueError(f"{key} must be a number in {left}{low:g}, {high:g}], got {value!r}")


@dataclass(frozen=True)
class WindowSettings:
    """How the events are cut into windows and how windows are run."""

    #: Events per window: a simulated scene gets a depth map every this many events (the
    #: paper's 15,000); depth=constant/ground_plane likewise.
    events: int = 15000
    #: Simulated scenes: windows simulated (events x count in all), so each has neighbours
    #: (recordings from disk keep their own windows); null: the scene's own.
    count: int | None = 3
    #: Neighbouring windows on each side clustered with each window, which keeps the labels
    #: of its own events (longer spans pin velocities down); 0: each window alone.
    context: int = 1
    #: none: windows one after the other, each also started from the one before's
    #: velocities; processes: a local pool; ray: Ray. In parallel, windows are independent.
    parallel: Literal["none", "processes", "ray"] = "none"
    #: Processes or Ray CPUs to start; null: one per core.
    workers: int | None = None

    def __post_init__(self) -> None:
        integer_setting(self.events, "window.events", 1)
        integer_setting(self.count, "window.count", 1, optional=True)
        integer_setting(self.context, "window.context", 0)
        integer_setting(self.workers, "window.workers", 1, optional=True)


@dataclass(frozen=True)
class EdpaSettings:
    """EDPA: each event's depth from the two depth maps around it."""

    #: drop: events without depth are left out (label -1); fill: the median of valid
    #: neighbours within fill_radius.
    unknown_depth: Literal["drop", "fill"] = "drop"
    #: Neighbourhood radius (pixels) for unknown_depth=fill.
    fill_radius: int = 2
    #: Maps differing by more than this share of the nearer depth mark an occlusion edge,
    #: where the event takes the nearer depth; null: always interpolate (the paper).
    edge_ratio: float | None = 0.2

    def __post_init__(self) -> None:
        integer_setting(self.fill_radius, "edpa.fill_radius", 1)
        optional_positive(self.edge_ratio, "edpa.edge_ratio")


@dataclass(frozen=True)
class DenoiseSettings:
    """The background-activity filter: unsupported events are left out of the fit (still
    labelled, from the fitted motions)."""

    enabled: bool = True
    #: Neighbourhood: pixels within this Chebyshev distance, the pixel itself excluded.
    radius: int = 1
    #: s; a neighbour must have fired at most this long before the event.
    window: float = 0.01

    def __post_init__(self) -> None:
        integer_setting(self.radius, "denoise.radius", 1)
        optional_positive(self.window, "denoise.window")


@dataclass(frozen=True)
class VolumeSettings:
    """The volume of warped events: its axes, bins and extent."""

    #: Warp reference time: start (T1) or middle of the window.
    t_ref: Literal["start", "middle"] = "middle"
    #: Grid axes: image (pixels + inverse depth, every depth equally sharp) or metric
    #: (X, Y, Z in metres, the paper's); spatial model only.
    coordinates: Literal["image", "metric"] = "image"
    #: Depth (or inverse-depth) bins over the points' range (spatial model).
    z_bins: int = 16
    #: The depth's relative error: no depth voxel is finer than it at the median depth.
    depth_error: float = 0.1
    #: Grid extent beyond the points' bounding box, fraction per axis.
    margin: float = 0.1
    max_voxels: int = 20_000_000
    #: Storage of points and volumes: float64, or float32 (less memory per event).
    dtype: Literal["float64", "float32"] = "float64"

    def __post_init__(self) -> None:
        integer_setting(self.z_bins, "volume.z_bins", 1)
        number_setting(self.depth_error, "volume.depth_error", 0)
        number_setting(self.margin, "volume.margin", 0)
        integer_setting(self.max_voxels, "volume.max_voxels", 1)


@dataclass(frozen=True)
class TilesSettings:
    """init.method=tiles: each image tile's own contrast maximum, K kept by a greedy cover."""

    #: Tile side, pixels.
    size: int = 16
    #: Tiles with fewer events propose no velocity (their events start unlabelled).
    min_events: int = 30
    #: Optimiser evaluations per tile (the run's optimiser, from zero velocity) and per
    #: re-fit of a chosen velocity.
    evals: int = 30
    #: Re-fit each chosen velocity on its tiles' events, re-assign the tiles.
    rounds: int = 2
    #: An optimiser preset: the local optimiser of the re-fits.
    refit: str = "nlopt_bobyqa"
    #: A tile is explained by a velocity within this share of its own best contrast; the
    #: cover first maximises the events newly explained; null: the graded sum only.
    explained: float | None = 0.85

    def __post_init__(self) -> None:
        integer_setting(self.size, "init.tiles.size", 1)
        integer_setting(self.min_events, "init.tiles.min_events", 1)
        integer_setting(self.evals, "init.tiles.evals", 1)
        integer_setting(self.rounds, "init.tiles.rounds", 0)
        _check_optimizer_preset(self.refit, "init.tiles.refit")
        if self.explained is not None:
            _in_range(self.explained, "init.tiles.explained", 0, 1, open_low=True)


@dataclass(frozen=True)
class InitSettings:
    """Initial motions and memberships (spatialseg.motion_init)."""

    #: tiles, image_flow, time_surface (the paper's 3 planes), or auto: cluster from each
    #: start of ``auto`` and keep the highest total contrast (the previous start's within 5 %
    #: of it: spatialseg.window.kept_run).
    method: str = "auto"
    #: method=auto: the starts tried (each runs the whole clustering); previous: the
    #: preceding window's final velocities (not in a recording's first window); planar: the
    #: planar model's segmentation of the window, lifted to 3-D (the spatial model only).
    auto: tuple[str, ...] = ("image_flow", "tiles", "previous", "planar")
    tiles: TilesSettings = field(default_factory=TilesSettings)
    #: Flow starts: plane-fit neighbourhood radius in cells.
    radius: int = 3
    #: Flow starts: hit cells needed for a plane fit.
    min_points: int = 6
    #: Flow starts: reject plane fits explaining less of the time variance than this.
    min_r2: float = 0.5
    #: Flow starts: reject per-event 3x3 systems worse conditioned than this.
    max_condition: float = 100.0
    #: Flow starts: events sampled for flow estimation.
    max_events: int = 5000
    #: k-means restarts.
    n_init: int = 10

    def __post_init__(self) -> None:
        integer_setting(self.radius, "init.radius", 1)
        integer_setting(self.min_points, "init.min_points", 1)
        number_setting(self.min_r2, "init.min_r2", 0)
        number_setting(self.max_condition, "init.max_condition", 1)
        integer_setting(self.max_events, "init.max_events", 1)
        integer_setting(self.n_init, "init.n_init", 1)


@dataclass(frozen=True)
class PStepAloneSettings:
    """The P-step's smoothing for a window clustered alone (no neighbouring windows), whose
    volumes hold a third of the events: blurred more."""

    sigma: Sigma = 3.0
    stride: int = 2


@dataclass(frozen=True)
class RefitSettings:
    """After the loop, each velocity re-fitted once with the final memberships on the
    events off occlusion edges (their depth is reliable); memberships fixed."""

    #: The local optimiser's budget per cluster; 0: off (the loop's velocities).
    evals: int = 30
    #: An optimiser preset: the refit's local optimiser.
    optimizer: str = "nlopt_bobyqa"
    #: It searches within this share of the search box around the loop's velocity.
    radius: float = 0.1

    def __post_init__(self) -> None:
        integer_setting(self.evals, "clustering.refit.evals", 0, hint="0: off")
        _check_optimizer_preset(self.optimizer, "clustering.refit.optimizer")
        _in_range(self.radius, "clustering.refit.radius", 0, 1, open_low=True)


@dataclass(frozen=True)
class ClusteringSettings:
    """Algorithm 1: the theta-step and P-step loop, its stopping rules and finishing steps."""

    #: Rule 3: iteration limit (10 since session 57, whose SQUAREM steps harden the
    #: memberships further in 10 than the plain P-steps did in 20: docs/method.md).
    max_iterations: int = 10
    #: Rule 1: relative change of total contrast ...
    tol: float = 0.001
    #: ... below tol for this many iterations; and after this many theta-steps in a row
    #: that moved no velocity the loop runs P-steps only (docs/method.md).
    patience: int = 2
    #: Rule 2: stop when the total contrast exceeds this value.
    target: float | None = None
    #: Rule 4: stop when fewer than this share of events change cluster for patience
    #: iterations (memberships settled); null: off.
    label_tol: float | None = None
    #: Optimiser budget per cluster per theta-step (30 until session 41: half of it paid
    #: nothing on the yardstick's dev seeds; docs/method.md, "theta-step budget").
    evals_per_step: int = 15
    #: Fit the motions (starts, loop, refit) on a random sample of at most this many
    #: events per voxel the unwarped events occupy in the grid, and label the others once
    #: at the end; null: fit on every event. 10: about the density the defaults were chosen
    #: at (docs/method.md, "The fit on a sample").
    fit_per_voxel: float | None = 10.0
    #: Theta-step on a random sample of at most this many events (P-step on all); null: all.
    step_events: int | None = 20000
    #: Events on an occlusion edge in the theta-step too; false: the P-step labels them,
    #: velocities ignore them.
    step_edges: bool = True
    #: Search box: motion moves points at most this share of the grid over the window (with
    #: its context windows); an axis a final velocity presses on doubles, up to the whole
    #: grid per window, and the window is clustered again from there.
    max_displacement: float = 0.15
    #: Search box, spatial model: |vz| changes the median depth by at most this share per
    #: window (time to contact >= 1/this windows); null: no cap.
    max_depth_change: float | None = 0.5
    #: flow: from the initial flow clustering; uniform: the paper's 1/K.
    init_memberships: Literal["flow", "uniform"] = "flow"
    #: flow: starting membership of an event's initial cluster.
    init_confidence: float = 0.9
    #: Gaussian smoothing (voxels) of each volume before the P-step samples it; a pair
    #: [image, depth] smooths x, y by the first, depth by the second. Depth is the least
    #: precise coordinate, so a membership leans on it least (docs/method.md, "P-step").
    p_step_sigma: Sigma = (1.5, 4.0)
    #: P-step on a grid this many times coarser in x and y; needs
    #: p_step_sigma >= sqrt((stride^2 - 1) / 3).
    p_step_stride: int = 1
    p_step_alone: PStepAloneSettings = field(default_factory=PStepAloneSettings)
    #: After the refit, one more P-step at the final velocities gives the labels, smoothed
    #: by this ([image, depth] voxels, full grid; rebuilt from every event where it leaves
    #: a cluster wasted); null: the loop's last memberships. A window clustered alone
    #: keeps the loop's (relabelling cost approach 0.94 -> 0.92).
    relabel_sigma: Sigma | None = (1.0, 4.0)
    #: Voxels: in the relabelling, an event whose two likeliest motions move its point less
    #: than about this far apart is weighted by the clusters' shares; null: no prior.
    relabel_prior_scale: float | None = 5.0
    #: n_clusters=auto: at most this many motions per window.
    max_clusters: int = 5
    #: Label -1 when an event's largest membership is below this.
    min_probability: float = 0.0
    #: The labels' Potts smoothness (spatialseg.mrf): the cost, in units of an event's
    #: log-membership, of each pair of space-time neighbours labelled apart (chosen on the
    #: dev split among 0.3, 1 and 3: docs/results.md); 0: each event its likeliest cluster.
    smoothness: float = 3.0
    refit: RefitSettings = field(default_factory=RefitSettings)

    def __post_init__(self) -> None:
        integer_setting(self.max_iterations, "clustering.max_iterations", 1)
        number_setting(self.tol, "clustering.tol", 0)
        integer_setting(self.patience, "clustering.patience", 1)
        number_setting(self.target, "clustering.target", optional=True)
        number_setting(self.label_tol, "clustering.label_tol", 0, optional=True)
        if self.label_tol is not None and self.label_tol >= 1:  # a share of the events
            raise ValueError(
                f"clustering.label_tol must be a number in [0, 1) or null, got {self.label_tol!r}"
            )
        integer_setting(self.evals_per_step, "clustering.evals_per_step", 1)
        optional_positive(self.fit_per_voxel, "clustering.fit_per_voxel")
        integer_setting(self.step_events, "clustering.step_events", 1, optional=True)
        _in_range(self.max_displacement, "clustering.max_displacement", 0, 1, open_low=True)
        optional_positive(self.max_depth_change, "clustering.max_depth_change")
        _in_range(self.init_confidence, "clustering.init_confidence", 0, 1, open_low=True)
        optional_positive(self.relabel_prior_scale, "clustering.relabel_prior_scale")
        integer_setting(self.max_clusters, "clustering.max_clusters", 1)
        _in_range(self.min_probability, "clustering.min_probability", 0, 1, open_low=False)
        number_setting(self.smoothness, "clustering.smoothness", 0)
        for sigma, stride, prefix in (
            (self.p_step_sigma, self.p_step_stride, "clustering.p_step_"),
            (self.p_step_alone.sigma, self.p_step_alone.stride, "clustering.p_step_alone."),
        ):
            _check_p_step(sigma, stride, prefix)
        if self.relabel_sigma is not None:
            smoothing(self.relabel_sigma, "clustering.relabel_sigma")


def _check_p_step(sigma: Sigma, stride: int, prefix: str) -> None:
    """A P-step's smoothing and grid stride, checked together (the stride's tents alone
    blur by ``(stride^2 - 1) / 3`` voxels squared)."""
    from spatialseg.volume import check_p_step_blur

    keys = (f"{prefix}sigma", f"{prefix}stride")
    integer_setting(stride, keys[1], 1)
    check_p_step_blur(smoothing(sigma, keys[0])[0], stride, sigma, keys)


@dataclass(frozen=True)
class ModelSettings:
    """The motion model: spatial (EDPA points, 3-D velocities in m/s) or planar (the image
    plane, 2-D velocities in px/s)."""

    name: Literal["spatial", "planar"] = "spatial"
    #: Voxel size in x, y: spatial, as a multiple of the pixel footprint at the median
    #: depth; planar, in pixels. Null: the model's own (2.0 spatial, 1.0 planar).
    xy_scale: float | None = None

    def __post_init__(self) -> None:
        optional_positive(self.xy_scale, "model.xy_scale")

    @property
    def voxel_scale(self) -> float:
        """``xy_scale``, or the model's own default."""
        if self.xy_scale is not None:
            return float(self.xy_scale)
        return 2.0 if self.name == "spatial" else 1.0


@dataclass(frozen=True)
class ObjectiveSettings:
    """The contrast of a volume of warped events (spatialseg.objectives' registry)."""

    #: variance (the paper's) or sum_of_squares, or any registered objective.
    name: str = "variance"
    #: Gaussian blur of the volume before the objective, in voxels (0: off).
    blur_sigma: float = 0.0

    def __post_init__(self) -> None:
        from spatialseg.objectives import objective_names

        if self.name not in objective_names():
            raise ValueError(
                f"objective={self.name} is unknown; choose one of: {', '.join(objective_names())}"
            )
        number_setting(self.blur_sigma, "objective.blur_sigma", 0)


@dataclass(frozen=True)
class DepthSettings:
    """Where EDPA's depth maps come from: ``name`` and that source's own parameters
    (spatialseg.depth's sources check them when they are built)."""

    name: str = "recording"
    params: Mapping[str, Any] = field(default_factory=dict)

    def as_config(self) -> dict[str, Any]:
        """The section as the depth sources read it: ``name`` and the parameters."""
        return {"name": self.name, **self.params}


@dataclass(frozen=True)
class Settings:
    """All of the method's settings (the defaults are the command line's)."""

    #: N_l, the number of motions per window; "auto": found per window (up to
    #: clustering.max_clusters).
    n_clusters: int | Literal["auto"] = 2
    window: WindowSettings = field(default_factory=WindowSettings)
    edpa: EdpaSettings = field(default_factory=EdpaSettings)
    denoise: DenoiseSettings = field(default_factory=DenoiseSettings)
    volume: VolumeSettings = field(default_factory=VolumeSettings)
    init: InitSettings = field(default_factory=InitSettings)
    clustering: ClusteringSettings = field(default_factory=ClusteringSettings)
    model: ModelSettings = field(default_factory=ModelSettings)
    objective: ObjectiveSettings = field(default_factory=ObjectiveSettings)
    depth: DepthSettings = field(default_factory=DepthSettings)

    def __post_init__(self) -> None:
        if self.n_clusters != "auto":
            integer_setting(
                self.n_clusters, "n_clusters", 1, hint="or auto: the number found per window"
            )

    @property
    def cluster_count(self) -> int | None:
        """``n_clusters`` as a number, or None for ``auto``."""
        return None if self.n_clusters == "auto" else int(self.n_clusters)


#: The sections of a run config the method reads; the others (scene, optimizer, output,
#: tracking, seed, hydra) belong to the app.
SECTIONS = tuple(f.name for f in dataclasses.fields(Settings))


def settings_from(config: Mapping[str, Any] | Settings) -> Settings:
    """The :class:`Settings` of a nested mapping (the run config, or part of it), checked;
    keys it does not give keep their defaults. A :class:`Settings` is returned as it is."""
    if isinstance(config, Settings):
        return config
    if not isinstance(config, Mapping):
        raise ValueError(f"settings must be a mapping of sections, got {type(config).__name__}")
    given = {key: config[key] for key in SECTIONS if key in config}
    return _build(Settings, given, "")


def _build(cls: type, values: Any, key: str) -> Any:
    """``cls`` (a settings dataclass) from the mapping ``values`` at the dotted ``key``."""
    if not isinstance(values, Mapping):
        raise ValueError(f"{key} must be a section of settings (a mapping), got {values!r}")
    if cls is DepthSettings:
        return _depth(values)
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(str(k) for k in values if k not in names)
    if unknown:
        where = f"{key}." if key else ""
        raise ValueError(
            f"{where}{unknown[0]} is not a setting; valid {key or 'sections'}: {', '.join(names)}"
        )
    args = {
        name: _coerce(hints[name], values[name], f"{key}.{name}" if key else name)
        for name in names
        if name in values
    }
    return cls(**args)


def _depth(values: Mapping[str, Any]) -> DepthSettings:
    """The ``depth`` section: its source's name and parameters (checked by the source)."""
    name = values.get("name", "recording")
    if not isinstance(name, str):
        raise ValueError(f"depth.name must be a depth source's name, got {name!r}")
    return DepthSettings(name, {str(k): v for k, v in values.items() if k != "name"})


def _coerce(hint: Any, value: Any, key: str) -> Any:
    """``value`` checked against the annotation ``hint`` (a settings section, a scalar, a
    Literal, a tuple, or a union of them), in one line naming ``key`` when it does not fit."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(hint)
        if value is None and type(None) in options:
            return None
        for option in options:
            if option is type(None):
                continue
            try:
                return _coerce(option, value, key)
            except ValueError:
                continue
        raise ValueError(f"{key} must be {_describe(hint)}, got {value!r}")
    if dataclasses.is_dataclass(hint):
        return _build(hint, value, key)
    if origin is Literal:
        if value not in typing.get_args(hint):
            raise ValueError(f"{key} must be {_describe(hint)}, got {value!r}")
        return value
    if origin is tuple:
        return _tuple(hint, value, key)
    return _scalar(hint, value, key)


def _tuple(hint: Any, value: Any, key: str) -> tuple[Any, ...]:
    """A list setting: ``tuple[X, ...]`` (any length) or ``tuple[X, Y]`` (that length)."""
    args = typing.get_args(hint)
    if not isinstance(value, Sequence) or isinstance(value, str):
        raise ValueError(f"{key} must be {_describe(hint)}, got {value!r}")
    if len(args) == 2 and args[1] is Ellipsis:
        return tuple(_coerce(args[0], v, key) for v in value)
    if len(value) != len(args):
        raise ValueError(f"{key} must be {_describe(hint)}, got {value!r}")
    return tuple(_coerce(a, v, key) for a, v in zip(args, value, strict=True))


def _scalar(hint: Any, value: Any, key: str) -> Any:
    """A bool, int, float or str setting (an int is a float's value too; a bool is no number)."""
    if hint is bool:
        if isinstance(value, bool | np.bool_):
            return bool(value)
    elif hint is int:
        if is_integer(value, -(2**63)):
            return int(value)
    elif hint is float:
        if isinstance(value, int | float | np.integer | np.floating) and not isinstance(
            value, bool
        ):
            return float(value)
    elif hint is str:
        if isinstance(value, str):
            return value
    elif hint is Any:
        return value
    raise ValueError(f"{key} must be {_describe(hint)}, got {value!r}")


_PLURALS = {int: "integers", float: "numbers", str: "strings"}


def _describe(hint: Any) -> str:
    """How an error message names the type ``hint``: "an integer", "one of 'a', 'b'", ..."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(
            "null" if a is type(None) else _describe(a) for a in typing.get_args(hint)
        )
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(hint))
    if origin is tuple:
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_PLURALS.get(args[0], _describe(args[0]))}"
        return f"a list [{', '.join(_describe(a) for a in args)}]"
    names = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    return names.get(hint, getattr(hint, "__name__", str(hint)))


def default_tree() -> dict[str, Any]:
    """The defaults as the nested plain mapping a config file would hold (the Hydra app's
    base config; lists for tuples, the depth section flattened)."""
    defaults = Settings()
    tree = _plain(defaults)
    tree["depth"] = defaults.depth.as_config()
    return tree


def _plain(value: Any) -> Any:
    """A settings value as plain YAML values: sections as dicts, tuples as lists."""
    if dataclasses.is_dataclass(value):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value
