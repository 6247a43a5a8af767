"""BCQ (Fujimoto et al. 2019) as a TorchRL LossModule: rm_torchrl.methods.bcq."""
from __future__ import annotations

import warnings

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import ValueOperator
from torchrl.objectives import SoftUpdate
from torchrl.objectives.utils import ValueEstimators

from rm_torchrl.methods.bcq import (
    BCQCritic,
    BCQLoss,
    BCQPerturbation,
    BCQVAE,
    make_bcq_loss,
    make_bcq_optimizers,
)

B, OBS, ACT = 32, 5, 3
SMALL = dict(vae_hidden=(32, 32), actor_hidden=(32, 32), critic_hidden=(32, 32))
# obs layout -> (observation keys, {key: width})
LAYOUTS = {
    "one_key": (["observation"], {"observation": OBS}),
    "two_keys": (["observation", "rm_encoding"], {"observation": OBS, "rm_encoding": 2}),
}


@pytest.fixture(autouse=True)
def _quiet_single_thread():
    # tiny networks: one intra-op thread is fastest and immune to a busy machine
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="No target network updater")
            yield
    finally:
        torch.set_num_threads(threads)


def make_batch(widths: dict, batch: int = B, max_action: float = 1.0, gen=None) -> TensorDict:
    gen = gen or torch.Generator().manual_seed(0)
    obs = {k: torch.randn(batch, w, generator=gen) for k, w in widths.items()}
    nxt = {k: torch.randn(batch, w, generator=gen) for k, w in widths.items()}
    terminated = torch.rand(batch, 1, generator=gen) < 0.2
    return TensorDict(
        {
            **obs,
            "action": (torch.rand(batch, ACT, generator=gen) * 2 - 1) * max_action,
            "next": {
                **nxt,
                "reward": torch.randn(batch, 1, generator=gen),
                "done": terminated.clone(),
                "terminated": terminated,
            },
        },
        [batch],
    )


def make_loss(layout: str = "one_key", **kwargs) -> tuple[BCQLoss, TensorDict]:
    keys, widths = LAYOUTS[layout]
    torch.manual_seed(0)
    loss = make_bcq_loss(sum(widths.values()), ACT, observation_keys=keys, **{**SMALL, **kwargs})
    return loss, make_batch(widths, max_action=float(kwargs.get("max_action", 1.0)))


# --------------------------------------------------------------------------------------------
# networks
# --------------------------------------------------------------------------------------------


def test_reference_defaults():
    vae = BCQVAE(OBS, ACT)
    assert vae.latent_dim == 2 * ACT
    assert [m.out_features for m in vae.encoder if isinstance(m, nn.Linear)] == [750, 750]
    assert [m.out_features for m in vae.decoder if isinstance(m, nn.Linear)] == [750, 750, ACT]
    actor = BCQPerturbation(OBS, ACT)
    assert actor.phi == 0.05
    assert [m.out_features for m in actor.net if isinstance(m, nn.Linear)] == [400, 300, ACT]
    critic = BCQCritic(OBS, ACT)
    assert [m.out_features for m in critic.net if isinstance(m, nn.Linear)] == [400, 300, 1]
    loss = BCQLoss(vae, actor, critic)
    assert (loss.lmbda, loss.num_target_samples, loss.num_eval_samples, loss.kl_weight) == (0.75, 10, 10, 0.5)
    assert loss.num_qvalue_nets == 2 and loss.loss_function == "l2"
    assert float(loss.value_estimator.gamma) == pytest.approx(0.99)
    # the twin critics are independent copies
    w = loss.qvalue_network_params["net", "0", "weight"]
    assert w.shape == (2, 400, OBS + ACT) and not torch.equal(w[0], w[1])


def test_vae_and_perturbation_ranges():
    torch.manual_seed(0)
    vae = BCQVAE(OBS, ACT, max_action=2.0, hidden=(16, 16))
    s, a = torch.randn(4, 7, OBS), torch.rand(4, 7, ACT) * 4 - 2
    mean, log_std = vae.encode(s, a * 1e3)
    assert mean.shape == log_std.shape == (4, 7, 2 * ACT)
    assert log_std.min() >= -4 and log_std.max() <= 15
    recon, _, _ = vae(s, a)
    assert recon.shape == a.shape and recon.abs().max() <= 2.0
    samples = vae.sample(s[0], 10)
    assert samples.shape == (7, 10, ACT) and samples.abs().max() <= 2.0
    # a latent far outside [-0.5, 0.5] decodes differently from the clipped prior samples
    torch.manual_seed(1)
    z = torch.randn(7, 2 * ACT).clamp(-0.5, 0.5)
    torch.manual_seed(1)
    assert torch.equal(vae.decode(s[0]), vae.decode(s[0], z))

    actor = BCQPerturbation(OBS, ACT, max_action=2.0, phi=0.05, hidden=(16,))
    out = actor(s, a)
    assert out.shape == a.shape and out.abs().max() <= 2.0
    assert (out - a).abs().max() <= 0.05 * 2.0 + 1e-6


