"""Loop verification: a known Sim(3) with outliers is recovered and accepted; noise is rejected."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slamkit.errors import ConfigError
from slamkit.loop_verification import (ConsistentGroup, LoopStatus, LoopVerificationConfig, update_consistent_groups,
                                      verify_loop, verify_loop_candidate)
from slamkit.pose_graph import sim3_decompose, sim3_matrix

TRUE_SCALE = 0.62
TRUE_R = Rotation.from_euler("zyx", [35, -10, 5], degrees=True).as_matrix()
TRUE_T = np.array([1.5, -0.4, 0.8])


def _cloud(n: int = 400, outliers: float = 0.2, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Query points (a room-sized cloud, metres), their images under the true Sim(3) with 1 mm noise, and
    a mask of the rows replaced by gross outliers (random points of the same cloud)."""
    rng = np.random.default_rng(seed)
    src = rng.uniform([-3, -2, 0], [3, 2, 2.5], (n, 3))
    tgt = TRUE_SCALE * src @ TRUE_R.T + TRUE_T + rng.normal(0, 0.001, (n, 3))
    bad = rng.random(n) < outliers
    tgt[bad] = TRUE_SCALE * rng.uniform([-3, -2, 0], [3, 2, 2.5], (int(bad.sum()), 3)) @ TRUE_R.T + TRUE_T
    return src, tgt, bad


def test_known_sim3_with_outliers_is_recovered_and_accepted():
    src, tgt, bad = _cloud()
    assert 0.15 < bad.mean() < 0.25
    v = verify_loop(src, tgt)
    assert v.accepted and v.status is LoopStatus.ACCEPTED, v.reason
    s, r, t = sim3_decompose(v.tgt_from_src)
    assert s == pytest.approx(TRUE_SCALE, rel=1e-3)
    assert np.degrees(Rotation.from_matrix(r @ TRUE_R.T).magnitude()) < 0.1
    np.testing.assert_allclose(t, TRUE_T, atol=5e-3)
    # the inliers are the rows that were not replaced (an outlier can fall near its true place by chance)
    assert (v.inlier_mask & ~bad).sum() == (~bad).sum()
    assert (v.inlier_mask & bad).sum() <= 2
    assert v.inlier_ratio == pytest.approx(v.num_inliers / len(src))


def test_pure_noise_is_rejected():
    rng = np.random.default_rng(1)
    src = rng.uniform(-3, 3, (300, 3))
    tgt = rng.uniform(-3, 3, (300, 3))
    v = verify_loop(src, tgt)
    assert not v.accepted
    assert v.status in (LoopStatus.TOO_FEW_INLIERS, LoopStatus.LOW_INLIER_RATIO, LoopStatus.NO_MODEL)
    assert "inliers" in v.reason


def test_thresholds_give_their_status():
    src, tgt, _ = _cloud(n=15)
    assert verify_loop(src, tgt).status is LoopStatus.TOO_FEW_MATCHES
    src, tgt, bad = _cloud(n=200, outliers=0.75, seed=2)
    v = verify_loop(src, tgt, LoopVerificationConfig(min_inliers=20, min_inlier_ratio=0.5))
    assert v.status is LoopStatus.LOW_INLIER_RATIO and v.num_inliers >= 20
    shrunk = 0.1 * np.asarray(src)
    v = verify_loop(src, shrunk, LoopVerificationConfig(max_error=0.01))
    assert v.status is LoopStatus.IMPLAUSIBLE_SCALE and v.scale == pytest.approx(0.1, rel=1e-6)


def test_candidate_points_matched_by_descriptor():
    """Binary descriptors per map point; the candidate holds the same points (shuffled, a few bits flipped)
    under the Sim(3) plus unrelated points: matching then RANSAC finds the Sim(3)."""
    rng = np.random.default_rng(3)
    src, tgt, _ = _cloud(n=300, outliers=0.0, seed=3)
    desc = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    flips = np.packbits(rng.random((300, 256)) < 0.03, axis=1)
    order = rng.permutation(300)
    cand_points = np.vstack([tgt[order], rng.uniform(-3, 3, (200, 3))])
    cand_desc = np.vstack([(desc ^ flips)[order], rng.integers(0, 256, (200, 32), dtype=np.uint8)])
    v, pairs = verify_loop_candidate(src, desc, cand_points, cand_desc, binary=True)
    assert v.accepted, v.reason
    assert len(pairs) > 250 and np.all(order[pairs[:, 1]] == pairs[:, 0])
    np.testing.assert_allclose(v.tgt_from_src, sim3_matrix(TRUE_SCALE, TRUE_R, TRUE_T), atol=5e-3)


def test_bad_input_is_a_config_error():
    with pytest.raises(ConfigError, match="query_points"):
        verify_loop(np.zeros((5, 2)), np.zeros((5, 3)))
    with pytest.raises(ConfigError, match="pair row by row"):
        verify_loop(np.zeros((5, 3)), np.zeros((6, 3)))
    with pytest.raises(ConfigError, match="min_inlier_ratio"):
        LoopVerificationConfig(min_inlier_ratio=2)


def test_candidates_must_be_consistent_over_successive_keyframes():
    """A place recognised by four successive query keyframes (candidates 10, 11, 12, 13 whose covisible
    groups overlap) passes at the fourth; a one-off candidate (50) and an interrupted chain do not."""
    covisible = {k: {k - 1, k + 1} for k in range(100)}
    groups: tuple[ConsistentGroup, ...] = ()
    passed = []
    for step, candidates in enumerate([[10, 50], [11], [12, 80], [13]]):
        groups, enough = update_consistent_groups(groups, {c: covisible[c] for c in candidates})
        passed.append(enough)
    assert passed == [[], [], [], [13]]
    assert max(g.consistency for g in groups) == 3
    groups = ()
    for candidates in ([10], [11], [], [12], [13]):  # a query keyframe without candidates breaks the chain
        groups, enough = update_consistent_groups(groups, {c: covisible[c] for c in candidates})
        assert enough == []
    with pytest.raises(ConfigError, match="min_consistency"):
        update_consistent_groups((), {}, min_consistency=-1)
