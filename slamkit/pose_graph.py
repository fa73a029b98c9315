"""Sim(3) pose-graph optimisation: ORB-SLAM's essential-graph correction after a loop closure.

Each keyframe ``i`` carries a similarity ``S_iw`` (world to camera: ``x_c = s R x_w + t``), starting from its
current rigid pose (``s = 1``). Edges hold relative measurements ``S_ij`` (camera ``j`` to camera ``i``):
spanning-tree and covisibility edges take them from the current poses (scale 1), loop edges from the Sim(3)
found by loop verification. The optimiser minimises ``sum_e w_e |r_e|^2`` with ``r_e = (rotvec, t, log s)``
of ``S_ij · S_jw · S_iw^-1`` (identity when consistent) while the gauge keyframes stay fixed; the corrected
keyframes get ``cam_from_world = (R, t / s)`` and points and frames follow their reference keyframe
(Strasdat et al., "Scale drift-aware large scale monocular SLAM", RSS 2010; Mur-Artal and Tardós, ORB-SLAM2).

Optimizer: ``scipy.optimize.least_squares`` (trust region, sparse Jacobian) by default, because scipy is already
installed (through scikit-image) while gtsam 4.3.0 (a 34 MB wheel that also requires pytest >= 9 at run time)
is an optional extra (``pip install slamkit[loop]``); ``PoseGraphConfig(backend="gtsam")`` uses GTSAM's
Levenberg-Marquardt with sparse Cholesky on ``BetweenFactorSimilarity3`` factors, far faster on large graphs.
The scipy solve and the Sim(3) algebra are kernels on plain arrays (:mod:`slamkit.kernels.pose_graph`,
:mod:`slamkit.kernels.sim3`); this module builds their input from keyframe poses and edges.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Collection, Iterable, Literal, Mapping

import numpy as np
import pycolmap

from .errors import ConfigError
from .kernels.pose_graph import solve_pose_graph
from .kernels.sim3 import rigid_from_sim3, sim3_decompose, sim3_inverse, sim3_matrix

EdgeKind = Literal["spanning", "covisibility", "loop"]


# ------------------------------------------------------------------------------------------------------
# similarities as 4x4 matrices [[s R, t], [0, 1]] (their algebra: slamkit.kernels.sim3), from pycolmap's


def sim3_from_pycolmap(sim: pycolmap.Sim3d) -> np.ndarray:
    """(4, 4) matrix of a ``pycolmap.Sim3d``."""
    return sim3_matrix(sim.scale, sim.rotation.matrix(), sim.translation)


def as_matrix(pose) -> np.ndarray:
    """(4, 4) float64 of a 4x4 / 3x4 array, a ``pycolmap.Rigid3d`` or a ``pycolmap.Sim3d``."""
    if isinstance(pose, pycolmap.Sim3d):
        return sim3_from_pycolmap(pose)
    if isinstance(pose, pycolmap.Rigid3d):
        pose = pose.matrix()
    m = np.asarray(pose, float)
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ConfigError(f"pose: expected a finite 4x4 or 3x4 matrix or a pycolmap Rigid3d/Sim3d, got shape {m.shape}")
    return m


# ------------------------------------------------------------------------------------------------------
# the graph


@dataclass(frozen=True)
class PoseGraphEdge:
    """A relative Sim(3) measurement ``i_from_j`` (4, 4): maps camera ``j`` coordinates to camera ``i``'s."""

    i: int
    j: int
    i_from_j: np.ndarray = field(repr=False)
    weight: float = 1.0
    """Weight of the squared residual (ORB-SLAM uses 1 for every essential-graph edge)."""
    kind: EdgeKind = "covisibility"


