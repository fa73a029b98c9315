"""Optical-flow score between matched points (seed §3.2)."""

from __future__ import annotations

import numpy as np


def flow_score(xy_ref: np.ndarray, xy_cur: np.ndarray, fx: float, fy: float) -> float:
    """Median normalised flow of matched points: median(|x1 - x2| / fx) + median(|y1 - y2| / fy).

    xy_ref, xy_cur: (N, 2) pixels of the same points in the reference keyframe and the current frame.
    Returns 0.0 when there are no matches. Unitless (roughly radians of apparent motion).
    """
    if len(xy_ref) == 0:
        return 0.0
    d = np.abs(np.asarray(xy_ref, np.float64) - np.asarray(xy_cur, np.float64))
    return float(np.median(d[:, 0]) / fx + np.median(d[:, 1]) / fy)
