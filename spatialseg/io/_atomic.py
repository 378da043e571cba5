"""Atomic writes: build a file or directory under a hidden temporary sibling, then rename it.

A reader never sees a partial result: the target path either does not exist, holds the
previous version, or holds the complete new one. Temporaries are named
``.<name>.<random>.tmp`` next to the target (same filesystem, so the rename is atomic); a
crash leaves at most such a hidden leftover, never a half-written target.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_directory", "atomic_file"]

#: Directories can be fsync'ed (to make a rename durable) on POSIX systems only.
_SYNC_DIRECTORIES = os.name == "posix"


def _sibling(path: Path, tag: str) -> Path:
    """A fresh hidden path next to ``path``, so that renaming it onto ``path`` is atomic."""
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.{tag}")


def _fsync(path: Path) -> None:
    """Flush a file (or, on POSIX, a directory's entries) to disk so a rename is durable."""
    if path.is_dir() and not _SYNC_DIRECTORIES:
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_tree(root: Path) -> None:
    """Flush every file and directory under ``root`` (children first) to disk."""
    for folder, _, files in os.walk(root, topdown=False):
        for name in files:
            _fsync(Path(folder, name))
        _fsync(Path(folder))


def _exists(path: Path) -> bool:
    """True if anything, including a dangling symlink, is at ``path``."""
    return path.exists() or path.is_symlink()


@contextmanager
def atomic_file(path: Path) -> Iterator[Path]:
    """Yield a temporary sibling path to write; on success it replaces ``path`` atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _sibling(path, "tmp")
    try:
        yield tmp
        _fsync(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync(path.parent)


def _check_target(path: Path, overwrite: bool) -> None:
    """Refuse to replace an existing path unless asked, and never replace a plain file."""
    if not _exists(path):
        return
    if not overwrite:
        raise FileExistsError(f"{path}: already exists; pass overwrite=True to replace it")
    if not path.is_dir():
        raise NotADirectoryError(f"{path}: exists and is not a directory; remove it first")


def _swap_in(tmp: Path, path: Path) -> None:
    """Rename ``tmp`` onto ``path``; an existing ``path`` is moved aside first, then deleted."""
    if not _exists(path):
        os.replace(tmp, path)
        return
    old = _sibling(path, "old")
    os.replace(path, old)
    try:
        os.replace(tmp, path)
    except BaseException:
        os.replace(old, path)
        raise
    if old.is_symlink():
        old.unlink()
    else:
        shutil.rmtree(old)


@contextmanager
def atomic_directory(path: Path, *, overwrite: bool) -> Iterator[Path]:
    """Yield an empty temporary sibling directory; on success it becomes ``path`` atomically."""
    _check_target(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _sibling(path, "tmp")
    tmp.mkdir()
    try:
        yield tmp
        _fsync_tree(tmp)
        _swap_in(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _fsync(path.parent)
