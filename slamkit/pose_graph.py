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
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Collection, Iterable, Literal, Mapping

import numpy as np
import pycolmap
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix
from scipy.spatial.transform import Rotation

from .errors import ConfigError

EdgeKind = Literal["spanning", "covisibility", "loop"]


# ------------------------------------------------------------------------------------------------------
# similarities as 4x4 matrices [[s R, t], [0, 1]]


def sim3_matrix(scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) float64 similarity ``x -> scale * rotation @ x + translation`` (rotation (3, 3), metres)."""
    m = np.eye(4)
    m[:3, :3] = float(scale) * np.asarray(rotation, float)
    m[:3, 3] = np.asarray(translation, float).reshape(3)
    return m


def sim3_decompose(m: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation (3, 3), translation (3,)) of a (4, 4) similarity matrix."""
    m = np.asarray(m, float)
    scale = float(np.cbrt(np.linalg.det(m[:3, :3])))
    if not scale > 0:
        raise ConfigError(f"not a similarity: determinant of the linear part is {scale ** 3:.3g}")
    return scale, m[:3, :3] / scale, m[:3, 3].copy()


def sim3_from_pycolmap(sim: pycolmap.Sim3d) -> np.ndarray:
    """(4, 4) matrix of a ``pycolmap.Sim3d``."""
    return sim3_matrix(sim.scale, sim.rotation.matrix(), sim.translation)


def sim3_inverse(m: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) similarity matrix."""
    s, r, t = sim3_decompose(m)
    return sim3_matrix(1.0 / s, r.T, -(r.T @ t) / s)


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


def rigid_from_sim3(m: np.ndarray) -> np.ndarray:
    """The rigid ``cam_from_world`` (4, 4) of a corrected ``S_cw``: rotation R and translation t / s."""
    s, r, t = sim3_decompose(m)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r, t / s
    return out


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


def _unpack(sims: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n,) scales, (n, 3, 3) rotations, (n, 3) translations of (n, 4, 4) similarities."""
    s = np.cbrt(np.linalg.det(sims[:, :3, :3]))
    return s, sims[:, :3, :3] / s[:, None, None], sims[:, :3, 3]


