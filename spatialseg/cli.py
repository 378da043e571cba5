"""The command line: ``python -m spatialseg +scene=interior optimizer=ssa_ga``.

A user mistake (unknown config key, malformed recording, empty window) ends the run with
one ``error:`` line on stderr and exit status 2, never a traceback. Set
``SPATIALSEG_DEBUG=1`` to get the full traceback instead. A multirun runs every job; if any
failed, it ends with one ``error: N of M jobs failed`` line and exit status 1. A config
option that no config directory holds (``+scene=nosuch``; a user's own go in ``--config-dir``)
ends in one ``error:`` line listing the options, exit status 2. SIGTERM ends a run like an
error (exit status 143), so it leaves no temporary files behind; Ctrl-C likewise ends it in
one line with exit status 130. With MLflow tracking, the job's run opens before any work and
ends FINISHED, FAILED or (SIGTERM, Ctrl-C) KILLED.

A run directory holds one run: before it writes (before it validates the config, even), a
run removes the outputs an earlier run left in a reused ``hydra.run.dir``. The run ends with
a table of the objects found over the whole recording, the run directory and, with MLflow
tracking, the command that opens the store.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import signal
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import hydra
import numpy as np
from hydra._internal.utils import run_and_report
from hydra.core.hydra_config import HydraConfig
from hydra.errors import (
    ConfigCompositionException,
    MissingConfigException,
    OverrideParseException,
    SearchPathException,
)
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from spatialseg.checks import boolean_setting, plural, unknown_key
from spatialseg.config import build_optimizer, conf_dir, validate_run
from spatialseg.interrupts import interruption, raise_pending, stop_on_signals
from spatialseg.progress import progress_bar

if TYPE_CHECKING:
    from spatialseg.recording import Recording
    from spatialseg.settings import Settings
    from spatialseg.tracking import LiveRun
    from spatialseg.window import WindowResult

__all__ = ["guarded", "launch", "main", "run"]

log = logging.getLogger("spatialseg")

#: Exceptions that signal a user mistake (bad input or config), reported in one line.
USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, PermissionError)


def _windows(ids: Sequence[int], shown: int = 4) -> str:
    """``window 2``, ``windows 0, 1, 2``, or ``12 windows`` when there are many."""
    if len(ids) == 1:
        return f"window {ids[0]}"
    if len(ids) > shown:
        return f"{len(ids)} windows"
    return f"windows {', '.join(map(str, ids))}"


def _convergence(windows: Sequence[Mapping[str, Any]]) -> str:
    """How many windows converged, and why the others stopped (grouped by reason)."""
    stopped: dict[str, list[int]] = {}
    for i, w in enumerate(windows):
        if not w["converged"]:
            stopped.setdefault(w["stop_reason"], []).append(i)
    done = len(windows) - sum(map(len, stopped.values()))
    text = f"{done} of {plural(len(windows), 'window')} converged"
    if not stopped:
        return text
    return f"{text} ({'; '.join(f'{_windows(ids)}: {why}' for why, ids in stopped.items())})"


def _report(summary: Mapping[str, Any], out_dir: Path, tracked: str | None) -> None:
    """Log the end-of-run summary of the whole recording: its events and windows, a table of
    its objects, accuracy, time, the run directory and how to open the MLflow run."""
    windows, objects = summary["windows"], summary["objects"]
    seen = [o for o in objects if o["n_events"]]
    log.info(
        "%s: %d events in %s, %d labelled as %s; %d iterations, %s",
        summary["scene"],
        summary["n_events"],
        plural(len(windows), "window"),
        summary["n_labelled"],
        plural(len(seen), "object"),
        summary["iterations"],
        _convergence(windows),
    )
    log.info(
        "  object   events  windows  velocity [vx, vy, vz] %s: the mean over its windows, "
        "weighted by its events in each",
        summary["units"],
    )
    for o in seen:
        span = f"{o['first_window']}-{o['last_window']}"
        velocity = ", ".join(f"{v:+.4f}" for v in o["velocity"])
        log.info("  %6d %8d %8s  [%s]", o["id"], o["n_events"], span, velocity)
    if len(seen) < len(objects):
        empty = ", ".join(str(o["id"]) for o in objects if not o["n_events"])
        log.info("  no events: object %s (a window's empty cluster)", empty)
    if "metrics" in summary:
        how = "" if len(windows) == 1 else "; each window matched alone, weighted by its events"
        log.info("  accuracy %.4f (ground truth%s)", summary["metrics"]["accuracy"], how)
    log.info("  time %.2f s; run directory %s", summary["timings"]["total"], out_dir)
    if tracked:
        log.info("  MLflow: %s", tracked)


def _restart_log(out_dir: Path) -> None:
    """Empty this run's log file in ``out_dir`` (Hydra's ``<job>.log``, which it opens to
    append) of an earlier run's lines; nothing of this run is logged yet."""
    for handler in logging.getLogger().handlers:
        if not isinstance(handler, logging.FileHandler) or handler.stream is None:
            continue
        if Path(handler.baseFilename).parent.resolve() == out_dir.resolve():
            with handler.lock or contextlib.nullcontext():
                handler.stream.seek(0)
                handler.stream.truncate()


