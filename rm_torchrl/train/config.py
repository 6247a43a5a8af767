"""Training recipes: one YAML per dataset x method, validated into dataclasses, with overrides.

Every hyper-parameter of a run lives in its recipe; ``key.sub=value`` overrides on the command
line (Hydra style) change any of them, and unknown keys or ill-typed values are refused with the
path of the offending entry.
"""
from __future__ import annotations

import dataclasses
import math
import os
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rm_torchrl.errors import RMError, read_yaml, yaml_problem

METHODS = ("iql", "bc", "cql", "bcq")
ACTORS = ("tanh_normal", "gaussian")  # network.actor: see rm_torchrl.train.networks.make_actor


@dataclass
class DataConfig:
    source: str = ""  # .hdf5 path, minari:<id> or a local Minari name
    episode_ends: str = "auto"
    refine: bool = True  # the paper's method; False trains on the raw data (baselines)
    events: str = ""  # event spec, also used online by the RM env transform
    alpha: float = 1.0
    constraints: list = field(default_factory=list)


@dataclass
class RMConfig:
    encoding: str = "one_hot"  # what the policy sees of the RM state: one_hot | slots


@dataclass
class MethodConfig:
    name: str = "iql"
    expectile: float = 0.7  # IQL tau
    temperature: float = 0.5  # IQL inverse temperature beta
    cql_alpha: float = 5.0  # CQL min-Q weight (Kumar et al. 2020, Adroit/kitchen)
    bcq_lambda: float = 0.75  # BCQ soft clipped double-Q
    bcq_phi: float = 0.05  # BCQ perturbation range
    bcq_vae_hidden: list = field(default_factory=lambda: [750, 750])  # BCQ's VAE
    actor_dropout: float = 0.1  # IQL's actor dropout on Adroit and kitchen


@dataclass
class NetworkConfig:
    hidden: list = field(default_factory=lambda: [256, 256])
    actor: str = "tanh_normal"  # tanh_normal | gaussian (tanh mean, state-independent std: the IQL authors')


@dataclass
class OptimConfig:
    lr_actor: float = 3e-4
    lr_critic: float = 3e-4
    lr_value: float = 3e-4
    weight_decay_q: float = 1e-4  # lambda_Q of eq. 7, on the Q and value networks
    weight_decay_pi: float = 1e-4  # lambda_pi of eq. 8, on the policy
    decay: str = "l2"  # l2: the paper's penalty lambda*||w||^2 (Adam weight_decay = 2 lambda); decoupled: AdamW
    fused: bool = True
    actor_schedule: str = "constant"  # constant | cosine: the actor's lr annealed to 0 over trainer.steps (IQL authors, CORL)


@dataclass
class TrainerConfig:
    steps: int = 500_000
    batch_size: int = 256
    gamma: float = 0.99
    tau: float = 0.005
    normalize_obs: bool = True
    log_every: int = 1000
    checkpoint_every: int = 50_000
    threads: int = 0  # 0: all cores
    compile: bool = False  # torch.compile the loss: ~25% more updates/s on CPU, after ~10 s of compilation
    flush_denormal: bool = True  # subnormal floats as 0 on CPU: without it updates slow 4-5x within 3k steps


@dataclass
class EvalConfig:
    env: str = ""  # gymnasium id, empty for no online evaluation
    env_kwargs: dict = field(default_factory=dict)
    observation: str = "flat"  # flat | kitchen-v0 (rebuild the D4RL v0 60-dim observation)
    max_steps: int = 200
    every: int = 2000
    episodes: int = 10
    score: str = ""  # door | relocate | kitchen: the D4RL normalisation of the return
    reward: str = "auto"  # auto: D4RL's reward where the v1 env's differs (door, relocate), else the env's | d4rl | env


@dataclass
class LoggerConfig:
    backend: str = "csv"  # csv | tensorboard | wandb
    project: str = "rm_torchrl"


@dataclass
class Recipe:
    name: str = "run"
    seed: int = 0
    out: str = "runs"
    resume: bool = False
    data: DataConfig = field(default_factory=DataConfig)
    rm: RMConfig = field(default_factory=RMConfig)
    method: MethodConfig = field(default_factory=MethodConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)

    @property
    def run_dir(self) -> Path:
        return Path(self.out) / f"{self.name}-seed{self.seed}"

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


#: Numbers PyYAML (YAML 1.1) reads as strings, such as ``1e-3``: a float field takes them as floats.
_FLOAT = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+$")

_CHOICES = {
    "data.episode_ends": ("auto", "terminals", "timeouts", "both"),
    "rm.encoding": ("one_hot", "slots"),
    "method.name": METHODS,
    "optim.decay": ("l2", "decoupled"),
    "optim.actor_schedule": ("constant", "cosine"),
    "network.actor": ACTORS,
    "eval.reward": ("auto", "d4rl", "env"),
    "eval.observation": ("flat", "kitchen-v0"),
    "eval.score": ("", "door", "relocate", "kitchen"),
    "logger.backend": ("csv", "tensorboard", "wandb"),
}


