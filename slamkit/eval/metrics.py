"""Trajectory error metrics: absolute trajectory error (ATE) and relative pose error (RPE).

Conventions are evo's (``evo_ape`` / ``evo_rpe``, evo 1.38), so the numbers agree with
``evo_ape tum GT EST -as --t_max_diff DT`` and ``evo_rpe tum GT EST -as --t_max_diff DT``:

1. associate estimate and ground-truth timestamps (:func:`~slamkit.eval.associate.associate`);
2. fit the alignment on the matched camera centres only and apply it to the matched estimate poses
   (:func:`~slamkit.eval.align.estimate_alignment`);
3. ATE (evo's APE w.r.t. the translation part): per matched frame ``|p_est,aligned - p_gt|`` in metres;
   beside it the rotation error (evo's APE with ``--pose_relation angle_deg``): the angle of
   ``R_est,aligned^T R_gt`` in degrees. An estimate whose centres are all one point (a run posed by rotation
   only, ``state.ROTATION_ONLY``) has no position to align nor to compare: its orientations are aligned by the
   rotation nearest to ``sum_i R_gt,i R_est,i^T`` (the chordal L2 mean, SO(3)'s analogue of Umeyama's rotation;
   ``Alignment.kind`` "rotation"), the rotation error is reported and the ATE is undefined (NaN statistics,
   ``AteResult.undefined`` says why) rather than a distance to the mean of the ground truth;
   when the positions do not fix the position fit's rotation (a nearly straight path, or few and noisy centres:
   :func:`rotation_fit_se_deg` above :data:`MAX_ROTATION_FIT_SE_DEG` and a quarter of the orientation error),
   evo's angle depends on an arbitrary turn about the path, so beside it the orientation error after aligning
   rotations alone (the chordal L2 mean above) is reported as the meaningful figure (``AteResult.rotation_free``
   says why; :func:`ate_line` shows it);
4. RPE on the aligned matched poses, for pairs ``(i, j)`` of matched frames chosen on the estimate: with
   ``Q`` ground truth and ``P`` estimate, ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``; the translation error is
   ``|t(E)|`` (metres), the rotation error the angle of ``R(E)`` (degrees). Pairs for ``unit="frames"``
   are ``(0, d), (d, 2d), ...`` (evo's consecutive pairs), with ``all_pairs=True`` every ``(i, i + d)``;
   for ``unit="m"`` a pair closes each time the estimate's path length since its start reaches ``delta``
   metres (evo's ``--delta_unit m``).

Statistics are evo's: rmse, mean, median, std (population), min, max, sse.
"""

from __future__ import annotations

import numbers
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import AssociationError, ConfigError, check_type
from ..kernels.geometry import invert_pose, rotation_angle_deg
from ..types import Trajectory
from .align import Alignment, estimate_alignment
from .associate import associate
from .pairing import load_pair

__all__ = ["ROTATION_ONLY_ATE", "MAX_ROTATION_FIT_SE_DEG", "rotation_fit_se_deg", "ErrorStats", "AteResult",
           "RpeResult", "ate", "ate_line", "rpe", "evaluate", "matched_warning", "MIN_MATCHED",
           "MIN_MATCHED_FRACTION"]

#: fewer matched poses than this raise AssociationError (Umeyama needs 3)
MIN_MATCHED = 3
#: evo's default relative tolerance of ``delta`` for all-pairs RPE in metres
RPE_REL_DELTA_TOL = 0.1
#: ``AteResult.undefined`` of an estimate posed by rotation only (every camera centre at one point)
ROTATION_ONLY_ATE = "ATE undefined: rotation only"
#: degrees: the position fit leaves its rotation free (evo's angle after it is then arbitrary) when the standard
#: error of that rotation about its weakest axis, :func:`rotation_fit_se_deg`, exceeds this and
#: :data:`MAX_ROTATION_FIT_SE_FRACTION` of the orientation error's RMSE (after aligning orientations alone)
MAX_ROTATION_FIT_SE_DEG = 0.1
#: below this fraction of the orientation error the fit's freedom adds at most 3 % to evo's angle (in quadrature)
MAX_ROTATION_FIT_SE_FRACTION = 0.25
_UNITS = {"frames": "frames", "f": "frames", "m": "m", "meters": "m", "metres": "m"}


