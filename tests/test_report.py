"""``rmrl report``: run directories -> Table 1 / Table 2 in Markdown and the learning-curve figures.

Fake run directories are written here exactly as the trainer lays them out (recipe.yaml, eval.csv,
refine_report.json, logs/scalars/*.csv) with known final scores, so every printed number is known:
the final scores of a cell's three seeds are ``mean - k, mean, mean + k``, hence ``mean ± k``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from rm_torchrl.cli import report as cli_report
from rm_torchrl.errors import RMError
from rm_torchrl.report import dataset_label, find_run_dirs, group_runs, load_runs, method_label, read_run
from rm_torchrl.report.runs import method_option
from rm_torchrl.run_format import run_label
from rm_torchrl.report.tables import results_table, stages_table

from helpers import EVAL_HEADER, PNG_MAGIC, table_rows, write_run

pytest.importorskip("matplotlib")

SEEDS = (0, 1, 2)
STEPS = (2000, 4000, 6000)

# dataset -> (eval.score, {method label: (final mean, spread k)})
CELLS = {
    "door-human": ("door", {"BC": (-20.4, 3.0), "IQL": (74.8, 5.0), "CQL": (75.8, 2.5), "Ours": (439.5, 12.0)}),
    "kitchen-partial": ("kitchen", {"BC": (1.3, 0.2), "IQL": (1.6, 0.4), "Ours": (3.2, 0.3)}),
    "relocate-cloned": ("", {"BC": (-51.6, 1.0), "BCQ": (-56.0, 2.0), "Ours": (492.4, 8.0)}),
}
# Table 2 (the paper's numbers) for the refined runs of each dataset
STAGES = {
    "door-human": {"original": 6704, "split": 5001, "ordered": 5001, "shorter": 2261},
    "kitchen-partial": {"original": 136345, "split": 98690, "ordered": 50114, "shorter": 22682},
    "relocate-cloned": {"original": 996242, "split": 364207, "ordered": 364207, "shorter": 364207},
}
RECIPE_NAMES = {"BC": "{d}-bc", "BCQ": "{d}-bcq", "IQL": "{d}-iql", "CQL": "{d}_cql", "Ours": "{d}"}


def build_runs(root: Path) -> Path:
    """Every cell of CELLS x 3 seeds under root/<dataset>/ (a nested layout, found recursively)."""
    for dataset, (score, cells) in CELLS.items():
        for label, (mean, k) in cells.items():
            method = {"Ours": "iql"}.get(label, label.lower())
            for seed, offset in zip(SEEDS, (-k, 0.0, k)):
                final = round(mean + offset, 6)
                steps = STEPS
                if label == "BC" and dataset == "door-human" and seed == 2:
                    steps = (3000, 6000)  # evaluated at other steps: the curve is interpolated
                finals = {s: final * s / max(steps) for s in steps}
                write_run(root / dataset, RECIPE_NAMES[label].format(d=dataset), seed, method,
                          refine=label == "Ours", score=score, finals=finals, steps=steps,
                          stages=STAGES[dataset] if label == "Ours" else None)
    return root


def args(*paths, out, dataset_from="name", decimals=1):
    return argparse.Namespace(paths=[str(p) for p in paths], out=str(out), dataset_from=dataset_from,
                              decimals=decimals, reps=None, gifs=False, gif_steps=100)


@pytest.fixture(scope="module")
def reported(tmp_path_factory):
    """The runs, the report written from their parent directory, and what it printed."""
    root = build_runs(tmp_path_factory.mktemp("runs"))
    out = tmp_path_factory.mktemp("out") / "reports"
    return root, out


@pytest.fixture(scope="module")
def report_output(reported):
    root, out = reported
    import contextlib
    import io

    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert cli_report.run(args(root, out=out)) == 0
    return stdout.getvalue()


# --- labels ----------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["door-human", "demo-ours", "door-human-v0-BCQ", "kitchen-mixed-iql", "run"])
def test_dataset_label_is_the_recipes_data_name_never_the_run_name(name):
    assert dataset_label({"name": name, "data": {"name": "door-human", "source": "x.hdf5"}}) == "door-human"


@pytest.mark.parametrize("source, expected", [
    ("../shared/data/d4rl/door-cloned-v0.hdf5", "door-cloned-v0"), ("minari:D4RL/door/human-v2", "door-human-v2"),
    ("mydata", "mydata"),
])
def test_dataset_label_from_source(source, expected):
    recipe = {"name": "door-human-bc", "data": {"name": "door-human", "source": source}}
    assert dataset_label(recipe, "source") == expected
    assert dataset_label({"name": "door-human-bc", "data": {"source": source}}) == expected  # no data.name
    assert dataset_label({"name": "x", "data": {"name": "data", "source": source}}) == expected  # the placeholder


@pytest.mark.parametrize("method, data, expected", [
    # the layout of today's recipes: an algorithm, its settings, a data treatment
    ({"name": "iql", "hparams": "ours"}, {"refine": "paper"}, "Ours"),
    ({"name": "iql", "hparams": "ours"}, {"refine": "reuse"}, "ours-reuse"),
    ({"name": "iql", "hparams": "ours"}, {"refine": "none"}, "IQL (ours' settings)"),
    ({"name": "iql", "hparams": "published"}, {"refine": "none"}, "IQL"),
    ({"name": "iql", "hparams": "published"}, {"refine": "paper"}, "IQL (refined)"),
    ({"name": "bc", "hparams": "published"}, {"refine": "paper"}, "BC (refined)"),
    ({"name": "bc", "hparams": "published"}, {"refine": "reuse"}, "BC (refined, reuse)"),
    ({"name": "cql", "hparams": "published"}, {"refine": "none"}, "CQL"),
    # earlier layouts: a boolean refine beside reuse, the method name carrying the treatment
    ({"name": "ours"}, {"refine": True}, "Ours"), ({"name": "ours-reuse"}, {"refine": True, "reuse": True}, "ours-reuse"),
    ({"name": "iql"}, {"refine": True}, "Ours"), ({"name": "iql"}, {"refine": False}, "IQL"),
    ({"name": "bc"}, {"refine": False}, "BC"), ({"name": "bcq"}, {"refine": False, "reuse": False}, "BCQ"),
    ({"name": "iql", "hparams": "ours"}, {"refine": False, "reuse": False}, "IQL (ours' settings)"),
    ({"name": "bc"}, {"refine": True, "reuse": True}, "BC (refined, reuse)"),
])
def test_method_label_comes_from_the_recipe_of_any_layout(method, data, expected):
    assert method_label({"name": "folder-names-do-not-count", "method": method, "data": data}) == expected


@pytest.mark.parametrize("algorithm", ["iql", "bc", "cql", "bcq"])
@pytest.mark.parametrize("hparams", ["published", "ours"])
@pytest.mark.parametrize("refine", ["none", "paper", "reuse"])
def test_method_option_inverts_the_label(algorithm, hparams, refine):
    """Every (algorithm, settings, treatment) has a label of its own, and the option comes back from it."""
    label = method_label({"method": {"name": algorithm, "hparams": hparams}, "data": {"refine": refine}})
    assert method_option(label) == run_label(algorithm, hparams, refine)


# --- Table 1 ---------------------------------------------------------------------------------

@pytest.mark.slow
def test_table1_mean_std_and_bold_best(report_output):
    """Beside mean ± std, the IQM of the three seeds m - k, m, m + k (their mean) and its bootstrap CI [m - k, m + k]:
    all three resampled alike has chance 1/27, above the 2.5% each tail cuts."""
    rows = table_rows(report_output)
    assert rows["Dataset"] == ["BC", "BCQ", "IQL", "CQL", "Ours"]  # the paper's column order
    assert rows["door-human"] == ["-20.4 ± 3.0 · IQM -20.4 [-23.4, -17.4]", "–", "74.8 ± 5.0 · IQM 74.8 [69.8, 79.8]",
                                  "75.8 ± 2.5 · IQM 75.8 [73.3, 78.3]", "**439.5 ± 12.0** · IQM 439.5 [427.5, 451.5]"]
    assert rows["kitchen-partial"] == ["1.3 ± 0.2 · IQM 1.3 [1.1, 1.5]", "–", "1.6 ± 0.4 · IQM 1.6 [1.2, 2.0]", "–",
                                       "**3.2 ± 0.3** · IQM 3.2 [2.9, 3.5]"]
    assert rows["relocate-cloned"] == ["-51.6 ± 1.0 · IQM -51.6 [-52.6, -50.6]", "-56.0 ± 2.0 · IQM -56.0 [-58.0, -54.0]",
                                       "–", "–", "**492.4 ± 8.0** · IQM 492.4 [484.4, 500.4]"]
    assert list(rows) == ["Dataset", "door-human", "kitchen-partial", "relocate-cloned"]


def test_table1_uses_score_only_when_eval_score_is_set(reported):
    root, _ = reported
    runs = load_runs([root])
    by = {(r.dataset, r.method, r.seed): r for r in runs}
    door = by[("door-human", "Ours", 1)]
    assert door.metric == "score" and door.final_value == pytest.approx(439.5)
    assert door.evals["return_mean"][-1] == pytest.approx(4395.0)
    relocate = by[("relocate-cloned", "Ours", 1)]
    assert relocate.metric == "return_mean" and relocate.final_value == pytest.approx(492.4)


def test_bold_marks_every_tie_and_not_a_lonely_cell(tmp_path):
    for seed in SEEDS:
        write_run(tmp_path, "door-human-bc", seed, "bc", False, "door", {6000: 10.04})
        write_run(tmp_path, "door-human-cql", seed, "cql", False, "door", {6000: 9.96})
        write_run(tmp_path, "door-human", seed, "iql", True, "door", {6000: 3.0})
        write_run(tmp_path, "relocate-human-bc", seed, "bc", False, "relocate", {6000: 5.0})
    table = results_table(group_runs(load_runs([tmp_path])))
    rows = table_rows(table)
    assert rows["door-human"] == ["**10.0 ± 0.0**", "**10.0 ± 0.0**", "3.0 ± 0.0"]  # equal as printed
    assert rows["relocate-human"] == ["5.0 ± 0.0", "–", "–"]


@pytest.mark.slow
def test_results_md_header_and_figures(reported, report_output):
    _, out = reported
    text = (out / "results.md").read_text()
    assert "30 training runs (3 datasets × 5 methods)" in text
    assert "seeds 0, 1, 2" in text
    assert "gradient step 6,000" in text and "10 episodes per evaluation" in text
    assert "`score` (door-human, kitchen-partial)" in text and "`return_mean` (relocate-cloned" in text
    assert "![Learning curves](learning_curves.png)" in text and "(dataset_sizes.png)" in text
    assert "| door-human | -20.4 ± 3.0 · IQM -20.4 [-23.4, -17.4] | – | 74.8 ± 5.0 · IQM 74.8 [69.8, 79.8] |" in text
    assert "IQM [lo, hi]: the interquartile mean over seeds with its stratified-bootstrap 95% CI" in text
    measured, table = report_output.strip().split("\n\n")  # stdout: what was measured (the budget), then Table 1
    assert measured.startswith("Measured: 30 training runs") and measured in text and table in text


def test_cells_with_fewer_seeds_or_unfinished_runs_are_marked(tmp_path):
    for seed in SEEDS:
        write_run(tmp_path, "door-human", seed, "iql", True, "door", {2000: 1.0, 4000: 5.0})
    write_run(tmp_path, "door-human-bc", 0, "bc", False, "door", {2000: 1.0})
    write_run(tmp_path, "door-human-bc", 1, "bc", False, "door", {2000: 3.0})
    runs = load_runs([tmp_path])
    rows = table_rows(results_table(group_runs(runs)))
    assert rows["door-human"] == ["2.0 ± 1.4 (n=2) †", "**5.0 ± 0.0**"]
    from rm_torchrl.report.tables import results_markdown

    assert "runs end at step 2,000 (2 runs), 4,000 (3 runs)" in results_markdown(runs)


# --- Table 2 ---------------------------------------------------------------------------------

@pytest.mark.slow
def test_table2_rows(reported, report_output):
    _, out = reported
    rows = table_rows((out / "results.md").read_text())
    assert rows["Procedure"] == ["door-human", "kitchen-partial", "relocate-cloned"]
    assert rows["Original Dataset"] == ["6,704", "136,345", "996,242"]
    assert rows["Splitting Traj."] == ["5,001 (74.6%)", "98,690 (72.4%)", "364,207 (36.6%)"]
    assert rows["Ordered Events"] == ["5,001 (74.6%)", "50,114 (36.8%)", "364,207 (36.6%)"]
    assert rows["Shorter Traj."] == ["2,261 (33.7%)", "22,682 (16.6%)", "364,207 (36.6%)"]
    assert "- door-human: reach_handle → door_0.2" in (out / "results.md").read_text()


def test_table2_range_when_refined_runs_disagree(tmp_path):
    other = dict(STAGES["door-human"], shorter=3000)
    write_run(tmp_path, "door-human", 0, "iql", True, "door", {6000: 1.0}, stages=STAGES["door-human"])
    write_run(tmp_path, "door-human", 1, "iql", True, "door", {6000: 1.0}, stages=other)
    rows = table_rows(stages_table(load_runs([tmp_path])))
    assert rows["Shorter Traj."] == ["2,261–3,000"]
    assert rows["Original Dataset"] == ["6,704"]


REUSED_STAGES = dict(STAGES["kitchen-partial"], reused=98690, shorter=45000)


@pytest.mark.slow
def test_ours_reuse_is_its_own_method_and_table2_column(tmp_path, capsys):
    """Runs of ours-reuse beside ours (whose reports, like those of old runs, have no "reused" stage): Table 1
    gets an ours-reuse column after Ours, Table 2 a column of its own and the row Reused Sub-traj."""
    for seed in SEEDS:
        write_run(tmp_path, "kitchen-partial-ours", seed, "ours", True, "kitchen", {6000: 3.0 + seed},
                  stages=STAGES["kitchen-partial"])
        write_run(tmp_path, "kitchen-partial-ours-reuse", seed, "ours-reuse", True, "kitchen", {6000: 2.0 + seed},
                  stages=REUSED_STAGES, reuse=True)
        write_run(tmp_path, "kitchen-partial-iql", seed, "iql", False, "kitchen", {6000: 1.0 + seed})
    out = tmp_path / "out"
    assert cli_report.run(args(tmp_path, out=out)) == 0
    capsys.readouterr()
    text = (out / "results.md").read_text()
    rows = table_rows(text)
    assert rows["Dataset"] == ["IQL", "Ours", "ours-reuse"]
    assert rows["kitchen-partial"][1].startswith("**4.0 ± 1.0**") and rows["kitchen-partial"][2].startswith("3.0 ± 1.0")
    assert rows["Procedure"] == ["kitchen-partial", "kitchen-partial (reuse)"]
    assert rows["Ordered Events"] == ["50,114 (36.8%)", "50,114 (36.8%)"]
    assert rows["Reused Sub-traj."] == ["–", "98,690 (72.4%)"]
    assert rows["Shorter Traj."] == ["22,682 (16.6%)", "45,000 (33.0%)"]
    assert list(rows).index("Ordered Events") < list(rows).index("Reused Sub-traj.") < list(rows).index("Shorter Traj.")
    assert "ours-reuse = Ours on the dataset refined with the reuse stage" in text
    aggregates = json.loads((out / "aggregates.json").read_text())
    assert {c["method"] for c in aggregates["cells"]} == {"ours", "ours-reuse", "iql"}
    assert (out / "dataset_sizes.png").read_bytes()[:8] == PNG_MAGIC


@pytest.mark.slow
def test_table2_has_no_reused_row_without_the_stage(reported, report_output):
    _, out = reported
    assert "Reused Sub-traj." not in (out / "results.md").read_text()
    assert "Reused Sub-traj." not in stages_table(load_runs([reported[0]]))


def test_error_reused_stage_not_a_number(tmp_path):
    write_run(tmp_path, "door-human", 0, "ours-reuse", True, "door", {6000: 1.0}, reuse=True,
              stages=dict(STAGES["door-human"], reused="many"))
    with pytest.raises(RMError, match="'stages' holds 'reused' .* must be a number, got 'many'"):
        load_runs([tmp_path])


# --- figures and files -----------------------------------------------------------------------

@pytest.mark.parametrize("name", ["learning_curves.png", "dataset_sizes.png"])
@pytest.mark.slow
def test_pngs_written(reported, report_output, name):
    _, out = reported
    data = (out / name).read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 5000


@pytest.mark.slow
def test_no_temporary_files_left(reported, report_output):
    _, out = reported
    assert sorted(p.name for p in out.iterdir()) == ["aggregates.json", "dataset_sizes.png", "learning_curves.png",
                                                     "performance_profile.png", "results.md"]


def test_without_refined_runs_there_is_no_size_figure(tmp_path, capsys):
    for seed in SEEDS:
        write_run(tmp_path / "runs", "door-human-bc", seed, "bc", False, "door", {2000: 1.0, 4000: seed})
    out = tmp_path / "out"
    out.mkdir()
    (out / "dataset_sizes.png").write_bytes(PNG_MAGIC)  # stale, from an earlier report
    assert cli_report.run(args(tmp_path / "runs", out=out)) == 0
    assert sorted(p.name for p in out.iterdir()) == ["aggregates.json", "learning_curves.png", "performance_profile.png",
                                                     "results.md"]
    assert "No run trained on refined data" in (out / "results.md").read_text()
    assert table_rows(capsys.readouterr().out)["door-human"] == ["1.0 ± 1.0 · IQM 1.0 [0.0, 2.0]"]


def test_curve_interpolates_seeds_onto_a_common_grid(reported):
    root, _ = reported
    groups = {(g.dataset, g.method): g for g in group_runs(load_runs([root / "door-human"]))}
    steps, mean, std = groups[("door-human", "BC")].curve()
    # seeds 0, 1 at 2000/4000/6000, seed 2 at 3000/6000: the grid is the union inside [3000, 6000]
    assert steps.tolist() == [3000, 4000, 6000]
    # each seed's curve is f * step / 6000 (f its final score), so linear interpolation is exact
    expected = np.array([-23.4, -20.4, -17.4])[:, None] * (np.array([3000, 4000, 6000]) / 6000)[None, :]
    np.testing.assert_allclose(mean, expected.mean(axis=0), rtol=1e-9)
    np.testing.assert_allclose(std, expected.std(axis=0, ddof=1), rtol=1e-9)
    steps, mean, std = groups[("door-human", "Ours")].curve()
    assert steps.tolist() == list(STEPS)
    assert mean[-1] == pytest.approx(439.5) and std[-1] == pytest.approx(12.0)


def test_read_run_and_scalars(reported):
    root, _ = reported
    run = read_run(root / "door-human" / "door-human-seed0")
    assert (run.dataset, run.method, run.seed, run.final_step) == ("door-human", "Ours", 0, 6000)
    assert run.scalars()["loss_actor"][:, 0].tolist() == [2000, 4000, 6000]
    assert run.steps.tolist() == [2000, 4000, 6000] and run.values[-1] == pytest.approx(427.5)
    assert run.evals["episodes"].tolist() == [10, 10, 10]


# --- discovery -------------------------------------------------------------------------------

def test_discovery_from_parents_run_dirs_and_files(reported):
    root, _ = reported
    everything = find_run_dirs([root])
    assert len(everything) == 30
    door = find_run_dirs([root / "door-human"])
    assert len(door) == 12 and all(p.parent.name == "door-human" for p in door)
    one = root / "door-human" / "door-human-seed1"
    assert find_run_dirs([one]) == [one.resolve()]
    assert find_run_dirs([one / "eval.csv", one, root / "door-human"]) == door  # no duplicates
    assert {r.dataset for r in load_runs([root / "kitchen-partial", one])} == {"kitchen-partial", "door-human"}


def test_run_dirs_are_not_searched_inside(tmp_path):
    run = write_run(tmp_path, "door-human", 0, "iql", True, "door", {6000: 1.0})
    write_run(run / "nested", "door-human", 1, "iql", True, "door", {6000: 1.0})
    assert find_run_dirs([tmp_path]) == [run.resolve()]


# --- errors ----------------------------------------------------------------------------------

def test_error_no_runs(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(RMError, match=r"no training runs found under .*empty .*eval\.csv and recipe\.yaml"):
        cli_report.run(args(tmp_path / "empty", out=tmp_path / "out"))
    assert not (tmp_path / "out").exists()


def test_error_no_runs_names_a_run_without_recipe(tmp_path):
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "eval.csv").write_text(EVAL_HEADER + "\n2000,1,1,1,1,1,10\n")
    with pytest.raises(RMError, match=r"has eval\.csv but no recipe\.yaml"):
        find_run_dirs([tmp_path])


def test_error_missing_path(tmp_path):
    with pytest.raises(RMError, match="nowhere: no such file or directory"):
        find_run_dirs([tmp_path / "nowhere"])


def test_runs_without_evaluations_or_failed_are_left_out_and_named(tmp_path, capsys):
    write_run(tmp_path, "door-human", 0, "iql", True, "door", {6000: 1.0})
    empty = write_run(tmp_path, "door-human", 1, "iql", True, "door", {}, steps=())
    failed = write_run(tmp_path, "door-human", 2, "iql", True, "door", {6000: 99.0})
    (failed / "failed.json").write_text(json.dumps({"step": 7, "message": "step 7: loss_qvalue is NaN or inf"}))
    assert cli_report.run(args(tmp_path, out=tmp_path / "out")) == 0
    err = capsys.readouterr().err
    rel_empty, rel_failed = empty.relative_to(tmp_path), failed.relative_to(tmp_path)
    assert f"run {rel_empty} has no evaluations" in err and f"{rel_failed}: failed: step 7: loss_qvalue" in err
    results = (tmp_path / "out" / "results.md").read_text()
    assert "## Runs left out" in results and f"- {rel_failed}: failed" in results
    assert str(tmp_path) not in results  # a report names runs below its root, not this machine's paths
    assert "99.0" not in results  # a failed run is never a score


def test_error_when_no_run_has_evaluations(tmp_path):
    a = write_run(tmp_path, "door-human", 0, "iql", True, "door", {}, steps=())
    b = write_run(tmp_path, "door-human", 1, "iql", True, "door", {}, steps=())
    with pytest.raises(RMError, match=r"no run has evaluations to report \(2 runs\)") as err:
        load_runs([tmp_path])
    assert str(a) in str(err.value) and str(b) in str(err.value)


@pytest.mark.parametrize("body, problem", [
    (EVAL_HEADER + "\n2000,1.0,oops,1,1,1,10\n", r"eval\.csv, line 2: non-numeric value"),
    (EVAL_HEADER + "\n2000,1.0,1,1\n", r"eval\.csv, line 2: 4 fields, the header has 7"),
    ("when,what\n1,2\n", r"eval\.csv: unexpected header 'when,what'"),
    ("", r"eval\.csv is empty"),
    (b"\xff\xfe\x00garbage", r"eval\.csv is not a readable CSV file"),
])
def test_error_unreadable_csv(tmp_path, body, problem):
    run = write_run(tmp_path, "door-human", 0, "iql", True, "door", {6000: 1.0})
    path = run / "eval.csv"
    path.write_bytes(body) if isinstance(body, bytes) else path.write_text(body)
    with pytest.raises(RMError, match=problem) as err:
        cli_report.run(args(tmp_path, out=tmp_path / "out"))
    assert str(run / "eval.csv") in str(err.value)


def test_an_eval_row_with_nan_episodes_leaves_its_run_out_as_unreadable_and_the_report_goes_on(tmp_path, capsys):
    write_run(tmp_path, "door-human", 0, "iql", True, "door", {6000: 1.0})
    bad = write_run(tmp_path, "door-human", 1, "iql", True, "door", {6000: 2.0})
    (bad / "eval.csv").write_text(EVAL_HEADER + "\n6000,20.0,1.5,2.0,0.5,2.0,nan\n")
    assert cli_report.run(args(tmp_path, out=tmp_path / "out")) == 0
    err = capsys.readouterr().err
    rel = bad.relative_to(tmp_path)
    assert (f"left out {rel}: unreadable: {rel / 'eval.csv'}, line 2: episodes must be a non-negative whole "
            "number, got 'nan'") in err
    results = (tmp_path / "out" / "results.md").read_text()
    assert table_rows(results)["door-human"][0].startswith("1.0 ·") and f"- {rel}: unreadable" in results


@pytest.mark.parametrize("damage", ["recipe", "refine_report", "eval"])
def test_one_unreadable_run_folder_is_left_out_with_a_line_naming_it(tmp_path, capsys, damage):
    write_run(tmp_path, "door-human", 0, "iql", True, "door", {6000: 1.0})
    bad = write_run(tmp_path, "door-human", 1, "iql", True, "door", {6000: 2.0}, stages=STAGES["door-human"])
    {"recipe": lambda: (bad / "recipe.yaml").write_bytes(b"name: caf\xe9\n"),
     "refine_report": lambda: (bad / "refine_report.json").write_text("{"),
     "eval": lambda: (bad / "eval.csv").write_text("when,what\n1,2\n")}[damage]()
    runs = load_runs([tmp_path], skipped=(skipped := []))
    assert [r.seed for r in runs] == [0]
    assert len(skipped) == 1 and skipped[0].startswith(f"{bad.relative_to(tmp_path)}: unreadable: "), skipped


def test_an_unfinished_run_is_left_out_not_reported_with_its_last_evaluation_as_final(tmp_path, capsys):
    """Two seeds whose last evaluation is at step 2,000: one ran its whole budget, the other stopped at 2,000 of
    6,000 (trainer.stop_at, a kill, or still training). Both end at the report's last step, so no dagger marks
    the cell; the unfinished one's evaluation must not count as a final score."""
    write_run(tmp_path, "door-human", 0, "iql", True, "door", {2000: 5.0})
    stopped = write_run(tmp_path, "door-human", 1, "iql", True, "door", {2000: 90.0})
    recipe = (stopped / "recipe.yaml").read_text().replace("steps: 2000", "steps: 6000")
    (stopped / "recipe.yaml").write_text(recipe)
    assert cli_report.run(args(tmp_path, out=tmp_path / "out")) == 0
    rel = stopped.relative_to(tmp_path)
    assert (f"left out {rel}: unfinished: its last evaluation is at step 2,000 of its trainer.steps 6,000"
            in capsys.readouterr().err)
    results = (tmp_path / "out" / "results.md").read_text()
    assert table_rows(results)["door-human"][0].startswith("5.0 ·") and "90.0" not in results
    assert f"- {rel}: unfinished" in results and "unfinished (short of their trainer.steps)" in results
    (tmp_path / "door-human-seed0" / "eval.csv").unlink()  # the finished one gone: nothing left to report
    with pytest.raises(RMError, match=r"unfinished: its last evaluation is at step 2,000"):
        load_runs([tmp_path])


