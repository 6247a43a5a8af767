"""rmrl: refine offline RL datasets with event-ordered reward machines, train and evaluate on them, report."""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading

# Back large CPU tensors with transparent huge pages: refinement allocates a few big tensors,
# and first-touch page faults would otherwise cost as much as the work itself.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

from rm_torchrl.data.d4rl import EPISODE_ENDS  # noqa: E402
from rm_torchrl.errors import RMError  # noqa: E402


def _constraint(text: str) -> tuple[str, str]:
    before, sep, after = text.partition("<")
    if not sep or not before.strip() or not after.strip() or "<" in after:
        raise argparse.ArgumentTypeError(f"constraints look like 'a<b' (event a before event b), got {text!r}")
    return before.strip(), after.strip()


def _add_source(p: argparse.ArgumentParser, required: bool = True) -> None:
    p.add_argument("--dataset", required=required, metavar="SRC",
                   help="a D4RL .hdf5 file, minari:<dataset id>, or a local Minari dataset name")
    p.add_argument("--events", required=required, metavar="NAME_OR_YAML",
                   help="built-in event spec (door, relocate, kitchen, kitchen-v0) or a YAML file")
    p.add_argument("--episode-ends", choices=EPISODE_ENDS, default=None if not required else "auto",
                   help="which HDF5 flags end episodes (default auto: the consistent ones)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rmrl", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("refine", help="refine a dataset with an event-ordered reward machine")
    p.add_argument("--config", metavar="YAML", help="a refine recipe (recipes/refine/*.yaml); flags override it")
    _add_source(p, required=False)
    p.add_argument("--alpha", help="fraction of shortest sub-trajectories kept per group, in (0, 1] (default 1)")
    p.add_argument("--constraint", action="append", type=_constraint, metavar="A<B",
                   help="event A must come before event B in the chosen order (repeatable)")
    p.add_argument("--out", metavar="DIR", help="output directory (data/ and report.json)")
    p.add_argument("--minari-name", metavar="NAME",
                   help="also write the refined data as the local Minari dataset NAME (namespace/name-vN): one "
                        "episode per sub-trajectory, observations with the RM state")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out if it is an earlier refine output holding only what refine wrote")
    p.add_argument("--overwrite-minari", action="store_true",
                   help="replace the Minari dataset --minari-name if an earlier rmrl refine --minari-name wrote it")
    p.set_defaults(run="rm_torchrl.cli.refine:run")

    p = sub.add_parser("inspect", help="per-event statistics of a dataset")
    _add_source(p)
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--plot", metavar="FILE.png", help="also draw event timelines: per episode when each event holds "
                                                      "and fires over the RM state, per group the lengths and alpha's cut")
    p.add_argument("--plot-episodes", type=int, default=6, help="episodes drawn (a seeded sample; default 6)")
    p.add_argument("--alpha", default="1.0", help="the alpha whose cut the length histograms mark (default 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the episode sample")
    p.set_defaults(run="rm_torchrl.cli.inspect_events:run")

    p = sub.add_parser("rm-graph", help="draw the event-ordered RM (Graphviz DOT or Mermaid)")
    p.add_argument("--events", required=True, metavar="NAME_OR_YAML")
    p.add_argument("--format", choices=("dot", "mermaid"), default="dot")
    p.add_argument("--order", metavar="A,B,C", help="draw only the path of this event order (comma-separated "
                                                    "event names of the spec, each once; some or all of them)")
    p.add_argument("--out", metavar="FILE", help="write to FILE instead of standard output")
    p.set_defaults(run="rm_torchrl.cli.graph:run")

    p = sub.add_parser("train", help="train offline: dataset=NAME method=NAME, or a recipe file (Hydra overrides)",
                       description="rmrl train [RECIPE.yaml] [key=value ...]: without RECIPE, recipes/train.yaml "
                                   "composes dataset=NAME (recipes/dataset/) with method=NAME (recipes/method/).")
    p.add_argument("args", nargs="*", metavar="[RECIPE] key=value",
                   help="a recipe YAML (optional), then Hydra overrides, e.g. method=iql trainer.steps=2000 seed=3")
    p.add_argument("-m", "--multirun", action="store_true",
                   help="a Hydra multirun over comma-separated values (seed=0,1,2); finished runs are skipped")
    p.add_argument("--jobs", type=int, default=2, help="parallel runs of the default (joblib) launcher (default 2)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(run="rm_torchrl.cli.train:run")

    from rm_torchrl.cli.evaluate import add_arguments as _evaluate_arguments

    p = sub.add_parser("evaluate", help="evaluate a run's checkpoint in its env, as the trainer does")
    _evaluate_arguments(p)
    p.set_defaults(run="rm_torchrl.cli.evaluate:run")

    from rm_torchrl.cli.report import add_arguments as _report_arguments

    p = sub.add_parser("report", help="Table 1/Table 2 in Markdown and learning curves from training runs")
    _report_arguments(p)
    p.set_defaults(run="rm_torchrl.cli.report:run")

    from rm_torchrl.cli.import_d4rl import add_arguments as _import_arguments

    p = sub.add_parser("import-d4rl", help="write a D4RL HDF5 file as a local Minari dataset (atomic)")
    _import_arguments(p)
    p.set_defaults(run="rm_torchrl.cli.import_d4rl:run")

    from rm_torchrl.cli.generate import add_arguments as _generate_arguments

    p = sub.add_parser("generate", help="record scripted demonstrations as a local Minari dataset (atomic)")
    _generate_arguments(p)
    p.set_defaults(run="rm_torchrl.cli.generate:run")

    p = sub.add_parser("demo", help="the main job: refine door data, train IQL with and without the RM, "
                                     "evaluate in MuJoCo, write the report (no download)")
    p.add_argument("--dataset", help="a door D4RL .hdf5 (default: ../shared/data/d4rl/door-human-v0.hdf5 if "
                                     "present, else door-like data built here)")
    p.add_argument("--steps", type=int, default=3000, help="gradient steps per run")
    p.add_argument("--transitions", type=int, default=20_000, help="size of the built door-like data")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/demo", metavar="DIR")
    p.set_defaults(run="rm_torchrl.cli.demo:run")
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that every command's clean-up runs (temporary outputs are removed)."""

    signum = signal.SIGTERM
    message = "terminated (SIGTERM); nothing was written"


def _terminate(signum, frame):
    raise Terminated


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    module, _, func = args.run.partition(":")
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate)  # the trainer checkpoints on it instead, inside its loop
    try:
        command = getattr(__import__(module, fromlist=[func]), func)
        return command(args) or 0
    except RMError as err:
        print(f"rmrl {args.command}: error: {err}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `rmrl rm-graph ... | head`: the reader has what it wanted
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except KeyboardInterrupt as err:
        return interrupted(err, f"rmrl {args.command}")


def interrupted(err: KeyboardInterrupt, prog: str) -> int:
    """Says what an interrupted command saved and returns its exit status (130 for SIGINT, 143 for SIGTERM)."""
    signum = getattr(err, "signum", None)  # RunInterrupted (a run, a sweep, run_many): says what was saved
    message = getattr(err, "message", None) or "interrupted; nothing was written"
    print(f"{prog}: {message}", file=sys.stderr)
    return 128 + (signum or 2)


if __name__ == "__main__":
    sys.exit(main())
