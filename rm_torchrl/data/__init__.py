"""Data sources (D4RL HDF5, Minari) and storage of refined datasets.

The readers are imported when first used: ``rmrl --help`` reads this package's option names without torch.
"""
_HOMES = {"load_d4rl_hdf5": "d4rl", "load_dataset": "sources", "load_minari": "minari",
          "minari_replay_buffer": "minari", "read_refined": "store", "write_refined": "store"}
__all__ = sorted(_HOMES)


def __getattr__(name: str):
    if name not in _HOMES:
        raise AttributeError(f"module 'rm_torchrl.data' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"rm_torchrl.data.{_HOMES[name]}"), name)
