"""Loop closing (ORB-SLAM's LoopClosing thread, run in line after each keyframe): detect, verify, correct.

For every new keyframe :class:`LoopCloser.step`:

1. adds it to one :class:`~slamkit.place_recognition.PlaceDatabase` of the run, keyed by the keyframe's frame
   index (unique across map segments); culled keyframes leave it (:meth:`LoopCloser.forget`);
2. queries the database for keyframes that are neither connected to it (covisible by ``neighbour_weight``
   points or more, ORB-SLAM's connections) nor among the last keyframes, scored
   at least as high as its least similar covisible neighbour (ORB-SLAM's ``DetectLoopCandidates`` rule);
3. keeps candidates whose covisibility groups were also found for the previous keyframes
   (:func:`~slamkit.loop_verification.update_consistent_groups`), and verifies at most a few of them by
   matching the keyframe's map points to the candidate's (and its neighbours') and a robust Sim(3)
   (:func:`~slamkit.loop_verification.verify_loop_candidate`, ``pycolmap.estimate_sim3d_robust``);
4. a verified candidate in the same segment closes the loop: a Sim(3) pose graph over the segment's keyframes
   (sequential + covisibility + loop edges, :func:`~slamkit.pose_graph.optimize_pose_graph`) corrects the
   keyframe poses in the pycolmap Reconstruction, each map point follows its reference keyframe
   (:func:`~slamkit.pose_graph.correct_points`), and the matched duplicate points are fused
   (``ObservationManager.merge_points3D``, which joins their tracks). The result asks the pipeline for a
   global bundle adjustment (stages do not call stages). A candidate in an earlier segment is only reported
   (``merge_candidate``): map merging is :mod:`slamkit.merging`'s job.

The database and the key bookkeeping are derived state (rebuilt from the segments' keyframes by
:meth:`LoopCloser.rebuild` when a session resumes: the same bags of words give the same scores); the
consistency groups and the list of closures live in :class:`~slamkit.state.SlamState`.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from ..errors import check_fields
from ..loop_verification import (ConsistentGroup, LoopStatus, LoopVerification, LoopVerificationConfig,
                                 match_map_points, update_consistent_groups, verify_loop_by_reprojection,
                                 verify_loop_candidate)
from ..map import keypoint_scales, rigid_from_matrix
from ..place_recognition import PlaceDatabase, default_vocabulary
from ..pose_graph import (PoseGraphConfig, correct_points, loop_edge, optimize_pose_graph, relative_edges,
                          sim3_decompose)

if TYPE_CHECKING:  # pragma: no cover
    from ..map import SlamMap
    from ..state import Segment, SlamState


VERIFICATION_RANGES = {
    "min_matches": "[3, inf)", "min_inliers": "[3, inf)", "min_inlier_ratio": "[0, 1]", "max_error": "(0, 1e6]",
    "relative_error": "(0, 10]", "scale_range": "(0, 1e6]", "random_seed": ("[-1, inf)", "-1: random"),
    "max_trials": "[1, 1000000]"}
"""Ranges of the :class:`LoopVerificationConfig` fields of ``verification`` and ``merge_verification`` (beyond
what its own ``__post_init__`` checks): finite, and bounded where a value would make no sense."""


@dataclass(frozen=True)
class LoopClosingConfig:
    """Loop detection, verification and correction (``SlamConfig.loop_closing``)."""

    enabled: bool = True
    """Detect and close loops (False: the source paper's behaviour, no place database at all)."""
    query_candidates: int = 10
    """Keyframes the place database returns per query (before the covisibility-score rule)."""
    min_consistency: int = 3
    """A candidate must be recognised by this many previous keyframes in a row (ORB-SLAM: 3)."""
    max_verifications: int = 2
    """At most this many consistent candidates are verified per keyframe (bounds the cost)."""
    recent_keyframes: int = 10
    """Keyframes inserted this recently (image ids of the same segment) are never candidates."""
    min_keyframes: int = 12
    """No detection before the segment has this many keyframes, nor within this many keyframes after a
    closure (ORB-SLAM: 10)."""
    merge_min_keyframes: int = 5
    """A segment with fewer keyframes than ``min_keyframes`` looks for places of earlier segments (map
    merging) once it has this many: a new segment after tracking was lost is usually still where the old map
    ends, and would pass the place before it has ``min_keyframes``."""
    neighbour_weight: int = 15
    """Covisible keyframes sharing at least this many points set the minimum score (ORB-SLAM: 15)."""
    group_span: int = 5
    """A candidate's group (consistency check) is it and this many keyframes of its segment inserted before
    and after it. Not its covisible keyframes, as ORB-SLAM: in a room a few early keyframes are covisible with
    almost every other, so every covisibility group overlaps every other and the check passes anything."""
    candidate_neighbours: int = 2
    """Keyframes inserted before and after the candidate whose map points join the candidate's for
    verification."""
    covisibility_weight: int = 100
    """Covisibility edges of the pose graph join keyframes sharing at least this many points (ORB-SLAM's
    essential graph: 100)."""
    loop_group: int = 5
    """Loop edges join the query and its most covisible keyframes to the candidate and its (this many each)."""
    verification: LoopVerificationConfig = field(default_factory=lambda: LoopVerificationConfig(max_trials=500))
    merge_verification: LoopVerificationConfig = field(default_factory=lambda: LoopVerificationConfig(
        max_trials=500, min_inlier_ratio=0.1, scale_range=(1e-3, 1e3)))
    """Verification of a place of another segment (map merging): any scale (each segment has its own
    monocular unit), and a smaller inlier ratio, as the query's points are matched with a whole stretch of the
    other map of which only the part in view overlaps."""
    max_correction: float = 0.3
    """A loop may move the query keyframe by at most this fraction of the path the camera travelled since the
    candidate keyframe. Drift grows slowly with the path (monocular SLAM: a few per cent); a verified Sim(3)
    that jumps much farther matched a different place that looks the same (a corridor of identical doors
    repeats a whole stretch of 3D structure, so the Sim(3) itself cannot tell). Not applied to places of
    other segments, whose maps are unrelated."""
    min_inliers: int = 30
    """Sim(3) inliers a loop needs (on top of ``verification``'s own thresholds)."""
    reprojection_check: bool = True
    """A loop in the segment is verified by reprojection in both keyframes (ORB-SLAM's Sim3Solver and
    OptimizeSim3, :func:`~slamkit.loop_verification.verify_loop_by_reprojection`): RANSAC on minimal sets scored
    by the matches that reproject within the chi-square bound at the keypoint's scale, the best Sim(3) refined
    the same way, then ``min_inliers`` and ``verification``'s ratio and scale on those inliers; only they are
    fused and the refined Sim(3) makes the loop edges. Off: COLMAP's LO-RANSAC on 3D distances
    (:func:`~slamkit.loop_verification.verify_loop`), which accepts wrong matches among near points and refuses
    right ones among far points, whose depth is uncertain by more than its threshold: on the city block it
    refused the right loop for 130 keyframes (benchmarks/HISTORY.md, "the city block's third seed")."""
    max_postings: int = 200_000
    """Place-database entries one query visits at most (bounded query time as the map grows)."""
    global_ba: bool = True
    """Global bundle adjustment after a loop correction."""
    correct: bool = True
    """Correct a verified loop inside the segment (pose graph, point fusion, global BA); False: detect and
    report it only (``LoopClosingResult.reason``), for the source paper's trajectories and for ablations.
    Places of other segments are merged either way (map merging, on with ``enabled``). On the synthetic city
    block driven round twice the correction cuts the ATE to 0.26 x (mean of 3 seeds); no sequence of the
    hard-motion suite closes a loop (benchmarks/HISTORY.md, "Loop closure (issue 18)")."""

    def validate(self) -> None:
        check_fields(self, "loop_closing", {
            **{name: "[1, inf)" for name in ("loop_group", "min_inliers", "max_postings")},
            "query_candidates": "[1, 1000]", "max_verifications": "[1, 1000]",
            **{name: "[0, inf)" for name in ("min_consistency", "recent_keyframes", "min_keyframes",
                                             "merge_min_keyframes", "neighbour_weight", "covisibility_weight",
                                             "group_span", "candidate_neighbours")},
            "max_correction": ("(0, 1e9]", "1e9: no limit"), "verification": VERIFICATION_RANGES,
            "merge_verification": VERIFICATION_RANGES})


@dataclass(frozen=True)
class LoopClosure:
    """A verified loop: keyframes by image id (in ``segment``) and frame index, the Sim(3) verification,
    and the size of the correction of the query keyframe (metres, degrees, Sim(3) scale)."""

    segment: int
    query_image_id: int
    query_frame: int
    candidate_image_id: int
    candidate_frame: int
    matches: int
    inliers: int
    translation_m: float = 0.0
    rotation_deg: float = 0.0
    scale: float = 1.0
    fused_points: int = 0
    keyframes_corrected: int = 0

    def to_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, float) else int(v)) for k, v in self.__dict__.items()}

    def __str__(self) -> str:
        return (f"loop closed: keyframe {self.query_image_id} (frame {self.query_frame}) ~ keyframe "
                f"{self.candidate_image_id} (frame {self.candidate_frame}), {self.inliers}/{self.matches} inliers, "
                f"correction {self.translation_m:.3g} m {self.rotation_deg:.2f} deg scale {self.scale:.3f}, "
                f"{self.fused_points} points fused")


