"""The compiled absolute pose refinement (:mod:`slamkit.kernels.absolute_pose`) against exact geometry and against
``pycolmap.refine_absolute_pose`` (Ceres) on the same problem.

Each problem: a camera looking at 40-800 known points 2-8 m away, pixels at the exact projection plus Gaussian
noise (1 px), 15 % of the correspondences planted outliers (10-40 px off), a tenth of them left out by the
inlier mask, the start 0.6 degree / 3 cm off the true pose. Both solvers minimize COLMAP's cost (Cauchy at 1 px
over the inliers, points held) by Ceres' Levenberg-Marquardt, so they must land on one pose, near the truth."""

from __future__ import annotations

import math

import numpy as np
import pycolmap
import pytest

from slamkit.kernels.absolute_pose import refine_absolute_pose
from slamkit.map import matrix_from_rigid, rigid_from_matrix
from slamkit.stages.tracker import Tracker, TrackerConfig

CAM = (525.0, 520.0, 320.0, 240.0)


def _rotation(rotvec) -> np.ndarray:
    angle = float(np.linalg.norm(rotvec))
    if angle == 0:
        return np.eye(3)
    a = np.asarray(rotvec, float) / angle
    W = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * W + (1 - math.cos(angle)) * W @ W


def _angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(R) - 1) / 2))))


def problem(seed: int, n: int | None = None):
    """(truth (4, 4), start (4, 4), xy (N, 2), xyz (N, 3), inlier mask (N,), planted outliers (N,))."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(40, 800)) if n is None else n
    fx, fy, cx, cy = CAM
    xyz = rng.uniform([-3, -2, 2], [3, 2, 8], (n, 3))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _rotation(rng.normal(0, 0.1, 3)), rng.normal(0, 0.3, 3)
    Pc = xyz @ T[:3, :3].T + T[:3, 3]
    xy = np.c_[fx * Pc[:, 0] / Pc[:, 2] + cx, fy * Pc[:, 1] / Pc[:, 2] + cy] + rng.normal(0, 1.0, (n, 2))
    out = rng.random(n) < 0.15
    d = rng.normal(size=(out.sum(), 2))
    xy[out] += d / np.linalg.norm(d, axis=1)[:, None] * rng.uniform(10, 40, out.sum())[:, None]
    T0 = T.copy()
    T0[:3, :3] = _rotation(rng.normal(0, 0.006, 3)) @ T[:3, :3]
    T0[:3, 3] += rng.normal(0, 0.03, 3)
    return T, T0, xy, xyz, rng.random(n) < 0.9, out


def _colmap(T0, xy, xyz, inl, iterations=20):
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=list(CAM))
    opt = pycolmap.AbsolutePoseRefinementOptions()
    opt.refine_focal_length, opt.refine_extra_params, opt.max_num_iterations = False, False, iterations
    ref = pycolmap.refine_absolute_pose(rigid_from_matrix(T0), xy, xyz, inl, cam, opt)
    return None if ref is None else matrix_from_rigid(ref["cam_from_world"])


def _cost(T, xy, xyz) -> float:
    """COLMAP's cost, evaluated here: 1/2 sum log(1 + |error|^2) (Cauchy at 1 px)."""
    fx, fy, cx, cy = CAM
    P = xyz @ T[:3, :3].T + T[:3, 3]
    err = np.c_[fx * P[:, 0] / P[:, 2] + cx, fy * P[:, 1] / P[:, 2] + cy] - xy
    return 0.5 * float(np.log1p((err ** 2).sum(axis=1)).sum())


def _centre(T):
    return -T[:3, :3].T @ T[:3, 3]