def _fresh_run_dir(out_dir: Path) -> None:
    """Make a reused run directory hold this run only: remove an earlier run's outputs
    (:func:`spatialseg.results.clear_outputs`) and its lines in the log file."""
    from spatialseg.results import clear_outputs

    _restart_log(out_dir)
    stale = clear_outputs(out_dir)
    if stale:
        log.info("removed %s of an earlier run from %s", plural(len(stale), "output"), out_dir)


#: ``output.plots``' value that adds each window's own figures to the summary figures.
EVERY_WINDOW = "windows"


def _check_output(output: Mapping[str, Any]) -> None:
    """Refuse an ``output.*`` switch that is not true or false (``output.h5=no`` is the
    string 'no', which would read as true); ``output.plots`` may also be ``windows``."""
    for key, value in output.items():
        if key == "plots" and value == EVERY_WINDOW:
            continue
        try:
            boolean_setting(value, f"output.{key}")
        except ValueError as error:
            extra = f" (or {EVERY_WINDOW}: every window's figures too)" if key == "plots" else ""
            raise ValueError(f"{error}{extra}") from None


def run(cfg: DictConfig) -> dict[str, Any]:
    """Validate the config, segment the scene, write the outputs; return result.json's content.

    The MLflow run is open from here on (:func:`spatialseg.tracking.live_run`): it shows the
    job as RUNNING while it loads and segments, and ends as the job ends."""
    from spatialseg.tracking import live_run

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    _fresh_run_dir(out_dir)
    with live_run(cfg) as tracked:
        return _run_tracked(cfg, out_dir, tracked)


