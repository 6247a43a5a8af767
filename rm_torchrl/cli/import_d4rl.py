"""``rmrl import-d4rl``: write a D4RL HDF5 file as a local Minari dataset, atomically, with a progress bar."""
from __future__ import annotations

import sys

from rm_torchrl.progress import progress_bar

from rm_torchrl.data.d4rl_to_minari import IMPORT_METADATA_KEY, import_d4rl
from rm_torchrl.data.embedded import expand_embedded


HELP = "write a D4RL HDF5 file as a local Minari dataset (atomic)"


def add_arguments(p) -> None:
    """The flags of ``rmrl import-d4rl`` (for ``cli/main.py``)."""
    from rm_torchrl.data.d4rl import EPISODE_ENDS

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
    import minari
    from minari.storage import get_dataset_path

    bar = None

    def progress(written: int, total: int) -> None:
        nonlocal bar
        if bar is None:  # opened on the first episode, so an early error prints no empty bar
            bar = progress_bar(total=total, desc="import", unit="episode", file=sys.stderr, leave=False)
        bar.update(written - bar.n)

    try:
        dataset_id = import_d4rl(expand_embedded(args.file), args.out_name, episode_ends=args.episode_ends, env_id=args.env_id,
                                 overwrite=args.overwrite, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    dataset = minari.load_dataset(dataset_id)
    record = dataset.storage.metadata.get(IMPORT_METADATA_KEY, {})
    env = f", env {dataset.env_spec.id}" if dataset.env_spec is not None else ""
    print(f"imported {args.file}: {dataset.total_episodes:,} episodes, {dataset.total_steps:,} transitions "
          f"(episodes ended by {record.get('episode_ends', '?')}{env})")
    skipped = record.get("skipped_single_step_episodes", 0)
    if skipped:
        print(f"skipped {skipped} single-step episode(s): they hold no transition")
    print(f"wrote Minari dataset {dataset_id} to {get_dataset_path(dataset_id)}")
    if dataset.total_episodes < 2:
        print("note: TorchRL's Minari reader (rmrl refine --dataset) needs at least 2 episodes", file=sys.stderr)
    else:
        print(f"read it with: rmrl refine --dataset {dataset_id} --events ... --out ...")
    return 0
