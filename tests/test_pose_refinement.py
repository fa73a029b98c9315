"""Motion-only bundle adjustment (slamkit.pose_refinement) against pycolmap.refine_absolute_pose (Ceres) on
the same correspondences: the same minimum of the same robust cost, from a perturbed start, with outliers."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from slamkit.geometry import rotation_angle_deg
from slamkit.map import matrix_from_rigid, rigid_from_matrix
from slamkit.pose_refinement import _cost, refine_pose

K = np.array([[525.0, 0, 320], [0, 525, 240], [0, 0, 1]])


def _rotvec(w: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(w)
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / max(theta, 1e-300)
    return np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * k @ k


def _problem(seed: int, n: int = 800, outliers: float = 0.15):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, (n, 3)) + [0, 0, 5]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _rotvec(rng.normal(0, 0.2, 3)), rng.normal(0, 0.3, 3)
    Xc = X @ T[:3, :3].T + T[:3, 3]
    uv = Xc[:, :2] / Xc[:, 2:] * 525 + [320, 240] + rng.normal(0, 1, (n, 2))
    bad = rng.random(n) < outliers
    uv[bad] += rng.normal(0, 40, (bad.sum(), 2))
    start = T.copy()
    start[:3, :3] = _rotvec(rng.normal(0, 0.02, 3)) @ start[:3, :3]
    start[:3, 3] += rng.normal(0, 0.05, 3)
    return T, start, uv, X, rng.random(n) < 0.9


def _robust_cost(T, uv, X, mask):
    return _cost(T[:3, :3].copy(), T[:3, 3].copy(), uv[mask], X[mask], 525.0, 525.0, 320.0, 240.0, 1.0)


@pytest.mark.parametrize("seed", range(5))
def test_same_minimum_as_pycolmap(seed):
    T, start, uv, X, mask = _problem(seed)
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[525, 525, 320, 240])
    opts = pycolmap.AbsolutePoseRefinementOptions()
    opts.max_num_iterations, opts.gradient_tolerance = 100, 1e-10
    ref = matrix_from_rigid(pycolmap.refine_absolute_pose(rigid_from_matrix(start), uv, X, mask, cam, opts)
                            ["cam_from_world"])
    got = refine_pose(start, uv, X, K, mask)
    # Ceres stops a little short of the minimum (function tolerance 1e-6): the same pose to a thousandth of a
    # degree and a tenth of a millimetre, at a cost no higher than Ceres'
    assert rotation_angle_deg(got[:3, :3] @ ref[:3, :3].T) < 1e-3
    assert np.linalg.norm(got[:3, 3] - ref[:3, 3]) < 1e-4
    assert _robust_cost(got, uv, X, mask) <= _robust_cost(ref, uv, X, mask) * (1 + 1e-12)
    # and near the truth: 1 px noise on 700 inliers
    assert rotation_angle_deg(got[:3, :3] @ T[:3, :3].T) < 0.05 and np.linalg.norm(got[:3, 3] - T[:3, 3]) < 0.01
    assert np.allclose(got[:3, :3] @ got[:3, :3].T, np.eye(3), atol=1e-12)


def test_the_robust_loss_resists_outliers_a_least_squares_fit_would_follow():
    T, start, uv, X, mask = _problem(7, outliers=0.3)
    got = refine_pose(start, uv, X, K)
    assert np.linalg.norm(got[:3, 3] - T[:3, 3]) < 0.01
    assert _robust_cost(got, uv, X, np.ones(len(uv), bool)) < _robust_cost(start, uv, X, np.ones(len(uv), bool))


def test_too_few_points_and_points_behind_the_camera():
    T, start, uv, X, mask = _problem(3, n=50, outliers=0)
    assert refine_pose(start, uv[:2], X[:2], K) is None
    assert refine_pose(start, uv, X, K, np.zeros(50, bool)) is None
    X_behind = X.copy()
    X_behind[:5, 2] = -5  # behind the camera: bounded cost, no pull
    got = refine_pose(start, uv, X_behind, K)
    assert np.isfinite(got).all() and np.linalg.norm(got[:3, 3] - T[:3, 3]) < 0.02
