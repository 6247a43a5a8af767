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


def _reopen_closed_streams() -> None:
    """A command started with stdout or stderr closed (``2>&-``) writes them to /dev/null: Python would set the
    stream to None (prints then land elsewhere), and libraries that load theirs through fd 2 (glfw) fail."""
    for fd, name in ((1, "stdout"), (2, "stderr")):
        try:
            os.fstat(fd)
        except OSError:
            null = os.open(os.devnull, os.O_WRONLY)
            if null != fd:
                os.dup2(null, fd)
                os.close(null)
            os.set_inheritable(fd, True)  # as a standard stream is: child processes write there too
            setattr(sys, name, open(fd, "w", closefd=False))
        if getattr(sys, name) is None:
            setattr(sys, name, open(os.devnull, "w"))


_reopen_closed_streams()  # before any import opens a file, which would take a closed descriptor's number

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


class _TrainHelp(argparse.Action):
    """``rmrl train -h``: the help, then the dataset and method options found where the recipes live
    (read only when asked, so that no other command pays for importing the recipe machinery)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        import textwrap

        from rm_torchrl.train.recipe import RECIPES

        lines = [f"Options come from the recipes folder {RECIPES} (a recipe file given first replaces "
                 "train.yaml):"]
        for group in ("dataset", "method"):
            names = sorted(p.stem for p in (RECIPES / group).glob("*.yaml"))
            listed = ", ".join(names) or "none found: the install lacks its recipes (reinstall rm_torchrl)"
            lines += textwrap.wrap(f"{group}=NAME ({RECIPES / group}): {listed}", width=100,
                                   subsequent_indent="  ", break_on_hyphens=False)
        parser.epilog = "\n".join(lines)
        parser.print_help()
        parser.exit()


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("rm_torchrl")
    except PackageNotFoundError:  # run from a checkout that was never installed
        from rm_torchrl import __version__

        return __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rmrl", description=__doc__)
    parser.add_argument("--version", action="version", version=f"rmrl {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("refine", help="refine a dataset with an event-ordered reward machine")
    p.add_argument("--config", metavar="YAML", help="a refine recipe (recipes/refine/*.yaml); flags override it")
    _add_source(p, required=False)
    p.add_argument("--alpha", help="fraction of shortest sub-trajectories kept per group, in (0, 1] (default 1)")
    p.add_argument("--constraint", action="append", type=_constraint, metavar="A<B",
                   help="event A must come before event B in the chosen order (repeatable)")
    p.add_argument("--reuse", action=argparse.BooleanOptionalAction, default=None,
                   help="beyond the paper: bring back the sub-trajectories the splice abandons, in the group of "
                        "their new event on the best order (default: off, the paper's refinement)")
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
                                   "composes\ndataset=NAME (recipes/dataset/) with method=NAME (recipes/method/); "
                                   "the options are listed below.",
                       formatter_class=argparse.RawDescriptionHelpFormatter, add_help=False)
    p.add_argument("-h", "--help", action=_TrainHelp, help="show this help, with the dataset and method options, and exit")
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

    from rm_torchrl.cli import demo as _demo

    p = sub.add_parser("demo", help="the main job on the real door-human-v0 shipped in the package: ours and IQL "
                                     "from the recipes, a few seeds, MuJoCo evaluation, the report (no download)",
                       description="rmrl demo [--out DIR] [--steps N] [key=value ...]: dataset=door-human-v0 with "
                                   "method=ours and method=iql, as rmrl train composes them, at a short budget; "
                                   "runs go to DIR/runs/demo-<method>-seed<k> (never deleted: run again, finished "
                                   "runs are skipped), the report to DIR/report (results.md, demo.md).")
    p.add_argument("overrides", nargs="*", metavar="key=value",
                   help="overrides for every run's recipe after the demo's own, e.g. trainer.compile=false")
    p.add_argument("--dataset", metavar="FILE.hdf5",
                   help="another door D4RL .hdf5 file (default: the packaged door-human-v0, D4RL, CC BY 4.0)")
    p.add_argument("--steps", type=int, default=_demo.STEPS, help=f"gradient steps per run (default {_demo.STEPS})")
    p.add_argument("--seeds", type=int, default=_demo.SEEDS,
                   help=f"seeds per method (default {_demo.SEEDS}: the report shows a spread)")
    p.add_argument("--seed", type=int, default=0, help="the first seed (default 0)")
    p.add_argument("--episodes", type=int, default=_demo.EPISODES,
                   help=f"episodes per evaluation (default {_demo.EPISODES}; {_demo.EVALUATIONS} evaluations a run)")
    p.add_argument("--out", default="runs/demo", metavar="DIR", help="output folder (default runs/demo)")
    p.set_defaults(run="rm_torchrl.cli.demo:run")
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that every command's clean-up runs (temporary outputs are removed)."""

    signum = signal.SIGTERM
    message = "terminated (SIGTERM); nothing was written"


def _terminate(signum, frame):
    raise Terminated


def _check_mujoco_gl() -> None:
    """MuJoCo picks its OpenGL backend from ``MUJOCO_GL`` when imported, and a bad one fails deep in PyOpenGL."""
    backend = os.environ.get("MUJOCO_GL")
    if not backend:
        return
    try:
        import mujoco  # noqa: F401
    except Exception as err:  # RuntimeError for an unknown name, AttributeError for a missing library
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise RMError(f"MuJoCo cannot start with MUJOCO_GL={backend} ({type(err).__name__}: {first}); "
                      "unset it, or set MUJOCO_GL=egl on a machine without a display") from None


def _check_minari_path() -> None:
    """``MINARI_DATASETS_PATH`` names the folder Minari keeps datasets in: a file there fails deep in its readers."""
    path = os.environ.get("MINARI_DATASETS_PATH")
    if path and os.path.exists(path) and not os.path.isdir(path):
        raise RMError(f"MINARI_DATASETS_PATH={path} is a file; point it at a folder (Minari keeps its datasets there)")


def main(argv: list[str] | None = None) -> int:
    try:
        _check_mujoco_gl()
        _check_minari_path()
    except RMError as err:
        print(f"rmrl: error: {err}", file=sys.stderr)
        return 2
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
        _quiet_stdout()
        return 0
    except OSError as err:  # a write the command did not foresee: a full disk or stdout, a name too long
        where = f": {err.filename}" if err.filename else " (writing the output)"
        _quiet_stdout()  # what stdout still buffers would fail again at exit
        print(f"rmrl {args.command}: error: {err.strerror or err}{where}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:
        return interrupted(err, f"rmrl {args.command}")


def _quiet_stdout() -> None:
    """Points stdout at /dev/null, so that flushing it at exit cannot fail again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())


def interrupted(err: KeyboardInterrupt, prog: str) -> int:
    """Says what an interrupted command saved and returns its exit status (130 for SIGINT, 143 for SIGTERM)."""
    signum = getattr(err, "signum", None)  # RunInterrupted (a run, a sweep, run_many): says what was saved
    message = getattr(err, "message", None) or "interrupted; nothing was written"
    print(f"{prog}: {message}", file=sys.stderr)
    return 128 + (signum or 2)


if __name__ == "__main__":
    sys.exit(main())
