"""``rmrl refine``: load, run the refinement stages one by one with a progress bar, write atomically."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from rm_torchrl.cli.options import add_source, constraint
from rm_torchrl.progress import progress_bar

from rm_torchrl.data.sources import load_dataset
from rm_torchrl.data.refined_to_minari import check_minari_target, export_refined_minari
from rm_torchrl.data.store import check_out, output_in_place, write_refined
from rm_torchrl.errors import RMError, read_yaml
from rm_torchrl.events.spec import load_event_spec
from rm_torchrl.refine.pipeline import RefineReport, make_refine_pipeline, run_pipeline
from rm_torchrl.refine.shortest import check_alpha
from rm_torchrl.segments import run_starts

#: Recipe keys and their defaults (None: required).
RECIPE_KEYS = {"dataset": None, "events": None, "alpha": 1.0, "episode_ends": "auto", "constraints": [], "out": None,
               "reuse": False}


HELP = "refine a dataset with an event-ordered reward machine"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="YAML", help="a refine recipe (recipes/refine/*.yaml); flags override it")
    add_source(p, required=False)
    p.add_argument("--alpha", help="fraction of shortest sub-trajectories kept per group, in (0, 1] (default 1)")
    p.add_argument("--constraint", action="append", type=constraint, metavar="A<B",
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


def refine_with_progress(data, spec, alpha, constraints, desc: str = "refine", reuse: bool = False):
    """Runs the pipeline stage by stage under a progress bar; returns ``(refined, report)``."""
    pipeline = make_refine_pipeline(spec, float(check_alpha(alpha)), constraints, reuse=reuse)
    with progress_bar(total=len(pipeline.transforms), desc=desc, unit="stage", file=sys.stderr, leave=False) as bar:

        def on_stage(stage):
            bar.set_postfix_str(type(stage).__name__)
            bar.update()

        refined, stats = run_pipeline(pipeline, data, on_stage)
    return refined, RefineReport.from_stats(stats)


def recipe_file(path: str) -> Path:
    """``path`` as given, else (relative and absent) under the package's recipes folder's parent, so that
    ``--config recipes/refine/door-human.yaml`` works from any directory and from an installed wheel."""
    given = Path(path)
    if given.exists() or given.is_absolute():
        return given
    from rm_torchrl.train.recipe import RECIPES

    shipped = RECIPES.parent / given
    return shipped if shipped.is_file() else given


def load_recipe(path: str) -> dict:
    """A refine recipe; relative dataset and event-spec files are found from the recipe's folder."""
    path = recipe_file(path)
    data = read_yaml(path, "recipe")
    if not isinstance(data, dict):
        raise RMError(f"recipe {path} must be a mapping of {sorted(RECIPE_KEYS)}")
    unknown = set(data) - set(RECIPE_KEYS)
    if unknown:
        raise RMError(f"recipe {path}: unknown key(s) {sorted(unknown)}; allowed: {sorted(RECIPE_KEYS)}")
    constraints = data.get("constraints") or []
    if not isinstance(constraints, list) or not all(isinstance(c, str) and c.count("<") == 1 for c in constraints):
        raise RMError(f"recipe {path}: constraints must be a list of 'a<b' strings")
    data["constraints"] = [tuple(x.strip() for x in c.split("<")) for c in constraints]
    base = Path(path).parent
    for key in ("dataset", "events", "out"):
        if key in data and not isinstance(data[key], str):
            raise RMError(f"recipe {path}: {key} must be a string, got {data[key]!r}")
    if "reuse" in data and not isinstance(data["reuse"], bool):
        raise RMError(f"recipe {path}: reuse must be true or false, got {data['reuse']!r}")
    for key in ("dataset", "events"):
        value = data.get(key)
        if (isinstance(value, str) and Path(value).suffix in (".hdf5", ".h5", ".yaml", ".yml")
                and not value.startswith(("embedded:", "minari:"))):
            data[key] = os.path.normpath(base / value)
    return data


def resolve_options(args) -> dict:
    """Recipe values, overridden by the flags given on the command line."""
    options = dict(RECIPE_KEYS)
    if args.config:
        options.update(load_recipe(args.config))
    flags = {"dataset": args.dataset, "events": args.events, "alpha": args.alpha,
             "episode_ends": args.episode_ends, "constraints": args.constraint, "out": args.out, "reuse": args.reuse}
    options.update({k: v for k, v in flags.items() if v is not None})
    missing = [k for k, v in options.items() if v is None]
    if missing:
        raise RMError(f"missing {', '.join('--' + m.replace('_', '-') for m in missing)} (give the flag or a --config recipe)")
    return options


def run(args) -> int:
    opts = resolve_options(args)
    check_alpha(opts["alpha"])
    check_out(opts["out"], args.overwrite)  # before the work, not after it
    if args.minari_name:
        check_minari_target(args.minari_name, args.overwrite_minari)
    spec = load_event_spec(opts["events"])
    print(f"loading {opts['dataset']} ...", file=sys.stderr)
    data = load_dataset(opts["dataset"], episode_ends=opts["episode_ends"])
    refined, report = refine_with_progress(data, spec, opts["alpha"], opts["constraints"], reuse=opts["reuse"])
    meta = {"dataset": opts["dataset"], "episode_ends": opts["episode_ends"], **report.to_dict()}
    out = None
    try:
        out = write_refined(opts["out"], refined, meta, overwrite=args.overwrite)
        print(report.table())
        print(f"wrote {refined.batch_size[0]:,} transitions to {out}/data and the report to {out}/report.json")
    except KeyboardInterrupt as err:  # once the output is in place the work is done: say so, and exit 0
        written = getattr(err, "written", None) or out
        if written is None:
            raise
        print(output_in_place(written), file=sys.stderr)
        return 0
    if args.minari_name:
        dataset_id = export_refined_minari(refined, report.to_dict(), args.minari_name, str(opts["events"]), spec.names,
                                           source=str(opts["dataset"]), overwrite=args.overwrite_minari)
        episodes = int(run_starts(refined.get("episode")).sum())
        print(f"wrote the local Minari dataset {dataset_id}: {episodes:,} episodes (one per sub-trajectory), "
              f"{refined.batch_size[0]:,} steps")
    return 0
