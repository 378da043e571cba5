"""Benchmark the background-activity filter: ``python experiments/bench_denoise.py``.

Speed: :func:`spatialseg.denoise.denoise_mask` on N uniformly spread DAVIS346 events
(default 1,000,000), median of ``--repeat`` runs after a warm-up call (numba compiles or
loads its cache), in events per second. Quality: on the simulated ``night`` and
``exterior`` scenes (seed 0, ``--events`` events, background activity labelled -1 by the
simulator), the share of object events kept (recall), of noise events removed, and the
precision of the kept events, for the configured ``denoise`` and a few neighbours of it.
Prints both tables and writes them as JSON to ``outputs/bench_denoise.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from _common import synthetic_events
from omegaconf import OmegaConf

from spatialseg.config import conf_dir
from spatialseg.denoise import denoise_mask
from spatialseg.settings import Settings
from spatialseg.simulate import simulate_scene

WIDTH, HEIGHT = 346, 260
SCENES = ("night", "exterior")


def speed(n: int, radius: int, window: float, repeat: int) -> dict[str, float]:
    """Median seconds and events per second of the filter on ``n`` synthetic events."""
    events = synthetic_events(n)
    denoise_mask(events.select(slice(0, 10)), radius=radius, window=window)
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        denoise_mask(events, radius=radius, window=window)
        times.append(time.perf_counter() - start)
    seconds = statistics.median(times)
    return {"events": n, "radius": radius, "seconds": seconds, "events_per_s": n / seconds}


def quality(scene: str, events: int, settings: list[tuple[int, float]]) -> list[dict]:
    """Recall, noise removed and precision of the filter on a simulated scene."""
    cfg = OmegaConf.to_container(OmegaConf.load(conf_dir() / "scene" / f"{scene}.yaml"))
    rec = simulate_scene(cfg, seed=0, max_events=events)
    signal = rec.ground_truth.labels >= 0
    rows = []
    for radius, window in settings:
        keep = denoise_mask(rec.events, radius=radius, window=window)
        rows.append(
            {
                "scene": scene,
                "radius": radius,
                "window": window,
                "events": len(keep),
                "noise_share": float(1.0 - signal.mean()),
                "recall": float(keep[signal].mean()),
                "noise_removed": float(1.0 - keep[~signal].mean()) if (~signal).any() else None,
                "precision": float(signal[keep].mean()) if keep.any() else None,
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=15000, help="events per simulated scene")
    parser.add_argument("--speed-events", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("outputs/bench_denoise.json"))
    args = parser.parse_args()
    base = Settings().denoise
    r, w = base.radius, base.window
    settings = [(r, w), (r, w / 10), (r, w * 10), (r + 1, w)]
    speeds = [speed(args.speed_events, radius, w, args.repeat) for radius in (r, r + 1)]
    print(f"{'events':>10} {'radius':>6} {'seconds':>8} {'Mevents/s':>9}")
    for s in speeds:
        rate = s["events_per_s"] / 1e6
        print(f"{s['events']:>10,} {s['radius']:>6} {s['seconds']:>8.3f} {rate:>9.1f}")
    rows = [row for scene in SCENES for row in quality(scene, args.events, settings)]
    print(
        f"\n{'scene':9} {'radius':>6} {'window s':>8} {'noise %':>7} {'recall':>7} "
        f"{'noise removed':>13} {'precision':>9}"
    )
    for q in rows:
        print(
            f"{q['scene']:9} {q['radius']:>6} {q['window']:>8g} {100 * q['noise_share']:>7.1f} "
            f"{q['recall']:>7.3f} {q['noise_removed']:>13.3f} {q['precision']:>9.3f}"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"speed": speeds, "quality": rows}, indent=2))


if __name__ == "__main__":
    main()
