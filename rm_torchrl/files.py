"""Whole-or-nothing file writes: a reader never sees half a file, and a full disk costs nothing."""
from __future__ import annotations

import os
from pathlib import Path

from rm_torchrl.errors import RMError


class WriteFailed(RMError):
    """A file could not be written (a full disk, a read-only or vanished directory): one line naming
    the path. Whatever the file held before is still there, and nothing partial is left."""

    def __init__(self, path: Path, err: OSError):
        super().__init__(f"cannot write {path}: {err.strerror or err}")
        self.path = Path(path)


def temp_name(name: str) -> str:
    """The name :func:`write_atomic` writes a file ``name`` under before renaming it (its default)."""
    return f".{name}.tmp"


def private_temp(path: Path) -> Path:
    """A temporary name beside ``path`` that is this process's own: two processes writing one file (two reports
    into one folder at once) never write into each other's temporary file."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def write_atomic(path: Path, data: bytes | str, tmp: Path | None = None) -> None:
    """``data`` into ``path`` through ``tmp`` (default :func:`temp_name` beside it), renamed over
    ``path`` when complete; when writing fails the temporary file is removed, so a full disk keeps
    the previous version and gets its space back."""
    path = Path(path)
    tmp = Path(tmp) if tmp is not None else path.with_name(temp_name(path.name))
    try:
        with open(tmp, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
        os.replace(tmp, path)
    except OSError as err:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:  # a read-only folder, a name too long: there is no temporary file to remove
            pass
        raise WriteFailed(path, err) from None
