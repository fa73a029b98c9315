"""Local bundle adjustment, compiled: Levenberg-Marquardt with the Schur complement on the poses (ORB-SLAM2's
``Optimizer::LocalBundleAdjustment``, COLMAP's local BA problem).

The problem, on plain arrays (no pycolmap): K keyframe poses cam_from_world, P world points, N observations
(pose index, point index, undistorted pixel, information weight). Poses flagged fixed and points flagged
fixed are held (ORB-SLAM's fixed keyframes that see the local points; COLMAP's long tracks held constant);
their observations still enter the cost. The cost is Ceres' convention,

    cost = 1/2 sum_i rho(s_i),   s_i = w_i |pi(R_k X_p + t_k) - x_i|^2   (the squared whitened error),

with rho the robust loss on s: "trivial" (s), "huber" at scale a (s for s <= a^2, else 2 a sqrt(s) - a^2:
ORB-SLAM's kernel with a = sqrt(5.991) on the whitened error) or "soft_l1" at scale a (2 a^2 (sqrt(1 + s/a^2)
- 1): COLMAP's default at a = 1 px with w = 1), "cauchy" at scale a (a^2 log(1 + s/a^2): COLMAP's absolute pose
refinement, :mod:`slamkit.kernels.absolute_pose`). w_i is the observation's information: 1 (COLMAP's flat
weights) or 1/sigma^2 of its keypoint's pyramid level (ORB-SLAM's).

Parametrization: the rotation is perturbed on the left, R <- exp([omega]x) R, the translation and points
additively, t <- t + dt, X <- X + dX (the parametrization of Ceres' quaternion manifold with a Euclidean
translation block, COLMAP's): a translation coordinate can then be held on its own (``gauge``, COLMAP's
TWO_CAMS_FROM_WORLD gauge when nothing outside the window fixes it).

Each iteration linearizes every observation (Jacobians of the pinhole projection, weights w rho'(s):
iteratively reweighted least squares, whose fixed point is the robust cost's optimum), eliminates the points
(3x3 blocks, each inverted), solves the reduced camera system (6 K_var)^2 densely by Cholesky (local windows
are <= ~30 keyframes) and back-substitutes the points. The damping and its updates are Ceres'
Levenberg-Marquardt: lambda diag(J^T J) (diagonal clamped to [1e-6, 1e32]), lambda = 1e-4 at first, on an
accepted step lambda *= max(1/3, 1 - (2 rho - 1)^3), on a refused one lambda *= nu, nu *= 2; a step must
lower the cost by 1e-3 of the model's prediction. Every linear solve counts as an iteration (Ceres'
``max_num_iterations``). Termination as Ceres': CONVERGENCE when a step would change the cost by at most
``function_tolerance`` times the cost (that step is not taken: Ceres' ``FunctionToleranceReached``), the step
is below ``parameter_tolerance`` (relative), or the gradient is below ``gradient_tolerance``, both measured as Ceres
measures them on COLMAP's quaternions (:mod:`slamkit.kernels.ceres_norms`); NO_CONVERGENCE
after ``max_iterations``; ABORTED when ``abort[0]`` is set (checked before each iteration: another thread may
set it; the result is the last accepted state); FAILURE for input that cannot be solved (the result says why). A step that moves a used observation's point to depth <=
``min_depth`` is refused (``behind_camera`` "refuse", ORB-SLAM's test treats such a point as an outlier), or
that observation's residual is 0 (``behind_camera`` "zero": COLMAP 4's ``ReprojErrorCost`` returns a zero
residual and Jacobian for a point behind the camera, so Ceres may move points there; the stage uses this to
solve COLMAP's problem).

The solver runs in one numba function that releases the GIL (``nogil``), on float64 arrays, with no state
between calls: a worker thread can run it beside tracking and its result never depends on other threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .ceres_norms import gradient_max_norm, rotation_step_squared

LOSSES = {"trivial": 0, "huber": 1, "soft_l1": 2, "cauchy": 3}
"""Robust losses by name -> the kernel's code."""
CHI2_2DOF_95 = 5.991
"""The 95 % quantile of chi-square with 2 degrees of freedom: ORB-SLAM's outlier bound on the squared
whitened error (and sqrt of it, its Huber scale)."""
TERMINATIONS = ("CONVERGENCE", "NO_CONVERGENCE", "ABORTED", "FAILURE")
_CONVERGENCE, _NO_CONVERGENCE, _ABORTED, _FAILURE = range(4)
_MIN_DIAGONAL, _MAX_DIAGONAL = 1e-6, 1e32
"""Ceres' clamp of the diagonal that Levenberg-Marquardt's damping scales (min/max_lm_diagonal)."""
_INITIAL_LAMBDA = 1e-4
"""1 / Ceres' initial trust region radius (1e4)."""
_MIN_RELATIVE_DECREASE = 1e-3
"""A step is accepted when it lowers the cost by at least this fraction of the model's prediction (Ceres)."""


