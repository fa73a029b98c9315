"""Local mapping of our own (ORB-SLAM's LocalMapping, monocular): map points created, checked, culled and fused
by slamkit instead of one ``IncrementalTriangulator.triangulate_image`` call.

For a new keyframe K with its tracked pose and 2D-3D inliers (``LocalMapper.step``):

1. *Registration*: K joins the Reconstruction with its pose, its tracked observations continue their tracks,
   and its correspondences to its covisible keyframes (the keyframes that see K's tracked points, most shared
   first: the covisibility graph, ``SlamMap.covisible_with``) go into the CorrespondenceGraph.
2. *Recent-point culling* (MapPointCulling): a point created by this stage is removed when tracking found it in
   fewer than ``min_found_ratio`` of the frames that predicted it visible, or when it is still observed by
   fewer than ``min_observers`` keyframes ``culling_keyframes`` keyframes after its birth; after
   ``culling_keyframes + 1`` keyframes it is trusted (``slamkit.state.RecentPoints``).
3. *New points* (CreateNewMapPoints): K against each of its ``neighbors`` best covisible keyframes whose
   baseline is not tiny against that keyframe's median scene depth; candidates among both keyframes' keypoints
   without a map point, near each other's epipolar line of the known poses (``features.epipolar``), descriptor
   ratio ``matching.ratio``; each match triangulated (linear, per pair) and accepted only with positive depth
   in both views, reprojection error within the chi-square bound (5.991, two degrees of freedom at 95 %) at
   the keypoint's scale, parallax above ``min_parallax_deg`` and consistent keypoint scales. A starving
   keyframe (``starved_points``: forward motion, where the points ahead see little parallax) keeps its
   candidates down to ``starved_parallax_deg``.
4. *Fusion* (SearchInNeighbors): K's points projected into its neighbours and theirs into K; a projected point
   that matches a keypoint by descriptor within ``fuse_radius_px`` (times the keypoint scale) and the
   chi-square bound either gains that observation or, when the keypoint already has another point, the two
   are merged (``ObservationManager.merge_points3D``; never two points that share a keyframe).

Local bundle adjustment and keyframe culling follow in the pipeline, as with COLMAP's mapper. The map stays a
pycolmap Reconstruction, so BA, sessions, export, evaluation and the viewers are unchanged. Keypoint scale: a
keypoint's size over the smallest size in its keyframe (ORB's pyramid levels: 1.2^octave), 1 without sizes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, check_fields
from ..features import FrameFeatures, MatchingConfig, guided_match
from ..features.epipolar import epipolar_match
from ..map import SlamMap, keypoint_scales, rigid_from_matrix, shared_observations
from ..results import MappingResult
from ..state import RecentPoints

CHI2_2DOF = 5.991
"""95 % quantile of the chi-square distribution with two degrees of freedom (a reprojection error in pixels,
squared, over the keypoint's variance)."""


@dataclass(frozen=True)
class LocalMappingConfig:
    neighbors: int = 15
    """New points come from the new keyframe against up to this many best covisible keyframes (ORB-SLAM: 20
    for monocular, 10 with depth)."""
    min_baseline_ratio: float = 0.01
    """A pair whose baseline is below this fraction of the neighbour's median scene depth creates no points."""
    min_parallax_deg: float = 1.0
    """A new point needs at least this angle between its two viewing rays, degrees (ORB-SLAM:
    cos < 0.9998, 1.15 degrees). Bundle adjustment's filter uses it too for the points this stage made. 2 is
    more accurate on hand-held motion (7-Scenes at every 5th frame: 3.3 against 4.8 cm) but loses KITTI at
    every 3rd frame (benchmarks/HISTORY.md, "Local mapping (issue 27)", "Session 15")."""
    starved_points: int = 0
    """A keyframe that would see fewer map points than this with ``min_parallax_deg`` is starving: its
    candidates down to ``starved_parallax_deg`` become points too, and the bundle adjustments of the next
    ``ba.local_window`` keyframes filter by that angle (as ``mapper.starved_points`` does for COLMAP's
    mapper). 0 disables. Off by default: with ``min_parallax_deg`` 2 and 300 points it keeps KITTI at every
    3rd frame mapped and gives the best fast-turn rows, but loses a KITTI skip-2 seed and costs KITTI skip-1
    accuracy (benchmarks/HISTORY.md, "Local mapping (issue 27)", "Session 15")."""
    starved_parallax_deg: float = 1.0
    """The smaller parallax of a starving keyframe's new points, degrees (see ``starved_points``)."""
    epipolar_band_px: float = 4.0
    """Candidates lie within this distance of the epipolar line, pixels (times the keypoint scale is not
    applied: the band is a prefilter, the chi-square test decides)."""
    matching: MatchingConfig = field(default_factory=lambda: MatchingConfig(ratio=0.6, mutual=False, max_hamming=50))
    """Descriptor tests of the pair matching (ORB-SLAM's SearchForTriangulation: ratio 0.6, 50 bits)."""
    scale_ratio_factor: float = 1.8
    """Scale consistency: the two depths' ratio must agree with the two keypoint scales' ratio within this
    factor (ORB-SLAM: 1.5 x the pyramid's scale factor 1.2)."""
    min_found_ratio: float = 0.25
    """A recent point found by tracking in fewer than this fraction of the frames that predicted it visible
    is removed."""
    min_observers: int = 3
    """A recent point observed by fewer keyframes than this ``culling_keyframes`` keyframes after its
    birth is removed (ORB-SLAM monocular: 3)."""
    culling_keyframes: int = 2
    """Keyframes after its birth when a recent point must have ``min_observers``; it is trusted one keyframe
    later."""
    fuse: bool = True
    """Fuse duplicated points and add observations between the new keyframe and its neighbours."""
    fuse_radius_px: float = 3.0
    """Search radius of fusion around a projected point, pixels (times the point's keypoint scale)."""
    fuse_matching: MatchingConfig = field(default_factory=lambda: MatchingConfig(ratio=1.0, mutual=False,
                                                                                max_hamming=50, max_l2=0.7))
    """Descriptor test of fusion (ORB-SLAM's Fuse: best candidate within 50 bits, no ratio test)."""

    def validate(self) -> None:
        check_fields(self, "local_mapping", {
            "neighbors": "[1, 1000]", "min_baseline_ratio": "[0, 100]", "min_parallax_deg": "[0, 45)",
            "starved_points": "[0, inf)", "starved_parallax_deg": "[0, 45)", "epipolar_band_px": "[0, 1e9]",
            "scale_ratio_factor": "[1, 1000]", "min_found_ratio": "[0, 1]", "min_observers": "[2, inf)",
            "culling_keyframes": "[1, inf)", "fuse_radius_px": "[0, 1e9]"})
        if self.starved_points > 0 and not self.starved_parallax_deg <= self.min_parallax_deg:
            raise ConfigError(f"local_mapping.starved_parallax_deg must be in [0, min_parallax_deg] (got "
                              f"{self.starved_parallax_deg})")


@dataclass(frozen=True)
class LocalMappingResult(MappingResult):
    """What local mapping did with a keyframe: the mapper's result (``new_points`` = ``created``) with the
    counts of this stage."""

    created: int = 0
    """Points created from the new keyframe and its covisible keyframes."""
    culled: int = 0
    """Recent points removed before the new points were created."""
    fused: int = 0
    """Duplicated points merged."""
    observations_added: int = 0
    """Observations fusion added to existing points."""


def _pose(m) -> np.ndarray:
    out = np.eye(4)
    out[:3] = np.asarray(m)[:3]
    return out


def triangulate_matches(x1: np.ndarray, x2: np.ndarray, T1: np.ndarray, T2: np.ndarray, K: np.ndarray
                        ) -> np.ndarray:
    """Linear (DLT) triangulation of matches. x1, x2: (M, 2) undistorted pixels in views 1 and 2; T1, T2:
    (4, 4) cam_from_world; K: (3, 3). Returns (M, 3) world points (NaN where the solution is at infinity)."""
    Kinv = np.linalg.inv(K)
    n1 = np.c_[x1, np.ones(len(x1))] @ Kinv.T
    n2 = np.c_[x2, np.ones(len(x2))] @ Kinv.T
    A = np.empty((len(x1), 4, 4))
    for row, (n, T) in enumerate(((n1, T1), (n2, T2))):
        P = T[:3]
        A[:, 2 * row] = n[:, 0:1] * P[2] - P[0]
        A[:, 2 * row + 1] = n[:, 1:2] * P[2] - P[1]
    _, _, vt = np.linalg.svd(A)
    X = vt[:, -1]
    w = X[:, 3]
    out = np.full((len(x1), 3), np.nan)
    ok = np.abs(w) > 1e-12
    out[ok] = X[ok, :3] / w[ok, None]
    return out


def check_new_points(X: np.ndarray, x1: np.ndarray, x2: np.ndarray, s1: np.ndarray, s2: np.ndarray,
                     T1: np.ndarray, T2: np.ndarray, K: np.ndarray, min_parallax_deg: float,
                     scale_ratio_factor: float) -> np.ndarray:
    """ORB-SLAM's tests of a triangulated point (CreateNewMapPoints): (M,) bool, True where the point X (M, 3)
    is in front of both cameras, reprojects within the chi-square bound (``CHI2_2DOF`` x scale^2) onto x1 and
    x2 (undistorted pixels, scales s1, s2), is seen under at least ``min_parallax_deg`` and at depths whose
    ratio agrees with the keypoint scales' ratio within ``scale_ratio_factor``."""
    ok = np.isfinite(X).all(axis=1)
    Xs = np.where(ok[:, None], X, 0.0)
    C1, C2 = -T1[:3, :3].T @ T1[:3, 3], -T2[:3, :3].T @ T2[:3, 3]
    for T, x, s in ((T1, x1, s1), (T2, x2, s2)):
        Xc = Xs @ T[:3, :3].T + T[:3, 3]
        z = Xc[:, 2]
        ok &= z > 0
        uv = Xc[:, :2] / np.where(z > 0, z, 1.0)[:, None] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        ok &= ((uv - x) ** 2).sum(axis=1) <= CHI2_2DOF * s ** 2
    r1, r2 = Xs - C1, Xs - C2
    d1, d2 = np.linalg.norm(r1, axis=1), np.linalg.norm(r2, axis=1)
    cos = (r1 * r2).sum(axis=1) / np.maximum(d1 * d2, 1e-300)
    ok &= cos < np.cos(np.radians(min_parallax_deg))
    ratio_dist, ratio_scale = d1 / np.maximum(d2, 1e-300), s2 / s1  # a farther point is seen at a finer scale
    ok &= (ratio_dist * scale_ratio_factor >= ratio_scale) & (ratio_dist <= ratio_scale * scale_ratio_factor)
    return ok


def median_depth(slam_map: SlamMap, image_id: int, max_points: int = 200) -> float:
    """Median depth of the keyframe's map points in its camera (NaN without points), from at most
    ``max_points`` of them (evenly spaced over its keypoints)."""
    pids = slam_map.point3D_ids(image_id)
    pids = pids[pids >= 0]
    pids = pids[:: max(1, len(pids) // max_points)]
    if len(pids) == 0:
        return float("nan")
    T = slam_map.cam_from_world(image_id).matrix()
    return float(np.median(slam_map.points_xyz(pids) @ T[:3, :3][2] + T[2, 3]))


class LocalMapper:
    """Inserts keyframes into a :class:`SlamMap` and maintains its points (see the module docstring)."""

    def __init__(self, config: LocalMappingConfig = LocalMappingConfig(), min_keyframe_points: int = 50):
        config.validate()
        self.config = config
        self.min_keyframe_points = min_keyframe_points

    def step(self, slam_map: SlamMap, frame: FrameFeatures, cam_from_world: np.ndarray, point2D_idxs: np.ndarray,
             point3D_ids: np.ndarray, recent: RecentPoints) -> LocalMappingResult:
        """Insert ``frame`` as a keyframe at pose ``cam_from_world`` (4, 4) with its tracked 2D-3D inliers
        (``point2D_idxs``, ``point3D_ids`` (K,)); ``recent``: the segment's recent points (updated)."""
        c = self.config
        neighbors = [i for i, _ in slam_map.covisible_with(point3D_ids, c.neighbors)]
        iid = slam_map.add_image(frame.index, frame.timestamp, frame.keypoints, frame.features, frame.colors,
                                 frame.thumbnail)
        T_new = _pose(cam_from_world)
        scales = keypoint_scales(frame.features)
        taken = np.zeros(len(frame), bool)
        taken[point2D_idxs] = True
        new_obs = []  # (neighbour, (M, 2) pairs (neighbour keypoint, new keypoint), (M, 3) points)
        low = []  # the same, parallax between starved_parallax_deg and min_parallax_deg (a starving keyframe's)
        for n in neighbors:
            pairs, X, parallax = self._new_points(slam_map, n, frame, T_new, scales, taken)
            good = parallax >= c.min_parallax_deg if c.starved_points > 0 else np.ones(len(pairs), bool)
            taken[pairs[good, 1]] = True  # a low-parallax candidate may still pair with a later neighbour
            new_obs.append((n, pairs[good], X[good]))
            low.append((pairs[~good], X[~good]))
        starved = c.starved_points > 0 and len(point2D_idxs) + sum(len(p) for _, p, _ in new_obs) < c.starved_points
        total = 0
        for k, (n, pairs, X) in enumerate(new_obs):
            if starved:
                lp, lX = low[k]
                keep = ~taken[lp[:, 1]]  # keypoints no neighbour gave a point with enough parallax
                lp, lX = lp[keep], lX[keep]
                first = np.sort(np.unique(lp[:, 1], return_index=True)[1])
                lp, lX = lp[first], lX[first]
                taken[lp[:, 1]] = True
                pairs, X = np.concatenate([pairs, lp]), np.concatenate([X, lX])
                new_obs[k] = (n, pairs, X)
            graph = np.concatenate([shared_observations(slam_map, n, point2D_idxs, point3D_ids), pairs])
            slam_map.add_matches(n, iid, graph)
            total += len(graph)
        slam_map.register(iid, rigid_from_matrix(cam_from_world))
        slam_map.add_observations(iid, point2D_idxs, point3D_ids)
        culled = self._cull_recent(slam_map, recent)
        created = []
        for n, pairs, X in new_obs:
            created += [slam_map.add_point(X[k], ((n, int(a)), (iid, int(b))), frame.colors[b])
                        for k, (a, b) in enumerate(pairs.tolist())]
        recent.add(created)
        fused, added = self._fuse(slam_map, iid, neighbors) if c.fuse else (0, 0)
        n_points = int((slam_map.point3D_ids(iid) >= 0).sum())
        counts = (f"{n_points} map points: {len(created)} new"
                  f"{f' (starving: parallax down to {c.starved_parallax_deg:g} deg)' if starved else ''}, "
                  f"{added} observations and {fused} duplicates fused, {culled} recent points culled")
        if n_points < self.min_keyframe_points:
            slam_map.deregister(iid)
            status, reason = "rejected", f"sees {n_points} map points < {self.min_keyframe_points}"
        else:
            status, reason = "registered", counts
        return LocalMappingResult(status=status, reason=reason, image_id=iid, num_points=n_points,
                                  new_points=len(created), neighbors=tuple(neighbors), num_correspondences=total,
                                  starved=starved,
                                  created=len(created), culled=culled, fused=fused, observations_added=added)

    # ----------------------------------------------------------------- new points
    def _new_points(self, slam_map: SlamMap, n: int, frame: FrameFeatures, T_new: np.ndarray, scales: np.ndarray,
                    taken: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Matches of keyframe ``n`` with the new frame that make good points: ((M, 2) int64 pairs (keypoint in
        n, keypoint in the new frame), (M, 3) points, (M,) parallax in degrees), down to the starving parallax
        when ``starved_points`` is on."""
        c = self.config
        empty = np.empty((0, 2), np.int64), np.empty((0, 3)), np.empty(0)
        T_n = _pose(slam_map.cam_from_world(n).matrix())
        C_n, C_new = -T_n[:3, :3].T @ T_n[:3, 3], -T_new[:3, :3].T @ T_new[:3, 3]
        depth = median_depth(slam_map, n)
        if not np.isfinite(depth) or depth <= 0 or np.linalg.norm(C_new - C_n) < c.min_baseline_ratio * depth:
            return empty
        kf = slam_map.keyframes[n]
        free_n = np.flatnonzero(slam_map.point3D_ids(n) < 0)
        free_c = np.flatnonzero(~taken)
        if len(free_n) == 0 or len(free_c) == 0:
            return empty
        K = slam_map.camera.K
        fa, fb = kf.features, frame.features
        pairs = epipolar_match(kf.keypoints[free_n], fa.descriptors[free_n], frame.keypoints[free_c],
                               fb.descriptors[free_c], fa.binary, T_new @ np.linalg.inv(T_n), K,
                               c.epipolar_band_px, c.matching)
        if len(pairs) == 0:
            return empty
        pairs = np.stack([free_n[pairs[:, 0]], free_c[pairs[:, 1]]], axis=1)
        x1, x2 = kf.keypoints[pairs[:, 0]], frame.keypoints[pairs[:, 1]]
        X = triangulate_matches(x1, x2, T_n, T_new, K)
        floor = c.starved_parallax_deg if c.starved_points > 0 else c.min_parallax_deg
        ok = check_new_points(X, x1, x2, keypoint_scales(fa)[pairs[:, 0]], scales[pairs[:, 1]], T_n, T_new, K,
                              floor, c.scale_ratio_factor)
        X = X[ok]
        r1, r2 = X - C_n, X - C_new
        cos = (r1 * r2).sum(axis=1) / np.maximum(np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1), 1e-300)
        return pairs[ok].astype(np.int64), X, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))

    # ----------------------------------------------------------------- culling
    def _cull_recent(self, slam_map: SlamMap, recent: RecentPoints) -> int:
        """ORB-SLAM's MapPointCulling over the recent points; counts this keyframe as one more mapping step.
        Returns how many points were removed."""
        c = self.config
        recent.steps += 1
        exists = np.array([slam_map.reconstruction.exists_point3D(int(p)) for p in recent.ids], bool)
        recent.keep(exists)
        if len(recent.ids) == 0:
            return 0
        age = recent.steps - recent.birth
        point3D = slam_map.reconstruction.point3D
        observers = np.array([point3D(int(p)).track.length() for p in recent.ids])
        bad = recent.found < c.min_found_ratio * recent.visible
        bad |= (age >= c.culling_keyframes) & (observers < c.min_observers)
        for p in recent.ids[bad].tolist():
            slam_map.delete_point(p)
        recent.keep(~bad & (age <= c.culling_keyframes))
        return int(bad.sum())

    # ----------------------------------------------------------------- fusion
    def _fuse(self, slam_map: SlamMap, iid: int, neighbors: list[int]) -> tuple[int, int]:
        """SearchInNeighbors: the new keyframe's points into each neighbour, then the neighbours' points into
        the new keyframe. Returns (points merged, observations added)."""
        own = self._points_of(slam_map, [iid])
        merged = added = 0
        for n in neighbors:
            m, a = self._fuse_into(slam_map, own, n)
            merged, added = merged + m, added + a
        m, a = self._fuse_into(slam_map, self._points_of(slam_map, neighbors), iid)
        return merged + m, added + a

    @staticmethod
    def _points_of(slam_map: SlamMap, image_ids: list[int]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(ids (P,), positions (P, 3), descriptors (P, D), scales (P,)) of the points the keyframes observe,
        each once, described by the first keyframe listed that observes it."""
        ids, desc, scale = [], [], []
        for i in image_ids:
            kf = slam_map.keyframes[i]
            pids = slam_map.point3D_ids(i)
            has = np.flatnonzero(pids >= 0)
            ids.append(pids[has])
            desc.append(kf.features.descriptors[has])
            scale.append(keypoint_scales(kf.features)[has])
        ids_all = np.concatenate(ids)
        _, first = np.unique(ids_all, return_index=True)
        first = np.sort(first)
        ids_all = ids_all[first]
        return ids_all, slam_map.points_xyz(ids_all), np.concatenate(desc)[first], np.concatenate(scale)[first]

    def _fuse_into(self, slam_map: SlamMap, points: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                   target: int) -> tuple[int, int]:
        """Project ``points`` (from :meth:`_points_of`, taken before this fusion began: a point merged since
        is skipped) into keyframe ``target`` and fuse them with the keypoints they match."""
        c = self.config
        ids, xyz, desc, pscale = points
        target_pids = slam_map.point3D_ids(target).copy()  # ids before this fusion changed any
        keep = ~np.isin(ids, target_pids)  # already observed there
        if not keep.any():
            return 0, 0
        ids, xyz, desc, pscale = ids[keep], xyz[keep], desc[keep], pscale[keep]
        kf = slam_map.keyframes[target]
        K, cam = slam_map.camera.K, slam_map.camera
        T = _pose(slam_map.cam_from_world(target).matrix())
        Xc = xyz @ T[:3, :3].T + T[:3, 3]
        front = Xc[:, 2] > 1e-9
        uv = Xc[:, :2] / np.where(front, Xc[:, 2], 1.0)[:, None] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        idx = np.flatnonzero(inside)
        if len(idx) == 0:
            return 0, 0
        pairs = guided_match(uv[idx], desc[idx], kf.keypoints, kf.features.descriptors, kf.features.binary,
                             c.fuse_radius_px * float(np.max(pscale[idx])), c.fuse_matching)
        if len(pairs) == 0:
            return 0, 0
        p_idx, kp = idx[pairs[:, 0]], pairs[:, 1]
        err2 = ((uv[p_idx] - kf.keypoints[kp]) ** 2).sum(axis=1)
        bound = np.minimum(CHI2_2DOF * keypoint_scales(kf.features)[kp] ** 2, (c.fuse_radius_px * pscale[p_idx]) ** 2)
        ok = err2 <= bound
        pids, kps = ids[p_idx[ok]], kp[ok]
        free = target_pids[kps] < 0
        added = slam_map.add_observations(target, kps[free], pids[free])
        merged = sum(slam_map.merge_points(q, p) >= 0 for p, q in zip(pids[~free].tolist(),
                                                                      target_pids[kps[~free]].tolist()))
        return merged, added