@dataclass(frozen=True)
class MergeCandidate:
    """A verified place of an earlier segment: what map merging needs. ``tgt_from_src`` (4, 4) Sim(3) maps
    the current segment's world to the candidate segment's (``candidate_world_from_query_world``)."""

    segment: int
    query_image_id: int
    candidate_segment: int
    candidate_image_id: int
    matches: int
    inliers: int
    tgt_from_src: np.ndarray = field(repr=False)
    point_pairs: np.ndarray = field(repr=False)
    """(K, 2) int64 inlier (query segment point id, candidate segment point id)."""


@dataclass(frozen=True)
class LoopClosingResult:
    """What :meth:`LoopCloser.step` did for one keyframe."""

    candidates: int = 0
    """Place-recognition candidates that passed the score rule."""
    verified: int = 0
    """Consistent candidates verified by Sim(3)."""
    closure: LoopClosure | None = None
    merge_candidate: MergeCandidate | None = None
    needs_global_ba: bool = False
    reason: str = ""


@dataclass
class _Verified:
    segment: "Segment"
    image_id: int
    verification: object
    pairs: np.ndarray
    """(K, 2) inlier (query point id, candidate point id)."""


PRIOR_KEY_BASE = 1 << 40
"""Database keys of a loaded map's keyframes (negative frame indices, :mod:`slamkit.map_reuse`) start here."""


