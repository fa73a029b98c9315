"""Loop verification: a known Sim(3) with outliers is recovered and accepted; noise is rejected."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slamkit.errors import ConfigError
from slamkit.loop_verification import (ConsistentGroup, LoopStatus, LoopVerificationConfig, project,
                                      refine_sim3, reprojection_inliers, update_consistent_groups, verify_loop,
                                      verify_loop_by_reprojection, verify_loop_candidate)
from slamkit.pose_graph import sim3_decompose, sim3_inverse, sim3_matrix

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


def _look(center: np.ndarray, yaw_deg: float) -> np.ndarray:
    """(4, 4) cam_from_world at ``center`` looking along +x rotated by ``yaw_deg`` about z (z up)."""
    th = np.radians(yaw_deg)
    forward = np.array([np.cos(th), np.sin(th), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    r = np.stack([np.cross(down, forward), down, forward])
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, -r @ center
    return m


def _two_views(n: int = 200, seed: int = 1):
    """Exact geometry of a loop: K, the candidate world's points (1-12 m before the candidate keyframe), the true
    Sim(3) ``candidate_world_from_query_world``, the points in the query world, both keyframes' rigid poses in
    their worlds and the points' pixels in each."""
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    rng = np.random.default_rng(seed)
    t_cand = _look(np.zeros(3), 0.0)
    depth = rng.uniform(1.0, 12.0, n)
    rays = np.stack([np.ones(n), rng.uniform(-0.5, 0.5, n), rng.uniform(-0.4, 0.4, n)], axis=1)
    world = rays / np.linalg.norm(rays, axis=1, keepdims=True) * depth[:, None]
    S = sim3_matrix(TRUE_SCALE, TRUE_R, TRUE_T)
    query_world = world @ sim3_inverse(S)[:3, :3].T + sim3_inverse(S)[:3, 3]
    t_query = _look(np.array([0.3, -0.2, 0.05]), 8.0) @ S  # cam_from_query_world, then made rigid again
    t_query[:3] /= TRUE_SCALE
    t_query[3] = [0, 0, 0, 1]
    xy_q, _ = project(K, t_query, query_world)
    xy_c, _ = project(K, t_cand, world)
    return K, world, S, query_world, t_query, t_cand, xy_q, xy_c, rays, depth


def test_sim3_refined_by_reprojection():
    """ORB-SLAM's OptimizeSim3 on exact geometry with 0.5 px noise and 15 % wrong matches: a Sim(3) off by 1 deg,
    5 cm and 3 % of scale (a 3D-3D estimate biased by far points' depth) comes back to the truth, and the wrong
    matches are left out."""
    K, world, S, query_world, t_query, t_cand, xy_q, xy_c, _, _ = _two_views(300)
    rng = np.random.default_rng(4)
    xy_q = xy_q + rng.normal(0, 0.5, xy_q.shape)
    xy_c = xy_c + rng.normal(0, 0.5, xy_c.shape)
    wrong = rng.random(len(world)) < 0.15
    world_m = world.copy()
    world_m[wrong] = world[rng.permutation(np.flatnonzero(wrong))]  # matched to another point
    err = sim3_matrix(1.03, Rotation.from_euler("z", 1.0, degrees=True).as_matrix(), [0.05, 0.0, -0.03])
    ones = np.ones(len(world))
    args = (K, query_world, t_query, xy_q, ones, world_m, t_cand, xy_c, ones)
    assert reprojection_inliers(err @ S, *args).mean() < 0.2  # the rough estimate reprojects badly
    refined, inl = refine_sim3(err @ S, *args)  # from all pairs (the wrong ones too), Huber
    s, r, t = sim3_decompose(refined)
    assert s == pytest.approx(TRUE_SCALE, rel=2e-3)
    assert np.degrees(Rotation.from_matrix(r @ TRUE_R.T).magnitude()) < 0.05
    np.testing.assert_allclose(t, TRUE_T, atol=5e-3)
    assert not (inl & wrong).any() and (inl[~wrong]).mean() > 0.95


