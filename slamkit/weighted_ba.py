"""Bundle adjustment weighted by each keypoint's pyramid level (ORB-SLAM's ``Optimizer::LocalBundleAdjustment``).

pycolmap's ``BundleAdjustmentConfig`` gives every observation the same weight. ORB-SLAM gives each one the
information 1/sigma^2 of its keypoint's level (sigma = 1.2^octave pixels: :func:`~slamkit.map.keypoint_scales`)
and a Huber loss at sqrt(5.991) on the whitened error, so a coarse-level keypoint pulls as hard as its
noise allows and no harder. Here the problem is built with pycolmap's own reprojection cost with a 2x2
covariance per observation (``pycolmap.cost_functions.ReprojErrorCost``) and solved by Ceres through
``pyceres``; the result is written back into the map's ``Reconstruction``.

Parameter blocks: a pose is pycolmap's 7-vector (quaternion xyzw, translation). pyceres 2.6 has no product
manifold for it and cannot take one written in Python, so each variable pose carries a stiff residual
``w (|q|^2 - 1)`` that keeps its quaternion on the unit sphere (the drift it allows is below 1e-8 rad),
and the quaternion is normalized when written back. Points are rows of one array (Ceres keeps a pointer
per block), so the solution is read back in one piece.
"""

from __future__ import annotations

from dataclasses import dataclass

import signal

import numpy as np
import pycolmap


def _import_pyceres():
    """pyceres, imported with SIGTERM's disposition kept: its import installs glog's failure handler, which
    catches SIGTERM and prints a stack trace (the worker processes of ``slamkit ablate``, stopped by their
    parent, wrote theirs into one stream, interleaved)."""
    before = signal.getsignal(signal.SIGTERM)
    import pyceres
    try:
        if before is not None:
            signal.signal(signal.SIGTERM, before)
    except ValueError:  # not the main thread: signals can only be set there
        pass
    return pyceres


pyceres = _import_pyceres()

from .map import CAMERA_ID, SlamMap, keypoint_scales

_REPROJ_COST = pycolmap._core.cost_functions.ReprojErrorCost
UNIT_QUATERNION_WEIGHT = 1e4
"""Weight of the unit-norm residual of a variable pose's quaternion (whitened pixels per unit of |q|^2 - 1)."""


class _UnitQuaternion(pyceres.CostFunction):
    """One residual, ``w (|q|^2 - 1)``, on a pose 7-vector (quaternion first)."""

    def __init__(self, weight: float = UNIT_QUATERNION_WEIGHT):
        super().__init__()
        self.set_num_residuals(1)
        self.set_parameter_block_sizes([7])
        self.weight = weight

    def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 (pyceres' name)
        q = parameters[0][:4]
        residuals[0] = self.weight * (float(q @ q) - 1.0)
        if jacobians is not None and jacobians[0] is not None:
            jacobians[0][:4] = 2.0 * self.weight * q
            jacobians[0][4:] = 0.0
        return True


@dataclass(frozen=True)
class WeightedSolve:
    """What one weighted solve did."""

    num_residuals: int
    num_images: int
    num_points: int
    termination: str
    initial_cost: float
    final_cost: float


def weighted_adjust(slam_map: SlamMap, variable_images, variable_points, constant_points=(),
                    fixed_images=(), iterations: int = 20, huber: float = float(np.sqrt(5.991)),
                    function_tolerance: float = 1e-6, num_threads: int = 1) -> WeightedSolve:
    """Adjust ``variable_images`` (keyframe ids) and ``variable_points`` (point ids) with every observation
    weighted by its keypoint's scale. Every observation of a variable point enters (keyframes outside
    ``variable_images`` held constant, ORB-SLAM's fixed keyframes); ``constant_points`` enter only through
    their observations in ``variable_images`` and are held constant (long tracks, as local BA holds them).
    ``fixed_images``: variable images held constant all the same (the gauge when nothing else holds it).
    The map camera's intrinsics are constant. Writes the solution into the reconstruction."""
    rec = slam_map.reconstruction
    camera = rec.camera(CAMERA_ID)
    cam_params = np.array(camera.params, np.float64)
    var_images = sorted(int(i) for i in variable_images)
    var_ids = np.unique(np.asarray(list(variable_points), np.int64))
    const_ids = np.setdiff1d(np.unique(np.asarray(list(constant_points), np.int64)), var_ids)
    images = set(var_images)
    if len(var_ids):
        images.update(i for i, _ in slam_map.covisible_with(var_ids))
    images = sorted(i for i in images if i in slam_map.keyframes)
    fixed = {int(i) for i in fixed_images} | (set(images) - set(var_images))

    all_ids = np.concatenate([var_ids, const_ids])
    xyz = slam_map.points_xyz(all_ids) if len(all_ids) else np.zeros((0, 3))
    xyz = np.ascontiguousarray(xyz)
    row_of = {int(p): k for k, p in enumerate(all_ids.tolist())}
    poses = {i: np.array(rec.frame(i).rig_from_world.params, np.float64) for i in images}

    problem = pyceres.Problem()
    loss = pyceres.HuberLoss(huber)
    model = camera.model
    used_rows: set[int] = set()
    covariances: dict[float, np.ndarray] = {}  # one 2x2 matrix per level
    n = 0
    for i in images:
        ids = slam_map.point3D_ids(i)
        wanted = var_ids if i in fixed else all_ids
        idx = np.flatnonzero(np.isin(ids, wanted))
        if not len(idx):
            continue
        kf = slam_map.keyframes[i]
        var2 = keypoint_scales(kf.features)[idx] ** 2
        uv = np.asarray(kf.keypoints, np.float64)[idx]
        pose = poses[i]
        for k, p2 in enumerate(idx.tolist()):
            row = row_of[int(ids[p2])]
            cov = covariances.get(var2[k])
            if cov is None:
                cov = covariances[var2[k]] = np.eye(2) * var2[k]
            cost = _REPROJ_COST(model, cov, uv[k])
            problem.add_residual_block(cost, loss, [xyz[row], pose, cam_params])
            used_rows.add(row)
            n += 1
        if i not in fixed:
            problem.add_residual_block(_UnitQuaternion(), None, [pose])
    if n == 0:
        return WeightedSolve(0, 0, 0, "NO_CONVERGENCE", 0.0, 0.0)
    problem.set_parameter_block_constant(cam_params)
    for i in images:
        if i in fixed and problem.has_parameter_block(poses[i]):
            problem.set_parameter_block_constant(poses[i])
    for row in sorted(used_rows):
        if row >= len(var_ids):
            problem.set_parameter_block_constant(xyz[row])

    options = pyceres.SolverOptions()
    options.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR if len(var_images) > 20 \
        else pyceres.LinearSolverType.DENSE_SCHUR
    options.max_num_iterations = iterations
    options.function_tolerance = function_tolerance
    options.num_threads = num_threads
    options.minimizer_progress_to_stdout = False
    options.logging_type = pyceres.LoggingType.SILENT
    summary = pyceres.SolverSummary()
    pyceres.solve(options, problem, summary)

    for i in var_images:
        if i in fixed or i not in poses:
            continue
        q = poses[i][:4] / np.linalg.norm(poses[i][:4])
        rec.frame(i).rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(q), poses[i][4:].copy())
    rows = [k for k in range(len(var_ids)) if k in used_rows]
    slam_map.set_positions(np.asarray(var_ids, np.int64)[rows], xyz[rows])
    slam_map.changed()
    return WeightedSolve(n, len(var_images), len(var_ids), str(summary.termination_type).split(".")[-1],
                         float(summary.initial_cost), float(summary.final_cost))