# --------------------------------------------------------------------------------------------
# loss
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_loss_shapes_and_finite(layout):
    loss, td = make_loss(layout)
    out = loss(td)
    assert set(loss.out_keys) == set(out.keys())
    for key in loss.out_keys:
        assert out[key].shape == (), key
        assert torch.isfinite(out[key]), key
    assert sorted(k for k in out.keys() if k.startswith("loss_")) == ["loss_actor", "loss_qvalue", "loss_vae"]
    assert td["td_error"].shape == (B,) and (td["td_error"] >= 0).all()

    loss.reduction = "none"
    out = loss(td)
    for key in ("loss_vae", "loss_actor", "loss_qvalue"):
        assert out[key].shape == (B,), key


def _groups(loss: BCQLoss) -> dict:
    return {
        "loss_vae": list(loss.vae_network_params.parameters()),
        "loss_actor": list(loss.actor_network_params.parameters()),
        "loss_qvalue": list(loss.qvalue_network_params.parameters()),
    }


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_each_loss_only_reaches_its_own_parameters(layout):
    loss, td = make_loss(layout)
    groups = _groups(loss)
    assert all(groups.values())
    ids = [id(p) for ps in groups.values() for p in ps]
    assert len(ids) == len(set(ids)) == len(list(loss.parameters()))
    for target in (loss.target_actor_network_params, loss.target_qvalue_network_params):
        assert not any(t.requires_grad for t in target.values(True, True))

    for name in groups:
        loss.zero_grad(set_to_none=True)
        loss(td.clone())[name].backward()
        for other, params in groups.items():
            grads = [p.grad for p in params]
            if other == name:
                assert all(g is not None for g in grads), name
                assert sum(g.abs().sum() for g in grads) > 0, name
            else:
                assert all(g is None or not g.any() for g in grads), (name, other)


def test_both_critics_get_gradients_and_actor_uses_q1_only():
    loss, td = make_loss()
    loss(td)["loss_qvalue"].backward()
    g = loss.qvalue_network_params["net", "0", "weight"].grad
    assert g[0].abs().sum() > 0 and g[1].abs().sum() > 0

    # the actor loss is -Q1: changing critic 2 leaves it unchanged
    torch.manual_seed(3)
    before = loss.actor_loss(td)[0]
    with torch.no_grad():
        for p in loss.qvalue_network_params.values(True, True):
            p[1].add_(1.0)
    torch.manual_seed(3)
    assert torch.equal(loss.actor_loss(td)[0], before)


def test_target_matches_manual_soft_clipped_double_q():
    loss, td = make_loss("two_keys")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.9)
    with torch.no_grad():  # make the targets differ from the online networks
        for p in loss.target_qvalue_network_params.values(True, True):
            p.add_(0.1 * torch.randn_like(p))
    torch.manual_seed(7)
    _, meta = loss.qvalue_loss(td)

    n, lam = loss.num_target_samples, loss.lmbda
    nxt = torch.cat([td["next", "observation"], td["next", "rm_encoding"]], -1)
    rep = nxt.unsqueeze(1).expand(B, n, nxt.shape[-1])
    vae = loss.vae_network
    torch.manual_seed(7)
    z = torch.randn(B, n, vae.latent_dim).clamp(-0.5, 0.5)
    with torch.no_grad():
        with loss.vae_network_params.to_module(vae):
            sampled = vae.decode(rep, z)
        with loss.target_actor_network_params.to_module(loss.actor_network):
            a_next = loss.actor_network(rep, sampled)
        qs = []
        for i in range(2):
            with loss.target_qvalue_network_params[i].to_module(loss.qvalue_network):
                qs.append(loss.qvalue_network(rep, a_next).squeeze(-1))
    q1, q2 = qs
    soft = lam * torch.minimum(q1, q2) + (1 - lam) * torch.maximum(q1, q2)
    v_next = soft.max(1).values
    target = td["next", "reward"].squeeze(-1) + 0.9 * (~td["next", "terminated"]).squeeze(-1).float() * v_next
    assert meta["target_value"] == pytest.approx(target.mean().item(), rel=1e-5, abs=1e-5)