class _Problem:
    """Residuals of a pose graph over perturbations ``(dω, dc, dσ)`` of the free keyframes: ``R = exp(dω) R0``,
    camera centre ``c = c0 + dc`` (world), ``s = s0 exp(dσ)``, ``t = -s R c``. Moving the centre rather than
    ``t`` keeps rotation and position decoupled (a rotation does not swing the camera about the world origin),
    which keeps long loops well conditioned; no singularity for rotation corrections below pi."""

    def __init__(self, ids: list[int], initial: np.ndarray, edges: list[PoseGraphEdge], fixed: set[int]):
        index = {k: n for n, k in enumerate(ids)}
        self.s0, self.r0, t0 = _unpack(initial)
        self.c0 = -np.einsum("nba,nb->na", self.r0, t0) / self.s0[:, None]
        self.free = np.array([k not in fixed for k in ids])
        self.slot = np.cumsum(self.free) - 1
        self.ei = np.array([index[e.i] for e in edges])
        self.ej = np.array([index[e.j] for e in edges])
        self.ms, self.mr, self.mt = _unpack(np.stack([e.i_from_j for e in edges]))
        self.sw = np.sqrt([e.weight for e in edges])
        self.num_params = 7 * int(self.free.sum())

    def states(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n,) scales, (n, 3, 3) rotations, (n, 3) centres of all keyframes for parameters x."""
        s, r, c = self.s0.copy(), self.r0.copy(), self.c0.copy()
        p = x.reshape(-1, 7)
        f = self.free
        r[f] = Rotation.from_rotvec(p[:, :3]).as_matrix() @ r[f]
        c[f] = c[f] + p[:, 3:6]
        s[f] = s[f] * np.exp(np.clip(p[:, 6], -20.0, 20.0))  # a wild trial step must stay finite
        return s, r, c

    def nodes(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(n,) scales, (n, 3, 3) rotations, (n, 3) translations of the ``S_iw`` for parameters x."""
        s, r, c = self.states(x)
        return s, r, -s[:, None] * np.einsum("nab,nb->na", r, c)

    def _edge_residuals(self, si, ri, ci, sj, rj, cj) -> np.ndarray:
        """(E, 7) unweighted residuals ``(rotvec, t, log s)`` of ``S_ij · S_jw · S_iw^-1`` per edge."""
        ti = -si[:, None] * np.einsum("eab,eb->ea", ri, ci)
        tj = -sj[:, None] * np.einsum("eab,eb->ea", rj, cj)
        sa = self.ms * sj  # S_ij · S_jw
        ra = self.mr @ rj
        ta = self.ms[:, None] * np.einsum("eab,eb->ea", self.mr, tj) + self.mt
        re = ra @ np.transpose(ri, (0, 2, 1))  # · S_iw^-1 = (1/si, ri^T, -ri^T ti / si)
        te = ta - (sa / si)[:, None] * np.einsum("eab,eb->ea", re, ti)
        return np.concatenate([Rotation.from_matrix(re).as_rotvec(), te, np.log(sa / si)[:, None]], axis=1)

    def _edge_states(self, x: np.ndarray):
        s, r, c = self.states(x)
        return [s[self.ei], r[self.ei], c[self.ei], s[self.ej], r[self.ej], c[self.ej]]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        return (self._edge_residuals(*self._edge_states(x)) * self.sw[:, None]).ravel()

    def jacobian(self, x: np.ndarray, step: float = 1e-6) -> csr_matrix:
        """Sparse (7E, num_params) Jacobian: each edge's 7 x 7 blocks for its two keyframes by central
        differences, all edges at once (14 x 2 evaluations of the vectorised edge residual)."""
        base = self._edge_states(x)
        rows, cols, vals = [], [], []
        e_rows = 7 * np.arange(len(self.ei))[:, None] + np.arange(7)[None, :]
        for side, node in ((0, self.ei), (3, self.ej)):
            free = self.free[node]
            for k in range(7):
                delta = np.zeros((len(node), 7))
                delta[:, k] = step
                plus, minus = list(base), list(base)
                plus[side:side + 3] = _perturb(base[side:side + 3], delta)
                minus[side:side + 3] = _perturb(base[side:side + 3], -delta)
                d = (self._edge_residuals(*plus) - self._edge_residuals(*minus)) / (2 * step) * self.sw[:, None]
                rows.append(e_rows[free].ravel())
                cols.append(np.repeat(7 * self.slot[node][free] + k, 7))
                vals.append(d[free].ravel())
        return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(7 * len(self.ei), self.num_params))


def _perturb(state: list[np.ndarray], delta: np.ndarray) -> list[np.ndarray]:
    """(scales, rotations, centres) of edge endpoints moved by per-edge perturbations (E, 7)."""
    s, r, c = state
    return [s * np.exp(delta[:, 6]), Rotation.from_rotvec(delta[:, :3]).as_matrix() @ r, c + delta[:, 3:6]]


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
    problem = _Problem(ids, initial, edges, fixed)
    x0 = np.zeros(problem.num_params)
    initial_cost = 0.5 * float(np.sum(problem.residuals(x0) ** 2))
    if problem.num_params == 0:
        sol_x, nfev, success, message, final = x0, 0, True, "nothing to optimise", initial_cost
    else:
        sol = least_squares(problem.residuals, x0, jac=problem.jacobian, method="trf", tr_solver="lsmr",
                            loss=cfg.loss, f_scale=cfg.loss_scale, max_nfev=cfg.max_evaluations,
                            ftol=cfg.tolerance, xtol=cfg.tolerance, gtol=cfg.tolerance, x_scale="jac",
                            # near-exact inner solves: loose LSMR steps stall long loops for hundreds of iterations
                            tr_options={"atol": 1e-14, "btol": 1e-14, "maxiter": 20 * problem.num_params})
        sol_x, nfev, success, message = sol.x, int(sol.nfev), bool(sol.success), str(sol.message)
        final = 0.5 * float(np.sum(problem.residuals(sol_x) ** 2))
    s, r, t = problem.nodes(sol_x)
    return _result(ids, [sim3_matrix(s[n], r[n], t[n]) for n in range(len(ids))], initial_cost, final, nfev,
                   success, message)


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
