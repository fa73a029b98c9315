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
inlier set, so a round that a burst of outliers pulled aside does not seed the next one. The
perturbation is on the left (T <- exp(xi) T, xi = (omega, v)) with the analytic Jacobian of the pinhole
projection; the damping follows g2o's Levenberg-Marquardt (lambda = 1e-5 max diag H, Nielsen's update).

The rounds run in one numba kernel on float64 arrays that releases the GIL (``nogil``): it can run beside
other threads, and its result never depends on them. pycolmap's equivalent is ``refine_absolute_pose``
(Ceres, one robust loss, every observation weighted alike, no re-classification).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .errors import check_fields

_TAU = 1e-5
"""Initial damping relative to the largest diagonal entry of the Gauss-Newton Hessian (g2o's ``tau``)."""
_MAX_TRIALS = 10
"""Damping increases tried per iteration before the round gives up (g2o's ``maxTrialsAfterFailure``)."""
_MIN_STEP = 1e-12
"""An accepted step shorter than this (norm of xi) ends the round: converged."""


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


@njit(cache=True, nogil=True)
def _chi2(R, t, p, q, inv_sigma2, fx, fy, cx, cy, min_depth):
    """chi2 of the observation q (pixel) of the point p at the pose (R, t); -1 when it is behind the camera."""
    x = R[0, 0] * p[0] + R[0, 1] * p[1] + R[0, 2] * p[2] + t[0]
    y = R[1, 0] * p[0] + R[1, 1] * p[1] + R[1, 2] * p[2] + t[1]
    z = R[2, 0] * p[0] + R[2, 1] * p[1] + R[2, 2] * p[2] + t[2]
    if not z > min_depth:
        return -1.0
    du = fx * x / z + cx - q[0]
    dv = fy * y / z + cy - q[1]
    return (du * du + dv * dv) * inv_sigma2


@njit(cache=True, nogil=True)
def _robust_cost(R, t, xy, xyz, inv_sigma2, fx, fy, cx, cy, active, delta, min_depth):
    """0.5 sum of Huber(chi2) over the active observations (plain chi2 when delta <= 0); inf when one of them
    is behind the camera (a step that moves an inlier behind the camera is refused)."""
    d2 = delta * delta
    total = 0.0
    for i in range(xy.shape[0]):
        if not active[i]:
            continue
        s = _chi2(R, t, xyz[i], xy[i], inv_sigma2[i], fx, fy, cx, cy, min_depth)
        if s < 0:
            return np.inf
        total += s if (delta <= 0 or s <= d2) else 2.0 * delta * math.sqrt(s) - d2
    return 0.5 * total


@njit(cache=True, nogil=True)
def _normal_equations(R, t, xy, xyz, inv_sigma2, fx, fy, cx, cy, active, delta, H, g):
    """Gauss-Newton Hessian H (6, 6) and gradient g (6,) of the robust cost in xi = (omega, v), the left
    perturbation T <- exp(xi) T; each observation weighted by its information times the Huber weight."""
    H[:, :] = 0.0
    g[:] = 0.0
    d2 = delta * delta
    ju = np.empty(6)
    jv = np.empty(6)
    for i in range(xy.shape[0]):
        if not active[i]:
            continue
        p = xyz[i]
        x = R[0, 0] * p[0] + R[0, 1] * p[1] + R[0, 2] * p[2] + t[0]
        y = R[1, 0] * p[0] + R[1, 1] * p[1] + R[1, 2] * p[2] + t[1]
        z = R[2, 0] * p[0] + R[2, 1] * p[1] + R[2, 2] * p[2] + t[2]
        iz = 1.0 / z
        u, v = x * iz, y * iz
        ru = fx * u + cx - xy[i, 0]
        rv = fy * v + cy - xy[i, 1]
        w = inv_sigma2[i]
        s = (ru * ru + rv * rv) * w
        if delta > 0 and s > d2:
            w *= delta / math.sqrt(s)
        # d(pixel)/d(omega) = d(pixel)/d(Xc) (-[Xc]x), d(pixel)/d(v) = d(pixel)/d(Xc)
        ju[0], ju[1], ju[2] = -fx * u * v, fx * (1.0 + u * u), -fx * v
        ju[3], ju[4], ju[5] = fx * iz, 0.0, -fx * u * iz
        jv[0], jv[1], jv[2] = -fy * (1.0 + v * v), fy * u * v, fy * u
        jv[3], jv[4], jv[5] = 0.0, fy * iz, -fy * v * iz
        for a in range(6):
            g[a] += w * (ju[a] * ru + jv[a] * rv)
            for b in range(a, 6):
                H[a, b] += w * (ju[a] * ju[b] + jv[a] * jv[b])
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]