def place_key(frame_index: int) -> int:
    """The place database's key of a keyframe: its frame index, unique across segments (a loaded map's
    keyframes, with negative frame indices, above :data:`PRIOR_KEY_BASE`)."""
    return int(frame_index) if frame_index >= 0 else PRIOR_KEY_BASE - int(frame_index)


class LoopCloser:
    """Place database of the run + loop detection/correction; see the module docstring."""

    def __init__(self, config: LoopClosingConfig = LoopClosingConfig(), features: str = "orb"):
        config.validate()
        self.config = config
        self.features = features
        self.database: PlaceDatabase | None = None
        self._where: dict[int, tuple[int, int]] = {}
        """database key (frame index) -> (segment id, image id)."""
        self._key_of: dict[tuple[int, int], int] = {}
        self._segments: list["Segment"] = []

    # ----------------------------------------------------------------- the database
    def _database(self) -> PlaceDatabase:
        if self.database is None:  # lazily: the vocabulary is trained on first use (then cached on disk)
            self.database = PlaceDatabase(default_vocabulary(self.features), self.config.max_postings)
        return self.database

    def add(self, seg: "Segment", image_id: int) -> tuple[int, tuple[np.ndarray, np.ndarray]]:
        """Store keyframe ``image_id`` of ``seg``; returns its key and bag of words."""
        kf = seg.slam_map.keyframes[image_id]
        key = place_key(kf.frame_index)
        db = self._database()
        bow = db.vocabulary.bow(kf.features.descriptors)
        db.add_bow(key, *bow)
        self._where[key] = (seg.id, image_id)
        self._key_of[(seg.id, image_id)] = key
        return key, bow

    def forget(self, seg: "Segment", image_id: int) -> None:
        """Keyframe ``image_id`` of ``seg`` was culled: it is no candidate any more."""
        key = self._key_of.pop((seg.id, image_id), None)
        if key is not None and self.database is not None:
            self.database.remove(key)
            self._where.pop(key, None)

    def rebuild(self, segments: list["Segment"]) -> None:
        """The database of a resumed run: every keyframe of every segment, by key."""
        self.database, self._where, self._key_of = None, {}, {}
        if not self.config.enabled:
            return
        keyframes = sorted((kf.frame_index, s.id, i) for s in segments for i, kf in s.slam_map.keyframes.items())
        for _, seg_id, image_id in keyframes:
            self.add(segments[seg_id], image_id)

    # ----------------------------------------------------------------- one keyframe
    def step(self, state: "SlamState", seg: "Segment", image_id: int) -> LoopClosingResult:
        """Add keyframe ``image_id`` of ``seg`` (the current segment) and look for a loop through it; a loop in
        ``seg`` is corrected in place (keyframe poses, points, frames' relative poses via ``state``)."""
        if not self.config.enabled:
            return LoopClosingResult(reason="loop closing disabled")
        for other in sorted(seg.slam_map.keyframes):  # the initial pair's keyframes come without a step
            if other != image_id and (seg.id, other) not in self._key_of:
                self.add(seg, other)
        key, bow = self.add(seg, image_id)
        self._segments = state.segments  # candidates may be in any segment
        c = self.config
        slam_map = seg.slam_map
        since = image_id - max(state.last_loop_image_id, 0) if state.last_loop_segment == seg.id else image_id
        young = slam_map.num_keyframes < c.min_keyframes or since < c.min_keyframes
        others = any(s is not seg and s.merged_into < 0 for s in state.segments)
        if young and (not others or slam_map.num_keyframes < c.merge_min_keyframes):
            state.loop_groups = ()
            return LoopClosingResult(reason="too few keyframes")
        candidates = self._candidates(seg, image_id, key, bow)
        if young:  # a young map may recognise an earlier segment (and merge), not close a loop in itself
            candidates = [k for k in candidates if self._where[k][0] != seg.id]
        groups = {cand: self._group(cand) for cand in candidates}
        state.loop_groups, consistent = update_consistent_groups(state.loop_groups, groups, c.min_consistency)
        if not consistent:
            return LoopClosingResult(len(candidates), reason="no consistent candidate")
        found, aliased, refused = None, 0, []
        for cand in consistent[:c.max_verifications]:
            found, why = self._verify(seg, image_id, cand)
            if found is not None and found.segment is seg and self._drift_ratio(state, seg, image_id, found) > \
                    c.max_correction:
                found, aliased, why = None, aliased + 1, "implausible: perceptual aliasing"
            if found is not None:
                break
            seg_id, cand_id = self._where[cand]
            refused.append(f"frame {self._segment(seg_id).slam_map.keyframes[cand_id].frame_index}: {why}")
        n_verified = min(len(consistent), c.max_verifications)
        if found is None:
            return LoopClosingResult(len(candidates), n_verified,
                                     reason=f"no candidate verified ({'; '.join(refused)})")
        state.loop_groups = ()
        v = found.verification
        if found.segment is not seg:
            mc = MergeCandidate(seg.id, image_id, found.segment.id, found.image_id, v.num_matches, v.num_inliers,
                                v.tgt_from_src, found.pairs)
            return LoopClosingResult(len(candidates), n_verified, merge_candidate=mc, reason="place of another segment")
        if not c.correct:
            cand = found.segment.slam_map.keyframes[found.image_id].frame_index
            return LoopClosingResult(len(candidates), n_verified, reason=(
                f"loop detected with the keyframe of frame {cand} ({v.num_inliers}/{v.num_matches} inliers), not "
                "corrected (loop_closing.correct is off)"))
        closure = self._correct(state, seg, image_id, found)
        state.last_loop_segment, state.last_loop_image_id = seg.id, image_id
        state.loop_closures.append(closure.to_dict())
        return LoopClosingResult(len(candidates), n_verified, closure=closure, needs_global_ba=c.global_ba,
                                 reason=str(closure))

    def _candidates(self, seg: "Segment", image_id: int, key: int, bow: tuple[np.ndarray, np.ndarray]) -> list[int]:
        """Keys of the database candidates of keyframe ``image_id``: not covisible, not recent, scored at least
        as high as its least similar covisible neighbour."""
        c, db = self.config, self._database()
        covisible = seg.slam_map.covisible(image_id)
        neighbours = [self._key_of[(seg.id, i)] for i, w in covisible[:50]
                      if w >= c.neighbour_weight and (seg.id, i) in self._key_of]
        if not neighbours:
            return []
        min_score = min(db.score(key, k) for k in neighbours)
        exclude = {key} | set(neighbours) | {self._key_of[(seg.id, i)] for i, w in covisible
                                              if w >= c.neighbour_weight and (seg.id, i) in self._key_of}
        exclude |= {self._key_of[(seg.id, i)] for i in range(image_id - c.recent_keyframes, image_id)
                    if (seg.id, i) in self._key_of}
        found = db.query_bow(*bow, k=c.query_candidates, exclude=exclude)
        return [k for k, s in found if s >= min_score]

    def _group(self, key: int) -> list[int]:
        """Keys of a candidate's consistency group: the keyframes inserted around it (``group_span``)."""
        seg_id, image_id = self._where[key]
        around = _around(self._segment(seg_id).slam_map, image_id, self.config.group_span)
        return [self._key_of[(seg_id, i)] for i in around if (seg_id, i) in self._key_of]

    def _segment(self, seg_id: int) -> "Segment":
        return self._segments[seg_id]

    # ----------------------------------------------------------------- verification
    def _verify(self, seg: "Segment", image_id: int, cand_key: int) -> tuple[_Verified | None, str]:
        """Match keyframe ``image_id``'s map points to those of the candidate and its neighbours; a robust
        Sim(3) with enough inliers makes a loop. Returns (the loop or None, why not)."""
        c = self.config
        cand_seg = self._segment(self._where[cand_key][0])
        cand_id = self._where[cand_key][1]
        q_ids, q_desc, binary, q_obs = _keyframe_points(seg.slam_map, [image_id])
        group = _around(cand_seg.slam_map, cand_id, c.candidate_neighbours)
        c_ids, c_desc, _, c_obs = _keyframe_points(cand_seg.slam_map, group)
        if len(q_ids) < c.min_inliers or len(c_ids) < c.min_inliers:
            return None, f"too few map points ({len(q_ids)} and {len(c_ids)})"
        if cand_seg is seg:  # points both keyframes already share are no evidence of a loop
            keep = ~np.isin(c_ids, q_ids)
            c_ids, c_desc, c_obs = c_ids[keep], c_desc[keep], c_obs[keep]
        check = c.verification if cand_seg is seg else c.merge_verification
        check = replace(check, min_inliers=max(check.min_inliers, c.min_inliers))
        q_xyz, c_xyz = seg.slam_map.points_xyz(q_ids), cand_seg.slam_map.points_xyz(c_ids)
        if c.reprojection_check and cand_seg is seg:
            pairs = match_map_points(q_desc, c_desc, binary)
            verification = _verify_by_reprojection(seg.slam_map, q_xyz[pairs[:, 0]], q_obs[pairs[:, 0]],
                                                   c_xyz[pairs[:, 1]], c_obs[pairs[:, 1]], check)
        else:
            verification, pairs = verify_loop_candidate(q_xyz, q_desc, c_xyz, c_desc, binary, check)
        if not verification.accepted:
            return None, verification.reason
        inl = pairs[verification.inlier_mask]
        return _Verified(cand_seg, cand_id, verification, np.stack([q_ids[inl[:, 0]], c_ids[inl[:, 1]]], axis=1)), ""

    def _drift_ratio(self, state: "SlamState", seg: "Segment", image_id: int, found: _Verified) -> float:
        """How far the verified Sim(3) would move the query keyframe, as a fraction of the path the camera
        travelled in ``seg`` from the candidate keyframe to it (every posed frame's centre in between)."""
        m = seg.slam_map
        first, last = sorted((m.keyframes[found.image_id].frame_index, m.keyframes[image_id].frame_index))
        first = max(first, 0)  # a loaded map's keyframe (slamkit.map_reuse): the path since this run began
        poses = [state.pose_of(r) for r in state.records[first:last + 1] if r.segment == seg.id]
        centres = np.array([_center(p) for p in poses if p is not None])
        path = float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum()) if len(centres) > 1 else 0.0
        sim = found.verification.tgt_from_src
        c_q = _center(_matrix(m.cam_from_world(image_id)))
        move = float(np.linalg.norm(sim[:3, :3] @ c_q + sim[:3, 3] - c_q))
        return move / path if path > 0 else float("inf")

    # ----------------------------------------------------------------- correction
    def _correct(self, state: "SlamState", seg: "Segment", image_id: int, found: _Verified) -> LoopClosure:
        """Pose graph, points following their keyframes, frames' relative poses rescaled, duplicates fused."""
        c, slam_map = self.config, seg.slam_map
        rec = slam_map.reconstruction
        ids = sorted(slam_map.keyframes)
        poses = {i: _matrix(slam_map.cam_from_world(i)) for i in ids}
        edges = relative_edges(poses, zip(ids, ids[1:]), kind="spanning")
        covis = sorted({(min(i, j), max(i, j)) for i in ids for j, w in slam_map.covisible(i)
                        if w >= c.covisibility_weight and j != i})
        edges += relative_edges(poses, covis)
        sim = found.verification.tgt_from_src
        # the sides of the loop by insertion order: in a room the query's covisible keyframes include old ones
        # (tracked again on the second lap) and the candidate's new ones; a loop edge between two keyframes of the
        # same side would move an old keyframe by the drift of the new ones
        mid = (image_id + found.image_id) / 2
        q_group = [image_id] + [i for i, _ in slam_map.covisible(image_id) if i > mid][:c.loop_group]
        c_group = [found.image_id] + [i for i, _ in slam_map.covisible(found.image_id) if i < mid][:c.loop_group]
        edges += [loop_edge(a, b, poses[a], poses[b], sim) for a in q_group for b in c_group]
        fixed = {found.image_id, ids[0]} - set(q_group)
        fixed |= {i for i in ids if slam_map.keyframes[i].frame_index < 0} - set(q_group)  # a loaded map's: held
        result = optimize_pose_graph(poses, edges, fixed or {ids[0]}, PoseGraphConfig())
        point_ids = np.array(sorted(rec.point3D_ids()), np.int64)
        refs = np.array([min(el.image_id for el in rec.point3D(int(p)).track.elements) for p in point_ids.tolist()],
                        np.int64)
        xyz = correct_points(slam_map.points_xyz(point_ids), refs, poses, result)
        slam_map.set_positions(point_ids, xyz)
        for i in ids:
            rec.frame(i).rig_from_world = rigid_from_matrix(result.cam_from_world[i])
        state.apply_loop_correction(seg, result.scales)
        fused = _fuse(slam_map, found.pairs)
        before, after = poses[image_id], result.cam_from_world[image_id]
        move = float(np.linalg.norm(_center(before) - _center(after)))
        angle = _angle_deg(after[:3, :3] @ before[:3, :3].T)
        v = found.verification
        qf, cf = slam_map.keyframes[image_id].frame_index, slam_map.keyframes[found.image_id].frame_index
        return LoopClosure(seg.id, image_id, int(qf), found.image_id, int(cf), v.num_matches, v.num_inliers, move,
                           angle, float(sim3_decompose(sim)[0]), fused, len(ids))