@dataclass(frozen=True, eq=False)
class LocalBAResult:
    """Outcome of :func:`local_bundle_adjustment`.

    success: the solve ran (False: the input could not be solved, ``reason`` says why, and the poses and points
    are the input's); reason: why not, or on success a note on observations left out ('' when none);
    termination: CONVERGENCE, NO_CONVERGENCE (max iterations), ABORTED or FAILURE; cam_from_world: (K, 4, 4)
    the adjusted poses; points: (P, 3) the adjusted points (world units); initial_cost / final_cost: Ceres'
    cost 1/2 sum rho(s) over the used observations; iterations: linear solves run; chi2: (N,) each
    observation's squared whitened error w |error|^2 at the result (inf: unusable, or at depth <= min_depth),
    for :func:`outlier_mask`; num_residuals: observations in the cost."""

    success: bool
    reason: str
    termination: str
    cam_from_world: np.ndarray
    points: np.ndarray
    initial_cost: float
    final_cost: float
    iterations: int
    chi2: np.ndarray
    num_residuals: int


def outlier_mask(chi2: np.ndarray, threshold: float = CHI2_2DOF_95) -> np.ndarray:
    """(N,) bool: ORB-SLAM's outliers after local BA, the observations whose squared whitened error ``chi2``
    ((N,), :attr:`LocalBAResult.chi2`) exceeds ``threshold`` (5.991: 95 % of chi-square with 2 DoF) or is
    inf (behind the camera, unusable)."""
    chi2 = np.asarray(chi2, np.float64)
    return ~(chi2 <= threshold)


@njit(cache=True, nogil=True)
def _rho(s, loss, a2):
    """(rho(s), rho'(s)) of the loss (code of :data:`LOSSES`) with squared scale a2."""
    if loss == 1:
        if s <= a2:
            return s, 1.0
        r = math.sqrt(s)
        a = math.sqrt(a2)
        return 2.0 * a * r - a2, a / r
    if loss == 2:
        q = math.sqrt(1.0 + s / a2)
        return 2.0 * a2 * (q - 1.0), 1.0 / q
    if loss == 3:
        q = 1.0 + s / a2
        return a2 * math.log(q), 1.0 / q
    return s, 1.0


@njit(cache=True, nogil=True)
def _to_camera(R, t, X, k, p):
    x = R[k, 0, 0] * X[p, 0] + R[k, 0, 1] * X[p, 1] + R[k, 0, 2] * X[p, 2] + t[k, 0]
    y = R[k, 1, 0] * X[p, 0] + R[k, 1, 1] * X[p, 1] + R[k, 1, 2] * X[p, 2] + t[k, 1]
    z = R[k, 2, 0] * X[p, 0] + R[k, 2, 1] * X[p, 1] + R[k, 2, 2] * X[p, 2] + t[k, 2]
    return x, y, z


@njit(cache=True, nogil=True)
def _cost(R, t, X, obs_pose, obs_point, xy, w, active, cam, loss, a2, min_depth, zero_behind=False):
    """1/2 sum rho(s) over the active observations; inf when one of them is at depth <= min_depth (with
    zero_behind: that observation adds 0, COLMAP's reprojection cost)."""
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    total = 0.0
    for i in range(obs_pose.shape[0]):
        if not active[i]:
            continue
        x, y, z = _to_camera(R, t, X, obs_pose[i], obs_point[i])
        if not z > min_depth:
            if zero_behind:
                continue
            return np.inf
        ru = fx * x / z + cx - xy[i, 0]
        rv = fy * y / z + cy - xy[i, 1]
        total += _rho(w[i] * (ru * ru + rv * rv), loss, a2)[0]
    return 0.5 * total


