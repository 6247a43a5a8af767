"""Online use of the event-ordered RM: TorchRL environment transforms."""
from rm_torchrl.envs.d4rl_reward import D4RLReward, d4rl_reward_task, import_gymnasium_robotics
from rm_torchrl.envs.kitchen_v0 import D4RL_V0_TASKS, KitchenV0Observation, kitchen_v0_goal
from rm_torchrl.envs.rm_transform import RMEnvTransform

__all__ = ["RMEnvTransform", "D4RLReward", "d4rl_reward_task", "import_gymnasium_robotics", "KitchenV0Observation", "kitchen_v0_goal",
           "D4RL_V0_TASKS"]
