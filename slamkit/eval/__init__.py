"""Evaluating trajectories against ground truth: association, alignment, ATE and RPE (evo's conventions)."""

from .align import ALIGN_KINDS, Alignment, AlignmentError, estimate_alignment
from .associate import associate
from .metrics import AteResult, ErrorStats, RpeResult, ate, evaluate, rpe
from .report import evaluate_run  # plots (matplotlib) are imported only when a report is written

__all__ = [
    "ALIGN_KINDS", "Alignment", "AlignmentError", "estimate_alignment", "associate",
    "AteResult", "ErrorStats", "RpeResult", "ate", "evaluate", "rpe",
    "evaluate_run",
]
