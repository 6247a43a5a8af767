"""Offline training on (observation, RM state): recipes, the trainer, evaluation and policies out of runs.

The methods it trains (networks, losses, their registry) are :mod:`rm_torchrl.methods`.
"""
from rm_torchrl.train.config import Recipe
from rm_torchrl.train.recipe import load_recipe
from rm_torchrl.train.trainer import train

__all__ = ["Recipe", "load_recipe", "train"]
