"""Motion-only pose optimization, compiled: the rounds of ORB-SLAM2's ``Optimizer::PoseOptimization`` on float64
arrays (:func:`slamkit.pose_optimization.optimize_pose` checks the input, builds the arrays and reads the result).

The perturbation is on the left (T <- exp(xi) T, xi = (omega, v)) with the analytic Jacobian of the pinhole
projection; the damping follows g2o's Levenberg-Marquardt (lambda = 1e-5 max diag H, Nielsen's update). Each
observation is weighted by its information 1/sigma^2 (and the Huber weight in the robust rounds); after each
round every usable observation is classed again by its chi2 = |reprojection error|^2 / sigma^2.

The rounds run in one numba kernel that releases the GIL (``nogil``): it can run beside other threads, and its
result never depends on them.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_TAU = 1e-5
"""Initial damping relative to the largest diagonal entry of the Gauss-Newton Hessian (g2o's ``tau``)."""
_MAX_TRIALS = 10
"""Damping increases tried per iteration before the round gives up (g2o's ``maxTrialsAfterFailure``)."""
_MIN_STEP = 1e-12
"""An accepted step shorter than this (norm of xi) ends the round: converged."""


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
