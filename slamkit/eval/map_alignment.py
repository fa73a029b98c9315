"""The error of a run made in a saved map (``slamkit run --map``) under the map's own alignment (issue 49).

A run in a saved map poses its frames in that map's frame and scale. Its ATE after its own Sim(3) says how
good its trajectory's shape is, not whether it shares the map's frame. :func:`map_alignment_error` applies
the Sim(3) that aligns the *map's* run (its ``trajectory_tum.txt``) to that run's ground truth to this run's
trajectory, and measures it against this run's ground truth: small only when both runs share one frame.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import SlamkitError
from ..io.trajectory import read_tum
from ..types import Trajectory
from .align import Alignment
from .associate import associate
from .metrics import ErrorStats, ate


def error_under(alignment: Alignment, est: Trajectory, gt: Trajectory, max_dt: float = 0.02) -> dict:
    """Position errors (metres) of ``est`` mapped by ``alignment`` (gt_from_est), paired with ``gt`` by time:
    ``{"ate": stats, "matched": K, "estimate_poses": N}``."""
    idx_gt, idx_est = associate(gt.timestamps, est.timestamps, max_dt)
    if len(idx_est) == 0:
        raise SlamkitError(f"no pose of the estimate ({len(est)}) matches the ground truth within {max_dt} s")
    moved = alignment.apply(est.subset(idx_est))
    errors = np.linalg.norm(moved.positions - gt.subset(idx_gt).positions, axis=1)
    return {"ate": ErrorStats.from_errors(errors).to_dict(), "matched": int(len(idx_est)), "estimate_poses": len(est)}


def map_alignment_error(run_dir: str | os.PathLike, gt: str | os.PathLike | None = None,
                        max_dt: float = 0.02) -> dict | None:
    """For a run folder made with ``--map`` (``summary.json["map"]``): the error of its trajectory under the
    map's run's Sim(3) alignment to that run's ground truth. None for a run made without a map; a dict with
    ``"error"`` (why not) when the map's run or a ground truth is missing."""
    run = Path(run_dir)
    try:
        summary = json.loads((run / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    info = summary.get("map") if isinstance(summary, dict) else None
    if not isinstance(info, dict) or not info.get("run"):
        return None
    prior = Path(info["run"])
    out = {"map_run": str(prior), "main_in_map": bool(info.get("main_in_map", True))}
    files = {"the map's trajectory": prior / "trajectory_tum.txt", "the map's ground truth": prior / "groundtruth_tum.txt",
             "this run's trajectory": run / "trajectory_tum.txt",
             "this run's ground truth": Path(gt) if gt is not None else run / "groundtruth_tum.txt"}
    missing = [f"{name} ({path})" for name, path in files.items() if not path.is_file()]
    if missing:
        return {**out, "error": f"missing: {', '.join(missing)}"}
    try:
        first = ate(read_tum(files["the map's ground truth"]), read_tum(files["the map's trajectory"]), "sim3", max_dt)
        res = error_under(first.alignment, read_tum(files["this run's trajectory"]),
                          read_tum(files["this run's ground truth"]), max_dt)
    except SlamkitError as e:
        return {**out, "error": str(e)}
    note = "" if out["main_in_map"] else "this run's trajectory is a segment that never met the map: not its frame"
    return {**out, **res, "alignment": first.alignment.to_dict(), "map_ate": first.stats.to_dict(),
            **({"note": note} if note else {})}


__all__ = ["map_alignment_error", "error_under"]
