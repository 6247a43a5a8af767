"""Offline training on (observation, RM state): recipes, the trainer, evaluation and policies out of runs.

The methods it trains (networks, losses, their registry) are :mod:`rm_torchrl.methods`. The names below are
imported when first used, so that ``rmrl train --help`` finds the recipes without torch.
"""
_HOMES = {"Recipe": "config", "load_recipe": "recipe", "train": "trainer"}
__all__ = sorted(_HOMES)


def __getattr__(name: str):
    if name not in _HOMES:
        raise AttributeError(f"module 'rm_torchrl.train' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"rm_torchrl.train.{_HOMES[name]}"), name)
