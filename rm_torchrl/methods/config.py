"""The methods' own sections of a recipe: ``method`` (one sub-section per method family), ``network`` and ``optim``.

These are typed OmegaConf structured configs, like the rest of the recipe schema
(:mod:`rm_torchrl.train.config`), which holds them as its ``method``, ``network`` and ``optim`` sections. The
method section holds one sub-section per method family (``method.iql``, ``method.cql``, ``method.bcq``); a
run uses the one its ``method.name`` names (:data:`METHOD_SECTIONS`). Of the ``trainer`` section the
methods read three entries alone (:class:`TrainerSection`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Protocol

#: Algorithm (``method.name``) -> the method section it reads. The data treatment is ``data.refine`` and whose
#: settings the values are ``method.hparams``: ``method=ours`` is a preset of the three (rm_torchrl.methods.ours writes recipes/method/ours.yaml).
METHOD_SECTIONS = {"iql": "iql", "bc": "bc", "cql": "cql", "bcq": "bcq"}
ACTORS = ("tanh_normal", "gaussian")  # network.actor: see rm_torchrl.methods.networks.make_actor
BC_LOSSES = ("mse", "nll")  # method.bc.loss


@dataclass
class IQLConfig:
    """IQL (Kostrikov et al. 2021); the ``ours`` preset is IQL with its own values."""

    expectile: float = 0.7  # tau
    temperature: float = 0.5  # inverse temperature beta of the advantage weights
    actor_dropout: float = 0.1  # the IQL authors' actor dropout on Adroit and kitchen


@dataclass
class BCConfig:
    """Behaviour cloning. ``mse``: CORL's BC (the deterministic action, tanh of the network, regressed on the
    dataset action); ``nll``: the Gaussian likelihood of the dataset action (this library's BC before)."""

    loss: str = "mse"


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
    name: str = "iql"  # the algorithm: iql | bc | cql | bcq
    hparams: str = "published"  # whose settings the values are: published (the algorithm's authors') | ours
    iql: IQLConfig = field(default_factory=IQLConfig)
    bc: BCConfig = field(default_factory=BCConfig)
    cql: CQLConfig = field(default_factory=CQLConfig)
    bcq: BCQConfig = field(default_factory=BCQConfig)

    @property
    def section(self):
        """This algorithm's own parameters."""
        return getattr(self, METHOD_SECTIONS[self.name])


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


class TrainerSection(Protocol):
    """What the methods read of the recipe's ``trainer`` section (``rm_torchrl.train.config.TrainerConfig``)."""

    gamma: float  # discount of the TD targets
    tau: float  # rate of the soft update of the target networks
    steps: int  # updates in the run: the length of the actor's schedule under optim.actor_schedule=cosine