def test_error_bad_recipe(tmp_path):
    run = write_run(tmp_path, "door-human", 0, "iql", True, "door", {6000: 1.0})
    (run / "recipe.yaml").write_text("name: [unclosed\n")
    with pytest.raises(RMError, match=r"recipe\.yaml is not valid YAML"):
        load_runs([tmp_path])


def test_error_same_seed_twice_in_a_cell(tmp_path):
    write_run(tmp_path, "door-human-iql", 0, "iql", False, "door", {6000: 1.0})
    write_run(tmp_path, "door-human-iql-raw", 0, "iql", False, "door", {6000: 2.0})
    with pytest.raises(RMError, match="are both IQL on door-human with seed 0"):
        group_runs(load_runs([tmp_path]))


def test_error_mixed_metrics_in_a_dataset(tmp_path):
    write_run(tmp_path, "door-human", 0, "iql", True, "door", {6000: 1.0})
    write_run(tmp_path, "door-human-bc", 0, "bc", False, "", {6000: 2.0})
    with pytest.raises(RMError, match="runs on door-human measure different things"):
        group_runs(load_runs([tmp_path]))


def test_error_out_is_a_file(reported, tmp_path):
    root, _ = reported
    (tmp_path / "file").write_text("x")
    with pytest.raises(RMError, match="is not a directory"):
        cli_report.run(args(root / "door-human", out=tmp_path / "file"))


