"""Fixtures shared by the test files (their helpers: ``helpers.py``)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A tiny D4RL-format file of door-like episodes, one per test module."""
    from helpers import write_d4rl  # imports torch: only in the sessions that use this fixture

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
