"""Motion-only pose optimization with outlier rejection by chi-square, compiled (ORB-SLAM2's
``Optimizer::PoseOptimization``).

The frame's 6-DoF pose is refined on its 2D-3D correspondences with the map points held fixed. Each
observation has the information 1/sigma^2 of its keypoint's pyramid level (sigma = 1.2^octave pixels for ORB:
:func:`~slamkit.map.keypoint_scales` squared), so a coarse-level keypoint pulls as hard as its noise allows.
ORB-SLAM's scheme, which keeps an optimization started from the motion model in its basin on frames with many
wrong matches:

1. ``rounds`` (4) rounds, each of up to ``iterations`` (10) Levenberg-Marquardt iterations over the
   observations currently classed inliers (at first every usable one), with a Huber kernel at ``huber_delta``
   (sqrt(5.991)) on the whitened error in the first ``robust_rounds`` (3) rounds and none in the last.
2. After each round, *every* observation, earlier outliers included, is classed again by its
   chi2 = |reprojection error|^2 / sigma^2 against ``chi2_threshold`` (5.991: the 95 % quantile of chi-square
   with 2 degrees of freedom); points at or behind the camera are outliers.
3. Fewer than ``min_inliers`` inliers after a round stops the optimization (a failure).

As in ORB-SLAM2, each round starts again from the initial pose (``restart_from_initial``) with the new
inlier set, so a round that a burst of outliers pulled aside does not seed the next one.

The rounds run in one compiled kernel on float64 arrays, :mod:`slamkit.kernels.pose_optimization` (its
parametrization and damping are described there); this module checks the input and says why a frame failed.
pycolmap's equivalent is ``refine_absolute_pose`` (Ceres, one robust loss, every observation weighted alike, no
re-classification).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import check_fields
from .kernels.pose_optimization import _pose_optimization_kernel


@dataclass(frozen=True)
class PoseOptimizationConfig:
    rounds: int = 4
    """Optimize-then-classify rounds (ORB-SLAM2: 4)."""
    iterations: int = 10
    """Levenberg-Marquardt iterations per round at most (ORB-SLAM2: 10)."""
    robust_rounds: int = 3
    """The first this many rounds use the Huber kernel; the later ones plain least squares on the inliers
    (ORB-SLAM2 drops the kernel after the third round's classification)."""
    chi2_threshold: float = 5.991
    """An observation is an inlier when |reprojection error|^2 / sigma^2 is below this (chi-square, 2 degrees
    of freedom, 95 %: 2.45 px at sigma = 1)."""
    huber_delta: float = math.sqrt(5.991)
    """Huber kernel width on the whitened error sqrt(chi2) (ORB-SLAM2: sqrt(5.991))."""
    min_inliers: int = 10
    """Fewer inliers than this after a round and the optimization stops and fails (ORB-SLAM2: 10)."""
    restart_from_initial: bool = True
    """Each round starts from the initial pose (ORB-SLAM2) rather than from the previous round's result."""
    min_depth: float = 1e-6
    """A point nearer than this along the optical axis (world units) is behind the camera: an outlier."""

    def validate(self) -> None:
        check_fields(self, "pose_optimization", {
            "rounds": "[1, inf)", "iterations": "[1, inf)", "robust_rounds": "[0, inf)",
            "chi2_threshold": "(0, 1e9]", "huber_delta": "(0, 1e9]", "min_inliers": ("[3, inf)", "a pose has 6 DoF"),
            "min_depth": "[0, 1e9]"})


@dataclass(frozen=True, eq=False)
class PoseOptimizationResult:
    """Outcome of :func:`optimize_pose`.

    success: at least ``min_inliers`` inliers after the last round; reason: why not (empty on success);
    cam_from_world: (4, 4) the refined pose (a copy of the initial pose when nothing could be optimized);
    inliers: (N,) bool, the last classification; chi2: (N,) float64, |error|^2 / sigma^2 at the refined pose
    (inf for unusable observations and points behind the camera); rounds / iterations: the rounds run and the
    Levenberg-Marquardt iterations they took in all."""

    success: bool
    reason: str
    cam_from_world: np.ndarray
    inliers: np.ndarray
    chi2: np.ndarray
    num_inliers: int
    rounds: int
    iterations: int


def optimize_pose(cam_from_world: np.ndarray, xy: np.ndarray, xyz: np.ndarray, sigma2: np.ndarray | None,
                  K: np.ndarray, config: PoseOptimizationConfig = PoseOptimizationConfig()
                  ) -> PoseOptimizationResult:
    """Refine ``cam_from_world`` ((4, 4) or (3, 4), the motion model's prediction or the last pose) on the
    correspondences ``xy`` ((N, 2) pixels, undistorted) <-> ``xyz`` ((N, 3) world points), each with the
    variance ``sigma2`` ((N,) pixels^2 of its keypoint's level, None: all 1), through the pinhole ``K``
    (3, 3). Observations with a non-finite value or sigma2 <= 0 are outliers and never used.

    Expected failures (too few usable observations or inliers, a non-finite pose or K) are a result with
    ``success`` False and its ``reason``; arrays of wrong shapes raise ValueError. Nothing given is modified."""
    config.validate()
    xy = np.ascontiguousarray(xy, np.float64)
    xyz = np.ascontiguousarray(xyz, np.float64)
    T0 = np.asarray(cam_from_world, np.float64)
    K = np.asarray(K, np.float64)
    n = len(xy)
    if xy.ndim != 2 or xy.shape[1] != 2 or xyz.shape != (n, 3):
        raise ValueError(f"xy must be (N, 2) and xyz (N, 3), got {xy.shape} and {xyz.shape}")
    if T0.shape not in ((4, 4), (3, 4)) or K.shape != (3, 3):
        raise ValueError(f"cam_from_world must be (4, 4) or (3, 4) and K (3, 3), got {T0.shape} and {K.shape}")
    s2 = np.ones(n) if sigma2 is None else np.ascontiguousarray(sigma2, np.float64).reshape(-1)
    if s2.shape != (n,):
        raise ValueError(f"sigma2 must be (N,) = ({n},), got {s2.shape}")
    T = np.eye(4)
    T[:3] = T0[:3]
    inliers, chi2 = np.zeros(n, bool), np.full(n, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        usable = np.isfinite(xy).all(1) & np.isfinite(xyz).all(1) & np.isfinite(s2) & (s2 > 0)
        inv_sigma2 = np.where(usable, 1.0 / s2, 0.0)

    def failed(reason: str) -> PoseOptimizationResult:
        return PoseOptimizationResult(False, reason, T, inliers, chi2, int(inliers.sum()), 0, 0)

    if not (np.isfinite(T).all() and np.isfinite(K).all()):
        return failed("the initial pose or K is not finite")
    if usable.sum() < config.min_inliers:
        return failed(f"{int(usable.sum())} usable observations of {n} < {config.min_inliers}")
    n_inl, rounds, iterations = _pose_optimization_kernel(
        T, xy, xyz, inv_sigma2, K[0, 0], K[1, 1], K[0, 2], K[1, 2], usable, config.rounds, config.iterations,
        config.robust_rounds, config.chi2_threshold, config.huber_delta, config.min_inliers,
        config.restart_from_initial, config.min_depth, inliers, chi2)
    if rounds == 0:
        return failed(f"{n_inl} observations in front of the camera of {n} < {config.min_inliers}")
    if n_inl < config.min_inliers:
        return PoseOptimizationResult(False, f"{n_inl} inliers after round {rounds} < {config.min_inliers}", T,
                                      inliers, chi2, int(n_inl), rounds, iterations)
    return PoseOptimizationResult(True, "", T, inliers, chi2, int(n_inl), rounds, iterations)
