"""A run's outputs: ``labels.npy``, ``probabilities.npy``, ``result.json`` and the figures.

Every file is written to a temporary name and renamed into place, and ``result.json`` is
written last, so a crashed run never leaves a directory that reads as a finished one.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from spatialseg.metrics import segmentation_metrics
from spatialseg.pipeline import SegmentationResult, WindowResult, spatial_velocities
from spatialseg.recording import Recording

__all__ = [
    "ArrayStream",
    "ProbabilityStream",
    "run_summary",
    "summarise",
    "window_summary",
    "write_json",
    "write_outputs",
]


def window_summary(res: WindowResult, truth: np.ndarray | None, motions: Any) -> dict[str, Any]:
    """JSON-ready description of one window: clusters, convergence, curves, metrics."""
    c = res.clustering
    counts = np.bincount(res.labels[res.labels >= 0], minlength=c.thetas.shape[0])
    thetas = spatial_velocities(c.thetas)
    ids = np.arange(len(thetas)) if res.ids is None else res.ids
    summary: dict[str, Any] = {
        "n_events": int(res.labels.size),
        "n_unassigned": int(np.sum(res.labels < 0)),
        "clusters": [
            {
                "id": int(ids[j]),
                "cluster": j,
                "theta": thetas[j].tolist(),
                "variance": float(c.values[j]),
                "n_events": int(counts[j]),
                "empty": bool(counts[j] == 0),  # no event's likeliest: no object seen
            }
            for j in range(thetas.shape[0])
        ],
        "units": res.prepared.units,
        "t_ref": res.t_ref,
        "grid_shape": list(res.prepared.grid.shape),
        "iterations": c.iterations,
        "converged": c.converged,
        "stop_reason": c.reason,
        "init_fallback": res.init_fallback,
        "init_method": res.init_method,
        "timings": {k: round(v, 6) for k, v in res.timings.items()},
        "history": {
            "total": [r.total for r in c.history],
            "per_cluster": [r.per_cluster.tolist() for r in c.history],
            "thetas": [r.thetas.tolist() for r in c.history],
            "n_evals": [r.n_evals for r in c.history],
        },
    }
    if truth is not None:
        velocities = thetas if res.prepared.units == "m/s" else None
        summary["metrics"] = segmentation_metrics(
            res.labels, truth, pred_velocities=velocities, true_motions=motions
        )  # the window's own clusters, matched within the window
    return summary


def summarise(
    recording: Recording,
    seg: SegmentationResult,
    cfg: Mapping[str, Any],
    timings: Mapping[str, float],
) -> dict[str, Any]:
    """The content of ``result.json``; the first window's fields are also at the top level."""
    gt = recording.ground_truth
    windows = []
    for res, index in zip(seg.windows, seg.indices, strict=True):
        truth = gt.labels[index] if gt is not None else None
        windows.append(window_summary(res, truth, gt.motions if gt is not None else None))
    summary = run_summary(recording.name, len(recording.events), cfg, windows, timings)
    if gt is not None:
        summary["metrics"] = _aggregate_metrics(windows)
    return summary


def run_summary(
    name: str,
    n_events: int,
    cfg: Mapping[str, Any],
    windows: list[dict[str, Any]],
    timings: Mapping[str, float],
) -> dict[str, Any]:
    """The run-level fields of ``result.json`` around the per-window summaries; the first
    window's clusters and convergence are repeated at the top level."""
    first = windows[0]
    return {
        "scene": name,
        "n_events": int(n_events),
        "n_clusters": cfg["n_clusters"],
        "model": cfg["model"]["name"],
        "objective": cfg["objective"]["name"],
        "optimizer": cfg["optimizer"].get("_target_", ""),
        **{k: first[k] for k in ("clusters", "units", "iterations", "converged", "stop_reason")},
        "timings": {k: round(float(v), 6) for k, v in timings.items()},
        "windows": windows,
    }


def _aggregate_metrics(windows: list[dict[str, Any]]) -> dict[str, Any]:
    """Metrics of a single window, or event-weighted means of accuracy over several."""
    if len(windows) == 1:
        return windows[0]["metrics"]
    weights = np.array([w["n_events"] for w in windows], float)
    keys = ("accuracy", "unassigned_share")
    return {k: float(np.average([w["metrics"][k] for w in windows], weights=weights)) for k in keys}