def test_vmap_loop_tdmodule_and_list_critics_agree():
    keys, widths = LAYOUTS["two_keys"]
    dim = sum(widths.values())

    def build(q, **kw):
        torch.manual_seed(0)
        vae = BCQVAE(dim, ACT, hidden=(16, 16))
        actor = BCQPerturbation(dim, ACT, hidden=(16, 16))
        return BCQLoss(vae, actor, q, observation_keys=keys, **kw)

    class Concat(nn.Module):
        def __init__(self, critic):
            super().__init__()
            self.critic = critic

        def forward(self, obs, rm, action):
            return self.critic(torch.cat([obs, rm], -1), action)

    torch.manual_seed(1)
    critics = [BCQCritic(dim, ACT, hidden=(16, 16)) for _ in range(2)]
    td = make_batch(widths)
    ref = build(critics)
    outs = []
    for loss in (
        ref,
        build(critics, deactivate_vmap=True),
        build([ValueOperator(Concat(c), in_keys=[*keys, "action"]) for c in critics]),
    ):
        torch.manual_seed(5)
        outs.append(loss(td.clone()))
    for out in outs[1:]:
        for key in ("loss_qvalue", "loss_actor", "q_mean", "target_value"):
            assert out[key].item() == pytest.approx(outs[0][key].item(), rel=1e-5, abs=1e-6), key


def test_set_keys():
    loss, td = make_loss("two_keys")
    renamed = TensorDict(
        {
            "obs": td["observation"],
            "u": td["rm_encoding"],
            "act": td["action"],
            "next": {
                "obs": td["next", "observation"],
                "u": td["next", "rm_encoding"],
                "rew": td["next", "reward"],
                "d": td["next", "done"],
                "t": td["next", "terminated"],
            },
        },
        [B],
    )
    torch.manual_seed(0)
    expected = loss(td)
    loss.set_keys(observation=["obs", "u"], action="act", reward="rew", done="d", terminated="t", priority="prio")
    assert loss.observation_keys == ["obs", "u"]
    assert set(map(str, loss.in_keys)) >= {"obs", "u", "act", str(("next", "rew")), str(("next", "t"))}
    torch.manual_seed(0)
    out = loss(renamed)
    assert "prio" in renamed.keys()
    for key in ("loss_vae", "loss_actor", "loss_qvalue"):
        assert out[key].item() == pytest.approx(expected[key].item(), rel=1e-6), key
    policy = loss.make_policy()
    assert policy.in_keys == ["obs", "u"] and policy.out_keys == ["act"]
    with pytest.raises(ValueError):
        loss.set_keys(not_a_key="x")


def test_soft_update_moves_targets():
    loss, td = make_loss()
    updater = SoftUpdate(loss, tau=0.005)
    old_actor = loss.target_actor_network_params.clone()
    old_q = loss.target_qvalue_network_params.clone()
    opts = make_bcq_optimizers(loss)
    for name, opt in opts.items():
        opt.zero_grad()
        loss(td.clone())[name].backward()
        opt.step()
    updater.step()
    for src, tgt, old in (
        (loss.actor_network_params, loss.target_actor_network_params, old_actor),
        (loss.qvalue_network_params, loss.target_qvalue_network_params, old_q),
    ):
        moved = False
        for key, p in src.items(True, True):
            if not isinstance(p, nn.Parameter):
                continue
            expected = 0.995 * old[key] + 0.005 * p.detach()
            torch.testing.assert_close(tgt[key], expected)
            moved = moved or not torch.equal(tgt[key], old[key])
        assert moved
    assert "target_vae_network_params" not in dict(loss.named_children())


def test_optimizers_cover_groups_without_weight_decay():
    loss, _ = make_loss()
    opts = make_bcq_optimizers(loss)
    groups = _groups(loss)
    for name, opt in opts.items():
        assert isinstance(opt, torch.optim.Adam)
        (group,) = opt.param_groups
        assert group["lr"] == 1e-3 and group["weight_decay"] == 0
        assert {id(p) for p in group["params"]} == {id(p) for p in groups[name]}


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_policy_module(layout):
    loss, td = make_loss(layout, max_action=2.0)
    policy = loss.make_policy()
    assert isinstance(policy, TensorDictModule)
    assert policy.in_keys == LAYOUTS[layout][0] and policy.out_keys == ["action"]
    obs = td.select(*policy.in_keys)
    out = policy(obs)
    action = out["action"]
    assert action.shape == (B, ACT) and not action.requires_grad
    assert action.abs().max() <= 2.0
    # unbatched and multi-dim batches
    single = policy(obs[0])
    assert single["action"].shape == (ACT,)
    assert policy(obs.reshape(4, 8))["action"].shape == (4, 8, ACT)

    # the chosen action is the argmax of Q1 over the perturbed samples
    state = torch.cat([td[k] for k in policy.in_keys], -1)
    torch.manual_seed(11)
    chosen = loss.select_action(state, num_samples=10)
    torch.manual_seed(11)
    rep = state.unsqueeze(1).expand(B, 10, state.shape[-1])
    with torch.no_grad():
        with loss.vae_network_params.to_module(loss.vae_network):
            sampled = loss.vae_network.decode(rep)
        with loss.actor_network_params.to_module(loss.actor_network):
            acts = loss.actor_network(rep, sampled)
        with loss.qvalue_network_params[0].to_module(loss.qvalue_network):
            q1 = loss.qvalue_network(rep, acts).squeeze(-1)
    torch.testing.assert_close(chosen, acts[torch.arange(B), q1.argmax(1)])


