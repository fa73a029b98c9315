"""The numerical core of the Sim(3) pose graph (:mod:`slamkit.pose_graph`), on plain arrays: residuals of the
relative similarities and their sparse Jacobian, solved by ``scipy.optimize.least_squares``.

Each keyframe ``i`` is a similarity ``S_iw`` (world to camera); each edge ``e = (i, j)`` a measurement ``S_ij``
with residual ``r_e = (rotvec, t, log s)`` of ``S_ij · S_jw · S_iw^-1`` (zero when consistent) and weight
``w_e`` on ``|r_e|^2``; the free keyframes move, the others hold the gauge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix
from scipy.spatial.transform import Rotation

from .sim3 import sim3_matrix


@dataclass(frozen=True)
class PoseGraphSolution:
    """Outcome of :func:`solve_pose_graph`."""

    sim_from_world: np.ndarray = field(repr=False)
    """(n, 4, 4) the corrected ``S_iw``, in the order of the input."""
    initial_cost: float
    final_cost: float
    """0.5 x sum of weighted squared residuals before and after."""
    evaluations: int
    success: bool
    message: str


def _unpack(sims: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n,) scales, (n, 3, 3) rotations, (n, 3) translations of (n, 4, 4) similarities."""
    s = np.cbrt(np.linalg.det(sims[:, :3, :3]))
    return s, sims[:, :3, :3] / s[:, None, None], sims[:, :3, 3]



class _Problem:
    """Residuals of a pose graph over perturbations ``(dω, dc, dσ)`` of the free keyframes: ``R = exp(dω) R0``,
    camera centre ``c = c0 + dc`` (world), ``s = s0 exp(dσ)``, ``t = -s R c``. Moving the centre rather than
    ``t`` keeps rotation and position decoupled (a rotation does not swing the camera about the world origin),
    which keeps long loops well conditioned; no singularity for rotation corrections below pi."""

    def __init__(self, initial: np.ndarray, free: np.ndarray, ei: np.ndarray, ej: np.ndarray, i_from_j: np.ndarray,
                 weights: np.ndarray):
        self.s0, self.r0, t0 = _unpack(initial)
        self.c0 = -np.einsum("nba,nb->na", self.r0, t0) / self.s0[:, None]
        self.free = free
        self.slot = np.cumsum(self.free) - 1
        self.ei = ei
        self.ej = ej
        self.ms, self.mr, self.mt = _unpack(i_from_j)
        self.sw = np.sqrt(weights)
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



def solve_pose_graph(initial: np.ndarray, free: np.ndarray, ei: np.ndarray, ej: np.ndarray, i_from_j: np.ndarray,
                     weights: np.ndarray, loss: str = "linear", loss_scale: float = 0.1, max_evaluations: int = 200,
                     tolerance: float = 1e-10) -> PoseGraphSolution:
    """Optimise the similarities ``initial`` (n, 4, 4) ``S_iw`` of the keyframes flagged ``free`` (n,) bool,
    the others held (the gauge), over E edges: keyframe indices ``ei``, ``ej`` (E,) int, measurements
    ``i_from_j`` (E, 4, 4) and weights (E,) > 0 of the squared residual. ``loss`` ("linear", "huber",
    "cauchy") at ``loss_scale``, ``max_evaluations`` and ``tolerance`` are scipy's ``least_squares``
    (trust region, sparse Jacobian, near-exact LSMR inner solves)."""
    problem = _Problem(initial, free, ei, ej, i_from_j, weights)
    x0 = np.zeros(problem.num_params)
    initial_cost = 0.5 * float(np.sum(problem.residuals(x0) ** 2))
    if problem.num_params == 0:
        sol_x, nfev, success, message, final = x0, 0, True, "nothing to optimise", initial_cost
    else:
        sol = least_squares(problem.residuals, x0, jac=problem.jacobian, method="trf", tr_solver="lsmr",
                            loss=loss, f_scale=loss_scale, max_nfev=max_evaluations,
                            ftol=tolerance, xtol=tolerance, gtol=tolerance, x_scale="jac",
                            # near-exact inner solves: loose LSMR steps stall long loops for hundreds of iterations
                            tr_options={"atol": 1e-14, "btol": 1e-14, "maxiter": 20 * problem.num_params})
        sol_x, nfev, success, message = sol.x, int(sol.nfev), bool(sol.success), str(sol.message)
        final = 0.5 * float(np.sum(problem.residuals(sol_x) ** 2))
    s, r, t = problem.nodes(sol_x)
    return PoseGraphSolution(np.stack([sim3_matrix(s[n], r[n], t[n]) for n in range(len(s))]), initial_cost, final,
                             nfev, success, message)
