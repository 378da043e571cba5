"""Depth sources: where the depth maps EDPA interpolates come from when a camera has none.

A real event camera records no depth. Each source here makes a :class:`DepthMap` for a
time, the camera and (optionally) a keyframe image; :func:`attach_depth` puts such maps into
a recording at its keyframe times or at regular event counts, and
:func:`with_configured_depth` is the one call a scene loader makes. Sources, selected by
``depth=NAME`` (``conf/depth/``; details and formulas in ``docs/depth.md``):

- ``recording``: the recording's own maps (``depthmaps.txt`` or the simulator's);
- ``constant``: one depth everywhere (the method then sees planar motion at that scale);
- ``ground_plane``: each ray's intersection with a flat ground below the camera;
- ``onnx``: a monocular depth network exported to ONNX, run on each keyframe image.

Unknown depth is NaN, as :class:`DepthMap` and :mod:`spatialseg.edpa` read it.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from spatialseg.checks import is_integer, optional_positive
from spatialseg.recording import Camera, DepthMap, Keyframe, Recording, event_boundaries
from spatialseg.settings import Settings

__all__ = [
    "DEPTH_SOURCES",
    "ConstantDepth",
    "DepthSource",
    "GroundPlaneDepth",
    "OnnxDepth",
    "RecordingDepth",
    "attach_depth",
    "make_depth_source",
    "resize_bilinear",
    "with_configured_depth",
]

log = logging.getLogger(__name__)


class DepthSource(ABC):
    """Makes a depth map (metres, NaN unknown) for a time, a camera and an optional image."""

    #: The ``depth.name`` that selects the source.
    name: ClassVar[str]
    #: True when :meth:`depth_map` needs a keyframe image (a network), not just the camera.
    needs_image: ClassVar[bool] = False
    #: The keys its config section may have besides ``name`` (``conf/depth/NAME.yaml``).
    keys: ClassVar[tuple[str, ...]] = ()

    @abstractmethod
    def depth_map(self, t: float, camera: Camera, image: np.ndarray | None) -> DepthMap:
        """The depth map at ``t`` for ``camera`` (H x W), from ``image`` if the source uses one."""

    @classmethod
    @abstractmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> DepthSource:
        """The source built from its validated config section (``conf/depth/NAME.yaml``)."""


def _number(cfg: Mapping[str, Any], key: str, *, positive: bool = False) -> float:
    """``cfg[key]`` as a finite float (positive if asked), or a one-line ValueError."""
    value = cfg.get(key)
    ok = isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value)
    if not ok or (positive and value <= 0):
        kind = "a positive number" if positive else "a finite number"
        raise ValueError(f"depth.{key} must be {kind}, got {value!r}; fix depth.{key}")
    return float(value)


class RecordingDepth(DepthSource):
    """The recording's own depth maps; it makes none of its own."""

    name = "recording"

    def depth_map(self, t: float, camera: Camera, image: np.ndarray | None) -> DepthMap:
        raise ValueError(
            "depth=recording makes no depth maps, it uses the recording's own; "
            "choose depth=constant, ground_plane or onnx to make them"
        )

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> RecordingDepth:
        return cls()


class ConstantDepth(DepthSource):
    """Every pixel at ``value`` metres: a fronto-parallel plane, i.e. planar motion in metres."""

    name = "constant"
    keys = ("value",)

    def __init__(self, value: float) -> None:
        self.value = _number({"value": value}, "value", positive=True)

    def depth_map(self, t: float, camera: Camera, image: np.ndarray | None) -> DepthMap:
        depth = np.full((camera.height, camera.width), self.value, dtype=np.float32)
        return DepthMap(t, depth, source=f"depth=constant t={t:.6f}")

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> ConstantDepth:
        return cls(_number(cfg, "value", positive=True))


def ground_normal(pitch: float, roll: float) -> np.ndarray:
    """The ground's downward unit normal in camera coordinates (x right, y down, z forward).

    ``pitch`` (radians) tilts the optical axis below the horizon, ``roll`` (radians) turns the
    camera about its optical axis (> 0 lowers the image's right side): ``(sin roll cos pitch,
    cos roll cos pitch, sin pitch)``.
    """
    return np.array(
        [np.sin(roll) * np.cos(pitch), np.cos(roll) * np.cos(pitch), np.sin(pitch)],
        dtype=np.float64,
    )


