"""``rmrl report``'s rliable statistics: IQMs with bootstrap CIs per Table 1 cell and over datasets, P(Ours >
baseline), ``aggregates.json`` and ``performance_profile.png``, from fake run directories of known final scores."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from rm_torchrl.cli.main import build_parser, main
from rm_torchrl.report import group_runs, load_runs
from rm_torchrl.report.choices import first_free_seeds, read_choices
from rm_torchrl.report.stats import REPS, _rliable, aggregate, improvement, iqm
from helpers import PNG_MAGIC, table_rows, write_run

pytest.importorskip("matplotlib")
metrics = pytest.importorskip("rliable.metrics")
_rliable()  # absl, imported with rliable, then logs to the process's stderr, not to this collection's capture

ROOT = Path(__file__).resolve().parent.parent
KEYS = {"metric", "confidence", "reps", "cells", "overall", "probability_of_improvement"}


def free_seeds(dataset: str, count: int) -> list[int]:
    """The seeds the benchmark scripts report on ``dataset``: the first ``count`` that no choice of settings used
    (``benchmarks/results/choices.json``; their reports leave the others out)."""
    return first_free_seeds(dataset, read_choices(ROOT / "benchmarks" / "results" / "choices.json"), count)


def runs(root: Path, dataset: str, method: str, finals, score: str = "door", step: int = 6000, seeds=None) -> None:
    """A run per seed (``seeds``, default 0, 1, ...) of ``method`` on ``dataset``, its last evaluation (at ``step``)
    ``finals[k]``, in the layout before ``data.refine`` named the treatment (``write_run``'s)."""
    name = dataset if method == "ours" else f"{dataset}-{method}"
    for seed, value in zip(seeds or range(len(finals)), finals):
        write_run(root, name, seed, method, method == "ours", score, {2000: 0.0, step: float(value)})


def report(root: Path, out: Path, *extra: str) -> dict:
    assert main(["report", str(root), "--out", str(out), *extra]) == 0
    return json.loads((out / "aggregates.json").read_text())


def by(entries: list[dict], key: str = "method") -> dict:
    return {e[key]: e for e in entries}


# --- the estimators against rliable's own ----------------------------------------------------

@pytest.mark.parametrize("n", range(1, 10))
def test_iqm_is_rliables_aggregate_iqm(n):
    scores = np.random.default_rng(n).normal(size=(n, 4))
    assert iqm(scores) == pytest.approx([metrics.aggregate_iqm(scores[:, j]) for j in range(4)])
    assert iqm(scores.reshape(-1, 1))[0] == pytest.approx(metrics.aggregate_iqm(scores))


@pytest.mark.parametrize("nx, ny, tasks, levels", [(3, 3, 1, 3), (3, 5, 4, 4), (5, 2, 6, 100), (1, 1, 2, 2)])
def test_improvement_is_rliables_probability_of_improvement(nx, ny, tasks, levels):
    rng = np.random.default_rng(nx * 100 + ny)
    x, y = rng.integers(0, levels, (nx, tasks)).astype(float), rng.integers(0, levels, (ny, tasks)).astype(float)
    assert improvement(x, y)[0] == pytest.approx(metrics.probability_of_improvement(x, y))  # ties count half
    assert improvement(x, x)[0] == pytest.approx(0.5)


def test_iqm_of_one_to_four():
    assert iqm(np.array([[1.0], [2.0], [3.0], [4.0]]))[0] == 2.5


# --- the report ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def two_datasets(tmp_path_factory):
    """Ours above IQL everywhere, BC with one run; CQL trained for fewer steps; a return_mean dataset."""
    root = tmp_path_factory.mktemp("runs")
    runs(root, "door-human", "ours", [1, 2, 3, 4])
    runs(root, "door-human", "iql", [0.1, 0.2, 0.3])
    runs(root, "door-human", "bc", [7])
    runs(root, "door-human", "cql", [50, 60, 70], step=4000)
    runs(root, "kitchen-partial", "ours", [50, 75, 25], score="kitchen")  # so door-human's seed 3 is cut
    runs(root, "kitchen-partial", "iql", [0, 0, 25], score="kitchen")
    runs(root, "relocate", "ours", [5000, 6000], score="")
    out = tmp_path_factory.mktemp("out") / "report"
    return root, out, report(root, out)


@pytest.mark.slow
def test_aggregates_json_shape_and_recipe_method_names(two_datasets):
    _, _, agg = two_datasets
    assert KEYS <= set(agg) and agg["metric"] == "final_score" and agg["confidence"] == 0.95 and agg["reps"] == REPS
    assert {c["method"] for c in agg["cells"]} == {"ours", "iql", "bc", "cql"}
    for entry in agg["cells"]:
        assert {"dataset", "method", "runs", "iqm", "ci"} <= set(entry) and len(entry["ci"]) == 2
    for entry in agg["overall"]:
        assert {"method", "iqm", "ci"} <= set(entry)
    for entry in agg["probability_of_improvement"]:
        assert {"x", "y", "p", "ci"} <= set(entry) and entry["x"] == "ours"


def test_cell_iqms_and_a_single_run_has_a_degenerate_ci(two_datasets):
    _, out, agg = two_datasets
    door = by([c for c in agg["cells"] if c["dataset"] == "door-human"])
    assert door["ours"]["runs"] == 4 and door["ours"]["iqm"] == 2.5
    assert 1.0 <= door["ours"]["ci"][0] < 2.5 < door["ours"]["ci"][1] <= 4.0
    assert door["bc"]["runs"] == 1 and door["bc"]["iqm"] == 7.0 and door["bc"]["ci"] == [7.0, 7.0]
    assert door["cql"]["steps"] == 4000 and door["ours"]["steps"] == 6000
    relocate = by([c for c in agg["cells"] if c["dataset"] == "relocate"])
    assert relocate["ours"]["column"] == "return_mean" and relocate["ours"]["iqm"] == 5500.0
    text = (out / "results.md").read_text()
    assert table_rows(text)["door-human"][0] == "7.0 · IQM 7.0 [7.0, 7.0] (n=1)"
    assert "one seed: [x, x], nothing to resample" in text


def test_overall_pools_scored_datasets_at_ours_budget_on_the_fewest_seeds(two_datasets):
    _, out, agg = two_datasets
    overall = by(agg["overall"])
    assert set(overall) == {"ours", "iql", "bc"}  # CQL stopped at step 4,000, ours at 6,000
    assert overall["ours"]["datasets"] == ["door-human", "kitchen-partial"] and overall["ours"]["runs_per_dataset"] == 3
    # door-human's seeds 0-2 and kitchen-partial's (1, 2, 3, 25, 50, 75): the middle four
    assert overall["ours"]["iqm"] == pytest.approx((2 + 3 + 25 + 50) / 4)
    assert overall["bc"]["datasets"] == ["door-human"] and overall["bc"]["ci"] == [7.0, 7.0]
    text = (out / "results.md").read_text()
    assert "## Aggregate over datasets" in text
    assert table_rows(text)["Ours"][1:] == ["3 × 2 datasets = 6", "6,000", "all 2"]
    assert table_rows(text)["BC"][1:] == ["1 × 1 dataset = 1", "6,000", "door-human"]
    assert "- CQL on door-human: 3 runs end at step 4,000, Ours there at 6,000: not in the aggregates" in text
    assert "- relocate: measured as return_mean (eval.score unset)" in text
    assert "- Ours: the aggregate takes the 3 lowest seeds of each dataset (door-human has 4)" in text
    assert "- BC: one run per dataset: nothing to resample, its CI is [x, x]" in text


def test_probability_of_improvement_over_the_datasets_both_have(two_datasets):
    _, out, agg = two_datasets
    better = by(agg["probability_of_improvement"], "y")
    assert set(better) == {"iql", "bc"}
    # door-human: 1, 2, 3 all above IQL's; kitchen-partial: 50, 75, 25 against 0, 0, 25 -> 8.5 of 9 pairs
    assert better["iql"]["p"] == pytest.approx((1 + 8.5 / 9) / 2)
    assert better["iql"]["datasets"] == ["door-human", "kitchen-partial"]
    assert better["iql"]["runs_per_dataset"] == {"x": 3, "y": 3}
    assert better["bc"]["p"] == 0.0 and better["bc"]["ci"] == [0.0, 0.0]  # BC's 7 beats 1, 2, 3, 4
    assert "| Ours > BC | 0.00 [0.00, 0.00] | 4 / 1 | 6,000 | door-human |" in (out / "results.md").read_text()


@pytest.mark.parametrize("ours, other, p", [([50, 60, 70], [1, 2, 3], 1.0), ([5, 5, 5], [5, 5, 5], 0.5),
                                            ([1, 2, 3], [4, 5, 6], 0.0)])
@pytest.mark.slow
def test_probability_of_improvement_dominance(tmp_path, ours, other, p):
    for dataset, score in (("door-human", "door"), ("kitchen-partial", "kitchen")):
        runs(tmp_path / "runs", dataset, "ours", ours, score=score)
        runs(tmp_path / "runs", dataset, "iql", other, score=score)
    (entry,) = report(tmp_path / "runs", tmp_path / "out", "--reps", "200")["probability_of_improvement"]
    assert (entry["x"], entry["y"], entry["p"], entry["ci"]) == ("ours", "iql", p, [p, p])


def test_performance_profile_png_and_link(two_datasets):
    _, out, _ = two_datasets
    data = (out / "performance_profile.png").read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 5000
    assert "![Performance profile](performance_profile.png)" in (out / "results.md").read_text()


def test_same_runs_same_cis_and_the_global_generator_is_left_alone(two_datasets):
    root, _, agg = two_datasets
    np.random.seed(123)
    expected = np.random.random()
    np.random.seed(123)
    again = aggregate(group_runs(load_runs([root])))
    assert np.random.random() == expected
    assert json.loads(json.dumps(again.to_json())) == agg


@pytest.mark.slow
def test_reps_option(tmp_path, capsys):
    runs(tmp_path / "runs", "door-human", "ours", [1, 2, 3])
    assert report(tmp_path / "runs", tmp_path / "out", "--reps", "50")["reps"] == 50
    assert "rliable, 50 resamples, seed 0" in (tmp_path / "out" / "results.md").read_text()
    assert build_parser().parse_args(["report", "x"]).reps is None  # the default: stats.REPS
    capsys.readouterr()
    for reps in ("0", "2"):  # two resamples once gave CIs that excluded their own estimate
        assert main(["report", str(tmp_path / "runs"), "--out", str(tmp_path / "o"), "--reps", reps]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"rmrl report: error: --reps must be at least 50 bootstrap resamples for a 95% interval, got {reps}"]
        assert not (tmp_path / "o").exists()


def test_without_a_scored_dataset_there_is_nothing_to_pool(tmp_path):
    runs(tmp_path / "runs", "relocate", "ours", [1, 2, 3], score="")
    runs(tmp_path / "runs", "relocate", "bc", [0, 1, 2], score="")
    out = tmp_path / "out"
    out.mkdir()
    (out / "performance_profile.png").write_bytes(PNG_MAGIC)  # stale, from an earlier report
    agg = report(tmp_path / "runs", out)
    assert agg["overall"] == [] and agg["probability_of_improvement"] == [] and len(agg["cells"]) == 2
    assert not (out / "performance_profile.png").exists()
    text = (out / "results.md").read_text()
    assert "No dataset has scores to pool" in text and "performance_profile.png" not in text


def test_nonfinite_runs_stay_out_of_the_json(tmp_path):
    runs(tmp_path / "runs", "door-human", "ours", [1, 2, float("nan")])
    runs(tmp_path / "runs", "door-human", "bc", [float("inf")])
    agg = report(tmp_path / "runs", tmp_path / "out")
    text = (tmp_path / "out" / "aggregates.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert [(c["method"], c["runs"], c["iqm"]) for c in agg["cells"]] == [("ours", 2, 1.5)]


def test_demo_accepts_the_files_its_report_writes(tmp_path):
    from rm_torchrl.launch.demo import check_report_dir

    for name in ("results.md", "demo.md", "learning_curves.png", "aggregates.json", "performance_profile.png"):
        (tmp_path / name).write_text("")
    check_report_dir(tmp_path)


@pytest.mark.slow
def test_table1_benchmark_report(tmp_path):
    """``benchmarks/studies/table1.py report`` on its own layout: the IQM column, the aggregate section and its files.
    Runs on a seed a choice of settings used, and BC runs from before CORL's BC (no method.bc: the Gaussian
    likelihood), are left out, each named under "Runs left out"."""
    results = tmp_path / "results"
    *seeds, other = free_seeds("door-human-v0", 4)
    for method, finals in (("ours", [30, 40, 50]), ("iql", [1, 2, 3]), ("bc", [0, 1, 2])):
        runs(results / "runs", "door-human-v0", method, finals, step=50_000, seeds=seeds)
    for seed in seeds:  # CORL's BC, as today's recipe writes it
        recipe = results / "runs" / f"door-human-v0-bc-seed{seed}" / "recipe.yaml"
        written = yaml.safe_load(recipe.read_text())
        recipe.write_text(yaml.safe_dump({**written, "data": {**written["data"], "refine": "none"},
                                          "method": {"name": "bc", "hparams": "published", "bc": {"loss": "mse"}}},
                                         sort_keys=False))
    runs(results / "runs", "door-human-v0", "bc", [99], step=50_000, seeds=[other])  # the likelihood BC of before
    runs(results / "runs", "door-human-v0", "iql", [99], step=50_000, seeds=[0])  # seed 0 chose ours' settings
    runs(results / "runs", "door-human-v0", "cql", [60, 70, 80], step=10_000, seeds=seeds)
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "studies" / "table1.py"), "report", "--out",
                           str(tmp_path / "none"), "--results", str(results), "--reps", "300"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    every = json.loads((results / "aggregates.json").read_text())
    assert set(every) == {"d4rl"}  # door-human-v0 is D4RL's file; generated stand-ins are aggregated apart
    agg = every["d4rl"]
    assert agg["reps"] == 300 and {o["method"] for o in agg["overall"]} == {"ours", "iql", "bc"}
    assert by(agg["probability_of_improvement"], "y")["iql"]["p"] == 1.0
    text = (results / "results.md").read_text()
    assert "final score IQM [95% CI]" in text and "99" not in text.split("## Runs left out")[0]
    assert "| door-human-v0 | Ours | 50k × 3 | 40.0 ± 10.0 | 40.0 [30.0, 50.0] |" in text
    assert "| door-human-v0 | BC | 50k × 3 | 1.0 ± 1.0 |" in text
    assert "## Aggregate over the D4RL data" in text and "| Ours > IQL | 1.00 [1.00, 1.00] |" in text
    assert "- CQL on door-human-v0: 3 runs end at step 10,000, Ours there at 50,000" in text
    left_out = text.split("## Runs left out")[1].splitlines()
    assert any(f"door-human-v0-bc-seed{other}" in line and "BC with the Gaussian likelihood" in line for line in left_out)
    assert any("door-human-v0-iql-seed0" in line and "seed 0 of door-human-v0 was used to choose" in line
               for line in left_out)
    assert (results / "performance_profile_d4rl.png").read_bytes()[:8] == PNG_MAGIC


def ours_500k():
    """ours' optimiser settings at the door study's 500k budget, as the recipes give them today (read, not pinned)."""
    from rm_torchrl.train.recipe import load_recipe

    return load_recipe(None, ["dataset=door-human-v0", "method=ours", "trainer.steps=500000"]).optim


def door_500k_report(out: Path, results: Path) -> None:
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "studies" / "door_500k.py"), "report",
                           "--out", str(out), "--results", str(results), "--reps", "200"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr


