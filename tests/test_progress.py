"""Progress (issue 28, item 5): a DEBUG line per iteration naming its window and start, an
INFO line per window as it ends, on a terminal a bar over the windows and over a sweep's jobs,
and the numba kernels' first compilation announced."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import textwrap
from io import StringIO
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import optimizers
from spatialseg import progress, sweep_progress
from spatialseg.compilation import cache_is_cold, compile_seconds, index_paths
from spatialseg.config import conf_dir
from spatialseg.pipeline import segment_recording
from spatialseg.plots import figure_count
from spatialseg.scenes import load_scene

EVENTS = 2000


def _config(*overrides: str) -> dict:
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose(
            "config", overrides=["+scene=interior", f"window.events={EVENTS}", *overrides]
        )
    return OmegaConf.to_container(cfg, resolve=True)


@pytest.fixture(scope="module")
def two_windows():
    cfg = _config("clustering.max_iterations=2", "window.context=0")
    return cfg, load_scene(cfg["scene"], seed=0, window_events=EVENTS, windows=2)


def _messages(caplog, level: int) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == level]


def test_iteration_lines_are_debug_and_name_the_window_and_start(two_windows, caplog):
    cfg, rec = two_windows
    caplog.set_level(logging.DEBUG, logger="spatialseg")
    seg = segment_recording(rec, cfg, optimizers.create("ssa_ga"), seed=0)
    debug, info = _messages(caplog, logging.DEBUG), _messages(caplog, logging.INFO)
    assert not [m for m in info if "total contrast" in m]
    iterations = [m for m in debug if ", iteration " in m]
    assert all(m.startswith(("window 0/2, start ", "window 1/2, start ")) for m in iterations)
    # the second window also starts from the first's velocities: both starts are named
    assert any(
        m.startswith("window 1/2, start previous, iteration 1: total contrast") for m in debug
    )
    assert any(m.startswith("window 1/2, start previous: total contrast") for m in debug)
    ran = sum(res.clustering.iterations for res in seg.windows)
    assert len(iterations) >= ran  # every start's iterations, the kept one's among them
    ends = [m for m in info if m.startswith("window ")]
    assert len(ends) == 2
    for w, (line, res) in enumerate(zip(ends, seg.windows, strict=True)):
        k, its = res.clustering.thetas.shape[0], res.clustering.iterations
        assert line.startswith(f"window {w}/2: {EVENTS} events, {k} clusters, {its} iterations, ")


def test_progress_off_logs_no_window_or_iteration_lines(two_windows, caplog):
    cfg, rec = two_windows
    caplog.set_level(logging.DEBUG, logger="spatialseg")
    segment_recording(rec, cfg, optimizers.create("ssa_ga"), seed=0, progress=False)
    text = [r.getMessage() for r in caplog.records]
    assert not [m for m in text if m.startswith("window ") or "total contrast" in m]


def test_a_stream_names_its_windows_from_first_window_without_a_count(two_windows, caplog):
    cfg, rec = two_windows
    caplog.set_level(logging.INFO, logger="spatialseg")
    segment_recording(rec, cfg, optimizers.create("ssa_ga"), seed=0, first_window=5)
    ends = [m for m in _messages(caplog, logging.INFO) if m.startswith("window ")]
    assert [m.split(":")[0] for m in ends] == ["window 5", "window 6"]


class Terminal(StringIO):
    """A stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True


def _terminal(monkeypatch) -> Terminal:
    """stderr as a terminal, bars drawn into it (set in the test's body: pytest's capture
    sets sys.stderr again between a fixture and the test)."""
    stream = Terminal()
    monkeypatch.setattr(sys, "stderr", stream)
    monkeypatch.delenv("TERM", raising=False)
    return stream


def test_a_bar_only_on_a_terminal(monkeypatch):
    terminal = _terminal(monkeypatch)
    with progress.progress_bar(3, "window") as update:
        update(2)
    assert "2/3" in terminal.getvalue()
    off, log = Terminal(), StringIO()
    with progress.progress_bar(3, "window", enabled=False, stream=off) as update:
        update(1)
    with progress.progress_bar(3, "window", stream=log) as update:
        update(1)
    assert off.getvalue() == log.getvalue() == ""


def test_windows_get_a_bar_on_a_terminal_and_their_lines_above_it(two_windows, monkeypatch, caplog):
    cfg, rec = two_windows
    terminal = _terminal(monkeypatch)
    caplog.set_level(logging.INFO, logger="spatialseg")
    segment_recording(rec, cfg, optimizers.create("ssa_ga"), seed=0)
    drawn = terminal.getvalue()
    assert "0/2" in drawn and "2/2" in drawn and "window" in drawn
    assert len([m for m in _messages(caplog, logging.INFO) if m.startswith("window ")]) == 2
    terminal.truncate(0)
    segment_recording(rec, cfg, optimizers.create("ssa_ga"), seed=0, progress=False)
    assert terminal.getvalue() == ""


