"""Scripted demonstrations recorded as local Minari datasets (``rmrl generate``).

``GENERATORS`` maps the names ``rmrl generate`` accepts to a ``Generator``: an environment id and a
scripted policy. ``generate_dataset`` records one atomically (see ``record``).
"""
from __future__ import annotations

from rm_torchrl.generate.record import GENERATE_METADATA_KEY, Generator, collect, generate_dataset
from rm_torchrl.generate.kitchen import ENV_KWARGS as KITCHEN_ENV_KWARGS
from rm_torchrl.generate.kitchen import KitchenPlayController, keep_all, keep_without_all_goals
from rm_torchrl.generate.relocate import RelocateController



def _kitchen(name: str, mix: str, keep, description: str) -> Generator:
    """A FrankaKitchen-v1 play generator (all seven tasks in the observation, 800-step episodes)."""
    return Generator(name=name, env_id="FrankaKitchen-v1", policy=KitchenPlayController, description=description,
                     env_kwargs=KITCHEN_ENV_KWARGS, policy_kwargs={"mix": mix}, keep=keep, events="kitchen",
                     max_steps=800)


GENERATORS = {
    "relocate-human": Generator(
        name="relocate-human",
        env_id="AdroitHandRelocate-v1",
        policy=RelocateController,
        description="Adroit relocate: grasp the ball, carry it to the target and hold it (scripted, human-like "
                    "variety of speed and style)",
        events="relocate",
        max_steps=800,  # D4RL's human demonstrations take about 400 steps, some far more
    ),
    "kitchen-partial": _kitchen(
        "kitchen-partial", "partial", keep_all,
        "Franka kitchen play like D4RL kitchen-partial: four scripted skills an episode, mostly in one habitual "
        "order; about 30% of the episodes plan all four goal tasks (microwave, kettle, light switch, slide cabinet), "
        "all episodes are kept",
    ),
    "kitchen-mixed": _kitchen(
        "kitchen-mixed", "mixed", keep_without_all_goals,
        "Franka kitchen play like D4RL kitchen-mixed: subsets of the tasks, no episode completes all four goal tasks",
    ),
}

__all__ = ["GENERATORS", "GENERATE_METADATA_KEY", "Generator", "KitchenPlayController", "RelocateController", "collect",
           "generate_dataset"]
