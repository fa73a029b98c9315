"""Absolute pose refinement, compiled: COLMAP's ``RefineAbsolutePose`` problem on plain arrays.

COLMAP refines a camera pose on its 2D-3D inliers with the points held constant: the cost is

    cost = 1/2 sum_i rho(|pi(R X_i + t) - x_i|^2),   rho = Cauchy at scale a (a^2 log(1 + s/a^2)), a = 1 px,

over the inliers, the rotation on Ceres' quaternion manifold, Levenberg-Marquardt with Ceres' default
tolerances (function 1e-6, parameter 1e-8) and COLMAP's ``gradient_tolerance`` (1.0) and iteration cap (the
tracker's 20). ``pycolmap.refine_absolute_pose`` builds a Ceres problem per call, about 6 ms per frame-round on
7-Scenes, a sixth of a run's time in tracking (issue 48's profile). Here the same problem is one call of the
local BA kernel (:mod:`slamkit.kernels.local_ba`, one variable pose and every point fixed: its Schur complement
is then the 6x6 normal equations), which reaches the same optimum (``tests/test_absolute_pose_kernel.py``:
against pycolmap on rendered problems with noise and outliers) in a few hundred microseconds, without the GIL.

A point behind the camera adds a zero residual, as COLMAP 4's reprojection cost. Imports no pycolmap.
"""

from __future__ import annotations

import numpy as np

from .local_ba import local_bundle_adjustment

COLMAP_LOSS_SCALE = 1.0
"""``AbsolutePoseRefinementOptions.loss_function_scale``: the Cauchy loss's scale, pixels."""
COLMAP_GRADIENT_TOLERANCE = 1.0
"""``AbsolutePoseRefinementOptions.gradient_tolerance``."""
CERES_FUNCTION_TOLERANCE, CERES_PARAMETER_TOLERANCE = 1e-6, 1e-8
"""Ceres' default tolerances, which COLMAP's pose refinement keeps."""
_EPS = float(np.finfo(np.float64).eps)
"""COLMAP's reprojection cost is 0 for a point at depth below this."""


def refine_absolute_pose(cam_from_world: np.ndarray, xy: np.ndarray, xyz: np.ndarray, inlier_mask: np.ndarray,
                         camera, max_iterations: int = 20, loss_scale: float = COLMAP_LOSS_SCALE,
                         gradient_tolerance: float = COLMAP_GRADIENT_TOLERANCE) -> np.ndarray | None:
    """``cam_from_world`` ((4, 4) or (3, 4)) refined on the inliers (``inlier_mask``, (N,) bool) of the
    correspondences ``xy`` ((N, 2) undistorted pixels) <-> ``xyz`` ((N, 3) world points, held), through the
    pinhole ``camera`` (fx, fy, cx, cy); COLMAP's problem (see the module docstring). Returns the (4, 4) pose, or
    None where COLMAP's refinement reports no usable solution (no inlier, a non-finite input). The rotation must
    be one (orthonormal to rounding): the solver turns it on the left and keeps what is not (pycolmap's own
    refinement starts from the unit quaternion of the matrix it is given)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    mask = np.asarray(inlier_mask, bool).reshape(-1)
    if not (len(xy) == len(xyz) == len(mask)):
        raise ValueError(f"xy, xyz and inlier_mask must have one row per correspondence, got {len(xy)}, "
                         f"{len(xyz)}, {len(mask)}")
    n = int(mask.sum())
    if n == 0:
        return None
    T = np.asarray(cam_from_world, np.float64)[None]
    res = local_bundle_adjustment(T, xyz[mask], np.zeros(n, np.int64), np.arange(n, dtype=np.int64), xy[mask],
                                  camera, point_fixed=np.ones(n, bool), loss="cauchy", loss_scale=loss_scale,
                                  max_iterations=max_iterations, function_tolerance=CERES_FUNCTION_TOLERANCE,
                                  parameter_tolerance=CERES_PARAMETER_TOLERANCE,
                                  gradient_tolerance=gradient_tolerance, min_depth=_EPS, behind_camera="zero")
    if not res.success or not np.isfinite(res.cam_from_world).all():
        return None
    return res.cam_from_world[0]
