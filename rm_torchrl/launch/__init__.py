"""Launching runs: Hydra sweeps, grids of unrelated runs, and the signals that stop them cleanly.

The CLI, the demo and the study scripts under ``benchmarks/`` all launch through here::

    from rm_torchrl.launch import run_grid
    run_grid([(None, ["dataset=door-human-v0", "method=ours", f"seed={s}"]) for s in (3, 4)], jobs=2)

Every launcher follows one policy: finished runs are skipped, killed ones resume from their
checkpoint, failed ones are not retried, and folders holding evaluations without a checkpoint are
left alone. SIGTERM or SIGINT reaches every running run, which checkpoints at its next update.
"""
_HOMES = {"run_grid": "processes", "run_many": "processes", "multirun": "sweep", "exit_status": "signals",
          "run_demo": "demo"}
__all__ = sorted(_HOMES)


def __getattr__(name: str):
    """The launchers, imported when first used: ``rmrl`` builds its parser without the training stack."""
    if name not in _HOMES:
        raise AttributeError(f"module 'rm_torchrl.launch' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"rm_torchrl.launch.{_HOMES[name]}"), name)