@njit(cache=True, nogil=True)
def _jacobians(R, t, X, k, p, xy_i, cam, Jp, Jx, r):
    """Residual r (2,) = pi(R_k X_p + t_k) - xy_i, its Jacobians Jp (2, 6) in (omega, dt) and Jx (2, 3) in X_p."""
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    x, y, z = _to_camera(R, t, X, k, p)
    iz = 1.0 / z
    r[0] = fx * x * iz + cx - xy_i[0]
    r[1] = fy * y * iz + cy - xy_i[1]
    a00, a02 = fx * iz, -fx * x * iz * iz  # d pixel / d Xc
    a11, a12 = fy * iz, -fy * y * iz * iz
    # d Xc / d omega = -[R X]x with R X = Xc - t (left perturbation); d Xc / d t = I; d Xc / d X = R
    qx, qy, qz = x - t[k, 0], y - t[k, 1], z - t[k, 2]
    # rows of -[q]x: (0, qz, -qy), (-qz, 0, qx), (qy, -qx, 0)
    Jp[0, 0] = a02 * qy
    Jp[0, 1] = a00 * qz - a02 * qx
    Jp[0, 2] = -a00 * qy
    Jp[1, 0] = -a11 * qz + a12 * qy
    Jp[1, 1] = -a12 * qx
    Jp[1, 2] = a11 * qx
    Jp[0, 3], Jp[0, 4], Jp[0, 5] = a00, 0.0, a02
    Jp[1, 3], Jp[1, 4], Jp[1, 5] = 0.0, a11, a12
    for c in range(3):
        Jx[0, c] = a00 * R[k, 0, c] + a02 * R[k, 2, c]
        Jx[1, c] = a11 * R[k, 1, c] + a12 * R[k, 2, c]


@njit(cache=True, nogil=True)
def _linearize(R, t, X, obs_pose, obs_point, xy, w, active, cam, loss, a2, pose_var, point_var, dof_mask,
               U, bx, V, by, Wb, min_depth=0.0):
    """Normal equations' blocks: U (Kv, 6, 6), bx (Kv, 6) of the variable poses, V (Pv, 3, 3), by (Pv, 3) of the
    variable points, Wb (N, 6, 3) of each observation joining both (zero otherwise); bx and by are the cost's
    gradient. Pose components held by dof_mask (K, 6) (0: held) get zero Jacobian columns; an observation at
    depth <= min_depth adds nothing (its residual is 0 or the state refused)."""
    U[:] = 0.0
    bx[:] = 0.0
    V[:] = 0.0
    by[:] = 0.0
    Jp, Jx, r = np.empty((2, 6)), np.empty((2, 3)), np.empty(2)
    for i in range(obs_pose.shape[0]):
        for a in range(6):
            for b in range(3):
                Wb[i, a, b] = 0.0
        if not active[i]:
            continue
        k, p = obs_pose[i], obs_point[i]
        kv, pv = pose_var[k], point_var[p]
        if kv < 0 and pv < 0:
            continue
        if not _to_camera(R, t, X, k, p)[2] > min_depth:
            continue
        _jacobians(R, t, X, k, p, xy[i], cam, Jp, Jx, r)
        om = w[i] * _rho(w[i] * (r[0] * r[0] + r[1] * r[1]), loss, a2)[1]
        if kv >= 0:
            for a in range(6):
                Jp[0, a] *= dof_mask[k, a]
                Jp[1, a] *= dof_mask[k, a]
            for a in range(6):
                bx[kv, a] += om * (Jp[0, a] * r[0] + Jp[1, a] * r[1])
                for b in range(6):
                    U[kv, a, b] += om * (Jp[0, a] * Jp[0, b] + Jp[1, a] * Jp[1, b])
        if pv >= 0:
            for a in range(3):
                by[pv, a] += om * (Jx[0, a] * r[0] + Jx[1, a] * r[1])
                for b in range(3):
                    V[pv, a, b] += om * (Jx[0, a] * Jx[0, b] + Jx[1, a] * Jx[1, b])
        if kv >= 0 and pv >= 0:
            for a in range(6):
                for b in range(3):
                    Wb[i, a, b] = om * (Jp[0, a] * Jx[0, b] + Jp[1, a] * Jx[1, b])


