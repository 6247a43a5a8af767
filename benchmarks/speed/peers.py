"""Updates per second of one IQL update four ways, each in its own process pinned to its own core(s), same data.

The update is the same in all four: two hidden layers of 256 for the actor, the twin critics and the value
network; batch 256; the expectile value loss (expectile 0.7) on the smaller twin target Q; the twin-Q TD(0)
loss (the sum of both critics' squared errors, batch mean) on r + 0.99 (1 - terminated) V(s'), V without
delay as TorchRL's ``IQLLoss`` defines it; the AWR actor loss with weights exp(0.5 A) capped at 100 for a
Gaussian actor N(tanh(mean), exp(log_std)) whose log_std (clipped to [-5, 2]) is state-independent; Adam at
3e-4 for every network, no weight decay, the actor's rate cosine-annealed to 0 over the whole run (as IQL's
authors do); soft target critics, tau 0.005; no dropout. All three losses are taken at the parameters before
the update. The contenders:

- ``rmrl_trainer``: rm_torchrl's own update, ``build_method`` + ``gradient_step`` with ``trainer.compile=true``
  (the loss under ``torch.compile``), its cosine schedule, batches from ``training_buffer(...).sample()``.
- ``corl_style_torch``: a plain eager PyTorch loop in the single-file style of CORL's IQL (written here):
  separate ``nn.Module`` critics called one after the other, three Adams stepped one after another
  (value, then critics, then actor), a ``CosineAnnealingLR`` on the actor, a tensor replay buffer.
- ``jax_corl_style``: a JAX loop in the style of JAX-CORL's IQL (written here, with optax): the sampling and
  the whole update jitted, ``--jax-updates-per-call`` updates (8) per call in a ``jax.lax.fori_loop``.
  Needs the optional ``bench`` extra (``pip install -e '.[bench]'``); skipped, with a note, without it.
- ``torchrl_iqlloss``: TorchRL's ``IQLLoss`` as its offline IQL example uses it: ``IQLLoss`` (vmapped twin
  critics), ``SoftUpdate``, one Adam per network (grouped), one backward of the summed losses,
  ``TensorDictReplayBuffer.sample``; the networks are rm_torchrl's (the same as the others').
- ``rmrl_trainer_eager`` (not run unless named in ``--contenders``): ``rmrl_trainer`` with ``trainer.compile=false``.

Each contender runs in a fresh process under ``taskset -c CORES`` with one thread (``--threads 2``: two, on
cores 0-1): ``torch.set_num_threads``, ``OMP_NUM_THREADS``, and for JAX ``XLA_FLAGS`` without Eigen's thread pool.
Each process first builds its update and runs the warm-up (the first call, which compiles or jits, timed apart),
then the rounds run interleaved across the processes, one process working at a time, so drifting machine load
hits all alike. Each round reports updates per wall-second and per CPU-second of the process
(``time.process_time``: what a busy machine's other work does not inflate), and the ratio of each contender's
rate to ``rmrl_trainer``'s in the same round.

The data are door-human-v0's (observation 39, action 28): the real D4RL file when it is at
``../shared/data/d4rl/door-human-v0.hdf5`` beside the repository (read with h5py; observations normalised as
CORL does), else 25k random transitions of that shape (``--data synthetic`` forces them).

One JSON object on stdout; progress on stderr.
"""
from __future__ import annotations

import argparse
import importlib.metadata
import importlib.util
import json
import math
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DOOR_HUMAN = ROOT.parent / "shared" / "data" / "d4rl" / "door-human-v0.hdf5"
OBS, ACT, HIDDEN, BATCH = 39, 28, (256, 256), 256
EXPECTILE, TEMPERATURE, GAMMA, TAU, LR = 0.7, 0.5, 0.99, 0.005, 3e-4
MAX_WEIGHT, LOG_STD_MIN, LOG_STD_MAX = 100.0, -5.0, 2.0
REFERENCE = "rmrl_trainer"
CONTENDERS = ("rmrl_trainer", "corl_style_torch", "jax_corl_style", "torchrl_iqlloss")
OPTIONAL = ("rmrl_trainer_eager",)
TORCH_CONTENDERS = ("rmrl_trainer", "corl_style_torch", "torchrl_iqlloss", "rmrl_trainer_eager")
MESSAGE = "@@peers "  # the prefix of a child's protocol lines on its stdout


def log(message: str) -> None:
    print(f"[peers] {message}", file=sys.stderr, flush=True)


# --- data -------------------------------------------------------------------------------------------

def load_data(source: str = "auto", transitions: int = 25_000, seed: int = 0) -> tuple[dict, str]:
    """Transitions as float32 numpy arrays (``observation``, ``action``, ``reward``, ``next_observation``,
    ``terminated``), and what they are: ``source`` is ``auto`` (the real file when present), ``synthetic`` or a path."""
    path = DOOR_HUMAN if source == "auto" else None if source == "synthetic" else Path(source)
    if path is not None and path.is_file():
        return _d4rl_transitions(path), f"D4RL {path.name} ({path}), observations normalised"
    if source not in ("auto", "synthetic"):
        raise SystemExit(f"--data: no file at {source}")
    rng = np.random.default_rng(seed)
    return {
        "observation": rng.standard_normal((transitions, OBS), dtype=np.float32),
        "action": rng.uniform(-1, 1, (transitions, ACT)).astype(np.float32),
        "reward": rng.standard_normal(transitions, dtype=np.float32),
        "next_observation": rng.standard_normal((transitions, OBS), dtype=np.float32),
        "terminated": np.zeros(transitions, np.float32),
    }, f"synthetic: {transitions} random transitions of door-human-v0's shape"


