"""One entry point for every dataset source the CLI and recipes accept."""
from __future__ import annotations

from pathlib import Path

from tensordict import TensorDict

from rm_torchrl.errors import RMError


def load_dataset(source: str, episode_ends: str = "auto") -> TensorDict:
    """``*.hdf5`` / ``*.h5`` D4RL files, ``minari:<dataset id>`` or a local Minari dataset name."""
    if not source:
        raise RMError("no dataset given")
    if source.startswith("minari:"):
        from rm_torchrl.data.minari import load_minari

        return load_minari(source[len("minari:"):])
    if Path(source).suffix in (".hdf5", ".h5") or Path(source).is_file():
        from rm_torchrl.data.d4rl import load_d4rl_hdf5

        return load_d4rl_hdf5(source, episode_ends=episode_ends)
    from rm_torchrl.data.minari import load_minari

    return load_minari(source, download=False)
