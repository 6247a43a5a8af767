"""``rmrl generate``: record scripted demonstrations as a local Minari dataset, atomically, with a progress bar."""
from __future__ import annotations

import math

from rm_torchrl.errors import RMError
from rm_torchrl.progress import Bars

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
    from rm_torchrl.generate import GENERATORS, describe_generated, generate_dataset
    from rm_torchrl.generate.cloned import CLONED, generate_cloned
    from rm_torchrl.train.config import check_seed

    if args.noise is not None and not (math.isfinite(args.noise) and args.noise >= 0):
        raise RMError(f"--noise must be a finite number >= 0, got {args.noise}")
    check_seed(args.seed, "--seed")
    name = args.generator
    with Bars() as bars:
        if name in CLONED:
            dataset_id = generate_cloned(name, args.out_name, steps=args.steps, seed=args.seed, workers=args.workers,
                                         demos_source=args.demos, overwrite=args.overwrite,
                                         progress=lambda stage, done, total: bars.update(f"{name} {stage}", done, total),
                                         noise=0.1 if args.noise is None else args.noise, bc_steps=args.bc_steps)
        else:
            dataset_id = generate_dataset(
                GENERATORS[name], args.out_name, episodes=args.episodes, seed=args.seed, workers=args.workers,
                max_steps=args.max_steps, overwrite=args.overwrite,
                policy_kwargs={} if args.noise is None else {"noise": args.noise},
                progress=lambda kept, total, attempts: bars.update(f"generate {name}", kept, total,
                                                                       f"{attempts} attempts", unit="episode"))
    print(describe_generated(dataset_id, name))
    return 0