@dataclass(frozen=True)
class ErrorStats:
    """Summary of an error array (units of the errors), as evo's ``get_all_statistics``."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    count: int

    @classmethod
    def from_errors(cls, errors: np.ndarray) -> "ErrorStats":
        e = np.asarray(errors, dtype=np.float64).reshape(-1)
        if len(e) == 0:
            nan = float("nan")
            return cls(nan, nan, nan, nan, nan, nan, 0.0, 0)
        sq = e**2
        return cls(rmse=float(np.sqrt(np.mean(sq))), mean=float(np.mean(e)), median=float(np.median(e)),
                   std=float(np.std(e)), min=float(np.min(e)), max=float(np.max(e)), sse=float(np.sum(sq)),
                   count=len(e))

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("rmse", "mean", "median", "std", "min", "max", "sse", "count")}


@dataclass(frozen=True, eq=False)
class AteResult:
    """Absolute trajectory error after alignment.

    ``errors`` (K,) metres per matched frame, at ``timestamps`` (K,) (the estimate's) and
    ``gt_timestamps`` (K,); ``idx_gt``/``idx_est`` (K,) the matched indices into the inputs.
    ``est_matched_fraction`` = K / estimate poses; ``gt_matched_fraction`` = distinct ground-truth poses
    matched / ground-truth poses (low by design when the ground truth is denser, e.g. TUM's 100 Hz
    motion capture against 30 Hz images); ``gt_time_coverage`` = time spanned by the matched frames /
    time spanned by the ground truth (``gt_span``, first and last ground-truth timestamp).
    """

    stats: ErrorStats
    errors: np.ndarray
    timestamps: np.ndarray
    gt_timestamps: np.ndarray
    idx_gt: np.ndarray
    idx_est: np.ndarray
    n_est: int
    n_gt: int
    alignment: Alignment
    max_dt: float
    offset: float
    gt_span: tuple[float, float]
    rotation_errors_deg: np.ndarray = None
    """(K,) degrees per matched frame: the angle of ``R_est,aligned^T R_gt`` (evo_ape ``--pose_relation angle_deg``)."""
    undefined: str = ""
    """Why the position error means nothing ("" when it does): :data:`ROTATION_ONLY_ATE`; its stats are then NaN."""
    oriented_rotation_errors_deg: np.ndarray = None
    """(K,) degrees per matched frame after aligning the orientations alone (the rotation nearest to
    ``sum_i R_gt,i R_est,i^T``): the meaningful rotation error when the positions leave the fit's rotation free."""
    rotation_fit_se_deg: float = 0.0
    """Degrees: the standard error of the position fit's rotation about its weakest axis (:func:`rotation_fit_se_deg`;
    0 for an alignment that fits no rotation to the positions)."""
    rotation_free: str = ""
    """Why evo's angle after the position fit is arbitrary ("" when the positions fix the fit's rotation)."""

    rmse = property(lambda self: self.stats.rmse, doc="metres")
    mean = property(lambda self: self.stats.mean, doc="metres")
    median = property(lambda self: self.stats.median, doc="metres")
    std = property(lambda self: self.stats.std, doc="metres")
    min = property(lambda self: self.stats.min, doc="metres")
    max = property(lambda self: self.stats.max, doc="metres")

    @property
    def rotation(self) -> ErrorStats:
        """Statistics of ``rotation_errors_deg`` (degrees)."""
        return ErrorStats.from_errors(self.rotation_errors_deg)

    @property
    def oriented_rotation(self) -> ErrorStats:
        """Statistics of ``oriented_rotation_errors_deg`` (degrees): orientations aligned alone."""
        return ErrorStats.from_errors(self.oriented_rotation_errors_deg)

    @property
    def meaningful_rotation(self) -> ErrorStats:
        """The rotation error to show (degrees): ``oriented_rotation`` when ``rotation_free``, else ``rotation``
        (evo_ape's angle after the position fit)."""
        return self.oriented_rotation if self.rotation_free else self.rotation

    @property
    def n_matched(self) -> int:
        return len(self.idx_est)

    @property
    def est_matched_fraction(self) -> float:
        return self.n_matched / self.n_est if self.n_est else 0.0

    @property
    def gt_matched_fraction(self) -> float:
        return len(np.unique(self.idx_gt)) / self.n_gt if self.n_gt else 0.0

    @property
    def gt_time_coverage(self) -> float:
        return _time_coverage(self.gt_timestamps, self.gt_span)

    def __repr__(self) -> str:
        return (f"AteResult(rmse={self.rmse:.6g} m, mean={self.mean:.6g} m, max={self.max:.6g} m, "
                f"matched={self.n_matched}/{self.n_est} estimate poses, {self.n_gt} ground-truth poses, "
                f"align={self.alignment.kind}, scale={self.alignment.scale:.6g})")

    def describe(self, unit: str = "m") -> str:
        """A short multi-line summary for people, every length in ``unit`` ("m", "cm" or "mm")."""
        k = {"m": 1.0, "cm": 100.0, "mm": 1000.0}.get(unit)
        if k is None:
            raise ValueError(f"unit must be 'm', 'cm' or 'mm' (got {unit!r})")
        kind = {"sim3": "Sim(3)", "se3": "SE(3)"}.get(self.alignment.kind, self.alignment.kind)
        rot = self.rotation
        if self.undefined:
            return (f"{self.undefined}; rotation error after aligning the orientations: RMSE {rot.rmse:.3g} deg, "
                    f"max {rot.max:.3g} deg\n  over {self.n_matched} of {self.n_est} estimated poses")
        rot_text = (f"rotation RMSE {self.oriented_rotation.rmse:.3g} deg after aligning orientations: "
                    f"{self.rotation_free}" if self.rotation_free else f"rotation RMSE {rot.rmse:.3g} deg")
        return (f"ATE after {kind} alignment (scale {self.alignment.scale:.4g}):\n"
                f"  RMSE {k * self.rmse:.3g} {unit}, mean {k * self.mean:.3g} {unit}, median {k * self.median:.3g} "
                f"{unit}, max {k * self.max:.3g} {unit}; {rot_text}\n"
                f"  over {self.n_matched} of {self.n_est} estimated poses ({self.n_gt} ground-truth poses)")

    def rotation_dict(self) -> dict:
        """The rotation error's part of :meth:`to_dict`: ``rotation_deg`` (evo_ape's angle after the position fit),
        ``rotation_oriented_deg`` (after aligning orientations alone), ``rotation_fit_se_deg`` and
        ``rotation_free`` (why the first is arbitrary, "" when it is not)."""
        return {"rotation_deg": self.rotation.to_dict(), "rotation_oriented_deg": self.oriented_rotation.to_dict(),
                "rotation_fit_se_deg": self.rotation_fit_se_deg, "rotation_free": self.rotation_free}

    def to_dict(self) -> dict:
        """JSON-serialisable summary (no per-frame arrays); the rotation keys are :meth:`rotation_dict`'s."""
        return {**self.stats.to_dict(), **self.rotation_dict(), "undefined": self.undefined,
                "matched": self.n_matched, "estimate_poses": self.n_est,
                "ground_truth_poses": self.n_gt, "estimate_matched_fraction": self.est_matched_fraction,
                "ground_truth_matched_fraction": self.gt_matched_fraction,
                "ground_truth_time_coverage": self.gt_time_coverage, "alignment": self.alignment.to_dict(),
                "max_dt": self.max_dt, "offset": self.offset}


@dataclass(frozen=True, eq=False)
class RpeResult:
    """Relative pose error over pairs of matched frames.

    ``translation`` stats in metres, ``rotation`` stats in degrees; per pair ``translation_errors`` (P,),
    ``rotation_errors_deg`` (P,), ``pairs`` (P, 2) indices into the matched frames, ``timestamps`` (P,) the
    estimate's timestamp of each pair's second frame (as evo's result).
    """

    translation: ErrorStats
    rotation: ErrorStats
    translation_errors: np.ndarray
    rotation_errors_deg: np.ndarray
    pairs: np.ndarray
    timestamps: np.ndarray
    delta: float
    unit: str
    all_pairs: bool
    n_matched: int
    alignment: Alignment

    @property
    def n_pairs(self) -> int:
        return len(self.pairs)

    def __repr__(self) -> str:
        return (f"RpeResult(translation rmse={self.translation.rmse:.6g} m, rotation rmse="
                f"{self.rotation.rmse:.6g} deg, {self.n_pairs} pairs, delta={self.delta} {self.unit}, "
                f"align={self.alignment.kind})")

    def to_dict(self) -> dict:
        """JSON-serialisable summary (no per-pair arrays)."""
        return {"delta": self.delta, "unit": self.unit, "all_pairs": self.all_pairs, "pairs": self.n_pairs,
                "translation": self.translation.to_dict(), "rotation_deg": self.rotation.to_dict()}


# ------------------------------------------------------------------------------------------- internals

@dataclass(frozen=True, eq=False)
class _Matched:
    gt: Trajectory            # matched ground-truth poses
    est: Trajectory           # matched estimate poses, aligned
    idx_gt: np.ndarray
    idx_est: np.ndarray
    alignment: Alignment
    n_gt: int
    n_est: int
    gt_span: tuple[float, float]
    max_dt: float
    offset: float


def _span(t: np.ndarray) -> str:
    return f"[{t[0]:.6f}, {t[-1]:.6f}] s" if len(t) else "(no poses)"


def _time_coverage(t: np.ndarray, span: tuple[float, float]) -> float:
    if len(t) == 0:
        return 0.0
    total = span[1] - span[0]
    return float(min(1.0, (t[-1] - t[0]) / total)) if total > 0 else 1.0


def _match_and_align(gt: Trajectory, est: Trajectory, align: str, max_dt: float, offset: float) -> _Matched:
    for name, t in (("gt", gt), ("est", est)):
        check_type(t, Trajectory, name, "read a file with slamkit.read_trajectory(path), or use "
                                        "slamkit.evaluate(est_path, gt_path)")
    check_type(max_dt, numbers.Real, "max_dt")
    check_type(offset, numbers.Real, "offset")
    if not max_dt >= 0:
        raise ConfigError(f"max_dt: must be >= 0 seconds, got {max_dt}")
    idx_gt, idx_est = associate(gt.timestamps, est.timestamps, max_dt, offset)
    if len(idx_est) < MIN_MATCHED:
        raise AssociationError(
            f"only {len(idx_est)} estimate poses matched ground truth within max_dt={max_dt} s "
            f"(offset {offset} s), need at least {MIN_MATCHED}: estimate has {len(est)} poses over "
            f"{_span(est.timestamps)}, ground truth {len(gt)} poses over {_span(gt.timestamps)}")
    gt_m, est_m = gt.subset(idx_gt), est.subset(idx_est)
    if align != "none" and is_rotation_only(est_m.positions):
        alignment = rotation_alignment(est_m, gt_m)
    else:
        alignment = estimate_alignment(est_m.positions, gt_m.positions, align)
    span = (float(gt.timestamps[0]), float(gt.timestamps[-1]))
    return _Matched(gt_m, alignment.apply(est_m), idx_gt, idx_est, alignment, len(gt), len(est), span,
                    float(max_dt), float(offset))


def is_rotation_only(positions: np.ndarray) -> bool:
    """Whether (N, 3) camera centres are all one point (to 1e-9 of their magnitude, at least 1e-9 units)."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    return len(p) > 0 and float(np.ptp(p, axis=0).max()) <= 1e-9 * max(1.0, float(np.abs(p).max()))


def rotation_alignment(est: Trajectory, gt: Trajectory) -> Alignment:
    """The alignment of a rotation-only estimate onto ground truth (matched rows): the rotation R nearest to
    ``sum_i R_gt,i R_est,i^T`` (minimising ``sum_i |R R_est,i - R_gt,i|_F^2``), the estimate's centre moved onto
    the ground truth's mean centre, scale 1 (a rotation has none). ``kind`` "rotation"."""
    M = np.einsum("nij,nkj->ik", gt.poses[:, :3, :3], est.poses[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    return Alignment(R, gt.positions.mean(axis=0) - R @ est.positions.mean(axis=0), 1.0, "rotation")


def rotation_fit_se_deg(positions: np.ndarray, residuals: np.ndarray, params: int = 7) -> float:
    """Degrees: the standard error of a position fit's rotation about its weakest axis.

    ``positions`` (N, 3) the aligned camera centres (metres of the ground truth), ``residuals`` (N, 3) their
    position errors after the fit (metres), ``params`` the fit's parameters (7 for Sim(3), 6 for SE(3)).
    Linearising Umeyama's least squares about the fitted rotation, a small turn ``w`` (radians) moves centre i by
    ``w x c_i`` (``c_i`` centred), so the information on ``w`` is the centres' inertia tensor
    ``sum_i |c_i|^2 I - c_i c_i^T`` (m^2), whose smallest eigenvalue is ``s2^2 + s3^2``, the two smaller singular
    values of the centred positions (their spread across the path's main axis). With the residual variance per
    coordinate ``sigma^2 = SSE / (3N - params)`` (m^2; the denominator counts what few frames leave to the
    residuals) the standard error of the turn about that axis is ``sigma / sqrt(s2^2 + s3^2)``. A nearly straight
    path (s2, s3 small against s1) or few, noisy centres make it large: the positions then leave the turn
    about the path to noise, and evo's angle after the fit with it. ``inf`` when the centres are on one line.
    """
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(residuals, dtype=np.float64).reshape(-1, 3)
    sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    info = float(sv[1] ** 2 + sv[2] ** 2)
    dof = 3 * len(p) - params
    sigma2 = float((r**2).sum()) / max(dof, 1)
    if not info > 0:
        return float("inf")
    return float(np.degrees(np.sqrt(sigma2 / info)))


def _rotation_free_reason(positions: np.ndarray, se_deg: float) -> str:
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    why = ("the path is nearly straight" if not sv[1] > 0.2 * sv[0] else
           f"{len(p)} camera centres this noisy are too few")
    return f"{why}, so the position fit leaves its rotation free (±{se_deg:.2g} deg)"


def _oriented_errors_deg(est: Trajectory, gt: Trajectory) -> np.ndarray:
    """(K,) degrees: the angle of ``(R R_est,i)^T R_gt,i`` with R the rotation nearest to ``sum_i R_gt,i R_est,i^T``
    (orientations aligned alone; the same for the raw and the position-aligned estimate)."""
    aligned = np.einsum("ij,njk->nik", rotation_alignment(est, gt).rotation, est.poses[:, :3, :3])
    return np.atleast_1d(rotation_angle_deg(np.einsum("nji,njk->nik", aligned, gt.poses[:, :3, :3])))


def _ate(m: _Matched) -> AteResult:
    rot = rotation_angle_deg(np.einsum("nji,njk->nik", m.est.poses[:, :3, :3], m.gt.poses[:, :3, :3]))
    undefined = ROTATION_ONLY_ATE if m.alignment.kind == "rotation" else ""
    errors = np.linalg.norm(m.est.positions - m.gt.positions, axis=1)
    oriented = _oriented_errors_deg(m.est, m.gt)
    se, free = 0.0, ""
    if m.alignment.kind in ("sim3", "se3"):
        se = rotation_fit_se_deg(m.est.positions, m.est.positions - m.gt.positions,
                                 7 if m.alignment.kind == "sim3" else 6)
        bound = max(MAX_ROTATION_FIT_SE_DEG, MAX_ROTATION_FIT_SE_FRACTION * ErrorStats.from_errors(oriented).rmse)
        if not se <= bound:
            free = _rotation_free_reason(m.gt.positions, se)
    stats = ErrorStats.from_errors(errors)
    if undefined:  # a distance to the ground truth's mean centre, not an error: NaN statistics
        stats = ErrorStats(*[float("nan")] * 7, count=len(errors))
    return AteResult(stats, errors, m.est.timestamps.copy(), m.gt.timestamps.copy(),
                     m.idx_gt, m.idx_est, m.n_est, m.n_gt, m.alignment, m.max_dt, m.offset, m.gt_span,
                     np.atleast_1d(rot), undefined, oriented, se, free)


def _pairs_by_frames(n: int, delta: int, all_pairs: bool) -> np.ndarray:
    if all_pairs:
        i = np.arange(max(n - delta, 0))
        return np.stack([i, i + delta], axis=1)
    ids = np.arange(0, n, delta)
    return np.stack([ids[:-1], ids[1:]], axis=1)


def _pairs_by_path(positions: np.ndarray, delta: float, all_pairs: bool) -> np.ndarray:
    """evo's ``filter_pairs_by_path`` (path length along the aligned estimate)."""
    steps = np.linalg.norm(positions[1:] - positions[:-1], axis=1)
    pairs = []
    if all_pairs:
        tol = delta * RPE_REL_DELTA_TOL
        distances = np.concatenate([[0.0], np.cumsum(steps)])
        for i in range(len(distances) - 1):
            from_here = distances[i + 1:] - distances[i]
            k = int(np.argmin(np.abs(from_here - delta)))
            if np.abs(from_here[k] - delta) <= tol:
                pairs.append((i, k + i + 1))
    else:
        start, path = 0, 0.0
        for i, step in enumerate(steps, start=1):
            path += float(step)
            if path >= delta:
                pairs.append((start, i))
                start, path = i, 0.0
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def _rpe(m: _Matched, delta: float, unit: str, all_pairs: bool) -> RpeResult:
    unit_name = _UNITS.get(unit)
    if unit_name is None:
        raise ConfigError(f"unit: {unit!r} is not 'frames' or 'm'")
    n = len(m.est)
    if unit_name == "frames":
        if not (float(delta).is_integer() and delta >= 1):
            raise ConfigError(f"delta: must be a whole number of frames >= 1, got {delta}")
        delta = int(delta)
        pairs = _pairs_by_frames(n, delta, all_pairs)
    else:
        if not delta > 0:
            raise ConfigError(f"delta: must be > 0 metres, got {delta}")
        delta = float(delta)
        pairs = _pairs_by_path(m.est.positions, delta, all_pairs)
    if len(pairs) == 0:
        raise ConfigError(f"delta: {delta} {unit_name} gives no pose pairs among {n} matched poses; "
                          "use a smaller delta")
    i, j = pairs[:, 0], pairs[:, 1]
    Q, P = m.gt.poses, m.est.poses
    Q_rel = invert_pose(Q[i]) @ Q[j]
    P_rel = invert_pose(P[i]) @ P[j]
    E = invert_pose(Q_rel) @ P_rel
    t_err = np.linalg.norm(E[:, :3, 3], axis=1)
    r_err = rotation_angle_deg(E[:, :3, :3])
    return RpeResult(ErrorStats.from_errors(t_err), ErrorStats.from_errors(r_err), t_err, r_err, pairs,
                     m.est.timestamps[j].copy(), delta, unit_name, all_pairs, n, m.alignment)


# ------------------------------------------------------------------------------------------- public API

def ate(gt: Trajectory, est: Trajectory, align: str = "sim3", max_dt: float = 0.02,
        offset: float = 0.0) -> AteResult:
    """Absolute trajectory error of ``est`` against ``gt`` (metres), after ``align``.

    ``align``: "sim3" (default, monocular), "se3", "scale" or "none". ``max_dt``: largest timestamp
    difference (seconds) of a matched pair; ``offset`` seconds added to the estimate's timestamps.
    AssociationError when fewer than 3 poses match (the message gives both time ranges).
    Equal to ``evo_ape tum GT EST -as --t_max_diff MAX_DT`` for ``align="sim3"``.
    """
    return _ate(_match_and_align(gt, est, align, max_dt, offset))


def rpe(gt: Trajectory, est: Trajectory, delta: float = 1, unit: str = "frames", align: str = "sim3",
        max_dt: float = 0.02, offset: float = 0.0, all_pairs: bool = False) -> RpeResult:
    """Relative pose error of ``est`` against ``gt``: translation (metres) and rotation (degrees).

    ``delta`` frames (``unit="frames"``) or metres of the aligned estimate's path (``unit="m"``);
    ``all_pairs`` uses every pair ``(i, i + delta)`` instead of consecutive pairs (evo's ``--all_pairs``).
    Equal to ``evo_rpe tum GT EST -as --t_max_diff MAX_DT --delta DELTA --delta_unit f|m`` (translation;
    rotation with ``--pose_relation angle_deg``).
    """
    return _rpe(_match_and_align(gt, est, align, max_dt, offset), delta, unit, all_pairs)


def ate_line(ate_dict: dict) -> str:
    """One line for people from an ATE dict (``AteResult.to_dict()`` or ``evaluate(...)["ate"]``): the ATE RMSE in
    cm and the rotation error's in degrees, or :data:`ROTATION_ONLY_ATE` with the rotation error alone. When the
    positions leave the fit's rotation free (``rotation_free``) the rotation error shown is the one after aligning
    orientations alone, and the line says why."""
    rot = (ate_dict.get("rotation_deg") or {}).get("rmse")
    rot_text = f"rotation error RMSE {rot:.3f} deg" if rot is not None else ""
    oriented = (ate_dict.get("rotation_oriented_deg") or {}).get("rmse")
    if ate_dict.get("rotation_free") and oriented is not None and not ate_dict.get("undefined"):
        rot_text = f"rotation error RMSE {oriented:.3f} deg after aligning orientations: {ate_dict['rotation_free']}"
    if ate_dict.get("undefined"):
        return f"{ate_dict['undefined']}; {rot_text} (orientations aligned)"
    return f"ATE RMSE {100 * ate_dict['rmse']:.2f} cm" + (f", {rot_text}" if rot_text else "")


MIN_MATCHED_FRACTION = 0.5
"""An evaluation that matches fewer than this fraction of the estimate's poses to ground truth is not a
measure of the run: :func:`matched_warning` says so and ``slamkit eval`` exits with a non-zero code."""


def matched_warning(ate_dict: dict, est_name: str = "the estimate") -> str | None:
    """The warning for an ATE (``AteResult.to_dict()``) that matched fewer than :data:`MIN_MATCHED_FRACTION`
    of the estimate's poses to ground truth, else None."""
    n, m = ate_dict.get("estimate_poses") or 0, ate_dict.get("matched") or 0
    if n and m < MIN_MATCHED_FRACTION * n:
        return (f"only {m} of {n} poses of {est_name} ({100 * m / n:.0f} %) matched ground truth: the ATE is not "
                "a measure of the run (another sequence, another clock, or a --max-dt too small?)")
    return None


def evaluate(est: Trajectory | str | os.PathLike, gt: Trajectory | str | os.PathLike, *, align: str = "sim3",
             max_dt: float = 0.02, offset: float = 0.0, rpe_delta: float = 1, rpe_unit: str = "frames",
             frames=None) -> dict:
    """One-call evaluation for the CLI and notebooks: ATE, RPE and counts as a JSON-serialisable dict.

    ``est`` and ``gt`` are Trajectories or paths of TUM/KITTI files. A KITTI file has no timestamps: it is
    paired by frame index (:func:`slamkit.eval.pairing.load_pair`; ``frames``, a
    :class:`~slamkit.eval.pairing.FrameTable`, defaults to the run folder holding ``est``), never read as
    times 0, 1, 2 s. Keys: ``ate`` (stats in metres), ``rpe`` (``translation`` metres, ``rotation_deg``),
    ``matched``, ``estimate_poses``, ``ground_truth_poses``, the matched fractions, ``alignment``, the
    settings, ``pairing`` ("time", "frame index" or "line"), ``notes`` and ``warnings`` (fewer than half of
    the estimate matched: :func:`matched_warning`). ``ate`` also holds ``rotation_deg`` (the rotation error's
    stats, degrees) and ``undefined`` (:data:`ROTATION_ONLY_ATE` for an estimate posed by rotation only).
    """
    for x, name in ((est, "est"), (gt, "gt")):
        if not isinstance(x, Trajectory):
            check_type(x, (str, os.PathLike), name, "give a Trajectory or the path of a TUM or KITTI file")
    pair = load_pair(est, gt, frames=frames)
    m = _match_and_align(pair.gt, pair.est, align, max_dt, offset)
    a = _ate(m)
    r = _rpe(m, rpe_delta, rpe_unit, False)
    result = {
        "estimate": None if isinstance(est, Trajectory) else str(Path(est)),
        "ground_truth": None if isinstance(gt, Trajectory) else str(Path(gt)),
        "ate": {**a.stats.to_dict(), **a.rotation_dict(), "undefined": a.undefined},
        "rpe": r.to_dict(),
        "matched": a.n_matched,
        "estimate_poses": a.n_est,
        "ground_truth_poses": a.n_gt,
        "estimate_matched_fraction": a.est_matched_fraction,
        "ground_truth_matched_fraction": a.gt_matched_fraction,
        "ground_truth_time_coverage": a.gt_time_coverage,
        "alignment": a.alignment.to_dict(),
        "max_dt": float(max_dt),
        "offset": float(offset),
        "pairing": pair.method,
        "notes": pair.notes,
    }
    warning = matched_warning(result, result["estimate"] or "the estimate")
    result["warnings"] = [warning] if warning else []
    return result
