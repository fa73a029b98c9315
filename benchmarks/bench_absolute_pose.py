"""Tracking's motion-only refinement, per call: ``pycolmap.refine_absolute_pose`` (Ceres) against the compiled kernel
(:mod:`slamkit.kernels.absolute_pose`) on the calls a real run makes.

One run of SOURCE (``--frames``, ``tracker.pose_optimizer`` "compiled") records the arguments of every refinement
the tracker asks for; each is then solved by both, interleaved, after one warm-up call. Prints a table and writes
CSV (one row per call: observations, inliers, ms of each, the largest difference of a pose entry)::

    PYTHONPATH=$PWD python benchmarks/bench_absolute_pose.py ../shared/data/7scenes-redkitchen --frames 150
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

import slamkit  # noqa: F401  (before pycolmap: slamkit/__init__.py says why)
import slamkit.stages.tracker as tracker_stage
from slamkit.config import SlamConfig
from slamkit.kernels.absolute_pose import refine_absolute_pose
from slamkit.map import matrix_from_rigid, rigid_from_matrix
from slamkit.pipeline import Slam
from slamkit.sources import open_source

import pycolmap  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def record_calls(source: str, frames: int) -> list[tuple]:
    """The (cam_from_world, xy, xyz, inlier_mask, camera, max_iterations, loss_scale, gradient_tolerance) of every
    compiled refinement the tracker makes over the first ``frames`` frames of ``source``."""
    calls: list[tuple] = []
    original = tracker_stage.refine_absolute_pose

    def record(*args):
        calls.append(tuple(np.array(a, copy=True) if isinstance(a, np.ndarray) else a for a in args))
        return original(*args)

    tracker_stage.refine_absolute_pose = record
    try:
        Slam(open_source(source), SlamConfig().with_overrides(
            **{"max_frames": frames, "tracker.pose_optimizer": "compiled"})).run()
    finally:
        tracker_stage.refine_absolute_pose = original
    return calls


def measure(calls: list[tuple]) -> list[dict]:
    rows = []
    for T0, xy, xyz, inl, cam, iterations, scale, gtol in calls:  # (T0 as the tracker gives it: a unit quaternion's)
        pcam = pycolmap.Camera(model="PINHOLE", width=1, height=1, params=list(cam))
        opt = pycolmap.AbsolutePoseRefinementOptions()
        opt.refine_focal_length, opt.refine_extra_params = False, False
        opt.max_num_iterations, opt.loss_function_scale, opt.gradient_tolerance = iterations, scale, gtol
        refine_absolute_pose(T0, xy, xyz, inl, cam, iterations, scale, gtol)  # warm (numba's first call)
        t0 = time.perf_counter()
        ref = pycolmap.refine_absolute_pose(rigid_from_matrix(T0), xy, xyz, inl, pcam, opt)
        t1 = time.perf_counter()
        ours = refine_absolute_pose(T0, xy, xyz, inl, cam, iterations, scale, gtol)
        t2 = time.perf_counter()
        gap = float(np.abs(matrix_from_rigid(ref["cam_from_world"]) - ours).max()) if ref is not None and \
            ours is not None else float("nan")
        rows.append({"observations": len(xy), "inliers": int(np.sum(inl)), "ceres_ms": 1e3 * (t1 - t0),
                     "compiled_ms": 1e3 * (t2 - t1), "pose_gap": gap})
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", help="a source path or spec (e.g. ../shared/data/7scenes-redkitchen)")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--csv", type=Path, default=RESULTS / "bench_absolute_pose.csv")
    args = ap.parse_args(argv)
    pycolmap.logging.minloglevel = 2
    rows = measure(record_calls(args.source, args.frames))
    if not rows:
        raise SystemExit("the run made no compiled refinement (a camera with distortion refines with pycolmap)")
    col = lambda k: np.array([r[k] for r in rows])  # noqa: E731
    ceres, ours, gap = col("ceres_ms"), col("compiled_ms"), col("pose_gap")
    print(f"| calls | inliers (median) | pycolmap ms/call | compiled ms/call | speed-up | pose entry gap median (max) |\n"
          f"|---|---|---|---|---|---|\n| {len(rows)} | {np.median(col('inliers')):.0f} | {ceres.mean():.3f} | "
          f"{ours.mean():.3f} | {ceres.sum() / ours.sum():.1f}x | {np.nanmedian(gap):.1e} ({np.nanmax(gap):.1e}) |")
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    with open(args.csv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f"written: {args.csv}")


if __name__ == "__main__":
    main()
