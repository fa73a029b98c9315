"""Ground-truth trajectories of image sequences: reading TUM trajectory files and associating image times
with ground-truth times. Shared by the TUM, EuRoC and folder layouts.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..geometry import pose_from_tum
from .textfiles import parse_float_rows


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM trajectory file -> (timestamps (N,) float64 s, poses (N, 4, 4) float64).

    Lines are ``timestamp tx ty tz qx qy qz qw`` (camera-to-world, quaternion normalised here); values must
    be finite, quaternions non-zero and timestamps strictly increasing (FormatError naming the line).
    """
    path = Path(path)
    rows, lines = parse_float_rows(path, 8, increasing=0, return_lines=True,
                                   what=("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"))
    norms = np.linalg.norm(rows[:, 4:8], axis=1)
    bad = norms < 1e-6
    if bad.any():
        raise FormatError(path, int(lines[np.argmax(bad)]), "quaternion (qx qy qz qw) has zero norm")
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
