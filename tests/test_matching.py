"""Guided matching (SearchByProjection) against a brute-force reference, including keypoints and
projections outside the image (undistorted keypoints can be negative)."""

import numpy as np
import pytest

from slamkit.features import MatchingConfig, guided_match
from slamkit.features.base import descriptor_distance


def brute_force_guided_match(proj, point_desc, keypoints, kp_desc, radius, cfg, kp_taken):
    """Every (point, keypoint) pair within the radius, then the same ratio test and one-to-one rule."""
    d2 = ((proj[:, None] - keypoints[None]) ** 2).sum(-1)
    pt, kp = np.nonzero(d2 <= radius * radius)
    keep = ~kp_taken[kp]
    pt, kp = pt[keep], kp[keep]
    dist = descriptor_distance(point_desc[pt], kp_desc[kp], True)
    keep = dist <= cfg.max_hamming
    pt, kp, dist = pt[keep], kp[keep], dist[keep]
    best = {}
    for p in np.unique(pt):
        m = np.flatnonzero(pt == p)
        o = m[np.lexsort((kp[m], dist[m]))]
        if len(o) == 1 or dist[o[0]] < cfg.ratio * dist[o[1]]:
            best[int(p)] = (int(kp[o[0]]), float(dist[o[0]]))
    per_kp = {}
    for p, (k, d) in sorted(best.items()):
        if k not in per_kp or d < per_kp[k][1]:
            per_kp[k] = (p, d)
    return {(p, k) for k, (p, _) in per_kp.items()}


@pytest.mark.parametrize("seed", range(6))
def test_guided_match_equals_brute_force(seed):
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(50, 1500)), int(rng.integers(50, 1500))
    radius = float(rng.choice([3.0, 6.0, 20.0]))
    keypoints = rng.uniform([-10, -10], [650, 490], (n, 2))
    kp_desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    proj = rng.uniform([-60, -60], [700, 540], (m, 2))
    point_desc = rng.integers(0, 256, (m, 32), dtype=np.uint8)
    k = min(n, m) // 2  # half the points are true keypoints, seen again within ~2 px
    point_desc[:k] = kp_desc[:k]
    proj[:k] = keypoints[:k] + rng.normal(0, 2, (k, 2))
    taken = rng.random(n) < 0.1
    cfg = MatchingConfig()
    pairs = guided_match(proj, point_desc, keypoints, kp_desc, True, radius, cfg, kp_taken=taken)
    assert len(set(pairs[:, 1].tolist())) == len(pairs)  # one map point per keypoint
    assert {tuple(p) for p in pairs.tolist()} == brute_force_guided_match(
        proj, point_desc, keypoints, kp_desc, radius, cfg, taken)
