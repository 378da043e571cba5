"""Background-activity filter: drop events that no neighbouring pixel supports in time.

Real sensors emit background-activity (BA) noise: isolated events from leakage and shot
noise, uncorrelated with their neighbours. An edge crossing the sensor fires neighbouring
pixels within a short time of each other. The standard filter (Delbruck 2008) therefore
keeps an event only if a pixel in its ``(2 radius + 1)^2`` neighbourhood, the pixel itself
excluded, fired within the last ``window`` seconds. One pass in time order over a map of
each pixel's last timestamp: O(N (2 radius + 1)^2), i.e. O(N) for a fixed radius.
"""

from __future__ import annotations

import numba
import numpy as np

from spatialseg.checks import is_integer
from spatialseg.events import EventStream

__all__ = ["denoise_mask"]


@numba.njit(cache=True)
def _support_mask(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, width: int, height: int, radius: int, window: float
) -> np.ndarray:
    """Keep-mask of the filter; ``last[y, x]`` holds the time of each pixel's latest event."""
    n = t.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    last = np.full((height, width), -np.inf)
    for i in range(n):
        xi, yi, ti = x[i], y[i], t[i]
        y0, y1 = max(yi - radius, 0), min(yi + radius, height - 1)
        x0, x1 = max(xi - radius, 0), min(xi + radius, width - 1)
        newest = -np.inf
        for yy in range(y0, y1 + 1):
            for xx in range(x0, x1 + 1):
                if (yy != yi or xx != xi) and last[yy, xx] > newest:
                    newest = last[yy, xx]
        keep[i] = ti - newest <= window
        last[yi, xi] = ti
    return keep


def denoise_mask(events: EventStream, *, radius: int, window: float) -> np.ndarray:
    """Keep-mask (N,): True where a pixel within ``radius`` fired at most ``window`` s before.

    The neighbourhood is the square of Chebyshev radius ``radius`` around the event's pixel,
    without the pixel itself (so a hot pixel does not support its own events); polarity is
    ignored. Events at the same timestamp support each other only in stream order.
    """
    if not is_integer(radius, 1):
        raise ValueError(f"denoise.radius must be an integer >= 1 (pixels), got {radius!r}")
    real = isinstance(window, int | float | np.floating) and not isinstance(window, bool)
    if not (real and np.isfinite(window) and window > 0):
        raise ValueError(f"denoise.window must be a positive number of seconds, got {window!r}")
    if not len(events):
        return np.zeros(0, dtype=bool)
    return _support_mask(
        events.x,
        events.y,
        events.t,
        int(events.width),
        int(events.height),
        int(radius),
        float(window),
    )
