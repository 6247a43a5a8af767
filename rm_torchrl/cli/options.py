"""Flags that several commands share: where the data comes from and which events it has."""
from __future__ import annotations

import argparse

from rm_torchrl.data.episode_ends import EPISODE_ENDS


def add_source(p: argparse.ArgumentParser, required: bool = True) -> None:
    """``--dataset``, ``--events`` and ``--episode-ends``."""
    p.add_argument("--dataset", required=required, metavar="SRC",
                   help="a D4RL .hdf5 file, minari:<dataset id>, or a local Minari dataset name")
    p.add_argument("--events", required=required, metavar="NAME_OR_YAML",
                   help="built-in event spec (door, relocate, kitchen, kitchen-v0) or a YAML file")
    p.add_argument("--episode-ends", choices=EPISODE_ENDS, default=None if not required else "auto",
                   help="which HDF5 flags end episodes (default auto: the consistent ones)")


def constraint(text: str) -> tuple[str, str]:
    """``a<b`` (event a before event b) -> ``("a", "b")``."""
    before, sep, after = text.partition("<")
    if not sep or not before.strip() or not after.strip() or "<" in after:
        raise argparse.ArgumentTypeError(f"constraints look like 'a<b' (event a before event b), got {text!r}")
    return before.strip(), after.strip()
