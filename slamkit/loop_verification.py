"""Loop candidate verification: a robust Sim(3) between the query keyframe's map points and the candidate's.

A place-recognition candidate is only a hint. It becomes a loop when the map points seen by the query
keyframe (in the current, drifted map) and those seen by the candidate keyframe (in the older part of the
map) match by descriptor and a similarity explains enough of those matches: ``candidate_world_from_query
_world``, the drift accumulated around the loop (rotation, translation and, monocular, scale). The Sim(3) is
COLMAP's LO-RANSAC ``pycolmap.estimate_sim3d_robust`` on 3D-3D correspondences; ORB-SLAM's equivalent is its
``Sim3Solver`` (Horn's closed form in RANSAC) followed by ``OptimizeSim3``.

Expected outcomes (too few matches, no model, too few inliers, low inlier ratio, implausible scale) are a
:class:`LoopStatus` in the frozen :class:`LoopVerification`; exceptions only for bad input.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Collection, Mapping, Sequence

import numpy as np
import pycolmap

from .errors import ConfigError, native_seed
from .features import MatchingConfig, match_descriptors
from .kernels.sim3 import CHI2_2DOF, project, ransac_sim3, refine_sim3, reprojection_inliers
from .pose_graph import sim3_from_pycolmap

__all__ = ["CHI2_2DOF", "ConsistentGroup", "LoopStatus", "LoopVerification", "LoopVerificationConfig",
           "match_map_points", "project", "refine_sim3", "reprojection_inliers", "update_consistent_groups",
           "verify_loop", "verify_loop_by_reprojection", "verify_loop_candidate"]


class LoopStatus(str, enum.Enum):
    """Why a loop candidate was accepted or rejected."""

    ACCEPTED = "accepted"
    TOO_FEW_MATCHES = "too few matches"
    NO_MODEL = "no Sim(3) found"
    TOO_FEW_INLIERS = "too few inliers"
    LOW_INLIER_RATIO = "low inlier ratio"
    IMPLAUSIBLE_SCALE = "implausible scale"


@dataclass(frozen=True)
class LoopVerificationConfig:
    """Thresholds of :func:`verify_loop`."""

    min_matches: int = 20
    """Fewest 3D-3D correspondences worth a RANSAC."""
    min_inliers: int = 20
    """Fewest correspondences the Sim(3) must explain (ORB-SLAM asks 20 for its Sim3Solver)."""
    min_inlier_ratio: float = 0.3
    """Smallest fraction of the correspondences that must be inliers."""
    max_error: float | None = None
    """Inlier threshold on the 3D distance in the candidate's map units (metres in a metric map); None: use
    ``relative_error``, as monocular maps have an arbitrary unit."""
    relative_error: float = 0.02
    """Inlier threshold as a fraction of the spread of the candidate's points (median distance to their
    median) when ``max_error`` is None."""
    scale_range: tuple[float, float] = (0.2, 5.0)
    """Plausible scales of the Sim(3) (monocular scale drift of one loop stays well inside)."""
    random_seed: int = 0
    """Seed of the RANSAC sampling (-1: random); a fixed seed gives repeatable decisions."""
    max_trials: int = 100_000
    """Most RANSAC iterations (pycolmap's default; ORB-SLAM's Sim3Solver stops at 300): a wrong candidate,
    with few inliers, runs them all, so this bounds the cost of rejecting it."""

    def __post_init__(self) -> None:
        if self.min_matches < 3 or self.min_inliers < 3:
            raise ConfigError("LoopVerificationConfig: min_matches and min_inliers must be >= 3 (a Sim(3) needs 3)")
        if not 0 <= self.min_inlier_ratio <= 1:
            raise ConfigError(f"LoopVerificationConfig.min_inlier_ratio must be in [0, 1] "
                              f"(got {self.min_inlier_ratio})")
        if self.max_error is not None and not self.max_error > 0:
            raise ConfigError(f"LoopVerificationConfig.max_error must be > 0 or None (got {self.max_error})")
        if self.max_trials < 1:
            raise ConfigError(f"LoopVerificationConfig.max_trials must be >= 1 (got {self.max_trials})")
        if not self.relative_error > 0:
            raise ConfigError(f"LoopVerificationConfig.relative_error must be > 0 (got {self.relative_error})")
        low, high = self.scale_range
        if not 0 < low <= 1 <= high:
            raise ConfigError(f"LoopVerificationConfig.scale_range must satisfy 0 < low <= 1 <= high "
                              f"(got {self.scale_range})")


@dataclass(frozen=True)
class LoopVerification:
    """Outcome of verifying one loop candidate."""

    status: LoopStatus
    num_matches: int
    """3D-3D correspondences given to RANSAC."""
    num_inliers: int = 0
    inlier_ratio: float = 0.0
    tgt_from_src: np.ndarray | None = field(default=None, repr=False)
    """(4, 4) similarity ``candidate_world_from_query_world`` (None when no model was found)."""
    scale: float = float("nan")
    max_error: float = float("nan")
    """Inlier threshold used (candidate map units)."""
    inlier_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, bool), repr=False)
    """(num_matches,) bool inliers of the Sim(3)."""

    @property
    def accepted(self) -> bool:
        return self.status is LoopStatus.ACCEPTED

    @property
    def reason(self) -> str:
        """One line saying why, e.g. ``too few inliers (12 < 20 of 85 matches)``."""
        return f"{self.status.value} ({self.num_inliers} inliers of {self.num_matches} matches, scale {self.scale:.3g})"


def _points(a: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(a, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ConfigError(f"{name}: expected (N, 3) points, got shape {p.shape}")
    if not np.isfinite(p).all():
        raise ConfigError(f"{name}: points must be finite")
    return p


def verify_loop(query_points: np.ndarray, candidate_points: np.ndarray,
                config: LoopVerificationConfig | None = None) -> LoopVerification:
    """Estimate ``candidate_world_from_query_world`` from paired points and accept or reject the loop.

    query_points: (N, 3) world coordinates (current map) of the query keyframe's matched map points.
    candidate_points: (N, 3) world coordinates of their matches among the candidate's map points (row i
        pairs with row i).
    """
    cfg = config or LoopVerificationConfig()
    src, tgt = _points(query_points, "query_points"), _points(candidate_points, "candidate_points")
    if len(src) != len(tgt):
        raise ConfigError(f"query_points ({len(src)}) and candidate_points ({len(tgt)}) must pair row by row")
    n = len(src)
    if n < cfg.min_matches:
        return LoopVerification(LoopStatus.TOO_FEW_MATCHES, n)
    max_error = cfg.max_error
    if max_error is None:
        spread = float(np.median(np.linalg.norm(tgt - np.median(tgt, axis=0), axis=1)))
        max_error = cfg.relative_error * spread if spread > 0 else 1e-9
    options = pycolmap.RANSACOptions(max_error=max_error, random_seed=native_seed(cfg.random_seed),
                                     max_num_trials=cfg.max_trials, min_num_trials=min(1000, cfg.max_trials))
    found = pycolmap.estimate_sim3d_robust(src, tgt, options)
    if found is None:
        return LoopVerification(LoopStatus.NO_MODEL, n, max_error=max_error)
    sim = found["tgt_from_src"]
    mask = np.asarray(found["inlier_mask"], bool)
    inliers = int(mask.sum())
    ratio = inliers / n
    if inliers < cfg.min_inliers:
        status = LoopStatus.TOO_FEW_INLIERS
    elif ratio < cfg.min_inlier_ratio:
        status = LoopStatus.LOW_INLIER_RATIO
    elif not cfg.scale_range[0] <= sim.scale <= cfg.scale_range[1]:
        status = LoopStatus.IMPLAUSIBLE_SCALE
    else:
        status = LoopStatus.ACCEPTED
    return LoopVerification(status, n, inliers, ratio, sim3_from_pycolmap(sim), float(sim.scale), max_error, mask)


def match_map_points(query_descriptors: np.ndarray, candidate_descriptors: np.ndarray, binary: bool,
                     matching: MatchingConfig | None = None) -> np.ndarray:
    """(M, 2) int64 pairs (query point index, candidate point index) by descriptor (ratio test, mutual).

    Descriptors are one per map point, (N, D) each: e.g. the point's representative descriptor (ORB-SLAM
    keeps the median one) or the descriptor of the keyframe's observation.
    """
    q, c = np.asarray(query_descriptors), np.asarray(candidate_descriptors)
    if q.ndim != 2 or c.ndim != 2 or (len(q) and len(c) and q.shape[1] != c.shape[1]):
        raise ConfigError(f"descriptors: (N, D) arrays of the same D expected, got {q.shape} and {c.shape}")
    return match_descriptors(q, c, binary, matching or MatchingConfig())


def verify_loop_candidate(query_points: np.ndarray, query_descriptors: np.ndarray, candidate_points: np.ndarray,
                          candidate_descriptors: np.ndarray, binary: bool,
                          config: LoopVerificationConfig | None = None,
                          matching: MatchingConfig | None = None) -> tuple[LoopVerification, np.ndarray]:
    """Match the two keyframes' map points by descriptor, then :func:`verify_loop`.

    query_points (N, 3) / query_descriptors (N, D): map points of the query keyframe (current map).
    candidate_points (M, 3) / candidate_descriptors (M, D): map points of the candidate (and, as ORB-SLAM
        does, of its covisible keyframes). Returns the verification and the (K, 2) matched index pairs (its
        ``inlier_mask`` refers to these rows).
    """
    qp, cp = _points(query_points, "query_points"), _points(candidate_points, "candidate_points")
    if len(qp) != len(query_descriptors) or len(cp) != len(candidate_descriptors):
        raise ConfigError("points and descriptors must have one row per map point")
    pairs = match_map_points(query_descriptors, candidate_descriptors, binary, matching)
    return verify_loop(qp[pairs[:, 0]], cp[pairs[:, 1]], config), pairs


def verify_loop_by_reprojection(K: np.ndarray, src_points: np.ndarray, src_cam_from_world: np.ndarray,
                                src_xy: np.ndarray, src_scales: np.ndarray, tgt_points: np.ndarray,
                                tgt_cam_from_world: np.ndarray, tgt_xy: np.ndarray, tgt_scales: np.ndarray,
                                config: LoopVerificationConfig | None = None, chi2: float = CHI2_2DOF,
                                confidence: float = 0.99) -> LoopVerification:
    """ORB-SLAM's ``Sim3Solver`` and ``OptimizeSim3``: RANSAC over minimal sets of three matched pairs (Horn's
    closed form), every hypothesis scored by the pairs that reproject through it in *both* keyframes (the
    chi-square bound at the keypoint's scale, :func:`reprojection_inliers`), the best refined by reprojection
    (:func:`refine_sim3`); then the thresholds of :func:`verify_loop` on its inliers. Arguments as
    :func:`reprojection_inliers`, pair i in row i.

    A RANSAC on 3D distances (:func:`verify_loop`) scores a far point's depth error, metres along its ray, as
    a wrong match: on a street of facades 10-40 m away, the right loop of the city block kept 4-29 % of 125-660
    matches within 2 % of the points' spread and was refused for 130 keyframes, while 94-97 % of the same
    matches reproject through the refined Sim(3) (benchmarks/HISTORY.md, "the city block's third seed").
    Trials stop at ``config.max_trials`` or once ``confidence`` that a set of three inliers was drawn."""
    cfg = config or LoopVerificationConfig()
    sp, tp = _points(src_points, "src_points"), _points(tgt_points, "tgt_points")
    n = len(sp)
    if len(tp) != n:
        raise ConfigError(f"src_points ({n}) and tgt_points ({len(tp)}) must pair row by row")
    if n < max(cfg.min_matches, 3):
        return LoopVerification(LoopStatus.TOO_FEW_MATCHES, n)
    Tq = np.asarray(src_cam_from_world, np.float64)
    Tc = np.asarray(tgt_cam_from_world, np.float64)
    Tc = np.ascontiguousarray(np.broadcast_to(Tc, (n, 4, 4)) if Tc.ndim == 2 else Tc)
    xq, xc = np.ascontiguousarray(src_xy, np.float64), np.ascontiguousarray(tgt_xy, np.float64)
    bq, bc = chi2 * np.asarray(src_scales, np.float64) ** 2, chi2 * np.asarray(tgt_scales, np.float64) ** 2
    best = ransac_sim3(K, sp, Tq, xq, bq, tp, Tc, xc, bc, cfg.max_trials, cfg.random_seed, confidence)
    best_count = 0 if best is None else int(best[1].sum())
    if best is None or best_count < 3:
        return LoopVerification(LoopStatus.NO_MODEL, n, max_error=float("nan"))
    if best_count < cfg.min_inliers:  # as the Sim3Solver: no refinement of a hypothesis this weak
        return LoopVerification(LoopStatus.TOO_FEW_INLIERS, n, best_count, best_count / n, best[0],
                                float(np.cbrt(np.linalg.det(best[0][:3, :3]))), float("nan"), best[1])
    S, mask = refine_sim3(best[0], K, sp, Tq, xq, src_scales, tp, Tc, xc, tgt_scales, initial_inliers=best[1],
                          chi2=chi2)
    inliers = int(mask.sum())
    scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
    if inliers < cfg.min_inliers:
        status = LoopStatus.TOO_FEW_INLIERS
    elif inliers / n < cfg.min_inlier_ratio:
        status = LoopStatus.LOW_INLIER_RATIO
    elif not cfg.scale_range[0] <= scale <= cfg.scale_range[1]:
        status = LoopStatus.IMPLAUSIBLE_SCALE
    else:
        status = LoopStatus.ACCEPTED
    return LoopVerification(status, n, inliers, inliers / n, S, scale, float("nan"), mask)


# ------------------------------------------------------------------------------------------------------
# temporal consistency of candidates (ORB-SLAM's covisibility-consistency check)


@dataclass(frozen=True)
class ConsistentGroup:
    """A candidate keyframe with its covisible keyframes, and for how many successive query keyframes a
    candidate group sharing a keyframe with it was found."""

    keyframes: frozenset[int]
    consistency: int


def update_consistent_groups(previous: Sequence[ConsistentGroup], candidate_groups: Mapping[int, Collection[int]],
                             min_consistency: int = 3) -> tuple[tuple[ConsistentGroup, ...], list[int]]:
    """One step of ORB-SLAM's loop-candidate consistency check (``LoopClosing::DetectLoop``).

    previous: the groups returned for the previous query keyframe (empty at first, and after a loop closure).
    candidate_groups: candidate keyframe id -> its covisible keyframe ids (the candidate itself is added),
        for the place-recognition candidates of the current query keyframe.
    min_consistency: a candidate passes once its group chains with groups of ``min_consistency`` previous
        query keyframes (ORB-SLAM: 3, so a place must be recognised by four successive keyframes).
    Returns (the groups to pass at the next query, candidates consistent enough, in the given order). A query
    without candidates returns no groups: consistency must be uninterrupted.
    """
    if int(min_consistency) != min_consistency or min_consistency < 0:
        raise ConfigError(f"min_consistency must be a non-negative integer (got {min_consistency!r})")
    current: list[ConsistentGroup] = []
    extended = [False] * len(previous)
    enough: list[int] = []
    for candidate, covisible in candidate_groups.items():
        group = frozenset(int(k) for k in covisible) | {int(candidate)}
        linked = False
        for g, prev in enumerate(previous):
            if not group & prev.keyframes:
                continue
            linked = True
            consistency = prev.consistency + 1
            if not extended[g]:
                current.append(ConsistentGroup(group, consistency))
                extended[g] = True
            if consistency >= min_consistency and int(candidate) not in enough:
                enough.append(int(candidate))
        if not linked:
            current.append(ConsistentGroup(group, 0))
    return tuple(current), enough
