"""``rmrl refine``: load, run the refinement stages one by one with a progress bar, write atomically.

    rmrl refine dataset=door-human-v0                        # the data section of the recipes' dataset option
    rmrl refine dataset=kitchen-partial data.refine=reuse data.alpha=0.3 --out runs/refine/kp
    rmrl refine --dataset my.hdf5 --events door --alpha 0.5 --out runs/refine/mine   # a file of your own

A dataset option is composed exactly as ``rmrl train dataset=NAME`` composes it (Hydra, recipes/dataset/), so
training and refining read one description of each dataset; the flags override what it says.
"""
from __future__ import annotations

import argparse
import sys

from rm_torchrl.cli.options import add_source, constraint
from rm_torchrl.errors import RMError
from rm_torchrl.progress import progress_bar

HELP = "refine a dataset with an event-ordered reward machine"
#: what refine reads of a composed recipe: the dataset option and the data section
OVERRIDES = ("dataset=", "data.", "+data.", "++data.")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("overrides", nargs="*", metavar="key=value",
                   help="dataset=NAME (recipes/dataset/, as rmrl train composes it) and data.* overrides "
                        "(data.alpha=0.3, data.refine=reuse, data.constraints=[a<b])")
    add_source(p, required=False)
    p.add_argument("--alpha", help="fraction of shortest sub-trajectories kept per group, in (0, 1] (default 1)")
    p.add_argument("--constraint", action="append", type=constraint, metavar="A<B",
                   help="event A must come before event B in the chosen order (repeatable)")
    p.add_argument("--reuse", action=argparse.BooleanOptionalAction, default=None,
                   help="beyond the paper: bring back the sub-trajectories the splice abandons, in the group of "
                        "their new event on the best order (default: off, the paper's refinement)")
    p.add_argument("--out", metavar="DIR", help="output directory (data/ and report.json; default with a dataset "
                                                "option: runs/refine/<data.name>)")
    p.add_argument("--minari-name", metavar="NAME",
                   help="also write the refined data as the local Minari dataset NAME (namespace/name-vN): one "
                        "episode per sub-trajectory, observations with the RM state")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out if it is an earlier refine output holding only what refine wrote")
    p.add_argument("--overwrite-minari", action="store_true",
                   help="replace the Minari dataset --minari-name if an earlier rmrl refine --minari-name wrote it")


def composed_options(overrides: list[str]) -> dict:
    """The refine options of a dataset option and data.* overrides, composed as ``rmrl train`` composes them."""
    stray = [o for o in overrides if not o.startswith(OVERRIDES)]
    if stray:
        raise RMError(f"rmrl refine takes dataset=NAME and data.* overrides, got {stray}")
    from rm_torchrl.train.recipe import load_recipe

    data = load_recipe(None, ["method=ours", *overrides]).data  # ours: the paper's refinement unless data.refine says
    if not data.refined:
        raise RMError("data.refine=none asks for the raw data: give data.refine=paper or reuse")
    return {"dataset": data.source, "events": data.events, "alpha": data.alpha, "episode_ends": data.episode_ends,
            "constraints": [tuple(x.strip() for x in c.split("<")) for c in data.constraints],
            "reuse": data.refine == "reuse", "out": f"runs/refine/{data.name}"}


def resolve_options(args) -> dict:
    """The composed dataset option's values (if any), overridden by the flags given on the command line."""
    options = {"dataset": None, "events": None, "alpha": 1.0, "episode_ends": "auto", "constraints": [], "out": None,
               "reuse": False}
    if args.overrides:
        options.update(composed_options(args.overrides))
    flags = {"dataset": args.dataset, "events": args.events, "alpha": args.alpha,
             "episode_ends": args.episode_ends, "constraints": args.constraint, "out": args.out, "reuse": args.reuse}
    options.update({k: v for k, v in flags.items() if v is not None})
    missing = [k for k, v in options.items() if v is None]
    if missing:
        raise RMError(f"missing {', '.join('--' + m.replace('_', '-') for m in missing)} (give the flag, or "
                      "dataset=NAME for a dataset option of the recipes)")
    return options


def refine_with_progress(data, spec, alpha, constraints, desc: str = "refine", reuse: bool = False):
    """Runs the pipeline stage by stage under a progress bar; returns ``(refined, report)``."""
    from rm_torchrl.refine.pipeline import RefineReport, make_refine_pipeline, run_pipeline
    from rm_torchrl.refine.shortest import check_alpha

    pipeline = make_refine_pipeline(spec, float(check_alpha(alpha)), constraints, reuse=reuse)
    with progress_bar(total=len(pipeline.transforms), desc=desc, unit="stage", file=sys.stderr, leave=False) as bar:

        def on_stage(stage):
            bar.set_postfix_str(type(stage).__name__)
            bar.update()

        refined, stats = run_pipeline(pipeline, data, on_stage)
    return refined, RefineReport.from_stats(stats)


def run(args) -> int:
    from rm_torchrl.data.refined_to_minari import check_minari_target, export_refined_minari
    from rm_torchrl.data.sources import load_dataset
    from rm_torchrl.data.store import check_out, output_in_place, write_refined
    from rm_torchrl.events.spec import load_event_spec
    from rm_torchrl.refine.shortest import check_alpha
    from rm_torchrl.row_runs import run_starts

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
