"""Studies of ours' hyper-parameters: weight decay on door-human-v0, the AWR temperature on any dataset.

Trains ours (``recipes/door-human-v0-ours.yaml``: IQL on the refined data with the RM state, the IQL
authors' Gaussian actor, cosine actor schedule, AntMaze expectile and temperature) with
lambda_Q = lambda_pi = lambda for every lambda in ``--lambdas`` and every seed in ``--seeds``, plus
control arms with IQL's Adroit expectile and temperature (flat AWR weights on the RM reward) and
with the tanh-squashed actor; then writes the study's table, curves and summary, and per run
``runs/<run>/`` (``eval.csv``, the resolved ``recipe.yaml``, the logged ``scalars/``). Resumable: run it
again and finished runs are skipped (also those whose results an earlier session committed), killed
ones resumed from their checkpoint. The choice rule is fixed before any run: the arm with the
highest mean D4RL score over the last ``--last`` evaluations (5: steps 42k-50k of 50k), averaged over
seeds; the control arms are candidates too (the recipe takes their expectile and temperature if
one of them wins). Arms equal to the printed precision go to the later one in the table (for
``--temperatures`` in ascending order, the larger beta: it keeps more of IQL's advantage weighting).

    python benchmarks/studies/decline_study.py --out runs/decline-study --results benchmarks/results/decline-study

``--dataset OPTION`` trains ``dataset=OPTION method=ours`` instead of the door-human-v0 recipe, and
``--temperatures`` adds arms with the recipe's lambda and these inverse temperatures beta, e.g. the
kitchen study (``benchmarks/results/kitchen-temperature``)::

    python benchmarks/studies/decline_study.py --dataset rmrl-kitchen-partial --temperatures 0 0.5 1 3 10 \
        --lambdas --adroit-lambdas --tanh-normal-lambdas --steps 20000 --last 3 --set eval.every=4000 \
        --out runs/kitchen-temperature --results benchmarks/results/kitchen-temperature
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

from common import RESULTS, ROOT, add_run_options, mean_std, run_study

from rm_torchrl.launch import run_grid
from rm_torchrl.events.spec import load_event_spec
from rm_torchrl.report.runs import read_eval_csv, read_scalars
from rm_torchrl.train.recipe import load_recipe
from rm_torchrl.train.evaluate import SCORE_RANGES

RECIPE = ROOT / "recipes" / "door-human-v0-ours.yaml"


#: Control arm: IQL's Adroit values, with which the AWR weights of the RM reward are flat (behaviour cloning).
ADROIT_IQL = ["method.iql.expectile=0.7", "method.iql.temperature=0.5"]


def arms(args) -> list[tuple[str, str, list[str]]]:
    """(label, run name, overrides): every lambda with the recipe's values, then the control arms."""
    row = row_name(args)
    out = [(f"λ={lam}", f"{row}-ours-wd{lam}", _decay(lam)) for lam in args.lambdas]
    out += [(f"β={float(b)!r}", f"{row}-ours-beta{float(b)!r}", [f"method.iql.temperature={float(b)!r}"])
            for b in args.temperatures]
    out += [(f"λ={lam}, τ=0.7 β=0.5 (IQL Adroit)", f"{row}-ours-beta0.5-wd{lam}", _decay(lam) + ADROIT_IQL)
            for lam in args.adroit_lambdas]
    out += [(f"λ={lam}, τ=0.7 β=0.5, tanh_normal actor", f"{row}-ours-beta0.5-wd{lam}-tanhnormal",
             _decay(lam) + ADROIT_IQL + ["network.actor=tanh_normal"]) for lam in args.tanh_normal_lambdas]
    return out


def row_name(args) -> str:
    """The dataset's Table 1 row: the generated stand-ins' options are ``rmrl-<row>``."""
    return args.dataset.removeprefix("rmrl-") if args.dataset else "door-human-v0"


def _decay(lam: str) -> list[str]:
    return [f"optim.weight_decay_q={float(lam)!r}", f"optim.weight_decay_pi={float(lam)!r}"]


def source(args) -> tuple[str | None, list[str]]:
    """The study's base recipe: ``dataset=OPTION method=ours``, or the door-human-v0 recipe file."""
    return (None, [f"dataset={args.dataset}", "method=ours"]) if args.dataset else (str(RECIPE), [])


