"""The run directory: one process at a time, safe checkpoints, and whether a run starts, resumes or is done.

A run directory holds only what the trainer writes (:data:`TRAINER_FILES`). A directory without a
checkpoint is a run that never got going (killed during set-up, a bad evaluation env): the next
start clears the trainer's files and begins again. Anything else in it is refused, never deleted.
"""
from __future__ import annotations

import errno
import fcntl
import hashlib
import io
import json
import os
import shutil
import sys
from contextlib import contextmanager
from pathlib import Path

import torch

from rm_torchrl.data.embedded import expand_embedded
from rm_torchrl.errors import RMError, read_json
from rm_torchrl.files import WriteFailed, write_atomic
from rm_torchrl.run_format import (CHECKPOINT, DATA_FILE, EVAL_FILE, FAILED_FILE as FAILED, LOCK_FILE as LOCK,
                                   TRAINER_FILES, flat_recipe, temp_name, upgrade_recipe)

#: Recipe entries a resumed run must share with its checkpoint: what it learns from, the budget its schedules
#: are built over (a longer budget is a new run) and how it is evaluated. Logging, checkpointing, threads,
#: compile, the device and ``trainer.stop_at`` may change between a run and its continuation.
FROZEN = ("seed", "data", "rm", "method", "network", "optim", "trainer.steps", "trainer.batch_size",
          "trainer.gamma", "trainer.tau", "trainer.normalize_obs", "trainer.flush_denormal", "eval.env",
          "eval.env_kwargs", "eval.observation", "eval.max_steps", "eval.every", "eval.episodes", "eval.score",
          "eval.reward")
_STATE_KEYS = ("step", "loss", "optimizers", "generator", "torch_rng", "obs_loc", "obs_scale", "recipe")


class RunBusy(RMError):
    """The run directory is locked by another process, which trains it now. ``rmrl train`` exits 75 on it
    (sysexits' EX_TEMPFAIL: try again later), so a launcher can wait for that run instead of counting a failure."""

    exit_status = 75


