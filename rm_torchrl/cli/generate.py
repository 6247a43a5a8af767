"""``rmrl generate``: record scripted demonstrations as a local Minari dataset, atomically, with a progress bar."""
from __future__ import annotations

import math
import sys

from rm_torchrl.progress import progress_bar

from rm_torchrl.errors import RMError


HELP = "record scripted demonstrations as a local Minari dataset (atomic)"


def add_arguments(p) -> None:
    """The flags of ``rmrl generate`` (for ``cli/main.py``)."""
    from rm_torchrl.generate import GENERATORS
    from rm_torchrl.generate.cloned import CLONED

    described = {**{n: g.description for n, g in GENERATORS.items()}, **{n: c.description for n, c in CLONED.items()}}
    p.add_argument("generator", choices=sorted(described), help="what to generate: " + "; ".join(  # argparse %-formats
        f"{name}: {text}" for name, text in sorted(described.items())).replace("%", "%%"))
    p.add_argument("--out-name", required=True, metavar="NAME",
                   help="Minari dataset id to write, e.g. rmrl/relocate-human-v0 (namespace/name-v<N>)")
    p.add_argument("--episodes", type=int, default=25,
                   help="episodes to keep (default 25): successful ones for relocate, every attempt for kitchen "
                        "play (kitchen-mixed drops the rare episode that completes all four goal tasks)")
    p.add_argument("--seed", type=int, default=0, help="the dataset is a function of the seed (default 0)")
    p.add_argument("--workers", type=int, default=1,
                   help="processes simulating in parallel; the dataset does not depend on it (default 1)")
    p.add_argument("--max-steps", type=int, default=None,
                   help="episode step limit (default: the generator's, 800 for relocate and kitchen)")
    p.add_argument("--noise", type=float, default=None,
                   help="std of the action noise (default: the generator's, 0.02 on relocate's wrist and fingers, "
                        "0.1 on every kitchen action)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset of that name")
    p.add_argument("--steps", type=int, default=1_000_000,
                   help="*-cloned: total transitions, half human demos (repeated), half BC rollouts (default 1,000,000)")
    p.add_argument("--demos", default=None, metavar="SOURCE",
                   help="*-cloned: the human demos, a D4RL .hdf5 or a local Minari id (default: "
                        "D4RL's door-human-v0 shipped in the package for door, rmrl/relocate-human-v0 for relocate)")
    p.add_argument("--bc-steps", type=int, default=5000, help="*-cloned: BC gradient steps (default 5000)")


def run(args) -> int:
    import minari
    from minari.storage import get_dataset_path

    from rm_torchrl.generate import GENERATE_METADATA_KEY, GENERATORS, generate_dataset

    if args.noise is not None and not (math.isfinite(args.noise) and args.noise >= 0):
        raise RMError(f"--noise must be a finite number >= 0, got {args.noise}")
    from rm_torchrl.train.config import check_seed

    check_seed(args.seed, "--seed")
    from rm_torchrl.generate.cloned import CLONED

    if args.generator in CLONED:
        return _run_cloned(args)
    policy_kwargs = {} if args.noise is None else {"noise": args.noise}
    bar = None

    def progress(kept: int, total: int, attempts: int) -> None:
        nonlocal bar
        if bar is None:
            bar = progress_bar(total=total, desc=f"generate {args.generator}", unit="episode", file=sys.stderr, leave=False)
        bar.set_postfix_str(f"{attempts} attempts")
        bar.update(kept - bar.n)

    try:
        dataset_id = generate_dataset(GENERATORS[args.generator], args.out_name, episodes=args.episodes,
                                      seed=args.seed, workers=args.workers, max_steps=args.max_steps,
                                      overwrite=args.overwrite, policy_kwargs=policy_kwargs, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    dataset = minari.load_dataset(dataset_id)
    record = dataset.storage.metadata.get(GENERATE_METADATA_KEY, {})
    length = record.get("episode_length", {})
    print(f"generated {dataset.total_episodes:,} episodes ({record.get('keep', 'kept')}; "
          f"{dataset.total_steps:,} transitions) of "
          f"{args.generator} in {record.get('attempts', '?')} attempts; episode length mean "
          f"{length.get('mean', float('nan')):.1f}, min {length.get('min', '?')}, max {length.get('max', '?')}")
    print(f"wrote Minari dataset {dataset_id} to {get_dataset_path(dataset_id)}")
    events = GENERATORS[args.generator].events
    if dataset.total_episodes >= 2 and events:
        print(f"refine it with: rmrl refine --dataset {dataset_id} --events {events} --out ...")
    return 0


def _run_cloned(args) -> int:
    import minari
    from minari.storage import get_dataset_path

    from rm_torchrl.generate import GENERATE_METADATA_KEY
    from rm_torchrl.generate.cloned import generate_cloned

    bars: dict = {}

    def progress(stage: str, done: int, total: int) -> None:
        if stage not in bars:
            bars[stage] = progress_bar(total=total, desc=f"{args.generator} {stage}", file=sys.stderr, leave=False)
        bars[stage].total = total
        bars[stage].update(done - bars[stage].n)

    try:
        dataset_id = generate_cloned(args.generator, args.out_name, steps=args.steps, seed=args.seed,
                                     workers=args.workers, demos_source=args.demos, overwrite=args.overwrite,
                                     progress=progress, noise=0.1 if args.noise is None else args.noise,
                                     bc_steps=args.bc_steps)
    finally:
        for bar in bars.values():
            bar.close()
    dataset = minari.load_dataset(dataset_id)
    mix = dataset.storage.metadata.get(GENERATE_METADATA_KEY, {}).get("mix", {})
    print(f"generated {args.generator}: {dataset.total_steps:,} transitions in {dataset.total_episodes:,} episodes "
          f"({mix.get('demo_episodes', '?')} demo episodes, {mix.get('demo_transitions', '?')} transitions; "
          f"{mix.get('rollout_episodes', '?')} BC rollouts, {mix.get('rollout_transitions', '?')} transitions)")
    print(f"wrote Minari dataset {dataset_id} to {get_dataset_path(dataset_id)}")
    events = args.generator.split("-")[0]
    print(f"refine it with: rmrl refine --dataset {dataset_id} --events {events} --out ...")
    return 0
