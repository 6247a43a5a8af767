"""What the study drivers share: the paper's tables, the ``rmrl`` call, and the bookkeeping of committed runs.

The drivers import it as a sibling (``from common import ...``): ``python benchmarks/studies/NAME.py`` puts this
folder first on ``sys.path``. Committed results follow one layout, ``benchmarks/results/<study>/runs/<run>/``
(``eval.csv``, the resolved ``recipe.yaml``, ``refine_report.json``, ``machine_seconds``), beside the study's
``summary.json`` and ``results.md``.
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from rm_torchrl.launch.processes import rmrl_command
from rm_torchrl.report.runs import load_runs, read_eval_csv
from rm_torchrl.report.stats import REPS
from rm_torchrl.run_format import run_identity
from rm_torchrl.train.rundir import load_checkpoint

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results"
#: the tuning record: runs whose (dataset, seed) a choice used are not reported (``benchmarks/PROTOCOL.md``)
CHOICES = RESULTS / "choices.json"
GENERATED_MARK = " (generated)"
#: run label -> the paper's Table 1 column
LABELS = {"ours": "Ours", "ours-reuse": "ours-reuse", "iql": "IQL", "bc": "BC", "cql": "CQL", "bcq": "BCQ"}
#: the paper's Table 1 (average D4RL return over 3 seeds after 0.5M steps); its Table 2 is PAPER_T2
PAPER = {
    "kitchen-partial": {"BC": 1.31, "BCQ": 0.46, "IQL": 1.60, "CQL": 0.92, "Ours": 3.24},
    "kitchen-mixed": {"BC": 1.61, "BCQ": 0.62, "IQL": 1.68, "CQL": 0.53, "Ours": 3.03},
    "door-human-v0": {"BC": -20.4, "BCQ": -54.8, "IQL": 74.8, "CQL": 75.8, "Ours": 439.5},
    "door-cloned": {"BC": -56.1, "BCQ": -57.5, "IQL": 20.1, "CQL": -56.5, "Ours": 415.9},
    "relocate-human": {"BC": 184.2, "BCQ": -25.1, "IQL": 288.6, "CQL": 78.1, "Ours": 633.3},
    "relocate-cloned": {"BC": -51.6, "BCQ": -56.0, "IQL": -52.4, "CQL": -30.1, "Ours": 492.4},
}
#: the paper's Table 2: transitions after each stage (original, split, ordered, shorter)
PAPER_T2 = {
    "kitchen-partial": (136345, 98690, 50114, 22682), "kitchen-mixed": (136345, 83792, 49855, 44298),
    "door-human-v0": (6704, 5001, 5001, 2261), "door-cloned": (995643, 372086, 372086, 167397),
    "relocate-human": (9917, 7211, 7211, 7211), "relocate-cloned": (996242, 364207, 364207, 364207),
}
#: the ``rmrl generate`` datasets: name, event spec, alpha (the paper's), and the size flags at full scale
GENERATED = [
    ("kitchen-partial", "kitchen", 0.5, {"episodes": 330}),
    ("kitchen-mixed", "kitchen", 0.9, {"episodes": 330}),
    ("relocate-human", "relocate", 1.0, {"episodes": 25}),
    ("door-cloned", "door", 0.5, {"steps": 1_000_000}),
    ("relocate-cloned", "relocate", 1.0, {"steps": 1_000_000}),
]


def row(dataset: str) -> str:
    """The Table 1 row of a shown dataset label (generated stand-ins are marked)."""
    return dataset.removesuffix(GENERATED_MARK)


def mean_std(values) -> str:
    """``mean ± sample std``, or the value alone for one seed."""
    values = np.asarray(values, dtype=float)
    return f"{values.mean():.1f} ± {values.std(ddof=1):.1f}" if len(values) > 1 else f"{values.mean():.1f}"


def rmrl(*argv: str, capture: bool = False) -> str:
    """Run ``rmrl ARGV`` in a child process (progress bars pass through to stderr)."""
    cmd = rmrl_command(*argv)
    print("$ rmrl " + " ".join(argv), file=sys.stderr, flush=True)
    out = subprocess.run(cmd, check=True, text=True, stdout=subprocess.PIPE if capture else None)
    return out.stdout if capture else ""


def committed(results: Path, name: str, steps: int) -> bool:
    """Whether ``results/runs/NAME`` holds a finished run: a later session skips it (run directories are not kept)."""
    csv = results / "runs" / name / "eval.csv"
    if not csv.is_file():
        return False
    steps_done = read_eval_csv(csv)["step"]
    return len(steps_done) > 0 and int(steps_done[-1]) >= steps


def pending(cells, results: Path, extra=()) -> list[tuple[None, list[str]]]:
    """The cells (``grid``'s form, with ``name``, ``seed`` and ``trainer.steps``) not finished in the committed results."""
    todo = []
    for path, overrides in cells:
        values = dict(o.split("=", 1) for o in overrides)
        if not committed(results, f"{values['name']}-seed{values['seed']}", int(values["trainer.steps"])):
            todo.append((path, [*overrides, *extra]))
    print(f"{len(todo)} runs to do or continue ({len(cells) - len(todo)} finished in the committed results)",
          file=sys.stderr)
    return todo


def gather(out: Path, results: Path, skipped: list[str]):
    """This session's runs under ``out`` and the committed copies (``results/runs``) of runs from earlier sessions."""
    fresh = {p.name for p in out.iterdir()} if out.is_dir() else set()
    earlier = [p for p in sorted((results / "runs").glob("*")) if p.is_dir() and p.name not in fresh]
    return load_runs([p for p in [out, *earlier] if p.exists()], skipped=skipped)


def collect(runs, results: Path) -> list[dict]:
    """Copy each run's small files to ``results/runs/<run>/`` and return one summary object per run.

    Copied: ``eval.csv``, the resolved ``recipe.yaml``, ``refine_report.json`` and the run's machine
    seconds (from its checkpoint); a run that is already the committed copy keeps its files.
    """
    (results / "runs").mkdir(parents=True, exist_ok=True)
    summary = []
    for run in runs:
        dest = results / "runs" / run.path.name
        elapsed = None
        if dest.resolve() != run.path.resolve():
            dest.mkdir(exist_ok=True)
            for name in ("eval.csv", "recipe.yaml", "refine_report.json"):
                if (run.path / name).is_file():
                    shutil.copyfile(run.path / name, dest / name)
            ckpt = run.path / "checkpoint.pt"
            if ckpt.is_file():
                elapsed = load_checkpoint(ckpt).get("elapsed_seconds")
                (dest / "machine_seconds").write_text(f"{float(elapsed):.1f}\n")
        elif (dest / "machine_seconds").is_file():
            elapsed = float((dest / "machine_seconds").read_text())
        algorithm, hparams, refine = run_identity(run.recipe)
        summary.append({"dataset": row(run.dataset), "source": run.origin, "method": run.method,
                        "algorithm": algorithm, "hparams": hparams, "refine": refine, "run": dest.name,
                        "seed": run.seed, "steps": run.final_step,
                        "eval_episodes": run.episodes, "final_score": float(run.evals["score"][-1]),
                        "mean_score": float(run.evals["score"].mean()),
                        "final_return": float(run.evals["return_mean"][-1]), "reward": run.reward,
                        "final_success": float(run.evals["success_rate"][-1]),
                        "final_events": float(run.evals["events_mean"][-1]),
                        "machine_seconds": None if elapsed is None else round(float(elapsed), 1)})
    return summary


def study_commands(doc: str):
    """A study's parser with subcommands (run, report, ...), its help the module's docstring as written."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    return parser, parser.add_subparsers(dest="command", required=True)


def add_reps_option(parser) -> None:
    """The report's bootstrap resamples, the same default in every study."""
    parser.add_argument("--reps", type=int, default=REPS, help=f"bootstrap resamples of the CIs (default {REPS})")


def add_run_options(parser, out: str = "runs") -> None:
    """The options every study's ``run`` shares: where run directories go, how many train at once, and extra
    recipe overrides for every run."""
    parser.add_argument("--out", default=out, help="run directories (not committed)")
    parser.add_argument("--jobs", type=int, default=2, help="runs training at once (default 2)")
    parser.add_argument("--set", dest="override", action="append", default=[], metavar="KEY=VALUE",
                        help="an extra recipe override for every run, e.g. trainer.threads=1 (repeatable)")


def run_study(main, name: str) -> None:
    """``main()`` as a command: its exit status; a signal to its runs exits 130/143 saying what they saved (the
    runs checkpointed), bad input (a broken run directory, ``--reps 0``) is one line, never a traceback."""
    from rm_torchrl.errors import RMError
    from rm_torchrl.launch import exit_status

    try:
        raise SystemExit(main())
    except KeyboardInterrupt as err:
        raise SystemExit(exit_status(err, name))
    except RMError as err:
        raise SystemExit(f"{name}: error: {err}")