@dataclass(frozen=True)
class PoseGraphConfig:
    """Options of :func:`optimize_pose_graph`."""

    max_evaluations: int = 200
    """Largest number of residual evaluations of the trust-region solver."""
    loss: Literal["linear", "huber", "cauchy"] = "linear"
    """Robust loss on edge residuals (``linear``: plain least squares, as ORB-SLAM's essential graph)."""
    loss_scale: float = 0.1
    """Residual size (radians / metres / log scale) where a robust loss starts to down-weight."""
    tolerance: float = 1e-10
    """Relative cost change (ftol) and step (xtol) at which the solver stops."""
    backend: Literal["scipy", "gtsam"] = "scipy"
    """``scipy`` (default install) or ``gtsam`` (optional extra ``loop``; ConfigError when not installed).
    GTSAM's residual is the Sim(3) logarithm of ``S_ij^-1 · S_iw · S_jw^-1`` (its robust losses are GTSAM's
    Huber / Cauchy m-estimators with the same ``loss_scale``)."""

    def __post_init__(self) -> None:
        if self.backend not in ("scipy", "gtsam"):
            raise ConfigError(f"PoseGraphConfig.backend must be scipy or gtsam (got {self.backend!r})")
        if self.loss not in ("linear", "huber", "cauchy"):
            raise ConfigError(f"PoseGraphConfig.loss must be linear, huber or cauchy (got {self.loss!r})")
        if self.max_evaluations < 1 or not self.loss_scale > 0 or not self.tolerance > 0:
            raise ConfigError("PoseGraphConfig: max_evaluations >= 1, loss_scale > 0 and tolerance > 0 required")


@dataclass(frozen=True)
class PoseGraphResult:
    """Corrected keyframes of :func:`optimize_pose_graph` (dicts keyed by keyframe id)."""

    sim_from_world: dict[int, np.ndarray] = field(repr=False)
    """Corrected ``S_iw`` (4, 4) similarities (world to camera, scale included)."""
    cam_from_world: dict[int, np.ndarray] = field(repr=False)
    """Corrected rigid poses (4, 4): rotation R and translation t / s of ``S_iw``."""
    scales: dict[int, float] = field(repr=False)
    """Scale s of each corrected ``S_iw`` (1 where the map scale did not change)."""
    initial_cost: float
    final_cost: float
    """0.5 x sum of weighted squared residuals before and after."""
    evaluations: int
    success: bool
    message: str


def relative_edges(poses: Mapping[int, object], pairs: Iterable[tuple[int, int]], weight: float = 1.0,
                   kind: EdgeKind = "covisibility") -> list[PoseGraphEdge]:
    """Edges ``(i, j)`` measured by the current rigid poses (scale 1): ``T_iw · T_jw^-1``.

    poses: keyframe id -> cam_from_world (4x4 array or pycolmap Rigid3d).
    """
    out = []
    for i, j in pairs:
        if i not in poses or j not in poses:
            raise ConfigError(f"edge ({i}, {j}): keyframe {i if i not in poses else j} has no pose")
        out.append(PoseGraphEdge(int(i), int(j), as_matrix(poses[i]) @ np.linalg.inv(as_matrix(poses[j])),
                                 weight, kind))
    return out


def loop_edge(query: int, candidate: int, query_pose, candidate_pose, candidate_world_from_query_world,
              weight: float = 1.0) -> PoseGraphEdge:
    """The loop edge ``query_from_candidate`` from the Sim(3) of loop verification.

    ``candidate_world_from_query_world`` maps points as the query keyframe's (drifted) map places them to
    where the candidate's map has them (``tgt_from_src`` of ``estimate_sim3d_robust`` with the query's
    points as source). The query's corrected pose is then ``S_qw = T_qw · S^-1`` and the edge is
    ``S_qw · T_cw^-1``. Poses are rigid cam_from_world (4x4 or Rigid3d); the Sim(3) a 4x4 or pycolmap Sim3d.
    """
    s_qw = as_matrix(query_pose) @ sim3_inverse(as_matrix(candidate_world_from_query_world))
    return PoseGraphEdge(int(query), int(candidate), s_qw @ np.linalg.inv(as_matrix(candidate_pose)), weight, "loop")


