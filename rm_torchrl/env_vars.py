"""The environment variables that third-party libraries read at import, checked before a command imports them:
a bad value would otherwise fail deep inside MuJoCo, PyOpenGL or Minari's readers."""
from __future__ import annotations

import os

from rm_torchrl.errors import RMError


def check_mujoco_gl() -> None:
    """MuJoCo picks its OpenGL backend from ``MUJOCO_GL`` when imported, and a bad one fails deep in PyOpenGL."""
    backend = os.environ.get("MUJOCO_GL")
    if not backend:
        return
    try:
        import mujoco  # noqa: F401
    except Exception as err:  # RuntimeError for an unknown name, AttributeError for a missing library
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise RMError(f"MuJoCo cannot start with MUJOCO_GL={backend} ({type(err).__name__}: {first}); "
                      "unset it, or set MUJOCO_GL=egl on a machine without a display") from None


def check_minari_path() -> None:
    """``MINARI_DATASETS_PATH`` names the folder Minari keeps datasets in: a file there fails deep in its readers."""
    path = os.environ.get("MINARI_DATASETS_PATH")
    if path and os.path.exists(path) and not os.path.isdir(path):
        raise RMError(f"MINARI_DATASETS_PATH={path} is a file; point it at a folder (Minari keeps its datasets there)")