def _run_tracked(cfg: DictConfig, out_dir: Path, tracked: LiveRun) -> dict[str, Any]:
    """:func:`run`'s work once its MLflow run is open (``tracked``)."""
    from spatialseg.pipeline import segment_loaded
    from spatialseg.results import recorded_window_summary, summarise, write_outputs
    from spatialseg.scenes import load_scene
    from spatialseg.window import check_config

    validate_run(cfg)
    plain = OmegaConf.to_container(cfg, resolve=True)
    settings = check_config(plain)
    _check_output(plain["output"])
    start = time.perf_counter()
    if cfg.scene.get("stream"):
        return run_stream(cfg, plain, settings, out_dir, tracked)
    recording = load_scene(
        cfg.scene,
        seed=int(cfg.seed),
        window_events=settings.window.events,
        windows=settings.window.count,
    )
    timings = {"load": time.perf_counter() - start}
    warn_motion_count(recording, settings)
    optimizer = build_optimizer(cfg)
    begin = time.perf_counter()
    scored = recording  # its ground truth scores each window as it ends

    def log_window(index: np.ndarray, res: WindowResult) -> None:
        """Log a window's metrics to the live run as it ends."""
        summary = recorded_window_summary(scored, index, res)
        tracked.log_windows([summary], prefixed=len(scored.depth_maps) != 2)  # one window: bare
        raise_pending()

    recording, seg = segment_loaded(
        recording,
        settings,
        optimizer,
        seed=int(cfg.seed),
        progress=bool(cfg.output.progress),
        on_window=log_window,
    )
    timings["segment"] = time.perf_counter() - begin
    timings["total"] = time.perf_counter() - start
    summary = summarise(recording, seg, plain, timings)
    if cfg.output.plots:
        from spatialseg.plots import figure_count, save_result_figures

        every_window = cfg.output.plots == EVERY_WINDOW
        count = figure_count(len(seg.windows), every_window=every_window)
        log.info("drawing %s ...", plural(count, "figure"))
        save_result_figures(out_dir, recording, seg, every_window=every_window)
    write_outputs(out_dir, recording, seg, summary, plain)
    _report(summary, out_dir, tracked.finish(summary, out_dir))
    return summary


def warn_motion_count(recording: Recording, settings: Settings) -> None:
    """One WARNING line when the recording's ground truth holds another number of motions
    (its objects, a moving camera's static scene among them) than ``n_clusters`` asks for
    (not with ``auto``): a scene of three motions segmented into the default two scores low
    with nothing else to say why."""
    truth, wanted = recording.ground_truth, settings.cluster_count
    if truth is None or wanted is None:
        return
    motions = len(np.unique(truth.labels[truth.labels >= 0]))
    if motions and motions != wanted:
        log.warning(
            "the ground truth has %s but n_clusters=%d: set n_clusters=%d (or auto) to "
            "segment each apart",
            plural(motions, "motion"),
            wanted,
            motions,
        )


def _real_time(span: tuple[float, float], wall: float) -> dict[str, float]:
    """The recording's duration (last minus first event time) and real-time factor."""
    recording = span[1] - span[0]
    return {"recording_s": recording, "real_time_factor": recording / wall}


