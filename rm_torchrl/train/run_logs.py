"""A run's logged history: TorchRL's logger under ``logs/``, and the rows a resume or a full disk leaves behind."""
from __future__ import annotations

from pathlib import Path

from rm_torchrl.errors import RMError
from rm_torchrl.files import WriteFailed, write_atomic
from rm_torchrl.run_format import EVAL_FILE, LOGS_DIR
from rm_torchrl.train.config import Recipe
from rm_torchrl.train.rundir import cut_partial_line


def make_logger(recipe: Recipe, run_dir: Path):
    from torchrl.record.loggers import get_logger

    backend = recipe.logger.backend
    kwargs = {"project": recipe.logger.project} if backend == "wandb" else {}
    try:
        return get_logger(backend, logger_name=str(run_dir), experiment_name=LOGS_DIR, **kwargs)
    except ImportError as err:
        raise RMError(f"logger.backend={backend} needs its package: pip install 'rm_torchrl[{backend}]' ({err})") from None


def trim_history(run_dir: Path, step: int) -> None:
    """Drops logged rows past ``step`` so a resumed run does not log them twice, and any row cut short
    (a full disk, a kill during a write); every row ends in ``\\n``, as new ones are written."""
    files = [run_dir / EVAL_FILE, *sorted((run_dir / LOGS_DIR / "scalars").glob("*.csv"))]
    for path in files:
        if not path.is_file():
            continue
        lines = path.read_text().splitlines(keepends=True)
        head = lines[:1] if path.name == EVAL_FILE else []
        kept = [row for row in lines[len(head):] if (at := row_step(row)) is not None and at <= step]
        write_atomic(path, "".join(line.rstrip("\r\n") + "\n" for line in head + kept))


def row_step(row: str) -> int | None:
    """The step of a logged row, or None for a blank or unfinished one."""
    if not row.endswith("\n") or not row.strip():
        return None
    try:
        return int(float(row.split(",")[0]))
    except ValueError:
        return None


class ScalarLog:
    """The TorchRL logger under ``logs/``; a full disk is a :class:`WriteFailed` with no half-written row."""

    def __init__(self, recipe: Recipe, run_dir: Path):
        self.dir = run_dir / LOGS_DIR
        try:
            self.logger = make_logger(recipe, run_dir)
        except OSError as err:  # its folders on a full disk
            raise WriteFailed(self.dir, err) from None

    def __call__(self, key: str, value: float, step: int) -> None:
        try:
            self.logger.log_scalar(key, value, step=step)
        except OSError as err:  # a full disk: close the logger's files now (no flush retried at exit), cut the last row
            for f in list(getattr(self.logger.experiment, "files", {}).values()):
                try:
                    f.close()
                except OSError:
                    pass
            for path in self.dir.rglob("*.csv"):
                cut_partial_line(path)
            raise WriteFailed(self.dir, err) from None