@njit(cache=True, nogil=True)
def _cholesky_solve(S, rhs, out, m):
    """out = S^-1 rhs for the leading m x m block of S (symmetric), in place of S's lower triangle; False when S
    is not positive definite."""
    for j in range(m):
        s = S[j, j]
        for k in range(j):
            s -= S[j, k] * S[j, k]
        if not s > 0:
            return False
        d = math.sqrt(s)
        S[j, j] = d
        for i in range(j + 1, m):
            s = S[i, j]
            for k in range(j):
                s -= S[i, k] * S[j, k]
            S[i, j] = s / d
    for i in range(m):
        s = rhs[i]
        for k in range(i):
            s -= S[i, k] * out[k]
        out[i] = s / S[i, i]
    for i in range(m - 1, -1, -1):
        s = out[i]
        for k in range(i + 1, m):
            s -= S[k, i] * out[k]
        out[i] = s / S[i, i]
    return True


@njit(cache=True, nogil=True)
def _invert3(A, out):
    """out = A^-1 (3 x 3); False when singular or not finite."""
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    if not (abs(det) > 1e-300 and np.isfinite(det)):
        return False
    inv = 1.0 / det
    out[0, 0], out[1, 0], out[2, 0] = c00 * inv, c01 * inv, c02 * inv
    out[0, 1] = (A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]) * inv
    out[1, 1] = (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) * inv
    out[2, 1] = (A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]) * inv
    out[0, 2] = (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) * inv
    out[1, 2] = (A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]) * inv
    out[2, 2] = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) * inv
    return True


@njit(cache=True, nogil=True)
def _solve_step(U, bx, V, by, Wb, obs_pose, active, pose_var, var_mask, pt_ptr, pt_obs, lam, S, rhs, dx, dy,
                Vinv, Du, Dv):
    """The damped step (dx (Kv*6,), dy (Pv, 3)) by the Schur complement on the poses; Du (Kv, 6) and Dv (Pv, 3)
    get the clamped diagonals the damping scales. var_mask (Kv*6,): 0 for pose components held. False when the
    damped system is not positive definite."""
    Kv, Pv = U.shape[0], V.shape[0]
    m = 6 * Kv
    S[:, :] = 0.0
    for kv in range(Kv):
        for a in range(6):
            Du[kv, a] = min(max(U[kv, a, a], _MIN_DIAGONAL), _MAX_DIAGONAL)
            for b in range(6):
                S[6 * kv + a, 6 * kv + b] = U[kv, a, b]
            S[6 * kv + a, 6 * kv + a] += lam * Du[kv, a]
            rhs[6 * kv + a] = -bx[kv, a]
    A = np.empty((3, 3))
    Y = np.empty((6, 3))
    for pv in range(Pv):
        for a in range(3):
            Dv[pv, a] = min(max(V[pv, a, a], _MIN_DIAGONAL), _MAX_DIAGONAL)
            for b in range(3):
                A[a, b] = V[pv, a, b]
            A[a, a] += lam * Dv[pv, a]
        if not _invert3(A, Vinv[pv]):
            return False
        for ia in range(pt_ptr[pv], pt_ptr[pv + 1]):
            i = pt_obs[ia]
            ka = pose_var[obs_pose[i]]
            if ka < 0 or not active[i]:
                continue
            for a in range(6):  # Y = W_i V^-1
                for b in range(3):
                    Y[a, b] = Wb[i, a, 0] * Vinv[pv, 0, b] + Wb[i, a, 1] * Vinv[pv, 1, b] + Wb[i, a, 2] * Vinv[pv, 2, b]
            for a in range(6):  # rhs_k += W V^-1 by (from -bx + W V^-1 by)
                rhs[6 * ka + a] += Y[a, 0] * by[pv, 0] + Y[a, 1] * by[pv, 1] + Y[a, 2] * by[pv, 2]
            for ib in range(ia, pt_ptr[pv + 1]):  # the pairs once: S[kb, ka] = S[ka, kb]^T
                j = pt_obs[ib]
                kb = pose_var[obs_pose[j]]
                if kb < 0 or not active[j]:
                    continue
                for a in range(6):
                    for b in range(6):
                        v = Y[a, 0] * Wb[j, b, 0] + Y[a, 1] * Wb[j, b, 1] + Y[a, 2] * Wb[j, b, 2]
                        S[6 * ka + a, 6 * kb + b] -= v
                        if kb != ka or ib != ia:
                            S[6 * kb + b, 6 * ka + a] -= v
    for c in range(m):  # held components: identity rows, zero steps
        if var_mask[c] == 0.0:
            for d in range(m):
                S[c, d] = 0.0
                S[d, c] = 0.0
            S[c, c] = 1.0
            rhs[c] = 0.0
    if m > 0 and not _cholesky_solve(S, rhs, dx, m):
        return False
    for pv in range(Pv):  # dy = V^-1 (-by - W^T dx)
        s0, s1, s2 = -by[pv, 0], -by[pv, 1], -by[pv, 2]
        for ia in range(pt_ptr[pv], pt_ptr[pv + 1]):
            i = pt_obs[ia]
            ka = pose_var[obs_pose[i]]
            if ka < 0 or not active[i]:
                continue
            for a in range(6):
                d = dx[6 * ka + a]
                s0 -= Wb[i, a, 0] * d
                s1 -= Wb[i, a, 1] * d
                s2 -= Wb[i, a, 2] * d
        for a in range(3):
            dy[pv, a] = Vinv[pv, a, 0] * s0 + Vinv[pv, a, 1] * s1 + Vinv[pv, a, 2] * s2
    return True


