"""``rmrl refine``: load, run the refinement stages one by one with a progress bar, write atomically."""
from __future__ import annotations

import sys

from tqdm import tqdm

from rm_torchrl.data.sources import load_dataset
from rm_torchrl.data.store import write_refined
from rm_torchrl.events.spec import load_event_spec
from rm_torchrl.refine.pipeline import RefineReport, make_refine_pipeline
from rm_torchrl.refine.shortest import check_alpha


def refine_with_progress(data, spec, alpha, constraints, desc: str = "refine"):
    """Runs the pipeline stage by stage under a progress bar; returns ``(refined, report)``."""
    pipeline = make_refine_pipeline(spec, float(check_alpha(alpha)), constraints)
    with tqdm(pipeline.transforms, desc=desc, unit="stage", file=sys.stderr, leave=False) as bar:
        for stage in bar:
            bar.set_postfix_str(type(stage).__name__)
            data = stage(data)
    return data, RefineReport.from_pipeline(pipeline)


def run(args) -> int:
    check_alpha(args.alpha)
    spec = load_event_spec(args.events)
    print(f"loading {args.dataset} ...", file=sys.stderr)
    data = load_dataset(args.dataset, episode_ends=args.episode_ends)
    refined, report = refine_with_progress(data, spec, args.alpha, args.constraint)
    out = write_refined(args.out, refined, {"dataset": args.dataset, **report.to_dict()}, overwrite=args.overwrite)
    print(report.table())
    print(f"wrote {refined.numel():,} transitions to {out}/data and the report to {out}/report.json")
    return 0