#: ``n.d`` at or below this is the horizon: it absorbs rounding (cos 90 deg = 6e-17), and a
#: ray meeting the ground more than 1e9 heights away is no measurement.
_HORIZON_EPS = 1e-9


class GroundPlaneDepth(DepthSource):
    """Depth where each pixel's ray meets a flat ground ``height`` metres below the camera.

    With ``n`` the ground's downward normal (:func:`ground_normal`) and the ray
    ``d = ((u - cx)/fx, (v - cy)/fy, 1)``, the point ``Z d`` is on the ground when
    ``Z n.d = height``, so ``Z = height / n.d``. Rays with ``n.d <= 0`` (at or above the
    horizon) never meet it: they get ``far_depth``, or NaN (unknown) when that is None;
    ``far_depth`` also caps the far ground.
    """

    name = "ground_plane"
    keys = ("height", "pitch", "roll", "far_depth")

    def __init__(
        self, height: float, pitch: float, roll: float = 0.0, far_depth: float | None = None
    ) -> None:
        self.height = _number({"height": height}, "height", positive=True)
        self.pitch = _number({"pitch": pitch}, "pitch")
        self.roll = _number({"roll": roll}, "roll")
        if not -90.0 < self.pitch < 90.0:
            raise ValueError(f"depth.pitch must be in (-90, 90) degrees, got {pitch}")
        if not -180.0 <= self.roll <= 180.0:
            raise ValueError(f"depth.roll must be in [-180, 180] degrees, got {roll}")
        self.far_depth = optional_positive(far_depth, "depth.far_depth")

    def depth_map(self, t: float, camera: Camera, image: np.ndarray | None) -> DepthMap:
        n = ground_normal(np.radians(self.pitch), np.radians(self.roll))
        dx = (np.arange(camera.width, dtype=np.float64) - camera.cx) / camera.fx
        dy = (np.arange(camera.height, dtype=np.float64) - camera.cy) / camera.fy
        denom = n[0] * dx[None, :] + n[1] * dy[:, None] + n[2]
        below = denom > _HORIZON_EPS
        depth = np.full(denom.shape, np.nan if self.far_depth is None else self.far_depth)
        depth[below] = self.height / denom[below]
        if self.far_depth is not None:
            np.minimum(depth, self.far_depth, out=depth)
        return DepthMap(t, depth, source=f"depth=ground_plane t={t:.6f}")

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> GroundPlaneDepth:
        return cls(
            height=_number(cfg, "height", positive=True),
            pitch=_number(cfg, "pitch"),
            roll=_number(cfg, "roll") if cfg.get("roll") is not None else 0.0,
            far_depth=optional_positive(cfg.get("far_depth"), "depth.far_depth"),
        )