@pytest.mark.parametrize("seed", range(12))
def test_reaches_colmaps_optimum_near_the_truth(seed):
    T, T0, xy, xyz, inl, _ = problem(seed)
    ours, theirs = refine_absolute_pose(T0, xy, xyz, inl, CAM), _colmap(T0, xy, xyz, inl)
    assert ours is not None and theirs is not None
    # Ceres' path step for step: the same damping, acceptance and stopping rules (a step that changes the cost by
    # less than 1e-6 of it is not taken) give the same pose to rounding (measured: 2e-16 to 1.1e-15 m)
    assert np.linalg.norm(_centre(ours) - _centre(theirs)) < 1e-9
    assert np.abs(ours[:3, :3] - theirs[:3, :3]).max() < 1e-9  # (acos cannot resolve angles below ~1e-6 deg)
    assert abs(_cost(ours, xy[inl], xyz[inl]) / _cost(theirs, xy[inl], xyz[inl]) - 1) < 1e-12
    # and it is the truth's neighbourhood: 1 px noise over 2-8 m gives millimetres (the start is 3 cm off)
    assert np.linalg.norm(_centre(ours) - _centre(T)) < 0.006
    assert _angle_deg(ours[:3, :3] @ T[:3, :3].T) < 0.1


def test_the_inlier_mask_is_honoured():
    """Refining on the planted outliers alone moves the pose far from the truth; on the clean ones it does not."""
    T, T0, xy, xyz, _, out = problem(3, 400)
    clean = refine_absolute_pose(T0, xy, xyz, ~out, CAM)
    assert np.linalg.norm(_centre(clean) - _centre(T)) < 0.01
    dirty = refine_absolute_pose(T0, xy, xyz, out, CAM)
    assert np.linalg.norm(_centre(dirty) - _centre(T)) > 3 * np.linalg.norm(_centre(clean) - _centre(T))


def test_points_behind_the_camera_add_nothing_as_in_colmap():
    T, T0, xy, xyz, inl, _ = problem(5, 300)
    behind = np.r_[xyz, [[0.0, 0.0, -4.0]] * 20]  # behind the camera: COLMAP's cost is 0 for them
    xy2 = np.r_[xy, np.full((20, 2), 300.0)]
    inl2 = np.r_[inl, np.ones(20, bool)]
    ours, theirs = refine_absolute_pose(T0, xy2, behind, inl2, CAM), _colmap(T0, xy2, behind, inl2)
    assert np.linalg.norm(_centre(ours) - _centre(theirs)) < 1e-4
    assert np.allclose(ours, refine_absolute_pose(T0, xy, xyz, inl, CAM), atol=1e-6)


def test_nothing_to_refine_is_none_and_bad_shapes_raise():
    T, T0, xy, xyz, inl, _ = problem(1, 50)
    assert refine_absolute_pose(T0, xy, xyz, np.zeros(50, bool), CAM) is None
    nan_start = T0.copy()
    nan_start[0, 3] = np.nan
    assert refine_absolute_pose(nan_start, xy, xyz, inl, CAM) is None
    with pytest.raises(ValueError, match="one row per correspondence"):
        refine_absolute_pose(T0, xy[:-1], xyz, inl, CAM)


def test_the_tracker_refines_with_either_solver_alike():
    """``tracker.pose_optimizer`` "compiled" and "ceres" give the tracker one refined pose (a pinhole camera)."""
    T, T0, xy, xyz, inl, _ = problem(7, 500)
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=list(CAM))
    poses = [Tracker(TrackerConfig(pose_optimizer=p))._refine_colmap(T0, xy, xyz, inl, cam)
             for p in ("compiled", "ceres")]
    assert np.linalg.norm(_centre(poses[0]) - _centre(poses[1])) < 1e-4
    radial = pycolmap.Camera(model="SIMPLE_RADIAL", width=640, height=480, params=[525.0, 320.0, 240.0, 0.0])
    kept = Tracker(TrackerConfig(pose_optimizer="compiled"))._refine_colmap(T0, xy, xyz, inl, radial)
    assert kept is not None  # a camera with distortion goes to pycolmap's refinement