@pytest.mark.slow
def test_door_500k_benchmark_report(tmp_path):
    """``benchmarks/studies/door_500k.py report``: per-method table with IQM, best, last five, the hold check;
    unfinished runs out."""
    results = tmp_path / "results"
    curve = {step: 10.0 for step in range(10_000, 500_001, 10_000)}
    seeds = free_seeds("door-human-v0", 3)
    for seed, late in zip(seeds, (10.0, 8.0, 2.0)):  # the third seed falls to a fifth of its plateau at the end
        write_run(results / "runs", "door-human-v0-ours", seed, "ours", True, "door",
                  {**curve, **{s: late for s in range(460_000, 500_001, 10_000)}})
    write_run(results / "runs", "door-human-v0-iql", seeds[0], "iql", False, "door", {10_000: 1.0, 250_000: 2.0})
    chosen = write_run(results / "runs", "door-human-v0-iql", 0, "iql", False, "door", {500_000: 50.0})
    assert 0 not in seeds  # seed 0 chose ours' settings on door-human-v0: its run is left out
    door_500k_report(tmp_path / "none", results)
    text = (results / "results.md").read_text()
    assert "| Ours | 3 | 6.7 ± 4.2 | 6.7 [2.0, 10.0] | 10.0 ± 0.0 | 6.7 ± 4.2 |" in text
    assert "| 10.0 ± 0.0 | 2 of 3 |" in text  # best five in a row, and the runs that kept half of it
    assert f"door-human-v0-iql-seed{seeds[0]}: in progress (250,000 of 500,000 steps)" in text
    assert f"{chosen.name}: seed 0 of door-human-v0 was used to choose" in text and "50.0" not in text
    assert "- IQL: 0 of 3 seeds" in text
    summary = json.loads((results / "summary.json").read_text())
    assert [s["holds"] for s in sorted(summary, key=lambda s: s["seed"])] == [True, True, False]
    assert {s["last5_mean"] for s in summary} == {10.0, 8.0, 2.0}
    assert (results / "curves.png").read_bytes()[:8] == PNG_MAGIC
    assert not (results / "arms.md").exists()  # no fix candidate has run


