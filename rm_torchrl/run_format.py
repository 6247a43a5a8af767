"""The run-directory format: what the trainer writes and ``rmrl report`` reads, in one place.

A run directory ``OUT/<name>-seed<k>/`` holds :data:`RECIPE_FILE` (the resolved recipe),
:data:`EVAL_FILE` (one row of :data:`EVAL_COLUMNS` per evaluation), :data:`REFINE_FILE` when the
data was refined (its stages are Table 2's rows, :data:`TABLE2_ROWS`), TorchRL logger output
under :data:`LOGS_DIR`, :data:`CHECKPOINT`, :data:`FAILED_FILE` when a non-finite loss stopped it,
and the lock of the process that owns it.
"""

RECIPE_FILE = "recipe.yaml"
EVAL_FILE = "eval.csv"
REFINE_FILE = "refine_report.json"
LOGS_DIR = "logs"  # TorchRL logger experiment; CSV scalars in logs/scalars/<name>.csv
CHECKPOINT = "checkpoint.pt"
CHECKPOINT_TMP = "checkpoint.tmp"  # a checkpoint being written (renamed over CHECKPOINT when complete)
FAILED_FILE = "failed.json"
LOCK_FILE = ".lock"


def temp_name(name: str) -> str:
    """The file a trainer's file ``name`` is written to before it is renamed over ``name``."""
    return CHECKPOINT_TMP if name == CHECKPOINT else f".{name}.tmp"


TRAINER_FILES = (RECIPE_FILE, EVAL_FILE, REFINE_FILE, LOGS_DIR, CHECKPOINT, FAILED_FILE, LOCK_FILE,
                 *(temp_name(n) for n in (RECIPE_FILE, EVAL_FILE, REFINE_FILE, CHECKPOINT, FAILED_FILE)))

#: ``reward`` names the reward convention of the returns: ``d4rl`` or ``env`` (the evaluation env's own).
EVAL_COLUMNS = ("step", "return_mean", "return_std", "score", "success_rate", "events_mean", "episodes", "reward")
REWARD_COLUMN = "reward"  # the one text column of eval.csv
#: What a run written before eval.csv had a reward column was evaluated with: the env's own reward.
LEGACY_REWARD = "env"

#: The refinement stages of ``refine_report.json``, as the paper's Table 2 labels its rows, in its order;
#: ``reused`` (beyond the paper: the rows after splicing with the abandoned pieces brought back) is there
#: only when the reuse stage ran.
TABLE2_ROWS = {"original": "Original Dataset", "split": "Splitting Traj.", "ordered": "Ordered Events",
               "reused": "Reused Sub-traj.", "shorter": "Shorter Traj."}
REUSED = "reused"
#: The stages every report has (the paper's Table 2).
STAGES = tuple(k for k in TABLE2_ROWS if k != REUSED)


def stage_rows(reports) -> list[str]:
    """The Table 2 rows of ``reports`` (each a ``stages`` mapping): the paper's, and ``reused`` if one has it."""
    reports = list(reports)
    return [k for k in TABLE2_ROWS if k != REUSED or any(REUSED in r for r in reports)]
