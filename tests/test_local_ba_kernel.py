"""The compiled local bundle adjustment (:mod:`slamkit.kernels.local_ba`) against exact geometry and against Ceres.

The problem: 8 keyframes on a 60 degree arc of radius 4 around 200 known points in a 2 m cube, every point seen
by every keyframe, pixels at the exact projection plus Gaussian noise (0.3 px x the level's sigma), 20 % of
the observations planted outliers (each point gets one or two, displaced 20-80 px), the two first keyframes
held (the gauge), the others started ~1 degree / 5 cm off and the points 5 cm off. The same problem is given
to Ceres through pyceres with pycolmap's own reprojection cost (as :mod:`slamkit.weighted_ba` builds it):
the same losses, scales and weights, so both minimize the same cost."""

from __future__ import annotations

import math
import threading

import numpy as np
import pycolmap
import pyceres
import pytest

from slamkit.weighted_ba import _UnitQuaternion
from slamkit.kernels.local_ba import (CHI2_2DOF_95, _cost, _linearize, _retract, local_bundle_adjustment,
                                      outlier_mask)

CAM = np.array([800.0, 800.0, 320.0, 240.0])
HUBER = math.sqrt(CHI2_2DOF_95)


def _rot(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    W = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * W + (1 - math.cos(angle)) * W @ W


def problem(seed: int = 0, num_points: int = 200, levels: bool = True, outliers: bool = True, K: int = 12):
    """dict: truth (T (K, 4, 4), X (P, 3)), start (T0, X0), observations (op, oq, xy, w), planted outlier mask."""
    rng = np.random.default_rng(seed)
    T = np.zeros((K, 4, 4))
    for k, ang in enumerate(np.linspace(-math.pi / 6, math.pi / 6, K)):
        c = np.array([4 * math.sin(ang), 0.2 * rng.normal(), -4 * math.cos(ang)])
        z = -c / np.linalg.norm(c)  # looking at the origin
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        T[k] = np.eye(4)
        T[k, :3, :3], T[k, :3, 3] = R, -R @ c
    X = rng.uniform(-1, 1, (num_points, 3))
    op, oq = np.meshgrid(np.arange(K), np.arange(num_points), indexing="ij")
    op, oq = op.ravel(), oq.ravel()
    Xc = np.einsum("nij,nj->ni", T[op, :3, :3], X[oq]) + T[op, :3, 3]
    xy = CAM[:2] * Xc[:, :2] / Xc[:, 2:] + CAM[2:]
    octave = rng.integers(0, 8, len(op)) if levels else np.zeros(len(op), int)
    sigma = 1.2 ** octave
    xy += rng.normal(size=xy.shape) * 0.3 * sigma[:, None]
    out = np.zeros(len(op), bool)
    if outliers:  # two or three of each point's 12 observations: 20 % in all
        for p in range(num_points):
            n = round(0.2 * K) + (rng.random() < 0.2 * K - round(0.2 * K))
            out[np.flatnonzero(oq == p)[rng.choice(K, n, replace=False)]] = True
        d = rng.normal(size=(out.sum(), 2))
        xy[out] += d / np.linalg.norm(d, axis=1)[:, None] * rng.uniform(20, 80, out.sum())[:, None]
    T0 = T.copy()
    for k in range(2, K):
        T0[k, :3, :3] = _rot(rng.normal(size=3), math.radians(1)) @ T[k, :3, :3]
        T0[k, :3, 3] += rng.normal(size=3) * 0.05
    X0 = X + rng.normal(size=X.shape) * 0.05
    return dict(T=T, X=X, T0=T0, X0=X0, op=op, oq=oq, xy=xy, w=1.0 / sigma ** 2, out=out,
                fixed=np.arange(K) < 2)


def ceres_solve(pb, loss: str, scale: float, weights: np.ndarray, iterations: int = 500):
    """The same problem solved by Ceres (pyceres, pycolmap's ReprojErrorCost with covariance I / w); returns
    ((K, 4, 4) poses, (P, 3) points)."""
    K, X = len(pb["T0"]), pb["X0"].copy()
    poses = [np.array(pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3].copy()).params) for T in pb["T0"]]
    cam = CAM.copy()
    rloss = pyceres.HuberLoss(scale) if loss == "huber" else pyceres.SoftLOneLoss(scale)
    problem = pyceres.Problem()
    for i in range(len(pb["op"])):
        cost = pycolmap._core.cost_functions.ReprojErrorCost(pycolmap.CameraModelId.PINHOLE, np.eye(2) / weights[i],
                                                       pb["xy"][i])
        problem.add_residual_block(cost, rloss, [X[pb["oq"][i]], poses[pb["op"][i]], cam])
    problem.set_parameter_block_constant(cam)
    for k in range(K):
        if pb["fixed"][k]:
            problem.set_parameter_block_constant(poses[k])
        else:  # pyceres 2.6 has no product manifold: weighted_ba's stiff unit-norm residual on the quaternion
            problem.add_residual_block(_UnitQuaternion(1e6), None, [poses[k]])
    options = pyceres.SolverOptions()
    options.linear_solver_type = pyceres.LinearSolverType.DENSE_SCHUR
    options.max_num_iterations = iterations
    options.function_tolerance = options.gradient_tolerance = options.parameter_tolerance = 1e-15
    options.logging_type = pyceres.LoggingType.SILENT
    summary = pyceres.SolverSummary()
    pyceres.solve(options, problem, summary)
    T = np.tile(np.eye(4), (K, 1, 1))
    for k in range(K):
        q = poses[k][:4] / np.linalg.norm(poses[k][:4])
        T[k, :3] = pycolmap.Rigid3d(pycolmap.Rotation3d(q), poses[k][4:].copy()).matrix()
    return T, X


