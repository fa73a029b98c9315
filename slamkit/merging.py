"""Map merging: one map segment's keyframes, points and frames moved into another through a Sim(3).

When the current segment recognises a place of an earlier one (a loop between segments), the two maps are
related by a similarity ``target_from_source`` (``x_target = s R x_source + t``: each segment has its own
gauge and, monocular, its own scale). :func:`merge_segments` then moves the whole source segment into the
target's map (ORB-SLAM3's map merging, ``LoopClosing::MergeLocal``; COLMAP merges two reconstructions the same
way in ``Reconstruction::Merge`` after ``AlignReconstructions``):

- every source keyframe becomes a new image of the target's Reconstruction (a new image id), posed by the
  Sim(3) (``cam_from_world' = diag(s, s, s, 1) @ cam_from_world @ S^-1``), with its keypoints, features,
  colours and thumbnail; the correspondence-graph matches between source keyframes are replayed, so
  triangulation and track merging keep working across the merged map;
- every source 3D point is added at ``s R x + t`` with its track re-pointed to the new image ids, through the
  target's ``ObservationManager`` (its statistics stay exact);
- the given pairs of the same physical point become keypoint matches between the target and source keyframes
  observing them (added to the correspondence graph before those keyframes are registered), and are fused
  with ``ObservationManager.merge_points3D`` (COLMAP's ``MergePoints3D``: one point at the track-length-weighted
  mean, the union of the tracks) and marked modified, so the next bundle adjustment completes and merges
  tracks across the seam;
- the source's frame records are re-pointed (segment, reference keyframe, relative translation times ``s``)
  so every frame's world pose in the target map is exactly the transformed old one;
- the source segment is emptied and marked ``merged_into`` the target (it stays in ``SlamState.segments`` so
  segment ids remain indices).

:func:`segment_alignment` estimates the Sim(3) and the point pairs from two maps' points matched by
descriptor (:func:`slamkit.loop_verification.verify_loop_candidate`, i.e. ``pycolmap.estimate_sim3d_robust``).
A global bundle adjustment afterwards is the caller's choice (:attr:`MergeResult.global_ba_advised`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pycolmap

from .errors import ConfigError
from .features import MatchingConfig
from .loop_verification import LoopVerification, LoopVerificationConfig, verify_loop_candidate
from .map import CAMERA_ID, SlamMap, graph_pairs, matrix_from_rigid, rigid_from_matrix
from .pose_graph import sim3_decompose
from .state import Segment, SlamState

MERGE_SCALE_RANGE = (1e-3, 1e3)
"""Plausible scales between two segments' maps: each has its own arbitrary monocular unit, so any scale is
possible; only a degenerate fit (near 0 or infinite) is refused."""


@dataclass(frozen=True)
class MergeResult:
    """What :func:`merge_segments` did."""

    target: int
    """Id of the segment that received the source's map and frames."""
    source: int
    """Id of the segment merged (now empty, ``merged_into == target``)."""
    keyframes_moved: int
    points_moved: int
    """Source 3D points added to the target map (before fusion)."""
    points_fused: int
    """Pairs of points fused into one (the target map has ``points before + points_moved - points_fused``)."""
    frames_moved: int
    """Frame records re-pointed to the target segment."""
    scale: float
    rotation: np.ndarray = field(repr=False)
    """(3, 3) rotation of ``target_from_source``."""
    translation: np.ndarray = field(repr=False)
    """(3,) translation of ``target_from_source`` (target map units)."""
    image_ids: dict[int, int] = field(repr=False, default_factory=dict)
    """Source image id -> its new image id in the target map."""
    point3D_ids: dict[int, int] = field(repr=False, default_factory=dict)
    """Source 3D point id -> its id in the target map (after fusion: the fused point's id)."""
    last_keyframe: int = -1
    """When the source was the current segment: the new id of its last keyframe, around which the caller
    rebuilds ``SlamState.local_map`` (left None by the merge); else -1."""
    global_ba_advised: bool = False
    """Points were fused, so the two parts share tracks: a global BA can now reconcile them (without shared
    points it could not move one part relative to the other)."""
    seam_image_pairs: int = 0
    """(target keyframe, source keyframe) pairs given correspondence-graph matches from the fused points, so
    later triangulation, track completion and merging work across the seam."""

    @property
    def local_map_stale(self) -> bool:
        """The current segment was the source: ``SlamState.local_map`` must be rebuilt around
        :attr:`last_keyframe` before the next frame is tracked."""
        return self.last_keyframe >= 0

    @property
    def reason(self) -> str:
        return (f"segment {self.source} merged into segment {self.target}: {self.keyframes_moved} keyframes, "
                f"{self.points_moved} points ({self.points_fused} fused), {self.frames_moved} frames, "
                f"scale {self.scale:.4g}")


