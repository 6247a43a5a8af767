"""Offline training on (observation, RM state): recipes, losses with weight decay, the trainer."""
from rm_torchrl.train.config import Recipe
from rm_torchrl.train.recipe import load_recipe
from rm_torchrl.train.trainer import train

__all__ = ["Recipe", "load_recipe", "train"]
