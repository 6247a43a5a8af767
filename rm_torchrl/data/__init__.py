"""Data sources (D4RL HDF5, Minari) and storage of refined datasets."""
from rm_torchrl.data.d4rl import load_d4rl_hdf5
from rm_torchrl.data.sources import load_dataset
from rm_torchrl.data.store import read_refined, write_refined

__all__ = ["load_d4rl_hdf5", "load_dataset", "read_refined", "write_refined"]
