"""The D4RL kitchen v0 observation, rebuilt from a gymnasium-robotics ``FrankaKitchen-v1`` env.

Policies trained on D4RL ``kitchen-{complete,partial,mixed}-v0`` read a flat 60-dim observation:
``[0:9]`` robot joint positions (MuJoCo ``qpos[0:9]``), ``[9:30]`` object positions
(``qpos[9:30]``) and ``[30:60]`` a constant goal vector: zeros except the goal joints of the four
D4RL tasks (microwave, kettle, light switch, slide cabinet). ``FrankaKitchen-v1`` gives a dict
whose ``observation`` is 59-dim (robot qpos, robot qvel, object qpos, object qvel, all with
simulated noise); :class:`KitchenV0Observation` replaces it with the v0 layout so that such a
policy and the ``kitchen-v0`` event spec work on the live environment::

    env = TransformedEnv(
        GymEnv("FrankaKitchen-v1", tasks_to_complete=["microwave", "kettle", "light switch", "slide cabinet"]),
        Compose(KitchenV0Observation(), RMEnvTransform("kitchen-v0")),
    )
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from rm_torchrl.errors import RMError

#: qpos indices and goal values of each kitchen task (D4RL adept_envs / gymnasium-robotics).
KITCHEN_TASK_INDICES: dict[str, list[int]] = {
    "bottom burner": [11, 12],
    "top burner": [15, 16],
    "light switch": [17, 18],
    "slide cabinet": [19],
    "hinge cabinet": [20, 21],
    "microwave": [22],
    "kettle": [23, 24, 25, 26, 27, 28, 29],
}
KITCHEN_TASK_GOALS: dict[str, list[float]] = {
    "bottom burner": [-0.88, -0.01],
    "top burner": [-0.92, -0.01],
    "light switch": [-0.69, -0.05],
    "slide cabinet": [0.37],
    "hinge cabinet": [0.0, 1.45],
    "microwave": [-0.75],
    "kettle": [-0.23, 0.75, 1.62, 0.99, 0.0, 0.0, -0.06],
}
#: The goal tasks of kitchen-complete/partial/mixed-v0.
D4RL_V0_TASKS = ("microwave", "kettle", "light switch", "slide cabinet")
_SOURCES = ("qpos", "observation")


def kitchen_v0_goal(tasks: Sequence[str] = D4RL_V0_TASKS) -> torch.Tensor:
    """The 30-dim goal half of the v0 observation: zeros except each task's goal joints."""
    goal = torch.zeros(30, dtype=torch.float64)
    for task in tasks:
        if task not in KITCHEN_TASK_INDICES:
            raise RMError(f"unknown kitchen task {task!r}; the tasks are {list(KITCHEN_TASK_INDICES)}")
        goal[KITCHEN_TASK_INDICES[task]] = torch.tensor(KITCHEN_TASK_GOALS[task], dtype=torch.float64)
    return goal


