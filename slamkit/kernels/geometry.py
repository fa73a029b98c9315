"""Rigid-body helpers in pure numpy: quaternions (x, y, z, w) and 4x4 poses; two-view measures (parallax,
flow score) shared by the stages.

Quaternions are Hamilton, stored ``(qx, qy, qz, qw)`` like TUM files and pycolmap's ``Rotation3d.quat``.
Poses are (4, 4) float64 homogeneous matrices; in slamkit they are camera-to-world unless named otherwise.
Every function accepts one item or a stack (leading batch dimension) and never mutates its arguments.
"""

from __future__ import annotations

import numpy as np


def normalize_quaternion(q_xyzw: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions -> (..., 4) float64 unit quaternions with ``qw >= 0``.

    Raises ``ValueError`` for a non-finite quaternion or one of zero norm: it encodes no rotation.
    """
    q = np.asarray(q_xyzw, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ValueError(f"quaternions need 4 values (qx qy qz qw), got shape {q.shape}")
    if not np.isfinite(q).all():
        raise ValueError("quaternion has non-finite values")
    scale = np.abs(q).max(axis=-1, keepdims=True)  # pre-scaling: no overflow/underflow in the norm
    if (scale == 0).any():
        raise ValueError("quaternion has zero norm")
    q = q / scale
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def rotation_from_quaternion(q_xyzw: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (x, y, z, w; normalised here) -> (..., 3, 3) float64 rotation matrices."""
    x, y, z, w = np.moveaxis(normalize_quaternion(q_xyzw), -1, 0)
    r = np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], axis=-1)
    return r.reshape(r.shape[:-1] + (3, 3))


def quaternion_from_rotation(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) float64 unit quaternions (x, y, z, w) with ``qw >= 0``.

    Shepperd's method (branch on the largest of w, x, y, z), stable for every rotation angle.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must be (..., 3, 3), got shape {R.shape}")
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    # 4 * (w^2, x^2, y^2, z^2) up to the common trace term
    diag = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    k = np.argmax(diag, axis=1)
    q = np.empty((len(m), 4))
    for i in range(len(m)):
        a = m[i]
        if k[i] == 0:
            s = 2.0 * np.sqrt(max(1.0 + tr[i], 0.0))
            q[i] = [(a[2, 1] - a[1, 2]) / s, (a[0, 2] - a[2, 0]) / s, (a[1, 0] - a[0, 1]) / s, 0.25 * s]
        elif k[i] == 1:
            s = 2.0 * np.sqrt(max(1.0 + a[0, 0] - a[1, 1] - a[2, 2], 0.0))
            q[i] = [0.25 * s, (a[0, 1] + a[1, 0]) / s, (a[0, 2] + a[2, 0]) / s, (a[2, 1] - a[1, 2]) / s]
        elif k[i] == 2:
            s = 2.0 * np.sqrt(max(1.0 + a[1, 1] - a[0, 0] - a[2, 2], 0.0))
            q[i] = [(a[0, 1] + a[1, 0]) / s, 0.25 * s, (a[1, 2] + a[2, 1]) / s, (a[0, 2] - a[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(max(1.0 + a[2, 2] - a[0, 0] - a[1, 1], 0.0))
            q[i] = [(a[0, 2] + a[2, 0]) / s, (a[1, 2] + a[2, 1]) / s, 0.25 * s, (a[1, 0] - a[0, 1]) / s]
    return normalize_quaternion(q).reshape(R.shape[:-2] + (4,))


def pose_from_tum(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """Translation (..., 3) metres and quaternion (..., 4) x, y, z, w -> (..., 4, 4) float64 pose.

    The TUM line ``timestamp tx ty tz qx qy qz qw`` is ``pose_from_tum(row[1:4], row[4:8])``; the
    quaternion is normalised (TUM files round to 4 decimals).
    """
    t = np.asarray(t, dtype=np.float64)
    R = rotation_from_quaternion(q_xyzw)
    if t.shape[-1] != 3 or t.shape[:-1] != R.shape[:-2]:
        raise ValueError(f"translation shape {t.shape} does not match quaternion shape {np.shape(q_xyzw)}")
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def tum_from_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 4, 4) or (..., 3, 4) pose -> (translation (..., 3), quaternion (..., 4) x, y, z, w)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] not in ((4, 4), (3, 4)):
        raise ValueError(f"poses must be (..., 4, 4) or (..., 3, 4), got shape {T.shape}")
    return T[..., :3, 3].copy(), quaternion_from_rotation(T[..., :3, :3])


def pose_from_rows(rows: np.ndarray) -> np.ndarray:
    """(..., 12) row-major 3x4 matrices (the KITTI pose line) -> (..., 4, 4) float64 poses."""
    rows = np.asarray(rows, dtype=np.float64)
    if rows.shape[-1] != 12:
        raise ValueError(f"3x4 poses need 12 values per row, got shape {rows.shape}")
    T = np.zeros(rows.shape[:-1] + (4, 4))
    T[..., :3, :] = rows.reshape(rows.shape[:-1] + (3, 4))
    T[..., 3, 3] = 1.0
    return T


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> angle in degrees (float for one rotation), accurate for small and large
    angles (atan2 of the axis norm and the trace, not acos of the trace)."""
    R = np.asarray(R, dtype=np.float64)
    axis = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    angle = np.degrees(np.arctan2(np.linalg.norm(axis, axis=-1), trace - 1.0))
    return float(angle) if angle.ndim == 0 else angle


def invert_pose(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) rigid transforms -> their inverses (R^T, -R^T t), without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def parallax_deg(x1: np.ndarray, x2: np.ndarray, R_2from1: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Triangulation angle (degrees) of matches x1 <-> x2 (N, 2) pixels: the angle between the viewing rays
    of both cameras expressed in camera 1 (rotation compensated; independent of the baseline length)."""
    Kinv = np.linalg.inv(K)
    r1 = np.c_[x1, np.ones(len(x1))] @ Kinv.T
    r2 = (np.c_[x2, np.ones(len(x2))] @ Kinv.T) @ R_2from1  # R^T r2, row-wise
    cos = np.einsum("ij,ij->i", r1, r2) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def flow_score(xy_ref: np.ndarray, xy_cur: np.ndarray, fx: float, fy: float) -> float:
    """Median normalised flow of matched points (seed §3.2): median(|x1 - x2| / fx) + median(|y1 - y2| / fy).

    xy_ref, xy_cur: (N, 2) pixels of the same points in the reference keyframe and the current frame.
    Returns 0.0 when there are no matches. Unitless (roughly radians of apparent motion).
    """
    if len(xy_ref) == 0:
        return 0.0
    d = np.abs(np.asarray(xy_ref, np.float64) - np.asarray(xy_cur, np.float64))
    return float(np.median(d[:, 0]) / fx + np.median(d[:, 1]) / fy)