@pytest.mark.slow
def test_door_500k_report_of_fix_candidates(tmp_path):
    """Arms (ours with ARMS' overrides) go to ``arms.md`` beside ours' default runs, also when stopped early, and
    stay out of the main table."""
    results = tmp_path / "results"
    seed, other = free_seeds("door-human-v0", 2)  # the seeds the report takes ours' default runs from
    stale = f"optim.lr_actor: 0.0003 -> {ours_500k().lr_actor!r}"
    write_run(results / "runs", "door-human-v0-ours", seed, "ours", True, "door",
              {**{s: 20.0 for s in range(10_000, 100_001, 10_000)}, **{s: 5.0 for s in range(110_000, 500_001, 10_000)}})
    write_run(tmp_path / "out", "door-human-v0-lra3e-5", seed, "ours", True, "door",
              {s: 15.0 if s <= 50_000 else 25.0 for s in range(5_000, 100_001, 5_000)})
    old = write_run(results / "runs", "door-human-v0-ours", other, "ours", True, "door",
                    {s: 3.0 for s in range(10_000, 500_001, 10_000)})
    recipe = yaml.safe_load((old / "recipe.yaml").read_text())
    (old / "recipe.yaml").write_text(yaml.safe_dump({**recipe, "optim": {"lr_actor": 3e-4}}))
    door_500k_report(tmp_path / "out", results)
    arms = (results / "arms.md").read_text()
    assert f"| ours (defaults) | {seed} | 500,000 | 20.0 | 5.0 | 20.0 | 5.0 | 5.0 |" in arms
    assert f"| {seed} | 100,000 | 20.0 | nan | 25.0 | 25.0 | 25.0 |" in arms  # 10 evaluations at 15, 10 at 25
    assert (results / "arms" / "runs" / f"door-human-v0-lra3e-5-seed{seed}" / "eval.csv").is_file()
    assert (results / "arms" / "curves.png").read_bytes()[:8] == PNG_MAGIC
    text = (results / "results.md").read_text()
    assert "| Ours | 1 |" in text  # neither the arm nor the run of an earlier default is one of ours' default runs
    assert f"door-human-v0-ours-seed{other}: trained with an earlier default ({stale})" in text
    (results / "before-fix").mkdir()
    old.rename(results / "before-fix" / old.name)
    door_500k_report(tmp_path / "out", results)
    assert f"| ours before the fix ({stale}) | {other} | 500,000 | 3.0 | 3.0 |" in (
        results / "arms.md").read_text()


