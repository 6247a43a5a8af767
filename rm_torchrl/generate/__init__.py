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



def describe_generated(dataset_id: str, name: str) -> str:
    """What ``rmrl generate NAME`` recorded into ``dataset_id``, where it is, and how to refine it."""
    import minari
    from minari.storage import get_dataset_path

    from rm_torchrl.generate.cloned import CLONED

    dataset = minari.load_dataset(dataset_id)
    record = dataset.storage.metadata.get(GENERATE_METADATA_KEY, {})
    if name in CLONED:
        mix = record.get("mix", {})
        lines = [f"generated {name}: {dataset.total_steps:,} transitions in {dataset.total_episodes:,} episodes "
                 f"({mix.get('demo_episodes', '?')} demo episodes, {mix.get('demo_transitions', '?')} transitions; "
                 f"{mix.get('rollout_episodes', '?')} BC rollouts, {mix.get('rollout_transitions', '?')} transitions)"]
        events = name.split("-")[0]
    else:
        length = record.get("episode_length", {})
        lines = [f"generated {dataset.total_episodes:,} episodes ({record.get('keep', 'kept')}; "
                 f"{dataset.total_steps:,} transitions) of {name} in {record.get('attempts', '?')} attempts; episode "
                 f"length mean {length.get('mean', float('nan')):.1f}, min {length.get('min', '?')}, "
                 f"max {length.get('max', '?')}"]
        events = GENERATORS[name].events
    lines.append(f"wrote Minari dataset {dataset_id} to {get_dataset_path(dataset_id)}")
    if dataset.total_episodes >= 2 and events:
        lines.append(f"refine it with: rmrl refine --dataset {dataset_id} --events {events} --out ...")
    return "\n".join(lines)


__all__ = ["GENERATORS", "GENERATE_METADATA_KEY", "Generator", "KitchenPlayController", "RelocateController", "collect",
           "describe_generated", "generate_dataset"]
