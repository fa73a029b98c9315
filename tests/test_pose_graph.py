"""Sim(3) pose-graph correction on exact geometry: a loop of keyframes with injected drift."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from slamkit.errors import ConfigError
from slamkit.pose_graph import (PoseGraphConfig, PoseGraphEdge, correct_points, loop_edge, optimize_pose_graph,
                                propagate_to_frames, relative_edges, sim3_decompose, sim3_from_pycolmap, sim3_inverse,
                                sim3_matrix)

N = 36


@pytest.fixture(params=["scipy", "gtsam"])
def config(request) -> PoseGraphConfig:
    """Both backends; gtsam (optional extra ``loop``) is skipped where it is not installed."""
    if request.param == "gtsam":
        pytest.importorskip("gtsam", reason="gtsam (optional extra 'loop') is not installed")
    return PoseGraphConfig(backend=request.param)


def _centre(cam_from_world: np.ndarray) -> np.ndarray:
    return -cam_from_world[:3, :3].T @ cam_from_world[:3, 3]


def _circle(n: int = N, radius: float = 2.0) -> dict[int, np.ndarray]:
    """Ground-truth cam_from_world of n keyframes on a circle (z up), each looking outwards, slightly tilted."""
    poses = {}
    for i in range(n):
        a = 2 * np.pi * i / n
        c = np.array([radius * np.cos(a), radius * np.sin(a), 1.5 + 0.1 * np.sin(3 * a)])
        z = np.array([np.cos(a), np.sin(a), -0.1])
        z /= np.linalg.norm(z)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        r_wc = np.stack([x, np.cross(z, x), z], axis=1)
        t = np.eye(4)
        t[:3, :3], t[:3, 3] = r_wc.T, -r_wc.T @ c
        poses[i] = t
    return poses


def _drifted(gt: dict[int, np.ndarray], rot_deg: float = 0.4, scale_step: float = 1.015,
             trans: float = 0.004) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """Chain the true relative motions with a growing error as visual odometry does: a small rotation and a
    translation bias per step, and a map scale multiplied by ``scale_step`` per step. Returns the rigid
    drifted cam_from_world and the (n,) local map scale (estimate / truth) at each keyframe."""
    est = {0: gt[0].copy()}
    scales = np.ones(len(gt))
    err = Rotation.from_euler("xyz", [rot_deg, -0.5 * rot_deg, 0.7 * rot_deg], degrees=True).as_matrix()
    for i in range(1, len(gt)):
        rel = gt[i] @ np.linalg.inv(gt[i - 1])
        scales[i] = scales[i - 1] * scale_step
        step = np.eye(4)
        step[:3, :3] = err @ rel[:3, :3]
        step[:3, 3] = scales[i] * rel[:3, 3] + trans * np.array([1.0, -0.5, 0.3])
        est[i] = step @ est[i - 1]
    return est, scales


def _errors(poses: dict[int, np.ndarray], gt: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(n,) camera-centre errors (metres) and (n,) rotation errors (degrees)."""
    pos = np.array([np.linalg.norm(_centre(poses[k]) - _centre(gt[k])) for k in gt])
    rot = np.array([np.degrees(Rotation.from_matrix(poses[k][:3, :3] @ gt[k][:3, :3].T).magnitude()) for k in gt])
    return pos, rot


def _sim_truth(gt: dict[int, np.ndarray], scales: np.ndarray) -> dict[int, np.ndarray]:
    """True S_iw of each keyframe at the scale of its (drifted) local map."""
    return {k: sim3_matrix(scales[k], np.eye(3), np.zeros(3)) @ gt[k] for k in gt}


def _odometry_graph(est: dict[int, np.ndarray]) -> list[PoseGraphEdge]:
    """Spanning tree (i-1, i) and covisibility (i-2, i) edges from the drifted poses, scale 1."""
    pairs = [(i, i - 1) for i in range(1, N)] + [(i, i - 2) for i in range(2, N)]
    return relative_edges(est, pairs)


def test_loop_with_drift_is_corrected(config):
    """Odometry drifts (0.2 degree, 0.5 % scale and 2 mm per keyframe, growing along the loop); one loop edge
    carries the true Sim(3) between the last and the first keyframe. The pose graph cannot know where along
    the loop the drift happened, so it spreads the loop error over the edges: the trajectory becomes
    consistent (errors several times smaller, the loop keyframe at its true place and scale) without being
    exact. Exact recovery with consistent edges is the next test."""
    gt = _circle()
    est, scales = _drifted(gt, rot_deg=0.2, scale_step=1.005, trans=0.002)
    # the Sim(3) loop verification finds: points of the last keyframe's map -> the first keyframe's map
    q = N - 1
    tgt_from_src = np.linalg.inv(gt[q]) @ sim3_matrix(1.0 / scales[q], np.eye(3), np.zeros(3)) @ est[q]
    edges = _odometry_graph(est) + [loop_edge(q, 0, est[q], est[0], tgt_from_src)]
    result = optimize_pose_graph(est, edges, fixed=0, config=config)
    assert result.success and result.final_cost < 0.05 * result.initial_cost
    pos_before, rot_before = _errors(est, gt)
    pos_after, rot_after = _errors(result.cam_from_world, gt)
    assert pos_before.max() > 0.4 and rot_before.max() > 3  # metres, degrees: a large drift before
    assert pos_after.max() < 0.25 * pos_before.max()
    assert np.sqrt(np.mean(pos_after ** 2)) < 0.25 * np.sqrt(np.mean(pos_before ** 2))
    assert rot_after.max() < 0.7 * rot_before.max()
    # the loop keyframe lands at its true place and local scale
    assert pos_after[q] < 0.1 * pos_before[q]
    assert result.scales[q] == pytest.approx(scales[q], rel=0.02) and result.scales[0] == 1.0


