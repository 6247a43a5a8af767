"""rm_torchrl: refine offline RL datasets with event-ordered reward machines, as TorchRL transforms."""
from rm_torchrl.errors import RMError

__version__ = "0.1.0"
__all__ = ["RMError", "__version__", "load_policy"]


def __getattr__(name: str):
    """``rm_torchrl.load_policy`` without importing torch and the trainer on ``import rm_torchrl``."""
    if name == "load_policy":
        from rm_torchrl.train.policy import load_policy

        return load_policy
    raise AttributeError(f"module 'rm_torchrl' has no attribute {name!r}")
