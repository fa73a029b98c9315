"""Tracking of every frame against the local map: guided matching and absolute pose (ORB-SLAM's
TrackWithMotionModel / TrackReferenceKeyFrame / TrackLocalMap, on pycolmap's estimators).

1. With a predicted pose (constant-velocity model): project the local map points and match each to
   keypoints within ``narrow_search_radius_px``, widened to ``search_radius_px`` when that finds too few
   (SearchByProjection); else brute-force match the frame against the local map descriptors.
2. Absolute pose: with the motion model, its prediction refined on all matches (robust loss) when most of
   them are then inliers (ORB-SLAM's TrackWithMotionModel, no RANSAC); else
   ``pycolmap.estimate_and_refine_absolute_pose`` (LO-RANSAC P3P + refinement).
   When that pose keeps fewer than ``recheck_inlier_ratio`` of the points tracked in the previous frame, the
   frame is matched against the whole local map by descriptor too, and the pose with more inliers wins.
3. Track the local map: project again with the estimated pose, match within ``refine_radius_px`` and
   refine the pose on all inliers (``pycolmap.refine_absolute_pose``, motion-only bundle adjustment);
   repeated (``local_map_rounds``) while the refinement moves the projections.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from ..errors import ConfigError, check_fields, native_seed
from ..kernels.absolute_pose import refine_absolute_pose
from ..features import FrameFeatures, MatchingConfig, guided_match, match_descriptors
from ..local_map import POINT_DESCRIPTORS, LocalMap
from ..map import keypoint_scales, matrix_from_rigid, rigid_from_matrix
from ..pose_optimization import PoseOptimizationConfig, optimize_pose
from ..results import TrackedMatches
from ..state import FrameStatus

POSE_OPTIMIZERS = ("ceres", "compiled", "orb")
"""Motion-only refiners of the local-map tracking (see ``TrackerConfig.pose_optimizer``)."""
_PINHOLES = ("SIMPLE_PINHOLE", "PINHOLE")
"""Camera models the compiled refinement takes (the map's camera; keypoints are undistorted)."""

if TYPE_CHECKING:  # pragma: no cover
    from ..state import Segment, SlamState




@dataclass(frozen=True)
class TrackerConfig:
    max_error_px: float = 4.0
    """RANSAC and inlier threshold on reprojection error, pixels."""
    min_inliers: int = 30
    """Fewer pose inliers than this and the frame is lost."""
    search_radius_px: float = 20.0
    """Guided-matching radius around map points projected with the predicted pose, pixels, when the narrow
    one finds fewer than 2 x ``min_inliers`` matches (ORB-SLAM widens its search the same way)."""
    narrow_search_radius_px: float = 10.0
    """Guided-matching radius tried first with the predicted pose, pixels (a fourth of the candidates)."""
    refine_radius_px: float = 6.0
    """Guided-matching radius with the estimated pose (tracking the local map), pixels."""
    prediction_min_inlier_ratio: float = 0.8
    """Pose from the motion model without RANSAC when, refined on all motion-model matches, it has this
    fraction of them as inliers (ORB-SLAM's TrackWithMotionModel); else RANSAC. > 1: always RANSAC."""
    local_map_rounds: int = 3
    """Rounds of guided search + pose refinement against the local map; another round only when the
    refinement moved the points' projections by more than a fourth of ``refine_radius_px`` (median)."""
    local_keyframes: int = 30
    """The local map: points of the last keyframe and of up to this many most covisible keyframes
    (ORB-SLAM's local map is every keyframe sharing points with the frame, up to 80). Smaller local maps
    lost accuracy, larger ones gained none (benchmarks/HISTORY.md, "Measurements moved from docstrings")."""
    point_descriptor: str = "newest"
    """The descriptor a local-map point is matched by: that of the reference keyframe or else of the latest
    keyframe of the local map observing it ("newest"), or of the earliest ("oldest"). The ``xfeat``
    pipelines use "oldest": XFeat's descriptors are sampled from a 1/8-resolution map, so keypoints a few
    pixels apart have near-equal descriptors, and a point matched by its newest descriptor can slide,
    keyframe after keyframe, onto a neighbouring keypoint. ORB's descriptors do not slide, and ORB tracks
    worse with "oldest" (benchmarks/HISTORY.md, "Feature pipelines" and "Measurements moved from docstrings")."""
    recheck_inlier_ratio: float = 0.5
    """When the pose from the motion model keeps fewer inliers than this fraction of the points tracked in
    the previous frame, the frame is also matched against the whole local map by descriptor (RANSAC, then
    the same local-map tracking) and the pose with more inliers is kept (0: never). A turn that starts
    or ends between two frames moves the projections beyond the search radius; RANSAC on the few matches left can
    then find a wrong pose that the small local-map radius confirms with a few inliers (the city block's
    corner: 156 inliers and a pose 0.6 m off, against 847 inliers and the right pose by descriptor)."""
    pose_optimizer: str = "ceres"
    """The motion-only refinement of the local-map tracking: "compiled" (COLMAP's ``RefineAbsolutePose``
    problem on the inliers, Cauchy at 1 px, every observation weighted alike, solved by
    :func:`~slamkit.kernels.absolute_pose.refine_absolute_pose` with Ceres' steps: the same pose as pycolmap's to
    1e-13 on most real calls, in a third of the time, benchmarks/bench_absolute_pose.py; a camera with distortion
    parameters goes to pycolmap; not the default: see ``ba.engine``), "ceres" (default,
    ``pycolmap.refine_absolute_pose``) or "orb"
    (:func:`~slamkit.pose_optimization.
    optimize_pose` on every match, ORB-SLAM2's PoseOptimization: keypoint-level weights, 4 rounds re-classing
    by chi2). The inliers after the refinement are ``max_error_px`` ones either way. "orb" on the suite's
    7scenes/skip5, kitti-07/skip2 and syn-jerky-30 (3 seeds, 2026-12-04): ATE within a standard error of
    "ceres" on the first two, 10 % above it on syn-jerky-30 (1.70 against 1.55 mm)."""
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    random_seed: int = 0
    """RANSAC seed (same input and seed give the same trajectory)."""

    def validate(self) -> None:
        check_fields(self, "tracker", {
            "max_error_px": "(0, 1e9]", "min_inliers": "[4, inf)", "search_radius_px": "(0, 1e9]",
            "narrow_search_radius_px": "(0, 1e9]", "refine_radius_px": "(0, 1e9]",
            "prediction_min_inlier_ratio": ("(0, 100]", "> 1 turns the motion-model pose off"),
            "local_map_rounds": "[1, 100]", "local_keyframes": "[0, 10000]", "recheck_inlier_ratio": "[0, 1]",
            "random_seed": "[0, inf)"})
        if self.pose_optimizer not in POSE_OPTIMIZERS:
            raise ConfigError(f"tracker.pose_optimizer must be one of {', '.join(POSE_OPTIMIZERS)} "
                              f"(got {self.pose_optimizer!r})")
        if self.point_descriptor not in POINT_DESCRIPTORS:
            raise ConfigError(f"tracker.point_descriptor must be one of {', '.join(POINT_DESCRIPTORS)} "
                              f"(got {self.point_descriptor!r})")


@dataclass(frozen=True, eq=False)
class TrackingResult:
    """Outcome of tracking one frame.

    status: "tracked" or "lost"; cam_from_world: (4, 4) pose or None; method: how the first pose came:
    "motion" (the motion model's prediction refined, no RANSAC), "motion+ransac" (RANSAC on the
    motion-model matches) or "local map" (RANSAC on descriptor matches to the whole local map), "none"
    when nothing was tried; point2D_idxs / point3D_ids: (K,)
    inlier correspondences; ref_matches: inliers whose point the last keyframe observes, with
    ``ref_xy`` / ``cur_xy`` their pixels in both (for the flow score); matches: every match of the last
    round with its inlier mask (for views).
    """

    status: str
    reason: str
    cam_from_world: np.ndarray | None
    method: str
    num_matches: int
    num_inliers: int
    point2D_idxs: np.ndarray
    point3D_ids: np.ndarray
    ref_xy: np.ndarray
    cur_xy: np.ndarray
    matches: TrackedMatches = field(default_factory=TrackedMatches.empty)

    @property
    def tracked(self) -> bool:
        return self.status == "tracked"

    @property
    def ref_matches(self) -> int:
        return len(self.ref_xy)


def _project(cam_from_world: np.ndarray, xyz: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of points xyz (N, 3) and their depths (N,) (pixels are meaningless where depth <= 0)."""
    Xc = xyz @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = Xc[:, 2]
    return Xc[:, :2] / np.maximum(z, 1e-9)[:, None] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]], z


def _matches(local_map: LocalMap, idx: np.ndarray, pairs: np.ndarray, xy: np.ndarray, inl: np.ndarray
             ) -> TrackedMatches:
    """The last round's matches (pairs: (K, 2) index into ``idx`` (projected local-map points), keypoint)
    with their inlier mask and their pixels in the reference keyframe (NaN where it does not see them)."""
    pids = local_map.ids[idx[pairs[:, 0]]]
    ref_xy = np.full((len(pids), 2), np.nan, np.float32)
    if len(local_map.ref_ids) and len(pids):
        pos = np.minimum(np.searchsorted(local_map.ref_ids, pids), len(local_map.ref_ids) - 1)
        seen = local_map.ref_ids[pos] == pids
        ref_xy[seen] = local_map.ref_xy[pos[seen]]
    return TrackedMatches(np.asarray(xy, np.float32).reshape(-1, 2), pids.astype(np.int64), inl.copy(), ref_xy)


def _lost(reason: str, method: str, num_matches: int = 0, num_inliers: int = 0) -> TrackingResult:
    e = np.empty(0, np.int64)
    return TrackingResult("lost", reason, None, method, num_matches, num_inliers, e, e, np.empty((0, 2)),
                          np.empty((0, 2)))


class Tracker:
    """Estimates the pose of every frame from 2D-3D matches to the local map."""

    def __init__(self, config: TrackerConfig = TrackerConfig()):
        config.validate()
        self.config = config
        est = pycolmap.AbsolutePoseEstimationOptions()
        est.ransac.max_error = config.max_error_px
        est.ransac.min_inlier_ratio = 0.1
        est.ransac.max_num_trials = 2000
        est.ransac.random_seed = native_seed(config.random_seed)
        self._estimation = est
        ref = pycolmap.AbsolutePoseRefinementOptions()
        ref.refine_focal_length = False
        ref.refine_extra_params = False
        ref.max_num_iterations = 20
        self._refinement = ref
        self._pose_optimization = PoseOptimizationConfig()

    def step(self, frame: FrameFeatures, local_map: LocalMap, camera: pycolmap.Camera,
             predicted: np.ndarray | None = None, last_ids: np.ndarray | None = None) -> TrackingResult:
        """Track ``frame``. predicted: (4, 4) cam_from_world from the motion model, or None; last_ids: map
        points tracked in the previous frame — the wide motion-model search looks for these only
        (ORB-SLAM's TrackWithMotionModel), the local-map search then covers all points with a small radius."""
        c = self.config
        if len(local_map) < c.min_inliers:
            return _lost(f"local map has only {len(local_map)} points", "none")
        if len(frame) < c.min_inliers:
            return _lost(f"frame has only {len(frame)} keypoints", "none")
        K = camera.calibration_matrix()
        size = (camera.width, camera.height)
        initial, method, num_matches = None, "motion", 0
        if predicted is not None:
            initial, method, num_matches = self._with_motion_model(frame, local_map, camera, K, size, predicted,
                                                                   last_ids)
        if initial is None:
            method = "local map"
            initial, n, why = self._from_local_map(frame, local_map, camera)
            num_matches = max(num_matches, n)
            if initial is None:
                return _lost(why, method, num_matches)
        best = self._track_local_map(frame, local_map, camera, K, size, initial)
        n_inl, recheck = int(best[4].sum()), ""
        if (method != "local map" and last_ids is not None and c.recheck_inlier_ratio > 0
                and n_inl < c.recheck_inlier_ratio * len(last_ids)):
            # a weak motion-model pose: the prediction may have missed (a turn starting) and RANSAC on its few
            # matches found a wrong pose that the small local-map radius cannot leave; match the whole local map
            alt, n, _ = self._from_local_map(frame, local_map, camera)
            num_matches = max(num_matches, n)
            if alt is not None:
                other = self._track_local_map(frame, local_map, camera, K, size, alt)
                if other[4].sum() > n_inl:
                    recheck = f" (the motion model's pose kept {n_inl} of {len(last_ids)}: re-matched by descriptor)"
                    best, method, n_inl = other, "local map", int(other[4].sum())
        pose, idx, pairs, xy, inl = best
        if n_inl < c.min_inliers:
            return _lost(f"{n_inl} pose inliers < {c.min_inliers}", method, num_matches, n_inl)
        kp_idx = pairs[inl, 1]
        pids = local_map.ids[idx[pairs[inl, 0]]]
        pos = np.searchsorted(local_map.ref_ids, pids)
        pos = np.minimum(pos, max(len(local_map.ref_ids) - 1, 0))
        in_ref = (local_map.ref_ids[pos] == pids) if len(local_map.ref_ids) else np.zeros(len(pids), bool)
        return TrackingResult("tracked", f"{n_inl} inliers of {len(pairs)} local-map matches{recheck}", pose, method,
                              num_matches, n_inl, kp_idx, pids, local_map.ref_xy[pos[in_ref]],
                              frame.keypoints[kp_idx[in_ref]], _matches(local_map, idx, pairs, xy, inl))

    def _with_motion_model(self, frame: FrameFeatures, local_map: LocalMap, camera: pycolmap.Camera, K: np.ndarray,
                           size: tuple[int, int], predicted: np.ndarray, last_ids: np.ndarray | None
                           ) -> tuple[np.ndarray | None, str, int]:
        """Guided matching around the predicted pose (narrow radius, widened when it finds too few), then the
        prediction refined on those matches, or RANSAC on them: (pose or None, method, matches)."""
        c = self.config
        desc = frame.features.descriptors
        idx, uv = local_map.project(predicted, K, size)
        if last_ids is not None and len(last_ids) >= 2 * c.min_inliers:
            keep = np.isin(local_map.ids[idx], last_ids)
            if keep.sum() >= 2 * c.min_inliers:
                idx, uv = idx[keep], uv[keep]
        pairs = guided_match(uv, local_map.descriptors[idx], frame.keypoints, desc, local_map.binary,
                             c.narrow_search_radius_px, c.matching)
        if len(pairs) < 2 * c.min_inliers and c.search_radius_px > c.narrow_search_radius_px:
            pairs = guided_match(uv, local_map.descriptors[idx], frame.keypoints, desc, local_map.binary,
                                 c.search_radius_px, c.matching)
        if len(pairs) < c.min_inliers:
            return None, "motion", len(pairs)
        xy, xyz = frame.keypoints[pairs[:, 1]], local_map.xyz[idx[pairs[:, 0]]]
        initial = self._from_prediction(predicted, xy, xyz, camera, K)
        if initial is not None:
            return initial, "motion", len(pairs)
        return self._ransac(xy, xyz, camera), "motion+ransac", len(pairs)

    def _from_local_map(self, frame: FrameFeatures, local_map: LocalMap, camera: pycolmap.Camera
                        ) -> tuple[np.ndarray | None, int, str]:
        """Descriptor matching of the frame against every local-map point, then RANSAC: (pose or None,
        matches, why not)."""
        c = self.config
        pairs = match_descriptors(local_map.descriptors, frame.features.descriptors, local_map.binary, c.matching)
        if len(pairs) < c.min_inliers:
            return None, len(pairs), f"{len(pairs)} matches to the local map < {c.min_inliers}"
        pose = self._ransac(frame.keypoints[pairs[:, 1]], local_map.xyz[pairs[:, 0]], camera)
        return pose, len(pairs), "" if pose is not None else f"no pose from {len(pairs)} matches to the local map"

    def _track_local_map(self, frame: FrameFeatures, local_map: LocalMap, camera: pycolmap.Camera, K: np.ndarray,
                         size: tuple[int, int], initial: np.ndarray) -> tuple:
        """Track the local map: guided search with the estimated pose, then motion-only refinement; again
        while the refinement moves the pose (a pose from few matches can sit in a rotation-translation
        ambiguity whose small search radius hides the points that would pull it out). Returns (pose, idx,
        pairs, xy, inliers) of the best round."""
        c = self.config
        desc = frame.features.descriptors
        sigma2 = keypoint_scales(frame.features) ** 2 if c.pose_optimizer == "orb" else None
        pose, best = initial, None
        for _ in range(c.local_map_rounds):
            idx, uv = local_map.project(pose, K, size)
            pairs = guided_match(uv, local_map.descriptors[idx], frame.keypoints, desc, local_map.binary,
                                 c.refine_radius_px, c.matching)
            xy = frame.keypoints[pairs[:, 1]]
            xyz = local_map.xyz[idx[pairs[:, 0]]]
            inl = self._inliers(pose, xy, xyz, K)
            moved = 0.0
            if inl.sum() >= c.min_inliers:
                refined = self._refine(pose, xy, xyz, inl, camera, K,
                                       None if sigma2 is None else sigma2[pairs[:, 1]])
                if refined is not None:
                    moved = float(np.median(np.linalg.norm(_project(refined, xyz[inl], K)[0]
                                                           - _project(pose, xyz[inl], K)[0], axis=1)))
                    pose = refined
                    inl = self._inliers(pose, xy, xyz, K)
            if best is not None and inl.sum() < best[4].sum():
                return best
            best = (pose, idx, pairs, xy, inl)
            if moved < 0.25 * c.refine_radius_px:  # the search around the refined pose would find the same
                break
        return best

    def _refine(self, pose: np.ndarray, xy: np.ndarray, xyz: np.ndarray, inl: np.ndarray, camera: pycolmap.Camera,
                K: np.ndarray, sigma2: np.ndarray | None) -> np.ndarray | None:
        """Motion-only refinement of ``pose`` ((4, 4)) by ``pose_optimizer``: Ceres on the inliers ``inl``, or
        ORB-SLAM2's PoseOptimization on every match with the keypoint variances ``sigma2`` ((N,) px^2); None
        when it fails."""
        if self.config.pose_optimizer == "orb":
            result = optimize_pose(pose, xy, xyz, sigma2, K, self._pose_optimization)
            return result.cam_from_world if result.success else None
        return self._refine_colmap(pose, xy, xyz, inl, camera)

    def _refine_colmap(self, pose: np.ndarray, xy: np.ndarray, xyz: np.ndarray, inl: np.ndarray,
                       camera: pycolmap.Camera) -> np.ndarray | None:
        """COLMAP's refinement of ``pose`` on the inliers ``inl`` (Cauchy loss, points held): by the compiled
        kernel (``pose_optimizer`` "compiled", a pinhole camera) or by ``pycolmap.refine_absolute_pose``."""
        if self.config.pose_optimizer == "compiled" and camera.model.name in _PINHOLES:
            # the pose as pycolmap holds it, a unit quaternion, in and out: a prediction composed of earlier poses
            # is a rotation only to rounding, and a turn on the left keeps whatever is not, so without this the
            # error doubled frame by frame through the motion model (0.18 off orthogonal on the default sequence)
            cam = (camera.focal_length_x, camera.focal_length_y, camera.principal_point_x, camera.principal_point_y)
            out = refine_absolute_pose(matrix_from_rigid(rigid_from_matrix(pose)), xy, xyz, inl, cam,
                                       self._refinement.max_num_iterations, self._refinement.loss_function_scale,
                                       self._refinement.gradient_tolerance)
            return None if out is None else matrix_from_rigid(rigid_from_matrix(out))
        ref = pycolmap.refine_absolute_pose(rigid_from_matrix(pose), xy, xyz, inl, camera, self._refinement)
        return None if ref is None else matrix_from_rigid(ref["cam_from_world"])

    def _from_prediction(self, predicted: np.ndarray, xy: np.ndarray, xyz: np.ndarray, camera: pycolmap.Camera,
                         K: np.ndarray) -> np.ndarray | None:
        """ORB-SLAM's TrackWithMotionModel without RANSAC: refine the predicted pose on all the matches
        (robust loss), accepted when most matches are then inliers; else None (RANSAC decides)."""
        pose = self._refine_colmap(predicted, xy, xyz, np.ones(len(xy), bool), camera)
        if pose is None:
            return None
        n_inl = int(self._inliers(pose, xy, xyz, K).sum())
        if n_inl < max(self.config.min_inliers, self.config.prediction_min_inlier_ratio * len(xy)):
            return None
        return pose

    def _ransac(self, xy: np.ndarray, xyz: np.ndarray, camera: pycolmap.Camera) -> np.ndarray | None:
        ans = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, camera, self._estimation, self._refinement)
        if ans is None or ans["num_inliers"] < self.config.min_inliers:
            return None
        return matrix_from_rigid(ans["cam_from_world"])

    def _inliers(self, cam_from_world: np.ndarray, xy: np.ndarray, xyz: np.ndarray, K: np.ndarray) -> np.ndarray:
        uv, z = _project(cam_from_world, xyz, K)
        err2 = ((uv - xy) ** 2).sum(axis=1)
        return (z > 1e-9) & (err2 < self.config.max_error_px ** 2)


def retrack_initial_frames(state: "SlamState", seg: "Segment", tracker: Tracker, local_map: LocalMap) -> None:
    """Track the frames of ``seg`` posed while its map was young again with ``tracker``, against
    ``local_map`` built around the map's first keyframe (their first poses came from a two- or three-keyframe
    map); keyframes keep the poses bundle adjustment gave them. Clears ``seg.initial_frames``."""
    slam_map = seg.slam_map
    first_kf = min(slam_map.keyframes)
    for f in seg.initial_frames:
        rec = state.records[f.index]
        if rec.keyframe_image_id > 0:  # keyframes are posed by bundle adjustment
            continue
        tr = tracker.step(f, local_map, slam_map.pycolmap_camera, state.pose_of(rec))
        if tr.tracked:
            ref = np.eye(4)
            ref[:3] = slam_map.cam_from_world(first_kf).matrix()
            rec.ref_image_id, rec.rel_pose, rec.segment, rec.status = (
                first_kf, tr.cam_from_world @ np.linalg.inv(ref), seg.id, FrameStatus.TRACKED)
            if rec.index not in seg.frames:
                seg.frames.append(rec.index)
    seg.frames.sort()
    seg.initial_frames = []  # done: features are no longer needed
