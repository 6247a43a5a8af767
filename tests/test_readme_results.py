"""benchmarks/readme_results.py: the results blocks of benchmarks/FINDINGS.md, generated from the committed summaries."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import load_benchmark

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "readme_results.py"


def run_row(dataset, source, method, seed, score, steps=50_000):
    return {"dataset": dataset, "source": source, "method": method, "run": f"{dataset}-{method.lower()}-seed{seed}",
            "seed": seed, "steps": steps, "eval_episodes": 10, "final_score": score, "mean_score": score / 2,
            "final_return": 10 * score, "final_success": 0.5, "final_events": 2.0}


def aggregate(cells, overall, pois, notes=()):
    return {"metric": "final_score", "confidence": 0.95, "reps": 2000, "seed": 0, "cells": cells,
            "overall": overall, "probability_of_improvement": pois, "notes": list(notes)}


def small_results(root: Path) -> Path:
    """A results folder: Table 1 on one D4RL dataset and one generated stand-in, and the choices."""
    t1 = root / "table1"
    t1.mkdir(parents=True)
    summary = [run_row("door-human-v0", "d4rl", "Ours", 3, 20.0), run_row("door-human-v0", "d4rl", "Ours", 4, 10.0),
               run_row("door-human-v0", "d4rl", "IQL", 3, 5.0), run_row("door-human-v0", "d4rl", "IQL", 4, 7.0),
               run_row("kitchen-partial", "generated", "Ours", 2, 25.0),
               run_row("kitchen-partial", "generated", "Ours", 3, 50.0)]
    (t1 / "summary.json").write_text(json.dumps(summary))
    for r in summary:  # evaluations every 2,000 steps
        (t1 / "runs" / r["run"]).mkdir(parents=True)
        (t1 / "runs" / r["run"] / "eval.csv").write_text("step,score\n2000,1.0\n4000,2.0\n")
    d4rl = aggregate(
        [{"dataset": "door-human-v0", "method": "ours", "runs": 2, "iqm": 15.0, "ci": [10.0, 20.0], "steps": 50000},
         {"dataset": "door-human-v0", "method": "iql", "runs": 2, "iqm": 6.0, "ci": [5.0, 7.0], "steps": 50000}],
        [{"method": "ours", "iqm": 15.0, "ci": [10.0, 20.0], "datasets": ["door-human-v0"], "steps": [50000],
          "runs_per_dataset": 2},
         {"method": "iql", "iqm": 6.0, "ci": [5.0, 7.0], "datasets": ["door-human-v0"], "steps": [50000],
          "runs_per_dataset": 2}],
        [{"x": "ours", "y": "iql", "p": 1.0, "ci": [1.0, 1.0], "datasets": ["door-human-v0"], "steps": [50000],
          "runs_per_dataset": {"x": 2, "y": 2}}])
    generated = aggregate(
        [{"dataset": "kitchen-partial (generated)", "method": "ours", "runs": 2, "iqm": 37.5, "ci": [25.0, 50.0],
          "steps": 50000}],
        [{"method": "ours", "iqm": 37.5, "ci": [25.0, 50.0], "datasets": ["kitchen-partial (generated)"],
          "steps": [50000], "runs_per_dataset": 2}], [], ["Ours: a note of the report"])
    (t1 / "aggregates.json").write_text(json.dumps({"d4rl": d4rl, "generated": generated}))
    (t1 / "results.md").write_text(
        "# Table 1\n\n| dataset | method | steps × seeds | paper's return (0.5M steps) |\n|---|---|---|---|\n"
        "| door-human-v0 | Ours | 50k × 2 | 439.5 |\n| kitchen-partial (generated) | Ours | 50k × 2 | 3.24 |\n\n"
        "## Cells not complete yet\n\n- door-human-v0 / CQL (10k steps): 0 of 3 seeds finished\n\n"
        "## Runs left out\n\n"
        "- door-human-v0-cql-seed0: seed 0 of door-human-v0 was used to choose optim.weight_decay_q (ours)\n"
        "- door-human-v0-ours-seed1: seed 1 of door-human-v0 was used to choose optim.weight_decay_q (ours)\n"
        "- kitchen-partial-ours-seed0: seed 0 of rmrl-kitchen-partial was used to choose "
        "method.iql.temperature (ours)\n"
        "- door-human-v0-bc-seed3: BC with the Gaussian likelihood, before CORL's BC replaced it\n\n## Findings\n")
    (root / "choices.json").write_text(json.dumps([
        {"what": "optim.weight_decay_q (ours)", "dataset": "door-human-v0", "seeds": [0, 1, 2]},
        {"what": "method.iql.temperature (ours)", "dataset": "rmrl-kitchen-partial", "seeds": [0, 1],
         "generated": True}]))
    (root / "door-human-v0-500k").mkdir()
    (root / "door-human-v0-500k" / "summary.json").write_text(json.dumps(
        [run_row("door-human-v0", "d4rl", "Ours", 0, 23.0, steps=500_000)]))
    return root


def test_table1_block_states_budget_marks_generated_and_keeps_aggregates_apart(tmp_path):
    rr = load_benchmark("readme_results")
    results = small_results(tmp_path / "results")
    md = rr.blocks(results)["table1"]
    rows = [line for line in md.splitlines() if line.startswith("| ")]
    table = [r for r in rows if "episodes every" in r]
    assert len(table) == 3  # Ours and IQL on door-human-v0, Ours on kitchen-partial
    for r in table:  # the budget beside every number: steps × seeds (which), episodes, spacing
        assert "50k × 2 seeds" in r and "10 episodes every 2,000 steps" in r
    door_ours = next(r for r in table if r.startswith("| door-human-v0 | Ours"))
    assert "(3, 4)" in door_ours and "15.0 ± 7.1" in door_ours and "15.0 [10.0, 20.0]" in door_ours
    assert "439.5" in door_ours
    kitchen = [r for r in rows if "kitchen-partial" in r]
    assert kitchen and all("kitchen-partial (generated)" in r for r in kitchen)
    assert "(2, 3)" in table[-1] and "37.5 ± 17.7" in table[-1]
    # D4RL's aggregate and the generated one are two sections, neither holding the other's datasets
    d4rl_at, gen_at = md.index("Aggregate over D4RL's datasets"), md.index("Aggregate over the generated stand-ins")
    d4rl_part, gen_part = md[d4rl_at:gen_at], md[gen_at:md.index("**Left out**")]
    assert "kitchen" not in d4rl_part and "door-human" not in gen_part
    assert "P(Ours > IQL) | 1.00 [1.00, 1.00]" in d4rl_part and "Ours: a note of the report" in gen_part
    # what was left out, and why
    left = md[md.index("**Left out**"):]
    assert "door-human-v0, seeds 0, 1: Ours, CQL (2 runs)" in left and "optim.weight_decay_q (ours)" in left
    assert "kitchen-partial (generated), seed 0: Ours (1 run)" in left
    assert "BC with the Gaussian likelihood, before CORL's BC replaced it (1 run): door-human-v0 BC seed 3" in left
    assert "So BC, CQL have no reported run" in left
    assert "CQL (10k steps × 3 seeds planned): seeds finished: 0 on door-human-v0" in left


def test_500k_and_ablation_blocks_leave_out_choice_seeds(tmp_path):
    rr = load_benchmark("readme_results")
    results = small_results(tmp_path / "results")
    blocks = rr.blocks(results)
    assert "does not exist" in blocks["ablation"]
    assert "Left out of `benchmarks/results/door-human-v0-500k/`" in blocks["500k"]
    assert "door-human-v0, seed 0: Ours (1 run)" in blocks["500k"] and "23.0" not in blocks["500k"]
    assert "Not finished yet, on door-human-v0 seeds no choice used (3 and up)" in blocks["500k"]
    # once door_500k.py's report leaves the choice runs out itself, its results.md says which
    (results / "door-human-v0-500k" / "summary.json").write_text(json.dumps(
        [run_row("door-human-v0", "d4rl", "IQL", s, 5.0 + s, steps=500_000) for s in (3, 4)]))
    for s in (3, 4):
        (results / "door-human-v0-500k" / "runs" / f"door-human-v0-iql-seed{s}").mkdir(parents=True)
        (results / "door-human-v0-500k" / "runs" / f"door-human-v0-iql-seed{s}" / "eval.csv").write_text(
            "step,score\n10000,1.0\n20000,2.0\n")
    (results / "door-human-v0-500k" / "results.md").write_text(
        "# 500k\n\n## Runs left out\n\n- door-human-v0-bc-seed1: seed 1 of door-human-v0 was used to choose "
        "optim.weight_decay_q (ours)\n- door-human-v0-ours-seed5: in progress (120,000 of 500,000 steps)\n")
    block = rr.blocks(results)["500k"]
    assert "| IQL | – | – | – | 500k × 2 seeds (3, 4); 10 episodes every 10,000 steps | 8.5 ± 0.7 |" in block
    assert "door-human-v0, seed 1: BC (1 run). That seed was used to choose optim.weight_decay_q (ours)." in block
    assert "- in progress (1 run): door-human-v0 Ours seed 5." in block
    ablation = [dict(run_row("rmrl-kitchen-partial", "generated", "x", s, 10.0 + s), algorithm="iql", hparams="ours",
                     refine=refine, eval_every=2000, method=None) for s in (1, 2, 3) for refine in ("none", "paper")]
    ablation += [dict(run_row("door-human-v0", "d4rl", "x", s, 20.0, steps=500_000), algorithm="iql", hparams="ours",
                      refine="paper", eval_every=10000, method=None) for s in (3, 4, 5)]
    (results / "refinement-ablation").mkdir()
    (results / "refinement-ablation" / "summary.json").write_text(json.dumps(ablation))
    blocks = rr.blocks(results)
    rows = [line for line in blocks["ablation"].splitlines() if line.startswith("| ")]
    assert any(r.startswith("| Ours | IQL | ours' | refined") and "50k × 2 seeds (2, 3)" in r for r in rows)
    assert any(r.startswith("| IQL (ours' settings) | IQL | ours' | raw") for r in rows)
    assert "*kitchen-partial (generated), 50k steps*" in blocks["ablation"]
    assert "kitchen-partial (generated), seed 1: Ours, IQL (ours' settings) (2 runs)" in blocks["ablation"]
    assert "500k × 3 seeds (3-5); 10 episodes every 10,000 steps | 20.0 ± 0.0" in blocks["500k"]
    # the ablation's own report lists what it left out: run labels become table labels
    (results / "refinement-ablation" / "results.md").write_text(
        "# ablation\n\n## Runs left out\n\n- rmrl-kitchen-partial-iql-ours-none-seed0: seed 0 of rmrl-kitchen-partial "
        "was used to choose method.iql.temperature (ours)\n")
    block = rr.blocks(results)["ablation"]
    assert ("kitchen-partial (generated), seed 0: IQL (ours' settings) (1 run). That seed was used to choose "
            "method.iql.temperature (ours).") in block


@pytest.mark.slow
def test_check_fails_on_a_stale_block_and_passes_on_a_fresh_one(tmp_path):
    results = small_results(tmp_path / "results")
    readme = tmp_path / "README.md"
    readme.write_text("# title\n\nkept text\n\n" + "".join(
        f"<!-- results:{name} -->\nSTALE-PLACEHOLDER\n<!-- /results:{name} -->\n\nmore text\n"
        for name in ("table1", "ablation", "500k")))

    def script(*args):
        return subprocess.run([sys.executable, str(SCRIPT), "--readme", str(readme), "--results", str(results), *args],
                              capture_output=True, text=True, timeout=120)

    stale = script("--check")
    assert stale.returncode == 1
    assert len(stale.stderr.strip().splitlines()) == 1
    assert "results:table1, results:ablation, results:500k" in stale.stderr
    assert readme.read_text().count("STALE-PLACEHOLDER") == 3  # --check writes nothing
    assert script().returncode == 0
    text = readme.read_text()
    assert text.startswith("# title\n\nkept text\n") and text.count("more text") == 3
    assert "STALE-PLACEHOLDER" not in text
    assert script("--check").returncode == 0
    assert not list(tmp_path.glob(".README.md.*"))  # no temporary file left beside it
    readme.write_text(text.replace("10 episodes every 2,000 steps", "10 episodes", 1))
    again = script("--check")
    assert again.returncode == 1 and "results:table1" in again.stderr and "results:500k" not in again.stderr
    readme.write_text(text.replace("<!-- /results:500k -->", ""))
    missing = script("--check")
    assert missing.returncode == 1 and "results:500k" in missing.stderr


def test_a_method_on_fewer_datasets_is_flagged_not_ranked(tmp_path):
    rr = load_benchmark("readme_results")
    both = ["kitchen-mixed (generated)", "kitchen-partial (generated)"]
    generated = aggregate(
        [{"dataset": d, "method": m, "runs": 1, "iqm": 1.0, "ci": [0.0, 2.0], "steps": 50000}
         for d in both for m in ("ours", "ours-reuse") if m == "ours" or d == both[1]],
        [{"method": "ours", "iqm": 5.0, "ci": [1.0, 9.0], "datasets": both, "steps": [50000, 50000],
          "runs_per_dataset": 1},
         {"method": "ours-reuse", "iqm": 12.0, "ci": [10.0, 14.0], "datasets": both[1:], "steps": [50000],
          "runs_per_dataset": 1}], [])
    summary = [run_row("kitchen-mixed", "generated", "Ours", 0, 1.0),
               run_row("kitchen-partial", "generated", "Ours", 0, 1.0),
               run_row("kitchen-partial", "generated", "ours-reuse", 0, 1.0)]
    md = rr.table1_block(summary, {"generated": generated}, images=(("profile.png", "profile", "generated"),))
    reuse = next(line for line in md.splitlines() if line.startswith("| ours-reuse | 12.0"))
    assert "only 1 of the 2: not comparable" in reuse
    assert "Aggregate over D4RL's datasets" not in md  # no D4RL data, no D4RL aggregate
    assert "In this profile ours-reuse's curve covers 1 of ours' 2 datasets" in md
    cells = [line for line in md.splitlines() if line.startswith("| kitchen")]
    assert len(cells) == 3 and all(" | 50k × 1 seed (0); 10 episodes | 1.0 | " in line for line in cells)