def door_500k(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "benchmarks" / "studies" / "door_500k.py"), *args],
                          capture_output=True, text=True, timeout=300)


def arm_run(results: Path, arm: str, overrides: list[str], every: int = 5_000, stop: int = 500_000,
            seed: int = 0) -> Path:
    """A committed arm run whose recipe is what the trainer resolves for ours with ``overrides`` at 500k."""
    from rm_torchrl.train.recipe import load_recipe

    run = results / "arms" / "runs" / f"door-human-v0-{arm}-seed{seed}"
    run.mkdir(parents=True)
    recipe = load_recipe(None, ["dataset=door-human-v0", "method=ours", "trainer.steps=500000", f"seed={seed}",
                                f"name=door-human-v0-{arm}", f"eval.every={every}", *overrides]).to_dict()
    (run / "recipe.yaml").write_text(yaml.safe_dump(recipe, sort_keys=False))
    (run / "eval.csv").write_text("step,return_mean,return_std,score,success_rate,events_mean,episodes,reward\n" + "".join(
        f"{s},{s / 1000},1.0,{s / 10_000},0.5,2.0,10,d4rl\n" for s in range(every, stop + 1, every)))
    (run / "machine_seconds").write_text("7000.0\n")
    return run


@pytest.mark.slow
def test_door_500k_adopts_an_arm_that_became_the_default(tmp_path):
    """``adopt``: the lr arm (today's default) becomes ours' seed-0 run, evaluations kept at every 10k; an arm that
    is not the default, one stopped early, or a recipe lacking a setting is refused in one line; a seed ours has
    is left alone. The arm runs on a seed the report takes ours' default runs from (no choice used it)."""
    results = tmp_path / "results"
    seed = free_seeds("door-human-v0", 1)[0]
    optim = ours_500k()
    arm_run(results, "lra3e-5", [f"optim.lr_actor={optim.lr_actor!r}"], seed=seed)
    done = door_500k("adopt", "--arms", "lra3e-5", "--seeds", str(seed), "--results", str(results))
    assert done.returncode == 0, done.stderr
    assert "100 evaluations" in done.stderr and "50 of 100" in done.stderr
    dest = results / "runs" / f"door-human-v0-ours-seed{seed}"
    rows = (dest / "eval.csv").read_text().splitlines()
    assert len(rows) == 51 and rows[1].startswith("10000,") and rows[-1].startswith("500000,500.0,1.0,50.0,")
    recipe = yaml.safe_load((dest / "recipe.yaml").read_text())
    assert recipe["name"] == "door-human-v0-ours" and recipe["eval"]["every"] == 10_000
    assert recipe["optim"]["lr_actor"] == optim.lr_actor
    assert (recipe["method"]["name"], recipe["method"]["hparams"], recipe["data"]["refine"]) == ("iql", "ours", "paper")
    adopted = json.loads((dest / "adopted.json").read_text())
    assert adopted["from"] == f"arms/runs/door-human-v0-lra3e-5-seed{seed}" and adopted["evaluated_every"] == 5_000
    assert (dest / "machine_seconds").read_text() == "7000.0\n"
    again = door_500k("adopt", "--arms", "lra3e-5", "--seeds", str(seed), "--results", str(results))
    assert again.returncode == 0 and f"door-human-v0-ours-seed{seed} exists; nothing adopted" in again.stderr
    door_500k_report(tmp_path / "none", results)
    assert "| Ours | 1 | 50.0 | 50.0 [50.0, 50.0] | 50.0 | 48.0 |" in (results / "results.md").read_text()

    for arm, overrides, stop, why in [
            ("wdpi1e-2", ["optim.weight_decay_pi=1.0e-2"], 500_000,
             f"optim.weight_decay_pi: 0.01 -> {optim.weight_decay_pi!r}"),
            ("lra3e-5", [f"optim.lr_actor={optim.lr_actor!r}"], 100_000,
             "step 100,000 of its trainer.steps 500,000 (stopped at trainer.stop_at, killed, or still training)")]:
        other = tmp_path / f"other-{arm}-{stop}"
        arm_run(other, arm, overrides, stop=stop, seed=seed)
        refused = door_500k("adopt", "--arms", arm, "--seeds", str(seed), "--results", str(other))
        assert refused.returncode != 0 and why in refused.stderr and "Traceback" not in refused.stderr
        assert len(refused.stderr.strip().splitlines()) == 1 and not (other / "runs").exists()
    legacy = tmp_path / "legacy"
    write_run(legacy / "arms" / "runs", "door-human-v0-lra3e-5", seed, "ours", True, "door",
              {s: 1.0 for s in range(10_000, 500_001, 10_000)})
    refused = door_500k("adopt", "--arms", "lra3e-5", "--seeds", str(seed), "--results", str(legacy))
    assert refused.returncode != 0 and f"optim.lr_actor: (absent) -> {optim.lr_actor!r}" in refused.stderr