def _atomic_save(path: Path, write: Any) -> None:
    """Write through a temporary file in the same directory, then rename into place."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        write(f)
    os.replace(tmp, path)


def write_outputs(out_dir: Path, seg: SegmentationResult, summary: Mapping[str, Any]) -> list[Path]:
    """Write labels, probabilities and result.json (last) into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    labels, probs, result = (
        out_dir / n for n in ("labels.npy", "probabilities.npy", "result.json")
    )
    _atomic_save(labels, lambda f: np.save(f, seg.labels.astype(np.int64)))
    _atomic_save(probs, lambda f: np.save(f, seg.probabilities.astype(np.float32)))
    write_json(result, summary)
    return [labels, probs, result]


def write_json(path: Path, summary: Mapping[str, Any]) -> None:
    """Write ``result.json`` atomically (the last file of a run)."""
    text = json.dumps(summary, indent=2).encode()
    _atomic_save(path, lambda f: f.write(text))


class ArrayStream:
    """Rows appended window by window to a temporary file, then written as one ``.npy``
    (atomically, copied in blocks), so a streamed run never holds all labels in memory."""

    def __init__(self, path: Path, dtype: Any, width: int | None = None) -> None:
        self.path, self.dtype, self.width, self.rows = path, np.dtype(dtype), width, 0
        self._raw_path = path.with_name(f".{path.name}.raw")
        self._raw = open(self._raw_path, "wb")  # noqa: SIM115 (closed by finish)

    def append(self, rows: np.ndarray) -> None:
        """Append rows (N, or N x width) in the stream's dtype."""
        block = np.ascontiguousarray(rows, dtype=self.dtype)
        self._raw.write(block.tobytes())
        self.rows += len(block)

    def abort(self) -> None:
        """Drop the appended rows (a failed run leaves no partial output)."""
        self._raw.close()
        self._raw_path.unlink(missing_ok=True)

    def finish(self) -> Path:
        """Write the ``.npy`` from the appended rows and remove the temporary file."""
        return self._write(self.width, lambda raw, f: shutil.copyfileobj(raw, f, 1 << 20))

    def _write(self, width: int | None, copy: Any) -> Path:
        """Close the temporary file and write the ``.npy`` of ``rows x width`` (``rows``
        alone for None), its body from ``copy(raw file, output file)``."""
        self._raw.close()
        shape = (self.rows,) if width is None else (self.rows, width)
        header = {
            "descr": np.lib.format.dtype_to_descr(self.dtype),
            "fortran_order": False,
            "shape": shape,
        }

        def write(f: Any) -> None:
            np.lib.format.write_array_header_1_0(f, header)
            with open(self._raw_path, "rb") as raw:
                copy(raw, f)

        _atomic_save(self.path, write)
        self._raw_path.unlink()
        return self.path


class ProbabilityStream(ArrayStream):
    """Memberships appended window by window (rows x the window's clusters) with each
    cluster's object id, written at the end as one ``rows x objects`` ``.npy`` (column =
    object id), one window in memory at a time."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, np.float32, 0)
        self._blocks: list[tuple[int, np.ndarray]] = []

    def append_window(self, rows: np.ndarray, ids: np.ndarray) -> None:
        """Append one window's memberships and its clusters' object ids."""
        self.append(rows)
        self._blocks.append((len(rows), np.asarray(ids)))

    def append_segmentation(self, seg: SegmentationResult) -> None:
        """Append every event of ``seg`` in order: each window's memberships, zeros for
        events outside every window."""
        done, none = 0, np.zeros(0, dtype=np.int64)
        for res, index in zip(seg.windows, seg.indices, strict=True):
            if len(index) and index[0] > done:
                self.append_window(np.zeros((index[0] - done, 0)), none)
            self.append_window(seg.probabilities[index][:, res.ids], res.ids)
            done = index[-1] + 1 if len(index) else done
        if len(seg.labels) > done:
            self.append_window(np.zeros((len(seg.labels) - done, 0)), none)

    def finish_objects(self, n_objects: int) -> Path:
        """Write the ``.npy`` with one column per object id."""

        def copy(raw: Any, f: Any) -> None:
            for count, ids in self._blocks:
                block = np.fromfile(raw, self.dtype, count * len(ids)).reshape(count, len(ids))
                out = np.zeros((count, n_objects), self.dtype)
                out[:, ids] = block
                f.write(out.tobytes())

        return self._write(n_objects, copy)
