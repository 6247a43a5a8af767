"""Fixtures shared by the test files."""
from __future__ import annotations

import os
from pathlib import Path

import pytest


def generate_cli(*argv: str) -> int:
    """``rmrl generate ARGV`` through the subcommand's own parser and ``run``."""
    import argparse

    from rm_torchrl.cli.generate import add_arguments, run

    parser = argparse.ArgumentParser(prog="rmrl generate")
    add_arguments(parser)
    args = parser.parse_args(list(argv))
    args.command = "generate"
    return run(args)


def load_benchmark(name: str):
    """The module of ``benchmarks/NAME.py`` (the scripts are not a package)."""
    import importlib.util

    script = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