def _axis_weights(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Source indices and weights of a half-pixel-centred linear resampling of one axis."""
    pos = np.clip((np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5, 0.0, n_in - 1)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, n_in - 1)
    return lo, hi, pos - lo


def resize_bilinear(array: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize the last two axes of ``array`` to ``height`` x ``width`` (bilinear, float64).

    Pixel centres are aligned (``align_corners=False``, as OpenCV and PyTorch resize); the
    border is clamped. Used for a network's input and output, which differ from the sensor.
    """
    a = np.asarray(array, dtype=np.float64)
    r0, r1, wr = _axis_weights(a.shape[-2], int(height))
    c0, c1, wc = _axis_weights(a.shape[-1], int(width))
    rows = a[..., r0, :] * (1.0 - wr)[:, None] + a[..., r1, :] * wr[:, None]
    return rows[..., c0] * (1.0 - wc) + rows[..., c1] * wc


_ONNX_OUTPUTS = ("inverse_depth", "depth")
_ONNX_SCALINGS = ("median", "affine")
_ORT_DTYPES = {"tensor(float)": np.float32, "tensor(float16)": np.float16}


def _choice(cfg: Mapping[str, Any], key: str, options: tuple[str, ...]) -> str:
    """``cfg[key]`` if it is one of ``options``, else a one-line ValueError listing them."""
    value = cfg.get(key)
    if value not in options:
        raise ValueError(f"depth.{key} must be one of {', '.join(options)}, got {value!r}")
    return str(value)


def _channel_stats(cfg: Mapping[str, Any], key: str) -> np.ndarray:
    """Per-channel normalisation constants (``depth.mean``/``depth.std``) as 3 floats."""
    values = cfg.get(key)
    try:
        array = np.asarray(list(values), dtype=np.float64)
    except (TypeError, ValueError):
        array = np.zeros(0)
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise ValueError(f"depth.{key} must be a list of 3 numbers (R, G, B), got {values!r}")
    if key == "std" and np.any(array <= 0):
        raise ValueError(f"depth.std must be positive, got {values!r}")
    return array


def _input_size(value: Any) -> tuple[int, int] | None:
    """``depth.input_size`` as (H, W), or None when it is null."""
    if value is None:
        return None
    size = list(value) if not isinstance(value, str | bytes) else []
    if len(size) != 2 or not all(is_integer(s, 1) for s in size):
        raise ValueError(f"depth.input_size must be null or [H, W] in pixels, got {value!r}")
    return int(size[0]), int(size[1])


def _image_to_unit(image: np.ndarray) -> np.ndarray:
    """An (H, W) or (H, W, 3) image as float64 in [0, 1] (integers by their dtype's maximum)."""
    a = np.asarray(image)
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
        raise ValueError(f"keyframe image must be (H, W) or (H, W, 3), got shape {a.shape}")
    if a.dtype.kind in "ui":
        return a.astype(np.float64) / float(np.iinfo(a.dtype).max)
    return a.astype(np.float64)


class OnnxDepth(DepthSource):
    """A monocular depth network (ONNX, run by onnxruntime on the CPU) on each keyframe image.

    The image goes to [0, 1], is resized to the network's input, normalised per channel and
    fed as one NCHW batch; the output (1 x H x W after squeezing) is resized back to the
    sensor. ``output`` says whether it is relative inverse depth (MiDaS, Depth Anything) or
    depth; ``scaling`` makes metres: ``median`` scales each map to a median of
    ``median_depth``; ``affine`` maps the output by ``scale * output + shift`` first (fitted
    once, so all maps share one scale). Values <= 0 and depths beyond ``max_depth`` are unknown.
    """

    name = "onnx"
    needs_image = True
    keys = (
        "model",
        "input_size",
        "mean",
        "std",
        "output",
        "scaling",
        "median_depth",
        "scale",
        "shift",
        "max_depth",
        "threads",
    )

    def __init__(self, cfg: Mapping[str, Any]) -> None:
        model = cfg.get("model")
        if not model:
            raise ValueError("depth=onnx needs a model: add depth.model=PATH/TO/model.onnx")
        self.model = Path(str(model)).expanduser()
        if not self.model.is_file():
            raise ValueError(f"depth.model={self.model}: no such file; export the network to ONNX")
        self.input_size = _input_size(cfg.get("input_size"))
        self.mean = _channel_stats(cfg, "mean")
        self.std = _channel_stats(cfg, "std")
        self.output = _choice(cfg, "output", _ONNX_OUTPUTS)
        self.scaling = _choice(cfg, "scaling", _ONNX_SCALINGS)
        self.median_depth = _number(cfg, "median_depth", positive=True)
        self.scale = _number(cfg, "scale")
        self.shift = _number(cfg, "shift")
        if self.scaling == "affine" and self.scale == 0:
            raise ValueError("depth.scale must be nonzero for scaling=affine")
        self.max_depth = optional_positive(cfg.get("max_depth"), "depth.max_depth")
        threads = cfg.get("threads")
        if not is_integer(threads, 0):
            raise ValueError(f"depth.threads must be an integer >= 0, got {threads!r}")
        self._session = self._load(threads)
        self._input = self._session.get_inputs()[0]
        shape = list(self._input.shape)
        if len(shape) != 4:
            raise ValueError(f"{self.model}: input has shape {shape}; expected NCHW (4-D)")
        channels = shape[1] if isinstance(shape[1], int) else 3
        if channels not in (1, 3):
            raise ValueError(f"{self.model}: input has {channels} channels; expected 1 or 3")
        self._channels = channels
        self._dtype = _ORT_DTYPES.get(self._input.type)
        if self._dtype is None:
            raise ValueError(f"{self.model}: input type {self._input.type}; expected float")
        self._size = self._network_size(shape[2], shape[3])

    def _load(self, threads: int) -> Any:
        """An onnxruntime CPU session for the model (deterministic: one provider)."""
        try:
            import onnxruntime as ort
        except ImportError:
            raise ValueError(
                "depth=onnx needs onnxruntime: pip install 'spatialseg[onnx]'"
            ) from None
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        try:
            session = ort.InferenceSession(
                str(self.model), sess_options=options, providers=["CPUExecutionProvider"]
            )
        except Exception as exc:  # onnxruntime raises its own exception types
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ValueError(f"{self.model}: onnxruntime cannot load it ({first})") from None
        if len(session.get_inputs()) != 1:
            raise ValueError(f"{self.model}: the network must take exactly one input (the image)")
        return session

    def _network_size(self, height: Any, width: Any) -> tuple[int, int]:
        """The (H, W) fed to the network: the model's fixed size, else ``input_size``."""
        fixed = isinstance(height, int) and isinstance(width, int)
        if self.input_size is None:
            if not fixed:
                raise ValueError(
                    f"{self.model}: the input size is not fixed ({height} x {width}); "
                    "set depth.input_size=[H,W]"
                )
            return int(height), int(width)
        if fixed and (int(height), int(width)) != self.input_size:
            raise ValueError(
                f"{self.model}: takes {height} x {width} but depth.input_size is "
                f"{list(self.input_size)}; set depth.input_size=null"
            )
        return self.input_size

    def _tensor(self, image: np.ndarray) -> np.ndarray:
        """The network's input (1 x C x H x W) for an image."""
        unit = _image_to_unit(image)
        chw = np.repeat(unit[None], 3, axis=0) if unit.ndim == 2 else unit.transpose(2, 0, 1)
        chw = (resize_bilinear(chw, *self._size) - self.mean[:, None, None]) / self.std[
            :, None, None
        ]
        if self._channels == 1:
            chw = chw.mean(axis=0, keepdims=True)
        return np.ascontiguousarray(chw[None], dtype=self._dtype)

    def _metres(self, raw: np.ndarray, t: float) -> np.ndarray:
        """The network's output (at sensor size) converted to metres; NaN where unknown."""
        value = self.scale * raw + self.shift if self.scaling == "affine" else raw
        positive = np.isfinite(value) & (value > 0)
        depth = np.full(value.shape, np.nan)
        inverse = self.output == "inverse_depth"
        depth[positive] = 1.0 / value[positive] if inverse else value[positive]
        if self.scaling == "median":
            if not positive.any():
                raise ValueError(
                    f"{self.model}: output at t={t:.6f} has no positive values to scale; "
                    "check depth.output"
                )
            depth *= self.median_depth / float(np.median(depth[positive]))
        if self.max_depth is not None:
            depth[depth > self.max_depth] = np.nan
        return depth

    def depth_map(self, t: float, camera: Camera, image: np.ndarray | None) -> DepthMap:
        if image is None:
            raise ValueError(
                "depth=onnx needs a keyframe image (images.txt); this recording has none"
            )
        shape = np.shape(image)[:2]
        if shape != (camera.height, camera.width):
            raise ValueError(
                f"keyframe at t={t:.6f} is {shape[1]}x{shape[0]} but the sensor is "
                f"{camera.width}x{camera.height}; keyframes must come from the event sensor"
            )
        out = self._session.run(None, {self._input.name: self._tensor(image)})[0]
        raw = np.squeeze(np.asarray(out, dtype=np.float64))
        if raw.ndim != 2:
            raise ValueError(
                f"{self.model}: output has shape {np.shape(out)}; expected one H x W map"
            )
        raw = resize_bilinear(raw, camera.height, camera.width)
        return DepthMap(t, self._metres(raw, t), source=f"depth=onnx t={t:.6f}")

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> OnnxDepth:
        return cls(cfg)


#: Depth source name -> its class (``from_config`` builds it from ``conf/depth/NAME.yaml``).
DEPTH_SOURCES: dict[str, type[DepthSource]] = {
    cls.name: cls for cls in (RecordingDepth, ConstantDepth, GroundPlaneDepth, OnnxDepth)
}


def make_depth_source(cfg: Mapping[str, Any]) -> DepthSource:
    """The depth source a ``depth`` config section names (``cfg['name']``), validated."""
    name = cfg.get("name")
    if name not in DEPTH_SOURCES:
        raise ValueError(
            f"unknown depth source {name!r}; use depth=NAME with NAME one of: "
            + ", ".join(sorted(DEPTH_SOURCES))
        )
    cls = DEPTH_SOURCES[str(name)]
    unknown = sorted(str(k) for k in cfg if k != "name" and k not in cls.keys)
    if unknown:
        raise ValueError(
            f"depth={name} has no parameter {unknown[0]!r}; valid: {', '.join(cls.keys) or 'none'}"
        )
    return cls.from_config(cfg)


def _keyframes_around(keyframes: tuple[Keyframe, ...], t0: float, t1: float) -> list[Keyframe]:
    """Time-sorted keyframes (one per time) from the last at or before ``t0`` to the first at
    or after ``t1``: frames beyond those bound no events and would cost a network run each."""
    frames: list[Keyframe] = []
    for k in sorted(keyframes, key=lambda k: k.t):
        if not frames or k.t != frames[-1].t:
            frames.append(k)
    times = np.array([k.t for k in frames])
    first = max(int(np.searchsorted(times, t0, side="right")) - 1, 0)
    last = min(int(np.searchsorted(times, t1, side="left")), len(frames) - 1)
    return frames[first : last + 1]


def attach_depth(recording: Recording, source: DepthSource, *, window_events: int) -> Recording:
    """The recording with ``source``'s depth maps at its keyframe times or every N events.

    A source that reads images (``onnx``) makes maps at the keyframe times, from the last
    keyframe at or before the first event to the first at or after the last; events outside
    them are in no window. Other sources make maps every ``window_events`` events, first and
    last event times included. Decision: a DAVIS's APS frames come every ~40 ms, about 1,300
    events on the road recording, too few per window for the motions to stand out; a
    geometric source needs no image, so the window length stays the user's
    (``window.events``). ``depth=recording`` returns the recording unchanged and needs its
    own two maps or more.
    """
    if isinstance(window_events, bool) or int(window_events) != window_events or window_events < 1:
        raise ValueError(f"window.events must be an integer >= 1, got {window_events!r}")
    if isinstance(source, RecordingDepth):
        if len(recording.depth_maps) < 2:
            raise ValueError(
                f"{recording.name}: has {len(recording.depth_maps)} depth map(s) and "
                "depth=recording needs two or more; choose depth=constant, ground_plane or onnx"
            )
        return recording
    t = recording.events.t
    if not len(t):
        raise ValueError(f"{recording.name}: no events to attach depth maps to")
    if source.needs_image:
        frames = _keyframes_around(recording.keyframes, float(t[0]), float(t[-1]))
        if len(frames) < 2:
            raise ValueError(
                f"{recording.name}: depth={source.name} needs two or more keyframe images "
                f"(images.txt) and the recording has {len(recording.keyframes)}"
            )
        pairs = [(k.t, k.image) for k in frames]
    else:
        pairs = [(float(b), None) for b in event_boundaries(t, int(window_events))]
        if len(pairs) < 2:
            raise ValueError(
                f"{recording.name}: all events share one timestamp; a window needs two times"
            )
    maps = tuple(source.depth_map(float(tk), recording.camera, image) for tk, image in pairs)
    return replace(recording, depth_maps=maps)


def with_configured_depth(recording: Recording, settings: Settings) -> Recording:
    """:func:`attach_depth` with the ``depth`` settings (``window.events`` sets the window
    length for sources that read no images)."""
    source = make_depth_source(settings.depth.as_config())
    return attach_depth(recording, source, window_events=settings.window.events)