@njit(cache=True, nogil=True)
def _solve_damped(H, g, lam, dx):
    """dx = -(H + lam I)^-1 g by Cholesky; False when the matrix is not positive definite."""
    L = np.zeros((6, 6))
    for j in range(6):
        s = H[j, j] + lam
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0:
            return False
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, 6):
            s = H[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    y = np.empty(6)
    for i in range(6):
        s = -g[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    for i in range(5, -1, -1):
        s = y[i]
        for k in range(i + 1, 6):
            s -= L[k, i] * dx[k]
        dx[i] = s / L[i, i]
    return True


@njit(cache=True, nogil=True)
def _retract(R, t, dx, R_out, t_out):
    """(R_out, t_out) = exp(xi) (R, t), xi = dx = (omega, v): SO(3) by Rodrigues, the translation by the
    left Jacobian V (Taylor series near zero angle)."""
    wx, wy, wz = dx[0], dx[1], dx[2]
    th2 = wx * wx + wy * wy + wz * wz
    if th2 < 1e-12:
        a, b, c = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    else:
        th = math.sqrt(th2)
        a, b, c = math.sin(th) / th, (1.0 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)
    W = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    W2 = W @ W
    dR = np.eye(3) + a * W + b * W2
    V = np.eye(3) + b * W + c * W2
    R_out[:, :] = dR @ R
    t_out[:] = dR @ t + V @ dx[3:]


@njit(cache=True, nogil=True)
def _levenberg_marquardt(R, t, xy, xyz, inv_sigma2, fx, fy, cx, cy, active, delta, iterations, min_depth):
    """Refine (R, t) in place on the active observations; returns the iterations run."""
    H, g, dx = np.empty((6, 6)), np.empty(6), np.empty(6)
    R_new, t_new = np.empty((3, 3)), np.empty(3)
    cost = _robust_cost(R, t, xy, xyz, inv_sigma2, fx, fy, cx, cy, active, delta, min_depth)
    if not np.isfinite(cost):
        return 0
    _normal_equations(R, t, xy, xyz, inv_sigma2, fx, fy, cx, cy, active, delta, H, g)
    lam, nu, new_cost = -1.0, 2.0, cost
    for it in range(iterations):
        if lam < 0:
            lam = _TAU * max(H[0, 0], H[1, 1], H[2, 2], H[3, 3], H[4, 4], H[5, 5])
            lam = max(lam, 1e-12)
        accepted = False
        for _ in range(_MAX_TRIALS):
            if _solve_damped(H, g, lam, dx):
                _retract(R, t, dx, R_new, t_new)
                new_cost = _robust_cost(R_new, t_new, xy, xyz, inv_sigma2, fx, fy, cx, cy, active, delta, min_depth)
                predicted = 0.0
                for a in range(6):
                    predicted += dx[a] * (lam * dx[a] - g[a])
                if new_cost < cost:
                    rho = (cost - new_cost) / max(0.5 * predicted, 1e-300)
                    lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                    nu = 2.0
                    accepted = True
                    break
            lam *= nu
            nu *= 2.0
        if not accepted:
            return it + 1
        R[:, :] = R_new
        t[:] = t_new
        cost = new_cost
        step = math.sqrt(dx[0] ** 2 + dx[1] ** 2 + dx[2] ** 2 + dx[3] ** 2 + dx[4] ** 2 + dx[5] ** 2)
        if step < _MIN_STEP or cost == 0.0:
            return it + 1
        _normal_equations(R, t, xy, xyz, inv_sigma2, fx, fy, cx, cy, active, delta, H, g)
    return iterations


@njit(cache=True, nogil=True)
def _classify(R, t, xy, xyz, inv_sigma2, fx, fy, cx, cy, usable, chi2_threshold, min_depth, inliers, chi2):
    """Class every usable observation by its chi2 (behind the camera: outlier, chi2 inf); the inlier count."""
    n = 0
    for i in range(xy.shape[0]):
        s = _chi2(R, t, xyz[i], xy[i], inv_sigma2[i], fx, fy, cx, cy, min_depth) if usable[i] else -1.0
        chi2[i] = s if s >= 0 else np.inf
        inliers[i] = 0 <= s < chi2_threshold
        n += inliers[i]
    return n


@njit(cache=True, nogil=True)
def _pose_optimization_kernel(T, xy, xyz, inv_sigma2, fx, fy, cx, cy, usable, rounds, iterations, robust_rounds,
                              chi2_threshold, huber_delta, min_inliers, restart, min_depth, inliers, chi2):
    """The rounds of :func:`optimize_pose` on float64 arrays; T (4, 4) is refined in place, inliers (N,) bool
    and chi2 (N,) written. Returns (inliers, rounds run, iterations run)."""
    R0, t0 = T[:3, :3].copy(), T[:3, 3].copy()
    R, t = R0.copy(), t0.copy()
    n_inl = 0
    for i in range(xy.shape[0]):  # ORB-SLAM starts with every correspondence an inlier; here every usable one
        inliers[i] = usable[i] and _chi2(R, t, xyz[i], xy[i], inv_sigma2[i], fx, fy, cx, cy, min_depth) >= 0
        n_inl += inliers[i]
    if n_inl < min_inliers:
        _classify(R, t, xy, xyz, inv_sigma2, fx, fy, cx, cy, usable, chi2_threshold, min_depth, inliers, chi2)
        return n_inl, 0, 0
    total, done = 0, 0
    for r in range(rounds):
        if restart:
            R[:, :] = R0
            t[:] = t0
        delta = huber_delta if r < robust_rounds else -1.0
        total += _levenberg_marquardt(R, t, xy, xyz, inv_sigma2, fx, fy, cx, cy, inliers, delta, iterations,
                                      min_depth)
        n_inl = _classify(R, t, xy, xyz, inv_sigma2, fx, fy, cx, cy, usable, chi2_threshold, min_depth, inliers,
                          chi2)
        done = r + 1
        if n_inl < min_inliers:
            break
    T[:3, :3] = R
    T[:3, 3] = t
    return n_inl, done, total


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