@njit(cache=True, nogil=True)
def _retract(R, t, X, pose_ids, point_ids, dx, dy, R_out, t_out, X_out):
    """(R_out, t_out, X_out) = the state moved by the step: R_k <- exp([omega]x) R_k (Rodrigues), t_k <- t_k + dt,
    X_p <- X_p + dX for the variable poses pose_ids (Kv,) and points point_ids (Pv,); the rest copied."""
    R_out[:] = R
    t_out[:] = t
    X_out[:] = X
    for kv in range(pose_ids.shape[0]):
        k = pose_ids[kv]
        wx, wy, wz = dx[6 * kv], dx[6 * kv + 1], dx[6 * kv + 2]
        th2 = wx * wx + wy * wy + wz * wz
        if th2 < 1e-12:
            a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
        else:
            th = math.sqrt(th2)
            a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
        W = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
        dR = np.eye(3) + a * W + b * (W @ W)
        R_out[k] = dR @ R[k]
        for c in range(3):
            t_out[k, c] = t[k, c] + dx[6 * kv + 3 + c]
    for pv in range(point_ids.shape[0]):
        p = point_ids[pv]
        for c in range(3):
            X_out[p, c] = X[p, c] + dy[pv, c]


@njit(cache=True, nogil=True)
def _local_ba_kernel(R, t, X, obs_pose, obs_point, xy, w, active, cam, loss, a2, pose_ids, pose_var, dof_mask,
                     point_ids, point_var, pt_ptr, pt_obs, max_iterations, function_tolerance, parameter_tolerance,
                     gradient_tolerance, min_depth, zero_behind, abort, info):
    """Levenberg-Marquardt on (R (K, 3, 3), t (K, 3), X (P, 3)) in place. info (4,) gets (initial cost, final
    cost, iterations, termination code)."""
    Kv, Pv, N = pose_ids.shape[0], point_ids.shape[0], obs_pose.shape[0]
    cost = _cost(R, t, X, obs_pose, obs_point, xy, w, active, cam, loss, a2, min_depth, zero_behind)
    info[0] = cost
    info[1] = cost
    info[2] = 0
    if not np.isfinite(cost):
        info[3] = _FAILURE
        return
    U, bx = np.empty((Kv, 6, 6)), np.empty((Kv, 6))
    V, by = np.empty((Pv, 3, 3)), np.empty((Pv, 3))
    Wb = np.empty((N, 6, 3))
    S, rhs, dx = np.empty((6 * Kv, 6 * Kv)), np.empty(6 * Kv), np.zeros(6 * Kv)
    dy, Vinv = np.zeros((Pv, 3)), np.empty((Pv, 3, 3))
    Du, Dv = np.empty((Kv, 6)), np.empty((Pv, 3))
    var_mask = np.empty(6 * Kv)
    for kv in range(Kv):
        for a in range(6):
            var_mask[6 * kv + a] = dof_mask[pose_ids[kv], a]
    R_new, t_new, X_new = np.empty_like(R), np.empty_like(t), np.empty_like(X)
    _linearize(R, t, X, obs_pose, obs_point, xy, w, active, cam, loss, a2, pose_var, point_var, dof_mask,
               U, bx, V, by, Wb, min_depth)
    lam, nu = _INITIAL_LAMBDA, 2.0
    it, term = 0, _NO_CONVERGENCE
    while it < max_iterations:
        if abort[0] != 0:
            term = _ABORTED
            break
        if gradient_max_norm(R, pose_ids, bx, by) <= gradient_tolerance:  # as Ceres measures it
            term = _CONVERGENCE
            break
        it += 1
        if not _solve_step(U, bx, V, by, Wb, obs_pose, active, pose_var, var_mask, pt_ptr, pt_obs, lam, S, rhs, dx,
                           dy, Vinv, Du, Dv):
            lam *= nu
            nu *= 2.0
            continue
        step2, x2, predicted = 0.0, float(Kv), 0.0
        for kv in range(Kv):
            step2 += rotation_step_squared(dx[6 * kv], dx[6 * kv + 1], dx[6 * kv + 2])  # in the quaternion
            for a in range(6):
                d = dx[6 * kv + a]
                step2 += d * d if a >= 3 else 0.0
                predicted += d * (lam * Du[kv, a] * d - bx[kv, a])
            k = pose_ids[kv]
            x2 += t[k, 0] ** 2 + t[k, 1] ** 2 + t[k, 2] ** 2
        for pv in range(Pv):
            p = point_ids[pv]
            for a in range(3):
                d = dy[pv, a]
                step2 += d * d
                predicted += d * (lam * Dv[pv, a] * d - by[pv, a])
                x2 += X[p, a] ** 2
        predicted *= 0.5
        if math.sqrt(step2) <= parameter_tolerance * (math.sqrt(x2) + parameter_tolerance):
            term = _CONVERGENCE
            break
        _retract(R, t, X, pose_ids, point_ids, dx, dy, R_new, t_new, X_new)
        new_cost = _cost(R_new, t_new, X_new, obs_pose, obs_point, xy, w, active, cam, loss, a2, min_depth,
                         zero_behind)
        if np.isfinite(new_cost) and abs(cost - new_cost) <= function_tolerance * cost:
            term = _CONVERGENCE  # Ceres' rule: the candidate that changes the cost this little is not taken
            break
        rho = (cost - new_cost) / predicted if predicted > 0 else -1.0
        if np.isfinite(new_cost) and rho > _MIN_RELATIVE_DECREASE:
            R[:] = R_new
            t[:] = t_new
            X[:] = X_new
            cost = new_cost
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            _linearize(R, t, X, obs_pose, obs_point, xy, w, active, cam, loss, a2, pose_var, point_var, dof_mask,
                       U, bx, V, by, Wb, min_depth)
        else:
            lam *= nu
            nu *= 2.0
    info[1] = cost
    info[2] = it
    info[3] = term


