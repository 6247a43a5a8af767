"""``rmrl demo``: the main job with nothing to download - build a door-like dataset and refine it."""
from __future__ import annotations

import sys

from rm_torchrl.cli.refine import refine_with_progress
from rm_torchrl.data.store import write_refined
from rm_torchrl.data.synthetic import make_door_like
from rm_torchrl.events.spec import load_event_spec
from rm_torchrl.refine.shortest import check_alpha


def run(args) -> int:
    check_alpha(args.alpha)
    print(f"building a door-like dataset of {args.transitions:,} transitions (seed {args.seed}) ...", file=sys.stderr)
    data = make_door_like(args.transitions, seed=args.seed)
    refined, report = refine_with_progress(data, load_event_spec("door"), args.alpha, ())
    out = write_refined(args.out, refined, {"dataset": "synthetic door-like", **report.to_dict()}, overwrite=True)
    print(report.table())
    print(f"wrote {refined.numel():,} refined transitions to {out}/data and the report to {out}/report.json")
    return 0
