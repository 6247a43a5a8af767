"""Recipes as Hydra composes them, checked against the schema of :mod:`rm_torchrl.train.config`.

``recipes/train.yaml`` composes ``dataset=<name>`` (``recipes/dataset/``) with ``method=<name>``
(``recipes/method/``); a named recipe such as ``recipes/door-human-v0-ours.yaml`` is the same
composition in a file, and a run's own ``recipe.yaml`` (fully resolved) loads as it is. Overrides
use Hydra's grammar (``optim.weight_decay_q=1e-3``, ``method=iql``); a value override of a key the
recipe does not spell out is accepted as long as the schema has it.

    >>> recipe = load_recipe(None, ["dataset=door-human-v0", "method=ours", "seed=1"])
    >>> recipe.run_dir.as_posix()
    'runs/door-human-v0-ours-seed1'
"""
from __future__ import annotations

import dataclasses
import math
import os
import re
from pathlib import Path

import yaml
from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException

from rm_torchrl.data.embedded import embedded_file
from rm_torchrl.envs.d4rl_reward import V1_ENVS, d4rl_reward_task
from rm_torchrl.errors import RMError, read_yaml, too_deep, yaml_problem
from rm_torchrl.methods.ours import temperature_for
from rm_torchrl.refine.shortest import check_alpha
from rm_torchrl.run_format import run_label, upgrade_recipe
from rm_torchrl.train.config import CHOICES, DEVICES, INTERVALS, Recipe, check_seed
from rm_torchrl.train.device import DEVICE_NAME
from rm_torchrl.train.recipes_root import RECIPES


SCHEMA = "rmrl_schema"  # a recipe's defaults list starts with it to get typed, complete sections
#: Top-level entries that are values, not config groups (``dataset`` and ``method`` are groups).
_VALUE_KEYS = tuple(f.name for f in dataclasses.fields(Recipe) if f.name != "method")

ConfigStore.instance().store(name=SCHEMA, node=Recipe)
#: ``${recipes_dir:}``: the recipes folder, for dataset options whose files lie beside the checkout.
OmegaConf.register_new_resolver("recipes_dir", lambda: str(RECIPES), replace=True)
#: ``${embedded:door-human-v0.hdf5}``: a data file shipped inside the package (works from any directory).
OmegaConf.register_new_resolver("embedded", lambda name: str(embedded_file(name)), replace=True)
#: ``${run_label:${method.name},${method.hparams},${data.refine}}``: the run's short name (``ours``, ``iql``,
#: ``iql-ours-none``), the default ``name`` after the dataset's.
OmegaConf.register_new_resolver("run_label", run_label, replace=True)


def scaled_to_budget(rate, reference_steps, steps) -> float:
    """``rate`` for a run of up to ``reference_steps`` updates, ``rate * reference_steps / steps`` for a longer
    one: the summed learning rate over the run stays the reference run's (``${scaled_to_budget:3e-4,50000,
    ${trainer.steps}}``: ours' actor memorises its few thousand refined transitions when 500k updates run at
    the 50k budget's rate)."""
    try:
        rate, reference_steps, steps = float(rate), int(reference_steps), int(steps)
    except (TypeError, ValueError):
        raise RMError(f"scaled_to_budget takes a rate and two step counts, got {rate!r}, {reference_steps!r}, "
                      f"{steps!r}") from None
    if reference_steps <= 0 or steps <= 0:
        raise RMError(f"scaled_to_budget: the reference steps and trainer.steps must be positive, got "
                      f"{reference_steps} and {steps}")
    return float(f"{rate * min(1.0, reference_steps / steps):.12g}")  # 3e-05, not 2.9999999999999997e-05


OmegaConf.register_new_resolver("scaled_to_budget", scaled_to_budget, replace=True)
#: ``${ours_temperature:${data.name}}``: ours' inverse temperature for the dataset (rm_torchrl.methods.ours)
OmegaConf.register_new_resolver("ours_temperature", temperature_for, replace=True)


