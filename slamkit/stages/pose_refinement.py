"""Motion-only bundle adjustment of the tracked frames on the final map (issue 42).

A frame that is not a keyframe keeps the pose tracking gave it: PnP against the local map *as it was then*,
expressed relative to its reference keyframe. Bundle adjustment (local, then the final global one) later moves
the points it was posed from, most where they were young: points first seen at the end of a fast turn,
triangulated from keyframes a few millimetres apart, whose depths the later keyframes correct by centimetres.
The keyframes follow (they are in the adjustment); the other frames do not, and carry the old points' error.
On ``syn-fast-yaw-20`` this was most of the ATE: 12.5 mm over all frames against 1.95 mm over the keyframes
(seed 0); the frames right after a held run and at the ends of the swings were 2-4 cm off.

So every frame tracking posed by PnP keeps its inlier correspondences (pixel, map point id: ~12 bytes each, not
the descriptors), and at the end of the run, after the final global bundle adjustment, its pose is refined
on the final positions of those points: the motion-only bundle adjustment ORB-SLAM runs while tracking, run
once more on the final map (``optimizer``: its PoseOptimization compiled, :mod:`slamkit.pose_optimization`, or
``pycolmap.refine_absolute_pose`` twice, the correspondences beyond ``max_error_px`` dropped between). Points
deleted or fused since are left out. A frame keeps its tracked pose when fewer than ``min_inliers``
correspondences remain. Frames
rotation held in place are re-centred afterwards on the refined poses (``rotation_phase.recentre_held_frames``).
Sessions save the correspondences (a resumed run refines every frame, as the uninterrupted run does).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from ..errors import ConfigError, check_fields
from ..map import matrix_from_rigid, rigid_from_matrix
from ..pose_optimization import PoseOptimizationConfig, optimize_pose

if TYPE_CHECKING:  # pragma: no cover
    from ..state import SlamState


@dataclass(frozen=True)
class PoseRefinementConfig:
    enabled: bool = True
    """Refine every frame tracking posed by PnP on the final map (False: frames keep their tracked poses)."""
    min_inliers: int = 30
    """Fewest correspondences (points still in the map, within ``max_error_px`` after a first refinement) a
    frame needs to be refined; the tracker's own minimum by default."""
    max_error_px: float = 4.0
    """Reprojection error (pixels) above which a correspondence is dropped before the second refinement (the
    tracker's inlier threshold); "ceres" only."""
    optimizer: str = "orb"
    """"orb": :func:`~slamkit.pose_optimization.optimize_pose` (ORB-SLAM2's PoseOptimization, compiled: 4 rounds
    re-classing at chi-square 5.991 px^2); "ceres": ``pycolmap.refine_absolute_pose`` twice (Cauchy loss; the
    ``max_error_px`` inliers again). Same accuracy (fast-yaw-20 6.9 against 5.8 mm, 7-Scenes skip 5 2.87 cm
    both, 3 seeds), but on 7-Scenes (600 frames) "ceres" costs 7.0 ms a frame, 10 % of the run, "orb" 1.5 ms
    (benchmarks/HISTORY.md, "Session 22 (issue 42)")."""

    def validate(self) -> "PoseRefinementConfig":
        check_fields(self, "pose_refinement", {"min_inliers": ("[4, inf)", "a pose has 6 unknowns"),
                                               "max_error_px": "(0, 1e9]"})
        if self.optimizer not in ("ceres", "orb"):
            raise ConfigError(f"pose_refinement.optimizer must be ceres or orb (got {self.optimizer!r})")
        return self


@dataclass(frozen=True, eq=False)
class TrackedCorrespondences:
    """A frame's PnP inliers: ``xy`` (K, 2) float32 pixels, ``point3D_ids`` (K,) int64 in map ``segment``;
    ``distortion``: the camera's distortion coefficients when they were observed (keypoints undistorted later
    with another k1 are not comparable)."""

    segment: int
    xy: np.ndarray
    point3D_ids: np.ndarray
    distortion: tuple


