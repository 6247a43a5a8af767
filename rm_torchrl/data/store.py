"""Atomic writing and reading of refined datasets (memory-mapped TensorDict + report.json), and the
markers that let ``--overwrite`` replace only what this project wrote."""
from __future__ import annotations

import ctypes
import errno
import functools
import glob
import json
import os
import re
import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable

from tensordict import TensorDict, TensorDictBase

from rm_torchrl.errors import RMError


#: Marks a directory as this project's refine output: only such a directory is replaced by --overwrite.
MARKER = ".rm_torchrl-refined"
COMMAND = "rmrl refine"
_PID = ".pid"
#: A temporary directory without a readable process id younger than this is being set up, not left over.
_SETTING_UP_S = 60.0
_AT_FDCWD, _RENAME_NOREPLACE = -100, 1


def files_in(directory: Path) -> set[str]:
    """Every path under ``directory`` but its non-empty directories: files and links (not followed), and
    empty directories (ending in ``/``), relative and ``/``-separated."""
    found = set()

    def walk(path: str, rel: str) -> None:
        with os.scandir(path) as entries:
            entries = list(entries)
        if rel and not entries:
            found.add(rel + "/")
        for entry in entries:
            name = f"{rel}/{entry.name}" if rel else entry.name
            if entry.is_dir(follow_symlinks=False):
                walk(entry.path, name)
            else:
                found.add(name)

    walk(os.fspath(directory), "")
    return found


def write_marker(directory: Path, marker: str, command: str) -> None:
    """Marks ``directory`` as written by ``command``, listing every path in it (see :func:`not_replaceable`)."""
    files = sorted(files_in(directory) - {_PID} | {marker})
    (directory / marker).write_text(json.dumps({"written_by": command, "files": files}, indent=1) + "\n")


def not_replaceable(directory: Path, marker: str, command: str,
                    legacy: Callable[[Path], Callable[[str], bool] | None] | None = None) -> str | None:
    """Why ``command`` may not replace ``directory``, or None when it may: it is empty, or it carries
    ``marker`` by ``command`` and holds nothing the marker does not list, so no file a user put there is
    deleted.

    ``legacy(directory)``: for outputs of versions that wrote no list, which paths are their own (None:
    not an output of ``command`` at all).
    """
    try:
        record = json.loads((directory / marker).read_text())
        written_by, listed = record["written_by"], set(record["files"])
        own = listed.__contains__
    except (OSError, ValueError, KeyError, TypeError):
        own, written_by = legacy(directory) if legacy is not None else None, command
        names = sorted(p.name for p in directory.iterdir())
        if own is None and names:
            return f"is not marked as written by {command} (no {marker}; it holds {_first(names)})"
    if written_by != command:
        return f"was written by {written_by}"
    foreign = sorted(p for p in files_in(directory) if own is None or not own(p))
    if foreign:
        return f"also holds files {command} did not write: {_first(foreign)}"
    return None


def _first(names: list[str], n: int = 5) -> str:
    more = f" and {len(names) - n} more" if len(names) > n else ""
    return f"{names[:n]}{more}"


def _legacy_refined(out: Path) -> Callable[[str], bool] | None:
    """A refine output of a version whose marker listed nothing: its files are tensordict's and report.json."""
    if not (out / MARKER).is_file():
        return None
    tensordict_file = re.compile(r"data/([^/]+/)*(meta\.json|[^/]+\.memmap)")
    return lambda p: p in ("report.json", MARKER) or tensordict_file.fullmatch(p) is not None


def check_out(out: str | Path, overwrite: bool) -> Path:
    """Refuses an output path that :func:`write_refined` must not touch; call it before the work starts.

    With ``overwrite``, only an earlier refine output holding nothing but what it wrote (its
    :data:`MARKER` lists that) is replaced; anything else is named and left alone.
    """
    out = Path(out)
    here = Path.cwd().resolve()
    target = out.resolve()
    if target == here or target in here.parents:
        raise RMError(f"--out {out} is the current directory or one above it; give a new directory")
    for parent in out.parents:
        if os.path.lexists(parent):
            if not parent.is_dir():
                raise RMError(f"--out {out} is under {parent}, which is a file, not a directory")
            break
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise RMError(f"--out {out} exists and is not a directory; refusing to replace it")
    if out.is_dir():
        if not overwrite:
            raise RMError(f"output directory {out} already exists; pass --overwrite to replace it")
        reason = not_replaceable(out, MARKER, COMMAND, _legacy_refined)
        if reason:
            raise RMError(f"--overwrite replaces only an earlier refine output, and {out} {reason}; "
                          "move it away or choose another --out")
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
        except ProcessLookupError:
            pass
        except PermissionError:
            continue  # alive, and another user's
        except (OSError, ValueError):  # no process id (yet, or any more: a run about to rename it)
            try:
                if time.time() - path.stat().st_mtime < _SETTING_UP_S:
                    continue
            except OSError:
                continue
        shutil.rmtree(path, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=suffix, dir=parent))
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700; the output is an ordinary directory
        (tmp / _PID).write_text(str(os.getpid()))
    except BaseException:  # a full disk, say: nothing is left behind
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return tmp


@functools.cache
def _renameat2():
    try:
        function = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return None
    function.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    function.restype = ctypes.c_int
    return function


