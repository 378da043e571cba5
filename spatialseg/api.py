"""The Python API: simulate or read a recording, segment it, write it; no Hydra app needed.

>>> import spatialseg
>>> rec = spatialseg.simulate("interior", window_events=3000, windows=2)
>>> seg = spatialseg.segment(rec, 2, seed=0, **{"clustering.max_iterations": 5})
>>> seg.labels.shape, seg.velocities.shape  # one id per event; K x 3 in seg.units
((6000,), (2, 3))

Every default is the command line's: the run config composed from ``conf/config.yaml`` and
its default groups (:func:`spatialseg.config.compose_config`). A setting is a section of
that config as a mapping (``clustering={"max_iterations": 5}``) or a dotted key
(``**{"clustering.max_iterations": 5}``); both forms may be mixed. A config group is chosen
by name (``model="planar"``, ``depth="constant"``, ``preset="fast"``). Every setting is
checked before any work starts: a wrong key or value raises one ``ValueError`` that names
the setting and the fix. Only this module and :mod:`spatialseg.config` know the config
files; the algorithm reads the typed :class:`~spatialseg.settings.Settings` built from it.
"""

from __future__ import annotations

import copy
import numbers
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any, get_args, get_type_hints

import numpy as np

from spatialseg import pipeline
from spatialseg.checks import integer_setting, optional_positive, unknown_key
from spatialseg.config import (
    build_optimizer,
    check_option,
    compose_config,
    group_options,
    simulated_scenes,
)
from spatialseg.depth import make_depth_source
from spatialseg.recording import Camera, Recording
from spatialseg.settings import Settings
from spatialseg.simulate import simulator
from spatialseg.window import WindowResult, check_config

__all__ = ["Segmentation", "read", "segment", "simulate", "write"]

#: Config groups a setting chooses by name (``model="planar"`` or ``model={"name": ...}``);
#: ``preset`` adds a ``conf/preset`` file on top (``+preset=NAME`` on the command line).
_CHOSEN_GROUPS = ("model", "objective", "depth")
_PRESET = "preset"

#: The config's top-level keys that are no setting of :func:`segment`: its own arguments
#: (the recording, ``n_clusters``, ``seed``) or the command line's alone.
_NOT_SETTINGS = ("scene", "seed", "n_clusters", "tracking", "output", "hydra")


def _nullable(cls: type = Settings, prefix: str = "") -> frozenset[str]:
    """The dotted keys of the settings whose type admits null (spatialseg/settings.py
    says what null means for each), read from the dataclasses' own annotations so that a
    new optional setting needs no second list."""
    hints = get_type_hints(cls)
    keys: set[str] = set()
    for item in fields(cls):
        kind = hints[item.name]
        if is_dataclass(kind):
            keys |= _nullable(kind, f"{prefix}{item.name}.")
        elif type(None) in get_args(kind):
            keys.add(prefix + item.name)
    return frozenset(keys)


#: Settings that take null as well as their type (elsewhere null is refused unless the
#: default is null).
_NULLABLE = _nullable()

_SETTINGS_FORMS = (
    "a section as a mapping, clustering={'max_iterations': 5}, or a dotted key, "
    "**{'clustering.max_iterations': 5}"
)


@dataclass(frozen=True, eq=False, repr=False)
class Segmentation:
    """A recording's segmentation by 3-D motion.

    ``labels`` (N,) give each input event's object id, -1 unassigned; an id names one
    object in every window. ``probabilities`` (N x objects, column = object id) are the
    memberships. ``velocities`` (objects x 3, in ``units``: m/s for the spatial model, px/s
    for the planar) are each object's whole-run velocity, the mean over its windows
    weighted by its events in each. ``windows`` are the pipeline's per-window results
    (clusters, convergence, timings) and ``window_indices`` their events; ``timings`` are
    seconds (``setup``: config and checks, ``segment``, ``total``); ``summary`` is what the
    command line writes as ``result.json``; ``recording`` is the input with the depth maps
    the segmentation used.
    """

    labels: np.ndarray
    probabilities: np.ndarray
    velocities: np.ndarray
    units: str
    windows: tuple[WindowResult, ...]
    window_indices: tuple[np.ndarray, ...]
    timings: Mapping[str, float]
    summary: Mapping[str, Any]
    recording: Recording

    @property
    def n_objects(self) -> int:
        """The number of object ids (0 .. n_objects - 1) over the whole recording."""
        return int(self.velocities.shape[0])

    def __repr__(self) -> str:
        """One line: events, windows, objects and labelled events (arrays left out)."""
        labelled = int(np.count_nonzero(self.labels >= 0))
        return (
            f"Segmentation({len(self.labels)} events, {len(self.windows)} windows, "
            f"{self.n_objects} objects, {labelled} labelled, velocities in {self.units})"
        )