def _check_segments(state: SlamState, target: Segment, source: Segment) -> None:
    for name, seg in (("target", target), ("source", source)):
        if not any(s is seg for s in state.segments):
            raise ConfigError(f"merge_segments: the {name} segment {seg.id} is not a segment of this state")
        if seg.merged_into >= 0:
            raise ConfigError(f"merge_segments: the {name} segment {seg.id} was already merged into segment "
                              f"{seg.merged_into}; merge into (or from) that one")
    if target is source:
        raise ConfigError(f"merge_segments: cannot merge segment {target.id} into itself")
    if source.slam_map.pending_image_ids or target.slam_map.pending_image_ids:
        raise ConfigError("merge_segments: a keyframe candidate is pending (between add_image and register); "
                          "merge between steps")


def _check_sim3(target_from_source: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    m = np.asarray(target_from_source, np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all() or not np.allclose(m[3], [0, 0, 0, 1]):
        raise ConfigError(f"target_from_source: expected a finite (4, 4) similarity [[s R, t], [0, 1]], "
                          f"got shape {m.shape}")
    try:
        s, r, t = sim3_decompose(m)
    except ConfigError as e:  # a reflection or a singular matrix
        raise ConfigError(f"target_from_source: {e}") from None
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or not MERGE_SCALE_RANGE[0] <= s <= MERGE_SCALE_RANGE[1]:
        raise ConfigError(f"target_from_source: not a similarity with a plausible scale (scale {s:.4g}, "
                          f"rotation orthonormal to {np.abs(r.T @ r - np.eye(3)).max():.2g})")
    return s, r, t


def _check_records(state: SlamState, source: Segment) -> None:
    """Every posed frame of the source is anchored to one of its keyframes (checked before anything moves)."""
    for rec in state.records:
        if rec.segment == source.id and rec.rel_pose is not None and rec.ref_image_id not in source.slam_map.keyframes:
            raise ConfigError(f"merge_segments: frame {rec.index} is posed relative to image {rec.ref_image_id}, "
                              f"not a keyframe of segment {source.id}")


def _check_pairs(point_pairs, target_map: SlamMap, source_map: SlamMap) -> np.ndarray:
    if point_pairs is None:
        return np.empty((0, 2), np.int64)
    pairs = np.asarray(point_pairs)
    if pairs.size == 0:
        return np.empty((0, 2), np.int64)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or not np.issubdtype(pairs.dtype, np.integer):
        raise ConfigError(f"point_pairs: expected (K, 2) integer (target point id, source point id), "
                          f"got {pairs.dtype} {pairs.shape}")
    for col, slam_map, name in ((0, target_map, "target"), (1, source_map, "source")):
        missing = [int(p) for p in pairs[:, col] if not slam_map.reconstruction.exists_point3D(int(p))]
        if missing:
            raise ConfigError(f"point_pairs: {len(missing)} {name} point ids are not in the {name} map "
                              f"(e.g. {missing[0]})")
    return pairs.astype(np.int64)


def transform_cam_from_world(cam_from_world: np.ndarray, target_from_source: np.ndarray) -> np.ndarray:
    """(4, 4) rigid cam_from_world in the target map of a camera posed (4, 4) in the source map:
    ``diag(s, s, s, 1) @ cam_from_world @ inv(S)`` (camera coordinates scale with the map)."""
    s, r, t = sim3_decompose(target_from_source)
    world_from_target = np.eye(4)
    world_from_target[:3, :3], world_from_target[:3, 3] = r.T / s, -(r.T @ t) / s
    return np.diag([s, s, s, 1.0]) @ np.asarray(cam_from_world, np.float64) @ world_from_target


def _seam_matches(target_map: SlamMap, source_map: SlamMap, pairs: np.ndarray
                  ) -> dict[tuple[int, int], np.ndarray]:
    """Keypoint matches across the seam that the fused points imply: for each (target point, source point)
    pair, every target observation with every source observation. Returns (target image id, source image id)
    -> (M, 2) uint32 (keypoint in the target image, keypoint in the source image), one match per keypoint
    on each side (the first)."""
    rec_t, rec_s = target_map.reconstruction, source_map.reconstruction
    found: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for a, b in pairs.tolist():
        for el_t in rec_t.point3D(a).track.elements:
            for el_s in rec_s.point3D(b).track.elements:
                if el_t.image_id in target_map.keyframes and el_s.image_id in source_map.keyframes:
                    found.setdefault((el_t.image_id, el_s.image_id), []).append((el_t.point2D_idx, el_s.point2D_idx))
    out = {}
    for key, rows in sorted(found.items()):
        m = np.array(rows, np.int64)
        m = m[np.unique(m[:, 0], return_index=True)[1]]
        m = m[np.unique(m[:, 1], return_index=True)[1]]
        out[key] = m.astype(np.uint32)
    return out


def _move_keyframes(target_map: SlamMap, source_map: SlamMap, sim: np.ndarray,
                    seam: dict[tuple[int, int], np.ndarray]) -> dict[int, int]:
    """Add every source keyframe to the target map (new ids, transformed poses, their graph matches and the
    ``seam`` matches with target keyframes, all before any is registered, as the mapper adds a keyframe);
    returns source image id -> new image id."""
    ids: dict[int, int] = {}
    for iid in sorted(source_map.keyframes):
        kf = source_map.keyframes[iid]
        ids[iid] = target_map.add_image(kf.frame_index, kf.timestamp, kf.keypoints, kf.features, kf.colors,
                                        kf.thumbnail)
    pairs, matches = graph_pairs(source_map)
    for (a, b), m in zip(pairs, matches):
        if a in ids and b in ids:
            target_map.add_matches(ids[a], ids[b], m)
    for (a, b), m in seam.items():
        target_map.add_matches(a, ids[b], m)
    target_map.observe(*ids.values())  # every match added before any of them is registered
    for iid, new in ids.items():
        pose = transform_cam_from_world(matrix_from_rigid(source_map.cam_from_world(iid)), sim)
        target_map.register(new, rigid_from_matrix(pose))
    return ids


def _move_points(target_map: SlamMap, source_map: SlamMap, ids: dict[int, int], s: float, r: np.ndarray,
                 t: np.ndarray) -> dict[int, int]:
    """Add every source 3D point, transformed, with its track on the new image ids (through the target's
    ObservationManager); returns source point id -> new point id."""
    out: dict[int, int] = {}
    for pid, point in sorted(source_map.reconstruction.points3D.items()):
        elements = [pycolmap.TrackElement(ids[el.image_id], el.point2D_idx) for el in point.track.elements
                    if el.image_id in ids]
        if len(elements) < 2:  # a point seen only by dropped images: nothing to carry over
            continue
        track = pycolmap.Track()
        track.add_elements(elements)
        xyz = s * (r @ np.asarray(point.xyz, np.float64)) + t
        out[int(pid)] = int(target_map.observations.add_point3D(xyz, track, np.asarray(point.color, np.uint8)))
    target_map.changed()
    return out


def _fuse_points(target_map: SlamMap, pairs: np.ndarray, moved: dict[int, int]) -> tuple[int, dict[int, int]]:
    """Fuse each (target point, source point) pair with ``ObservationManager.merge_points3D``; returns (pairs
    fused, id now standing for each id that was fused away). Chains (a point in several pairs) follow the
    ids the earlier fusions gave; a pair whose points are already one, or that would give a track two
    observations in one image, is skipped."""
    rec, current = target_map.reconstruction, {}

    def now(pid: int) -> int:
        while pid in current:
            pid = current[pid]
        return pid

    fused = 0
    for a, b in pairs.tolist():
        if b not in moved:
            continue
        p, q = now(int(a)), now(moved[b])
        if p == q or not (rec.exists_point3D(p) and rec.exists_point3D(q)):
            continue
        images_p = {el.image_id for el in rec.point3D(p).track.elements}
        if any(el.image_id in images_p for el in rec.point3D(q).track.elements):
            continue
        new = int(target_map.observations.merge_points3D(p, q))
        current[p] = current[q] = new
        target_map.triangulator.add_modified_point3D(new)
        fused += 1
    target_map.changed()
    return fused, {k: now(k) for k in current}


def _repoint_records(state: SlamState, target: Segment, source: Segment, ids: dict[int, int], s: float) -> int:
    """Frames posed in the source segment now are in the target's: reference keyframe -> its new id and the
    relative translation times ``s`` (``rel' = D rel D^-1``, D = diag(s, s, s, 1), so ``rel' @ ref'`` is
    ``D @ rel @ ref @ S^-1``: the old pose, transformed). Returns how many were moved."""
    moved = 0
    for rec in state.records:
        if rec.segment != source.id:
            continue
        if rec.rel_pose is not None:
            rec.rel_pose = rec.rel_pose.copy()
            rec.rel_pose[:3, 3] *= s
            rec.ref_image_id = ids[rec.ref_image_id]
        rec.keyframe_image_id = ids.get(rec.keyframe_image_id, -1) if rec.keyframe_image_id >= 0 else -1
        rec.segment = target.id
        moved += 1
    return moved


def _move_bookkeeping(target: Segment, source: Segment, ids: dict[int, int]) -> None:
    """Frames, initial frames, signatures and counters of the source go to the target; the source keeps an
    empty map of the same camera and is marked merged."""
    target.frames = sorted(set(target.frames) | set(source.frames))
    target.initial_frames = sorted(target.initial_frames + source.initial_frames, key=lambda f: f.index)
    target.signatures.update({ids[i]: sig for i, sig in source.signatures.items() if i in ids})
    target.relocalizations += source.relocalizations
    target.keyframes_culled += source.keyframes_culled
    old = source.slam_map
    source.slam_map = SlamMap(old.camera, old.triangulation)
    source.slam_map.reconstruction.camera(CAMERA_ID).params = old.reconstruction.camera(CAMERA_ID).params  # refined
    source.frames, source.initial_frames, source.signatures = [], [], {}
    source.relocalizations = source.keyframes_culled = 0
    source.merged_into = target.id


def _move_cursor(state: SlamState, target: Segment, source: Segment, ids: dict[int, int],
                 points: dict[int, int]) -> int:
    """When the source was being tracked, tracking continues in the target: returns the new id of the last
    keyframe (the local map, of source point ids, is dropped for the caller to rebuild), else -1."""
    if state.segment is not source:
        return -1
    state.segment = target
    state.last_keyframe = ids.get(state.last_keyframe, max(ids) if ids else -1)
    state.local_map = None
    if state.last_ids is not None:
        state.last_ids = np.array([points[int(p)] for p in state.last_ids if int(p) in points], np.int64)
    return state.last_keyframe


def merge_segments(state: SlamState, target: Segment, source: Segment, target_from_source: np.ndarray,
                   point_pairs: np.ndarray | None = None) -> MergeResult:
    """Move segment ``source`` (its keyframes, points, matches and frames) into ``target``'s map.

    target_from_source: (4, 4) similarity ``[[s R, t], [0, 1]]`` mapping source-map coordinates to the
        target map's (e.g. :attr:`SegmentAlignment.target_from_source`).
    point_pairs: (K, 2) int (target point id, source point id) of the same physical points, fused into one.
    Mutates ``state``, both segments and the target's map (the source's map objects are left as they were
    and dropped). ConfigError for a merge of a segment into itself, of or into a merged segment, a matrix that
    is not a similarity, or point ids not in the maps.
    """
    _check_segments(state, target, source)
    s, r, t = _check_sim3(target_from_source)
    sim = np.asarray(target_from_source, np.float64)
    pairs = _check_pairs(point_pairs, target.slam_map, source.slam_map)
    if source.slam_map.num_keyframes == 0:
        raise ConfigError(f"merge_segments: segment {source.id} has no keyframes to merge")
    _check_records(state, source)
    target_map, source_map = target.slam_map, source.slam_map
    seam = _seam_matches(target_map, source_map, pairs)
    ids = _move_keyframes(target_map, source_map, sim, seam)
    points = _move_points(target_map, source_map, ids, s, r, t)
    fused, fused_ids = _fuse_points(target_map, pairs, points)
    points = {k: fused_ids.get(v, v) for k, v in points.items()}
    frames = _repoint_records(state, target, source, ids, s)
    n_points = len(points)
    _move_bookkeeping(target, source, ids)
    last = _move_cursor(state, target, source, ids, points)
    return MergeResult(target.id, source.id, len(ids), n_points, fused, frames, s, r, t, ids, points, last,
                       global_ba_advised=fused > 0, seam_image_pairs=len(seam))


# ------------------------------------------------------------------------------------------------------
# estimating the Sim(3) between two segments


@dataclass(frozen=True)
class SegmentAlignment:
    """Outcome of :func:`segment_alignment`: the verification of the Sim(3) and the matched points."""

    verification: LoopVerification
    point_pairs: np.ndarray = field(repr=False)
    """(K, 2) int64 (target point id, source point id): the Sim(3)'s inliers (empty unless accepted)."""

    @property
    def accepted(self) -> bool:
        return self.verification.accepted

    @property
    def target_from_source(self) -> np.ndarray | None:
        """(4, 4) similarity from source-map to target-map coordinates, or None."""
        return self.verification.tgt_from_src


def map_point_descriptors(slam_map: SlamMap, image_ids=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Map points observed by the keyframes ``image_ids`` (default: all): (ids (M,) int64, xyz (M, 3),
    descriptors (M, D) — each point's from the first of those keyframes (ascending id) observing it, binary)."""
    image_ids = sorted(slam_map.keyframes) if image_ids is None else sorted(int(i) for i in image_ids)
    unknown = [i for i in image_ids if i not in slam_map.keyframes]
    if unknown or not image_ids:
        raise ConfigError(f"map_point_descriptors: no keyframes given or not keyframes of the map: {unknown}")
    all_ids, all_desc = [], []
    for iid in image_ids:
        pids = slam_map.point3D_ids(iid)
        has = pids >= 0
        all_ids.append(pids[has])
        all_desc.append(slam_map.keyframes[iid].features.descriptors[has])
    ids, first = np.unique(np.concatenate(all_ids), return_index=True)
    binary = bool(slam_map.keyframes[image_ids[0]].features.binary)
    return ids, slam_map.points_xyz(ids), np.concatenate(all_desc)[first], binary


def segment_alignment(target_map: SlamMap, source_map: SlamMap, target_keyframes=None, source_keyframes=None,
                      config: LoopVerificationConfig | None = None,
                      matching: MatchingConfig | None = None) -> SegmentAlignment:
    """Sim(3) ``target_from_source`` between two maps from their points matched by descriptor.

    The points seen by ``target_keyframes`` / ``source_keyframes`` (default: every keyframe) are matched
    (ratio test, mutual) and a robust Sim(3) is fitted (``pycolmap.estimate_sim3d_robust`` through
    :func:`~slamkit.loop_verification.verify_loop`); the inliers are the point pairs to fuse. The default
    config accepts any scale in :data:`MERGE_SCALE_RANGE` (two segments have unrelated units) and an inlier
    ratio from 0.1: matching whole maps, most descriptor matches fall where the segments do not overlap.
    """
    cfg = config or LoopVerificationConfig(min_inlier_ratio=0.1, scale_range=MERGE_SCALE_RANGE)
    t_ids, t_xyz, t_desc, binary = map_point_descriptors(target_map, target_keyframes)
    s_ids, s_xyz, s_desc, s_binary = map_point_descriptors(source_map, source_keyframes)
    if binary != s_binary:
        raise ConfigError("segment_alignment: the two maps hold different kinds of descriptors")
    verification, pairs = verify_loop_candidate(s_xyz, s_desc, t_xyz, t_desc, binary, cfg, matching)
    if not verification.accepted:
        return SegmentAlignment(verification, np.empty((0, 2), np.int64))
    inl = pairs[verification.inlier_mask]
    return SegmentAlignment(verification, np.stack([t_ids[inl[:, 1]], s_ids[inl[:, 0]]], axis=1).astype(np.int64))

def merge_candidate(state: SlamState, candidate) -> MergeResult:
    """Loop closing recognised a place of an earlier segment (a
    :class:`~slamkit.stages.loop_closer.MergeCandidate`): move the current segment's map and frames into the
    earlier segment's map through the verified Sim(3) (:func:`merge_segments`), fusing the matched points,
    and record the merge in ``state.map_merges`` (loop groups start over). The caller rebuilds its place
    database: the moved keyframes' image ids changed."""
    target, source = state.segments[candidate.candidate_segment], state.segments[candidate.segment]
    query_frame = source.slam_map.keyframes[candidate.query_image_id].frame_index
    candidate_frame = target.slam_map.keyframes[candidate.candidate_image_id].frame_index
    res = merge_segments(state, target, source, candidate.tgt_from_src, candidate.point_pairs[:, ::-1])
    state.loop_groups = ()
    state.map_merges.append({"segment": res.source, "into": res.target, "query_frame": int(query_frame),
                             "candidate_frame": int(candidate_frame), "inliers": candidate.inliers,
                             "matches": candidate.matches, "keyframes_moved": res.keyframes_moved,
                             "points_fused": res.points_fused, "scale": float(res.scale)})
    return res

