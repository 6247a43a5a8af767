"""The methods a recipe can name, in one registry: each one's loss, optimisers, policy and loss terms.

``METHODS[name].build(recipe, obs_keys, obs_dim, action_dim, device)`` returns a
:class:`~rm_torchrl.train.method.Method` whose loss sits on ``device`` (networks are moved
there before the loss is built, so the evaluation policy shares the loss's parameters); ``terms`` are the loss
entries summed into the objective. Each builder reads the method's own section of the recipe
(``recipe.method.iql`` and so on) plus the shared ``network``, ``optim`` and ``trainer`` sections.

    >>> from rm_torchrl.train.config import Recipe
    >>> recipe = Recipe()
    >>> recipe.method.name = "bc"
    >>> method = build_method(recipe, ["observation"], obs_dim=5, action_dim=2)
    >>> METHODS["bc"].terms
    ('loss_actor',)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torchrl.objectives import CQLLoss, SoftUpdate
from torchrl.objectives.utils import ValueEstimators

from rm_torchrl.train.bcq import make_bcq_loss, make_bcq_optimizers
from rm_torchrl.methods.config import METHOD_SECTIONS
from rm_torchrl.train.config import Recipe
from rm_torchrl.train.iql import SharedForwardIQLLoss
from rm_torchrl.train.losses import ActorSchedule, BCLoss, ForeachSoftUpdate, adam
from rm_torchrl.train.method import Method
from rm_torchrl.train.networks import make_actor, make_qvalue, make_value


@dataclass(frozen=True)
class MethodSpec:
    build: Callable[..., Method]  # (recipe, obs_keys, obs_dim, action_dim, device) -> Method
    terms: tuple[str, ...]  # loss entries summed into the objective


def _bc(recipe: Recipe, obs_keys, obs_dim, action_dim, device) -> Method:
    o = recipe.optim
    actor = make_actor(obs_keys, obs_dim, action_dim, recipe.network.hidden, 0.0, distribution=recipe.network.actor)
    loss = BCLoss(actor.to(device)).to(device)
    return Method(loss, [adam([(loss.actor_network_params, o.lr_actor, o.weight_decay_pi)], o)], actor, None)


def _iql(recipe: Recipe, obs_keys, obs_dim, action_dim, device) -> Method:
    m, o, hidden = recipe.method.iql, recipe.optim, recipe.network.hidden
    actor = make_actor(obs_keys, obs_dim, action_dim, hidden, m.actor_dropout, distribution=recipe.network.actor)
    loss = SharedForwardIQLLoss(actor.to(device), make_qvalue(obs_keys, obs_dim, action_dim, hidden).to(device),
                                make_value(obs_keys, obs_dim, hidden).to(device), num_qvalue_nets=2, loss_function="l2",
                                temperature=m.temperature, expectile=m.expectile).to(device)
    opt = [adam([(loss.actor_network_params, o.lr_actor, o.weight_decay_pi),
                 (loss.qvalue_network_params, o.lr_critic, o.weight_decay_q),
                 (loss.value_network_params, o.lr_value, o.weight_decay_q)], o)]
    loss.make_value_estimator(gamma=recipe.trainer.gamma)
    return Method(loss, opt, actor, ForeachSoftUpdate(loss, tau=recipe.trainer.tau))


def _cql(recipe: Recipe, obs_keys, obs_dim, action_dim, device) -> Method:
    m, o, hidden = recipe.method.cql, recipe.optim, recipe.network.hidden
    actor = make_actor(obs_keys, obs_dim, action_dim, hidden, 0.0, distribution=recipe.network.actor)
    loss = CQLLoss(actor.to(device), make_qvalue(obs_keys, obs_dim, action_dim, hidden).to(device), loss_function="l2",
                   min_q_weight=m.min_q_weight, deterministic_backup=True, num_random=m.num_random,
                   with_lagrange=False, target_entropy=-float(action_dim)).to(device)
    opt = [adam([(loss.actor_network_params, o.lr_actor, o.weight_decay_pi),
                 (loss.qvalue_network_params, o.lr_critic, o.weight_decay_q)], o),
           torch.optim.Adam([loss.log_alpha], lr=o.lr_actor)]
    loss.make_value_estimator(gamma=recipe.trainer.gamma)
    return Method(loss, opt, actor, ForeachSoftUpdate(loss, tau=recipe.trainer.tau))


def _bcq(recipe: Recipe, obs_keys, obs_dim, action_dim, device) -> Method:
    """BCQ: ``network.hidden`` for the perturbation model and critics, ``method.bcq.vae_hidden`` for the
    VAE; ``optim.lr_value`` / ``lr_actor`` / ``lr_critic`` for VAE / perturbation / critics; no weight decay."""
    m, o = recipe.method.bcq, recipe.optim
    loss = make_bcq_loss(obs_dim, action_dim, observation_keys=list(obs_keys), max_action=1.0, phi=m.phi,
                         lmbda=m.lmbda, vae_hidden=m.vae_hidden, actor_hidden=recipe.network.hidden,
                         critic_hidden=recipe.network.hidden).to(device)
    loss.make_value_estimator(ValueEstimators.TD0, gamma=recipe.trainer.gamma)
    optimizers = list(make_bcq_optimizers(loss, lr_vae=o.lr_value, lr_actor=o.lr_actor, lr_qvalue=o.lr_critic,
                                          fused=o.fused).values())
    return Method(loss, optimizers, loss.make_policy(), SoftUpdate(loss, tau=recipe.trainer.tau))


_IQL_TERMS = ("loss_actor", "loss_qvalue", "loss_value")
METHODS = {
    "ours": MethodSpec(_iql, _IQL_TERMS),  # IQL on the refined data, the RM state in the policy input
    "iql": MethodSpec(_iql, _IQL_TERMS),
    "bc": MethodSpec(_bc, ("loss_actor",)),
    "cql": MethodSpec(_cql, ("loss_actor", "loss_qvalue", "loss_cql", "loss_alpha")),
    "bcq": MethodSpec(_bcq, ("loss_vae", "loss_actor", "loss_qvalue")),
}
assert set(METHODS) == set(METHOD_SECTIONS), "every method of the schema has a builder"


def build_method(recipe: Recipe, obs_keys: list, obs_dim: int, action_dim: int,
                 device: torch.device | str = "cpu") -> Method:
    """The recipe's method on ``device``, with the actor's learning-rate schedule of ``optim.actor_schedule``."""
    method = METHODS[recipe.method.name].build(recipe, obs_keys, obs_dim, action_dim, torch.device(device))
    if recipe.optim.actor_schedule == "cosine":
        method.schedule = ActorSchedule(method, recipe.trainer.steps)
    return method
