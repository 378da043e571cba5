"""The event stream: one small structure-of-arrays type, validated on construction.

Every reader, the simulator and the method exchange events as an :class:`EventStream`:
``x``, ``y`` integer pixel coordinates, ``t`` float64 seconds (non-decreasing), ``p``
polarity in {-1, +1}, and the sensor size. A violation raises a ``ValueError`` that names
the source (file), the offending event index and the fix.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["EventStream", "normalise_polarity"]


def normalise_polarity(p: np.ndarray, source: str = "<memory>") -> np.ndarray:
    """Map polarity given as {0, 1} or {-1, +1} (or booleans) to int8 {-1, +1}."""
    p = np.asarray(p)
    if p.dtype == bool:
        return np.where(p, 1, -1).astype(np.int8)
    if p.size and not np.all(np.isfinite(p.astype(np.float64))):
        bad = int(np.flatnonzero(~np.isfinite(p.astype(np.float64)))[0])
        raise ValueError(f"{source}: polarity of event {bad} is not finite; use 0/1 or -1/+1")
    values = set(np.unique(p).tolist())
    if values <= {0, 1}:
        return np.where(p > 0, 1, -1).astype(np.int8)
    if values <= {-1, 1}:
        return p.astype(np.int8)
    bad = int(np.flatnonzero(~np.isin(p, (-1, 0, 1)))[0]) if values - {-1, 0, 1} else 0
    raise ValueError(
        f"{source}: polarity of event {bad} is {p[bad]!r} (values seen: {sorted(values)[:5]}); "
        "polarity must be 0/1 or -1/+1, not a mix"
    )


@dataclass(frozen=True, eq=False)
class EventStream:
    """A time-sorted stream of events from a sensor of ``width`` x ``height`` pixels.

    Arrays are coerced to ``x, y: int32``, ``t: float64`` (seconds), ``p: int8`` and
    validated: equal 1-D lengths, finite non-decreasing times, pixels inside the sensor,
    polarity in {-1, +1}. ``source`` names the origin (a file path) in error messages.
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray
    width: int
    height: int
    source: str = field(default="<memory>", compare=False)

    def __post_init__(self) -> None:
        src = self.source
        arrays = {}
        for name, dtype in (("x", np.int32), ("y", np.int32), ("t", np.float64), ("p", np.int8)):
            a = np.asarray(getattr(self, name))
            if a.ndim != 1:
                raise ValueError(f"{src}: events.{name} must be 1-D, got shape {a.shape}")
            if name in ("x", "y", "p") and a.size and a.dtype.kind == "f":
                finite = np.isfinite(a)
                if not finite.all():
                    bad = int(np.flatnonzero(~finite)[0])
                    raise ValueError(f"{src}: event {bad} has a non-finite {name}; drop it")
                if np.any(a != np.round(a)):
                    bad = int(np.flatnonzero(a != np.round(a))[0])
                    raise ValueError(
                        f"{src}: event {bad} has non-integer {name}={a[bad]}; "
                        "pixel coordinates must be integers"
                    )
            arrays[name] = np.ascontiguousarray(a, dtype=dtype)
        n = {k: v.size for k, v in arrays.items()}
        if len(set(n.values())) != 1:
            raise ValueError(f"{src}: event arrays differ in length {n}; give one value per event")
        for name, value in arrays.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"{src}: sensor size {self.width}x{self.height} must be positive")
        self._validate()

    def _validate(self) -> None:
        src, t = self.source, self.t
        if not t.size:
            return
        finite = np.isfinite(t)
        if not finite.all():
            bad = int(np.flatnonzero(~finite)[0])
            raise ValueError(f"{src}: event {bad} has a non-finite timestamp; drop it")
        back = np.flatnonzero(np.diff(t) < 0)
        if back.size:
            k = int(back[0]) + 1
            raise ValueError(
                f"{src}: timestamps not sorted at event {k} ({t[k]:.9f} s < {t[k - 1]:.9f} s); "
                "sort the events by time"
            )
        for name, size in (("x", self.width), ("y", self.height)):
            a = getattr(self, name)
            out = np.flatnonzero((a < 0) | (a >= size))
            if out.size:
                k = int(out[0])
                raise ValueError(
                    f"{src}: event {k} has {name}={a[k]} outside the sensor "
                    f"(0..{size - 1}); check the sensor size or crop the events"
                )
        if not np.all(np.abs(self.p) == 1):
            k = int(np.flatnonzero(np.abs(self.p) != 1)[0])
            raise ValueError(f"{src}: event {k} has polarity {self.p[k]}; use -1/+1")

    def __len__(self) -> int:
        return int(self.t.size)

    @property
    def duration(self) -> float:
        """Time from the first to the last event, in seconds (0 for fewer than two events)."""
        return float(self.t[-1] - self.t[0]) if len(self) > 1 else 0.0

    def select(self, index: slice | np.ndarray) -> EventStream:
        """Events picked by a slice, boolean mask or sorted index array (order is kept)."""
        return EventStream(
            self.x[index],
            self.y[index],
            self.t[index],
            self.p[index],
            self.width,
            self.height,
            self.source,
        )

    def between(self, t0: float, t1: float) -> EventStream:
        """Events with ``t0 <= t <= t1`` (a contiguous slice, since times are sorted)."""
        i0 = int(np.searchsorted(self.t, t0, side="left"))
        i1 = int(np.searchsorted(self.t, t1, side="right"))
        return self.select(slice(i0, i1))
