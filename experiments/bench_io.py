"""Benchmark event-file reading and writing: ``python experiments/bench_io.py``.

Writes N synthetic DAVIS346 events (default 1,000,000) as ``.txt``, ``.h5`` and ``.npz``
with :func:`spatialseg.io.write_events`, reads them back with :func:`read_events`, and times
both (median of ``--repeat`` runs), plus how long naming a bad last line of ``events.txt``
takes. Prints a table with the read/write ratios and writes the numbers as JSON.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _common import synthetic_events, write_json

from spatialseg.io import read_events, write_events

WIDTH, HEIGHT = 346, 260
FORMATS = (".txt", ".h5", ".npz")


def median_seconds(action: Callable[[], object], repeat: int) -> float:
    """Median wall time of ``repeat`` runs of ``action``."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        action()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def diagnosis_seconds(path: Path, repeat: int) -> float:
    """Time to fail on ``events.txt`` whose last line is bad (fast pass, then line scan)."""

    def read_bad() -> None:
        try:
            read_events(path, width=WIDTH, height=HEIGHT)
        except ValueError:
            return
        raise AssertionError("the bad last line was not detected")

    with path.open("a") as f:
        f.write("99.0 1 2\n")
    return median_seconds(read_bad, repeat)


def run(n: int, repeat: int) -> dict[str, object]:
    """Time writing and reading each format; return the results as a JSON-ready dict."""
    events = synthetic_events(n)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for suffix in FORMATS:
            path = Path(tmp) / f"events{suffix}"
            write = median_seconds(lambda p=path: write_events(events, p), repeat)
            read = median_seconds(lambda p=path: read_events(p, width=WIDTH, height=HEIGHT), repeat)
            rows[suffix] = {
                "write_s": write,
                "read_s": read,
                "read_mev_per_s": n / read / 1e6,
                "size_mb": path.stat().st_size / 1e6,
            }
        diagnose = diagnosis_seconds(Path(tmp) / "events.txt", repeat)
    txt = rows[".txt"]
    return {
        "events": n,
        "repeat": repeat,
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "numpy": np.__version__,
        "formats": rows,
        "txt_bad_last_line_s": diagnose,
        "read_ratio_txt_over": {s: txt["read_s"] / rows[s]["read_s"] for s in FORMATS[1:]},
        "write_ratio_txt_over": {s: txt["write_s"] / rows[s]["write_s"] for s in FORMATS[1:]},
        "txt_read_s_per_million_lines": txt["read_s"] * 1e6 / n,
        "txt_read_target_s_per_million_lines": 2.0,
    }


def print_table(result: dict) -> None:
    """Print the timings and ratios as a plain-text table."""
    n = result["events"]
    print(f"{n:,} events, median of {result['repeat']} runs")
    print(f"{'format':8} {'write s':>8} {'read s':>8} {'read Mev/s':>11} {'size MB':>8}")
    for suffix, row in result["formats"].items():
        print(
            f"{suffix:8} {row['write_s']:8.3f} {row['read_s']:8.3f} "
            f"{row['read_mev_per_s']:11.2f} {row['size_mb']:8.1f}"
        )
    for suffix in FORMATS[1:]:
        print(
            f"txt / {suffix[1:]}: read {result['read_ratio_txt_over'][suffix]:.1f}x slower, "
            f"write {result['write_ratio_txt_over'][suffix]:.1f}x slower"
        )
    print(f"events.txt with a bad last line: error after {result['txt_bad_last_line_s']:.3f} s")
    per_million = result["txt_read_s_per_million_lines"]
    verdict = "meets" if per_million < result["txt_read_target_s_per_million_lines"] else "MISSES"
    print(f"events.txt: {per_million:.3f} s per 1,000,000 lines; {verdict} the < 2 s target")


def main() -> None:
    """Parse arguments, run the benchmark, print the table and write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=1_000_000, help="number of events")
    parser.add_argument("--repeat", type=int, default=3, help="runs per measurement")
    parser.add_argument(
        "--out", type=Path, default=Path("outputs/bench_io.json"), help="JSON results file"
    )
    args = parser.parse_args()
    result = run(args.events, args.repeat)
    print_table(result)
    write_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
