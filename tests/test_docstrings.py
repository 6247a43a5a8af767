"""Every ``>>>`` example in the package runs (doctest), so a shape or a value in a docstring cannot go stale;
none is skipped: an example that needs what tests cannot build points at the README block that runs it."""
from __future__ import annotations

import doctest
import importlib
import os
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "rm_torchrl"
WITH_EXAMPLES = sorted(p for p in PACKAGE.rglob("*.py") if ">>>" in p.read_text())


def module_name(path: Path) -> str:
    return ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)


def test_the_package_has_examples():
    assert len(WITH_EXAMPLES) >= 7


@pytest.mark.parametrize("path", WITH_EXAMPLES, ids=module_name)
def test_docstring_examples_run(path, monkeypatch):
    assert "doctest: +SKIP" not in path.read_text(), f"{path.name}: an example that does not run"
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))
    module = importlib.import_module(module_name(path))
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.attempted > 0, f"{path.name}: no example found"
    assert result.failed == 0, f"{path.name}: {result.failed} of {result.attempted} examples failed (see above)"