def _around(slam_map: "SlamMap", image_id: int, span: int) -> list[int]:
    """Keyframe ``image_id`` and the ``span`` keyframes inserted before and after it (image ids)."""
    ids = sorted(slam_map.keyframes)
    at = bisect.bisect_left(ids, image_id)
    return ids[max(0, at - span):at + span + 1]


def _keyframe_points(slam_map: "SlamMap", image_ids: list[int]) -> tuple[np.ndarray, np.ndarray, bool, np.ndarray]:
    """(M,) unique map point ids observed by the keyframes, (M, D) the descriptor of the first observation,
    whether descriptors are binary, and (M, 2) int64 that observation (image id, keypoint index)."""
    ids, desc, obs, seen, binary = [], [], [], set(), True
    for i in image_ids:
        kf = slam_map.keyframes[i]
        binary = kf.features.binary
        pid = slam_map.point3D_ids(i)
        for j in np.flatnonzero(pid >= 0).tolist():
            p = int(pid[j])
            if p not in seen:
                seen.add(p)
                ids.append(p)
                desc.append(kf.features.descriptors[j])
                obs.append((i, j))
    d = np.array(desc) if desc else np.zeros((0, 32), np.uint8)
    return np.array(ids, np.int64), d, binary, np.array(obs, np.int64).reshape(-1, 2)