def hydra_overrides(overrides, path=None) -> list[str]:
    """The overrides for Hydra. A plain recipe file (a run's ``recipe.yaml``: no defaults list, so no
    schema during composition) gets value overrides as ``++key=value``, set whether or not the file
    spells the key out; the schema refuses unknown keys afterwards. Group choices (``method=iql``),
    ``hydra`` settings and overrides that carry ``+``/``~`` pass as they are.
    """
    plain = path is not None and "defaults" not in (read_yaml(recipe_path(path), "recipe") or {})
    out = []
    for item in overrides:
        key = item.split("=", 1)[0]
        if "=" not in item or not key.strip():
            raise RMError(f"overrides look like key.sub=value, got {item!r}")
        value = not key.startswith(("+", "~", "hydra")) and "/" not in key and ("." in key or key in _VALUE_KEYS)
        out.append(f"++{item}" if plain and value else item)
    return out


def recipe_path(path) -> Path:
    """The primary recipe file (``recipes/train.yaml`` for the ``dataset=... method=...`` form)."""
    path = Path(path) if path else RECIPES / "train.yaml"
    if path.suffix not in (".yaml", ".yml"):
        raise RMError(f"a recipe is a .yaml file, got {str(path)!r}")
    if not path.is_file():
        raise RMError(f"recipe {path} does not exist")
    return path.resolve()


def search_path_override() -> str:
    return f"hydra.searchpath=[file://{RECIPES}]"


def compose_recipe(path=None, overrides=()) -> DictConfig:
    """Hydra's composition of the recipe at ``path`` with ``overrides`` (not yet checked)."""
    path = recipe_path(path)
    try:
        with initialize_config_dir(config_dir=str(path.parent), version_base="1.3", job_name="rmrl"):
            return compose(config_name=path.name, overrides=[*hydra_overrides(overrides, path), search_path_override()])
    except (HydraException, OmegaConfBaseException) as err:
        unknown = re.match(r"Could not override '([^']+)'", str(err))
        if unknown and _allowed(unknown.group(1)) is not None:
            key = unknown.group(1)
            raise RMError(f"recipe: unknown key {key}; allowed under {key.rpartition('.')[0] or 'top level'}: "
                          f"{_allowed(key)}") from None
        plain = next((o for o in overrides if not str(o).isascii() and "'" not in str(o) and '"' not in str(o)), None)
        if "LexerNoViableAlt" in str(err) and plain:
            key, _, value = str(plain).partition("=")
            raise RMError(f"override {plain!r}: Hydra reads unquoted values as ASCII; quote the value, as in "
                          f"\"{key}='{value}'\"") from None
        raise RMError(f"recipe {path.name}: {_one_line(err)}") from None
    except yaml.YAMLError as err:  # in the recipe or in one of the options it composes
        raise RMError(f"recipe {path.name} (or an option it composes) is not valid YAML: {yaml_problem(err)}") from None
    except RecursionError:  # OmegaConf recurses deeper per level than PyYAML, which read_yaml guards
        raise too_deep("recipe", path) from None


def split_recipe_args(items: list[str]) -> tuple[str | None, list[str]]:
    """``[RECIPE.yaml] key=value ...`` (the arguments of ``rmrl train``) -> (recipe or None, overrides)."""
    if items and "=" not in items[0]:
        return items[0], list(items[1:])
    stray = [a for a in items if "=" not in a]
    if stray:
        raise RMError(f"expected key=value overrides after the recipe, got {stray}")
    return None, list(items)


def load_recipe(path=None, overrides=()) -> Recipe:
    """The checked recipe at ``path`` (default ``recipes/train.yaml``) with ``overrides`` applied.

    Relative ``data.source`` and ``data.events`` files are found from the recipe's folder, so that
    a run's ``recipe.yaml`` (with absolute paths) works from anywhere.
    """
    return build_recipe(compose_recipe(path, overrides), recipe_path(path).parent)