def _plain(value: Any) -> Any:
    """``value`` with every mapping a dict and every NumPy scalar a Python one (deep copy)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return copy.deepcopy(value)


def _flatten(settings: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mappings and dotted keys as one form, ``{"a.b": value}``; a key given twice
    (``a={"b": 1}`` and ``**{"a.b": 2}``) is a ValueError."""
    flat: dict[str, Any] = {}
    for key, value in settings.items():
        path = f"{prefix}{key}"
        parts = _flatten(value, f"{path}.") if isinstance(value, Mapping) else {path: value}
        for name, leaf in parts.items():
            if name in flat:
                raise ValueError(f"{name} is given twice; give it once")
            flat[name] = _plain(leaf)
    return flat


def _kind(default: Any) -> str:
    """What a setting's value must be, judged by its default's type."""
    if isinstance(default, dict):
        return f"a section: a mapping of its keys ({', '.join(_public(default))})"
    if isinstance(default, bool):
        return "true or false"
    kinds = ((int, "an integer"), (float, "a number"), (str, "a string"), (list, "a list"))
    return next(text for kind, text in kinds if isinstance(default, kind))


def _fits(key: str, value: Any, default: Any) -> bool:
    """Whether ``value`` has the type of the setting's ``default``: an integer for an
    integer, a number for a number, a list or one number for a list (a P-step sigma); null
    where the default is null or its type admits it (:data:`_NULLABLE`)."""
    if value is None:
        return default is None or key in _NULLABLE
    number = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if default is None:
        return True
    if isinstance(default, str):
        return isinstance(value, str)
    if isinstance(default, bool):
        return isinstance(value, bool)
    if isinstance(default, int):
        return number and isinstance(value, numbers.Integral)
    if isinstance(default, float):
        return number
    if isinstance(default, list):
        return isinstance(value, list) or number
    return False  # a section given a value


def _public(section: Mapping[str, Any]) -> list[str]:
    """A section's keys a user sets (not Hydra's ``_target_``), sorted."""
    return sorted(k for k in section if not k.startswith("_"))


def _assign(tree: dict[str, Any], key: str, value: Any, *, known_only: bool) -> None:
    """Set the dotted ``key`` of ``tree`` to ``value``. ``known_only``: the key must exist
    and the value have its default's type (:func:`_fits`), else a ValueError listing the
    section's keys; otherwise missing sections are made (a scene, which its parser checks)."""
    parts = key.split(".")
    node = tree
    for depth, part in enumerate(parts):
        where = ".".join(parts[:depth])
        if not isinstance(node, dict):
            raise ValueError(f"{where} is a single value, not a section; give {where}=VALUE")
        if part not in node:
            if known_only:
                unknown = ".".join(parts[: depth + 1])
                raise ValueError(unknown_key(unknown, _public(node), "setting"))
            node[part] = {}
        if depth < len(parts) - 1:
            node = node[part]
            continue
        default = node[part]
        if known_only and not _fits(key, value, default):
            shown = "" if isinstance(default, dict) else f" (default {default!r})"
            raise ValueError(f"{key} must be {_kind(default)}{shown}, got {value!r}")
        node[part] = value


def _split_choices(flat: Mapping[str, Any]) -> tuple[dict[str, str], dict[str, Any]]:
    """The config groups chosen by name (``model="planar"``, ``model.name``, ``preset``),
    each checked against its options, and the remaining settings."""
    choices: dict[str, str] = {}
    values: dict[str, Any] = {}
    for key, value in flat.items():
        group, _, sub = key.partition(".")
        if (group == _PRESET and not sub) or (group in _CHOSEN_GROUPS and sub in ("", "name")):
            choices[group] = check_option(group, value, key)
        else:
            values[key] = value
    return choices, values


def _overrides(choices: Mapping[str, str], optimizer: str | None) -> list[str]:
    """The Hydra overrides that choose the config groups (and the optimiser preset)."""
    chosen = {**choices, **({} if optimizer is None else {"optimizer": optimizer})}
    return [f"+{g}={v}" if g == _PRESET else f"{g}={v}" for g, v in chosen.items()]


