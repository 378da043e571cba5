"""A run's outputs: ``labels.npy``, ``probabilities.npy``, ``segmentation.h5``
(:mod:`spatialseg.segmentation_h5`), ``result.json`` and the figures.

Every file is written to a temporary name and renamed into place
(:func:`spatialseg.io._atomic.atomic_file`), and ``result.json`` is written last, so a
crashed run never leaves a directory that reads as a finished one; before a run writes,
:func:`clear_outputs` removes an earlier run's outputs from a reused run directory.

``result.json``'s top level describes the whole run: its events, its objects (one id per
object across the windows: events, velocity, first and last window), the iterations of all
windows and whether every window converged; ``windows`` holds each window's clusters,
convergence, curves and metrics.
"""

from __future__ import annotations

import json
import re
import shutil
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any, Self

import numpy as np

from spatialseg.io._atomic import atomic_file
from spatialseg.metrics import segmentation_metrics
from spatialseg.pipeline import SegmentationResult
from spatialseg.points import spatial_velocities
from spatialseg.recording import Recording
from spatialseg.segmentation_h5 import write_segmentation_h5
from spatialseg.window import WindowResult

__all__ = [
    "DATA_FILES",
    "FIGURES",
    "ArrayStream",
    "ProbabilityStream",
    "clear_outputs",
    "data_paths",
    "is_output",
    "objects_summary",
    "run_summary",
    "summarise",
    "window_summary",
    "write_json",
    "write_outputs",
]

#: The data files a run writes into its directory, ``result.json`` last.
DATA_FILES = ("labels.npy", "probabilities.npy", "segmentation.h5", "result.json")

#: The figures a run writes (:mod:`spatialseg.plots`): ``NAME.png``, and each window's
#: own with ``output.plots=windows``, ``NAME_w<window>.png``.
FIGURES = ("clusters", "warped_volumes", "variance", "theta", "windows", "objects")

_FIGURE = re.compile(rf"(?:{'|'.join(FIGURES)})(?:_w\d+)?\.png")

#: A hidden temporary of an output: ``.NAME.<hex>.tmp`` (an atomic write), ``.NAME.tmp``
#: (the same, before it took a random part) or ``.NAME.raw`` (a streamed run's rows).
_TEMPORARY = re.compile(r"\.(?P<name>.+?)(?:\.[0-9a-f]{12})?\.(?:tmp|raw)")


def is_output(name: str) -> bool:
    """True for the name of a file a run writes into its directory, or of its temporary."""
    hidden = _TEMPORARY.fullmatch(name)
    plain = hidden["name"] if hidden else name
    return plain in DATA_FILES or _FIGURE.fullmatch(plain) is not None


def clear_outputs(out_dir: Path) -> list[Path]:
    """Remove an earlier run's outputs and temporaries from ``out_dir`` (a reused run
    directory), so none survives beside a new run's config; other files are left alone."""
    if not out_dir.is_dir():
        return []
    stale = sorted(p for p in out_dir.iterdir() if is_output(p.name) and not p.is_dir())
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


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
        "n_fitted": len(res.prepared.points),  # the events the motions were fitted on
        "sampled": res.prepared.unsampled is not None,  # a dense span's fit sample
        "iterations": c.iterations,
        "converged": c.converged,
        "stop_reason": c.reason,
        "init_fallback": res.init_fallback,
        "init_method": res.init_method,
        "start_totals": res.start_totals,  # each start's total contrast (window.kept_run)
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


def recorded_window_summary(
    recording: Recording, index: np.ndarray, res: WindowResult
) -> dict[str, Any]:
    """:func:`window_summary` of the window whose events are ``index`` in ``recording``,
    scored against the recording's ground truth where it has one."""
    gt = recording.ground_truth
    if gt is None:
        return window_summary(res, None, None)
    return window_summary(res, gt.labels[index], gt.motions)


def summarise(
    recording: Recording,
    seg: SegmentationResult,
    cfg: Mapping[str, Any],
    timings: Mapping[str, float],
) -> dict[str, Any]:
    """The content of ``result.json``: the whole run, each window below in ``windows``."""
    windows = [
        recorded_window_summary(recording, index, res)
        for res, index in zip(seg.windows, seg.indices, strict=True)
    ]
    summary = run_summary(recording.name, len(recording.events), cfg, windows, timings)
    if recording.ground_truth is not None:
        summary["metrics"] = _aggregate_metrics(windows)
    return summary


def run_summary(
    name: str,
    n_events: int,
    cfg: Mapping[str, Any],
    windows: list[dict[str, Any]],
    timings: Mapping[str, float],
) -> dict[str, Any]:
    """The whole run's fields of ``result.json`` around the per-window summaries: events,
    objects (:func:`objects_summary`), all windows' iterations, and whether all converged."""
    objects = objects_summary(windows)
    labelled = sum(o["n_events"] for o in objects)
    return {
        "scene": name,
        "n_events": int(n_events),
        "n_labelled": labelled,
        "n_unassigned": int(n_events) - labelled,  # with any events outside every window
        "n_windows": len(windows),
        "n_objects": len(objects),
        "n_clusters": cfg["n_clusters"],
        "model": cfg["model"]["name"],
        "objective": cfg["objective"]["name"],
        "optimizer": cfg["optimizer"].get("name") or cfg["optimizer"].get("_target_", ""),
        "units": windows[0]["units"] if windows else None,  # the model's, in every window
        "objects": objects,
        "iterations": sum(w["iterations"] for w in windows),
        "converged": all(w["converged"] for w in windows),
        "timings": {k: round(float(v), 6) for k, v in timings.items()},
        "windows": windows,
    }


