"""The tuning record (benchmarks/results/choices.json) and the rule that reported runs never share its seeds."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from rm_torchrl.errors import RMError
from rm_torchrl.report.choices import KEYS, first_free_seeds, leave_out_chosen, read_choices, used_pairs
from rm_torchrl.report.runs import dataset_label, load_runs

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
CHOICE = {"what": "method.iql.temperature", "options": [0.5, 10], "dataset": "door-human-v0", "seeds": [0, 2],
          "steps": 20000, "criterion": "final score", "chosen": 0.5}


def write(tmp_path: Path, content) -> Path:
    path = tmp_path / "choices.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    return path


def run_dir(root: Path, dataset: str, seed: int) -> Path:
    run = root / f"{dataset}-ours-seed{seed}"
    run.mkdir(parents=True)
    recipe = {"name": f"{dataset}-ours", "seed": seed, "data": {"name": dataset, "source": "x.hdf5", "refine": "paper"},
              "method": {"name": "iql", "hparams": "ours"}, "eval": {"score": "door"}}
    (run / "recipe.yaml").write_text(yaml.safe_dump(recipe))
    (run / "eval.csv").write_text("step,return_mean,return_std,score\n2000,1.0,0.0,1.0\n")
    return run


def test_runs_a_choice_used_are_left_out_whatever_their_method(tmp_path):
    for seed in range(4):
        run_dir(tmp_path / "runs", "door-human-v0", seed)
    run_dir(tmp_path / "runs", "door-cloned", 0)
    kept, lines = leave_out_chosen(load_runs([tmp_path / "runs"]), read_choices(write(tmp_path, [CHOICE])))
    assert sorted((r.dataset, r.seed) for r in kept) == [("door-cloned", 0), ("door-human-v0", 1), ("door-human-v0", 3)]
    assert len(lines) == 2 and all("was used to choose method.iql.temperature" in line for line in lines)


def test_first_free_seeds_skip_the_seeds_a_choice_used():
    assert first_free_seeds("door-human-v0", [CHOICE], 3) == [1, 3, 4]
    assert first_free_seeds("door-cloned", [CHOICE], 2) == [0, 1]
    assert used_pairs([CHOICE, dict(CHOICE, what="other", seeds=[2, 5])]) == {
        ("door-human-v0", 0): CHOICE["what"], ("door-human-v0", 2): CHOICE["what"], ("door-human-v0", 5): "other"}


def test_an_exempt_choice_is_recorded_but_leaves_no_seed_out(tmp_path):
    exempt = dict(CHOICE, what="the data", seeds=[1, 3], leaves_out=False, exempt="PROTOCOL.md section 3")
    for seed in range(4):
        run_dir(tmp_path / "runs", "door-human-v0", seed)
    choices = read_choices(write(tmp_path, [CHOICE, exempt]))
    kept, lines = leave_out_chosen(load_runs([tmp_path / "runs"]), choices)
    assert sorted(r.seed for r in kept) == [1, 3] and len(lines) == 2
    assert first_free_seeds("door-human-v0", choices, 2) == [1, 3]


@pytest.mark.parametrize("content, problem", [
    ("[{", "is not valid JSON"), ({"a": 1}, "must hold a JSON list of choices, got dict"),
    ([{k: v for k, v in CHOICE.items() if k != "criterion"}], r"choice 0: missing \['criterion'\]"),
    ([dict(CHOICE, seeds=[0, "1"])], "choice 0: dataset must be a name and seeds a list of integers"),
    ([dict(CHOICE, seeds=3)], "choice 0: dataset must be a name and seeds a list of integers"),
    ([dict(CHOICE, leaves_out="no")], "choice 0: leaves_out must be true or false"),
    ([dict(CHOICE, leaves_out=False)], "choice 0: leaves_out is false, so exempt must name the rule"),
])
def test_a_bad_choices_file_is_one_line(tmp_path, content, problem):
    with pytest.raises(RMError, match=problem):
        read_choices(write(tmp_path, content))


def test_the_committed_record_is_complete():
    choices = read_choices(RESULTS / "choices.json")
    assert choices and all(set(KEYS) <= set(c) for c in choices)
    assert all(isinstance(c["steps"], int) and c["seeds"] for c in choices)


@pytest.mark.parametrize("study", ["table1", "refinement-ablation", "door-human-v0-500k"])
def test_no_reported_run_shares_a_dataset_and_seed_with_a_choice(study):
    """The protocol (benchmarks/PROTOCOL.md) on what is committed: every run a summary.json reports."""
    summary = RESULTS / study / "summary.json"
    if not summary.is_file():
        pytest.skip(f"{study} has no summary yet")
    pairs = used_pairs(read_choices(RESULTS / "choices.json"))
    reported = json.loads(summary.read_text())
    assert reported or study == "door-human-v0-500k"  # its runs are all on seeds a choice used: none reported
    for row in reported:
        recipe = yaml.safe_load((RESULTS / study / "runs" / row["run"] / "recipe.yaml").read_text())
        assert (dataset_label(recipe), row["seed"]) not in pairs, row["run"]


@pytest.mark.slow
def test_table1_report_leaves_a_non_finite_seed_out_of_every_column_by_name(tmp_path):
    """A NaN seed is named under "Runs left out"; mean ± std and the IQM use the same finite seeds; a cell whose
    every seed is NaN is left out instead of crashing the report."""
    results = tmp_path / "results"
    for method, finals in (("ours", [10.0, 20.0, float("nan")]), ("iql", [float("nan")] * 2)):
        for seed, value in zip((3, 4, 5), finals):
            run = results / "runs" / f"door-human-v0-{method}-seed{seed}"
            run.mkdir(parents=True)
            recipe = {"name": f"door-human-v0-{method}", "seed": seed,
                      "data": {"name": "door-human-v0", "source": "x.hdf5", "refine": "paper" if method == "ours" else "none",
                               "events": "door"},
                      "method": {"name": "iql", "hparams": "ours" if method == "ours" else "published"},
                      "trainer": {"steps": 50000}, "eval": {"score": "door", "episodes": 10}}
            (run / "recipe.yaml").write_text(yaml.safe_dump(recipe))
            (run / "eval.csv").write_text("step,return_mean,return_std,score,success_rate,events_mean,episodes,reward\n"
                                          f"50000,{value},0.0,{value},0.0,1.0,10,d4rl\n")
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "studies" / "table1.py"), "report",
                           "--out", str(tmp_path / "none"), "--results", str(results), "--reps", "50"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    text = (results / "results.md").read_text()
    assert "nan" not in text.split("## Runs left out")[0]
    assert "| door-human-v0 | Ours | 50k × 2 | 15.0 ± 7.1 |" in text
    assert "door-human-v0-ours-seed5: final evaluation nan (a policy gone non-finite): left out of every column" in text
    assert "door-human-v0-iql-seed4: final evaluation nan" in text