def optimize_pose_graph(poses: Mapping[int, object], edges: Collection[PoseGraphEdge],
                        fixed: int | Collection[int], config: PoseGraphConfig | None = None) -> PoseGraphResult:
    """Optimise the Sim(3) of every keyframe in ``poses`` over ``edges``, keeping ``fixed`` ones (the gauge).

    poses: keyframe id -> current cam_from_world (4x4 or pycolmap Rigid3d), or a (4, 4) ``S_iw`` with scale
        (e.g. a previous correction). Not modified.
    edges: relative measurements between keyframes of ``poses`` (spanning tree, covisibility, loops).
    fixed: one id or several; at least one, all in ``poses``.
    Raises ConfigError for an edge or fixed id without a pose, or a keyframe that no edge reaches.
    """
    cfg = config or PoseGraphConfig()
    fixed_set = {int(fixed)} if isinstance(fixed, (int, np.integer)) else {int(k) for k in fixed}
    ids = sorted(int(k) for k in poses)
    _check_graph(ids, list(edges), fixed_set)
    initial = np.stack([as_matrix(poses[k]) for k in ids])
    solve = _solve_gtsam if cfg.backend == "gtsam" else _solve_scipy
    return solve(ids, initial, list(edges), fixed_set, cfg)


def _solve_scipy(ids: list[int], initial: np.ndarray, edges: list[PoseGraphEdge], fixed: set[int],
                 cfg: PoseGraphConfig) -> PoseGraphResult:
    """:func:`slamkit.kernels.pose_graph.solve_pose_graph` on the graph's arrays."""
    index = {k: n for n, k in enumerate(ids)}
    sol = solve_pose_graph(initial, np.array([k not in fixed for k in ids]), np.array([index[e.i] for e in edges]),
                           np.array([index[e.j] for e in edges]), np.stack([e.i_from_j for e in edges]),
                           np.array([e.weight for e in edges], np.float64), cfg.loss, cfg.loss_scale,
                           cfg.max_evaluations, cfg.tolerance)
    return _result(ids, list(sol.sim_from_world), sol.initial_cost, sol.final_cost, sol.evaluations, sol.success,
                   sol.message)


def _result(ids: list[int], sims: list[np.ndarray], initial_cost: float, final_cost: float, evaluations: int,
            success: bool, message: str) -> PoseGraphResult:
    by_id = dict(zip(ids, sims))
    return PoseGraphResult(by_id, {k: rigid_from_sim3(m) for k, m in by_id.items()},
                           {k: sim3_decompose(m)[0] for k, m in by_id.items()}, initial_cost, final_cost,
                           evaluations, success, message)