def test_linked_and_unreadable_run_folders_are_counted_or_named(tmp_path):
    """A linked run directory is a run; a linked folder of runs (not followed) and an unreadable folder each get
    a 'left out' line: the statistics never silently use fewer seeds."""
    import os

    root, elsewhere = tmp_path / "runs", tmp_path / "elsewhere"
    runs(root, "door-human-v0", "ours", [10.0, 20.0])
    runs(elsewhere, "door-human-v0", "ours", [30.0], seeds=[2])
    runs(elsewhere / "group", "door-human-v0", "ours", [40.0], seeds=[3])
    (root / "linked-seed2").symlink_to(next(elsewhere.glob("*-seed2")))
    (root / "linked-group").symlink_to(elsewhere / "group")
    locked = root / "locked"
    runs(locked, "door-human-v0", "ours", [50.0], seeds=[4])
    locked.chmod(0)
    try:
        skipped = []
        loaded = load_runs([root], skipped=skipped)
        if os.access(locked, os.R_OK):  # root reads everything: the folder's runs count
            assert sorted(r.seed for r in loaded) == [0, 1, 2, 4]
        else:
            assert sorted(r.seed for r in loaded) == [0, 1, 2]
            assert any("locked: cannot be read" in line for line in skipped), skipped
        assert any("linked-group: a link to a folder, not followed" in line for line in skipped), skipped
    finally:
        locked.chmod(0o755)