def run_stream(
    cfg: DictConfig, plain: dict[str, Any], settings: Settings, out_dir: Path, tracked: LiveRun
) -> dict[str, Any]:
    """``scene.stream=true``: read, segment and write the file window by window, holding one
    window in memory (with ``window.parallel``, a few per worker: :func:`segment_stream`);
    the outputs are those of any run except the figures and metrics. Each
    window's metrics go to MLflow as it ends; the end reports the real-time factor. ``plain``
    is the run config (the outputs record it), ``settings`` the method's."""
    from spatialseg.pipeline import segment_stream
    from spatialseg.results import (
        ArrayStream,
        ProbabilityStream,
        data_paths,
        run_summary,
        window_summary,
        write_json,
    )
    from spatialseg.scenes import stream_scene
    from spatialseg.segmentation_h5 import SegmentationH5

    start = time.perf_counter()
    if settings.depth.name in ("recording", "onnx"):
        raise ValueError(
            f"scene.stream=true makes depth maps per window without images: use "
            f"depth=constant or depth=ground_plane, not depth={settings.depth.name}"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    labels_path, probabilities_path, h5_path, result_path = data_paths(out_dir)
    with (  # the temporary files go however the block ends
        ArrayStream(labels_path, np.int64) as labels,
        ProbabilityStream(probabilities_path) as probabilities,
        SegmentationH5(h5_path) if cfg.output.h5 else contextlib.nullcontext() as h5,
        progress_bar(None, "window", enabled=bool(cfg.output.progress)) as bar,
    ):
        windows, handover = [], None
        span = (np.inf, -np.inf)  # the first and last event times seen
        chunks = stream_scene(plain["scene"], window_events=settings.window.events)
        segmented = segment_stream(
            chunks,
            settings,
            build_optimizer(cfg),
            seed=int(cfg.seed),
            progress=bool(cfg.output.progress),
        )
        for window, seg in segmented:
            handover = seg.handover or handover
            labels.append(seg.labels)
            probabilities.append_segmentation(seg)
            if h5 is not None:
                h5.append_events(window.events)
            t = window.events.t
            span = (min(span[0], float(t.min())), max(span[1], float(t.max())))
            ended = [window_summary(res, None, None) for res in seg.windows]
            tracked.log_windows(ended)
            windows += ended
            bar(len(ended))
            raise_pending()
        if not windows:
            raise ValueError(f"{cfg.scene.path or cfg.scene.name}: the file has no events")
        wall = time.perf_counter() - start
        timings = {"total": wall, **_real_time(span, wall)}
        log.info(
            "streamed %.2f s of recording in %.2f s: real-time factor %.2f (> 1: faster "
            "than real time)",
            timings["recording_s"],
            wall,
            timings["real_time_factor"],
        )
        summary = run_summary(str(cfg.scene.name), labels.rows, plain, windows, timings)
        summary["stream"] = True
        labels.finish()
        probabilities.finish_objects(handover.boundary.next_id if handover else 1)
        if h5 is not None:
            h5.finish(labels_path, probabilities_path, summary, plain)
    write_json(result_path, summary)
    _report(summary, out_dir, tracked.finish(summary, out_dir))
    return summary


def _fail_job(exc: Exception) -> None:
    """Record a failed multirun job and report it, so the sweep goes on with the next job
    (its MLflow run has ended FAILED already)."""
    from spatialseg.tracking import mark_job

    mark_job(exc)
    print(f"error: {exc}", file=sys.stderr)
    if not isinstance(exc, USER_ERRORS):
        log.error("job failed", exc_info=exc)


def _exit_interrupted() -> NoReturn:
    """End a run stopped by Ctrl-C in one line, exit status 128 + SIGINT."""
    print("error: interrupted by SIGINT", file=sys.stderr)
    raise SystemExit(128 + signal.SIGINT) from None


def guarded(task: Callable[[DictConfig], object]) -> Callable[[DictConfig], None]:
    """Wrap a Hydra task so a user mistake ends in one ``error:`` line and exit status 2,
    Ctrl-C in one line and exit status 130.

    In a multirun, a failing job (any exception) is recorded as failed and the sweep goes on;
    every job leaves its outcome for the sweep's exit status (:func:`tracking.mark_job`).
    """

    def wrapper(cfg: DictConfig) -> None:
        from spatialseg.tracking import mark_job

        try:
            with stop_on_signals():
                task(cfg)
                raise_pending()
            mark_job(None)
        except KeyboardInterrupt:
            if os.environ.get("SPATIALSEG_DEBUG"):
                raise
            _exit_interrupted()
        except Exception as exc:
            if os.environ.get("SPATIALSEG_DEBUG"):
                raise
            stop = interruption(exc)  # a signal's exception that a library's clean-up replaced
            if isinstance(stop, SystemExit):
                raise SystemExit(stop.code) from None  # SIGTERM's handler printed its line
            if stop is not None:
                _exit_interrupted()
            if HydraConfig.get().mode == RunMode.MULTIRUN:
                _fail_job(exc)
                return
            if not isinstance(exc, USER_ERRORS):
                raise
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(2)

    return wrapper


def launch(task: Callable[[DictConfig], object], config_name: str) -> None:
    """Start a Hydra app on ``conf/<config_name>.yaml`` running ``task`` guarded.

    The process ends after it: everything it made is frozen out of the garbage collector
    (:func:`gc.freeze`), so the interpreter's exit does not trace numba's and the other
    libraries' objects once more (0.3 s of a 65,000-event run)."""
    try:
        path = str(conf_dir())
    except USER_ERRORS as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    main_of = hydra.main(version_base="1.3", config_path=path, config_name=config_name)
    try:
        _run_reporting_missing_configs(main_of(guarded(task)))
        _exit_if_jobs_failed()
    finally:
        gc.freeze()


def _first_line(exc: Exception) -> str:
    """The first line of a Hydra error's message (the rest is its advice for Hydra users)."""
    return str(exc).strip().splitlines()[0]


def _missing_config_line(exc: MissingConfigException | SearchPathException) -> str:
    """Hydra's first line of a missing-config error, with the group's options and the fix."""
    line = _first_line(exc)
    if not isinstance(exc, MissingConfigException) or not exc.options or not exc.missing_cfg_file:
        return line
    group = exc.missing_cfg_file.rpartition("/")[0]
    return (
        f"{line}; options in '{group}': {', '.join(exc.options)}; "
        f"or put your own in DIR/{group}/NAME.yaml and add --config-dir DIR"
    )


def _override_line(exc: ConfigCompositionException | OverrideParseException) -> str:
    """One line for an override Hydra could not apply: an unknown key (``clustering.max_iter=3``)
    names the closest known key, or the keys its section has; a malformed one says so."""
    if isinstance(exc, OverrideParseException):
        grammar = "https://hydra.cc/docs/advanced/override_grammar/basic/"
        return f"cannot parse an override: {_first_line(exc)} (the grammar: {grammar})"
    cause = exc.__cause__
    full_key = getattr(cause, "full_key", None)
    parent = getattr(cause, "parent_node", None)
    if not isinstance(cause, OmegaConfBaseException) or not full_key:
        return _first_line(exc)
    if not isinstance(parent, DictConfig):
        return f"unknown config key '{full_key}' (--cfg job lists every setting)"
    known = [str(k) for k in parent if not str(k).startswith("_") and k != "hydra"]
    return f"{unknown_key(str(full_key), known)} (--cfg job lists every setting)"


def _reraise(exc: Exception) -> None:
    """Raise ``exc`` again (for Hydra's own report of it)."""
    raise exc


def _run_reporting_missing_configs(app: Callable[[], None]) -> None:
    """Run the Hydra ``app``; an unknown config option, key or ``--config-dir``, or a
    malformed override, ends in one ``error:`` line and exit status 2.

    Hydra prints these in many lines and exits 1; with HYDRA_FULL_ERROR set it raises them,
    so they are caught here and any other error goes back to Hydra's own report. A user's
    own HYDRA_FULL_ERROR=1 leaves every error to Hydra.
    """
    if os.environ.get("HYDRA_FULL_ERROR"):
        app()
        return
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        app()
    except (MissingConfigException, SearchPathException) as exc:
        print(f"error: {_missing_config_line(exc)}", file=sys.stderr)
        sys.exit(2)
    except (ConfigCompositionException, OverrideParseException) as exc:
        print(f"error: {_override_line(exc)}", file=sys.stderr)
        sys.exit(2)
    except Exception as exc:
        del os.environ["HYDRA_FULL_ERROR"]
        run_and_report(partial(_reraise, exc))
    finally:
        os.environ.pop("HYDRA_FULL_ERROR", None)


def _exit_if_jobs_failed() -> None:
    """After a multirun, exit with status 1 and one summary line if any job failed."""
    from spatialseg.tracking import last_sweep

    tally = last_sweep()
    if tally is None or not tally.failed:
        return
    parent = f"; MLflow parent run {tally.parent_run_id}" if tally.parent_run_id else ""
    print(
        f"error: {tally.failed} of {tally.total} jobs failed; "
        f"see {tally.jobs_dir}/*.failed{parent}",
        file=sys.stderr,
    )
    sys.exit(1)


def main() -> None:
    """Console entry point (``python -m spatialseg``)."""
    launch(run, "config")