def _optimizer_name(optimizer: Any, flat: Mapping[str, Any]) -> str | None:
    """``optimizer`` checked: an optimiser preset name (returned), or an object with
    ``maximize`` (None; its hyperparameters are its own, not ``optimizer.*`` settings)."""
    if isinstance(optimizer, str):
        return check_option("optimizer", optimizer, "optimizer")
    if not callable(getattr(optimizer, "maximize", None)):
        raise ValueError(
            f"optimizer must be a preset name ({', '.join(group_options('optimizer'))}) or an "
            f"optimizers.Optimizer, got {optimizer!r}"
        )
    given = [k for k in flat if k.startswith("optimizer.")]
    if given:
        raise ValueError(
            f"{given[0]}: set hyperparameters on the optimizer object you pass, or pass a "
            "preset name"
        )
    return None


def _configure(
    n_clusters: int | str, seed: int, optimizer: Any, settings: Mapping[str, Any]
) -> tuple[dict[str, Any], Settings, Any]:
    """The run config, the method's settings and the optimiser for :func:`segment`'s
    arguments, every value checked before any work (the command line's checks:
    :func:`spatialseg.window.check_config`, the depth source, the optimiser's
    hyperparameters)."""
    integer_setting(seed, "seed", 0)
    flat = _flatten(settings)
    name = _optimizer_name(optimizer, flat)
    choices, values = _split_choices(flat)
    cfg = compose_config(*_overrides(choices, name))
    sections = {k: v for k, v in cfg.items() if k not in _NOT_SETTINGS}
    for key, value in values.items():
        if key.partition(".")[0] not in sections:
            line = unknown_key(key.partition(".")[0], [*sections, _PRESET], "setting")
            raise ValueError(f"{line} ({_SETTINGS_FORMS})")
        _assign(sections, key, value, known_only=True)
    cfg.update(sections, n_clusters=n_clusters, seed=seed)
    checked = check_config(cfg)
    if checked.depth.name == "onnx":  # check_config builds every other source already
        make_depth_source(checked.depth.as_config())
    if name is None:
        cfg["optimizer"] = {"_target_": f"{type(optimizer).__module__}.{type(optimizer).__name__}"}
        return cfg, checked, optimizer
    return cfg, checked, build_optimizer(cfg)


def _check_recording(recording: Any, cfg: Mapping[str, Any]) -> Recording:
    """``recording`` if it is a Recording with the depth the config's source needs."""
    if not isinstance(recording, Recording):
        raise ValueError(
            "recording must be a spatialseg.Recording (from spatialseg.simulate, spatialseg.read "
            f"or Recording(events, camera, ...)), got {type(recording).__name__}"
        )
    maps = len(recording.depth_maps)
    if cfg["depth"]["name"] == "recording" and maps < 2:
        raise ValueError(
            f"{recording.name}: the recording has {maps} depth map(s) and the default "
            "depth='recording' needs two or more; give a depth source: depth='constant' (one "
            "depth everywhere, **{'depth.value': METRES}), depth='ground_plane' (a camera "
            "above flat ground) or depth='onnx' (a depth network on the keyframes)"
        )
    return recording


def segment(
    recording: Recording,
    n_clusters: int | str = 2,
    *,
    seed: int = 0,
    optimizer: Any = "ssa_ga",
    **settings: Any,
) -> Segmentation:
    """Segment ``recording``'s events by 3-D motion into ``n_clusters`` motions per window
    (``"auto"``: found per window), object ids linked across windows.

    ``optimizer``: an optimiser preset name (``optimizers.preset``; its hyperparameters as
    settings, ``**{"optimizer.population": 30}``) or an ``optimizers.Optimizer``. ``settings``: the
    run config's sections (window, edpa, denoise, volume, init, clustering, model,
    objective, depth, optimizer), each as a mapping (``clustering={"max_iterations": 5}``)
    or by dotted key (``**{"clustering.max_iterations": 5}``), and config groups by name
    (``model="planar"``, ``depth="constant"``, ``preset="fast"``); defaults are
    :class:`spatialseg.Settings`'. A recording without depth maps needs a depth source
    (``depth="constant"``). A wrong setting raises ValueError before any work starts.
    """
    start = time.perf_counter()
    cfg, checked, solver = _configure(n_clusters, seed, optimizer, settings)
    recording = _check_recording(recording, cfg)
    begin = time.perf_counter()
    used, result = pipeline.segment_loaded(recording, checked, solver, seed=int(seed))
    end = time.perf_counter()
    timings = {"setup": begin - start, "segment": end - begin, "total": end - start}
    return _segmentation(used, result, cfg, timings)