def _kernel_cost(pb, T, X, loss, scale, w):
    R, t = np.ascontiguousarray(T[:, :3, :3]), np.ascontiguousarray(T[:, :3, 3])
    code = {"trivial": 0, "huber": 1, "soft_l1": 2}[loss]
    return _cost(R, t, np.ascontiguousarray(X), pb["op"], pb["oq"], pb["xy"], w, np.ones(len(w), bool), CAM, code,
                 scale ** 2, 1e-6)


def _pose_gap(A, B):
    """(largest camera-centre distance m, largest rotation angle deg) between two pose stacks."""
    centre = lambda T: -np.einsum("kji,kj->ki", T[:, :3, :3], T[:, :3, 3])  # noqa: E731
    dc = np.linalg.norm(centre(A) - centre(B), axis=1).max()
    cosines = (np.einsum("kij,kij->k", A[:, :3, :3], B[:, :3, :3]) - 1) / 2
    return float(dc), float(np.degrees(np.arccos(np.clip(cosines, -1, 1))).max())


def _solve(pb, **kw):
    kw.setdefault("pose_fixed", pb["fixed"])
    return local_bundle_adjustment(pb["T0"], pb["X0"], pb["op"], pb["oq"], pb["xy"], CAM, **kw)


@pytest.mark.parametrize("loss", ["trivial", "huber", "soft_l1"])
def test_the_gradient_is_the_cost_derivative(loss):
    """The normal equations' right-hand side is the cost's gradient in (omega, dt) (left rotation perturbation,
    additive translation) and in the points, by central differences."""
    pb = problem(1, num_points=30)
    R, t, X = (np.ascontiguousarray(pb["T0"][:, :3, :3]), np.ascontiguousarray(pb["T0"][:, :3, 3]),
               pb["X0"].copy())
    K, P, N = len(R), len(X), len(pb["op"])
    code, a2 = {"trivial": 0, "huber": 1, "soft_l1": 2}[loss], 2.0
    args = (pb["op"], pb["oq"], pb["xy"], pb["w"], np.ones(N, bool), CAM, code, a2)
    U, bx, V, by, Wb = np.empty((K, 6, 6)), np.empty((K, 6)), np.empty((P, 3, 3)), np.empty((P, 3)), np.empty((N, 6, 3))
    _linearize(R, t, X, *args, np.arange(K), np.arange(P), np.ones((K, 6)), U, bx, V, by, Wb)
    num = np.empty((K, 6))
    Rn, tn, Xn = np.empty_like(R), np.empty_like(t), np.empty_like(X)
    for k in range(K):
        for a in range(6):
            dx = np.zeros(6 * K)
            dx[6 * k + a] = 1e-6
            _retract(R, t, X, np.arange(K), np.arange(P), dx, np.zeros((P, 3)), Rn, tn, Xn)
            plus = _cost(Rn, tn, Xn, *args, 1e-6)
            _retract(R, t, X, np.arange(K), np.arange(P), -dx, np.zeros((P, 3)), Rn, tn, Xn)
            num[k, a] = (plus - _cost(Rn, tn, Xn, *args, 1e-6)) / 2e-6
    np.testing.assert_allclose(bx, num, rtol=1e-5, atol=1e-3 * np.abs(bx).max() * 1e-3)
    nump = np.empty((P, 3))
    for p in range(P):
        for a in range(3):
            Xn = X.copy()
            Xn[p, a] += 1e-6
            plus = _cost(R, t, Xn, *args, 1e-6)
            Xn[p, a] -= 2e-6
            nump[p, a] = (plus - _cost(R, t, Xn, *args, 1e-6)) / 2e-6
    np.testing.assert_allclose(by, nump, rtol=1e-5, atol=1e-6 * np.abs(by).max())
    assert np.all(np.linalg.eigvalsh(U) > 0) and np.all(np.linalg.eigvalsh(V) > 0)


