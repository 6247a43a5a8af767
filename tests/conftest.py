"""Fixtures shared by the test files."""
from __future__ import annotations

import os
from pathlib import Path

import pytest


def leftovers(cache: Path) -> list[str]:
    """Everything in a Minari cache, hidden temporary directories included."""
    return sorted(p.relative_to(cache).as_posix() for p in cache.rglob("*")) if cache.exists() else []


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