def _d4rl_transitions(path: Path) -> dict:
    """(s_t, a_t, r_t, s_t+1) inside each episode of a D4RL file whose ``terminals`` mark each episode's last step
    (door-human-v0's: its ``timeouts`` are misplaced); door episodes end on time, so nothing is terminated."""
    import h5py

    with h5py.File(path, "r") as f:
        obs, act, rew, ends = (np.asarray(f[k]) for k in ("observations", "actions", "rewards", "terminals"))
    last = ends.astype(bool)
    last[-1] = True
    valid = ~last  # step t has a successor in its episode
    mean, std = obs.mean(0), obs.std(0) + 1e-3  # CORL's state normalisation
    obs = ((obs - mean) / std).astype(np.float32)
    idx = np.flatnonzero(valid)
    return {"observation": obs[idx], "action": act[idx].astype(np.float32), "reward": rew[idx].astype(np.float32),
            "next_observation": obs[idx + 1], "terminated": np.zeros(len(idx), np.float32)}


def torch_transitions(data: dict):
    """The transitions as a TorchRL TensorDict (``next`` holding the next observation, reward, done, terminated)."""
    import torch
    from tensordict import TensorDict

    n = len(data["reward"])
    terminated = torch.from_numpy(data["terminated"] > 0).unsqueeze(-1)
    return TensorDict({
        "observation": torch.from_numpy(data["observation"]),
        "action": torch.from_numpy(data["action"]),
        "next": {"observation": torch.from_numpy(data["next_observation"]),
                 "reward": torch.from_numpy(data["reward"]).unsqueeze(-1),
                 "done": terminated.clone(), "terminated": terminated},
    }, batch_size=[n])


# --- (a) rm_torchrl's trainer -----------------------------------------------------------------------

def iql_recipe(total: int, compile: bool = True):
    """``rmrl train method=iql``'s settings (recipes/method/iql.yaml) without the actor's dropout, so that all
    contenders train the same networks; ``trainer.steps`` is the run's length (the cosine schedule's)."""
    from rm_torchrl.train.config import Recipe

    recipe = Recipe()
    recipe.method.name = "iql"
    iql = recipe.method.iql
    iql.expectile, iql.temperature, iql.actor_dropout = EXPECTILE, TEMPERATURE, 0.0
    recipe.network.hidden, recipe.network.actor = list(HIDDEN), "gaussian"
    o = recipe.optim
    o.lr_actor = o.lr_critic = o.lr_value = LR
    o.weight_decay_q = o.weight_decay_pi = 0.0
    o.decay, o.actor_schedule = "l2", "cosine"
    t = recipe.trainer
    t.steps, t.batch_size, t.gamma, t.tau, t.compile = total, BATCH, GAMMA, TAU, compile
    return recipe


class RmrlUpdate:
    """rm_torchrl's update as its trainer runs it: ``method.schedule(step)``, a batch from the training buffer,
    ``gradient_step`` (with its finiteness checks); ``compile``: ``trainer.compile=true`` (falls back to eager,
    with a note, where compiling fails, as the trainer does)."""

    def __init__(self, data: dict, total: int, seed: int = 0, compile: bool = True):
        import torch

        from rm_torchrl.methods.method import compile_method
        from rm_torchrl.methods.registry import METHODS, build_method
        from rm_torchrl.train.training_data import training_buffer
        from rm_torchrl.train.update import NonFinite, gradient_step

        torch.manual_seed(seed)
        recipe = iql_recipe(total, compile)
        self.method = build_method(recipe.method, recipe.network, recipe.optim, recipe.trainer, ["observation"],
                                   OBS, ACT)
        if recipe.trainer.compile:
            compile_method(self.method)
        self.buffer = training_buffer(torch_transitions(data), recipe.trainer.batch_size, seed)
        self.terms = METHODS["iql"].terms
        self._gradient_step, self._non_finite = gradient_step, NonFinite
        self.step, self.notes = 0, []

    def sample(self):
        return self.buffer.sample().exclude("index")  # TrainingData.sample

    def run(self, n: int) -> int:
        for _ in range(n):
            self.step += 1
            self.method.schedule(self.step)
            batch = self.sample()
            if self.step == 1 and self.method.compiled is not None:
                try:
                    self._gradient_step(self.method, self.terms, batch)
                except self._non_finite:
                    raise
                except Exception as err:  # no C++ compiler, say: the trainer trains eagerly then
                    self.method.compiled = None
                    self.notes.append(f"torch.compile failed ({type(err).__name__}: {str(err)[:160]}); ran eagerly")
                    self._gradient_step(self.method, self.terms, batch)
                continue
            self._gradient_step(self.method, self.terms, batch)
        return n

    def sync(self) -> None:
        pass

    def update_on(self, batch) -> dict:
        """One update on ``batch`` (a TensorDict of ``sample``'s form); its loss terms, at the parameters before it."""
        self.step += 1
        self.method.schedule(self.step)
        return _floats(self._gradient_step(self.method, self.terms, batch))


