"""Timestamp association of a ground truth and an estimate, as evo does it.

Follows ``evo.core.sync.associate_trajectories`` with the nearest-time method (evo 1.38) step for step, so
that the matched pairs, and hence every metric computed on them, are the same as ``evo_ape`` /
``evo_rpe`` report with the same ``--t_max_diff`` and ``--t_offset``:

* the trajectory with fewer poses (the estimate when both have as many) is the *query*; each of its
  timestamps is matched to the nearest timestamp of the other within ``max_dt`` (binary search; on a tie
  the earlier one; a linear search when the other's timestamps are not sorted);
* ``offset`` is added to the estimate's timestamps (subtracted from the ground truth's when the estimate
  is the query, as evo does).

Every query pose is used at most once; a pose of the denser trajectory can, in evo, be the nearest of two
query poses when the denser one has a gap (``max_dt`` larger than half the query's frame interval). Pass
``one_to_one=True`` to keep only the closer of such pairs (then the numbers may differ from evo's).
"""

from __future__ import annotations

import numpy as np

__all__ = ["associate"]


def _matching_time_indices(stamps_1: np.ndarray, stamps_2: np.ndarray, max_diff: float,
                           offset_2: float) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised ``evo.core.sync.matching_time_indices``: for each stamp_1 the nearest stamp_2 (+ offset)."""
    stamps_2 = stamps_2 + offset_2
    if len(stamps_1) == 0 or len(stamps_2) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if not np.all(np.diff(stamps_2) >= 0):
        # evo's fallback for unsorted stamps: nearest by linear search (first of equal distances)
        idx_1, idx_2 = [], []
        for i, s in enumerate(stamps_1):
            diffs = np.abs(stamps_2 - s)
            j = int(np.argmin(diffs))
            if diffs[j] <= max_diff:
                idx_1.append(i)
                idx_2.append(j)
        return np.asarray(idx_1, dtype=np.int64), np.asarray(idx_2, dtype=np.int64)

    in_range = (stamps_1 >= stamps_2[0] - max_diff) & (stamps_1 <= stamps_2[-1] + max_diff)
    upper = np.minimum(np.searchsorted(stamps_2, stamps_1, side="right"), len(stamps_2) - 1)
    diff_ub = stamps_2[upper] - stamps_1
    diff_lb = np.full(len(stamps_1), np.inf)
    has_lower = upper > 0
    diff_lb[has_lower] = stamps_1[has_lower] - stamps_2[upper[has_lower] - 1]
    take_upper = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    take_lower = ~take_upper & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    keep = in_range & (take_upper | take_lower)
    idx_1 = np.flatnonzero(keep)
    idx_2 = np.where(take_upper, upper, upper - 1)[keep]
    return idx_1.astype(np.int64), idx_2.astype(np.int64)


def associate(t_ref: np.ndarray, t_est: np.ndarray, max_dt: float = 0.02, offset: float = 0.0, *,
              one_to_one: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Match estimate timestamps to reference (ground-truth) timestamps by nearest time.

    ``t_ref`` (N,) and ``t_est`` (M,) seconds; ``max_dt`` seconds (evo's ``--t_max_diff``, whose default is
    0.01); ``offset`` seconds added to the estimate's clock (evo's ``--t_offset``).
    Returns ``(idx_ref, idx_est)``: (K,) int64 index arrays of the matched pairs, in time order.
    """
    t_ref = np.asarray(t_ref, dtype=np.float64).reshape(-1)
    t_est = np.asarray(t_est, dtype=np.float64).reshape(-1)
    est_longer = len(t_est) > len(t_ref)
    if est_longer:
        idx_ref, idx_est = _matching_time_indices(t_ref, t_est, max_dt, offset)
        query_dt = np.abs(t_est[idx_est] + offset - t_ref[idx_ref])
        idx_query, idx_other = idx_ref, idx_est
    else:
        idx_est, idx_ref = _matching_time_indices(t_est, t_ref, max_dt, -offset)
        query_dt = np.abs(t_ref[idx_ref] - offset - t_est[idx_est])
        idx_query, idx_other = idx_est, idx_ref
    if one_to_one and len(idx_other):
        # among the query poses that share one pose of the other trajectory, keep the closest in time
        order = np.lexsort((idx_query, query_dt, idx_other))
        first = np.ones(len(order), dtype=bool)
        first[1:] = idx_other[order][1:] != idx_other[order][:-1]
        keep = np.sort(order[first])
        idx_ref, idx_est = idx_ref[keep], idx_est[keep]
    return idx_ref, idx_est