class KitchenV0Observation(Transform):
    """Writes the D4RL kitchen v0 60-dim observation into ``observation`` (replacing the 59-dim one).

    Args:
        source: ``"qpos"`` (default) reads the exact MuJoCo ``qpos`` of the wrapped
            ``GymEnv`` (``base_env._env.unwrapped.data.qpos``), so the transform must sit on a
            ``GymEnv("FrankaKitchen-v1")`` or a ``GymWrapper`` of a gymnasium ``SyncVectorEnv`` of them
            (inside each worker of a ``SerialEnv``/``ParallelEnv``);
            ``"observation"`` rebuilds it from the 59-dim observation itself (``[0:9]`` and
            ``[18:39]``, which carry the env's small simulated noise) and works anywhere, also
            outside ``SerialEnv``/``ParallelEnv``.
        tasks: the tasks whose goals fill ``[30:60]``; the default is the four D4RL v0 tasks,
            whatever ``tasks_to_complete`` the env was made with (it is what the datasets hold).
        out_key: where the v0 observation goes (``observation`` by default).
        original_key: if given, the 59-dim observation is kept under this key.
    """

    def __init__(
        self,
        source: str = "qpos",
        tasks: Sequence[str] = D4RL_V0_TASKS,
        out_key: str = "observation",
        original_key: str | None = None,
    ):
        if source not in _SOURCES:
            raise RMError(f"unknown source {source!r}; use one of {list(_SOURCES)}")
        if original_key is not None and original_key == out_key:
            raise RMError("original_key must differ from out_key")
        out_keys = [out_key] + ([original_key] if original_key else [])
        super().__init__(in_keys=["observation"], out_keys=out_keys)
        self.source = source
        self.tasks = tuple(tasks)
        self.out_key = out_key
        self.original_key = original_key
        self.register_buffer("goal", kitchen_v0_goal(self.tasks))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(source={self.source!r}, tasks={list(self.tasks)})"

    # ------------------------------------------------------------------ data
    def _qpos(self) -> np.ndarray:
        """``qpos[:30]`` of the wrapped env, ``(30,)``, or ``(N, 30)`` under a gymnasium vector env of N."""
        parent = self.parent
        base = getattr(parent, "base_env", None) if parent is not None else None
        gym_env = getattr(base, "_env", None) if base is not None else None
        batched = base is not None and len(base.batch_size) > 0
        subs = getattr(gym_env, "envs", None) if batched else [gym_env]
        datas = [getattr(getattr(e, "unwrapped", None), "data", None) for e in subs or []]
        if not datas or any(d is None or not hasattr(d, "qpos") for d in datas) or \
                (batched and (len(base.batch_size) != 1 or len(datas) != base.batch_size[0])):
            raise RMError(
                "KitchenV0Observation(source='qpos') reads the MuJoCo state of a GymEnv('FrankaKitchen-v1') or of "
                "a gymnasium SyncVectorEnv of them, but its base env is "
                f"{type(base).__name__ if base is not None else 'missing'}; put the transform inside each "
                "worker of a batched env, or use source='observation'"
            )
        if datas[0].qpos.shape[0] < 30:
            raise RMError(f"KitchenV0Observation: the env's qpos has {datas[0].qpos.shape[0]} entries, expected 30 (FrankaKitchen-v1)")
        return np.stack([d.qpos[:30] for d in datas]) if batched else datas[0].qpos[:30].copy()

    def _v0(self, obs: torch.Tensor) -> torch.Tensor:
        if obs.shape[-1] != 59:
            raise RMError(
                f"KitchenV0Observation expects the 59-dim FrankaKitchen-v1 observation, got last dimension "
                f"{obs.shape[-1]} (is it already transformed?)"
            )
        if self.source == "qpos":
            qpos = torch.as_tensor(self._qpos(), dtype=obs.dtype, device=obs.device)
            state = qpos.expand(*obs.shape[:-1], 30)
        else:
            state = torch.cat([obs[..., 0:9], obs[..., 18:39]], -1)
        goal = self.goal.to(dtype=obs.dtype, device=obs.device).expand(*obs.shape[:-1], 30)
        return torch.cat([state, goal], -1)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        obs = next_tensordict.get("observation", None)
        if obs is None:
            raise RMError("KitchenV0Observation: the env output has no 'observation' entry")
        if self.original_key is not None:
            next_tensordict.set(self.original_key, obs)
        next_tensordict.set(self.out_key, self._v0(obs))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.source == "qpos":
            raise RMError("KitchenV0Observation(source='qpos') needs the live env; use source='observation' on stored data")
        return self._call(tensordict)

    # ------------------------------------------------------------------ specs
    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        old = observation_spec["observation"] if "observation" in observation_spec.keys() else None
        if old is None:
            raise RMError("KitchenV0Observation: the env has no 'observation' entry (is it FrankaKitchen-v1?)")
        if old.shape[-1] != 59:
            raise RMError(f"KitchenV0Observation expects a 59-dim 'observation', the env's is {tuple(old.shape)}")
        if self.original_key is not None:
            observation_spec[self.original_key] = old.clone()
        observation_spec[self.out_key] = Unbounded(
            shape=(*old.shape[:-1], 60), dtype=old.dtype, device=old.device
        )
        return observation_spec
