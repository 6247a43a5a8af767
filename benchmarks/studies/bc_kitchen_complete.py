"""CORL's BC on D4RL's own kitchen data (kitchen-complete-v0), beside the BC the papers report.

    python benchmarks/studies/bc_kitchen_complete.py run --jobs 2 --set trainer.threads=1 --out DIR  # resumable
    python benchmarks/studies/bc_kitchen_complete.py report --out DIR   # benchmarks/results/bc-kitchen-complete/

Table 1's kitchen rows are generated stand-ins, so BC's kitchen level is checked here on the one D4RL kitchen file
this machine has (``../shared/data/d4rl/kitchen-complete-v0.hdf5``: 19 demonstrations, each completing the four
tasks), evaluated in gymnasium-robotics' ``FrankaKitchen-v1`` with the D4RL v0 observation rebuilt
(``recipes/dataset/kitchen-complete-v0.yaml``). Protocol as Table 1: ``rmrl train dataset=kitchen-complete-v0
method=bc`` for 50k gradient steps, evaluation every 2,000 steps over 10 episodes, 5 seeds (the first no choice
used). ``report`` copies each run's ``eval.csv``, ``recipe.yaml`` and ``machine_seconds`` to ``runs/`` and writes
``summary.json`` and ``results.md``; ``diagnostics/*.json`` (``benchmarks/diagnostics/kitchen_start_pose.py``
on a run) are summarised beside them.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from common import CHOICES, RESULTS, add_reps_option, add_run_options, collect, gather, mean_std, pending, run_study, study_commands

from rm_torchrl.files import write_atomic
from rm_torchrl.launch import run_grid
from rm_torchrl.report.choices import first_free_seeds, leave_out_chosen, read_choices
from rm_torchrl.report.plots import plot_learning_curves
from rm_torchrl.report.runs import Group
from rm_torchrl.report.stats import cell_iqm

STUDY = RESULTS / "bc-kitchen-complete"
DATASET = "kitchen-complete-v0"
STEPS = 50_000
SEEDS = 5
TASK = 25.0  # score points per completed task (the kitchen score is 100 x tasks / 4)
#: BC on kitchen-complete-v0 as published: (normalised score, where)
PUBLISHED = [(33.8, "D4RL (Fu et al. 2020), BC"), (65.0, "IQL (Kostrikov et al. 2022), Table 1, BC")]


def grid(out: str) -> list[tuple[None, list[str]]]:
    seeds = first_free_seeds(DATASET, read_choices(CHOICES), SEEDS)
    return [(None, [f"dataset={DATASET}", "method=bc", f"name={DATASET}-bc", f"seed={k}", f"out={out}",
                    f"trainer.steps={STEPS}"]) for k in seeds]


def run(args) -> None:
    run_grid(pending(grid(args.out), Path(args.results), args.override), args.jobs)


KINDS = (("env_reset", "env reset"), ("data_start", "recorded first states"),
         ("data_mean_robot", "reset, robot at the data's mean first pose"))


def diagnostics_lines(study: Path) -> list[str]:
    found = sorted((study / "diagnostics").glob("*.json"))
    if not found:
        return []
    runs = [json.loads(path.read_text()) for path in found]
    lines = ["## Where the policy starts", "",
             "`benchmarks/diagnostics/kitchen_start_pose.py` on each run's final checkpoint: tasks completed per "
             "episode, mean over the episodes (how many), from FrankaKitchen-v1's reset (the robot at D4RL v0's "
             "`init_qpos`: what the evaluation above does), from each recorded episode's first state, and from the "
             "reset with the robot's joints moved to the mean of the recorded first poses.", "",
             "| run | " + " | ".join(name for _, name in KINDS) + " |", "|---|" + "---:|" * len(KINDS)]
    for path, d in zip(found, runs):
        cells = [f"{d['policy'][k]['mean_tasks']:.2f} ({len(d['policy'][k]['tasks_per_episode'])})" for k, _ in KINDS]
        lines.append(f"| [{Path(d['run']).name}](diagnostics/{path.name}) | " + " | ".join(cells) + " |")
    means = [np.mean([d["policy"][k]["mean_tasks"] for d in runs]) for k, _ in KINDS]
    lines.append(f"| mean over {len(runs)} runs | " + " | ".join(f"{m:.2f}" for m in means) + " |")
    replay = runs[0]["replay"]
    lines += ["", f"The dataset's actions replayed open loop from each recorded first state (no policy): "
              f"{np.mean([len(r['tasks']) for r in replay]):.2f} tasks on average over {len(replay)} episodes "
              f"(per episode: {', '.join(str(len(r['tasks'])) for r in replay)}), the robot joints "
              f"{np.mean([r['robot_gap_mean'] for r in replay]):.3f} rad from the recorded ones on average (first "
              f"episode {replay[0]['robot_gap_mean']:.3f}). The reset pose minus the data's mean first pose, per robot "
              f"joint (rad): {[round(x, 3) for x in runs[0]['reset_robot_minus_data_mean_start']]}; the first poses' "
              f"standard deviation: {[round(x, 3) for x in runs[0]['data_start_robot_std']]}.", ""]
    return lines


def report(args) -> None:
    study = Path(args.results)
    skipped: list[str] = []
    runs, left_out = leave_out_chosen([r for r in gather(Path(args.out), study, skipped)
                                       if r.path.name.startswith(f"{DATASET}-bc-seed")], read_choices(CHOICES))
    done = [r for r in runs if r.final_step >= STEPS]
    if not done:
        raise SystemExit(f"no finished {DATASET} BC run under {args.out} or {study / 'runs'}")
    summary = collect(done, study)
    write_atomic(study / "summary.json", json.dumps(summary, indent=1) + "\n")
    finals = [r.final_value for r in done]
    est = cell_iqm(finals, args.reps)
    lines = ["# CORL's BC on D4RL kitchen-complete-v0", "",
             "Generated by `python benchmarks/studies/bc_kitchen_complete.py report` (its docstring has the commands). "
             f"D4RL's file, not a stand-in. {STEPS // 1000}k gradient steps, evaluation every 2,000 steps over 10 "
             "episodes in FrankaKitchen-v1 (D4RL v0 observation rebuilt); score = 100 x tasks completed / 4.", "",
             "| seed | final score | final tasks (of 4) | best score (step) | mean score over evaluations |",
             "|---:|---:|---:|---:|---:|"]
    for r in sorted(done, key=lambda r: r.seed):
        score = np.asarray(r.evals["score"], dtype=float)
        best = int(np.argmax(score))
        lines.append(f"| {r.seed} | {score[-1]:.1f} | {score[-1] / TASK:.2f} | {score[best]:.1f} "
                     f"({int(r.evals['step'][best]):,}) | {score.mean():.1f} |")
    lines += ["", f"Over {len(done)} seeds: final score {mean_std(finals)}, IQM {est.value:.1f} [{est.lo:.1f}, "
              f"{est.hi:.1f}] (95% stratified-bootstrap CI, {args.reps} resamples).", "",
              "Published BC on kitchen-complete-v0 (D4RL's v0 env, other budgets): " + "; ".join(
                  f"{score} ({score / TASK:.2f} tasks), {where}" for score, where in PUBLISHED) + ".", ""]
    lines += diagnostics_lines(study)
    plot_learning_curves([Group(DATASET, "BC", done)], study / "curves.png")
    lines += ["![learning curves](curves.png)", ""]
    for note in (*skipped, *left_out):
        lines.append(f"- left out: {note}")
    if (study / "findings.md").is_file():
        lines += ["", "What it says: [findings.md](findings.md).", ""]
    write_atomic(study / "results.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> int:
    p, sub = study_commands(__doc__)
    r = sub.add_parser("run", help="train the seeds not yet in runs/ (resumable)")
    add_run_options(r)
    rep = sub.add_parser("report", help="summary.json, results.md and curves.png")
    rep.add_argument("--out", default="runs", help="where this session's run directories are")
    for command in (r, rep):
        command.add_argument("--results", default=str(STUDY), help="the study's committed results (default %(default)s)")
    add_reps_option(rep)
    args = p.parse_args()
    {"run": run, "report": report}[args.command](args)
    return 0


if __name__ == "__main__":
    run_study(main, Path(__file__).name)
