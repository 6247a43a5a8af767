"""The wheel is the product: it ships the recipes, and an installed (not editable) package trains from any
directory."""
from __future__ import annotations

import os
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_is_listed():
    """pyproject names the packages (to map recipes/ into the wheel): a new subpackage must be added there."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "rm_torchrl").rglob("__init__.py")}
    assert listed == found | {"rm_torchrl.recipes"}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(ROOT)],
                          capture_output=True, text=True, timeout=600)
    if proc.returncode != 0 and "No matching distribution" in proc.stderr:
        pytest.skip("no package index to fetch the build backend from")
    assert proc.returncode == 0, proc.stderr
    (built,) = out.glob("rm_torchrl-*.whl")
    return built


@pytest.mark.slow
def test_wheel_ships_every_recipe(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    recipes = {p.relative_to(ROOT).as_posix() for p in (ROOT / "recipes").rglob("*.yaml")}
    assert {f"rm_torchrl/{r}" for r in recipes} <= names
    assert "rm_torchrl/data/d4rl_files/door-human-v0.hdf5" in names


@pytest.mark.slow
def test_installed_wheel_trains_from_any_directory(wheel, tmp_path):
    """The wheel installed into a folder of its own (the checkout nowhere on the path) lists its options,
    refines from a shipped recipe and trains ours on the embedded file, from an empty directory."""
    target, cwd = tmp_path / "site", tmp_path / "empty"
    cwd.mkdir()
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), str(wheel)],
                   check=True, timeout=300)
    env = {**os.environ, "PYTHONPATH": str(target)}

    def rmrl(*argv):
        return subprocess.run([sys.executable, "-c", "from rm_torchrl.cli.main import main; main()", *argv],
                              cwd=cwd, env=env, capture_output=True, text=True, timeout=600)

    where = subprocess.run([sys.executable, "-c", "import rm_torchrl; print(rm_torchrl.__file__)"], cwd=cwd,
                           env=env, capture_output=True, text=True, check=True).stdout
    assert where.startswith(str(target)), where
    help_text = rmrl("train", "--help").stdout
    assert f"recipes folder {target / 'rm_torchrl' / 'recipes'}" in help_text
    assert "door-human-v0" in help_text and "ours-reuse" in help_text
    refined = rmrl("refine", "dataset=door-human-v0", "--out", "refined")
    assert refined.returncode == 0, refined.stderr
    assert "wrote 2,261 transitions" in refined.stdout
    trained = rmrl("train", "dataset=door-human-v0", "method=ours", "trainer.steps=10", "trainer.compile=false",
                   "trainer.threads=1", "eval.every=10", "eval.episodes=1", "eval.max_steps=5", "--no-progress")
    assert trained.returncode == 0, trained.stderr
    run = cwd / "runs" / "door-human-v0-ours-seed0"
    assert (run / "eval.csv").read_text().splitlines()[-1].startswith("10,")
    demo = rmrl("demo", "--steps", "10", "--seeds", "1", "--episodes", "1", "--out", "demo", "trainer.compile=false",
                "eval.max_steps=5")
    assert demo.returncode == 0, demo.stderr
    assert (cwd / "demo" / "report" / "demo.md").is_file()
