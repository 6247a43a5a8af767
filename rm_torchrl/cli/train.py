"""``rmrl train``: one run, or a Hydra multirun over datasets x methods x seeds x anything else.

    rmrl train dataset=door-human-v0 method=ours seed=1            # recipes/train.yaml's groups
    rmrl train recipes/door-human-v0-ours.yaml trainer.steps=50000  # a recipe file (or a run's recipe.yaml)
    rmrl train -m dataset=door-human-v0 method=ours,iql seed=0,1,2  # parallel on local cores (--jobs)
    rmrl train -m ... hydra/launcher=submitit_slurm hydra.launcher.partition=gpu

The multirun's policy (skip finished runs, resume killed ones, stop cleanly on a signal) is
:func:`rm_torchrl.launch.multirun`'s.
"""
from __future__ import annotations

import argparse

ADD_HELP = False  # -h is TrainHelp, which lists the recipe options
HELP = "train offline: dataset=NAME method=NAME, or a recipe file (Hydra overrides)"


class TrainHelp(argparse.Action):
    """``rmrl train -h``: the help, then the dataset and method options found where the recipes live
    (read only when asked, so that no other command pays for importing the recipe machinery)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        import textwrap

        from rm_torchrl.train.recipes_root import RECIPES

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


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("rmrl train [RECIPE.yaml] [key=value ...]: without RECIPE, recipes/train.yaml composes\n"
                     "dataset=NAME (recipes/dataset/) with method=NAME (recipes/method/); the options are listed below.")
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("-h", "--help", action=TrainHelp, help="show this help, with the dataset and method options, and exit")
    p.add_argument("args", nargs="*", metavar="[RECIPE] key=value",
                   help="a recipe YAML (optional), then Hydra overrides, e.g. method=iql trainer.steps=2000 seed=3")
    p.add_argument("-m", "--multirun", action="store_true",
                   help="a Hydra multirun over comma-separated values (seed=0,1,2); finished runs are skipped")
    p.add_argument("--jobs", type=int, default=2, help="parallel runs of the default (joblib) launcher (default 2)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args) -> int:
    from rm_torchrl.train.recipe import load_recipe, split_recipe_args

    path, overrides = split_recipe_args(args.args)
    if args.multirun:
        from rm_torchrl.launch import multirun

        return multirun(path, overrides, jobs=args.jobs)
    from rm_torchrl.train.trainer import train

    recipe = load_recipe(path, overrides)
    run_dir = train(recipe, progress=not args.no_progress)
    print(f"finished {recipe.trainer.steps} steps: {run_dir}")
    return 0