def test_a_seed_that_is_not_a_whole_number_is_one_line(tmp_path):
    from rm_torchrl.errors import RMError

    runs(tmp_path, "door-human-v0", "ours", [10.0])
    recipe = next(tmp_path.glob("*-seed0")) / "recipe.yaml"
    recipe.write_text(recipe.read_text().replace("seed: 0", "seed: abc"))
    with pytest.raises(RMError, match=r"recipe.yaml: seed must be a whole number >= 0, got 'abc'"):
        load_runs([tmp_path])


def test_the_performance_profile_spans_the_scores_own_range(tmp_path):
    """Scores in 0-17 draw a profile over 0-17 (and a little more), not over 0-100."""
    runs(tmp_path, "door-human-v0", "ours", [5.0, 17.0, 12.0])
    runs(tmp_path, "door-human-v0", "iql", [1.0, 3.0, 2.0])
    stats = aggregate(group_runs(load_runs([tmp_path])), reps=50)
    assert stats.taus[0] == 0.0 and 17.0 < stats.taus[-1] < 18.0


def test_a_cells_and_a_methods_intervals_do_not_depend_on_other_runs_in_the_report(tmp_path):
    """The same runs give the same CIs whatever else is reported beside them (another method, another dataset)."""
    alone, crowded = tmp_path / "alone", tmp_path / "crowded"
    for root in (alone, crowded):
        runs(root, "door-human-v0", "ours", [5.0, 17.0, 12.0, 9.0])
        runs(root, "door-human-v0", "iql", [1.0, 3.0, 2.0, 8.0])
    runs(crowded, "door-human-v0", "bc", [0.0, 4.0, 1.0])
    runs(crowded, "relocate-human", "bc", [1.0, 2.0, 0.5])
    a, b = (aggregate(group_runs(load_runs([root])), reps=200) for root in (alone, crowded))
    cell = {(c.dataset, c.method): c.iqm for c in b.cells}
    for c in a.cells:
        assert cell[(c.dataset, c.method)] == c.iqm, c
    assert [i.p for i in a.improvement if i.y == "IQL"] == [i.p for i in b.improvement if i.y == "IQL"]


