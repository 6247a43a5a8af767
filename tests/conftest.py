"""Fixtures shared by the test files (their helpers: ``helpers.py``)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from helpers import write_d4rl


def load_benchmark(name: str):
    """The module of the script ``benchmarks/NAME.py`` (``NAME`` may name a subfolder: ``diagnostics/iql_diagnostics``).

    The scripts are not a package: as ``python benchmarks/NAME.py`` does, the script's own folder comes first on
    ``sys.path`` while it loads, so its sibling imports resolve; the path is restored afterwards.
    """
    import importlib.util
    import sys

    script = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(script.stem, script)
    module = importlib.util.module_from_spec(spec)
    saved = list(sys.path)
    sys.path.insert(0, str(script.parent))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path[:] = saved
    return module


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A tiny D4RL-format file of door-like episodes, one per test module."""
    return write_d4rl(tmp_path_factory.mktemp("data") / "door-like.hdf5")


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A Minari cache (MINARI_DATASETS_PATH) of the test module's own."""
    path = tmp_path_factory.mktemp("minari")
    previous = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(path)
    try:
        yield path
    finally:
        if previous is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = previous
