"""One entry point for every dataset source the CLI and recipes accept."""
from __future__ import annotations

import errno
import os
from pathlib import Path

from tensordict import TensorDict

from rm_torchrl.data.embedded import expand_embedded
from rm_torchrl.errors import RMError


def load_dataset(source, episode_ends: str = "auto") -> TensorDict:
    """``*.hdf5`` / ``*.h5`` D4RL files (a path or a ``str``), ``embedded:<file>`` (a file shipped in the package,
    e.g. ``embedded:door-human-v0.hdf5``), ``minari:<dataset id>`` or a local Minari dataset name.

    Every floating-point entry (observations, actions, rewards) must be real, finite and within
    float32's range: one NaN would otherwise train to NaN networks that still report a score. Each
    loader checks its data as read (``require_finite``), before the cast to float32.
    """
    if isinstance(source, os.PathLike):
        source = os.fspath(source)
    if not isinstance(source, str):
        raise RMError(f"a dataset source is a path or a string, got {type(source).__name__}")
    if not source:
        raise RMError("no dataset given")
    source = expand_embedded(source)
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