@njit(cache=True, nogil=True)
def _chi2(R, t, X, obs_pose, obs_point, xy, w, usable, cam, min_depth, out):
    """out (N,): w |error|^2 of each usable observation at depth > min_depth, else inf."""
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    for i in range(obs_pose.shape[0]):
        out[i] = np.inf
        if not usable[i]:
            continue
        x, y, z = _to_camera(R, t, X, obs_pose[i], obs_point[i])
        if z > min_depth:
            ru = fx * x / z + cx - xy[i, 0]
            rv = fy * y / z + cy - xy[i, 1]
            out[i] = w[i] * (ru * ru + rv * rv)


def local_bundle_adjustment(cam_from_world: np.ndarray, points: np.ndarray, obs_pose: np.ndarray,
                            obs_point: np.ndarray, obs_xy: np.ndarray, camera, obs_weight: np.ndarray | None = None,
                            pose_fixed: np.ndarray | None = None, point_fixed: np.ndarray | None = None,
                            gauge: tuple[int, int] | None = None, loss: str = "huber",
                            loss_scale: float = math.sqrt(CHI2_2DOF_95), max_iterations: int = 20,
                            function_tolerance: float = 1e-6, parameter_tolerance: float = 1e-8,
                            gradient_tolerance: float = 1e-10,
                            min_depth: float = 1e-6, abort: np.ndarray | None = None,
                            obs_mask: np.ndarray | None = None, behind_camera: str = "refuse") -> LocalBAResult:
    """Adjust the poses and points (see the module docstring for the cost and the solver).

    cam_from_world: (K, 4, 4) or (K, 3, 4) poses; points: (P, 3) world points; obs_pose, obs_point: (N,) int
    indices into them; obs_xy: (N, 2) undistorted pixels; camera: (fx, fy, cx, cy) pinhole, pixels;
    obs_weight: (N,) information per observation (1/sigma^2 pixels^-2; None: all 1); pose_fixed (K,) and
    point_fixed (P,) bool: held constant (None: none); gauge: (pose index, axis 0-2) of one translation
    coordinate held besides (COLMAP's TWO_CAMS_FROM_WORLD: the second camera's largest baseline coordinate);
    loss: "huber", "soft_l1", "cauchy" or "trivial", at ``loss_scale`` on the whitened error; abort: a one-element
    integer array, the solve stops before the next iteration once it is non-zero; obs_mask: (N,) bool, the
    observations in the cost (None: all): the others are only measured (their chi2 at the result), as
    ORB-SLAM's second pass leaves out the first pass's outliers and then tests every observation again;
    behind_camera: an observation whose point is at depth <= min_depth, "refuse": left out when it is so at
    the start, and a step that puts a used one there is refused; "zero": its residual is 0 (COLMAP 4's
    reprojection cost: it drops out while behind, and may come back), so the optimum is Ceres' on COLMAP's
    problem.

    Observations with a non-finite pixel, a weight <= 0 or not finite, or ("refuse") a point at depth <=
    min_depth at the start are left out of the cost (chi2 inf: :func:`outlier_mask` classes them outliers) and
    counted in ``reason``. Non-finite poses, points or camera, or no usable observation, give a result with ``success``
    False and the reason, the input unchanged; arrays of wrong shapes or indices out of range raise
    ValueError. Nothing given is modified."""
    T = np.asarray(cam_from_world, np.float64)
    if T.ndim != 3 or T.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"cam_from_world must be (K, 4, 4) or (K, 3, 4), got {T.shape}")
    K = T.shape[0]
    X = np.array(points, np.float64).reshape(-1, 3) if np.size(points) else np.zeros((0, 3))
    P = X.shape[0]
    obs_pose = np.ascontiguousarray(obs_pose, np.int64).reshape(-1)
    obs_point = np.ascontiguousarray(obs_point, np.int64).reshape(-1)
    N = obs_pose.shape[0]
    xy = np.ascontiguousarray(obs_xy, np.float64).reshape(-1, 2) if N else np.zeros((0, 2))
    w = np.ones(N) if obs_weight is None else np.ascontiguousarray(obs_weight, np.float64).reshape(-1)
    if obs_point.shape != (N,) or xy.shape != (N, 2) or w.shape != (N,):
        raise ValueError(f"obs_pose, obs_point, obs_weight must be (N,) and obs_xy (N, 2), got {obs_pose.shape}, "
                         f"{obs_point.shape}, {w.shape}, {xy.shape}")
    if N and (obs_pose.min() < 0 or obs_pose.max() >= K or obs_point.min() < 0 or obs_point.max() >= P):
        raise ValueError(f"obs_pose must index the {K} poses and obs_point the {P} points")
    pose_fixed = np.zeros(K, bool) if pose_fixed is None else np.asarray(pose_fixed, bool).reshape(-1)
    point_fixed = np.zeros(P, bool) if point_fixed is None else np.asarray(point_fixed, bool).reshape(-1)
    if pose_fixed.shape != (K,) or point_fixed.shape != (P,):
        raise ValueError(f"pose_fixed must be ({K},) and point_fixed ({P},), got {pose_fixed.shape}, "
                         f"{point_fixed.shape}")
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {sorted(LOSSES)}, got {loss!r}")
    cam = np.asarray(camera, np.float64).reshape(-1)
    if cam.shape != (4,):
        raise ValueError(f"camera must be (fx, fy, cx, cy), got shape {cam.shape}")
    abort = np.zeros(1, np.int64) if abort is None else abort
    R, t = np.ascontiguousarray(T[:, :3, :3]), np.ascontiguousarray(T[:, :3, 3])
    chi2 = np.full(N, np.inf)

    def result(success, reason, termination="FAILURE", c0=0.0, c1=0.0, its=0, n=0):
        out = np.tile(np.eye(4), (K, 1, 1))
        out[:, :3, :3], out[:, :3, 3] = R, t
        return LocalBAResult(success, reason, termination, out, X, float(c0), float(c1), int(its), chi2, int(n))

    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        return result(False, f"pose {int(np.flatnonzero(~np.isfinite(T).all(axis=(1, 2)))[0])} is not finite")
    if not np.isfinite(X).all():
        return result(False, f"point {int(np.flatnonzero(~np.isfinite(X).all(axis=1))[0])} is not finite")
    if not (np.isfinite(cam).all() and cam[0] > 0 and cam[1] > 0):
        return result(False, f"camera {cam.tolist()} is not a pinhole with positive focal lengths")
    if not np.isfinite(loss_scale) or loss_scale <= 0:
        return result(False, f"loss_scale {loss_scale} is not positive")
    with np.errstate(invalid="ignore"):
        usable = np.isfinite(xy).all(axis=1) & np.isfinite(w) & (w > 0)
    in_front = np.einsum("nj,nj->n", R[obs_pose, 2], X[obs_point]) + t[obs_pose, 2] > min_depth
    if behind_camera not in ("refuse", "zero"):
        raise ValueError(f"behind_camera must be 'refuse' or 'zero', got {behind_camera!r}")
    zero_behind = behind_camera == "zero"
    active = usable & (in_front | zero_behind)
    if obs_mask is not None:
        if np.shape(obs_mask) != (N,):
            raise ValueError(f"obs_mask must be ({N},), got {np.shape(obs_mask)}")
        active &= np.asarray(obs_mask, bool)
    left_out = []
    if (~usable).any():
        left_out.append(f"{int((~usable).sum())} unusable (pixel or weight not finite, or weight <= 0)")
    if (usable & ~in_front).any():
        left_out.append(f"{int((usable & ~in_front).sum())} at depth <= {min_depth} (behind the camera"
                        + (": residual 0)" if zero_behind else ")"))
    note = ("observations left out: " + ", ".join(left_out)) if left_out else ""
    if not active.any():
        return result(False, f"no usable observation of {N}" + (f" ({note})" if note else ""))

    dof_mask = np.ones((K, 6))
    if gauge is not None:
        g_pose, g_axis = int(gauge[0]), int(gauge[1])
        if not (0 <= g_pose < K and 0 <= g_axis < 3):
            raise ValueError(f"gauge must be (pose index < {K}, axis 0-2), got {gauge}")
        dof_mask[g_pose, 3 + g_axis] = 0.0
    pose_ids, point_ids = np.flatnonzero(~pose_fixed).astype(np.int64), np.flatnonzero(~point_fixed).astype(np.int64)
    pose_var = np.where(pose_fixed, -1, np.cumsum(~pose_fixed) - 1).astype(np.int64)
    point_var = np.where(point_fixed, -1, np.cumsum(~point_fixed) - 1).astype(np.int64)
    pv = point_var[obs_point]
    with_var = np.flatnonzero(pv >= 0)
    pt_obs = with_var[np.argsort(pv[with_var], kind="stable")].astype(np.int64)
    pt_ptr = np.searchsorted(pv[pt_obs], np.arange(len(point_ids) + 1)).astype(np.int64)
    info = np.zeros(4)
    w_used = np.where(usable, w, 0.0)
    xy_used = np.where(usable[:, None], xy, 0.0)
    _local_ba_kernel(R, t, X, obs_pose, obs_point, xy_used, w_used, active, cam, LOSSES[loss],
                     float(loss_scale) ** 2, pose_ids, pose_var, dof_mask, point_ids, point_var, pt_ptr, pt_obs,
                     int(max_iterations), float(function_tolerance), float(parameter_tolerance),
                     float(gradient_tolerance), float(min_depth), zero_behind, abort, info)
    _chi2(R, t, X, obs_pose, obs_point, xy_used, w_used, usable, cam, float(min_depth), chi2)
    term = TERMINATIONS[int(info[3])]
    if term == "FAILURE":
        return result(False, "the initial cost is not finite", term, info[0], info[1], info[2], active.sum())
    return result(True, note, term, info[0], info[1], info[2], active.sum())