def _sweep_config(*sweep: str, **hydra: str):
    """The composed config of a multirun over ``sweep`` (``hydra``: its hydra.* settings)."""
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[f"hydra.{k}={v}" for k, v in hydra.items()],
            return_hydra_config=True,
        )
    cfg.hydra.overrides.task = list(sweep)
    return cfg


def test_the_sweep_size_is_the_basic_sweepers_job_count():
    assert sweep_progress.sweep_size(_sweep_config("n_clusters=2,3", "seed=range(0,3)")) == 6
    assert sweep_progress.sweep_size(_sweep_config("seed=0")) == 1
    other = _sweep_config("n_clusters=2,3", **{"sweeper._target_": "somewhere.Else"})
    assert sweep_progress.sweep_size(other) is None


def test_a_sweep_in_this_process_gets_a_bar_over_its_jobs(monkeypatch):
    terminal = _terminal(monkeypatch)
    config = _sweep_config("n_clusters=2,3")
    bar = sweep_progress.SweepProgress()
    bar.on_multirun_start(config)
    for _ in range(2):
        bar.on_job_start(config)
        logging.getLogger("spatialseg").warning("a job's line")
        bar.on_job_end(config, None)
    bar.on_multirun_end(config)
    drawn = terminal.getvalue()
    assert "2/2" in drawn and "job" in drawn
    elsewhere = _sweep_config("n_clusters=2,3", **{"launcher._target_": "somewhere.Else"})
    terminal.truncate(0)
    bar = sweep_progress.SweepProgress()
    bar.on_multirun_start(elsewhere)
    bar.on_job_end(elsewhere, None)
    bar.on_multirun_end(elsewhere)
    assert terminal.getvalue() == ""


def test_figure_count_is_what_save_result_figures_draws(two_windows, tmp_path):
    """Two windows: the three summary figures, and with every window's own four more each."""
    from spatialseg.plots import save_result_figures

    cfg, rec = two_windows
    seg = segment_recording(rec, cfg, optimizers.create("ssa_ga"), seed=0, progress=False)
    summary = save_result_figures(tmp_path / "summary", rec, seg)
    assert [p.name for p in summary] == ["clusters.png", "windows.png", "objects.png"]
    assert len(summary) == figure_count(2) == 3
    every = save_result_figures(tmp_path / "every", rec, seg, every_window=True)
    assert len(every) == figure_count(2, every_window=True) == 11
    assert {"clusters_w1.png", "theta_w1.png"} <= {p.name for p in every}
    assert figure_count(1) == figure_count(1, every_window=True) == 4


@pytest.mark.parametrize(
    ("windows", "shown"),
    [(1, [0]), (5, [0, 1, 2, 3, 4]), (24, list(range(24))), (100, None)],
)
def test_the_windows_figure_shows_at_most_its_panels_first_and_last_included(windows, shown):
    from spatialseg.plots import MAX_WINDOW_PANELS, shown_windows

    drawn = shown_windows(windows).tolist()
    if shown is not None:
        assert drawn == shown
    else:
        assert len(drawn) == MAX_WINDOW_PANELS and drawn[0] == 0 and drawn[-1] == windows - 1
        assert drawn == sorted(set(drawn))


def test_the_kernels_index_paths_and_a_warm_cache():
    paths = index_paths()
    assert len(paths) >= 5 and all(p.suffix == ".nbi" for p in paths)
    assert not cache_is_cold()  # this process's install has compiled (the tests above)


def test_compile_seconds_sums_the_outermost_spans():
    from numba.core.event import Event, EventStatus

    def ev(status):
        return Event("numba:compile", status)

    start, end = EventStatus.START, EventStatus.END
    records = [(0.0, ev(start)), (1.0, ev(start)), (2.0, ev(end)), (3.0, ev(end))]
    records += [(10.0, ev(start)), (10.5, ev(end))]
    assert compile_seconds(records) == pytest.approx(3.5)


SCRIPT = textwrap.dedent(
    """
    import logging, sys
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
    from spatialseg.compilation import announce_compilation
    from spatialseg.objectives import volume_moments
    import numpy as np
    with announce_compilation():
        volume_moments(np.ones((2, 3, 4)))
    """
)


def test_a_cold_cache_announces_the_compilation_once(tmp_path):
    """With NUMBA_CACHE_DIR empty the first run announces and times the compile; a second
    run on the same cache finds it warm and says nothing."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}

    def run() -> str:
        done = subprocess.run(
            [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=300
        )
        assert done.returncode == 0, done.stderr
        return done.stdout

    first = run()
    assert "compiling the numba kernels (once per install, about" in first
    assert "compiled in " in first
    assert any(Path(tmp_path).rglob("*.nbi"))
    second = run()
    assert "compil" not in second
