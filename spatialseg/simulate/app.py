"""The simulator's command line: ``python -m spatialseg.simulate +scene=interior out=DIR``.

It simulates the scene, writes the recording directory (``spatialseg.io.write_recording``),
the composed config (``simulate.yaml``, for provenance) and ``preview.png`` into ``out``,
and prints a one-line summary. A user mistake ends the
run with one ``error:`` line on stderr and exit status 2, as in :mod:`spatialseg.cli`
(``SPATIALSEG_DEBUG=1`` shows the traceback instead).
"""

from __future__ import annotations

from pathlib import Path

from hydra.utils import to_absolute_path
from omegaconf import DictConfig, OmegaConf

from spatialseg.checks import is_integer
from spatialseg.cli import launch
from spatialseg.config import ConfigError, validate_run
from spatialseg.recording import Recording

__all__ = ["main", "run", "summary"]


def summary(recording: Recording) -> str:
    """One line: event count, time span, and each object's share of the events."""
    from spatialseg.plots import label_shares

    events = recording.events
    shares = ", ".join(f"{k} {100 * v:.0f}%" for k, v in label_shares(recording).items())
    text = f"{recording.name}: {len(events)} events over {1e3 * events.duration:.1f} ms"
    return f"{text}; {shares}" if shares else text


def _window_events(cfg: DictConfig) -> int | None:
    """``window.events`` as a positive int, or None to simulate the whole duration."""
    events = cfg.window.events
    if events is None:
        return None
    if not is_integer(events, 1):
        raise ConfigError(f"window.events must be a positive integer or null, got {events!r}")
    return events


def _output_dir(cfg: DictConfig) -> Path:
    """The ``out`` directory (absolute); refuse an existing one unless ``overwrite=true``."""
    if cfg.out is None:
        raise ConfigError("no output directory; add out=DIR")
    out = Path(to_absolute_path(str(cfg.out)))
    if out.exists() and not cfg.overwrite:
        raise ConfigError(f"{out} already exists; choose another out=DIR or add overwrite=true")
    return out


def run(cfg: DictConfig) -> Path:
    """Validate the config, simulate, write the recording and its preview; return ``out``."""
    validate_run(cfg, primary="simulate.yaml")
    if cfg.scene.get("kind") != "simulated":
        raise ConfigError(
            f"scene '{cfg.scene.get('name')}' is not simulated; pick one, e.g. +scene=interior"
        )
    events, out = _window_events(cfg), _output_dir(cfg)
    try:
        from spatialseg.io import write_recording
    except ImportError as exc:
        raise ConfigError(f"cannot write recordings: spatialseg.io is unavailable ({exc})") from exc
    from spatialseg.plots import save_scene_preview
    from spatialseg.simulate import simulate_scene

    recording = simulate_scene(
        cfg.scene, seed=int(cfg.seed), max_events=events, windows=cfg.window.count
    )
    write_recording(recording, out, overwrite=bool(cfg.overwrite))
    OmegaConf.save(cfg, out / "simulate.yaml", resolve=True)
    if cfg.preview:
        save_scene_preview(recording, out / "preview.png")
    print(f"{summary(recording)} -> {out}")
    return out


def main() -> None:
    """Console entry point (``python -m spatialseg.simulate``)."""
    launch(run, "simulate")