def lock_holder(run_dir: Path) -> str | None:
    """The pid (as the lock file records it) of the process holding ``run_dir``'s :class:`RunLock`, else None;
    takes nothing and creates nothing."""
    try:
        fd = os.open(Path(run_dir) / LOCK, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return None
    except OSError:
        return _holder(fd)
    finally:
        os.close(fd)


def _holder(fd: int) -> str:
    """The pid a lock file records (its holder writes it), for messages."""
    return os.read(fd, 64).decode(errors="replace").strip() or "another process"


class RunLock:
    """An exclusive ``flock`` on ``RUN_DIR/.lock`` for the run's life.

    The kernel drops the lock when its process dies, however it dies, so a lock left by a killed
    run never blocks the next one; the file records the holder's pid for the error message.
    """

    def __init__(self, run_dir: Path):
        self.path = Path(run_dir) / LOCK
        self.fd = None

    def __enter__(self) -> "RunLock":
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise RMError(f"cannot use run directory {self.path.parent}: {err.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            holder = _holder(fd)
            os.close(fd)
            if err.errno in (errno.EWOULDBLOCK, errno.EACCES):
                raise RunBusy(f"run directory {self.path.parent} is in use by process {holder}") from None
            raise
        try:
            os.ftruncate(fd, 0)
            os.write(fd, str(os.getpid()).encode())
        except OSError:  # a full disk: the lock holds all the same, only others' messages lack the pid
            pass
        self.fd = fd
        return self

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            try:  # a run that wrote nothing (a bad source, say) leaves no folder behind; removed while still held
                if set(os.listdir(self.path.parent)) <= {LOCK, DATA_FILE}:
                    (self.path.parent / DATA_FILE).unlink(missing_ok=True)
                    self.path.unlink()
                    self.path.parent.rmdir()
            except OSError:
                pass
            os.close(self.fd)  # releases the flock; a kept file stays (harmless, recognised as the trainer's)
            self.fd = None


@contextmanager
def appending(path: Path):
    """A text file opened to append rows, all or nothing: when writing fails, the file is cut back
    to what it held before (cutting needs no space), so a full disk never leaves half a row."""
    path = Path(path)
    size = path.stat().st_size if path.exists() else 0
    try:
        with open(path, "a", newline="") as f:
            yield f
    except OSError as err:
        try:
            os.truncate(path, size)
        except OSError:
            pass
        raise WriteFailed(path, err) from None


def cut_partial_line(path: Path) -> None:
    """Drops an unfinished last line (a write cut short by a full disk) in place, needing no space."""
    try:
        with open(path, "rb") as f:
            data = f.read()
        if data and not data.endswith(b"\n"):
            os.truncate(path, data.rfind(b"\n") + 1)
    except OSError:
        pass


def save_checkpoint(path: Path, state: dict) -> None:
    """Plain tensors and containers only (loadable with ``weights_only=True``), written atomically:
    serialised in memory first, so that a full disk is an ``OSError`` (:class:`WriteFailed`) and not
    a torch zip-writer error, and the previous checkpoint stays whole."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_atomic(path, buffer.getbuffer(), Path(path).with_name(temp_name(Path(path).name)))


def load_checkpoint(path: Path) -> dict:
    """A checkpoint written by :func:`save_checkpoint`; never unpickles code (``weights_only=True``)."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated zip, garbage, a pickle with code in it: all unusable
        first = str(err).strip().splitlines()[0][:160] if str(err).strip() else type(err).__name__
        raise RMError(f"{path} is not a readable checkpoint ({first}); move its run directory away, or pick another "
                      "name or seed, to train the run afresh") from None
    if not isinstance(state, dict) or any(k not in state for k in _STATE_KEYS):
        raise RMError(f"{path} is not a checkpoint of rm_torchrl (expected the entries {list(_STATE_KEYS)})")
    if isinstance(state["step"], bool) or not isinstance(state["step"], int) or state["step"] < 0:
        raise RMError(f"{path} is not a checkpoint of rm_torchrl: its step must be a whole number >= 0, "
                      f"got {state['step']!r}")
    return state


def recipe_changes(old: dict, new: dict, keys=FROZEN, added=lambda value: True) -> list[str]:
    """``key: old -> new`` for every entry under ``keys`` (default :data:`FROZEN`) that differs between two
    recipe dicts. A key ``old`` lacks (an option added since) counts where ``added(its value in new)``."""
    a, b = flat_recipe(old), flat_recipe(new)
    wanted = [k for k in sorted(set(a) | set(b)) if any(k == f or k.startswith(f + ".") for f in keys)
              and (k in a or added(b[k]))]
    return [f"{k}: {_shown(a, k)} -> {_shown(b, k)}" for k in wanted if a.get(k) != b.get(k)]


def _shown(flat: dict, key: str) -> str:
    return repr(flat[key]) if key in flat else "(absent)"


def _foreign(run_dir: Path) -> list[str]:
    return sorted(p.name for p in run_dir.iterdir() if p.name not in TRAINER_FILES)


def last_evaluated_step(run_dir: Path) -> int | None:
    """The step of ``eval.csv``'s last row, None when the run holds no evaluation (or an unreadable one)."""
    try:
        rows = (Path(run_dir) / EVAL_FILE).read_text().splitlines()[1:]
    except (OSError, UnicodeDecodeError):
        return None
    rows = [row for row in rows if row.strip()]
    try:
        return int(rows[-1].split(",", 1)[0]) if rows else None
    except ValueError:
        return -1  # rows that are not this trainer's: evaluations all the same, never to be deleted


def data_file(source: str) -> dict | None:
    """What identifies the data file ``source``: its size, modification time and SHA-256 (compared: a copy or
    ``touch`` changes the time, not the data), None for a source that is not a file (a Minari dataset)."""
    path = Path(expand_embedded(str(source)))
    if not path.is_file():
        return None
    try:
        info = path.stat()
        with open(path, "rb") as f:
            digest = hashlib.file_digest(f, "sha256").hexdigest()
    except OSError as err:
        raise RMError(f"cannot read dataset file {path}: {err.strerror}") from None
    return {"path": str(path), "size": info.st_size, "mtime_ns": info.st_mtime_ns, "sha256": digest}


def _check_data_file(recipe, run_dir: Path) -> None:
    """Refuses a resume whose data file is not the one the run began on (replaced at the same path): the recipe
    would match, the data not. Runs begun before :data:`DATA_FILE` existed are not checked."""
    path = run_dir / DATA_FILE
    if not path.is_file():
        return
    was, now = read_json(path, "run data record"), data_file(recipe.data.source)
    if not isinstance(was, dict) or now is None or was.get("sha256") == now["sha256"]:
        return
    changed = f"{was.get('size')} bytes -> {now['size']} bytes" if was.get("size") != now["size"] else \
        "same size, other content"
    raise RMError(f"resume=true, but the dataset {now['path']} is not the file run {run_dir} began on ({changed}; "
                  f"recorded in {DATA_FILE}); restore that file, or pick another name or seed to train on this one")


def open_run(recipe) -> dict | None:
    """Decides how ``recipe`` starts: returns the checkpoint to resume, or None.

    Call it holding the :class:`RunLock`. Refuses: a checkpoint without ``resume=true``, a resume
    whose method, data or network differ from the checkpoint's or whose data file was replaced since the
    run began (:data:`DATA_FILE`), a checkpoint already past ``trainer.steps``, and a directory without a
    checkpoint that holds files the trainer did not write. Nothing is written but, for a new run,
    :data:`DATA_FILE`, before the data is read.
    """
    run_dir = recipe.run_dir
    ckpt = run_dir / CHECKPOINT
    if ckpt.is_file():
        state = load_checkpoint(ckpt)
        if not recipe.resume and state["step"] >= recipe.trainer.steps:  # another process may have just finished it
            raise RMError(f"run directory {run_dir} holds a finished run (its checkpoint is at step {state['step']}); "
                          "pick another name or seed")
        if not recipe.resume:
            raise RMError(f"run directory {run_dir} holds a checkpoint; pass resume=true to continue it "
                          "or pick another name/seed")
        changes = recipe_changes(upgrade_recipe(state["recipe"]), recipe.to_dict())
        if changes:
            budget = any(c.startswith("trainer.steps:") for c in changes)
            raise RMError(f"resume=true with a recipe that differs from the checkpoint's: {'; '.join(changes)}"
                          + ("; a run of another budget is a new run: pick another name or seed" if budget else ""))
        if state["step"] > recipe.trainer.steps:
            raise RMError(f"{ckpt} is at step {state['step']}, past trainer.steps={recipe.trainer.steps}")
        _check_data_file(recipe, run_dir)
        (run_dir / FAILED).unlink(missing_ok=True)
        return state
    evaluated = last_evaluated_step(run_dir)
    if evaluated is not None:
        raise RMError(f"run directory {run_dir} holds evaluations (eval.csv) but no checkpoint: it can neither "
                      "continue nor be trained again in place; pick another name or seed (or move it away)")
    foreign = _foreign(run_dir)
    if foreign:
        raise RMError(f"run directory {run_dir} has no checkpoint and holds files the trainer did not write: "
                      f"{foreign}; move them away or pick another name/seed")
    for name in TRAINER_FILES:
        path = run_dir / name
        if name != LOCK:
            shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
    if recipe.resume:
        print(f"resume=true, but {run_dir} holds no checkpoint yet: starting from step 0", file=sys.stderr)
    identity = data_file(recipe.data.source)
    if identity is not None:
        write_atomic(run_dir / DATA_FILE, json.dumps(identity, indent=1) + "\n")
    return None


def mark_failed(run_dir: Path, step: int, what: str, message: str) -> None:
    """``failed.json``: the run stopped on an error; ``rmrl report`` leaves it out of every table."""
    write_atomic(run_dir / FAILED, json.dumps({"step": step, "what": what, "message": message}, indent=1) + "\n")


def run_status(recipe) -> str:
    """What a multirun does with ``recipe``'s run: ``new``, ``resumable``, ``finished``, ``stopped`` (at its
    ``trainer.stop_at``: nothing to do this session), or one of :data:`LEFT_ALONE` (``failed``, ``kept``:
    evaluations without a checkpoint, ``unreadable``)."""
    run_dir = recipe.run_dir
    if (run_dir / FAILED).is_file():
        return "failed"
    ckpt = run_dir / CHECKPOINT
    if not ckpt.is_file():
        return "new" if last_evaluated_step(run_dir) is None else "kept"
    try:
        step = load_checkpoint(ckpt)["step"]
    except RMError:
        return "unreadable"
    if step >= recipe.trainer.steps:
        return "finished"
    return "stopped" if recipe.trainer.stop_at and step >= recipe.trainer.stop_at else "resumable"
