"""``rmrl inspect``: how many episodes reach each event, and when."""
from __future__ import annotations

import argparse
import json
import sys

from rm_torchrl.cli.options import add_source
from rm_torchrl.errors import RMError


HELP = "per-event statistics of a dataset"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_source(p)
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--plot", metavar="FILE.png", help="also draw event timelines: per episode when each event holds "
                                                      "and fires over the RM state, per group the lengths and alpha's cut")
    p.add_argument("--plot-episodes", type=int, default=6, help="episodes drawn (a seeded sample; default 6)")
    p.add_argument("--alpha", default="1.0", help="the alpha whose cut the length histograms mark (default 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the episode sample")


def run(args) -> int:
    from rm_torchrl.data.sources import load_dataset
    from rm_torchrl.refine.shortest import check_alpha
    from rm_torchrl.events.spec import load_event_spec
    from rm_torchrl.events.stats import event_statistics, format_event_table

    spec = load_event_spec(args.events)
    if args.plot and not args.plot.endswith(".png"):
        raise RMError(f"--plot writes a PNG file, got {args.plot!r}")
    if args.plot_episodes < 1:
        raise RMError(f"--plot-episodes must be positive, got {args.plot_episodes}")
    check_alpha(args.alpha)
    print(f"loading {args.dataset} ...", file=sys.stderr)
    data = load_dataset(args.dataset, episode_ends=args.episode_ends)
    stats = event_statistics(data, spec)
    print(json.dumps(stats, indent=2) if args.json else format_event_table(stats))
    if args.plot:
        from rm_torchrl.refine.timeline import event_timelines
        from rm_torchrl.report.plots import plot_event_timelines

        timelines = event_timelines(data, spec, args.alpha, episodes=args.plot_episodes, seed=args.seed)
        path = plot_event_timelines(timelines, args.plot)
        print(f"wrote {path}: {len(timelines.episodes)} episodes, groups of the order "
              f"{' > '.join(timelines.order)} with the alpha={args.alpha} cut", file=sys.stderr)
    return 0