def _floats(losses) -> dict:
    return {k: float(losses[k].detach()) for k in ("loss_value", "loss_qvalue", "loss_actor")}


# --- (b) a plain eager loop in CORL's single-file style ---------------------------------------------

def _corl_classes():
    import torch
    from torch import nn

    class MLP(nn.Module):
        def __init__(self, sizes, out_tanh=False):
            super().__init__()
            layers = []
            for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
                layers.append(nn.Linear(a, b))
                if i < len(sizes) - 2:
                    layers.append(nn.ReLU())
            if out_tanh:
                layers.append(nn.Tanh())
            self.net = nn.Sequential(*layers)

        def forward(self, x):
            return self.net(x)

    class TwinQ(nn.Module):
        def __init__(self, obs_dim, act_dim, hidden):
            super().__init__()
            self.q1 = MLP([obs_dim + act_dim, *hidden, 1])
            self.q2 = MLP([obs_dim + act_dim, *hidden, 1])

        def both(self, obs, act):
            sa = torch.cat([obs, act], 1)
            return self.q1(sa).squeeze(-1), self.q2(sa).squeeze(-1)

        def forward(self, obs, act):
            return torch.min(*self.both(obs, act))

    class ValueFunction(nn.Module):
        def __init__(self, obs_dim, hidden):
            super().__init__()
            self.v = MLP([obs_dim, *hidden, 1])

        def forward(self, obs):
            return self.v(obs).squeeze(-1)

    class GaussianPolicy(nn.Module):
        def __init__(self, obs_dim, act_dim, hidden):
            super().__init__()
            self.net = MLP([obs_dim, *hidden, act_dim], out_tanh=True)
            self.log_std = nn.Parameter(torch.zeros(act_dim))

        def forward(self, obs):
            std = torch.exp(self.log_std.clamp(LOG_STD_MIN, LOG_STD_MAX))
            return torch.distributions.Normal(self.net(obs), std)

    return MLP, TwinQ, ValueFunction, GaussianPolicy


class CorlUpdate:
    """The eager single-file loop: value step, then critic step (and the target's soft update), then actor step."""

    def __init__(self, data: dict, total: int, seed: int = 0):
        import copy

        import torch

        torch.manual_seed(seed)
        _, TwinQ, ValueFunction, GaussianPolicy = _corl_classes()
        self.qf, self.vf = TwinQ(OBS, ACT, HIDDEN), ValueFunction(OBS, HIDDEN)
        self.actor = GaussianPolicy(OBS, ACT, HIDDEN)
        self.q_target = copy.deepcopy(self.qf).requires_grad_(False)
        self.v_optim = torch.optim.Adam(self.vf.parameters(), lr=LR)
        self.q_optim = torch.optim.Adam(self.qf.parameters(), lr=LR)
        self.actor_optim = torch.optim.Adam(self.actor.parameters(), lr=LR)
        self.actor_lr_schedule = torch.optim.lr_scheduler.CosineAnnealingLR(self.actor_optim, total)
        self.states = torch.from_numpy(data["observation"])
        self.actions = torch.from_numpy(data["action"])
        self.rewards = torch.from_numpy(data["reward"])
        self.next_states = torch.from_numpy(data["next_observation"])
        self.dones = torch.from_numpy(data["terminated"])
        self.generator = torch.Generator().manual_seed(seed)
        self.notes = []

    def sample(self):
        import torch

        idx = torch.randint(len(self.rewards), (BATCH,), generator=self.generator)
        return (self.states[idx], self.actions[idx], self.rewards[idx], self.next_states[idx], self.dones[idx])

    def update(self, batch) -> dict:
        import torch

        obs, act, rew, next_obs, done = batch
        log = {}
        with torch.no_grad():
            target_q = self.q_target(obs, act)
            next_v = self.vf(next_obs)
        # value: expectile regression of V(s) on the smaller target Q
        v = self.vf(obs)
        adv = target_q - v
        v_loss = (torch.abs(EXPECTILE - (adv < 0).float()) * adv ** 2).mean()
        log["loss_value"] = v_loss.item()
        self.v_optim.zero_grad(set_to_none=True)
        v_loss.backward()
        self.v_optim.step()
        # critics: TD(0) on V(s'), each critic's squared error, summed
        targets = rew + (1.0 - done) * GAMMA * next_v
        q1, q2 = self.qf.both(obs, act)
        q_loss = ((q1 - targets) ** 2).mean() + ((q2 - targets) ** 2).mean()
        log["loss_qvalue"] = q_loss.item()
        self.q_optim.zero_grad(set_to_none=True)
        q_loss.backward()
        self.q_optim.step()
        with torch.no_grad():
            for t, s in zip(self.q_target.parameters(), self.qf.parameters()):
                t.mul_(1 - TAU).add_(s, alpha=TAU)
        # actor: advantage-weighted log-likelihood of the dataset action
        weight = torch.exp(TEMPERATURE * adv.detach()).clamp(max=MAX_WEIGHT)
        log_prob = self.actor(obs).log_prob(act).sum(-1)
        actor_loss = (-(weight * log_prob)).mean()
        log["loss_actor"] = actor_loss.item()
        self.actor_optim.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_optim.step()
        self.actor_lr_schedule.step()
        return log

    def run(self, n: int) -> int:
        for _ in range(n):
            self.update(self.sample())
        return n

    def update_on(self, batch) -> dict:
        """``update`` on a TensorDict batch (``RmrlUpdate.sample``'s form)."""
        nxt = batch["next"]
        return self.update((batch["observation"], batch["action"], nxt["reward"].squeeze(-1), nxt["observation"],
                            nxt["terminated"].squeeze(-1).float()))

    def sync(self) -> None:
        pass

    def load_from(self, rmrl: RmrlUpdate) -> None:
        """Take ``rmrl``'s parameters (online and target critics, value, actor)."""
        loss = rmrl.method.loss
        critics, targets = _linear_params(loss.qvalue_network_params), _linear_params(loss.target_qvalue_network_params)
        for i, q in enumerate((self.qf.q1, self.qf.q2)):
            _copy_into(q, [p[i] for p in critics])
        for i, q in enumerate((self.q_target.q1, self.q_target.q2)):
            _copy_into(q, [p[i] for p in targets])
        _copy_into(self.vf, _linear_params(loss.value_network_params))
        _copy_into(self.actor.net, _linear_params(loss.actor_network_params))
        self.actor.log_std.data.copy_(_log_std(loss.actor_network_params))


