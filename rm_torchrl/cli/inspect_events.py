"""``rmrl inspect``: how many episodes reach each event, and when."""
from __future__ import annotations

import json
import sys

from rm_torchrl.data.sources import load_dataset
from rm_torchrl.events.spec import load_event_spec
from rm_torchrl.events.stats import event_statistics, format_event_table


def run(args) -> int:
    spec = load_event_spec(args.events)
    print(f"loading {args.dataset} ...", file=sys.stderr)
    stats = event_statistics(load_dataset(args.dataset, episode_ends=args.episode_ends), spec)
    print(json.dumps(stats, indent=2) if args.json else format_event_table(stats))
    return 0
