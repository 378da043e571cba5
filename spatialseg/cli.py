"""The command line: ``python -m spatialseg +scene=interior optimizer=ssa_ga``.

A user mistake (unknown config key, malformed recording, empty window) ends the run with
one ``error:`` line on stderr and exit status 2, never a traceback. Set
``SPATIALSEG_DEBUG=1`` to get the full traceback instead. A multirun runs every job; if any
failed, it ends with one ``error: N of M jobs failed`` line and exit status 1. A config
option that no config directory holds (``+scene=nosuch``; a user's own go in ``--config-dir``)
ends in one ``error:`` line listing the options, exit status 2.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra._internal.utils import run_and_report
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException, MissingConfigException, SearchPathException
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from spatialseg.config import ConfigError, conf_dir, validate_run

__all__ = ["guarded", "launch", "main", "run"]

log = logging.getLogger("spatialseg")

#: Exceptions that signal a user mistake (bad input or config), reported in one line.
USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, PermissionError)


def build_optimizer(cfg: DictConfig) -> Any:
    """Instantiate the configured optimiser, turning a bad hyperparameter into one line."""
    try:
        return hydra.utils.instantiate(cfg.optimizer)
    except InstantiationException as exc:
        cause = exc.__cause__ or exc
        raise ConfigError(f"optimizer: {cause}") from exc


def _report(summary: dict[str, Any], out_dir: Path) -> None:
    """Log the short end-of-run summary: clusters, velocities, accuracy, time."""
    log.info(
        "%s: %d events, n_clusters=%s, %d iterations (%s)",
        summary["scene"],
        summary["n_events"],
        summary["n_clusters"],
        summary["iterations"],
        summary["stop_reason"],
    )
    for c in summary["clusters"]:
        theta = ", ".join(f"{v:+.4f}" for v in c["theta"])
        log.info(
            "  cluster %d: %6d events, theta = [%s] %s",
            c["id"],
            c["n_events"],
            theta,
            summary["units"],
        )
    if "metrics" in summary:
        log.info("  accuracy %.4f (ground truth)", summary["metrics"]["accuracy"])
    log.info("  time %.2f s; outputs in %s", summary["timings"]["total"], out_dir)


def run(cfg: DictConfig) -> dict[str, Any]:
    """Validate the config, segment the scene, write the outputs; return result.json's content."""
    from spatialseg.pipeline import check_config, log_iteration, segment_loaded
    from spatialseg.results import summarise, write_outputs
    from spatialseg.scenes import load_scene
    from spatialseg.tracking import record

    validate_run(cfg)
    plain = OmegaConf.to_container(cfg, resolve=True)
    check_config(plain)
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    start = time.perf_counter()
    if cfg.scene.get("stream"):
        return run_stream(cfg, plain, out_dir)
    recording = load_scene(
        cfg.scene,
        seed=int(cfg.seed),
        window_events=int(cfg.window.events),
        windows=cfg.window.count,
    )
    timings = {"load": time.perf_counter() - start}
    optimizer = build_optimizer(cfg)
    progress = log_iteration if cfg.output.progress else None
    begin = time.perf_counter()
    recording, seg = segment_loaded(
        recording, plain, optimizer, seed=int(cfg.seed), on_iteration=progress
    )
    timings["segment"] = time.perf_counter() - begin
    timings["total"] = time.perf_counter() - start
    summary = summarise(recording, seg, plain, timings)
    if cfg.output.plots:
        from spatialseg.plots import save_result_figures

        save_result_figures(out_dir, recording, seg)
    write_outputs(out_dir, seg, summary)
    record(cfg, summary, out_dir)
    _report(summary, out_dir)
    return summary