def _linear_params(td) -> list:
    """The weights and biases of a parameter TensorDict of rm_torchrl's networks, layer by layer."""
    return [v.data for k, v in td.flatten_keys(".").items() if k.endswith((".weight", ".bias"))]


def _log_std(td):
    return next(v.data for k, v in td.flatten_keys(".").items() if k.endswith("log_std"))


def _copy_into(module, tensors: list) -> None:
    import torch

    params = [p for m in module.modules() if isinstance(m, torch.nn.Linear) for p in (m.weight, m.bias)]
    assert len(params) == len(tensors), (len(params), len(tensors))
    for p, t in zip(params, tensors):
        p.data.copy_(t)


# --- (c) a jitted JAX loop in JAX-CORL's style ------------------------------------------------------

class JaxUpdate:
    """The whole update, batch sampling included, jitted; ``per_call`` updates per call in a ``fori_loop``."""

    def __init__(self, data: dict, total: int, seed: int = 0, per_call: int = 8):
        import jax
        import jax.numpy as jnp
        import optax

        self.jax, self.per_call, self.notes = jax, per_call, []
        self.data = {k: jnp.asarray(v) for k, v in data.items()}
        key, k_actor, k_q1, k_q2, k_value = jax.random.split(jax.random.key(seed), 5)
        critic = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), _jax_mlp_init(k_q1, [OBS + ACT, *HIDDEN, 1]),
                                        _jax_mlp_init(k_q2, [OBS + ACT, *HIDDEN, 1]))
        params = {"actor": {"mlp": _jax_mlp_init(k_actor, [OBS, *HIDDEN, ACT]), "log_std": jnp.zeros(ACT)},
                  "critic": critic, "value": _jax_mlp_init(k_value, [OBS, *HIDDEN, 1])}
        self.txs = {"actor": optax.adam(optax.cosine_decay_schedule(LR, total)), "critic": optax.adam(LR),
                    "value": optax.adam(LR)}
        self.state = self._state(params, critic, key)
        n_data = len(data["reward"])

        def update_on(state, batch):
            params, target, opt_states, key = state
            (_, terms), grads = jax.value_and_grad(_jax_losses, has_aux=True)(params, target, batch)
            new_params, new_states = {}, {}
            for name, tx in self.txs.items():
                updates, new_states[name] = tx.update(grads[name], opt_states[name], params[name])
                new_params[name] = optax.apply_updates(params[name], updates)
            target = optax.incremental_update(new_params["critic"], target, TAU)
            return (new_params, target, new_states, key), terms

        def update_n(state, data):  # the dataset is an argument, not a constant folded into the program
            def one_update(_, state):
                key, sub = jax.random.split(state[3])
                idx = jax.random.randint(sub, (BATCH,), 0, n_data)
                return update_on((*state[:3], key), jax.tree_util.tree_map(lambda x: x[idx], data))[0]

            return jax.lax.fori_loop(0, per_call, one_update, state)

        self._update_n = jax.jit(update_n)
        self._update_on = jax.jit(update_on)

    def _state(self, params, target, key):
        return params, target, {k: tx.init(params[k]) for k, tx in self.txs.items()}, key

    def run(self, n: int) -> int:
        calls = math.ceil(n / self.per_call)
        for _ in range(calls):
            self.state = self._update_n(self.state, self.data)
        return calls * self.per_call

    def sync(self) -> None:
        self.jax.block_until_ready(self.state)

    def load_from(self, rmrl: RmrlUpdate) -> None:
        """Take ``rmrl``'s parameters (torch's [out, in] weights as [in, out]); fresh optimiser states."""
        import jax.numpy as jnp

        loss = rmrl.method.loss

        def mlp(tensors):  # weight, bias, weight, bias, ...; twin critics' with a leading dimension of 2
            return [(jnp.asarray(w.transpose(-1, -2).numpy()), jnp.asarray(b.numpy()))
                    for w, b in zip(tensors[0::2], tensors[1::2])]

        params = {"actor": {"mlp": mlp(_linear_params(loss.actor_network_params)),
                            "log_std": jnp.asarray(_log_std(loss.actor_network_params).numpy())},
                  "critic": mlp(_linear_params(loss.qvalue_network_params)),
                  "value": mlp(_linear_params(loss.value_network_params))}
        self.state = self._state(params, mlp(_linear_params(loss.target_qvalue_network_params)), self.state[3])

    def update_on(self, batch) -> dict:
        """One update on a TensorDict batch (``RmrlUpdate.sample``'s form); its loss terms."""
        nxt = batch["next"]
        arrays = {"observation": batch["observation"], "action": batch["action"],
                  "reward": nxt["reward"].squeeze(-1), "next_observation": nxt["observation"],
                  "terminated": nxt["terminated"].squeeze(-1).float()}
        self.state, terms = self._update_on(self.state, {k: v.numpy() for k, v in arrays.items()})
        return {k: float(v) for k, v in zip(("loss_value", "loss_qvalue", "loss_actor"), terms)}


