"""Corner tracks through the first frames of a sequence, for self-calibration
(:mod:`~slamkit.stages.self_calibration`, :mod:`~slamkit.stages.self_calibration.rotation`): pyramidal Lucas-Kanade
with a forward-backward check, so that any feature type works."""

from __future__ import annotations

import cv2
import numpy as np


def track_corners(grays: list[np.ndarray], max_corners: int = 1000) -> list[dict[int, np.ndarray]]:
    """Corner tracks through consecutive frames: one ``{track id: (2,) xy}`` per frame. Lucas-Kanade with a
    forward-backward check (0.5 px); lost corners are replaced by new ones when fewer than half are left."""
    h, w = grays[0].shape[:2]
    min_distance = max(5, int(round(max(w, h) / 80)))
    lk = dict(winSize=(21, 21), maxLevel=4, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    out: list[dict[int, np.ndarray]] = []
    ids = np.zeros(0, np.int64)
    xy = np.zeros((0, 2), np.float32)
    next_id = 0
    for k, g in enumerate(grays):
        if k > 0 and len(xy):
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(grays[k - 1], g, xy.reshape(-1, 1, 2), None, **lk)
            p0, st0, _ = cv2.calcOpticalFlowPyrLK(g, grays[k - 1], p1, None, **lk)
            ok = (st1.ravel() == 1) & (st0.ravel() == 1)
            ok &= np.linalg.norm(p0.reshape(-1, 2) - xy, axis=1) < 0.5
            p1 = p1.reshape(-1, 2)
            ok &= (p1[:, 0] >= 0) & (p1[:, 0] < w) & (p1[:, 1] >= 0) & (p1[:, 1] < h)
            ids, xy = ids[ok], p1[ok]
        if len(xy) < max_corners // 2:
            mask = np.full((h, w), 255, np.uint8)
            for x, y in xy:
                cv2.circle(mask, (int(x), int(y)), min_distance, 0, -1)
            new = cv2.goodFeaturesToTrack(g, max_corners - len(xy), 0.01, min_distance, mask=mask)
            if new is not None:
                new = new.reshape(-1, 2).astype(np.float32)
                ids = np.concatenate([ids, np.arange(next_id, next_id + len(new))])
                xy = np.concatenate([xy, new])
                next_id += len(new)
        out.append(dict(zip(ids.tolist(), xy.astype(np.float64))))
    return out


def _pair_matches(a: dict[int, np.ndarray], b: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    common = sorted(set(a) & set(b))
    if not common:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.array([a[i] for i in common]), np.array([b[i] for i in common])