def rename_noreplace(src: Path, dst: Path) -> None:
    """Renames ``src`` to ``dst``, or raises FileExistsError when ``dst`` exists.

    Atomic where Linux's ``renameat2(RENAME_NOREPLACE)`` works, so that of two runs placing their
    output at one new path, one wins and the other is told; elsewhere the check precedes the rename.
    """
    renameat2 = _renameat2()
    if renameat2 is not None:
        if renameat2(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst), _RENAME_NOREPLACE) == 0:
            return
        code = ctypes.get_errno()
        if code not in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):  # not: this filesystem cannot
            raise OSError(code, os.strerror(code), os.fspath(dst))
    if os.path.lexists(dst):
        raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), os.fspath(dst))
    os.rename(src, dst)


def reserve_space(directory: Path, nbytes: int) -> None:
    """Raises OSError ENOSPC now when ``directory``'s filesystem cannot take ``nbytes`` more.

    For writers that do not fail cleanly on a full disk (HDF5 crashes on closing a file whose write
    failed): the space is allocated in a scratch file and freed again just before they write.
    """
    fd, path = tempfile.mkstemp(dir=directory, prefix=".reserve-")
    try:
        os.posix_fallocate(fd, 0, max(1, int(nbytes)))
    except OSError as err:
        if err.errno in (errno.ENOSPC, errno.EDQUOT):
            raise
    finally:
        os.close(fd)
        os.unlink(path)


def no_space(err: BaseException) -> bool:
    """Whether ``err`` is a full disk: an OSError, or a RuntimeError of torch or HDF5 that names errno 28."""
    return (getattr(err, "errno", None) in (errno.ENOSPC, errno.EDQUOT)
            or re.search(r"No space left on device|errno = 28\b", str(err)) is not None)


def write_failure(err: BaseException, path: Path) -> RMError:
    """The one-line error for a failed write of ``path``, e.g. ``no space left on device writing PATH``."""
    code = getattr(err, "errno", None) or (errno.ENOSPC if no_space(err) else None)
    reason = os.strerror(code) if code else str(err)
    return RMError(f"{reason[:1].lower()}{reason[1:]} writing {path}")


def _memmap(data: TensorDictBase, prefix: Path) -> None:
    """``data.memmap(prefix)`` with each file's blocks allocated before it is mapped: a write through a
    mapping into a full filesystem is a SIGBUS that kills the process, a failed allocation an ENOSPC."""
    like = data.memmap_like(prefix=prefix)
    for path in prefix.rglob("*.memmap"):
        size = path.stat().st_size
        if size:
            fd = os.open(path, os.O_RDWR)
            try:
                os.posix_fallocate(fd, 0, size)
            finally:
                os.close(fd)
    like.update_(data)


def _restore_previous(out: Path, old: Path) -> None:
    """A run killed between moving the previous output aside and moving the new one in left ``old``."""
    if old.is_dir() and (old / MARKER).is_file():
        if out.exists():
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(old, out)


def output_in_place(out) -> str:
    """What an interrupt once the new output is in place says (the work is done)."""
    return f"interrupted after the output was written: {out} holds the new result, whole"


def write_refined(out: str | Path, data: TensorDictBase, report: dict, overwrite: bool = False) -> Path:
    """Writes ``out/data`` and ``out/report.json`` into a temporary sibling, then renames it into place.

    A failure or interruption leaves ``out`` as it was (absent, or the previous result); the
    temporary directory a killed run leaves is removed by the next run into the same place. Without
    ``overwrite`` the rename never replaces an output that another run placed meanwhile.
    """
    out = check_out(out, overwrite)
    old = out.with_name(f".{out.name}.old")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        _restore_previous(out, old)
        tmp = temp_dir(out.parent, f".{out.name}.", ".tmp")
    except OSError as err:
        if no_space(err):
            raise write_failure(err, out) from None
        raise RMError(f"cannot write into {out.parent}: {err.strerror}") from None
    try:
        try:
            _memmap(data, tmp / "data")
            (tmp / "report.json").write_text(json.dumps(report, indent=2) + "\n")
            write_marker(tmp, MARKER, COMMAND)
        except (OSError, RuntimeError) as err:  # torch reports a full disk as a RuntimeError
            if not isinstance(err, OSError) and not no_space(err):
                raise
            raise write_failure(err, out) from None
        if out.exists():
            check_out(out, overwrite)  # again: another run may have placed it, or a user added files, meanwhile
            shutil.rmtree(old, ignore_errors=True)
            os.replace(out, old)
        (tmp / _PID).unlink()
        try:
            rename_noreplace(tmp, out)
        except FileExistsError:
            raise RMError(f"output directory {out} already exists (another run wrote it meanwhile); "
                          "pass --overwrite to replace it") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old.exists() and not out.exists():
            os.replace(old, out)
        raise
    try:
        shutil.rmtree(old, ignore_errors=True)
    except KeyboardInterrupt as err:  # SIGINT/SIGTERM now: the new output is in place; finish removing the old one
        shutil.rmtree(old, ignore_errors=True)
        err.message = output_in_place(out)
        err.written = out
        raise
    return out


def read_refined(path: str | Path) -> tuple[TensorDict, dict]:
    """The refined dataset (memory-mapped) and its report, as written by ``write_refined``."""
    path = Path(path)
    if not (path / "report.json").is_file() or not (path / "data").is_dir():
        raise RMError(f"{path} is not a refined dataset directory (expected data/ and report.json)")
    return TensorDict.load_memmap(path / "data"), json.loads((path / "report.json").read_text())
