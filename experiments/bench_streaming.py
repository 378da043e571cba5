"""Peak memory of reading events whole vs streamed: ``python experiments/bench_streaming.py``.

Writes N synthetic DAVIS346 events (default 5,000,000) as ``.h5``, ``.npz``, ``.txt`` and
Prophesee EVT 3.0 ``.raw``, then, for each file, reads it in a fresh subprocess either whole
(:func:`spatialseg.io.read_any`) or chunk by chunk (:func:`spatialseg.io.iter_event_chunks`,
``--chunk`` events, only a count kept) and reports the wall time and the subprocess's peak
resident memory (which includes ~70 MB of interpreter and imports) of a plain run, and the
peak memory ``tracemalloc`` traces (numpy's arrays included) in a second run. Prints a
table with the whole / streamed ratios measured in the same run and writes them as JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
from _common import synthetic_events, write_json

from spatialseg.io import (
    iter_event_chunks,
    read_any,
    write_events,
    write_prophesee,
)
from spatialseg.recording import Camera

WIDTH, HEIGHT = 346, 260
FORMATS = (".h5", ".npz", ".txt", ".raw")
CAMERA = Camera(200.0, 200.0, 172.5, 129.5, WIDTH, HEIGHT)  # any camera: only events are read


def _maxrss_mb() -> float:
    """This process image's peak resident memory so far, in MB.

    Linux: ``VmHWM`` of ``/proc/self/status`` (``ru_maxrss`` would keep the parent's peak
    across fork + exec); elsewhere ``ru_maxrss`` (KiB on Linux, bytes on macOS).
    """
    status = Path("/proc/self/status")
    if status.is_file():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    divisor = 1024 * 1024 if sys.platform == "darwin" else 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / divisor


def child(mode: str, path: Path, chunk: int) -> dict[str, float]:
    """Read ``path`` whole or streamed in this process: time and peak RSS on a plain run,
    then the tracemalloc peak on a second, traced run (tracing slows Python allocations)."""

    def read() -> int:
        if mode == "whole":
            return len(read_any(path, camera=CAMERA).events)
        return sum(len(c) for c in iter_event_chunks(path, chunk, width=WIDTH, height=HEIGHT))

    baseline = _maxrss_mb()
    start = time.perf_counter()
    count = read()
    seconds = time.perf_counter() - start
    rss = _maxrss_mb()
    tracemalloc.start()
    read()
    traced = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return {
        "events": count,
        "seconds": seconds,
        "traced_peak_mb": traced,
        "rss_baseline_mb": baseline,
        "rss_peak_mb": rss,
    }


def measure(mode: str, path: Path, chunk: int) -> dict[str, float]:
    """Run :func:`child` in a fresh interpreter (so peaks do not carry over)."""
    args = [sys.executable, __file__, "--child", mode, str(path), "--chunk", str(chunk)]
    out = subprocess.run(args, capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def run(n: int, chunk: int) -> dict[str, object]:
    """Write each format, measure whole and streamed reads; return a JSON-ready dict."""
    events = synthetic_events(n)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for suffix in FORMATS:
            path = Path(tmp) / f"events{suffix}"
            if suffix == ".raw":
                write_prophesee(events, path, encoding="evt3")
            else:
                write_events(events, path)
            whole = measure("whole", path, chunk)
            streamed = measure("stream", path, chunk)
            assert whole["events"] == streamed["events"] == n
            rows[suffix] = {
                "size_mb": path.stat().st_size / 1e6,
                "whole": whole,
                "stream": streamed,
                "traced_ratio": whole["traced_peak_mb"] / streamed["traced_peak_mb"],
                "rss_ratio": whole["rss_peak_mb"] / streamed["rss_peak_mb"],
            }
    return {
        "events": n,
        "chunk_events": chunk,
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "numpy": np.__version__,
        "formats": rows,
    }


def print_table(result: dict) -> None:
    """Print traced and resident peak memory (MB) and time per format, whole vs streamed."""
    print(f"{result['events']:,} events, streamed {result['chunk_events']:,} at a time")
    print(
        "| format | file MB | traced whole | traced stream | ratio | RSS whole | RSS stream "
        "| ratio | whole s | stream s |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for suffix, row in result["formats"].items():
        w, s = row["whole"], row["stream"]
        print(
            f"| `{suffix}` | {row['size_mb']:.1f} | {w['traced_peak_mb']:.1f} | "
            f"{s['traced_peak_mb']:.1f} | {row['traced_ratio']:.1f} | {w['rss_peak_mb']:.0f} | "
            f"{s['rss_peak_mb']:.0f} | {row['rss_ratio']:.1f} | {w['seconds']:.2f} | "
            f"{s['seconds']:.2f} |"
        )


def main() -> None:
    """Parse arguments; run the benchmark (or one measuring child), print, write JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=5_000_000)
    parser.add_argument("--chunk", type=int, default=100_000)
    parser.add_argument("--out", type=Path, default=Path("outputs/bench_streaming.json"))
    parser.add_argument("--child", nargs=2, metavar=("MODE", "PATH"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child[0], Path(args.child[1]), args.chunk)))
        return
    result = run(args.events, args.chunk)
    print_table(result)
    write_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
