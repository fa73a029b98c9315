"""Aligning an estimated trajectory to ground truth: Sim(3), SE(3) or scale only (Umeyama).

A monocular estimate lives in its own frame and scale; before comparing it with ground truth it is
mapped by the similarity that best fits its camera centres to the ground truth's in the least-squares
sense (Umeyama 1991). The estimate is wrapped from pycolmap: ``pycolmap.estimate_sim3d`` (COLMAP's
``EstimateSim3d``) for Sim(3) and ``pycolmap.estimate_rigid3d`` (``EstimateRigid3d``) for SE(3), both
Eigen's ``umeyama``. COLMAP refuses point sets whose *uncentred* 3xN matrix has rank < 3, which includes
any trajectory lying exactly in a plane through the origin (a synthetic path at z = 0); for those the same
closed form is evaluated here in numpy. Point sets that are degenerate for Umeyama itself (all centres on a
line or at one point) raise :class:`AlignmentError`, as evo does.

The kinds match evo's flags: ``"sim3"`` = ``-as``, ``"se3"`` = ``-a``, ``"scale"`` = ``-s`` (the scale of
the Sim(3) fit, no rotation or translation), ``"none"`` = no flag.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ..errors import ConfigError, SlamkitError
from ..kernels.geometry import rotation_angle_deg
from ..types import Trajectory

__all__ = ["ALIGN_KINDS", "Alignment", "AlignmentError", "estimate_alignment"]

ALIGN_KINDS = ("sim3", "se3", "scale", "none")


class AlignmentError(SlamkitError):
    """The positions cannot be aligned: fewer than 3, non-finite, or all on one line or point."""


@dataclass(frozen=True, eq=False)
class Alignment:
    """The similarity ``x_gt = scale * rotation @ x_est + translation`` (gt_from_est).

    ``rotation`` (3, 3), ``translation`` (3,) metres of the ground truth, ``scale`` > 0 (metres of the
    ground truth per unit of the estimate), ``kind`` one of ``ALIGN_KINDS``.
    """

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0
    kind: str = "none"

    def __post_init__(self) -> None:
        object.__setattr__(self, "rotation", np.array(self.rotation, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "translation", np.array(self.translation, dtype=np.float64).reshape(3))
        object.__setattr__(self, "scale", float(self.scale))

    def __repr__(self) -> str:
        angle = rotation_angle_deg(self.rotation)
        return (f"Alignment(kind={self.kind!r}, scale={self.scale:.6g}, rotation={angle:.4g} deg, "
                f"translation={np.array2string(self.translation, precision=4)})")

    def matrix(self) -> np.ndarray:
        """(4, 4) Sim(3) matrix ``[[s R, t], [0, 1]]`` (evo's ``alignment_transformation_sim3``)."""
        T = np.eye(4)
        T[:3, :3] = self.scale * self.rotation
        T[:3, 3] = self.translation
        return T

    def apply_to_points(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points in the estimate's frame -> (N, 3) in the ground truth's frame."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self.scale * (p @ self.rotation.T) + self.translation

    def apply_to_poses(self, poses: np.ndarray) -> np.ndarray:
        """(N, 4, 4) camera-to-world poses -> new (N, 4, 4) poses in the ground truth's frame.

        The camera centre is mapped like a point (scaled, rotated, translated) and the camera orientation
        is rotated, so the result is again rigid: ``[[R_a R_i, s R_a t_i + t_a], [0, 1]]``.
        """
        P = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        out = np.zeros_like(P)
        out[:, :3, :3] = np.einsum("ij,njk->nik", self.rotation, P[:, :3, :3])
        out[:, :3, 3] = self.apply_to_points(P[:, :3, 3])
        out[:, 3, 3] = 1.0
        return out

    def apply(self, traj: Trajectory) -> Trajectory:
        """A new Trajectory with the same timestamps and aligned poses (``traj`` is not changed)."""
        return Trajectory(traj.timestamps.copy(), self.apply_to_poses(traj.poses))

    def to_dict(self) -> dict:
        """JSON-serialisable form."""
        return {"kind": self.kind, "scale": self.scale, "rotation": self.rotation.tolist(),
                "translation": self.translation.tolist()}


def _umeyama(src: np.ndarray, tgt: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Umeyama's closed form (eqs. 34-43), for the point sets COLMAP's rank test turns away."""
    n = len(src)
    mu_s, mu_t = src.mean(axis=0), tgt.mean(axis=0)
    xs, xt = src - mu_s, tgt - mu_t
    var_s = float((xs**2).sum()) / n
    U, d, Vt = np.linalg.svd(xt.T @ xs / n)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    c = float(np.trace(np.diag(d) @ S)) / var_s if with_scale else 1.0
    return R, mu_t - c * (R @ mu_s), c


def _check_spread(points: np.ndarray, what: str) -> None:
    centred = points - points.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if not sv[0] > 0 or sv[1] <= 1e-9 * sv[0]:
        shape = "all at one point" if not sv[0] > 0 else "all on one line"
        raise AlignmentError(f"cannot align: the {what} positions are {shape}; Umeyama's rotation is undefined")


def estimate_alignment(est_positions: np.ndarray, gt_positions: np.ndarray, kind: str = "sim3") -> Alignment:
    """Least-squares alignment of (N, 3) estimate positions onto (N, 3) ground-truth positions (metres).

    ``kind``: "sim3" (rotation, translation, scale), "se3" (rotation, translation), "scale" (scale of the
    Sim(3) fit only), "none" (identity). Row i of both arrays must be the same instant (see ``associate``).
    Raises ConfigError for an unknown kind and AlignmentError for fewer than 3 or degenerate positions.
    """
    if kind not in ALIGN_KINDS:
        raise ConfigError(f"align: {kind!r} is not one of {', '.join(ALIGN_KINDS)}")
    src = np.asarray(est_positions, dtype=np.float64).reshape(-1, 3)
    tgt = np.asarray(gt_positions, dtype=np.float64).reshape(-1, 3)
    if len(src) != len(tgt):
        raise ValueError(f"{len(src)} estimate positions but {len(tgt)} ground-truth positions")
    if kind == "none":
        return Alignment(kind="none")
    if len(src) < 3:
        raise AlignmentError(f"cannot align {len(src)} positions: need at least 3")
    if not (np.isfinite(src).all() and np.isfinite(tgt).all()):
        raise AlignmentError("cannot align: positions contain non-finite values")
    with_scale = kind in ("sim3", "scale")
    fit = pycolmap.estimate_sim3d(src, tgt) if with_scale else pycolmap.estimate_rigid3d(src, tgt)
    if fit is not None:
        R = np.asarray(fit.rotation.matrix(), dtype=np.float64)
        t = np.asarray(fit.translation, dtype=np.float64)
        s = float(fit.scale) if with_scale else 1.0
    else:
        _check_spread(src, "estimate")
        _check_spread(tgt, "ground-truth")
        R, t, s = _umeyama(src, tgt, with_scale)
    if not (np.isfinite(R).all() and np.isfinite(t).all() and np.isfinite(s) and s > 0):
        raise AlignmentError("cannot align: the Umeyama fit is not finite (degenerate positions)")
    if kind == "scale":
        return Alignment(scale=s, kind="scale")
    return Alignment(R, t, s, kind)
