"""The wheel ships conf/, py.typed and the console scripts; a user's own config dir works."""

from __future__ import annotations

import configparser
import importlib.metadata
import json
import shutil
import subprocess
import sys
import zipfile
from collections.abc import Iterator
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

import spatialseg as installed
from spatialseg.config import conf_dir, config_roots, group_options
from tests.test_cli import spatialseg

REPO = Path(__file__).resolve().parents[1]
#: What the wheel is built from (a copy, so no build/ is left in the checkout).
SOURCES = ("pyproject.toml", "README.md", "conf", "spatialseg", "optimizers")
#: A run of a few seconds: one small window, a short loop, no plots or MLflow.
QUICK = (
    "window.events=1000",
    "window.count=1",
    "init.method=image_flow",
    "clustering.max_iterations=2",
    "tracking=none",
    "output.plots=false",
    "output.progress=false",
)


def _files(root: Path, pattern: str) -> set[str]:
    """Paths (relative to ``root``) of the files matching ``pattern``, caches left out."""
    return {
        p.relative_to(root).as_posix()
        for p in root.rglob(pattern)
        if p.is_file() and "__pycache__" not in p.parts
    }


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Iterator[zipfile.ZipFile]:
    """The wheel ``pip wheel`` builds from a copy of the checkout."""
    src, out = tmp_path_factory.mktemp("src"), tmp_path_factory.mktemp("wheel")
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info")
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=ignore)
        else:
            shutil.copy2(REPO / name, src / name)
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", str(src), "-w", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    (built,) = out.glob("spatialseg-*.whl")
    with zipfile.ZipFile(built) as archive:
        yield archive


def test_the_suite_runs_the_installed_package():
    """The tests import the package pip installed: the checkout for an editable install,
    the venv's copy for a wheel (CI installs one; pytest's --import-mode=append keeps the
    checkout behind site-packages on sys.path)."""
    dist = importlib.metadata.distribution("spatialseg")
    direct = json.loads(dist.read_text("direct_url.json") or "{}")
    if direct.get("dir_info", {}).get("editable", False):
        expected = Path(direct["url"].removeprefix("file://")) / "spatialseg"
    else:
        expected = Path(str(dist.locate_file("spatialseg")))
    assert Path(installed.__file__).resolve().parent == expected.resolve()
    assert conf_dir().is_dir() and (conf_dir() / "config.yaml").is_file()


def test_wheel_holds_every_config_module_and_py_typed(wheel):
    names = set(wheel.namelist())
    conf = {n.removeprefix("spatialseg/conf/") for n in names if n.startswith("spatialseg/conf/")}
    assert "config.yaml" in conf and "scene/interior.yaml" in conf
    assert conf == _files(REPO / "conf", "*.yaml")
    for package in ("spatialseg", "optimizers"):
        assert {f"{package}/{p}" for p in _files(REPO / package, "*.py")} <= names
        assert f"{package}/py.typed" in names


def test_wheel_console_scripts_are_the_module_entry_points(wheel):
    (entry_points,) = (n for n in wheel.namelist() if n.endswith(".dist-info/entry_points.txt"))
    parser = configparser.ConfigParser()
    parser.read_string(wheel.read(entry_points).decode())
    scripts = dict(parser["console_scripts"])
    assert set(scripts) == {"spatialseg", "spatialseg-simulate"}
    load = {
        name: EntryPoint(name, value, "console_scripts").load() for name, value in scripts.items()
    }
    from spatialseg.__main__ import main as spatialseg_main
    from spatialseg.simulate.__main__ import main as simulate_main

    assert load["spatialseg"] is spatialseg_main
    assert load["spatialseg-simulate"] is simulate_main


def _user_conf(root: Path) -> Path:
    """A user's config dir holding ``scene/mycam.yaml``: the interior scene renamed."""
    text = (conf_dir() / "scene" / "interior.yaml").read_text()
    (root / "scene").mkdir(parents=True)
    (root / "scene" / "mycam.yaml").write_text(text.replace("name: interior", "name: mycam"))
    return root


def test_config_roots_follow_hydra_search_path(tmp_path):
    user = _user_conf(tmp_path / "user")
    sources = [
        {"schema": "pkg", "path": "hydra.conf"},
        {"schema": "file", "path": str(conf_dir())},
        {"schema": "file", "path": str(user)},
        {"schema": "pkg", "path": "no_such_package.conf"},
        {"schema": "structured", "path": ""},
    ]
    roots = config_roots(sources)
    assert [str(r) for r in roots[1:]] == [str(conf_dir()), str(user)]
    assert "mycam" in group_options("scene", roots)
    assert "mycam" not in group_options("scene")


@pytest.mark.parametrize("how", ["--config-dir", "hydra.searchpath"])
def test_a_user_scene_runs_from_its_own_config_dir(tmp_path, how):
    user = _user_conf(tmp_path / "user")
    where = ("--config-dir", str(user)) if how == "--config-dir" else (f"{how}=[file://{user}]",)
    out = tmp_path / "run"
    res = spatialseg(*where, "+scene=mycam", *QUICK, f"hydra.run.dir={out}", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["scene"] == "mycam" and result["n_events"] == 1000


@pytest.mark.parametrize(
    ("args", "messages"),
    [
        (
            ("--config-dir", "{user}", "+scene=nosuch"),
            ("Could not find 'scene/nosuch'; options in 'scene': approach,", "mycam", "DIR"),
        ),
        (
            ("--config-dir", "{user}", "+scene=mycam", "+scene.camra=1"),
            ("unknown config key 'scene.camra'; did you mean 'scene.camera'?",),
        ),
        (
            ("--config-dir", "{user}/nodir", "+scene=mycam"),
            ("Additional config directory", "nodir' not found"),
        ),
    ],
)
def test_user_config_mistakes_give_one_line(tmp_path, args, messages):
    user = _user_conf(tmp_path / "user")
    given = [a.format(user=user) for a in args]
    res = spatialseg(*given, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ")
    assert all(m in lines[0] for m in messages), lines[0]