def objects_summary(windows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Each object's whole-run entry, by id, from the windows' clusters: its events, its
    velocity and the first and last window it appears in (:func:`_object_entry`)."""
    seen: dict[int, list[tuple[int, int, list[float]]]] = {}
    for w, window in enumerate(windows):
        for c in window["clusters"]:
            seen.setdefault(int(c["id"]), []).append((w, int(c["n_events"]), c["theta"]))
    return [_object_entry(obj, seen[obj]) for obj in sorted(seen)]


def _object_entry(obj: int, seen: list[tuple[int, int, list[float]]]) -> dict[str, Any]:
    """One object from its ``(window, events, velocity)`` per window: the velocity is the
    mean of its windows' velocities weighted by its events in each (the plain mean for an
    object without events), so a window it barely appears in counts little."""
    windows = [w for w, _, _ in seen]
    counts = np.array([n for _, n, _ in seen], dtype=np.float64)
    weights = counts if counts.sum() > 0 else np.ones_like(counts)
    velocity = np.average(np.array([v for _, _, v in seen]), axis=0, weights=weights)
    return {
        "id": obj,
        "n_events": int(counts.sum()),
        "velocity": velocity.tolist(),
        "first_window": min(windows),
        "last_window": max(windows),
        "n_windows": len(windows),
    }


def _aggregate_metrics(windows: list[dict[str, Any]]) -> dict[str, Any]:
    """Metrics of a single window, or event-weighted means of accuracy over several."""
    if len(windows) == 1:
        return windows[0]["metrics"]
    weights = np.array([w["n_events"] for w in windows], float)
    keys = ("accuracy", "unassigned_share")
    return {k: float(np.average([w["metrics"][k] for w in windows], weights=weights)) for k in keys}


def _atomic_save(path: Path, write: Callable[[IO[bytes]], object]) -> None:
    """Write through a temporary sibling (:func:`atomic_file`), then rename into place."""
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        write(f)


def data_paths(out_dir: Path) -> tuple[Path, Path, Path, Path]:
    """The paths of ``labels.npy``, ``probabilities.npy``, ``segmentation.h5`` and
    ``result.json`` in ``out_dir``."""
    labels, probs, h5, result = (out_dir / name for name in DATA_FILES)
    return labels, probs, h5, result


def write_outputs(
    out_dir: Path,
    recording: Recording,
    seg: SegmentationResult,
    summary: Mapping[str, Any],
    settings: Mapping[str, Any],
) -> list[Path]:
    """Write labels, probabilities, with ``output.h5`` in ``settings`` segmentation.h5 (the
    recording's events, the run's labels and objects), and result.json (last)."""
    labels, probs, h5, result = data_paths(out_dir)
    _atomic_save(labels, lambda f: np.save(f, seg.labels.astype(np.int64)))
    _atomic_save(probs, lambda f: np.save(f, seg.probabilities.astype(np.float32)))
    written = [labels, probs]
    if settings["output"]["h5"]:
        write_segmentation_h5(h5, recording.events, labels, probs, summary, settings)
        written.append(h5)
    write_json(result, summary)
    return [*written, result]


def write_json(path: Path, summary: Mapping[str, Any]) -> None:
    """Write ``result.json`` atomically (the last file of a run)."""
    text = json.dumps(summary, indent=2).encode()
    _atomic_save(path, lambda f: f.write(text))


class ArrayStream:
    """Rows appended window by window to a temporary file, then written as one ``.npy``
    (atomically, copied in blocks), so a streamed run never holds all labels in memory.

    Used as a context manager, it removes its temporary file however the block ends (an
    error, Ctrl-C, or a SIGTERM that :func:`spatialseg.cli.guarded` turns into an exit).
    """

    def __init__(self, path: Path, dtype: Any, width: int | None = None) -> None:
        self.path, self.dtype, self.width, self.rows = path, np.dtype(dtype), width, 0
        self._raw_path = path.with_name(f".{path.name}.raw")
        self._raw = open(self._raw_path, "wb")  # noqa: SIM115 (closed by finish or abort)

    def __enter__(self) -> Self:
        """The stream, whose temporary file :meth:`__exit__` removes."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Remove the temporary file (already gone after :meth:`finish`)."""
        self.abort()

    def append(self, rows: np.ndarray) -> None:
        """Append rows (N, or N x width) in the stream's dtype."""
        block = np.ascontiguousarray(rows, dtype=self.dtype)
        self._raw.write(block.tobytes())
        self.rows += len(block)

    def abort(self) -> None:
        """Drop the appended rows (a failed run leaves no partial output); idempotent."""
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
