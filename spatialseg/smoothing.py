"""Separable Gaussian smoothing of a volume, as one parallel numba pass per axis.

``scipy.ndimage.gaussian_filter(volume, sigma, mode=mode, truncate=4.0)`` computes the same
thing (tested to 1e-12) for ``mode`` constant or reflect; this version runs the three 1-D
passes on every core and writes into reused buffers. The P-step smooths each cluster's
volume every outer iteration: with scipy that was 40 % of a 15,000-event window's
clustering time.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numba import njit, prange

__all__ = ["MODES", "gaussian_kernel", "gaussian_smooth"]

#: Boundary modes (scipy.ndimage's names).
MODES = ("constant", "reflect")

#: Kernel half-width in standard deviations (scipy's default ``truncate``).
TRUNCATE = 4.0

#: Columns per parallel task along the contiguous axis.
_CHUNK = 64

#: The last axis is convolved as a matrix product when it has at most this many voxels.
_ROWS_MAX = 64


def gaussian_kernel(sigma: float, truncate: float = TRUNCATE) -> np.ndarray:
    """The normalised sampled Gaussian of ``sigma`` (> 0) over ``+-round(truncate sigma)``."""
    radius = int(truncate * sigma + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    weights = np.exp(-0.5 * (x / sigma) ** 2)
    return weights / weights.sum()


def _sources(n: int, taps: int, mode: str) -> np.ndarray:
    """``sources[j, t]``: the index along an axis of ``n`` voxels that tap ``t`` of a
    ``taps``-wide centred kernel reads for output ``j``; -1 reads zero. ``constant``: zero
    beyond the border; ``reflect``: mirrored about it (scipy's ``reflect``, ``dcba|abcd|dcba``)."""
    r = (taps - 1) // 2
    index = np.arange(n)[:, None] + np.arange(taps)[None, :] - r
    if mode == "constant":
        return np.where((index >= 0) & (index < n), index, -1)
    folded = np.mod(index, 2 * n)
    return np.where(folded < n, folded, 2 * n - 1 - folded)


@njit(cache=True, parallel=True, fastmath=True)
def _convolve_middle(src: np.ndarray, dst: np.ndarray, kernel: np.ndarray, sources) -> None:
    """``dst[i, j, l] = sum_t kernel[t] src[i, sources[j, t], l]`` (0 where the source is -1)
    over a (a, n, b) array; parallel over ``i`` and blocks of ``l``. A block's all-zero
    source rows are skipped: a window's volume holds events in a few percent of its voxels."""
    a, n, b = src.shape
    chunks = (b + _CHUNK - 1) // _CHUNK
    for task in prange(a * chunks):
        i = task // chunks
        lo = (task % chunks) * _CHUNK
        hi = min(lo + _CHUNK, b)
        filled = np.zeros(n, dtype=np.bool_)
        for j in range(n):
            for c in range(lo, hi):
                if src[i, j, c] != 0.0:
                    filled[j] = True
                    break
        acc = np.empty(hi - lo, dtype=src.dtype)  # private, so the inner loop vectorises
        for j in range(n):
            acc[:] = 0.0
            for t in range(kernel.shape[0]):
                source = sources[j, t]
                if source >= 0 and filled[source]:
                    w = kernel[t]
                    row = src[i, source, lo:hi]
                    for c in range(hi - lo):
                        acc[c] += w * row[c]
            dst[i, j, lo:hi] = acc


@njit(cache=True, parallel=True, fastmath=True)
def _convolve_rows(src: np.ndarray, dst: np.ndarray, banded: np.ndarray) -> None:
    """``dst[i] = src[i] @ banded`` for each short row of the (a, n) ``src``; parallel over
    rows (numba's own loop: a BLAS call here would fight numba's threads for the cores)."""
    a, n = src.shape
    for i in prange(a):
        acc = np.zeros(n, dtype=src.dtype)
        for k in range(n):
            x = src[i, k]
            if x != 0.0:
                for j in range(n):
                    acc[j] += x * banded[k, j]
        dst[i] = acc


def _banded(kernel: np.ndarray, sources: np.ndarray) -> np.ndarray:
    """The n x n matrix ``B`` with ``x @ B`` the convolution of a row ``x`` by ``kernel``."""
    n = sources.shape[0]
    banded = np.zeros((n + 1, n))  # row n collects the taps that read zero
    outputs = np.broadcast_to(np.arange(n)[:, None], sources.shape)
    np.add.at(banded, (np.where(sources >= 0, sources, n), outputs), kernel[None, :])
    return banded[:n]


@dataclass(frozen=True)
class _Pass:
    """One 1-D pass of a smoothing, made ready for its kernel: along ``axis``, either the
    banded matrix of a short last axis (``banded``) or the taps and their sources."""

    axis: int
    kernel: np.ndarray
    sources: np.ndarray
    banded: np.ndarray | None


@lru_cache(maxsize=64)
def _passes(shape: tuple[int, int, int], sigmas: tuple[float, ...], mode: str, dtype: str):
    """The passes of a smoothing of ``sigmas`` over a volume of ``shape`` and ``dtype``, made
    once: the P-step smooths every cluster's volume of a window alike, every iteration."""
    passes = []
    for axis, sigma in enumerate(sigmas):
        if sigma == 0:
            continue
        kernel = gaussian_kernel(sigma)
        sources = _sources(shape[axis], kernel.shape[0], mode)
        short = axis == 2 and shape[2] <= _ROWS_MAX  # a small matrix product per row
        banded = _banded(kernel, sources).astype(dtype) if short else None
        passes.append(_Pass(axis, kernel.astype(dtype), sources, banded))
    return tuple(passes)


def _convolve_axis(src: np.ndarray, dst: np.ndarray, step: _Pass) -> None:
    """One 1-D pass along ``step.axis`` of the C-contiguous 3-D ``src`` into ``dst``."""
    n0, n1, n2 = src.shape
    if step.banded is not None:
        _convolve_rows(src.reshape(-1, n2), dst.reshape(-1, n2), step.banded)
        return
    shape = {0: (1, n0, n1 * n2), 1: (n0, n1, n2), 2: (n0 * n1, n2, 1)}[step.axis]
    _convolve_middle(src.reshape(shape), dst.reshape(shape), step.kernel, step.sources)


def gaussian_smooth(
    volume: np.ndarray,
    sigma: float | tuple[float, ...],
    out: np.ndarray | None = None,
    *,
    work: np.ndarray | None = None,
    mode: str = "constant",
) -> np.ndarray:
    """``volume`` (3-D) smoothed by a Gaussian of ``sigma`` voxels per axis (a scalar: every
    axis; 0 leaves an axis alone), beyond the border zero (``mode="constant"``) or mirrored
    (``"reflect"``); written into ``out`` (same shape
    and dtype) when given. ``work`` (C-contiguous, same shape and dtype; may be ``volume``
    itself when its values are no longer needed) is scratch for the passes, so a caller with
    reused buffers allocates nothing."""
    if volume.ndim != 3:
        raise ValueError(f"gaussian_smooth takes a 3-D volume, got {volume.ndim} dimensions")
    if mode not in MODES:
        raise ValueError(f"smoothing mode must be one of {MODES}, got {mode!r}")
    sigmas = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (3,))
    if np.any(sigmas < 0) or not np.all(np.isfinite(sigmas)):
        raise ValueError(f"smoothing sigma must be finite and >= 0, got {sigma}")
    if out is None:
        out = np.empty_like(volume, order="C")
    elif out is volume or out.shape != volume.shape or out.dtype != volume.dtype:
        raise ValueError("out must be a separate array with the volume's shape and dtype")
    if work is not None and (
        work is out
        or work.shape != volume.shape
        or work.dtype != volume.dtype
        or not work.flags.c_contiguous
    ):
        raise ValueError("work must be a C-contiguous array with the volume's shape and dtype")
    result = out if out.flags.c_contiguous else np.empty_like(volume, order="C")
    src = volume if volume.flags.c_contiguous else np.ascontiguousarray(volume)
    spare = work if work is not None else (src if src is not volume else None)
    for step in _passes(volume.shape, tuple(map(float, sigmas)), mode, volume.dtype.str):
        if src is not result:
            dst = result
        else:
            dst = spare = np.empty_like(result) if spare is None else spare
        _convolve_axis(src, dst, step)
        src = dst
    if src is not out:
        out[...] = src
    return out