def test_a_cell_whose_runs_learn_differently_is_noted(tmp_path):
    runs(tmp_path, "door-human-v0", "ours", [5.0, 17.0])
    recipe = next(tmp_path.glob("*-seed1")) / "recipe.yaml"
    recipe.write_text(recipe.read_text().replace("alpha: 0.5", "alpha: 1.0"))
    notes = aggregate(group_runs(load_runs([tmp_path])), reps=50).notes
    assert any(n.startswith("Ours on door-human-v0: its runs differ in data.alpha (0.5, 1.0), yet are one cell")
               for n in notes), notes


def test_every_interval_takes_at_least_the_minimum_resamples():
    from rm_torchrl.errors import RMError
    from rm_torchrl.report.stats import cell_iqm, probability_of_improvement

    with pytest.raises(RMError, match="at least 50 bootstrap resamples"):
        cell_iqm([1.0, 2.0, 3.0], reps=2)
    with pytest.raises(RMError, match="at least 50 bootstrap resamples"):
        probability_of_improvement([1.0, 2.0], [0.0, 1.0], reps=2)


@pytest.mark.slow
def test_bc_kitchen_complete_report(tmp_path):
    """``benchmarks/studies/bc_kitchen_complete.py report``: per-seed rows in tasks, the published BC beside them,
    the start-pose diagnostics' mean row; an unfinished run stays out."""
    results = tmp_path / "results"
    for seed, final in zip(range(3), (0.0, 50.0, 25.0)):
        write_run(tmp_path / "out", "kitchen-complete-v0-bc", seed, "bc", False, "kitchen",
                  {s: (75.0 if s == 20_000 else final) for s in range(2_000, 50_001, 2_000)})
    write_run(tmp_path / "out", "kitchen-complete-v0-bc", 3, "bc", False, "kitchen", {2_000: 100.0})
    (results / "diagnostics").mkdir(parents=True)
    for seed, reset in ((0, [0, 0]), (1, [2, 3])):
        (results / "diagnostics" / f"kitchen-complete-v0-bc-seed{seed}.json").write_text(json.dumps({
            "run": f"/somewhere/kitchen-complete-v0-bc-seed{seed}", "reset_robot_minus_data_mean_start": [0.03, -0.05],
            "data_start_robot_std": [0.032, 0.057],
            "replay": [{"tasks": ["kettle", "microwave"], "robot_gap_mean": 0.1}, {"tasks": [], "robot_gap_mean": 0.3}],
            "policy": {kind: {"tasks_per_episode": tasks, "mean_tasks": float(np.mean(tasks))} for kind, tasks in
                       (("env_reset", reset), ("data_start", [1, 1, 1]), ("data_mean_robot", [2, 1]))}}))
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "studies" / "bc_kitchen_complete.py"), "report",
                           "--out", str(tmp_path / "out"), "--results", str(results), "--reps", "200"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    rows = table_rows((results / "results.md").read_text())
    assert rows["1"] == ["50.0", "2.00", "75.0 (20,000)", "51.0"]
    assert "3" not in rows  # stopped at 2,000 of 50,000 steps
    assert rows["mean over 2 runs"] == ["1.25", "1.00", "1.50"]
    text = (results / "results.md").read_text()
    assert "final score 25.0 ± 25.0" in text and "33.8 (1.35 tasks)" in text
    assert "1.00 tasks on average over 2 episodes (per episode: 2, 0)" in text
    summary = json.loads((results / "summary.json").read_text())
    assert sorted(s["seed"] for s in summary) == [0, 1, 2] and {s["source"] for s in summary} == {"d4rl"}
    assert (results / "curves.png").read_bytes()[:8] == PNG_MAGIC