def _solve_gtsam(ids: list[int], initial: np.ndarray, edges: list[PoseGraphEdge], fixed: set[int],
                 cfg: PoseGraphConfig) -> PoseGraphResult:
    """GTSAM: variables ``X_k = S_kw^-1``, so that ``BetweenFactor(i, j)`` measures ``X_i^-1 X_j = S_ij``.
    GTSAM's ``Similarity3(R, t, s)`` maps ``x -> s (R x + t)``: our (s, R, t) is ``Similarity3(R, t / s, s)``."""
    try:
        import gtsam  # optional extra "loop"
    except ImportError as e:
        raise ConfigError("PoseGraphConfig.backend='gtsam' needs the gtsam package (pip install slamkit[loop])") from e

    def to_gtsam(m: np.ndarray):
        s, r, t = sim3_decompose(m)
        return gtsam.Similarity3(gtsam.Rot3(r), t / s, s)

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, m in zip(ids, initial):
        values.insert(k, to_gtsam(sim3_inverse(m)))
    for e in edges:
        noise = gtsam.noiseModel.Isotropic.Sigma(7, 1.0 / np.sqrt(e.weight))
        if cfg.loss != "linear":
            estimator = gtsam.noiseModel.mEstimator.Huber if cfg.loss == "huber" else gtsam.noiseModel.mEstimator.Cauchy
            noise = gtsam.noiseModel.Robust.Create(estimator.Create(cfg.loss_scale), noise)
        graph.add(gtsam.BetweenFactorSimilarity3(e.i, e.j, to_gtsam(e.i_from_j), noise))
    for k in sorted(fixed):
        graph.add(gtsam.NonlinearEqualitySimilarity3(k, values.atSimilarity3(k)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.max_evaluations)
    params.setRelativeErrorTol(cfg.tolerance)
    params.setAbsoluteErrorTol(cfg.tolerance)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    solution = optimizer.optimize()
    sims = []
    for k in ids:
        x = solution.atSimilarity3(k)
        sims.append(sim3_inverse(sim3_matrix(x.scale(), x.rotation().matrix(), x.scale() * x.translation())))
    iterations = int(optimizer.iterations())
    return _result(ids, sims, float(graph.error(values)), float(graph.error(solution)), iterations,
                   iterations < cfg.max_evaluations, f"gtsam Levenberg-Marquardt, {iterations} iterations")


def _check_graph(ids: list[int], edges: list[PoseGraphEdge], fixed: set[int]) -> None:
    """ConfigError unless edges and fixed ids name posed keyframes and every keyframe reaches a fixed one."""
    known = set(ids)
    if not fixed:
        raise ConfigError("fixed: at least one keyframe must be fixed (the gauge)")
    if fixed - known:
        raise ConfigError(f"fixed: keyframe {min(fixed - known)} has no pose")
    if not edges:
        raise ConfigError("edges: the pose graph has no edge")
    parent = {k: k for k in ids}

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for e in edges:
        if e.i not in known or e.j not in known:
            raise ConfigError(f"edge ({e.i}, {e.j}): keyframe {e.i if e.i not in known else e.j} has no pose")
        if e.i == e.j or not e.weight > 0 or np.shape(e.i_from_j) != (4, 4):
            raise ConfigError(f"edge ({e.i}, {e.j}): needs two keyframes, a positive weight and a 4x4 Sim(3)")
        parent[root(e.i)] = root(e.j)
    anchored = {root(k) for k in fixed}
    loose = [k for k in ids if root(k) not in anchored]
    if loose:
        raise ConfigError(f"keyframe {loose[0]} is not connected to a fixed keyframe by any edge")


# ------------------------------------------------------------------------------------------------------
# following the correction


def propagate_to_frames(frame_poses: Mapping[int, object], reference_keyframe: Mapping[int, int],
                        keyframe_poses: Mapping[int, object], result: PoseGraphResult) -> dict[int, np.ndarray]:
    """Corrected cam_from_world (4, 4) of frames that follow their reference keyframe's Sim(3).

    Frame f keeps its rigid pose relative to keyframe k = reference_keyframe[f] as it was before the
    correction (``T_fk = T_fw · T_kw^-1``, from ``keyframe_poses``, the poses before): ``S_fw = T_fk · S_kw``,
    and its rigid pose is ``(R, t / s)`` of that. Frames whose keyframe was not optimised are left out.
    """
    out = {}
    for f, pose in frame_poses.items():
        k = reference_keyframe.get(f)
        if k is None or k not in result.sim_from_world:
            continue
        if k not in keyframe_poses:
            raise ConfigError(f"frame {f}: reference keyframe {k} has no pose before the correction")
        t_fk = as_matrix(pose) @ np.linalg.inv(as_matrix(keyframe_poses[k]))
        out[int(f)] = rigid_from_sim3(t_fk @ result.sim_from_world[k])
    return out


def correct_points(points: np.ndarray, reference_keyframes: np.ndarray, keyframe_poses: Mapping[int, object],
                   result: PoseGraphResult) -> np.ndarray:
    """Map points (N, 3) world metres moved with their reference keyframe: ``X' = S_kw'^-1 · T_kw · X``.

    reference_keyframes: (N,) keyframe id per point (e.g. the keyframe that first observed it).
    keyframe_poses: cam_from_world before the correction. Returns a new (N, 3) array.
    """
    pts = np.asarray(points, float).reshape(-1, 3)
    refs = np.asarray(reference_keyframes).reshape(-1)
    if len(refs) != len(pts):
        raise ConfigError(f"reference_keyframes: {len(refs)} ids for {len(pts)} points")
    out = pts.copy()
    for k in np.unique(refs):
        k = int(k)
        if k not in result.sim_from_world:
            continue
        m = sim3_inverse(result.sim_from_world[k]) @ as_matrix(keyframe_poses[k])
        sel = refs == k
        out[sel] = pts[sel] @ m[:3, :3].T + m[:3, 3]
    return out