def _verify_by_reprojection(slam_map: "SlamMap", q_xyz: np.ndarray, q_obs: np.ndarray, c_xyz: np.ndarray,
                            c_obs: np.ndarray, check) -> "LoopVerification":
    """A loop's Sim(3) by RANSAC on reprojection in both keyframes and refined the same way
    (:func:`~slamkit.loop_verification.verify_loop_by_reprojection`, ORB-SLAM's Sim3Solver and OptimizeSim3).
    Pair i: the query point at ``q_xyz[i]`` observed as ``q_obs[i]`` = (image id, keypoint) in the query
    keyframe, the candidate point likewise in a keyframe of the candidate's group."""
    def side(obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        poses = {i: _matrix(slam_map.cam_from_world(i)) for i in np.unique(obs[:, 0]).tolist()}
        xy = np.zeros((len(obs), 2))
        scales = np.ones(len(obs))
        for i in poses:
            sel = obs[:, 0] == i
            kf = slam_map.keyframes[i]
            xy[sel] = kf.keypoints[obs[sel, 1]]
            scales[sel] = keypoint_scales(kf.features)[obs[sel, 1]]
        return np.stack([poses[i] for i in obs[:, 0].tolist()]).reshape(-1, 4, 4), xy, scales

    if len(q_obs) < 3:
        return LoopVerification(LoopStatus.TOO_FEW_MATCHES, len(q_obs))
    T_q, xy_q, s_q = side(q_obs)  # one keyframe: the query
    T_c, xy_c, s_c = side(c_obs)
    return verify_loop_by_reprojection(slam_map.camera.K, q_xyz, T_q[0], xy_q, s_q, c_xyz, T_c, xy_c, s_c, check)


def _fuse(slam_map: "SlamMap", pairs: np.ndarray) -> int:
    """Merge each (query point, candidate point) pair into one track (``ObservationManager.merge_points3D``)
    unless the two tracks share an image (a track observes a point once per image). Returns merges made."""
    rec, obs = slam_map.reconstruction, slam_map.observations
    alias: dict[int, int] = {}
    fused = 0
    def current(p: int) -> int:
        while p in alias:
            p = alias[p]
        return p

    for a, b in pairs.tolist():
        a, b = current(a), current(b)
        if a == b or not rec.exists_point3D(a) or not rec.exists_point3D(b):
            continue
        ia = {el.image_id for el in rec.point3D(a).track.elements}
        if ia & {el.image_id for el in rec.point3D(b).track.elements}:
            continue
        new = int(obs.merge_points3D(b, a))  # b (older) first: its position weighs by track length anyway
        alias[a] = alias[b] = new
        fused += 1
    slam_map.changed()
    return fused


def _matrix(rigid) -> np.ndarray:
    out = np.eye(4)
    out[:3] = rigid.matrix()
    return out


def _center(cam_from_world: np.ndarray) -> np.ndarray:
    return -cam_from_world[:3, :3].T @ cam_from_world[:3, 3]


def _angle_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


__all__ = ["LoopCloser", "LoopClosingConfig", "LoopClosingResult", "LoopClosure", "MergeCandidate",
           "ConsistentGroup"]