def _brute_force_p(x, y) -> float:
    """The two-sided permutation p of Mann-Whitney's U over every split of the pooled runs: the reference."""
    from itertools import combinations

    from scipy import stats

    pooled = np.concatenate([x, y])
    observed = stats.mannwhitneyu(x, y, method="asymptotic").statistic
    us = []
    for idx in combinations(range(len(pooled)), len(x)):
        mask = np.zeros(len(pooled), bool)
        mask[list(idx)] = True
        us.append(stats.mannwhitneyu(pooled[mask], pooled[~mask], method="asymptotic").statistic)
    us = np.array(us)
    return min(1.0, 2 * min(np.mean(us >= observed - 1e-9), np.mean(us <= observed + 1e-9)))


@pytest.mark.parametrize("x, y", [([5.0, 6.0, 7.0, 8.0], [1.0, 2.0, 3.0, 4.0]),
                                  ([1.0, 1.0, 2.0, 3.0, 5.0], [1.0, 2.0, 2.0, 0.0, 4.0]),
                                  ([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
                                  ([3.3, 1.2, 9.9, 4.0], [2.2, 8.1, 0.5])])
def test_rank_test_is_the_exact_permutation_p(x, y):
    from rm_torchrl.report.stats import rank_test

    assert rank_test(x, y) == pytest.approx(_brute_force_p(np.array(x), np.array(y)), abs=1e-9)
    assert rank_test(x, y) == pytest.approx(rank_test(y, x), abs=1e-9)


def test_rank_test_without_ties_is_scipys_exact_mann_whitney():
    from scipy import stats

    from rm_torchrl.report.stats import rank_test

    rng = np.random.default_rng(3)
    x, y = rng.normal(size=15), rng.normal(size=15) + 1.0
    assert rank_test(x, y) == stats.mannwhitneyu(x, y, alternative="two-sided", method="exact").pvalue


def test_rank_test_refuses_empty_or_nonfinite_sides():
    from rm_torchrl.errors import RMError
    from rm_torchrl.report.stats import rank_test

    with pytest.raises(RMError, match="finite scores on both sides"):
        rank_test([], [1.0])
    with pytest.raises(RMError, match="finite scores on both sides"):
        rank_test([np.nan, 1.0], [1.0, 2.0])


@pytest.mark.parametrize("p, adjusted", [([0.01, 0.04, 0.03], [0.03, 0.06, 0.06]),
                                         ([0.5, 0.001], [0.5, 0.002]),
                                         ([0.4, 0.3, 0.2, 0.1], [0.6, 0.6, 0.6, 0.4]),
                                         ([0.9], [0.9])])
def test_holm_step_down(p, adjusted):
    from rm_torchrl.report.stats import holm

    assert holm(p) == pytest.approx(adjusted)
