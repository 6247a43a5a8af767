"""Scripted demonstrations recorded as local Minari datasets (``rmrl generate``).

``GENERATORS`` maps the names ``rmrl generate`` accepts to a ``Generator``: an environment id and a
scripted policy. ``generate_dataset`` records one atomically (see ``record``).
"""
from __future__ import annotations

from rm_torchrl.generate.record import GENERATE_METADATA_KEY, Generator, collect, generate_dataset
from rm_torchrl.generate.relocate import RelocateController

GENERATORS = {
    "relocate-human": Generator(
        name="relocate-human",
        env_id="AdroitHandRelocate-v1",
        policy=RelocateController,
        description="Adroit relocate: grasp the ball, carry it to the target and hold it (scripted, human-like "
                    "variety of speed and style)",
    ),
}

__all__ = ["GENERATORS", "GENERATE_METADATA_KEY", "Generator", "RelocateController", "collect", "generate_dataset"]