def test_consistent_sim3_graph_recovers_truth_exactly(config):
    """Edges that are the true relative Sim(3)s (scales included) from drifted initial poses: the optimum
    is the truth up to solver precision."""
    gt = _circle()
    est, scales = _drifted(gt, rot_deg=1.0, scale_step=1.02, trans=0.01)
    truth = _sim_truth(gt, scales)
    pairs = [(i, i - 1) for i in range(1, N)] + [(N - 1, 0), (N // 2, 0)]
    edges = [PoseGraphEdge(i, j, truth[i] @ sim3_inverse(truth[j])) for i, j in pairs]
    result = optimize_pose_graph(est, edges, fixed=[0], config=config)
    for k in range(N):
        np.testing.assert_allclose(result.sim_from_world[k], truth[k], atol=1e-6)
        assert result.scales[k] == pytest.approx(scales[k], rel=1e-7)


def test_known_scale_recovered_on_two_keyframes(config):
    """One loop edge with scale 2.5 between a fixed and a free keyframe: the free one gets scale 2.5."""
    q_xyzw = np.array([0.1, -0.2, 0.3, 0.927])
    sim = pycolmap.Sim3d(2.5, pycolmap.Rotation3d(q_xyzw / np.linalg.norm(q_xyzw)), np.array([0.3, -1.0, 2.0]))
    m = sim3_from_pycolmap(sim)
    result = optimize_pose_graph({0: np.eye(4), 1: np.eye(4)}, [PoseGraphEdge(1, 0, m, kind="loop")], fixed=0,
                                 config=config)
    assert result.scales[1] == pytest.approx(2.5, rel=1e-8)
    np.testing.assert_allclose(result.sim_from_world[1], m, atol=1e-8)
    s, r, t = sim3_decompose(result.sim_from_world[1])
    np.testing.assert_allclose(r, sim.rotation.matrix(), atol=1e-8)
    np.testing.assert_allclose(result.cam_from_world[1][:3, 3], t / 2.5, atol=1e-8)
    np.testing.assert_array_equal(result.cam_from_world[0], np.eye(4))


def test_frames_and_points_follow_their_keyframe(config):
    gt = _circle()
    est, scales = _drifted(gt)
    truth = _sim_truth(gt, scales)
    edges = [PoseGraphEdge(i, j, truth[i] @ sim3_inverse(truth[j])) for i, j in [(i, i - 1) for i in range(1, N)]]
    result = optimize_pose_graph(est, edges, fixed=0, config=config)
    # a non-keyframe between keyframes 20 and 21, and points seen by keyframe 20, in the drifted map
    k = 20
    rel_true = Rotation.from_rotvec([0.0, 0.05, 0.0]).as_matrix()
    frame_true = sim3_matrix(1.0, rel_true, [0.05, 0.0, 0.0]) @ gt[k]
    frame_est = sim3_matrix(1.0, rel_true, [0.05 * scales[k], 0.0, 0.0]) @ est[k]
    fixed = propagate_to_frames({500: frame_est, 501: est[3]}, {500: k}, est, result)
    assert set(fixed) == {500}
    np.testing.assert_allclose(fixed[500], frame_true, atol=1e-6)
    pts_true = np.random.default_rng(0).uniform(-1, 1, (20, 3)) + _centre(gt[k])
    cam = pts_true @ gt[k][:3, :3].T + gt[k][:3, 3]
    pts_est = (scales[k] * cam - est[k][:3, 3]) @ est[k][:3, :3]  # the drifted map: the same camera view, scaled
    moved = correct_points(pts_est, np.full(20, k), est, result)
    np.testing.assert_allclose(moved, pts_true, atol=1e-6)


def test_bad_graphs_are_config_errors():
    poses = {0: np.eye(4), 1: np.eye(4), 2: np.eye(4)}
    edge = PoseGraphEdge(1, 0, np.eye(4))
    with pytest.raises(ConfigError, match="not connected"):
        optimize_pose_graph(poses, [edge], fixed=0)
    with pytest.raises(ConfigError, match="fixed: keyframe 7"):
        optimize_pose_graph(poses, [edge], fixed=7)
    with pytest.raises(ConfigError, match="keyframe 9 has no pose"):
        optimize_pose_graph(poses, [edge, PoseGraphEdge(2, 9, np.eye(4))], fixed=0)
    with pytest.raises(ConfigError, match="no edge"):
        optimize_pose_graph(poses, [], fixed=0)
    with pytest.raises(ConfigError, match="pose"):
        relative_edges({0: np.eye(4), 1: np.zeros((2, 2))}, [(0, 1)])
    with pytest.raises(ConfigError, match="backend"):
        PoseGraphConfig(backend="g2o")
