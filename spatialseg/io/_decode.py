"""What every format's decoder shares: the :class:`Block` it yields, and for a damaged file one
``ValueError`` naming the file, the place in it, the problem and the fix.

Every reader runs its third-party decoders (zipfile and numpy for ``.npz``/``.npy``, h5py,
Pillow, the Rust ``aedat`` extension) inside :func:`decoding`, so whatever
they raise on damaged bytes (``BadZipFile``, ``KeyError``, ``SyntaxError``, a pyo3
``PanicException``, which is a ``BaseException``) reaches the caller as one line.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import numpy as np

from spatialseg.recording import Keyframe

__all__ = ["Block", "damaged", "decoding"]

#: The likely cause of a decoding failure and what to do about it.
_FIX = "the file is damaged or truncated; copy or export it again"
#: Never turned into a ValueError: the user or the interpreter stopping the read.
_PASS_THROUGH = (KeyboardInterrupt, SystemExit, GeneratorExit)
_MAX_DETAIL = 160  # characters of a decoder's own message kept in ours


class Block(NamedTuple):
    """Events a decoder read, in file order: ``t`` in seconds, ``x``, ``y`` pixels and ``p`` as
    stored (0/1, -1/+1 or bool), plus any keyframes decoded among them (AEDAT4 frames)."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    p: np.ndarray
    keyframes: tuple[Keyframe, ...] = ()


def _one_line(text: str, limit: int = _MAX_DETAIL) -> str:
    """``text`` with runs of whitespace (newlines too) as one space, cut to ``limit`` characters."""
    flat = re.sub(r"\s+", " ", text).strip()
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."


def damaged(path: Path, problem: str, where: str | None = None) -> ValueError:
    """The error for a damaged file: ``<path> <where>: <problem>; <fix>``, on one line."""
    place = f" {where}" if where else ""
    return ValueError(f"{path}{place}: {_one_line(problem, 2 * _MAX_DETAIL)}; {_FIX}")


@contextmanager
def decoding(path: Path, what: str, where: str | None = None) -> Iterator[None]:
    """Turn any failure of the decoder calls inside the block into :func:`damaged`'s error.

    Keep the block to the decoder's calls on the file's bytes: anything raised there,
    Rust panics included, is the file's fault; only interruptions pass through.
    """
    try:
        yield
    except _PASS_THROUGH:
        raise
    except BaseException as exc:
        detail = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise damaged(path, f"cannot read as {what} ({_one_line(detail)})", where) from exc