def build_recipe(cfg: DictConfig, base: Path) -> Recipe:
    """A composed config checked against the schema: typed sections, valid choices, finite numbers."""
    raw = upgrade_recipe(OmegaConf.to_container(cfg, resolve=False))
    raw.pop("hydra", None)
    _check_bools(raw)
    try:
        recipe = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(Recipe), raw))
    except OmegaConfBaseException as err:
        raise RMError(f"recipe: {_schema_message(err)}") from None
    for attr in ("source", "events"):
        value = getattr(recipe.data, attr)
        if Path(value).suffix in (".hdf5", ".h5", ".yaml", ".yml"):
            setattr(recipe.data, attr, os.path.abspath(Path(base) / value))  # normalised where absolute
    validate(recipe)
    return recipe


def _check_bools(raw: dict, node=Recipe, prefix: str = "") -> None:
    """Refuses a boolean entry given as anything but true or false: the schema would read "yes", "on"
    or 1 as true. Interpolations (``${...}``) are left to the schema."""
    for f in dataclasses.fields(node):
        value = raw.get(f.name) if isinstance(raw, dict) else None
        if value is None:
            continue
        if dataclasses.is_dataclass(f.default_factory):
            _check_bools(value, f.default_factory, f"{prefix}{f.name}.")
        elif f.type in ("bool", bool) and not isinstance(value, bool) and not (isinstance(value, str) and "${" in value):
            raise RMError(f"recipe: {prefix}{f.name} must be true or false, got {value!r}")


def _allowed(key: str) -> list[str] | None:
    """The schema's entries beside ``key`` (a dotted path whose last part may not exist), or None."""
    node = Recipe
    for part in key.split(".")[:-1]:
        fields = {f.name: f for f in dataclasses.fields(node)}
        if part not in fields or not isinstance(fields[part].default_factory, type):
            return None
        node = fields[part].default_factory
    return sorted(f.name for f in dataclasses.fields(node))


def _one_line(err: Exception) -> str:
    text = str(err)
    if "Available options in" in text:  # Hydra lists a group's options one per line: keep them, on one line
        head, _, options = text.partition("Available options in")
        group, _, names = options.partition(":")
        names = names.split("Config search path")[0]  # the search path Hydra appends
        return f"{head.strip()}; available options in{group}: {', '.join(names.split())}"
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    cause = err.__cause__
    if cause is not None and str(cause).strip():
        lines.append(str(cause).strip().splitlines()[0])
    return "; ".join(lines[:2]) or type(err).__name__


def _schema_message(err: OmegaConfBaseException) -> str:
    key = getattr(err, "full_key", None) or "?"
    if isinstance(err, ConfigKeyError) and getattr(err, "object_type", None) is not None:
        allowed = sorted(f.name for f in dataclasses.fields(err.object_type))
        parent = key.rpartition(".")[0] or "top level"
        return f"unknown key {key}; allowed under {parent}: {allowed}"
    message = str(getattr(err, "msg", err)).strip().splitlines()[0]
    return f"{key}: {message}"


def _floats(node, prefix: str = ""):
    for f in dataclasses.fields(node):
        value = getattr(node, f.name)
        if dataclasses.is_dataclass(value):
            yield from _floats(value, f"{prefix}{f.name}.")
        elif isinstance(value, float):
            yield prefix + f.name, value


def _lookup(recipe: Recipe, dotted: str):
    node = recipe
    for part in dotted.split("."):
        node = getattr(node, part)
    return node


def _inside(value: float, interval: str) -> bool:
    """Whether ``value`` lies in ``interval``, written as in :data:`~rm_torchrl.train.config.INTERVALS`."""
    low, high = (float(end) for end in interval[1:-1].split(","))
    above = low < value if interval[0] == "(" else low <= value
    below = value < high if interval[-1] == ")" else value <= high
    return above and below