@pytest.mark.parametrize("loss,scale,levels", [("huber", HUBER, True), ("soft_l1", 1.0, False)])
def test_the_same_optimum_as_ceres_and_the_chi2_test_finds_exactly_the_planted_outliers(loss, scale, levels):
    """ORB-SLAM's (Huber at sqrt(5.991), information 1/sigma^2 per level) and COLMAP's (soft L1 at 1 px, flat
    weights) local BA: the kernel and Ceres reach the same optimum: cost within 1e-9 relative, poses within
    1e-3 mm and 1e-4 degrees, points within 1e-3 mm. At it the chi-square test (on the level's sigma) finds
    every planted outlier and at most 0.5 % of the inliers; ORB-SLAM's second pass, without the first pass's
    outliers, then classes exactly the planted ones."""
    pb = problem(2, levels=levels)
    w = pb["w"] if levels else np.ones(len(pb["op"]))
    tight = dict(max_iterations=500, function_tolerance=1e-15, parameter_tolerance=1e-15)
    res = _solve(pb, obs_weight=w, loss=loss, loss_scale=scale, **tight)
    assert res.success and res.reason == "" and res.termination == "CONVERGENCE", res
    assert res.final_cost < res.initial_cost and res.num_residuals == len(w)
    T_ceres, X_ceres = ceres_solve(pb, loss, scale, w)
    c_kernel = _kernel_cost(pb, res.cam_from_world, res.points, loss, scale, w)
    c_ceres = _kernel_cost(pb, T_ceres, X_ceres, loss, scale, w)
    assert c_kernel == pytest.approx(res.final_cost, rel=1e-12)
    assert abs(c_kernel - c_ceres) <= 1e-9 * c_ceres, (c_kernel, c_ceres)
    dc, dr = _pose_gap(res.cam_from_world, T_ceres)
    assert dc < 1e-6 and dr < 1e-4, (dc, dr)
    assert np.abs(res.points - X_ceres).max() < 1e-6
    dc_truth, dr_truth = _pose_gap(res.cam_from_world, pb["T"])  # the outliers did not drag the optimum far
    assert dc_truth < 0.03 and dr_truth < 0.4, (dc_truth, dr_truth)
    whiten = 1.0 if levels else pb["w"]  # classify on the level's sigma (ORB-SLAM's test)
    first = outlier_mask(res.chi2 * whiten)
    assert first[pb["out"]].all() and first[~pb["out"]].sum() <= 0.005 * (~pb["out"]).sum()
    second = local_bundle_adjustment(res.cam_from_world, res.points, pb["op"], pb["oq"], pb["xy"], CAM,
                                     obs_weight=w, pose_fixed=pb["fixed"], loss=loss, loss_scale=scale,
                                     obs_mask=~first, **tight)
    assert second.success and second.num_residuals == (~first).sum()
    np.testing.assert_array_equal(outlier_mask(second.chi2 * whiten), pb["out"])
    dc_truth2, _ = _pose_gap(second.cam_from_world, pb["T"])
    assert dc_truth2 < 0.5 * dc_truth  # without the outliers' pull, closer to the truth


def test_fixed_poses_and_points_do_not_move_and_a_gauge_coordinate_is_held():
    pb = problem(3, num_points=60)
    point_fixed = np.arange(60) % 5 == 0
    res = _solve(pb, point_fixed=point_fixed, gauge=(2, 1), obs_weight=pb["w"])
    assert res.success and res.iterations > 0
    assert np.array_equal(res.cam_from_world[:2], pb["T0"][:2])  # bit for bit
    assert np.array_equal(res.points[point_fixed], pb["X0"][point_fixed])
    assert res.cam_from_world[2, 1, 3] == pb["T0"][2, 1, 3]
    assert not np.array_equal(res.cam_from_world[2:], pb["T0"][2:])
    assert not np.array_equal(res.points[~point_fixed], pb["X0"][~point_fixed])
    R = res.cam_from_world[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)


