"""Motion-only pose refinement: the compiled ORB-SLAM2 PoseOptimization (``slamkit.pose_optimization``)
against ``pycolmap.refine_absolute_pose`` (Ceres) as the tracker calls it, on synthetic frames.

A frame: ``--sizes`` correspondences of points 1-3 units in front of a 640x480 pinhole camera (f = 500 px),
keypoint octaves 0-7 drawn as ORB's pyramid fills them (a level holds 1/1.2 of the one below), Gaussian noise
of ``--noise-px`` x 1.2^octave, a fraction ``--outliers`` of them displaced by 20-100 px; the refinement
starts from the true pose turned by ``--perturb-deg`` about a random axis and moved by ``--perturb-m``
(a motion model's miss). Methods:

- ``orb``: :func:`slamkit.pose_optimization.optimize_pose` (4 rounds, chi2 5.991, level weights);
- ``ceres``: one ``refine_absolute_pose`` on every correspondence with the tracker's options (Cauchy loss of
  scale 1, 20 iterations: ``Tracker._from_prediction``);
- ``ceres x2``: that, then a second refinement on the correspondences within ``max_error_px`` (4) of the
  first pose (the tracker's ``_track_local_map`` refinement) — two Ceres calls, as a tracked frame makes.

Reported per size, outlier fraction and method, over ``--frames`` frames: mean and largest rotation error
(degrees) and camera-centre error (mm, the scene 1-3 units deep read as metres), the share of true inliers
classed outliers and of planted outliers classed inliers (``orb``: its chi2 mask; Ceres: error < 4 px at its
pose), and the median milliseconds per call (``ceres x2``: both calls). Timing is ``time.perf_counter`` around
each call after numba's compilation, the methods interleaved frame by frame in one process: on a machine
shared with other jobs read it as a same-process, side-by-side ratio under load, not as absolute speed.

Usage::

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_pose_optimization.py
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_pose_optimization.py --sizes 300 1000 --outliers 0.1 0.3 \
        --frames 50 --csv /tmp/bench_pose_optimization.csv
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pycolmap  # noqa: E402

from slamkit.geometry import rotation_angle_deg  # noqa: E402
from slamkit.map import matrix_from_rigid, rigid_from_matrix  # noqa: E402
from slamkit.pose_optimization import optimize_pose  # noqa: E402

WIDTH, HEIGHT, F = 640, 480, 500.0
K = np.array([[F, 0, WIDTH / 2], [0, F, HEIGHT / 2], [0, 0, 1]])
MAX_ERROR_PX = 4.0
"""The tracker's inlier threshold (``TrackerConfig.max_error_px``)."""
METHODS = ("orb", "ceres", "ceres x2")


