"""rm_torchrl: refine offline RL datasets with event-ordered reward machines, as TorchRL transforms."""
from rm_torchrl.errors import RMError

__version__ = "0.1.0"
__all__ = ["RMError", "__version__"]