def _segmentation(
    recording: Recording,
    result: pipeline.SegmentationResult,
    cfg: Mapping[str, Any],
    timings: Mapping[str, float],
) -> Segmentation:
    """The pipeline's result with the whole run's summary (:func:`results.summarise`, as
    ``result.json``): its objects' velocities and units."""
    from spatialseg.results import summarise

    summary = summarise(recording, result, cfg, timings)
    velocities = np.full((result.n_objects, 3), np.nan)
    for obj in summary["objects"]:
        velocities[obj["id"]] = obj["velocity"]
    return Segmentation(
        labels=result.labels,
        probabilities=result.probabilities,
        velocities=velocities,
        units=str(summary["units"]),
        windows=tuple(result.windows),
        window_indices=tuple(result.indices),
        timings=dict(timings),
        summary=summary,
        recording=recording,
    )


def _scene_config(scene: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """The scene's mapping and the run config's ``window`` defaults for a shipped scene's
    name or a mapping like ``conf/scene/NAME.yaml``; a ValueError otherwise."""
    if isinstance(scene, Mapping):
        return _plain(scene), compose_config()["window"]
    shipped = simulated_scenes()
    if not isinstance(scene, str) or scene not in shipped:
        recorded = isinstance(scene, str) and scene in group_options("scene")
        why = " is a recording: read it with spatialseg.read" if recorded else " is unknown"
        raise ValueError(
            f"scene: {scene!r}{why}; choose a simulated scene ({', '.join(shipped)}) or give "
            "a mapping like conf/scene/interior.yaml"
        )
    cfg = compose_config(f"+scene={scene}")
    return cfg["scene"], cfg["window"]


def simulate(
    scene: str | Mapping[str, Any],
    seed: int = 0,
    *,
    window_events: int | None = None,
    windows: int | None = None,
    **overrides: Any,
) -> Recording:
    """Simulate ``scene`` (a shipped scene's name, ``conf/scene/NAME.yaml``, or a mapping
    like one) into a Recording with depth maps, keyframes and ground truth.

    ``windows`` windows of ``window_events`` events each, a depth map between each two
    (defaults: the run config's ``window.count`` and ``window.events``, as
    ``python -m spatialseg +scene=NAME`` simulates). ``overrides`` change the scene's keys,
    as mappings merged into its sections or dotted (``duration=0.5``,
    ``sensor={"noise_rate": 0.0}``, ``**{"camera.ego_velocity": [0.5, 0, 0]}``); the scene
    parser rejects an unknown key or a bad value before anything is rendered.
    """
    seed = integer_setting(seed, "seed", 0)
    spec, window = _scene_config(scene)
    count = integer_setting(window["count"] if windows is None else windows, "windows", 1)
    events = window["events"] if window_events is None else window_events
    events = integer_setting(events, "window_events", 1)
    for key, value in _flatten(overrides).items():
        _assign(spec, key, value, known_only=False)
    return simulator.simulate_scene(spec, seed=seed, max_events=events, windows=count)


def read(
    path: str | Path,
    *,
    camera: Camera | Mapping[str, Any] | None = None,
    fov_deg: float | None = None,
) -> Recording:
    """Read a recording directory or an events file of any supported type (``.txt``,
    ``.h5``, ``.npz``, ``.aedat4``, ``.raw``, ``.dat``; docs/formats.md) into a Recording,
    as ``+scene=recording scene.path=PATH`` does. A file without intrinsics needs
    ``camera`` (a Camera or a mapping of fx, fy, cx, cy, width, height) or ``fov_deg`` (a
    nominal pinhole); ``camera`` replaces a directory's ``calib.txt``."""
    from spatialseg.scenes import read_scene

    given = asdict(camera) if isinstance(camera, Camera) else camera
    scene = {"path": str(path), "camera": given, "fov_deg": optional_positive(fov_deg, "fov_deg")}
    return read_scene(scene)


def write(
    recording: Recording,
    directory: str | Path,
    *,
    overwrite: bool = False,
    events_format: str = "txt",
) -> Path:
    """Write ``recording`` as a recording directory (events, ``calib.txt``, depth maps,
    keyframes, ground truth; docs/formats.md), atomically; ``overwrite`` replaces an
    existing one. Returns the directory; :func:`read` reads it back."""
    from spatialseg.io import write_recording

    write_recording(recording, directory, events_format=events_format, overwrite=overwrite)
    return Path(directory)