def _jax_mlp_init(key, sizes) -> list:
    """PyTorch's default ``nn.Linear`` initialisation (uniform in +-1/sqrt(fan_in)), weights as [in, out]."""
    import jax

    layers = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        key, kw, kb = jax.random.split(key, 3)
        bound = 1.0 / math.sqrt(a)
        layers.append((jax.random.uniform(kw, (a, b), minval=-bound, maxval=bound),
                       jax.random.uniform(kb, (b,), minval=-bound, maxval=bound)))
    return layers


def _jax_mlp(layers, x):
    import jax

    for w, b in layers[:-1]:
        x = jax.nn.relu(x @ w + b)
    w, b = layers[-1]
    return x @ w + b


def _jax_losses(params, target, batch):
    """value + critic + actor loss (each reaches only its own network's parameters) and the three terms."""
    import jax
    import jax.numpy as jnp

    obs, act = batch["observation"], batch["action"]
    sa = jnp.concatenate([obs, act], -1)
    twin = jax.vmap(_jax_mlp, in_axes=(0, None))
    min_q = jax.lax.stop_gradient(twin(target, sa)[..., 0].min(0))
    v = _jax_mlp(params["value"], obs)[..., 0]
    diff = min_q - v
    loss_value = jnp.mean(jnp.where(diff > 0, EXPECTILE, 1 - EXPECTILE) * diff ** 2)
    next_v = jax.lax.stop_gradient(_jax_mlp(params["value"], batch["next_observation"])[..., 0])
    td_target = batch["reward"] + GAMMA * (1.0 - batch["terminated"]) * next_v
    q = twin(params["critic"], sa)[..., 0]
    loss_qvalue = jnp.mean(jnp.sum((q - td_target) ** 2, 0))
    weight = jnp.minimum(jnp.exp(TEMPERATURE * jax.lax.stop_gradient(diff)), MAX_WEIGHT)
    mean = jnp.tanh(_jax_mlp(params["actor"]["mlp"], obs))
    log_std = jnp.clip(params["actor"]["log_std"], LOG_STD_MIN, LOG_STD_MAX)
    log_prob = jnp.sum(-0.5 * ((act - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * math.log(2 * math.pi), -1)
    loss_actor = jnp.mean(-(weight * log_prob))
    return loss_value + loss_qvalue + loss_actor, (loss_value, loss_qvalue, loss_actor)


# --- (d) TorchRL's IQLLoss as its offline example uses it -------------------------------------------

class TorchRLUpdate:
    """``IQLLoss`` + ``SoftUpdate`` + an Adam per network (grouped), ``TensorDictReplayBuffer.sample``."""

    def __init__(self, data: dict, total: int, seed: int = 0):
        import torch
        from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        from torchrl.objectives import IQLLoss, SoftUpdate, group_optimizers

        from rm_torchrl.methods.networks import make_actor, make_qvalue, make_value

        torch.manual_seed(seed)
        transitions = torch_transitions(data)
        self.rb = TensorDictReplayBuffer(storage=LazyTensorStorage(len(transitions)), batch_size=BATCH)
        self.rb.extend(transitions)
        keys = ["observation"]
        self.loss = IQLLoss(make_actor(keys, OBS, ACT, list(HIDDEN), distribution="gaussian"),
                            make_qvalue(keys, OBS, ACT, list(HIDDEN)), make_value(keys, OBS, list(HIDDEN)),
                            num_qvalue_nets=2, loss_function="l2", temperature=TEMPERATURE, expectile=EXPECTILE)
        self.loss.make_value_estimator(gamma=GAMMA)
        self.updater = SoftUpdate(self.loss, tau=TAU)
        actor_optim = torch.optim.Adam(list(self.loss.actor_network_params.flatten_keys().values()), lr=LR)
        critic_optim = torch.optim.Adam(list(self.loss.qvalue_network_params.flatten_keys().values()), lr=LR)
        value_optim = torch.optim.Adam(list(self.loss.value_network_params.flatten_keys().values()), lr=LR)
        self.optimizer = group_optimizers(actor_optim, critic_optim, value_optim)
        # the actor's group (the first) cosine-annealed over the run, the critics' constant
        cosine = lambda step: 0.5 * (1 + math.cos(math.pi * min(step, total) / total))  # noqa: E731
        self.lr_schedule = torch.optim.lr_scheduler.LambdaLR(self.optimizer, [cosine, lambda _: 1.0, lambda _: 1.0])
        self.notes = []

    def run(self, n: int) -> int:
        for _ in range(n):
            self._step(self.rb.sample())
        return n

    def update_on(self, batch) -> dict:
        """One update on ``batch``; its loss terms, at the parameters before it."""
        return _floats(self._step(batch))

    def _step(self, batch):
        out = self.loss(batch)
        loss = (out["loss_actor"] + out["loss_qvalue"] + out["loss_value"]).sum()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.updater.step()
        self.lr_schedule.step()
        return out

    def sync(self) -> None:
        pass

    def load_from(self, rmrl: RmrlUpdate) -> None:
        src = rmrl.method.loss
        for name in ("actor_network_params", "qvalue_network_params", "target_qvalue_network_params",
                     "value_network_params"):
            dst, origin = getattr(self.loss, name).flatten_keys("."), getattr(src, name).flatten_keys(".")
            assert list(dst.keys()) == list(origin.keys())
            for k, v in dst.items():
                v.data.copy_(origin.get(k).data)


def snapshot(update) -> dict:
    """A contender's parameters as numpy arrays in torch's layout (weights [out, in]; twin critics stacked on a
    first dimension of 2), network by network: to check that two contenders train alike."""
    if isinstance(update, (RmrlUpdate, TorchRLUpdate)):
        loss = update.method.loss if isinstance(update, RmrlUpdate) else update.loss
        arrays = lambda td: [t.numpy().copy() for t in _linear_params(td)]  # noqa: E731
        return {"actor": [*arrays(loss.actor_network_params), _log_std(loss.actor_network_params).numpy().copy()],
                "critic": arrays(loss.qvalue_network_params), "value": arrays(loss.value_network_params),
                "target_critic": arrays(loss.target_qvalue_network_params)}
    if isinstance(update, CorlUpdate):
        import torch

        def linear(module):
            return [p.detach().numpy().copy() for m in module.modules() if isinstance(m, torch.nn.Linear)
                    for p in (m.weight, m.bias)]

        def twin(q):
            return [np.stack([a, b]) for a, b in zip(linear(q.q1), linear(q.q2))]

        return {"actor": [*linear(update.actor.net), update.actor.log_std.detach().numpy().copy()],
                "critic": twin(update.qf), "value": linear(update.vf), "target_critic": twin(update.q_target)}
    params, target = update.state[0], update.state[1]

    def layers(mlp):
        return [np.asarray(x) for w, b in mlp for x in (np.swapaxes(np.asarray(w), -1, -2), b)]

    return {"actor": [*layers(params["actor"]["mlp"]), np.asarray(params["actor"]["log_std"])],
            "critic": layers(params["critic"]), "value": layers(params["value"]), "target_critic": layers(target)}


def build(name: str, data: dict, total: int, seed: int = 0, per_call: int = 8):
    if name == "rmrl_trainer":
        return RmrlUpdate(data, total, seed, compile=True)
    if name == "rmrl_trainer_eager":
        return RmrlUpdate(data, total, seed, compile=False)
    if name == "corl_style_torch":
        return CorlUpdate(data, total, seed)
    if name == "jax_corl_style":
        return JaxUpdate(data, total, seed, per_call)
    if name == "torchrl_iqlloss":
        return TorchRLUpdate(data, total, seed)
    raise ValueError(f"unknown contender {name!r}")


# --- one contender's process ------------------------------------------------------------------------

def _send(obj: dict) -> None:
    sys.stdout.write(MESSAGE + json.dumps(obj) + "\n")
    sys.stdout.flush()


def _peak_rss_mib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines() if Path("/proc/self/status").exists() else []:
        if line.startswith("VmHWM:"):
            return round(int(line.split()[1]) / 1024)
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def _timed(fn) -> tuple:
    wall, cpu = time.perf_counter(), time.process_time()
    switches = resource.getrusage(resource.RUSAGE_SELF).ru_nivcsw
    result = fn()
    return (result, time.perf_counter() - wall, time.process_time() - cpu,
            resource.getrusage(resource.RUSAGE_SELF).ru_nivcsw - switches)


def child(args) -> None:
    """Build, warm up (the first call apart), then run one round per ``run`` line on stdin until ``exit``."""
    name = args._child
    try:
        if name in TORCH_CONTENDERS:
            import torch

            torch.set_num_threads(args.threads)
            torch.set_flush_denormal(args.flush_denormal)
        data, _ = load_data(args.data, args.transitions, args.seed)
        total = args.warmup + args.rounds * args.updates
        (update, setup_s, _, _) = _timed(lambda: build(name, data, total, args.seed, args.jax_updates_per_call))

        def go(n):
            done = update.run(n)
            update.sync()
            return done

        first, first_s, first_cpu, _ = _timed(lambda: go(1))
        rest, rest_s, rest_cpu, _ = _timed(lambda: go(max(args.warmup - first, 0)))
        _send({"ready": True, "setup_seconds": round(setup_s, 2), "first_call_updates": first,
               "first_call_seconds": round(first_s, 2), "first_call_cpu_seconds": round(first_cpu, 2),
               "warmup_updates": first + rest, "warmup_seconds": round(first_s + rest_s, 2),
               "rest_of_warmup_updates_per_second": round(rest / rest_s, 1) if rest else None,
               "affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
               **({"torch_compile": update.method.compiled is not None} if isinstance(update, RmrlUpdate) else {})})
        for line in sys.stdin:
            if line.strip() != "run":
                break
            done, wall, cpu, switches = _timed(lambda: go(args.updates))
            _send({"updates": done, "wall_seconds": round(wall, 3), "cpu_seconds": round(cpu, 3),
                   "involuntary_context_switches": switches})
        _send({"done": True, "peak_rss_mib": _peak_rss_mib(), "notes": update.notes})
    except Exception as err:
        traceback.print_exc()
        _send({"error": f"{type(err).__name__}: {str(err).splitlines()[0][:300] if str(err) else ''}"})
        sys.exit(1)


# --- the orchestration ------------------------------------------------------------------------------

class _Process:
    def __init__(self, name: str, args, cores: str, env: dict):
        argv = [sys.executable, __file__, f"--_child={name}", f"--threads={args.threads}",
                f"--warmup={args.warmup}", f"--updates={args.updates}", f"--rounds={args.rounds}",
                f"--data={args.data}", f"--transitions={args.transitions}", f"--seed={args.seed}",
                f"--jax-updates-per-call={args.jax_updates_per_call}",
                "--flush-denormal" if args.flush_denormal else "--no-flush-denormal"]
        if shutil.which("taskset"):
            argv = ["taskset", "-c", cores, *argv]
        self.name = name
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)

    def receive(self) -> dict:
        for line in self.proc.stdout:
            if line.startswith(MESSAGE):
                return json.loads(line[len(MESSAGE):])
            sys.stderr.write(line)  # anything a library printed
        return {"error": f"the process ended (exit status {self.proc.wait()}) without a reply"}

    def ask(self, command: str) -> dict:
        try:
            self.proc.stdin.write(command + "\n")
            self.proc.stdin.flush()
        except BrokenPipeError:
            return {"error": "the process is gone"}
        return self.receive()

    def close(self) -> dict:
        reply = self.ask("exit")
        self.proc.wait(timeout=60)
        return reply


def child_env(threads: int, cache_dir: str | None) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads), JAX_PLATFORMS="cpu",
               XLA_FLAGS=(f"--xla_cpu_multi_thread_eigen={'false' if threads == 1 else 'true'} "
                          f"intra_op_parallelism_threads={threads}"))
    if cache_dir:
        env["TORCHINDUCTOR_CACHE_DIR"] = cache_dir
    return env


