"""Dataset refinement stages (paper sections 3.2-3.4, and reuse beyond it) as composable TorchRL transforms."""
from rm_torchrl.refine.encode import RMEncoding
from rm_torchrl.refine.label import LabelRM
from rm_torchrl.refine.order import EventOrder, best_event_order
from rm_torchrl.refine.pipeline import RefineReport, make_refine_pipeline, refine, refine_replay_buffer, run_pipeline
from rm_torchrl.refine.relabel import CounterfactualRelabel
from rm_torchrl.refine.reuse import ReuseAbandoned
from rm_torchrl.refine.shortest import KeepShortest
from rm_torchrl.refine.splice import Splice
from rm_torchrl.refine.split import SplitGroup

__all__ = [
    "LabelRM",
    "SplitGroup",
    "EventOrder",
    "ReuseAbandoned",
    "Splice",
    "KeepShortest",
    "CounterfactualRelabel",
    "RMEncoding",
    "best_event_order",
    "make_refine_pipeline",
    "refine",
    "refine_replay_buffer",
    "run_pipeline",
    "RefineReport",
]
