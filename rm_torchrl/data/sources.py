"""One entry point for every dataset source the CLI and recipes accept."""
from __future__ import annotations

import errno
import os
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase

from rm_torchrl.errors import RMError


def load_dataset(source: str, episode_ends: str = "auto") -> TensorDict:
    """``*.hdf5`` / ``*.h5`` D4RL files, ``minari:<dataset id>`` or a local Minari dataset name.

    Every floating-point entry (observations, actions, rewards) must be real, finite and within
    float32's range: one NaN would otherwise train to NaN networks that still report a score. Each
    loader checks its data as read (``require_finite``), before the cast to float32.
    """
    if not source:
        raise RMError("no dataset given")
    _check_path(source)
    if Path(source).is_dir():
        raise RMError(f"{source} is a directory: give a D4RL .hdf5 file, minari:<dataset id> or a local Minari "
                      "dataset name")
    if source.startswith("minari:"):
        from rm_torchrl.data.minari import load_minari

        if not source[len("minari:"):]:
            raise RMError("minari: needs a Minari dataset id after it, e.g. minari:D4RL/door/human-v2")
        return load_minari(source[len("minari:"):])
    if Path(source).suffix in (".hdf5", ".h5") or Path(source).is_file():
        from rm_torchrl.data.d4rl import load_d4rl_hdf5

        return load_d4rl_hdf5(source, episode_ends=episode_ends)
    from rm_torchrl.data.minari import load_minari

    return load_minari(source, download=False)


def _check_path(source: str) -> None:
    """A symlink loop or a dangling link named as such (elsewhere they read as "does not exist")."""
    try:
        os.stat(source)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise RMError(f"{source} is a symlink loop (following its links leads back to it); "
                          "give the real file") from None
        if os.path.islink(source):
            raise RMError(f"{source} is a symbolic link to {os.readlink(source)}, which does not exist") from None


_FLOAT32_MAX = torch.finfo(torch.float32).max


def require_finite(entries, source, unit: str = "transition") -> None:
    """Refuses complex, NaN, inf or beyond-float32 values in ``entries``, naming the entry, rows and columns.

    ``entries``: a TensorDict or a ``name -> tensor`` mapping, checked as read, before the cast to
    float32 that would turn 1e300 into inf after a finiteness test (or drop an imaginary part with
    only a warning). ``unit`` names what a row is ("row" of a file, "transition").
    """
    items = entries.items(include_nested=True, leaves_only=True) if isinstance(entries, TensorDictBase) \
        else entries.items()
    for key, value in items:
        name = "/".join(key) if isinstance(key, tuple) else key
        if value.is_complex():
            raise RMError(f"{source}: {name} hold complex numbers ({str(value.dtype).removeprefix('torch.')}); "
                          "only real values can be used")
        if not value.is_floating_point():
            continue
        flat = value.reshape(value.shape[0] if value.ndim else 1, -1)
        if not bool(torch.isfinite(flat).all()):
            _refuse(~torch.isfinite(flat), source, name, "NaN or inf", unit)
        if torch.finfo(value.dtype).max > _FLOAT32_MAX:  # float64
            big = flat.abs() > _FLOAT32_MAX
            if bool(big.any()):
                _refuse(big, source, name, f"values beyond float32's range (|x| > {_FLOAT32_MAX:.2g})", unit)


def _refuse(bad: torch.Tensor, source, name: str, what: str, unit: str) -> None:
    """The one-line error for the (rows, columns) ``bad`` of entry ``name``."""
    rows = bad.any(1).nonzero().flatten()
    columns = bad.any(0).nonzero().flatten()
    where = f" (column(s) {columns[:5].tolist()})" if bad.shape[1] > 1 else ""
    raise RMError(f"{source}: {name} contain {what} in {rows.numel()} {unit}(s), first at {unit}s "
                  f"{rows[:5].tolist()}{where}")
