"""Two yardstick runs compared scene by scene: what a change moved, against its noise.

    python experiments/compare_runs.py BEFORE.json AFTER.json [--model spatial] [--step 0.02]
    python experiments/compare_runs.py docs/data/heldout_session41.json new.json --model spatial
    python experiments/compare_runs.py base.json variants.json \
        --after-variant "spatial:init.auto=[image_flow,dominant,previous]"

Pairs the rows of two ``generalisation.py --json`` files by family and scene seed (the
model's kind, the part of its name before ``:``, must match ``--model``; a file holding
several variants of it names the one compared with ``--before-variant`` or
``--after-variant``, the variant's whole name) and prints, per family and over all pairs,
the mean accuracy before and after, the paired difference with its standard error, the
scenes that moved up and down by more than ``--step``, and the summed time's ratio. A
scene run with several optimiser seeds counts as the mean of its rows. Decision: the same
settings run again on other optimiser seeds (``generalisation.py --first-run 1``) move
single recordings by up to 0.28, so a change is read against that run's spread, not
against zero.
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

#: A scene's key: its family and seed.
Scene = tuple[str, int]


def scene_means(
    rows: list[dict[str, Any]], model: str, variant: str | None = None
) -> dict[Scene, tuple[float, float]]:
    """Each scene's mean accuracy and summed time over the rows of ``model``'s kind: of its
    one variant in the file, or of ``variant`` (a whole model name); else a ValueError
    naming the file's variants."""
    kept = [r for r in rows if r["model"].partition(":")[0] == model]
    variants = sorted({r["model"] for r in kept})
    if variant is not None:
        if variant not in variants:
            raise ValueError(f"no rows of {variant!r}; the file has: {', '.join(variants)}")
        kept = [r for r in kept if r["model"] == variant]
    elif len(variants) > 1:
        raise ValueError(
            f"several {model} variants in one file: {', '.join(variants)}; "
            "name one with --before-variant or --after-variant"
        )
    grouped: dict[Scene, list[dict[str, Any]]] = defaultdict(list)
    for row in kept:
        grouped[(row["family"], int(row["seed"]))].append(row)
    return {
        scene: (
            float(np.mean([r["accuracy"] for r in group])),
            float(sum(r["time_s"] for r in group)),
        )
        for scene, group in grouped.items()
    }


def paired_line(label: str, before: list[float], after: list[float], step: float) -> str:
    """One table line: mean before and after, paired difference (standard error), the
    scenes up and down by more than ``step``."""
    diff = np.asarray(after) - np.asarray(before)
    se = float(diff.std(ddof=1) / math.sqrt(len(diff))) if len(diff) > 1 else float("nan")
    up, down = int((diff > step).sum()), int((diff < -step).sum())
    return (
        f"| {label} | {len(diff)} | {np.mean(before):.3f} | {np.mean(after):.3f} | "
        f"{diff.mean():+.3f} ({se:.3f}) | {up} / {down} |"
    )


def compare(
    before: dict[Scene, tuple[float, float]], after: dict[Scene, tuple[float, float]], step: float
) -> str:
    """The Markdown table of the scenes both runs hold: per family, then all of them with
    the median and 10th percentile before and after and the summed time's ratio."""
    common = [k for k in before if k in after]  # the yardstick's order of families
    if not common:
        raise ValueError("the two runs share no scene (family and seed)")
    lines = [
        "| family | scenes | mean before | mean after | paired difference (s.e.) | up / down |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for family in dict.fromkeys(f for f, _ in common):
        keys = [k for k in common if k[0] == family]
        lines.append(
            paired_line(family, [before[k][0] for k in keys], [after[k][0] for k in keys], step)
        )
    first = [before[k][0] for k in common]
    second = [after[k][0] for k in common]
    lines.append(paired_line("all", first, second, step))
    ratio = sum(after[k][1] for k in common) / sum(before[k][1] for k in common)
    lines.append("")
    lines.append(
        f"median {np.median(first):.3f} -> {np.median(second):.3f}, 10th percentile "
        f"{np.percentile(first, 10):.3f} -> {np.percentile(second, 10):.3f}, worst "
        f"{min(first):.3f} -> {min(second):.3f}; summed time x{ratio:.2f}; up / down: by more "
        f"than {step:g}"
    )
    return "\n".join(lines)


def read_rows(path: Path) -> list[dict[str, Any]]:
    """The rows of one ``generalisation.py --json`` file."""
    payload = json.loads(path.read_text())
    if not isinstance(payload, dict) or "rows" not in payload:
        raise ValueError(f"{path} is not a generalisation.py --json file (it has no rows)")
    return payload["rows"]


def build_parser() -> argparse.ArgumentParser:
    """The command line: two runs' JSON files, the model's kind, the variant compared in
    each (for a file of several) and the step."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--model", default="spatial", help="the model's kind: spatial or planar")
    for side in ("before", "after"):
        parser.add_argument(
            f"--{side}-variant", help=f"the variant of {side}'s file compared (its whole name)"
        )
    parser.add_argument("--step", type=float, default=0.02, help="a scene moved by more than this")
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        runs = [
            scene_means(read_rows(path), args.model, variant)
            for path, variant in (
                (args.before, args.before_variant),
                (args.after, args.after_variant),
            )
        ]
        print(compare(*runs, args.step))
    except (OSError, ValueError) as exc:
        parser.exit(2, f"error: {exc}\n")


if __name__ == "__main__":
    main()
