"""``rmrl inspect``: how many episodes reach each event, and when."""
from __future__ import annotations

import json
import sys

from rm_torchrl.data.sources import load_dataset
from rm_torchrl.errors import RMError
from rm_torchrl.refine.shortest import check_alpha
from rm_torchrl.events.spec import load_event_spec
from rm_torchrl.events.stats import event_statistics, format_event_table


def run(args) -> int:
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