@pytest.mark.slow
def test_training_on_linear_behaviour_policy():
    torch.manual_seed(0)
    n, obs_dim = 512, 5
    W = torch.randn(obs_dim, ACT) * 0.3
    states = torch.randn(n, obs_dim)
    actions = (states @ W).clamp(-0.95, 0.95)
    next_states = states + 0.1 * torch.randn(n, obs_dim)
    rewards = -(actions.pow(2).sum(-1, keepdim=True))
    terminated = torch.rand(n, 1) < 0.05
    data = TensorDict(
        {
            "observation": states,
            "action": actions,
            "next": {"observation": next_states, "reward": rewards, "done": terminated, "terminated": terminated},
        },
        [n],
    )
    loss = make_bcq_loss(obs_dim, ACT, vae_hidden=(64, 64), actor_hidden=(64, 64), critic_hidden=(64, 64))
    opts = make_bcq_optimizers(loss)
    updater = SoftUpdate(loss, tau=0.005)
    recon, qloss = [], []
    for _ in range(300):
        batch = data[torch.randint(0, n, (64,))]
        out = loss(batch)
        for opt in opts.values():
            opt.zero_grad(set_to_none=True)
        (out["loss_vae"] + out["loss_actor"] + out["loss_qvalue"]).backward()
        for opt in opts.values():
            opt.step()
        updater.step()
        recon.append(out["vae_recon"].item())
        qloss.append(out["loss_qvalue"].item())
    first, last = sum(recon[:20]) / 20, sum(recon[-20:]) / 20
    assert last < 0.3 * first, (first, last)
    assert all(torch.isfinite(torch.tensor(qloss)))
    # the policy stays close to the behaviour action (VAE + phi-bounded perturbation)
    policy_action = loss.make_policy()(data[:128].select("observation"))["action"]
    err = (policy_action - actions[:128]).abs().mean()
    assert err < (actions[:128] - actions[:128].mean(0)).abs().mean()


def test_bad_arguments():
    vae, actor, critic = BCQVAE(OBS, ACT, hidden=(8,)), BCQPerturbation(OBS, ACT, hidden=(8,)), BCQCritic(OBS, ACT, hidden=(8,))
    with pytest.raises(TypeError):
        BCQLoss(TensorDictModule(vae, in_keys=["observation", "action"], out_keys=["x"]), actor, critic)
    with pytest.raises(ValueError):
        BCQLoss(vae, actor, critic, lmbda=1.5)
    with pytest.raises(ValueError):
        BCQLoss(vae, actor, critic, observation_keys=[])
    with pytest.raises(NotImplementedError):
        BCQLoss(vae, actor, critic).make_value_estimator(ValueEstimators.GAE)


def test_recipe_build_method():
    from rm_torchrl.methods.config import BCQConfig, MethodConfig
    from rm_torchrl.train.config import Recipe
    from rm_torchrl.methods.registry import METHODS, build_method

    recipe = Recipe(method=MethodConfig(name="bcq", bcq=BCQConfig(lmbda=0.5, phi=0.1, vae_hidden=[32, 32])))
    recipe.trainer.gamma = 0.95
    recipe.network.hidden = [24, 16]
    recipe.optim.lr_actor, recipe.optim.lr_critic, recipe.optim.lr_value = 1e-3, 2e-3, 3e-3
    keys, widths = LAYOUTS["two_keys"]
    method = build_method(recipe.method, recipe.network, recipe.optim, recipe.trainer, keys, sum(widths.values()), ACT)
    loss = method.loss
    assert isinstance(loss, BCQLoss) and loss.lmbda == 0.5 and loss.actor_network.phi == 0.1
    assert float(loss.value_estimator.gamma) == pytest.approx(0.95)
    assert len(method.optimizers) == 3
    assert [o.param_groups[0]["lr"] for o in method.optimizers] == [3e-3, 1e-3, 2e-3]  # vae, actor, critics
    assert all(g["weight_decay"] == 0 for o in method.optimizers for g in o.param_groups)
    widths_of = [p.shape[0] for p in loss.actor_network_params.flatten_keys().values() if p.ndim == 2]
    assert widths_of[:2] == [24, 16], widths_of
    td = make_batch(widths, batch=16)
    out = loss(td)
    sum(out[t] for t in METHODS["bcq"].terms).backward()
    for opt in method.optimizers:
        opt.step()
    method.target_updater.step()
    assert method.policy(td.select(*keys))["action"].shape == (16, ACT)
