"""The run-directory format: what the trainer writes and ``rmrl report`` reads, in one place.

A run directory ``OUT/<name>-seed<k>/`` holds :data:`RECIPE_FILE` (the resolved recipe),
:data:`EVAL_FILE` (one row of :data:`EVAL_COLUMNS` per evaluation), :data:`REFINE_FILE` when the
data was refined (its stages are Table 2's rows, :data:`TABLE2_ROWS`), TorchRL logger output
under :data:`LOGS_DIR`, :data:`CHECKPOINT`, :data:`FAILED_FILE` when a non-finite loss stopped it,
:data:`DATA_FILE` (what the data file was when the run began, so a resume on a replaced file is refused)
and the lock of the process that owns it.
"""
from rm_torchrl import files

RECIPE_FILE = "recipe.yaml"
EVAL_FILE = "eval.csv"
REFINE_FILE = "refine_report.json"
LOGS_DIR = "logs"  # TorchRL logger experiment; CSV scalars in logs/scalars/<name>.csv
CHECKPOINT = "checkpoint.pt"
CHECKPOINT_TMP = "checkpoint.tmp"  # a checkpoint being written (renamed over CHECKPOINT when complete)
FAILED_FILE = "failed.json"
DATA_FILE = "data_file.json"
LOCK_FILE = ".lock"


def temp_name(name: str) -> str:
    """The file a trainer's file ``name`` is written to before it is renamed over ``name``."""
    return CHECKPOINT_TMP if name == CHECKPOINT else files.temp_name(name)


TRAINER_FILES = (RECIPE_FILE, EVAL_FILE, REFINE_FILE, LOGS_DIR, CHECKPOINT, FAILED_FILE, DATA_FILE, LOCK_FILE,
                 *(temp_name(n) for n in (RECIPE_FILE, EVAL_FILE, REFINE_FILE, CHECKPOINT, FAILED_FILE, DATA_FILE)))

#: ``reward`` names the reward convention of the returns: ``d4rl`` or ``env`` (the evaluation env's own).
#: Run statuses a multirun leaves alone, and why (``new`` and ``resumable`` runs train, ``finished`` ones are
#: skipped): :func:`rm_torchrl.train.rundir.run_status`.
LEFT_ALONE = {"failed": "failed before (see failed.json): not retried",
              "kept": "with evaluations but no checkpoint: kept, not retrained",
              "unreadable": "with a checkpoint that cannot be read: left as it is"}
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


# --- what a run is: algorithm, settings, data treatment, dataset -------------------------------

#: ``data.refine``: ``none`` (the raw data), ``paper`` (the paper's refinement), ``reuse`` (the paper's, then
#: the sub-trajectories the splice abandons brought back: beyond the paper).
REFINE = ("none", "paper", "reuse")
#: ``method.hparams``: whose settings the values are: the algorithm's authors' published ones, or ours'
#: (rm_torchrl.methods.ours: each value and the choice that set it, recorded as rm_torchrl.report.choices reads).
HPARAMS = ("published", "ours")
#: The method options that are a preset (algorithm, settings, refinement) rather than an algorithm.
PRESETS = {("iql", "ours", "paper"): "ours", ("iql", "ours", "reuse"): "ours-reuse"}
#: Display labels of the presets and algorithms (the paper's Table 1 columns).
DISPLAY = {"ours": "Ours", "ours-reuse": "ours-reuse", "iql": "IQL", "bc": "BC", "cql": "CQL", "bcq": "BCQ"}
#: Method entries of recipes written before the method section had one sub-section per algorithm.
_RENAMED = {"expectile": ("iql", "expectile"), "temperature": ("iql", "temperature"),
            "actor_dropout": ("iql", "actor_dropout"), "cql_alpha": ("cql", "min_q_weight"),
            "bcq_lambda": ("bcq", "lmbda"), "bcq_phi": ("bcq", "phi"), "bcq_vae_hidden": ("bcq", "vae_hidden")}


def upgrade_recipe(raw: dict) -> dict:
    """A recipe of any earlier layout in today's, in place (same values, same experiment).

    Before ``data.refine`` named the treatment it was a boolean beside ``data.reuse``, and the method
    name carried it: ``ours`` / ``ours-reuse`` were IQL with ours' settings on refined data (and older
    still, ``iql`` with ``refine: true`` was that method). ``method.hparams`` absent: the published settings,
    except for those presets. ``method.bc`` absent on a BC run: the Gaussian-likelihood BC it was then.
    A ``data.refine`` of today's (a string: an override such as ``data.refine=none`` on an old run's recipe)
    says the treatment, whatever the old entries beside it say.
    """
    method, data = raw.get("method"), raw.get("data")
    if not isinstance(method, dict) or not isinstance(data, dict):
        return raw
    if any(k in method for k in _RENAMED):
        for old, (section, new) in _RENAMED.items():
            if old in method:
                method.setdefault(section, {})[new] = method.pop(old)
    name, refine = method.get("name", "iql"), data.get("refine")
    # a boolean is the old layout's, unless the recipe is today's otherwise (method.hparams and no data.reuse):
    # then a user wrote true/false, which validation refuses with the hint of today's values
    old = isinstance(refine, bool) and ("reuse" in data or "hparams" not in method)
    if old or "reuse" in data:
        reuse = bool(data.pop("reuse", False))
        if old:
            if name == "iql" and refine and "hparams" not in method:
                name = "ours"  # IQL on refined data was the paper's method before it had a name
            data["refine"] = ("reuse" if reuse else "paper") if refine else "none"
        elif reuse and refine in ("paper", "reuse"):  # data.reuse=true beside today's value (an old run's recipe)
            data["refine"] = "reuse"
    if name in ("ours", "ours-reuse"):
        method["name"] = "iql"
        method.setdefault("hparams", "ours")
        if "refine" not in data:  # a value of today's (data.refine=none on an old run's recipe) stays as it is
            data["refine"] = "reuse" if name == "ours-reuse" else "paper"
    method.setdefault("hparams", "published")
    if method.get("name") == "bc" and "bc" not in method:
        method["bc"] = {"loss": "nll"}
    return raw