def _convert(value: Any, kind, path: str):
    if dataclasses.is_dataclass(kind):
        if not isinstance(value, dict):
            raise RMError(f"recipe: {path} must be a mapping, got {value!r}")
        return _build(kind, value, path + ".")
    origin = typing.get_origin(kind) or kind
    if origin is bool:
        if isinstance(value, bool):
            return value
    elif origin is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif origin is float:
        if isinstance(value, str) and _FLOAT.match(value.strip()):
            value = float(value)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):
                raise RMError(f"recipe: {path} must be a finite number, got {value!r}")
            return float(value)
    elif origin is str:
        if isinstance(value, str):
            return value
    elif origin is list:
        if isinstance(value, list):
            return value
    elif origin is dict:
        if isinstance(value, dict):
            return value
    raise RMError(f"recipe: {path} must be of type {getattr(origin, '__name__', origin)}, got {value!r}")


def _build(cls, data: dict, prefix: str = ""):
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise RMError(f"recipe: unknown key(s) {[prefix + u for u in unknown]}; allowed under {prefix or 'top level'}: {sorted(names)}")
    values = {}
    for name, value in data.items():
        path = prefix + name
        values[name] = _convert(value, hints[name], path)
        if path in _CHOICES and values[name] not in _CHOICES[path]:
            raise RMError(f"recipe: {path} must be one of {list(_CHOICES[path])}, got {value!r}")
    return cls(**values)


def _set_path(data: dict, dotted: str, value) -> None:
    *parents, leaf = dotted.split(".")
    node = data
    for p in parents:
        node = node.setdefault(p, {})
        if not isinstance(node, dict):
            raise RMError(f"override {dotted}: {p} is not a section")
    node[leaf] = value


def parse_override(text: str) -> tuple[str, Any]:
    """``trainer.steps=2000`` -> ("trainer.steps", 2000); values are read as YAML scalars."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise RMError(f"overrides look like key.sub=value, got {text!r}")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError as err:
        raise RMError(f"override {text!r}: {yaml_problem(err)}") from None
    return key.strip(), value


def load_recipe(path: str | Path, overrides: list[str] = ()) -> Recipe:
    """The recipe at ``path`` with ``overrides`` applied; data and event files are resolved next to it."""
    path = Path(path)
    data = read_yaml(path, "recipe") or {}
    if not isinstance(data, dict):
        raise RMError(f"recipe {path} must be a mapping")
    data.setdefault("name", path.stem)
    for item in overrides:
        _set_path(data, *parse_override(item))
    recipe = _build(Recipe, data)
    for attr in ("source", "events"):
        value = getattr(recipe.data, attr)
        if Path(value).suffix in (".hdf5", ".h5", ".yaml", ".yml") and not Path(value).is_absolute():
            setattr(recipe.data, attr, os.path.abspath(path.parent / value))  # a run's recipe.yaml works from anywhere
    validate(recipe)
    return recipe


def validate(recipe: Recipe) -> None:
    """Checks across fields that the types alone do not catch."""
    from rm_torchrl.refine.shortest import check_alpha

    if not recipe.data.source:
        raise RMError("recipe: data.source is required")
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._=+-]*", recipe.name) or ".." in recipe.name:
        raise RMError(f"recipe: name must be a plain directory name (letters, digits, . _ - = +), got {recipe.name!r}")
    if recipe.trainer.threads < 0:
        raise RMError(f"recipe: trainer.threads must be >= 0 (0: all cores), got {recipe.trainer.threads}")
    if recipe.data.refine:
        if not recipe.data.events:
            raise RMError("recipe: data.events is required when data.refine is true")
        check_alpha(recipe.data.alpha)
    positive = {
        "trainer.steps": recipe.trainer.steps, "trainer.batch_size": recipe.trainer.batch_size,
        "trainer.log_every": recipe.trainer.log_every, "trainer.checkpoint_every": recipe.trainer.checkpoint_every,
        "eval.every": recipe.eval.every, "eval.episodes": recipe.eval.episodes, "eval.max_steps": recipe.eval.max_steps,
    }
    for key, value in positive.items():
        if value <= 0:
            raise RMError(f"recipe: {key} must be positive, got {value}")
    if not 0 < recipe.trainer.gamma <= 1 or not 0 < recipe.trainer.tau <= 1:
        raise RMError("recipe: trainer.gamma and trainer.tau must lie in (0, 1]")
    if not 0 < recipe.method.expectile < 1:
        raise RMError(f"recipe: method.expectile must lie in (0, 1), got {recipe.method.expectile}")
    for key, hidden in (("network.hidden", recipe.network.hidden), ("method.bcq_vae_hidden", recipe.method.bcq_vae_hidden)):
        if not hidden or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in hidden):
            raise RMError(f"recipe: {key} must be a list of positive ints, got {hidden}")
    for key in ("lr_actor", "lr_critic", "lr_value"):
        if getattr(recipe.optim, key) <= 0:
            raise RMError(f"recipe: optim.{key} must be positive")
    for key in ("weight_decay_q", "weight_decay_pi"):
        if getattr(recipe.optim, key) < 0:
            raise RMError(f"recipe: optim.{key} must be >= 0")
    if recipe.eval.env and recipe.eval.reward == "d4rl":
        from rm_torchrl.envs.d4rl_reward import V1_ENVS, d4rl_reward_task

        if d4rl_reward_task(recipe.eval.env, recipe.eval.env_kwargs) is None:
            raise RMError(f"recipe: eval.reward=d4rl needs a dense v1 env with a known correction "
                          f"({sorted(V1_ENVS)}), got eval.env={recipe.eval.env!r}; use auto or env")
