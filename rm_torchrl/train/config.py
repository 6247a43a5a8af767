"""The recipe schema: typed OmegaConf structured configs, one section per part of a run.

A recipe is composed by Hydra (:mod:`rm_torchrl.train.recipe`) from a dataset option
(``recipes/dataset/*.yaml``: data and evaluation) and a method option (``recipes/method/*.yaml``:
the method's own section, networks and optimisers), then checked against these classes: unknown
keys and ill-typed values are refused with the path of the entry. The sections the methods read
(``method``, ``network``, ``optim``) are defined with the methods, in :mod:`rm_torchrl.methods.config`.
The method section holds one sub-section per method family (``method.iql``, ``method.cql``,
``method.bcq``); a run uses the one its ``method.name`` names and its resolved ``recipe.yaml`` keeps
only that one.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List

from omegaconf import OmegaConf

from rm_torchrl.errors import RMError
from rm_torchrl.methods.config import ACTORS, BC_LOSSES, METHOD_SECTIONS, MethodConfig, NetworkConfig, OptimConfig
from rm_torchrl.run_format import HPARAMS, REFINE

DEVICES = "auto | cpu | cuda | cuda:N"

#: Entries that take one of a few values (checked after composition, with the valid ones named).
CHOICES = {
    "data.episode_ends": ("auto", "terminals", "timeouts", "both"),
    "rm.encoding": ("one_hot", "slots"),
    "method.name": tuple(METHOD_SECTIONS),
    "method.hparams": HPARAMS,
    "method.bc.loss": BC_LOSSES,
    "data.refine": REFINE,
    "optim.decay": ("l2", "decoupled"),
    "optim.actor_schedule": ("constant", "cosine"),
    "network.actor": ACTORS,
    "eval.reward": ("auto", "d4rl", "env"),
    "eval.observation": ("flat", "kitchen-v0"),
    "eval.score": ("", "door", "relocate", "kitchen"),
    "logger.backend": ("csv", "tensorboard", "wandb"),
}

#: Probability-like entries (rates, fractions, expectiles) and the interval each must lie in:
#: ``(`` and ``)`` leave the end out, ``[`` and ``]`` take it in. ``data.alpha`` has its own check.
INTERVALS = {
    "trainer.gamma": "(0, 1]",
    "trainer.tau": "(0, 1]",
    "method.iql.expectile": "(0, 1)",
    "method.iql.actor_dropout": "[0, 1)",  # a dropout of 1 zeroes every hidden unit
    "method.bcq.lmbda": "[0, 1]",
    "method.bcq.phi": "[0, 1]",  # a fraction of the action range
}
#: Seeds every generator a run seeds accepts: numpy's legacy ``RandomState`` is the narrowest (torch
#: takes up to 2**64-1, gymnasium any int >= 0, none of them a negative one).
SEED_MAX = 2**32 - 1


def check_seed(seed, what: str = "seed") -> int:
    """``seed`` if every seeded generator takes it (an integer in [0, 2**32-1]), else a one-line RMError."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= SEED_MAX:
        raise RMError(f"{what} must be an integer in [0, 2**32-1], got {seed!r}")
    return seed
#: Seconds within which a second SIGINT/SIGTERM to a run or a sweep counts as the first one again, not
#: as the request to stop at once (the trainer's ``_StopOnSignal``, the sweeps' forwarding).
SIGNAL_REPEAT = 1.0


@dataclass
class DataConfig:
    name: str = "data"  # the dataset's label (reports read it): run names default to <data.name>-<run label>
    source: str = ""  # .hdf5 path, minari:<id> or a local Minari name
    episode_ends: str = "auto"
    refine: str = "none"  # none: the raw data | paper: the paper's refinement | reuse: it, plus the abandoned pieces
    events: str = ""  # event spec, also used online by the RM env transform
    alpha: float = 1.0
    constraints: List[str] = field(default_factory=list)

    @property
    def refined(self) -> bool:
        """Whether training sees refined data (with RM states, which the policy then reads)."""
        return self.refine != "none"


@dataclass
class RMConfig:
    encoding: str = "one_hot"  # what the policy sees of the RM state: one_hot | slots


@dataclass
class TrainerConfig:
    steps: int = 500_000
    batch_size: int = 256
    gamma: float = 0.99
    tau: float = 0.005
    normalize_obs: bool = True
    log_every: int = 1000
    checkpoint_every: int = 50_000
    stop_at: int = 0  # >0: this session stops (checkpointed) after that step; the run continues with resume=true
    threads: int = 0  # 0: the cores idle at the start (train/threads.py; a multirun shares them between its jobs)
    device: str = "auto"  # auto (cuda if available) | cpu | cuda | cuda:N; environments stay on CPU
    compile: bool = False  # torch.compile the loss: ~25% more updates/s on CPU, after ~10 s of compilation
    flush_denormal: bool = True  # subnormal floats as 0 on CPU: without it updates slow 4-5x within 3k steps


@dataclass
class EvalConfig:
    env: str = ""  # gymnasium id, empty for no online evaluation
    env_kwargs: Dict[str, Any] = field(default_factory=dict)
    observation: str = "flat"  # flat | kitchen-v0 (rebuild the D4RL v0 60-dim observation)
    max_steps: int = 200
    every: int = 2000
    episodes: int = 10
    vectorised: bool = True  # all episodes as one batch of envs; false: one after another (same starts)
    score: str = ""  # door | relocate | kitchen: the D4RL normalisation of the return
    reward: str = "auto"  # auto: D4RL's reward where the v1 env's differs (door, relocate), else the env's | d4rl | env


@dataclass
class LoggerConfig:
    backend: str = "csv"  # csv | tensorboard | wandb
    project: str = "rm_torchrl"


@dataclass
class Recipe:
    name: str = "${data.name}-${run_label:${method.name},${method.hparams},${data.refine}}"
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
    #: values a dataset option of a user's sets for a settings preset (``tuned.ours.temperature`` wins over the table
    #: of rm_torchrl.methods.ours), read by the preset's interpolations; resolved, so not in ``recipe.yaml``
    tuned: Dict[str, Any] = field(default_factory=dict)

    @property
    def run_dir(self) -> Path:
        return Path(self.out) / f"{self.name}-seed{self.seed}"

    def to_dict(self) -> dict:
        """The resolved recipe, with only the method sub-section this run reads."""
        data = OmegaConf.to_container(OmegaConf.structured(self), resolve=True)
        own = METHOD_SECTIONS.get(self.method.name)
        data["method"] = {k: v for k, v in data["method"].items() if k in ("name", "hparams") or k == own}
        data.pop("tuned")
        return data
