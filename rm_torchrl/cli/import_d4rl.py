"""``rmrl import-d4rl``: write a D4RL HDF5 file as a local Minari dataset, atomically, with a progress bar."""
from __future__ import annotations

from rm_torchrl.progress import Bars


HELP = "write a D4RL HDF5 file as a local Minari dataset (atomic)"


def add_arguments(p) -> None:
    """The flags of ``rmrl import-d4rl`` (for ``cli/main.py``)."""
    from rm_torchrl.data.episode_ends import EPISODE_ENDS

    p.add_argument("file", metavar="FILE", help="a D4RL .hdf5 file (observations, actions, rewards, terminals, timeouts), or "
                        "embedded:door-human-v0.hdf5 for the one shipped in the package")
    p.add_argument("--out-name", required=True, metavar="NAME",
                   help="Minari dataset id to write, e.g. d4rl/door-human-v0 (namespace/name-v<N>)")
    p.add_argument("--episode-ends", choices=EPISODE_ENDS, default="auto",
                   help="which HDF5 flags end episodes (default auto: the consistent ones)")
    p.add_argument("--env-id", metavar="ID",
                   help="gymnasium id stored as the dataset's env spec, e.g. AdroitHandDoor-v1 or FrankaKitchen-v1")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the dataset of that name if rmrl import-d4rl wrote it")


def run(args) -> int:
    from rm_torchrl.data.d4rl_to_minari import describe_import, import_d4rl
    from rm_torchrl.data.embedded import expand_embedded

    with Bars() as bars:
        dataset_id = import_d4rl(expand_embedded(args.file), args.out_name, episode_ends=args.episode_ends,
                                 env_id=args.env_id, overwrite=args.overwrite,
                                 progress=lambda done, total: bars.update("import", done, total, unit="episode"))
    print(describe_import(dataset_id, args.file))
    return 0
