"""experiments/compare_runs.py: two yardstick runs paired scene by scene."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

import compare_runs


def _row(family: str, seed: int, accuracy: float, model: str = "spatial", time_s: float = 1.0):
    return {"family": family, "seed": seed, "model": model, "accuracy": accuracy, "time_s": time_s}


def test_scenes_pair_by_family_and_seed_and_average_their_optimiser_seeds():
    rows = [_row("many", 0, 0.6), _row("many", 0, 0.8), _row("many", 0, 0.1, model="planar")]
    assert compare_runs.scene_means(rows, "spatial") == {("many", 0): (pytest.approx(0.7), 2.0)}
    with pytest.raises(ValueError, match="several spatial variants"):
        compare_runs.scene_means([*rows, _row("many", 1, 0.5, "spatial:seed=3")], "spatial")


def test_a_file_of_several_variants_compares_the_one_named(tmp_path, capsys):
    base, variants = tmp_path / "base.json", tmp_path / "variants.json"
    base.write_text(json.dumps({"rows": [_row("many", 0, 0.5), _row("many", 1, 0.7)]}))
    rows = [_row("many", s, 0.9, "spatial:a=1") for s in (0, 1)]
    rows += [_row("many", s, 0.1, "spatial:a=2") for s in (0, 1)]
    variants.write_text(json.dumps({"rows": rows}))
    compare_runs.main([str(base), str(variants), "--after-variant", "spatial:a=2"])
    assert "| all | 2 | 0.600 | 0.100 | -0.500 (0.100) | 0 / 2 |" in capsys.readouterr().out
    with pytest.raises(SystemExit) as stop:
        compare_runs.main([str(base), str(variants), "--after-variant", "spatial:a=3"])
    assert stop.value.code == 2
    message = capsys.readouterr().err
    assert message.count("\n") == 1 and "spatial:a=1, spatial:a=2" in message


def test_the_table_gives_the_paired_difference_and_the_scenes_that_moved():
    before = {("opposite", 0): (1.0, 2.0), ("opposite", 1): (0.5, 2.0), ("many", 0): (0.9, 4.0)}
    after = {("opposite", 0): (1.0, 1.0), ("opposite", 1): (0.9, 1.0), ("many", 7): (0.1, 1.0)}
    table = compare_runs.compare(before, after, step=0.02)
    assert "| opposite | 2 | 0.750 | 0.950 | +0.200 (0.200) | 1 / 0 |" in table
    assert "many" not in table  # no scene of it in both runs
    assert "summed time x0.50" in table
    with pytest.raises(ValueError, match="share no scene"):
        compare_runs.compare(before, {("long", 0): (1.0, 1.0)}, step=0.02)


def test_a_file_that_is_not_a_run_ends_in_one_line(tmp_path, capsys):
    run = tmp_path / "run.json"
    run.write_text(json.dumps({"rows": [_row("many", 0, 0.5)]}))
    other = tmp_path / "other.json"
    other.write_text("[]")
    with pytest.raises(SystemExit) as exit_info:
        compare_runs.main([str(run), str(other)])
    assert exit_info.value.code == 2
    assert "other.json is not a generalisation.py --json file" in capsys.readouterr().err
    compare_runs.main([str(run), str(run)])
    assert "| many | 1 | 0.500 | 0.500 | +0.000 (nan) | 0 / 0 |" in capsys.readouterr().out