class FinalPoseRefiner:
    """:meth:`observe` per frame posed by PnP; :meth:`refine` once, at the end of the run (module docstring)."""

    def __init__(self, config: PoseRefinementConfig = PoseRefinementConfig()):
        config.validate()
        self.config = config
        self.tracked: dict[int, TrackedCorrespondences] = {}
        """Frame index -> its last PnP correspondences."""
        opts = pycolmap.AbsolutePoseRefinementOptions()
        opts.refine_focal_length = False
        opts.refine_extra_params = False
        self._options = opts

    def observe(self, frame_index: int, segment: int, xy: np.ndarray, point3D_ids: np.ndarray,
                distortion=()) -> None:
        """Frame ``frame_index`` was posed by PnP in segment ``segment`` from pixels ``xy`` (K, 2) of map points
        ``point3D_ids`` (K,); a later call for the same frame replaces the earlier one."""
        if self.config.enabled:
            self.tracked[frame_index] = TrackedCorrespondences(
                segment, np.asarray(xy, np.float32).reshape(-1, 2), np.asarray(point3D_ids, np.int64).reshape(-1),
                tuple(float(d) for d in distortion))

    def state(self) -> tuple[list[dict], list[np.ndarray], list[np.ndarray]]:
        """The correspondences kept so far, for sessions: per frame (ascending index) ``{"frame", "segment",
        "distortion"}``, and the lists of their ``xy`` and ``point3D_ids`` arrays."""
        items = sorted(self.tracked.items())
        return ([{"frame": int(i), "segment": int(o.segment), "distortion": list(o.distortion)} for i, o in items],
                [o.xy for _, o in items], [o.point3D_ids for _, o in items])

    def restore(self, entries: list[dict], xy: list[np.ndarray], point3D_ids: list[np.ndarray]) -> None:
        """Continue from :meth:`state` of another refiner (a resumed session)."""
        self.tracked = {int(e["frame"]): TrackedCorrespondences(
            int(e["segment"]), np.asarray(x, np.float32).reshape(-1, 2), np.asarray(ids, np.int64).reshape(-1),
            tuple(float(d) for d in e["distortion"])) for e, x, ids in zip(entries, xy, point3D_ids)}

    def refine(self, state: "SlamState", distortion=()) -> list[int]:
        """Refine every observed frame that is still posed by PnP in the segment it was observed in (not a
        keyframe: those are bundle-adjusted) on its segment's current points. ``distortion``: the camera's
        coefficients now. Returns the indices of the frames refined; clears the correspondences."""
        refined: list[int] = []
        distortion = tuple(float(d) for d in distortion)
        for index, obs in sorted(self.tracked.items()):
            rec = state.records[index]
            if rec.rel_pose is None or rec.keyframe_image_id > 0 or rec.segment != obs.segment \
                    or rec.motion_model not in ("general", "") or obs.distortion != distortion:
                continue
            slam_map = state.segments[rec.segment].slam_map
            T = refine_pose(state.pose_of(rec), obs.xy, obs.point3D_ids, slam_map, self.config, self._options)
            if T is None:
                continue
            ref = np.eye(4)
            ref[:3] = slam_map.cam_from_world(rec.ref_image_id).matrix()
            rec.rel_pose = T @ np.linalg.inv(ref)
            refined.append(index)
        self.tracked = {}
        return refined


def refine_pose(cam_from_world: np.ndarray, xy: np.ndarray, point3D_ids: np.ndarray, slam_map,
                config: PoseRefinementConfig = PoseRefinementConfig(),
                options: pycolmap.AbsolutePoseRefinementOptions | None = None) -> np.ndarray | None:
    """(4, 4) cam_from_world refined from ``cam_from_world`` on the points ``point3D_ids`` of ``slam_map`` (those
    still in it) seen at ``xy``: refined, correspondences beyond ``config.max_error_px`` dropped, refined again.
    None when fewer than ``config.min_inliers`` remain or the refinement fails."""
    rec = slam_map.reconstruction
    keep = np.array([rec.exists_point3D(int(i)) for i in point3D_ids], bool)
    if keep.sum() < config.min_inliers:
        return None
    xy, xyz = np.asarray(xy, np.float64)[keep], slam_map.points_xyz(point3D_ids[keep])
    if config.optimizer == "orb":  # ORB-SLAM2's PoseOptimization, compiled: one call, ~5x less time than Ceres
        res = optimize_pose(cam_from_world, xy, xyz, None, slam_map.pycolmap_camera.calibration_matrix(),
                            PoseOptimizationConfig(min_inliers=config.min_inliers))
        return res.cam_from_world if res.success else None
    camera = slam_map.pycolmap_camera
    options = options if options is not None else pycolmap.AbsolutePoseRefinementOptions()
    pose = rigid_from_matrix(cam_from_world)
    for _ in range(2):
        ans = pycolmap.refine_absolute_pose(pose, xy, xyz, np.ones(len(xy), bool), camera, options)
        if ans is None:
            return None
        pose = ans["cam_from_world"]
        T = matrix_from_rigid(pose)
        p = (T[:3, :3] @ xyz.T + T[:3, 3:4]).T
        ok = p[:, 2] > 1e-9
        uv = camera.img_from_cam(p[ok]) if ok.any() else np.empty((0, 2))
        err = np.full(len(xy), np.inf)
        err[ok] = np.linalg.norm(uv - xy[ok], axis=1)
        inliers = err < config.max_error_px
        if inliers.sum() < config.min_inliers:
            return None
        if inliers.all():
            break
        xy, xyz = xy[inliers], xyz[inliers]
    return matrix_from_rigid(pose)


__all__ = ["FinalPoseRefiner", "PoseRefinementConfig", "TrackedCorrespondences", "refine_pose"]