def run_stream(cfg: DictConfig, plain: dict[str, Any], out_dir: Path) -> dict[str, Any]:
    """``scene.stream=true``: read, segment and write the file window by window, holding one
    window in memory; the outputs are those of any run except the figures and metrics."""
    from spatialseg.pipeline import segment_loaded
    from spatialseg.results import (
        ArrayStream,
        ProbabilityStream,
        run_summary,
        window_summary,
        write_json,
    )
    from spatialseg.scenes import stream_scene
    from spatialseg.tracking import record

    start = time.perf_counter()
    if plain["depth"]["name"] in ("recording", "onnx"):
        raise ValueError(
            f"scene.stream=true makes depth maps per window without images: use "
            f"depth=constant or depth=ground_plane, not depth={plain['depth']['name']}"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    labels = ArrayStream(out_dir / "labels.npy", np.int64)
    probabilities = ProbabilityStream(out_dir / "probabilities.npy")
    optimizer, windows, handover = build_optimizer(cfg), [], None
    try:
        stream = stream_scene(plain["scene"], window_events=int(cfg.window.events))
        for w, window in enumerate(stream):
            seed = int(np.random.default_rng([int(cfg.seed), w]).integers(2**31 - 1))
            _, seg = segment_loaded(window, plain, optimizer, seed=seed, handover=handover)
            handover = seg.handover or handover
            labels.append(seg.labels)
            probabilities.append_segmentation(seg)
            windows += [window_summary(res, None, None) for res in seg.windows]
            elapsed = time.perf_counter() - start
            log.info("window %d: %d events, %.1f s", w, len(window.events), elapsed)
        if not windows:
            raise ValueError(f"{cfg.scene.path or cfg.scene.name}: the file has no events")
    except BaseException:
        labels.abort()
        probabilities.abort()
        raise
    timings = {"total": time.perf_counter() - start}
    summary = run_summary(str(cfg.scene.name), labels.rows, plain, windows, timings)
    summary["stream"] = True
    labels.finish()
    probabilities.finish_objects(handover.boundary.next_id if handover else 1)
    write_json(out_dir / "result.json", summary)
    record(cfg, summary, out_dir)
    _report(summary, out_dir)
    return summary


def _fail_job(cfg: DictConfig, exc: Exception) -> None:
    """Record a failed multirun job and report it, so the sweep goes on with the next job."""
    from spatialseg.tracking import mark_job, record_failure

    record_failure(cfg, exc)
    mark_job(exc)
    print(f"error: {exc}", file=sys.stderr)
    if not isinstance(exc, USER_ERRORS):
        log.error("job failed", exc_info=exc)


def guarded(task: Callable[[DictConfig], object]) -> Callable[[DictConfig], None]:
    """Wrap a Hydra task so a user mistake ends in one ``error:`` line and exit status 2.

    In a multirun, a failing job (any exception) is recorded as failed and the sweep goes on;
    every job leaves its outcome for the sweep's exit status (:func:`tracking.mark_job`).
    """

    def wrapper(cfg: DictConfig) -> None:
        from spatialseg.tracking import mark_job

        try:
            task(cfg)
            mark_job(None)
        except Exception as exc:
            if os.environ.get("SPATIALSEG_DEBUG"):
                raise
            if HydraConfig.get().mode == RunMode.MULTIRUN:
                _fail_job(cfg, exc)
                return
            if not isinstance(exc, USER_ERRORS):
                raise
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(2)

    return wrapper


def launch(task: Callable[[DictConfig], object], config_name: str) -> None:
    """Start a Hydra app on ``conf/<config_name>.yaml`` running ``task`` guarded."""
    try:
        path = str(conf_dir())
    except USER_ERRORS as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    main_of = hydra.main(version_base="1.3", config_path=path, config_name=config_name)
    _run_reporting_missing_configs(main_of(guarded(task)))
    _exit_if_jobs_failed()


def _missing_config_line(exc: MissingConfigException | SearchPathException) -> str:
    """Hydra's first line of a missing-config error, with the group's options and the fix."""
    line = str(exc).strip().splitlines()[0]
    if not isinstance(exc, MissingConfigException) or not exc.options or not exc.missing_cfg_file:
        return line
    group = exc.missing_cfg_file.rpartition("/")[0]
    return (
        f"{line}; options in '{group}': {', '.join(exc.options)}; "
        f"or put your own in DIR/{group}/NAME.yaml and add --config-dir DIR"
    )


def _reraise(exc: Exception) -> None:
    """Raise ``exc`` again (for Hydra's own report of it)."""
    raise exc


def _run_reporting_missing_configs(app: Callable[[], None]) -> None:
    """Run the Hydra ``app``; an unknown config option or ``--config-dir`` ends in one
    ``error:`` line and exit status 2.

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