def grid(args) -> list[tuple[str, list[str]]]:
    runs = []
    path, base = source(args)
    for seed in args.seeds:  # seed-major over every arm: a partial study covers them all
        for _, name, overrides in arms(args):
            runs.append((path, [*base, f"name={name}", f"seed={seed}", f"out={args.out}", *overrides,
                                f"trainer.steps={args.steps}", "trainer.checkpoint_every=5000", *args.override]))
    return runs


#: The logged scalars kept with the results (the curves' diagnostic panels), per run.
KEPT_SCALARS = ("entropy", "weight_clamped", "advantage_mean", "value_mean", "loss_actor", "loss_qvalue", "loss_value")


def finished(args, run: str) -> tuple[dict, dict] | None:
    """(evaluations, scalars) of a run that reached ``--steps``: from its run directory, or else from the
    copy committed with the results by an earlier session (run directories do not outlive a session)."""
    run_dir, kept = Path(args.out) / run, Path(args.results) / "runs" / run
    if (run_dir / "eval.csv").is_file():
        evals, scalars = read_eval_csv(run_dir / "eval.csv"), read_scalars(run_dir)
    elif (kept / "eval.csv").is_file():
        evals = read_eval_csv(kept / "eval.csv")
        scalars = {p.stem: np.loadtxt(p, delimiter=",", ndmin=2) for p in sorted((kept / "scalars").glob("*.csv"))}
    else:
        return None
    return (evals, scalars) if len(evals["step"]) and int(evals["step"][-1]) >= args.steps else None


def run_name(overrides: list[str]) -> str:
    """The run directory's name (``NAME-seedK``) that a run's overrides give."""
    values = dict(o.split("=", 1) for o in overrides)
    return f"{values['name']}-seed{values['seed']}"


def summarise(args) -> dict:
    """Per arm: every finished run's evaluations and logged scalars."""
    found = {}
    for label, name, _ in arms(args):
        seeds = {}
        for seed in args.seeds:
            done = finished(args, f"{name}-seed{seed}")
            if done:
                seeds[seed] = (Path(args.out) / f"{name}-seed{seed}", *done)
        if seeds:
            found[label] = seeds
    return found