def run_identity(recipe: dict) -> tuple[str, str, str]:
    """(algorithm, hparams, refine) of a run's recipe, of any layout."""
    raw = upgrade_recipe({"method": dict(recipe.get("method") or {}), "data": dict(recipe.get("data") or {})})
    return str(raw["method"].get("name", "iql")), str(raw["method"]["hparams"]), str(raw["data"].get("refine", "none"))


def run_label(algorithm: str, hparams: str, refine: str) -> str:
    """The run's short name: a preset's (``ours``, ``ours-reuse``), the algorithm's on raw data with its
    published settings (``iql``, ``bc``), else all three (``iql-ours-none``, ``bc-published-paper``)."""
    if (algorithm, hparams, refine) in PRESETS:
        return PRESETS[algorithm, hparams, refine]
    if hparams == "published" and refine == "none":
        return algorithm
    return f"{algorithm}-{hparams}-{refine}"


def display_label(algorithm: str, hparams: str, refine: str) -> str:
    """How tables name the run: ``Ours``, ``ours-reuse``, ``IQL``, ``BC``, else the algorithm with what
    differs from its published form on raw data: ``IQL (ours' settings)``, ``BC (refined)``, ``IQL (refined, reuse)``."""
    label = run_label(algorithm, hparams, refine)
    if label in DISPLAY:
        return DISPLAY[label]
    parts = (["ours' settings"] if hparams == "ours" else []) + (
        ["refined"] if refine == "paper" else ["refined, reuse"] if refine == "reuse" else [])
    return f"{DISPLAY.get(algorithm, algorithm.upper())} ({', '.join(parts)})"


#: Local Minari ids of the datasets ``rmrl generate`` makes (its default ``--out-name`` namespace).
GENERATED_PREFIX = "rmrl/"


def data_origin(recipe: dict) -> str:
    """``generated`` for a stand-in made by ``rmrl generate`` (a local Minari ``rmrl/...`` dataset, or a
    dataset option named ``rmrl-...``), else ``d4rl`` (a D4RL file, or a Minari download)."""
    data = recipe.get("data") or {}
    source, name = str(data.get("source") or ""), str(data.get("name") or "")
    return "generated" if source.startswith(GENERATED_PREFIX) or name.startswith("rmrl-") else "d4rl"


def flat_recipe(recipe: dict, prefix: str = "") -> dict:
    """A recipe dict as ``dotted.key -> value`` (an empty section stays one entry)."""
    out = {}
    for key, value in recipe.items():
        path = f"{prefix}{key}"
        out.update(flat_recipe(value, path + ".") if isinstance(value, dict) and value else {path: value})
    return out


#: Recipe entries that decide what a run learns (beside its seed): runs of one report cell should share them.
LEARNING_KEYS = ("data.source", "data.episode_ends", "data.refine", "data.events", "data.alpha", "data.constraints",
                 "rm", "method", "network", "optim", "trainer.batch_size", "trainer.gamma", "trainer.tau",
                 "trainer.normalize_obs")


def learning_differences(recipes: list[dict]) -> list[str]:
    """``key (v1, v2)`` for each of :data:`LEARNING_KEYS` on which ``recipes`` differ."""
    flats = [flat_recipe(upgrade_recipe(r)) for r in recipes]
    for f in flats:  # the same file read from two checkouts (an embedded file, ../shared) is the same data
        if isinstance(f.get("data.source"), str):
            f["data.source"] = f["data.source"].replace("\\", "/").rsplit("/", 1)[-1]
    algorithms = {f.get("method.name") for f in flats}
    keys = sorted({k for f in flats for k in f if any(k == p or k.startswith(p + ".") for p in LEARNING_KEYS)
                   and all(k in g for g in flats)  # an entry an older layout lacks took the default it now names
                   and not (k.count(".") >= 2 and k.startswith("method.") and k.split(".")[1] not in algorithms)})
    out = []
    for key in keys:
        values = list(dict.fromkeys(repr(f.get(key)) for f in flats))
        if len(values) > 1:
            out.append(f"{key} ({', '.join(values)})")
    return out