def _version(package: str) -> str | None:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return None


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def _rate(updates: int, seconds: float) -> float:
    return round(updates / seconds, 1) if seconds > 0 else float("nan")


def orchestrate(args) -> dict:
    names = list(dict.fromkeys(args.contenders))
    for name in names:
        if name not in CONTENDERS + OPTIONAL:
            raise SystemExit(f"--contenders: unknown {name!r} (one of {', '.join(CONTENDERS + OPTIONAL)})")
    cores = args.cores or ("0-1" if args.threads == 2 else str(args.core))
    data, data_note = load_data(args.data, args.transitions, args.seed)
    results, notes = {}, []
    if not shutil.which("taskset"):
        notes.append("taskset not found: the processes were not pinned to cores")
    if "jax_corl_style" in names and not (importlib.util.find_spec("jax") and importlib.util.find_spec("optax")):
        names.remove("jax_corl_style")
        results["jax_corl_style"] = {"skipped": "jax and optax are not importable: pip install -e '.[bench]'"}
        notes.append("jax_corl_style skipped: jax/optax not installed (the optional bench extra)")
    cache = None if args.warm_compile_cache else tempfile.mkdtemp(prefix="peers-inductor-")
    env = child_env(args.threads, cache)
    load = {"before": os.getloadavg() if hasattr(os, "getloadavg") else None}
    processes = {}
    try:
        for name in names:  # one warm-up at a time
            log(f"{name}: starting on core(s) {cores}, warm-up of {args.warmup} updates")
            proc = _Process(name, args, cores, env)
            reply = proc.receive()
            if "error" in reply:
                results[name] = {"error": reply["error"]}
                proc.proc.wait()
                log(f"{name}: failed: {reply['error']}")
                continue
            reply.pop("ready", None)
            results[name] = {**reply, "rounds": []}
            processes[name] = proc
            log(f"{name}: warm-up done in {reply['warmup_seconds']} s (first call {reply['first_call_seconds']} s)")
        for r in range(args.rounds):
            order = list(processes) if r % 2 == 0 else list(reversed(processes))  # alternate who goes first
            for name in order:
                if "error" in results[name]:
                    continue
                loadavg = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
                reply = processes[name].ask("run")
                if "error" in reply:
                    results[name]["error"] = reply["error"]
                    continue
                reply.update(updates_per_wall_second=_rate(reply["updates"], reply["wall_seconds"]),
                             updates_per_cpu_second=_rate(reply["updates"], reply["cpu_seconds"]),
                             loadavg_1min_before=loadavg)
                results[name]["rounds"].append(reply)
                log(f"round {r + 1}/{args.rounds} {name}: {reply['updates_per_wall_second']} updates/s wall, "
                    f"{reply['updates_per_cpu_second']} updates/CPU-s")
        for name, proc in processes.items():
            reply = proc.close()
            if "error" in reply:
                results[name].setdefault("error", reply["error"])
            else:
                results[name]["peak_rss_mib"] = reply["peak_rss_mib"]
                if reply["notes"]:
                    results[name]["notes"] = reply["notes"]
    finally:
        for proc in processes.values():
            if proc.proc.poll() is None:
                proc.proc.kill()
        if cache:
            shutil.rmtree(cache, ignore_errors=True)
    load["after"] = os.getloadavg() if hasattr(os, "getloadavg") else None
    _summarise(results)
    return {
        "benchmark": "one IQL update, four implementations, one process each",
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cpu": _cpu_model(), "logical_cpus": os.cpu_count(), "loadavg_before": load["before"],
                    "loadavg_after": load["after"], "python": platform.python_version(),
                    "versions": {p: _version(p) for p in ("torch", "torchrl", "tensordict", "jax", "jaxlib", "optax",
                                                          "numpy")}},
        "settings": {"threads": args.threads, "cores": cores, "data": data_note, "transitions": len(data["reward"]),
                     "observation_dim": OBS, "action_dim": ACT, "hidden": list(HIDDEN), "batch_size": BATCH,
                     "expectile": EXPECTILE, "temperature": TEMPERATURE, "gamma": GAMMA, "tau": TAU, "lr": LR,
                     "actor_schedule": "cosine to 0 over warmup + rounds * updates",
                     "warmup_updates": args.warmup, "updates_per_round": args.updates, "rounds": args.rounds,
                     "jax_updates_per_call": args.jax_updates_per_call, "torch_flush_denormal": args.flush_denormal,
                     "inductor_cache": "default (warm)" if args.warm_compile_cache else "fresh (cold compile)"},
        "reference": REFERENCE,
        "contenders": results,
        "notes": notes,
    }