def write_results(args, arms: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = Path(args.results)
    results.mkdir(parents=True, exist_ok=True)
    rows, summary = [], []
    low, high = SCORE_RANGES[args.score]
    span = high - low
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    for label, seeds in arms.items():
        steps = next(iter(seeds.values()))[1]["step"]
        scores = np.stack([e["score"] for _, e, _ in seeds.values()])
        success = np.stack([e["success_rate"] for _, e, _ in seeds.values()])
        events = np.stack([e["events_mean"] for _, e, _ in seeds.values()])
        sem = np.stack([e["return_std"] for _, e, _ in seeds.values()]) / np.sqrt(
            np.stack([e["episodes"] for _, e, _ in seeds.values()]))
        mean, std = scores.mean(0), scores.std(0, ddof=1) if len(scores) > 1 else np.zeros(len(steps))
        line, = axes[0].plot(steps, mean, label=label, linestyle="--" if "τ=0.7" in label else "-")
        axes[0].fill_between(steps, mean - std, mean + std, alpha=0.2, color=line.get_color())
        for key, ax in (("weight_clamped", axes[1]), ("entropy", axes[2])):
            curves = [s[key] for _, _, s in seeds.values() if key in s]
            if curves:
                n = min(len(c) for c in curves)
                ax.plot(curves[0][:n, 0], np.mean([c[:n, 1] for c in curves], 0), color=line.get_color(),
                        linestyle=line.get_linestyle())
        last = scores[:, -args.last:].mean(1)
        peak = scores.max(1)
        rows.append((label, len(seeds), scores[:, -1], last, scores.mean(1), peak, success[:, -args.last:].mean(1),
                     events[:, -args.last:].mean(1), float(np.median(sem)) * 100 / span))
        for seed, (run_dir, evals, scalars) in seeds.items():
            if (run_dir / "eval.csv").is_file():
                dest = results / "runs" / run_dir.name
                (dest / "scalars").mkdir(parents=True, exist_ok=True)
                shutil.copyfile(run_dir / "eval.csv", dest / "eval.csv")
                shutil.copyfile(run_dir / "recipe.yaml", dest / "recipe.yaml")
                for key in KEPT_SCALARS:
                    if (run_dir / "logs" / "scalars" / f"{key}.csv").is_file():
                        shutil.copyfile(run_dir / "logs" / "scalars" / f"{key}.csv", dest / "scalars" / f"{key}.csv")
            summary.append({"arm": label, "seed": seed, "steps": int(evals["step"][-1]),
                            "eval_episodes": int(evals["episodes"][-1]), "final_score": float(evals["score"][-1]),
                            f"last{args.last}_score": float(evals["score"][-args.last:].mean()),
                            "mean_score": float(evals["score"].mean()),
                            "peak_score": float(evals["score"].max()), "peak_step": int(evals["step"][np.argmax(evals["score"])]),
                            "final_return": float(evals["return_mean"][-1]), "reward": str(evals.get("reward", ["env"])[-1])})
    axes[0].set(xlabel="gradient step", ylabel="D4RL score (mean ± std over seeds)", title=f"{row_name(args)}, ours")
    axes[0].legend()
    axes[1].set(xlabel="gradient step", ylabel="share of advantage weights at the clamp (100)", title="actor weights")
    axes[2].set(xlabel="gradient step", ylabel="-log pi(a|s) on the batch", title="actor negative log-likelihood")
    fig.tight_layout()
    fig.savefig(results / "curves.png", dpi=110)

    # ties as printed go to the later arm: with --temperatures ascending, the larger beta (more IQL, less BC)
    best = max(enumerate(rows), key=lambda ir: (round(float(ir[1][3].mean()), 1), ir[0]))[1][0] if rows else None
    n_events = load_event_spec(load_recipe(*source(args)).data.events).n
    lines = [f"| arm (λ = λ_Q = λ_π, β: AWR inverse temperature) | seeds | final score | last {args.last} evaluations | "
             f"mean over evaluations | peak | success (last {args.last}) | events of {n_events} (last {args.last}) |",
             "|---|---|---|---|---|---|---|---|"]
    for lam, n, final, last, mean, peak, succ, ev, _ in rows:
        mark = " **(chosen)**" if lam == best else ""
        lines.append(f"| {lam}{mark} | {n} | {mean_std(final)} | {mean_std(last)} | {mean_std(mean)} | {mean_std(peak)} | "
                     f"{succ.mean():.0%} | {ev.mean():.2f} |")
    noise = np.median([r[8] for r in rows]) if rows else float("nan")
    (results / "table.md").write_text("\n".join(lines) + f"\n\nStandard error of one evaluation's score "
                                      f"(10 episodes, median over evaluations): {noise:.1f} points.\n")
    (results / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print("\n".join(lines))
    print(f"chosen: {best}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_run_options(p, out="runs/decline-study")
    p.add_argument("--results", default=str(RESULTS / "decline-study"))
    p.add_argument("--lambdas", nargs="*", default=["0", "1e-4", "1e-3", "1e-2"])
    p.add_argument("--adroit-lambdas", nargs="*", default=["0", "1e-4"],
                   help="control arms with IQL's Adroit expectile and temperature (0.7, 0.5)")
    p.add_argument("--tanh-normal-lambdas", nargs="*", default=["1e-4"],
                   help="control arms with IQL's Adroit values and the tanh-squashed Gaussian actor")
    p.add_argument("--dataset", default=None, help="a dataset option of recipes/dataset/ (default: the door-human-v0 recipe)")
    p.add_argument("--temperatures", nargs="*", default=[], help="arms with the recipe's lambda and these betas")
    p.add_argument("--last", type=int, default=5, help="evaluations the choice rule averages (the last ones)")
    p.add_argument("--score", default="door", choices=sorted(SCORE_RANGES), help="the score's D4RL range")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--steps", type=int, default=50_000)
    p.add_argument("--report-only", action="store_true", help="only tabulate the runs that finished")
    args = p.parse_args()
    if not args.report_only:
        todo = [(path, o) for path, o in grid(args) if not finished(args, run_name(o))]
        run_grid(todo, args.jobs)
    write_results(args, summarise(args))
    return 0


if __name__ == "__main__":
    run_study(main, Path(__file__).name)
