"""Mapping a new keyframe with COLMAP's machinery (seed §3.5).

Register the keyframe in the Reconstruction with its tracked pose, add its correspondences to the last
keyframe and its covisible keyframes to the CorrespondenceGraph, add the tracked 2D-3D observations, and
triangulate (``IncrementalTriangulator.triangulate_image``: continue tracks and create new points). A
keyframe that then sees fewer than ``min_keyframe_points`` map points is deregistered.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, check_fields
from ..features import FrameFeatures, MatchingConfig, NearestNeighborMatcher, PairMatcher
from ..features.epipolar import epipolar_match
from ..map import SlamMap, rigid_from_matrix
from ..results import MappingResult


MAPPER_METHODS = ("colmap", "local")


@dataclass(frozen=True)
class MapperConfig:
    method: str = "local"
    """How a keyframe's new map points are made: "local" (the default; ``slamkit.stages.local_mapper``:
    ORB-SLAM's local mapping, points created against 10-20 covisible keyframes, checked, culled when tracking
    does not find them, and fused; config ``local_mapping``) or "colmap" (this module: COLMAP's
    ``IncrementalTriangulator`` with one angle threshold, matched with ``neighbors`` keyframes; the ``seed``
    preset, the source paper's design). Local mapping keeps forward motion mapped where COLMAP's triangulator
    loses it (KITTI 07 at every 2nd / 3rd frame: 100 % posed against 56 % / 35 %; benchmarks/HISTORY.md,
    "Local mapping by default (issue 39)")."""
    neighbors: int = 4
    """The new keyframe is matched with the last keyframe and up to ``neighbors - 1`` covisible ones."""
    max_epipolar_error_px: float = 2.0
    """Matches to neighbours must satisfy the epipolar constraint of the known poses (Sampson, pixels)."""
    min_keyframe_points: int = 50
    """A keyframe seeing fewer map points after triangulation is deregistered (seed §3.5)."""
    min_tri_angle_deg: float = 1.5
    """New points need a triangulation angle of at least this, degrees (the map's
    ``IncrementalTriangulatorOptions.min_angle``; COLMAP's default)."""
    starved_points: int = 0
    """A keyframe that sees fewer map points than this after triangulation is a starving map: its
    remaining correspondences are triangulated again with ``starved_tri_angle_deg`` (0 disables; the
    ``driving`` preset uses 150). In forward motion (KITTI at 1-2 m per frame) the points ahead see little
    parallax between neighbouring keyframes; with COLMAP's 1.5 degrees only the points near the image
    border are mapped, they leave the view within a frame or two, and tracking is lost. Off by default:
    on the hard-motion suite it costs a little at KITTI's natural rate and on fast synthetic turns
    (benchmarks/HISTORY.md, "Hard-motion suite (issue 17)", "Tracking work")."""
    starved_tri_angle_deg: float = 0.5
    """The smaller triangulation angle of a starving keyframe, degrees (see ``starved_points``); the
    bundle adjustment after it filters points by this angle too (``ba.min_tri_angle_deg`` otherwise), or it
    would remove them again. Lowering both angles for every keyframe instead cost 7-Scenes accuracy."""
    guided: bool = False
    """Match a new keyframe with a neighbour only among keypoint pairs near each other's epipolar line of the
    known poses (within twice ``max_epipolar_error_px``, in front of both cameras;
    ``slamkit.features.epipolar``) instead of by brute force: about half the matching time, and its ratio
    test compares a keypoint with the few look-alikes on its epipolar line only, so it finds more matches
    over long baselines. Off by default: the extra matches cost 7-Scenes accuracy (benchmarks/HISTORY.md,
    "Tracking work"). Applies to the descriptor matcher (``nn``); learned pair matchers match by brute
    force."""
    guided_matching: MatchingConfig = field(default_factory=lambda: MatchingConfig(ratio=0.6, max_hamming=50))
    """Descriptor tests of guided matching (ORB-SLAM's for triangulation: ratio 0.6, 50 bits): among the
    few candidates on an epipolar line the ratio test is weaker than among all keypoints, and a wrong match
    along the line still fits the poses, so it is made stricter than ``matching``'s."""
    matching: MatchingConfig = field(default_factory=lambda: MatchingConfig(ratio=0.8, mutual=True))
    compact_dropped: int = 100
    """Images no longer keyframes (culled or rejected) stay in pycolmap's Reconstruction and correspondence
    graph with all their keypoints and matches; once there are this many, and at least as many as keyframes,
    the map is rebuilt without them (``SlamMap.compact``; amortized O(1) per keyframe). 0: never."""

    def validate(self) -> None:
        if self.method not in MAPPER_METHODS:
            raise ConfigError(f"mapper.method must be one of {', '.join(MAPPER_METHODS)} (got {self.method!r})")
        check_fields(self, "mapper", {
            "neighbors": "[1, 1000]", "max_epipolar_error_px": "(0, 1e9]", "min_keyframe_points": "[0, inf)",
            "min_tri_angle_deg": "[0, 45)", "starved_points": "[0, inf)", "starved_tri_angle_deg": "[0, 45)",
            "compact_dropped": ("[0, inf)", "0: never")})
        if not self.starved_tri_angle_deg <= self.min_tri_angle_deg:
            raise ConfigError("mapper: 0 <= starved_tri_angle_deg <= min_tri_angle_deg < 45 degrees needed (got "
                              f"{self.starved_tri_angle_deg}, {self.min_tri_angle_deg})")


def sampson_error_px(x1: np.ndarray, x2: np.ndarray, cam2_from_cam1: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Sampson distance (pixels) of pixel matches x1 (N, 2) in camera 1 and x2 (N, 2) in camera 2."""
    R, t = cam2_from_cam1[:3, :3], cam2_from_cam1[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Kinv = np.linalg.inv(K)
    F = Kinv.T @ (tx @ R) @ Kinv
    h1 = np.c_[x1, np.ones(len(x1))]
    h2 = np.c_[x2, np.ones(len(x2))]
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.einsum("ij,ij->i", h2, Fx1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-300))


class Mapper:
    """Inserts keyframes into a :class:`SlamMap`."""

    def __init__(self, config: MapperConfig = MapperConfig(), matcher: PairMatcher | None = None):
        config.validate()
        self.config = config
        self.matcher = matcher if matcher is not None else NearestNeighborMatcher(config.matching)

    def step(self, slam_map: SlamMap, frame: FrameFeatures, cam_from_world: np.ndarray, point2D_idxs: np.ndarray,
             point3D_ids: np.ndarray, ref_image_id: int) -> MappingResult:
        """Insert ``frame`` as a keyframe at pose ``cam_from_world`` (4, 4) with its tracked 2D-3D inliers."""
        c = self.config
        neighbors = [ref_image_id] + [i for i, _ in slam_map.covisible(ref_image_id, c.neighbors - 1)]
        iid = slam_map.add_image(frame.index, frame.timestamp, frame.keypoints, frame.features, frame.colors,
                                 frame.thumbnail)
        K = slam_map.camera.K
        tracked = np.zeros(len(frame), bool)
        tracked[point2D_idxs] = True
        total = 0
        for n in neighbors:
            pairs = self._correspondences(slam_map, n, frame, cam_from_world, point2D_idxs, point3D_ids, tracked, K)
            slam_map.add_matches(n, iid, pairs)
            total += len(pairs)
        slam_map.register(iid, rigid_from_matrix(cam_from_world))
        slam_map.add_observations(iid, point2D_idxs, point3D_ids)
        new, n_points, starved = self._triangulate(slam_map, iid)
        if n_points < c.min_keyframe_points:
            slam_map.deregister(iid)
            return MappingResult("rejected", f"sees {n_points} map points < {c.min_keyframe_points}", iid,
                                 n_points, new, tuple(neighbors), total, starved)
        how = f" (starving: triangulated down to {c.starved_tri_angle_deg:g} deg)" if starved else ""
        return MappingResult("registered", f"{n_points} map points, {new} triangulated observations{how}", iid,
                             n_points, new, tuple(neighbors), total, starved)

    def _triangulate(self, slam_map: SlamMap, iid: int) -> tuple[int, int, bool]:
        """Triangulate through keyframe ``iid`` with ``min_tri_angle_deg``, again with
        ``starved_tri_angle_deg`` when it then sees fewer than ``starved_points`` map points. Returns
        (triangulated observations, map points the keyframe sees, whether it was starving)."""
        c, opts = self.config, slam_map.triangulation
        opts.min_angle = c.min_tri_angle_deg
        new = slam_map.triangulate(iid)
        n_points = slam_map.reconstruction.image(iid).num_points3D
        if n_points >= c.starved_points or c.starved_tri_angle_deg >= c.min_tri_angle_deg:
            return new, n_points, False
        opts.min_angle = c.starved_tri_angle_deg
        new += slam_map.triangulate(iid)
        opts.min_angle = c.min_tri_angle_deg
        return new, slam_map.reconstruction.image(iid).num_points3D, True

    def _correspondences(self, slam_map: SlamMap, n: int, frame: FrameFeatures, cam_from_world: np.ndarray,
                         point2D_idxs: np.ndarray, point3D_ids: np.ndarray, tracked: np.ndarray, K: np.ndarray
                         ) -> np.ndarray:
        """(M, 2) keypoint matches (index in keyframe n, index in the new frame), one-to-one.

        Tracked observations of points that n sees come first; then descriptor matches between keypoints
        without a map point on both sides, kept when they satisfy the epipolar geometry of the poses.
        """
        kf = slam_map.keyframes[n]
        n_pids = slam_map.point3D_ids(n)
        # tracked points seen by n
        has = np.flatnonzero(n_pids >= 0)
        o = np.argsort(n_pids[has])
        sorted_pids, sorted_kp = n_pids[has][o], has[o]
        pos = np.minimum(np.searchsorted(sorted_pids, point3D_ids), max(len(sorted_pids) - 1, 0))
        seen = (sorted_pids[pos] == point3D_ids) if len(sorted_pids) else np.zeros(len(point3D_ids), bool)
        track_pairs = np.stack([sorted_kp[pos[seen]], point2D_idxs[seen]], axis=1) if seen.any() else \
            np.empty((0, 2), np.int64)
        # new correspondences between unmapped keypoints
        free_n = np.flatnonzero(n_pids < 0)
        free_c = np.flatnonzero(~tracked)
        T_n = np.eye(4)
        T_n[:3] = slam_map.cam_from_world(n).matrix()
        cur_from_n = cam_from_world @ np.linalg.inv(T_n)
        if self.config.guided and isinstance(self.matcher, NearestNeighborMatcher):
            fa, fb = kf.features, frame.features
            pairs = epipolar_match(kf.keypoints[free_n], fa.descriptors[free_n], frame.keypoints[free_c],
                                   fb.descriptors[free_c], fa.binary, cur_from_n, K,
                                   2 * self.config.max_epipolar_error_px, self.config.guided_matching)
        else:
            pairs = self.matcher.match(kf.features.subset(free_n), frame.features.subset(free_c))
        new_pairs = np.stack([free_n[pairs[:, 0]], free_c[pairs[:, 1]]], axis=1) if len(pairs) else \
            np.empty((0, 2), np.int64)
        if len(new_pairs):
            err = sampson_error_px(kf.keypoints[new_pairs[:, 0]], frame.keypoints[new_pairs[:, 1]], cur_from_n, K)
            new_pairs = new_pairs[err < self.config.max_epipolar_error_px]
        out = np.concatenate([track_pairs, new_pairs]).astype(np.int64)
        # one-to-one on both sides, tracked pairs first
        _, first_n = np.unique(out[:, 0], return_index=True)
        out = out[np.sort(first_n)]
        _, first_c = np.unique(out[:, 1], return_index=True)
        return out[np.sort(first_c)]
