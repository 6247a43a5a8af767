"""The methods a recipe can name, in one registry: each one's loss, optimisers, policy and loss terms.

``build_method(method, network, optim, trainer, obs_keys, obs_dim, action_dim, device)`` returns a
:class:`~rm_torchrl.methods.method.Method` whose loss sits on ``device`` (networks are moved
there before the loss is built, so the evaluation policy shares the loss's parameters); ``METHODS[name].terms``
are the loss entries summed into the objective. It takes the recipe sections it reads and no more: the
method's own section (``method.iql`` and so on, picked by ``method.name``), ``network``, ``optim`` and of
``trainer`` its ``gamma``, ``tau`` and ``steps`` (:class:`~rm_torchrl.methods.config.TrainerSection`).

    >>> from rm_torchrl.train.config import Recipe
    >>> recipe = Recipe()
    >>> recipe.method.name = "bc"
    >>> method = build_method(recipe.method, recipe.network, recipe.optim, recipe.trainer, ["observation"],
    ...                       obs_dim=5, action_dim=2)
    >>> METHODS["bc"].terms
    ('loss_actor',)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torchrl.objectives import CQLLoss, SoftUpdate
from torchrl.objectives.utils import ValueEstimators

from rm_torchrl.methods.bcq import make_bcq_loss, make_bcq_optimizers
from rm_torchrl.methods.config import (METHOD_SECTIONS, BCConfig, BCQConfig, CQLConfig, IQLConfig, MethodConfig,
                                       NetworkConfig, OptimConfig, TrainerSection)
from rm_torchrl.methods.iql import SharedForwardIQLLoss
from rm_torchrl.methods.bc import BCLoss
from rm_torchrl.methods.optim import ActorSchedule, adam, ForeachSoftUpdate
from rm_torchrl.methods.method import Method
from rm_torchrl.methods.networks import make_actor, make_qvalue, make_value


@dataclass(frozen=True)
class MethodSpec:
    build: Callable[..., Method]  # (section, network, optim, trainer, obs_keys, obs_dim, action_dim, device) -> Method
    terms: tuple[str, ...]  # loss entries summed into the objective


def _bc(m: BCConfig, net: NetworkConfig, o: OptimConfig, trainer: TrainerSection, obs_keys, obs_dim, action_dim,
        device) -> Method:
    actor = make_actor(obs_keys, obs_dim, action_dim, net.hidden, 0.0, distribution=net.actor)
    loss = BCLoss(actor.to(device), m.loss).to(device)
    return Method(loss, [adam([(loss.actor_network_params, o.lr_actor, o.weight_decay_pi)], o)], actor, None)


def _iql(m: IQLConfig, net: NetworkConfig, o: OptimConfig, trainer: TrainerSection, obs_keys, obs_dim, action_dim,
         device) -> Method:
    hidden = net.hidden
    actor = make_actor(obs_keys, obs_dim, action_dim, hidden, m.actor_dropout, distribution=net.actor)
    loss = SharedForwardIQLLoss(actor.to(device), make_qvalue(obs_keys, obs_dim, action_dim, hidden).to(device),
                                make_value(obs_keys, obs_dim, hidden).to(device), num_qvalue_nets=2, loss_function="l2",
                                temperature=m.temperature, expectile=m.expectile).to(device)
    opt = [adam([(loss.actor_network_params, o.lr_actor, o.weight_decay_pi),
                 (loss.qvalue_network_params, o.lr_critic, o.weight_decay_q),
                 (loss.value_network_params, o.lr_value, o.weight_decay_q)], o)]
    loss.make_value_estimator(gamma=trainer.gamma)
    return Method(loss, opt, actor, ForeachSoftUpdate(loss, tau=trainer.tau))


def _cql(m: CQLConfig, net: NetworkConfig, o: OptimConfig, trainer: TrainerSection, obs_keys, obs_dim, action_dim,
         device) -> Method:
    hidden = net.hidden
    actor = make_actor(obs_keys, obs_dim, action_dim, hidden, 0.0, distribution=net.actor)
    loss = CQLLoss(actor.to(device), make_qvalue(obs_keys, obs_dim, action_dim, hidden).to(device), loss_function="l2",
                   min_q_weight=m.min_q_weight, deterministic_backup=True, num_random=m.num_random,
                   with_lagrange=False, target_entropy=-float(action_dim)).to(device)
    opt = [adam([(loss.actor_network_params, o.lr_actor, o.weight_decay_pi),
                 (loss.qvalue_network_params, o.lr_critic, o.weight_decay_q)], o),
           torch.optim.Adam([loss.log_alpha], lr=o.lr_actor)]
    loss.make_value_estimator(gamma=trainer.gamma)
    return Method(loss, opt, actor, ForeachSoftUpdate(loss, tau=trainer.tau))


def _bcq(m: BCQConfig, net: NetworkConfig, o: OptimConfig, trainer: TrainerSection, obs_keys, obs_dim, action_dim,
         device) -> Method:
    """BCQ: ``network.hidden`` for the perturbation model and critics, ``method.bcq.vae_hidden`` for the
    VAE; ``optim.lr_value`` / ``lr_actor`` / ``lr_critic`` for VAE / perturbation / critics; no weight decay."""
    loss = make_bcq_loss(obs_dim, action_dim, observation_keys=list(obs_keys), max_action=1.0, phi=m.phi,
                         lmbda=m.lmbda, vae_hidden=m.vae_hidden, actor_hidden=net.hidden,
                         critic_hidden=net.hidden).to(device)
    loss.make_value_estimator(ValueEstimators.TD0, gamma=trainer.gamma)
    optimizers = list(make_bcq_optimizers(loss, lr_vae=o.lr_value, lr_actor=o.lr_actor, lr_qvalue=o.lr_critic,
                                          fused=o.fused).values())
    return Method(loss, optimizers, loss.make_policy(), SoftUpdate(loss, tau=trainer.tau))


_IQL_TERMS = ("loss_actor", "loss_qvalue", "loss_value")
METHODS = {
    "iql": MethodSpec(_iql, _IQL_TERMS),
    "bc": MethodSpec(_bc, ("loss_actor",)),
    "cql": MethodSpec(_cql, ("loss_actor", "loss_qvalue", "loss_cql", "loss_alpha")),
    "bcq": MethodSpec(_bcq, ("loss_vae", "loss_actor", "loss_qvalue")),
}
assert set(METHODS) == set(METHOD_SECTIONS), "every method of the schema has a builder"


def build_method(method: MethodConfig, network: NetworkConfig, optim: OptimConfig, trainer: TrainerSection,
                 obs_keys: list, obs_dim: int, action_dim: int, device: torch.device | str = "cpu") -> Method:
    """``method.name``'s method on ``device``, with the actor's learning-rate schedule of ``optim.actor_schedule``."""
    built = METHODS[method.name].build(method.section, network, optim, trainer, obs_keys, obs_dim, action_dim,
                                       torch.device(device))
    if optim.actor_schedule == "cosine":
        built.schedule = ActorSchedule(built, trainer.steps)
    return built