def _rotation(axis: np.ndarray, deg: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    W = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = np.radians(deg)
    return np.eye(3) + np.sin(th) * W + (1 - np.cos(th)) * W @ W


def synthetic_frame(rng: np.random.Generator, n: int, outlier_ratio: float, noise_px: float, perturb_deg: float,
                    perturb_m: float, orb_levels: bool = True, exact_shift: bool = True):
    """(true cam_from_world, initial pose, xy (N, 2), xyz (N, 3), sigma2 (N,), planted outliers (N,) bool):
    points at depths 1-3 seen across the image, Gaussian noise of ``noise_px`` x 1.2^octave, outliers displaced
    by 20-100 px in a random direction. Octaves as ORB finds them (fewer at coarser levels), or uniform over
    0-7 with ``orb_levels`` False; the initial pose turned by ``perturb_deg`` and moved by ``perturb_m`` (or, with
    ``exact_shift`` False, by ``perturb_m`` per axis, Gaussian). Also the frames of tests/test_pose_optimization.py."""
    uv = rng.uniform([0, 0], [WIDTH, HEIGHT], (n, 2))
    depth = rng.uniform(1, 3, n)
    xc = np.column_stack([(uv[:, 0] - K[0, 2]) / F * depth, (uv[:, 1] - K[1, 2]) / F * depth, depth])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _rotation(rng.normal(size=3), 30), rng.normal(size=3) * 0.5
    xyz = (xc - T[:3, 3]) @ T[:3, :3]
    level_share = 1.2 ** -np.arange(8)
    scale = 1.2 ** (rng.choice(8, n, p=level_share / level_share.sum()) if orb_levels else rng.integers(0, 8, n))
    xy = uv + rng.normal(0, noise_px, (n, 2)) * scale[:, None]
    planted = np.zeros(n, bool)
    planted[rng.choice(n, int(round(outlier_ratio * n)), replace=False)] = True
    angle, shift = rng.uniform(0, 2 * np.pi, planted.sum()), rng.uniform(20, 100, planted.sum())
    xy[planted] += np.column_stack([np.cos(angle), np.sin(angle)]) * shift[:, None]
    T0 = T.copy()
    T0[:3, :3] = _rotation(rng.normal(size=3), perturb_deg) @ T[:3, :3]
    direction = rng.normal(size=3)
    T0[:3, 3] += (direction / np.linalg.norm(direction) if exact_shift else direction) * perturb_m
    return T, T0, xy, xyz, scale ** 2, planted


def _within(T: np.ndarray, xy: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """The tracker's inliers: in front of the camera and reprojected within MAX_ERROR_PX."""
    xc = xyz @ T[:3, :3].T + T[:3, 3]
    uv = xc[:, :2] / np.maximum(xc[:, 2:], 1e-9) * F + K[:2, 2]
    return (xc[:, 2] > 1e-9) & (((uv - xy) ** 2).sum(1) < MAX_ERROR_PX ** 2)


def _run(method: str, T0, xy, xyz, sigma2, camera, options) -> tuple[np.ndarray, np.ndarray, float]:
    """(pose, inlier mask, seconds) of one method on one frame."""
    t = time.perf_counter()
    if method == "orb":
        result = optimize_pose(T0, xy, xyz, sigma2, K)
        return result.cam_from_world, result.inliers, time.perf_counter() - t
    ref = pycolmap.refine_absolute_pose(rigid_from_matrix(T0), xy, xyz, np.ones(len(xy), bool), camera, options)
    pose = T0 if ref is None else matrix_from_rigid(ref["cam_from_world"])
    if method == "ceres x2":
        inl = _within(pose, xy, xyz)
        ref = pycolmap.refine_absolute_pose(rigid_from_matrix(pose), xy, xyz, inl, camera, options)
        pose = pose if ref is None else matrix_from_rigid(ref["cam_from_world"])
    seconds = time.perf_counter() - t
    return pose, _within(pose, xy, xyz), seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[300, 1000], help="correspondences per frame")
    ap.add_argument("--outliers", type=float, nargs="+", default=[0.1, 0.3], help="planted outlier fractions")
    ap.add_argument("--frames", type=int, default=30, help="frames per size and outlier fraction")
    ap.add_argument("--noise-px", type=float, default=1.0, help="keypoint noise at octave 0, pixels")
    ap.add_argument("--perturb-deg", type=float, default=2.0, help="initial rotation error, degrees")
    ap.add_argument("--perturb-m", type=float, default=0.03, help="initial translation error, scene units")
    ap.add_argument("--repeat", type=int, default=5, help="timed calls per frame and method (median taken)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--csv", type=Path, default=None, help="also write the table here")
    args = ap.parse_args()

    camera = pycolmap.Camera(model="PINHOLE", width=WIDTH, height=HEIGHT, params=[F, F, K[0, 2], K[1, 2]])
    options = pycolmap.AbsolutePoseRefinementOptions()  # Tracker.__init__'s refinement options
    options.refine_focal_length = False
    options.refine_extra_params = False
    options.max_num_iterations = 20
    rng = np.random.default_rng(args.seed)
    warm = synthetic_frame(rng, 50, 0.1, 1.0, 1.0, 0.01)
    optimize_pose(warm[1], warm[2], warm[3], warm[4], K)  # numba compiles (or loads its cache) here

    rows = []
    for n in args.sizes:
        for ratio in args.outliers:
            acc = {m: {"rot": [], "centre": [], "false_out": [], "missed": [], "ms": []} for m in METHODS}
            for _ in range(args.frames):
                T, T0, xy, xyz, sigma2, planted = synthetic_frame(rng, n, ratio, args.noise_px, args.perturb_deg,
                                                                  args.perturb_m)
                centre = -T[:3, :3].T @ T[:3, 3]
                for method in METHODS:
                    times = []
                    for _ in range(args.repeat):
                        pose, inl, seconds = _run(method, T0, xy, xyz, sigma2, camera, options)
                        times.append(seconds)
                    a = acc[method]
                    a["rot"].append(rotation_angle_deg(pose[:3, :3] @ T[:3, :3].T))
                    a["centre"].append(1e3 * np.linalg.norm(-pose[:3, :3].T @ pose[:3, 3] - centre))
                    a["false_out"].append(np.mean(~inl[~planted]))
                    a["missed"].append(np.mean(inl[planted]) if planted.any() else 0.0)
                    a["ms"].append(1e3 * np.median(times))
            orb_ms = np.median(acc["orb"]["ms"])
            for method in METHODS:
                a = acc[method]
                ms = float(np.median(a["ms"]))
                rows.append({"correspondences": n, "outliers": ratio, "method": method,
                             "rot_err_deg_mean": np.mean(a["rot"]), "rot_err_deg_max": np.max(a["rot"]),
                             "centre_err_mm_mean": np.mean(a["centre"]), "centre_err_mm_max": np.max(a["centre"]),
                             "inliers_classed_out_pct": 100 * np.mean(a["false_out"]),
                             "outliers_classed_in_pct": 100 * np.mean(a["missed"]),
                             "ms_per_call": ms, "time_vs_orb": ms / orb_ms})

    print(f"{args.frames} frames per row; noise {args.noise_px} px x 1.2^octave; start {args.perturb_deg} deg, "
          f"{args.perturb_m} units off; load average {os.getloadavg()[0]:.1f} (timing: same-process ratio under load)")
    print("| N | outliers | method | rot err deg mean / max | centre err mm mean / max | inliers out % "
          "| outliers in % | ms/call | time / orb |")
    print("|---:|---:|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['correspondences']} | {100 * r['outliers']:.0f} % | {r['method']} "
              f"| {r['rot_err_deg_mean']:.4f} / {r['rot_err_deg_max']:.4f} "
              f"| {r['centre_err_mm_mean']:.2f} / {r['centre_err_mm_max']:.2f} | {r['inliers_classed_out_pct']:.1f} "
              f"| {r['outliers_classed_in_pct']:.1f} | {r['ms_per_call']:.2f} | {r['time_vs_orb']:.2f} |")
    if args.csv:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        with open(args.csv, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        print(f"wrote {args.csv}")


if __name__ == "__main__":
    main()