def _summarise(results: dict) -> None:
    """Each contender's best round and, round by round, its rates over the reference's."""
    ref = results.get(REFERENCE, {}).get("rounds") or []
    for name, res in results.items():
        rounds = res.get("rounds")
        if not rounds:
            continue
        for unit in ("wall", "cpu"):
            key = f"updates_per_{unit}_second"
            res[f"best_{key}"] = max(r[key] for r in rounds)
            if ref and len(ref) == len(rounds):
                res[f"ratio_to_{REFERENCE}_{unit}_per_round"] = [round(r[key] / q[key], 2) for r, q in zip(rounds, ref)]
                res[f"ratio_to_{REFERENCE}_{unit}_best"] = round(res[f"best_{key}"] / max(q[key] for q in ref), 2)


def main(argv: list | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2, help="interleaved rounds (2)")
    parser.add_argument("--updates", type=int, default=800, help="updates per round (800)")
    parser.add_argument("--warmup", type=int, default=200, help="warm-up updates, the compiling first call among them")
    parser.add_argument("--threads", type=int, choices=(1, 2), default=1, help="1: one core (--core); 2: cores 0-1")
    parser.add_argument("--core", type=int, default=0, help="the core for --threads 1 (0)")
    parser.add_argument("--cores", default="", help="a taskset core list overriding --core / the 0-1 of --threads 2")
    parser.add_argument("--contenders", nargs="+", default=list(CONTENDERS),
                        help=f"any of {' '.join(CONTENDERS + OPTIONAL)} (default: the first four)")
    parser.add_argument("--data", default="auto", help="auto (door-human-v0.hdf5 when present) | synthetic | PATH")
    parser.add_argument("--transitions", type=int, default=25_000, help="synthetic transitions (25000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jax-updates-per-call", type=int, default=8)
    parser.add_argument("--flush-denormal", action=argparse.BooleanOptionalAction, default=True,
                        help="torch.set_flush_denormal in the torch contenders, as rmrl's trainer does (on)")
    parser.add_argument("--warm-compile-cache", action="store_true",
                        help="use torch inductor's default cache (a fresh one by default: cold compile times)")
    parser.add_argument("--_child", default="", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if min(args.rounds, args.updates, args.warmup, args.jax_updates_per_call) < 1:
        parser.error("--rounds, --updates, --warmup and --jax-updates-per-call must be at least 1")
    if args._child:
        child(args)
        return
    print(json.dumps(orchestrate(args), indent=2))


if __name__ == "__main__":
    main()
