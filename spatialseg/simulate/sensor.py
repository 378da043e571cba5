"""The ESIM-style pixel: events where log intensity crosses its reference by a threshold.

Between two renders the log intensity of a pixel is taken as linear in time. Every level
``ref + k C`` (k = 1, 2, ...) crossed in the render interval is an event whose timestamp
is interpolated linearly; the reference moves to the last crossed level. A crossing less
than ``refractory`` seconds after the pixel's previous event is not emitted but still
moves the reference (as ESIM does), so a suppressed pixel does not fire a burst later.
Background-activity noise is a Poisson process per pixel with random polarity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from spatialseg.simulate.scene import SensorModel

__all__ = ["EventChunk", "Pixels"]


@dataclass(frozen=True, eq=False)
class EventChunk:
    """Events of one render interval: flat pixel index, time, polarity, object id."""

    pixel: np.ndarray
    t: np.ndarray
    p: np.ndarray
    label: np.ndarray

    def __len__(self) -> int:
        return int(self.t.size)


@numba.njit(cache=True)
def _crossings(changed, l0, l1, ref, c_pos, c_neg, last_t, t0, dt, refractory):
    """Emit the threshold crossings of the changed pixels; update ref and last_t in place."""
    counts = np.zeros(changed.size, dtype=np.int64)
    for n in range(changed.size):
        i = changed[n]
        if l1[i] > ref[i]:
            counts[n] = int(np.floor((l1[i] - ref[i]) / c_pos[i]))
        else:
            counts[n] = int(np.floor((ref[i] - l1[i]) / c_neg[i]))
    total = counts.sum()
    pixel = np.empty(total, dtype=np.int64)
    times = np.empty(total, dtype=np.float64)
    polarity = np.empty(total, dtype=np.int8)
    m = 0
    for n in range(changed.size):
        i = changed[n]
        if counts[n] == 0:
            continue
        rising = l1[i] > ref[i]
        step = c_pos[i] if rising else -c_neg[i]
        slope = l1[i] - l0[i]
        for k in range(1, counts[n] + 1):
            level = ref[i] + k * step
            te = t0 + (level - l0[i]) / slope * dt
            te = min(max(te, t0), t0 + dt)
            if te - last_t[i] >= refractory:
                pixel[m] = i
                times[m] = te
                polarity[m] = 1 if rising else -1
                last_t[i] = te
                m += 1
        ref[i] += counts[n] * step
    return pixel[:m], times[:m], polarity[:m]


class Pixels:
    """The sensor's per-pixel state: thresholds, reference levels, last event times."""

    def __init__(self, model: SensorModel, log_intensity: np.ndarray, rng: np.random.Generator):
        shape = log_intensity.size
        self.model = model
        self.rng = rng
        self.c_pos, self.c_neg = (
            np.maximum(
                rng.normal(model.threshold_mean, model.threshold_std, shape), model.threshold_min
            )
            for _ in range(2)
        )
        self.ref = log_intensity.ravel().astype(np.float64)
        self.last_t = np.full(shape, -np.inf)

    def step(
        self, l0: np.ndarray, l1: np.ndarray, labels: np.ndarray, t0: float, t1: float
    ) -> EventChunk:
        """Events between renders at t0 (log image l0) and t1 (l1), time-sorted.

        ``labels`` holds the object id each pixel's events get in this interval.
        """
        a, b = l0.ravel(), l1.ravel()
        changed = np.flatnonzero(a != b)
        pixel, t, p = _crossings(
            changed,
            a,
            b,
            self.ref,
            self.c_pos,
            self.c_neg,
            self.last_t,
            t0,
            t1 - t0,
            self.model.refractory,
        )
        label = labels.ravel()[pixel]
        noise = self._noise(t0, t1)
        pixel = np.concatenate([pixel, noise.pixel])
        t = np.concatenate([t, noise.t])
        order = np.argsort(t, kind="stable")
        return EventChunk(
            pixel[order],
            t[order],
            np.concatenate([p, noise.p])[order],
            np.concatenate([label, noise.label])[order],
        )

    def _noise(self, t0: float, t1: float) -> EventChunk:
        """Background-activity events (label -1) at uniformly random pixels and times."""
        n_pixels = self.ref.size
        n = int(self.rng.poisson(self.model.noise_rate * n_pixels * (t1 - t0)))
        return EventChunk(
            self.rng.integers(0, n_pixels, n),
            t0 + (t1 - t0) * self.rng.random(n),
            (2 * self.rng.integers(0, 2, n) - 1).astype(np.int8),
            np.full(n, -1, dtype=np.int64),
        )
