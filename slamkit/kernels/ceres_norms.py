"""The norms by which Ceres stops, measured as Ceres measures them on COLMAP's parameters.

COLMAP gives Ceres each rotation as a unit quaternion on ``EigenQuaternionManifold``, whose
``Plus(q, d) = [cos|d|, sin|d| d/|d|] q`` turns by 2|d| on the left; the kernels perturb a rotation matrix on the
left by omega (``R <- exp([omega]x) R``), so d = omega / 2 and the gradient in d is twice the gradient in omega.
Ceres stops by the gradient when ``max |x - Plus(x, -g)|`` over the ambient coordinates (the quaternion's four,
translations, points) is at most ``gradient_tolerance``, and by the step when ``|x - Plus(x, step)|`` is at most
``parameter_tolerance (|x| + parameter_tolerance)``. A rotation's part of either is not its tangent's: these
functions give the kernels' solvers the same tests, so they stop where Ceres does (the tracker's
``gradient_tolerance`` of 1.0, COLMAP's, is met or not in the first iterations of many refinements)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _quaternion(R, k, q):
    """q (4,) = (w, x, y, z), the unit quaternion of the rotation matrix R[k] (Shepperd's method)."""
    m00, m11, m22 = R[k, 0, 0], R[k, 1, 1], R[k, 2, 2]
    tr = m00 + m11 + m22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q[0], q[1], q[2], q[3] = 0.25 * s, (R[k, 2, 1] - R[k, 1, 2]) / s, (R[k, 0, 2] - R[k, 2, 0]) / s, \
            (R[k, 1, 0] - R[k, 0, 1]) / s
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        q[0], q[1], q[2], q[3] = (R[k, 2, 1] - R[k, 1, 2]) / s, 0.25 * s, (R[k, 0, 1] + R[k, 1, 0]) / s, \
            (R[k, 0, 2] + R[k, 2, 0]) / s
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        q[0], q[1], q[2], q[3] = (R[k, 0, 2] - R[k, 2, 0]) / s, (R[k, 0, 1] + R[k, 1, 0]) / s, 0.25 * s, \
            (R[k, 1, 2] + R[k, 2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        q[0], q[1], q[2], q[3] = (R[k, 1, 0] - R[k, 0, 1]) / s, (R[k, 0, 2] + R[k, 2, 0]) / s, \
            (R[k, 1, 2] + R[k, 2, 1]) / s, 0.25 * s


@njit(cache=True, nogil=True)
def gradient_max_norm(R, pose_ids, bx, by):
    """Ceres' ``max |x - Plus(x, -g)|`` for the gradients bx (Kv, 6: omega, t) of the variable poses ``pose_ids``
    (rotations R (K, 3, 3)) and by (Pv, 3) of the variable points."""
    gmax = 0.0
    q = np.empty(4)
    for kv in range(pose_ids.shape[0]):
        for a in range(3, 6):
            gmax = max(gmax, abs(bx[kv, a]))
        gx, gy, gz = -2.0 * bx[kv, 0], -2.0 * bx[kv, 1], -2.0 * bx[kv, 2]  # -(gradient in d)
        n = math.sqrt(gx * gx + gy * gy + gz * gz)
        if n == 0.0:
            continue
        _quaternion(R, pose_ids[kv], q)
        s = math.sin(n) / n
        ew, ex, ey, ez = math.cos(n) - 1.0, s * gx, s * gy, s * gz  # Plus(q, -g) - q = (exp(-g) - 1) q
        gmax = max(gmax, abs(ew * q[0] - ex * q[1] - ey * q[2] - ez * q[3]),
                   abs(ew * q[1] + ex * q[0] + ey * q[3] - ez * q[2]),
                   abs(ew * q[2] - ex * q[3] + ey * q[0] + ez * q[1]),
                   abs(ew * q[3] + ex * q[2] - ey * q[1] + ez * q[0]))
    for pv in range(by.shape[0]):
        for a in range(3):
            gmax = max(gmax, abs(by[pv, a]))
    return gmax


@njit(cache=True, nogil=True)
def rotation_step_squared(wx, wy, wz):
    """|Plus(q, d) - q|^2 of a left turn by omega = (wx, wy, wz) (d = omega / 2): (2 sin(|omega| / 4))^2."""
    s = 2.0 * math.sin(0.25 * math.sqrt(wx * wx + wy * wy + wz * wz))
    return s * s