def test_parser_defaults_and_exit_code(tmp_path, capsys):
    from rm_torchrl.cli.main import build_parser, main

    parsed = build_parser().parse_args(["report", "a", "b"])
    assert parsed.paths == ["a", "b"] and parsed.out == "reports" and parsed.dataset_from == "name"
    assert main(["report", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "rmrl report: error:" in capsys.readouterr().err


def test_rmrl_report_subcommand(reported, tmp_path, capsys):
    from rm_torchrl.cli.main import main

    root, _ = reported
    assert main(["report", str(root / "relocate-cloned"), "--out", str(tmp_path / "o")]) == 0
    assert table_rows(capsys.readouterr().out)["relocate-cloned"][-1] == "**492.4 ± 8.0** · IQM 492.4 [484.4, 500.4]"
    assert main(["report", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 2


# --- non-finite evaluations and single seeds (issue 19, case 13) ----------------------------

@pytest.mark.slow
def test_one_seed_shows_its_value_alone_never_plus_minus_zero(tmp_path, capsys):
    write_run(tmp_path, "door-human-bc", 0, "bc", False, "door", {6000: 2.0})
    write_run(tmp_path, "door-human", 0, "iql", True, "door", {6000: 5.0})
    assert cli_report.run(args(tmp_path, out=tmp_path / "out")) == 0
    out = capsys.readouterr().out
    assert table_rows(out)["door-human"] == ["2.0 · IQM 2.0 [2.0, 2.0]", "**5.0** · IQM 5.0 [5.0, 5.0]"]  # degenerate CIs
    assert "±" not in out.split("| Dataset |")[1]
    assert "one seed: its value alone" in (tmp_path / "out" / "results.md").read_text()


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_a_nonfinite_final_evaluation_is_left_out_and_named(tmp_path, capsys, bad):
    for seed, value in zip(SEEDS, (4.0, 6.0, float(bad))):
        write_run(tmp_path / "runs", "door-human", seed, "iql", True, "door", {2000: 1.0, 6000: value})
    write_run(tmp_path / "runs", "door-human-bc", 0, "bc", False, "door", {2000: 1.0, 6000: float(bad)})
    assert cli_report.run(args(tmp_path / "runs", out=tmp_path / "out")) == 0
    captured = capsys.readouterr()
    rows = table_rows(captured.out)
    # the two finite seeds: mean 5, sample std 1.4; the BC cell has no finite seed left
    assert rows["door-human"] == ["non-finite ‡", "5.0 ± 1.4 · IQM 5.0 [4.0, 6.0] (n=2) ‡"]
    assert "nan" not in captured.out and "inf" not in captured.out
    for name in ("door-human-seed2", "door-human-bc-seed0"):
        line = f"rmrl report: left out of the statistics: {name}: the final evaluation (step 6,000) has score {bad}"
        assert line in captured.err.splitlines()
    results = (tmp_path / "out" / "results.md").read_text()
    assert "‡ Left out of the statistics" in results and "- door-human-seed2: the final evaluation" in results
    assert (tmp_path / "out" / "learning_curves.png").read_bytes()[:8] == PNG_MAGIC


def test_nonfinite_evaluations_are_missing_points_of_the_curve(tmp_path):
    write_run(tmp_path, "door-human", 0, "iql", True, "door", {2000: 1.0, 4000: float("nan"), 6000: 3.0})
    write_run(tmp_path, "door-human", 1, "iql", True, "door", {2000: 3.0, 4000: 5.0, 6000: float("inf")})
    (group,) = group_runs(load_runs([tmp_path]))
    steps, mean, std = group.curve()
    assert mean.tolist() == [2.0, 5.0, 3.0]
    assert std.tolist() == [pytest.approx(2 ** 0.5), 0.0, 0.0]
    assert group.mean == 3.0 and group.std is None and [r.seed for r in group.nonfinite] == [1]


def test_the_demo_summary_leaves_out_nan_seeds_and_claims_only_what_its_ci_shows(tmp_path):
    from rm_torchrl.launch.demo import summary

    for seed, (ours, iql) in enumerate([(0.2, 0.1), (0.1, 0.2), (float("nan"), 0.1)]):
        write_run(tmp_path, "demo-ours", seed, "ours", True, "door", {20: ours})
        write_run(tmp_path, "demo-iql", seed, "iql", False, "door", {20: iql})
    text = summary(sorted(tmp_path.iterdir()), "door-human-v0")
    assert "nan" not in text.split("Left out")[0]
    assert "Left out (non-finite final evaluation): demo-ours-seed2 (final score nan)." in text
    assert "These seeds do not separate ours from IQL at this budget: P(ours > IQL) = " in text  # 2 against 3 seeds
    assert "over 2 and 3 seeds" in text


@pytest.mark.slow
def test_a_users_folder_with_the_demos_runs_beside_theirs_reports_one_dataset(tmp_path):
    """`rmrl report runs/` over the demo's runs (runs/demo/runs/demo-*) and the user's: the demo's are door-human-v0
    runs (their recipe says so), never a dataset called "demo"; --dataset-from source reads the same."""
    from rm_torchrl.cli.main import main

    source = "/somewhere/rm_torchrl/data/d4rl_files/door-human-v0.hdf5"
    for seed in (0, 1):
        write_run(tmp_path / "runs" / "demo" / "runs", "demo-ours", seed, "ours", True, "door", {2000: 5.0 + seed},
                  source=source, dataset="door-human-v0")
    write_run(tmp_path / "runs", "door-human-v0-ours", 3, "ours", True, "door", {2000: 9.0}, source=source,
              dataset="door-human-v0")
    for extra in ([], ["--dataset-from", "source"]):
        out = tmp_path / f"report{len(extra)}"
        assert main(["report", str(tmp_path / "runs"), "--out", str(out), *extra]) == 0
        text = (out / "results.md").read_text()
        assert "| door-human-v0 |" in text and "| demo" not in text
