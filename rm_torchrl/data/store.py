"""Atomic writing and reading of refined datasets (memory-mapped TensorDict + report.json)."""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

from tensordict import TensorDict, TensorDictBase

from rm_torchrl.errors import RMError


def write_refined(out: str | Path, data: TensorDictBase, report: dict, overwrite: bool = False) -> Path:
    """Writes ``out/data`` and ``out/report.json`` into a temporary sibling, then renames it into place.

    A failure or interruption leaves ``out`` as it was (absent, or the previous result).
    """
    out = Path(out)
    if out.exists() and not overwrite:
        raise RMError(f"output directory {out} already exists; pass --overwrite to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    old = out.with_name(f".{out.name}.old")
    try:
        data.memmap(prefix=tmp / "data")
        (tmp / "report.json").write_text(json.dumps(report, indent=2) + "\n")
        if out.exists():
            shutil.rmtree(old, ignore_errors=True)
            os.replace(out, old)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old.exists() and not out.exists():
            os.replace(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)
    return out


def read_refined(path: str | Path) -> tuple[TensorDict, dict]:
    """The refined dataset (memory-mapped) and its report, as written by ``write_refined``."""
    path = Path(path)
    if not (path / "report.json").is_file() or not (path / "data").is_dir():
        raise RMError(f"{path} is not a refined dataset directory (expected data/ and report.json)")
    return TensorDict.load_memmap(path / "data"), json.loads((path / "report.json").read_text())