def test_the_abort_flag_stops_the_solve_and_the_kernel_runs_beside_another_thread():
    pb = problem(4)
    abort = np.ones(1, np.int64)
    res = _solve(pb, abort=abort)
    assert res.success and res.termination == "ABORTED" and res.iterations == 0
    assert np.array_equal(res.cam_from_world, pb["T0"]) and res.final_cost == res.initial_cost
    # nogil: two threads solving the same problem give the same, bit for bit, as one
    alone = _solve(pb, max_iterations=10)
    out = [None, None]

    def run(j):
        out[j] = _solve(pb, max_iterations=10)

    threads = [threading.Thread(target=run, args=(j,)) for j in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    for r in out:
        assert np.array_equal(r.cam_from_world, alone.cam_from_world) and np.array_equal(r.points, alone.points)


def test_degenerate_input_is_a_result_with_a_reason():
    pb = problem(5, num_points=40)
    empty = local_bundle_adjustment(pb["T0"], pb["X0"], [], [], np.zeros((0, 2)), CAM)
    assert not empty.success and "no usable observation" in empty.reason and empty.termination == "FAILURE"
    nan_pose = pb["T0"].copy()
    nan_pose[3, 0, 3] = np.nan
    r = local_bundle_adjustment(nan_pose, pb["X0"], pb["op"], pb["oq"], pb["xy"], CAM)
    assert not r.success and r.reason == "pose 3 is not finite"
    nan_point = pb["X0"].copy()
    nan_point[7, 2] = np.inf
    r = local_bundle_adjustment(pb["T0"], nan_point, pb["op"], pb["oq"], pb["xy"], CAM)
    assert not r.success and r.reason == "point 7 is not finite"
    # a NaN pixel and a point behind one camera: those observations are left out, said, and classed outliers
    xy, X0 = pb["xy"].copy(), pb["X0"].copy()
    xy[5] = np.nan
    behind = 11
    T = pb["T0"][0]
    X0[behind] = T[:3, :3].T @ (np.array([0.0, 0.0, -1.0]) - T[:3, 3])  # 1 m behind keyframe 0
    r = local_bundle_adjustment(pb["T0"], X0, pb["op"], pb["oq"], xy, CAM, pose_fixed=pb["fixed"], loss="huber")
    ahead = np.einsum("nij,nj->ni", pb["T0"][pb["op"], :3, :3], X0[pb["oq"]])[:, 2] + pb["T0"][pb["op"], 2, 3] > 0
    assert r.success and "1 unusable" in r.reason and f"{(~ahead).sum()} at depth" in r.reason, r.reason
    assert r.num_residuals == len(xy) - 1 - (~ahead).sum() and (~ahead).sum() >= 1
    mask = outlier_mask(r.chi2)
    assert mask[5] and np.isinf(r.chi2[5])
    assert mask[~ahead].all() and not ahead[np.flatnonzero((pb["op"] == 0) & (pb["oq"] == behind))[0]]
    with pytest.raises(ValueError, match="obs_pose"):
        local_bundle_adjustment(pb["T0"], pb["X0"], pb["op"] + 100, pb["oq"], pb["xy"], CAM)


def test_behind_the_camera_zero_is_colmaps_cost():
    """``behind_camera="zero"``: an observation whose point is behind its camera adds 0 to the cost and is still
    in the problem (COLMAP 4's ReprojErrorCost returns a zero residual there: checked here on pycolmap's own
    cost function), so the initial cost is that of the other observations."""
    pb = problem(6, num_points=40)
    X0 = pb["X0"].copy()
    T = pb["T0"][0]
    X0[3] = T[:3, :3].T @ (np.array([0.1, 0.0, -2.0]) - T[:3, 3])  # 2 m behind keyframe 0
    cost = pycolmap._core.cost_functions.ReprojErrorCost(pycolmap.CameraModelId.PINHOLE, np.eye(2), pb["xy"][0])
    quat_t = np.array(pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3].copy()).params)
    assert np.array_equal(np.asarray(cost.evaluate(X0[3], quat_t, CAM.copy())[0]).ravel(), [0.0, 0.0])
    ahead = np.einsum("nij,nj->ni", pb["T0"][pb["op"], :3, :3], X0[pb["oq"]])[:, 2] + pb["T0"][pb["op"], 2, 3] > 0
    zero = local_bundle_adjustment(pb["T0"], X0, pb["op"], pb["oq"], pb["xy"], CAM, pose_fixed=pb["fixed"],
                                   loss="soft_l1", loss_scale=1.0, behind_camera="zero", max_iterations=0,
                                   min_depth=np.finfo(float).eps)
    assert zero.success and zero.num_residuals == len(pb["op"]) and "residual 0" in zero.reason
    kept = local_bundle_adjustment(pb["T0"], X0, pb["op"], pb["oq"], pb["xy"], CAM, pose_fixed=pb["fixed"],
                                   loss="soft_l1", loss_scale=1.0, max_iterations=0, obs_mask=ahead)
    assert zero.initial_cost == pytest.approx(kept.initial_cost, rel=1e-12) and (~ahead).sum() >= 1
    solved = local_bundle_adjustment(pb["T0"], X0, pb["op"], pb["oq"], pb["xy"], CAM, pose_fixed=pb["fixed"],
                                     loss="soft_l1", loss_scale=1.0, behind_camera="zero")
    assert solved.success and solved.final_cost < solved.initial_cost
