"""Atomic writing and reading of refined datasets (memory-mapped TensorDict + report.json)."""
from __future__ import annotations

import glob
import json
import os
import shutil
import tempfile
from pathlib import Path

from tensordict import TensorDict, TensorDictBase

from rm_torchrl.errors import RMError


#: Marks a directory as this project's refine output: only such a directory is replaced by --overwrite.
MARKER = ".rm_torchrl-refined"
_OWN = {"data", "report.json", MARKER}
_PID = ".pid"


def check_out(out: str | Path, overwrite: bool) -> Path:
    """Refuses an output path that :func:`write_refined` must not touch; call it before the work starts.

    With ``overwrite``, only an earlier refine output (it holds :data:`MARKER`, or only ``data/``
    and ``report.json``) is replaced; anything else is named and left alone.
    """
    out = Path(out)
    here = Path.cwd().resolve()
    target = out.resolve()
    if target == here or target in here.parents:
        raise RMError(f"--out {out} is the current directory or one above it; give a new directory")
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise RMError(f"--out {out} exists and is not a directory; refusing to replace it")
    if out.is_dir():
        if not overwrite:
            raise RMError(f"output directory {out} already exists; pass --overwrite to replace it")
        names = {p.name for p in out.iterdir()}
        if MARKER not in names and not names <= _OWN:
            raise RMError(f"--overwrite replaces only an earlier refine output, and {out} holds "
                          f"{sorted(names - _OWN)[:5]}; move it away or choose another --out")
    return out


def temp_dir(parent: Path, prefix: str, suffix: str = "") -> Path:
    """A new ``parent/<prefix>XXXX<suffix>`` directory for output being built, mode as umask allows.

    It records its process id, so the next call with the same prefix removes the leftovers of
    killed runs (whose process is gone) and leaves those of running ones alone.
    """
    for path in parent.glob(f"{glob.escape(prefix)}*{glob.escape(suffix)}"):
        try:
            os.kill(int((path / _PID).read_text()), 0)
            continue  # its process is alive: a run into the same place, right now
        except (OSError, ValueError):
            shutil.rmtree(path, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=suffix, dir=parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700; the output is an ordinary directory
    (tmp / _PID).write_text(str(os.getpid()))
    return tmp


def _restore_previous(out: Path, old: Path) -> None:
    """A run killed between moving the previous output aside and moving the new one in left ``old``."""
    if old.is_dir() and (old / MARKER).is_file():
        if out.exists():
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(old, out)


def write_refined(out: str | Path, data: TensorDictBase, report: dict, overwrite: bool = False) -> Path:
    """Writes ``out/data`` and ``out/report.json`` into a temporary sibling, then renames it into place.

    A failure or interruption leaves ``out`` as it was (absent, or the previous result); the
    temporary directory a killed run leaves is removed by the next run into the same place.
    """
    out = check_out(out, overwrite)
    old = out.with_name(f".{out.name}.old")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        _restore_previous(out, old)
        tmp = temp_dir(out.parent, f".{out.name}.", ".tmp")
    except OSError as err:
        raise RMError(f"cannot write into {out.parent}: {err.strerror}") from None
    try:
        data.memmap(prefix=tmp / "data")
        (tmp / "report.json").write_text(json.dumps(report, indent=2) + "\n")
        (tmp / MARKER).write_text("written by rmrl refine; rmrl refine --overwrite may replace this directory\n")
        (tmp / _PID).unlink()
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
