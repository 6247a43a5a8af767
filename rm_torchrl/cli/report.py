"""``rmrl report RUN_DIR... [--out DIR]``: Table 1, Table 2 and Figure 5 of the paper from training runs.

What it writes is :func:`rm_torchrl.report.write.write_report`'s; prints Table 1 on stdout.
"""
from __future__ import annotations

import argparse

from rm_torchrl.errors import RMError

HELP = "Table 1/Table 2 in Markdown and learning curves from training runs"


def add_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("paths", nargs="+", metavar="RUN_DIR",
                   help="run directories (eval.csv + recipe.yaml) or directories holding them, searched recursively")
    p.add_argument("--out", default="reports", metavar="DIR",
                   help="where results.md and the figures go (default: reports/)")
    p.add_argument("--dataset-from", choices=("name", "source"), default="name",
                   help="dataset label: the recipe's data.name (default), or the stem of data.source")
    p.add_argument("--decimals", type=int, default=1, help="decimals in Table 1 (default 1)")
    p.add_argument("--reps", type=int, default=None, metavar="N",
                   help="bootstrap resamples of the CIs (default 2000; seeded, so a report repeats its CIs)")
    p.add_argument("--gifs", action="store_true",
                   help="render one episode of each run's final policy as a GIF and embed it (MUJOCO_GL=egl "
                        "without a display)")
    p.add_argument("--gif-steps", type=int, default=100, help="steps per GIF (default 100)")
    return p


def run(args) -> int:
    from functools import partial

    from rm_torchrl.report.write import write_report

    gifs = None
    if args.gifs:
        if args.gif_steps < 1:
            raise RMError(f"--gif-steps must be positive, got {args.gif_steps}")
        from rm_torchrl.train.policy import policy_gifs

        gifs = partial(policy_gifs, steps=args.gif_steps)
    write_report(args.paths, args.out, args.dataset_from, args.decimals, args.reps, extra=gifs)
    return 0

