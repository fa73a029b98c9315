"""Ground-truth trajectories of image sequences: reading TUM trajectory files and associating image times
with ground-truth times. Shared by the TUM, EuRoC and folder layouts.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..kernels.geometry import pose_from_tum
from .textfiles import parse_float_rows


ROTATION_TOLERANCE = 1e-2
"""Largest error of a ground-truth rotation: max |R^T R - I| of a matrix, | |q| - 1 | of a quaternion (files
round to 4-6 decimals: errors of 1e-4; a larger one is a file in another format, or columns in another order)."""


def check_rotations(path: str | Path, R: np.ndarray, lines: np.ndarray, what: str = "pose") -> None:
    """FormatError naming the first line whose (3, 3) rotation in ``R`` (N, 3, 3) is not a rotation:
    not orthonormal within :data:`ROTATION_TOLERANCE`, or a reflection (determinant -1)."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    if len(R) == 0:
        return
    with np.errstate(all="ignore"):
        error = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(R)
    bad = ~(error <= ROTATION_TOLERANCE) | ~(det > 0)
    if bad.any():
        k = int(np.argmax(bad))
        kind = "a reflection (determinant -1)" if error[k] <= ROTATION_TOLERANCE else \
            f"not orthonormal (|R^T R - I| up to {error[k]:.3g}, determinant {det[k]:.4g})"
        raise FormatError(path, int(lines[k]), f"the {what}'s rotation is not a rotation: {kind}; is the file "
                                               "in this format, its numbers in this order?")


def check_quaternions(path: str | Path, q: np.ndarray, lines: np.ndarray, names: str = "qx qy qz qw") -> None:
    """FormatError naming the first line whose quaternion (N, 4) has a norm other than 1 (within
    :data:`ROTATION_TOLERANCE`): not a rotation, or columns in another order."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    if len(q) == 0:
        return
    with np.errstate(all="ignore"):
        norm = np.linalg.norm(q, axis=1)
    bad = ~(np.abs(norm - 1) <= ROTATION_TOLERANCE)
    if bad.any():
        k = int(np.argmax(bad))
        what = "has zero norm" if norm[k] < 1e-6 else f"has norm {norm[k]:.6g}, not 1: not a rotation"
        raise FormatError(path, int(lines[k]), f"quaternion ({names}) {what}; is the file in this format, its "
                                               "numbers in this order?")


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM trajectory file -> (timestamps (N,) float64 s, poses (N, 4, 4) float64).

    Lines are ``timestamp tx ty tz qx qy qz qw`` (camera-to-world, quaternion normalised here); values must
    be finite, quaternions of norm 1 (within :data:`ROTATION_TOLERANCE`) and timestamps strictly increasing
    (FormatError naming the line).
    """
    path = Path(path)
    rows, lines = parse_float_rows(path, 8, increasing=0, return_lines=True,
                                   what=("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"))
    check_quaternions(path, rows[:, 4:8], lines)
    if len(rows) == 0:
        return np.zeros(0), np.zeros((0, 4, 4))
    return rows[:, 0].copy(), pose_from_tum(rows[:, 1:4], rows[:, 4:8])


def associate_nearest(t_query: np.ndarray, t_ref: np.ndarray, max_dt: float) -> np.ndarray:
    """For each query time, the index of the nearest reference time within ``max_dt`` seconds, else -1.

    ``t_ref`` must be sorted ascending. Returns (len(t_query),) int64.
    """
    t_query = np.asarray(t_query, dtype=np.float64).reshape(-1)
    t_ref = np.asarray(t_ref, dtype=np.float64).reshape(-1)
    out = np.full(len(t_query), -1, dtype=np.int64)
    if len(t_ref) == 0 or len(t_query) == 0:
        return out
    right = np.clip(np.searchsorted(t_ref, t_query), 0, len(t_ref) - 1)
    left = np.clip(right - 1, 0, len(t_ref) - 1)
    pick = np.where(np.abs(t_ref[left] - t_query) <= np.abs(t_ref[right] - t_query), left, right)
    ok = np.abs(t_ref[pick] - t_query) <= max_dt
    out[ok] = pick[ok]
    return out