def test_reprojection_tells_a_wrong_match_from_depth_error():
    """Exact geometry: the candidate keyframe sees a wall 1-12 m away; the query keyframe (drifted world: the
    true Sim(3)) sees the same points. A wrong match 5 cm from the true point (inside a 3D threshold of a few
    centimetres) is off by pixels, so reprojection rejects it; a right match whose far point has 30 cm of depth
    error (outside any such 3D threshold) stays on its ray, so reprojection keeps it."""
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    rng = np.random.default_rng(1)
    n = 200
    t_cand = _look(np.zeros(3), 0.0)
    depth = rng.uniform(1.0, 12.0, n)
    rays = np.stack([np.ones(n), rng.uniform(-0.5, 0.5, n), rng.uniform(-0.4, 0.4, n)], axis=1)
    world = rays / np.linalg.norm(rays, axis=1, keepdims=True) * depth[:, None]  # candidate (true) world
    S = sim3_matrix(TRUE_SCALE, TRUE_R, TRUE_T)  # candidate world from query world
    query_world = world @ sim3_inverse(S)[:3, :3].T + sim3_inverse(S)[:3, 3]
    t_query_true = _look(np.array([0.3, -0.2, 0.05]), 8.0)  # the query camera, in the candidate's world
    t_query = t_query_true @ S  # its pose in the drifted (query) world: cam_from_query_world
    t_query[:3, :3] /= TRUE_SCALE  # rigid again: the query world's unit is 1 / TRUE_SCALE of the candidate's
    t_query[:3, 3] /= TRUE_SCALE
    xy_q, z_q = project(K, t_query, query_world)
    xy_c, z_c = project(K, t_cand, world)
    assert (z_q > 0).all() and (z_c > 0).all()
    ones = np.ones(n)
    ok = reprojection_inliers(S, K, query_world, t_query, xy_q, ones, world, t_cand, xy_c, ones)
    assert ok.all()  # exact geometry: every right match reprojects

    wrong = world.copy()
    near = np.flatnonzero(depth < 3.0)[:20]  # wrong matches: a point 5 cm to the side of the true one
    side = np.cross(rays[near], [0, 0, 1])
    wrong[near] += side / np.linalg.norm(side, axis=1, keepdims=True) * 0.05
    far = np.flatnonzero(depth > 8.0)[:20]  # right matches with 30 cm of depth error along the candidate's ray
    wrong[far] *= (1 + 0.3 / depth[far])[:, None]
    dist = np.linalg.norm(wrong - world, axis=1)
    assert np.allclose(dist[near], 0.05) and np.allclose(dist[far], 0.3)
    ok = reprojection_inliers(S, K, query_world, t_query, xy_q, ones, wrong, t_cand, xy_c, ones)
    assert not ok[near].any()  # 5 cm at 1-3 m: 8-25 px in the query keyframe
    # a far point's depth error moves it along the candidate's ray: nothing there, and in the query keyframe
    # (30 cm off the axis 8-12 m away, seen from 30 cm aside) a pixel or less
    assert ok[far].mean() > 0.8
    assert ok[np.setdiff1d(np.arange(n), np.r_[near, far])].all()
    # pixel noise at the keypoint scale: the bound grows with the scale
    noisy = xy_q + [4.0, 0.0]
    assert not reprojection_inliers(S, K, query_world, t_query, noisy, ones, world, t_cand, xy_c, ones).any()
    assert reprojection_inliers(S, K, query_world, t_query, noisy, 1.2 ** 3 * ones, world, t_cand, xy_c, ones).all()


def test_ransac_by_reprojection_accepts_the_loop_a_3d_test_refuses():
    """ORB-SLAM's Sim3Solver on exact geometry: the candidate's points carry depth error along their rays (5 %
    of the depth, as far points triangulated over a short baseline do), the query's pixels 0.5 px of noise and
    20 % of the matches are wrong. RANSAC on 3D distances keeps too few of the right matches to accept the loop
    (the city block's right loop, refused for 130 keyframes); RANSAC on reprojection in both keyframes accepts
    it, recovers the Sim(3) and flags every wrong match."""
    n = 400
    K, world, S, query_world, t_query, t_cand, xy_q, xy_c, rays, depth = _two_views(n, seed=3)
    rng = np.random.default_rng(5)
    cand = world * (1 + 0.05 * rng.standard_normal(n))[:, None]  # along the candidate's rays: its pixels stay
    xy_q = xy_q + rng.normal(0, 0.5, xy_q.shape)
    wrong = rng.random(n) < 0.2
    cand[wrong] = cand[rng.permutation(np.flatnonzero(wrong))]
    xy_c = xy_c.copy()
    xy_c[wrong] = project(K, t_cand, cand[wrong])[0]  # a wrong match is observed where its point projects
    config = LoopVerificationConfig(max_trials=500)
    assert not verify_loop(query_world, cand, config).accepted
    ones = np.ones(n)
    v = verify_loop_by_reprojection(K, query_world, t_query, xy_q, ones, cand, t_cand, xy_c, ones, config)
    assert v.accepted, v.reason
    s, r, t = sim3_decompose(v.tgt_from_src)
    assert s == pytest.approx(TRUE_SCALE, rel=0.01)
    assert np.degrees(Rotation.from_matrix(r @ TRUE_R.T).magnitude()) < 0.2
    assert not (v.inlier_mask & wrong).any() and v.inlier_mask[~wrong].mean() > 0.8  # measured 0.87


def test_ransac_by_reprojection_rejects_unrelated_points():
    """Matches with no common Sim(3) (every pair wrong) give no loop."""
    n = 200
    K, world, S, query_world, t_query, t_cand, xy_q, xy_c, _, _ = _two_views(n, seed=6)
    perm = np.random.default_rng(7).permutation(n)
    ones = np.ones(n)
    v = verify_loop_by_reprojection(K, query_world, t_query, xy_q, ones, world[perm], t_cand, xy_c[perm], ones,
                                    LoopVerificationConfig(max_trials=500))
    assert not v.accepted and v.num_inliers < 20
