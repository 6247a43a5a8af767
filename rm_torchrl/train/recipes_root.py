"""Where the recipes live, found without importing the recipe machinery (``rmrl train --help`` lists them)."""
from __future__ import annotations

from pathlib import Path


def _recipes_root() -> Path:
    """The recipes folder: ``rm_torchrl/recipes`` in an installed wheel (pyproject maps the top-level folder
    there), else the checkout's top-level ``recipes/`` (an editable install or a plain checkout)."""
    package = Path(__file__).resolve().parents[1]
    installed = package / "recipes"
    return installed if (installed / "train.yaml").is_file() else package.parent / "recipes"


#: The package's recipes folder (the config root of ``rmrl train dataset=... method=...``).
RECIPES = _recipes_root()
