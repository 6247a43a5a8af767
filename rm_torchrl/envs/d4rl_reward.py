"""D4RL's dense Adroit rewards from gymnasium-robotics' ``AdroitHandDoor-v1`` / ``AdroitHandRelocate-v1``.

gymnasium-robotics 1.4.2's v1 dense rewards *add* ``0.1 * ||palm - handle||`` (door) and
``0.1 * ||palm - ball||`` (relocate), where D4RL's ``door-v0`` / ``relocate-v0`` (the DAPG
``mj_envs`` code that made the datasets and the reference scores) subtract them; every other term
(hinge angle, velocity cost, lift and target bonuses) is the same. Upstream fixed the sign only in
the v2 envs of gymnasium-robotics >= 1.4.3 (Farama-Foundation/Gymnasium-Robotics PR 220). So the
D4RL reward of a v1 transition is the v1 reward minus ``0.2 * ||palm - x||``, and both distances
are part of the v1 observation after the step:

- door (``door_v0.py`` in D4RL's ``hand_manipulation_suite``): ``obs[35:38]`` is palm - handle;
- relocate (``relocate_v0.py`` there): ``obs[30:33]`` is palm - ball.

Checked against the stored rewards of D4RL's ``door-human-v0.hdf5`` in ``tests/test_envs_d4rl_reward.py``.

gymnasium-robotics 1.2.1-1.4.2 print :data:`ADROIT_NOTICE` on stderr when imported (through
``farama_notifications``, not :mod:`warnings`); :func:`import_gymnasium_robotics` leaves it out
for an evaluation env this transform corrects, and only then.
"""
from __future__ import annotations

import sys

import torch
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from rm_torchrl.errors import RMError

#: task -> (slice of the v1 observation holding the palm-to-target offset, observation size).
DISTANCE_SLICES = {"door": (slice(35, 38), 39), "relocate": (slice(30, 33), 39)}
#: D4RL subtracts 0.1 * distance where v1 adds it: the correction is twice that.
CORRECTION = 0.2
#: gymnasium ids of the v1 envs whose dense reward this corrects -> task.
V1_ENVS = {"AdroitHandDoor-v1": "door", "AdroitHandRelocate-v1": "relocate"}


#: The start of the notice gymnasium-robotics 1.2.1-1.4.2 print when imported: the v1 Adroit dense rewards changed.
ADROIT_NOTICE = ("AdroitHandRelocateDense-v1, AdroitHandHammerDense-v1, AdroitHandDoorDense-v1 environment's "
                 "reward functions were updated")


def import_gymnasium_robotics(quiet: bool):
    """``gymnasium_robotics``, imported without its :data:`ADROIT_NOTICE` when ``quiet`` (the env is wrapped
    by :class:`D4RLReward`, which restores D4RL's reward); every other notice, and this one otherwise, stays."""
    if quiet and "gymnasium_robotics" not in sys.modules:  # it prints only on the first import
        try:
            from farama_notifications import notifications
        except ImportError:
            notifications = {}
        saved = notifications.get("gymnasium_robotics")
        if isinstance(saved, dict):
            notifications["gymnasium_robotics"] = {
                version: text for version, text in saved.items() if not str(text).startswith(ADROIT_NOTICE)}
        try:
            import gymnasium_robotics
        finally:
            if isinstance(saved, dict):
                notifications["gymnasium_robotics"] = saved
    import gymnasium_robotics

    return gymnasium_robotics


def d4rl_reward_task(env_id: str, env_kwargs: dict | None = None) -> str | None:
    """The :class:`D4RLReward` task for evaluation env ``env_id``, or None when its reward needs no correction
    this module knows (other envs) or cannot be corrected (the sparse variant)."""
    if str((env_kwargs or {}).get("reward_type", "dense")).lower() != "dense":
        return None
    return V1_ENVS.get(env_id)


class D4RLReward(Transform):
    """Turns a v1 Adroit env's dense ``reward`` into D4RL's reward for the same transition.

    Place it before any observation normalisation: it reads the raw observation after the step.

    Args:
        task: ``"door"`` or ``"relocate"``.
        observation_key: the raw v1 observation.
        reward_key: the reward entry it rewrites in place.

    Example:
        >>> from torchrl.envs import GymEnv, TransformedEnv
        >>> _ = import_gymnasium_robotics(quiet=True)  # registers the Adroit envs
        >>> env = TransformedEnv(GymEnv("AdroitHandDoor-v1"), D4RLReward("door"))
        >>> rollout = env.rollout(5)  # rollout["next", "reward"] is D4RL's door reward
        >>> rollout["next", "reward"].shape
        torch.Size([5, 1])

    Also works outside an env, on transitions with ``("next", observation_key)`` and
    ``("next", reward_key)`` (a replay buffer of v1 rollouts), and on one step's root entries:

        >>> import torch
        >>> from tensordict import TensorDict
        >>> step = TensorDict({"observation": torch.zeros(2, 39), "reward": torch.ones(2, 1)}, batch_size=[2])
        >>> D4RLReward("door")(step)["reward"].squeeze(-1)
        tensor([1., 1.])
    """

    def __init__(self, task: str, observation_key="observation", reward_key="reward"):
        if task not in DISTANCE_SLICES:
            raise RMError(f"D4RLReward: task must be one of {sorted(DISTANCE_SLICES)}, got {task!r}")
        super().__init__(in_keys=[observation_key, reward_key], out_keys=[reward_key])
        self.task = task
        self.observation_key, self.reward_key = observation_key, reward_key
        self._slice, self._size = DISTANCE_SLICES[task]

    def _d4rl(self, observation: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
        if observation.shape[-1] != self._size:
            raise RMError(f"D4RLReward({self.task!r}): expects the {self._size}-value v1 observation, "
                          f"got {observation.shape[-1]} values")
        distance = torch.linalg.vector_norm(observation[..., self._slice].to(torch.float64), dim=-1)
        distance = distance.reshape(reward.shape).to(reward.dtype)
        return reward - CORRECTION * distance

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        """Rewrites the root reward from the root observation: an env step's output, or one step's TensorDict."""
        missing = [k for k in (self.observation_key, self.reward_key) if k not in next_tensordict.keys(True)]
        if missing:
            raise RMError(f"D4RLReward({self.task!r}): the transition has no {missing[0]!r} entry (it reads "
                          f"{self.observation_key!r} and {self.reward_key!r}, at the root or under 'next')")
        reward = next_tensordict.get(self.reward_key)
        next_tensordict.set(self.reward_key, self._d4rl(next_tensordict.get(self.observation_key), reward))
        return next_tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._call(next_tensordict)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Transitions (``("next", reward)``, a replay buffer of rollouts) or a step's own root entries."""
        nested = tensordict.get("next", None)
        if isinstance(nested, TensorDictBase) and self.reward_key in nested.keys(True):
            self._call(nested)
            return tensordict
        return self._call(tensordict)
