"""The one dataset shipped inside the package: D4RL's ``door-human-v0`` (CC BY 4.0, see
``d4rl_files/CREDIT.md``), so that the demo and the ``door-human-v0`` recipes need no download."""
from __future__ import annotations

from pathlib import Path

from rm_torchrl.errors import RMError

EMBEDDED_DIR = Path(__file__).resolve().parent / "d4rl_files"
DOOR_HUMAN_V0 = EMBEDDED_DIR / "door-human-v0.hdf5"


def embedded_file(name: str) -> Path:
    """The packaged data file ``name`` (``${embedded:NAME}`` in recipes)."""
    path = EMBEDDED_DIR / name
    if Path(name).name != name or path.suffix != ".hdf5" or not path.is_file():
        shipped = sorted(p.name for p in EMBEDDED_DIR.glob("*.hdf5"))
        raise RMError(f"no embedded data file {name!r}; the package ships {shipped}")
    return path


def expand_embedded(source: str) -> str:
    """``embedded:NAME`` as the packaged file's path (any other source unchanged): a spelling that works from any
    directory and from an installed wheel."""
    return str(embedded_file(source[len("embedded:"):])) if source.startswith("embedded:") else source
