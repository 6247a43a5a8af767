"""The recipe schema: typed OmegaConf structured configs, one section per part of a run.

A recipe is composed by Hydra (:mod:`rm_torchrl.train.recipe`) from a dataset option
(``recipes/dataset/*.yaml``: data and evaluation) and a method option (``recipes/method/*.yaml``:
the method's own section, networks and optimisers), then checked against these classes: unknown
keys and ill-typed values are refused with the path of the entry. The method section holds one
sub-section per method family (``method.iql``, ``method.cql``, ``method.bcq``); a run uses the one
its ``method.name`` names and its resolved ``recipe.yaml`` keeps only that one.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List

from omegaconf import OmegaConf

from rm_torchrl.errors import RMError

#: Method name -> the method section it reads (``None``: no parameters of its own). ``ours`` is IQL
#: on the refined data with the RM state as policy input; the others are the paper's baselines.
METHOD_SECTIONS = {"ours": "iql", "iql": "iql", "bc": None, "cql": "cql", "bcq": "bcq"}
ACTORS = ("tanh_normal", "gaussian")  # network.actor: see rm_torchrl.train.networks.make_actor
DEVICES = "auto | cpu | cuda | cuda:N"

#: Entries that take one of a few values (checked after composition, with the valid ones named).
CHOICES = {
    "data.episode_ends": ("auto", "terminals", "timeouts", "both"),
    "rm.encoding": ("one_hot", "slots"),
    "method.name": tuple(METHOD_SECTIONS),
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
    name: str = "data"  # the dataset's label: run names default to <data.name>-<method.name>
    source: str = ""  # .hdf5 path, minari:<id> or a local Minari name
    episode_ends: str = "auto"
    refine: bool = True  # the paper's method; False trains on the raw data (baselines)
    events: str = ""  # event spec, also used online by the RM env transform
    alpha: float = 1.0
    constraints: List[str] = field(default_factory=list)


@dataclass
class RMConfig:
    encoding: str = "one_hot"  # what the policy sees of the RM state: one_hot | slots


@dataclass
class IQLConfig:
    """IQL (Kostrikov et al. 2021), used by ``ours`` and ``iql``."""

    expectile: float = 0.7  # tau
    temperature: float = 0.5  # inverse temperature beta of the advantage weights
    actor_dropout: float = 0.1  # the IQL authors' actor dropout on Adroit and kitchen


@dataclass
class CQLConfig:
    """CQL (Kumar et al. 2020)."""

    min_q_weight: float = 5.0  # Adroit and kitchen
    num_random: int = 10  # random actions per state in the log-sum-exp


@dataclass
class BCQConfig:
    """BCQ (Fujimoto et al. 2019)."""

    lmbda: float = 0.75  # soft clipped double-Q
    phi: float = 0.05  # perturbation range
    vae_hidden: List[int] = field(default_factory=lambda: [750, 750])


@dataclass
class MethodConfig:
    name: str = "iql"  # ours | iql | bc | cql | bcq
    iql: IQLConfig = field(default_factory=IQLConfig)
    cql: CQLConfig = field(default_factory=CQLConfig)
    bcq: BCQConfig = field(default_factory=BCQConfig)

    @property
    def section(self):
        """This method's own parameters (None for BC)."""
        name = METHOD_SECTIONS.get(self.name)
        return None if name is None else getattr(self, name)


@dataclass
class NetworkConfig:
    hidden: List[int] = field(default_factory=lambda: [256, 256])
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
    threads: int = 0  # 0: all cores (a multirun shares them between its parallel jobs)
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
    name: str = "${data.name}-${method.name}"
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
        """The resolved recipe, with only the method sub-section this run reads."""
        data = OmegaConf.to_container(OmegaConf.structured(self), resolve=True)
        own = METHOD_SECTIONS.get(self.method.name)
        data["method"] = {k: v for k, v in data["method"].items() if k == "name" or k == own}
        return data