def validate(recipe: Recipe) -> None:
    """Checks across fields that the types alone do not catch."""
    for key, value in _floats(recipe):
        if not math.isfinite(value):
            raise RMError(f"recipe: {key} must be a finite number, got {value!r}")
    check_seed(recipe.seed, "recipe: seed")
    if str(recipe.data.refine).lower() in ("true", "false"):
        raise RMError(f"recipe: data.refine is none | paper | reuse (true was paper, false none), got {recipe.data.refine!r}")
    for key, choices in CHOICES.items():
        if _lookup(recipe, key) not in choices:
            raise RMError(f"recipe: {key} must be one of {list(choices)}, got {_lookup(recipe, key)!r}")
    if recipe.method.hparams == "ours" and recipe.method.name != "iql":
        raise RMError(f"recipe: method.hparams=ours names ours' IQL settings (method=ours); {recipe.method.name} has only "
                      "its published ones")
    if not recipe.data.source:
        raise RMError("recipe: data.source is required")
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._=+-]*", recipe.name) or ".." in recipe.name:
        raise RMError(f"recipe: name must be a plain directory name (letters, digits, . _ - = +), got {recipe.name!r}")
    if not 0 <= recipe.trainer.stop_at <= recipe.trainer.steps:
        raise RMError(f"recipe: trainer.stop_at must lie in [0, trainer.steps={recipe.trainer.steps}] (0: run to the "
                      f"end), got {recipe.trainer.stop_at}")
    if recipe.trainer.threads < 0:
        raise RMError(f"recipe: trainer.threads must be >= 0 (0: the idle cores), got {recipe.trainer.threads}")
    if not DEVICE_NAME.fullmatch(recipe.trainer.device):
        raise RMError(f"recipe: trainer.device must be {DEVICES}, got {recipe.trainer.device!r}")
    if recipe.data.refined:
        if not recipe.data.events:
            raise RMError(f"recipe: data.events is required when data.refine is {recipe.data.refine}")
        check_alpha(recipe.data.alpha)
    positive = {
        "trainer.steps": recipe.trainer.steps, "trainer.batch_size": recipe.trainer.batch_size,
        "trainer.log_every": recipe.trainer.log_every, "trainer.checkpoint_every": recipe.trainer.checkpoint_every,
        "eval.every": recipe.eval.every, "eval.episodes": recipe.eval.episodes, "eval.max_steps": recipe.eval.max_steps,
        "method.cql.num_random": recipe.method.cql.num_random,
    }
    for key, value in positive.items():
        if value <= 0:
            raise RMError(f"recipe: {key} must be positive, got {value}")
    for key, interval in INTERVALS.items():
        if not _inside(_lookup(recipe, key), interval):
            raise RMError(f"recipe: {key} must lie in {interval}, got {_lookup(recipe, key)}")
    for key, hidden in (("network.hidden", recipe.network.hidden), ("method.bcq.vae_hidden", recipe.method.bcq.vae_hidden)):
        if not hidden or not all(h > 0 for h in hidden):
            raise RMError(f"recipe: {key} must be a list of positive ints, got {hidden}")
    for key in ("lr_actor", "lr_critic", "lr_value"):
        if getattr(recipe.optim, key) <= 0:
            raise RMError(f"recipe: optim.{key} must be positive")
    for key in ("weight_decay_q", "weight_decay_pi"):
        if getattr(recipe.optim, key) < 0:
            raise RMError(f"recipe: optim.{key} must be >= 0")
    if recipe.eval.env and recipe.eval.reward == "d4rl":
        if d4rl_reward_task(recipe.eval.env, recipe.eval.env_kwargs) is None:
            raise RMError(f"recipe: eval.reward=d4rl needs a dense v1 env with a known correction "
                          f"({sorted(V1_ENVS)}), got eval.env={recipe.eval.env!r}; use auto or env")

