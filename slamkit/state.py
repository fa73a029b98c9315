"""The SLAM state as a value: what a run is, apart from the stages that change it.

:class:`SlamState` holds the frame records (each frame's status and pose), the map segments, and the
tracking cursor and counters; :class:`~slamkit.pipeline.Slam` composes the stages over one such value, and
a session (:mod:`slamkit.session`) saves and restores it field by field. Every frame's pose is stored
relative to its reference keyframe (``rel_pose`` = cam_from_refcam), so frames follow their keyframe through
bundle adjustment, normalization only rescales those relative translations, and culling a keyframe
re-anchors its frames to a neighbour without changing their absolute poses.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING, Sequence

import numpy as np

from .types import Fingerprint, Trajectory

if TYPE_CHECKING:  # pragma: no cover
    from .features import FrameFeatures
    from .local_map import LocalMap
    from .map import SlamMap


ROTATION_ONLY = "rotation only: no 3-D structure"
"""What the summary, the progress line and the step results say of a map made by rotation alone."""
ROTATION, GENERAL = "rotation", "general"
"""``FrameRecord.motion_model``: posed by its rotation alone (position held), or in 6-DoF."""


class FrameStatus(StrEnum):
    """What became of a frame. A ``str``: saved JSON and CSV hold the plain strings, and
    ``status == "tracked"`` holds."""

    INITIALIZING = "initializing"
    """Buffered by the initializer (no map yet)."""
    INITIALIZED = "initialized"
    """The step that built the initial map (its result only; the record says tracked or lost)."""
    TRACKED = "tracked"
    LOST = "lost"
    SKIPPED = "skipped"
    """Featureless, or unreadable (``FrameRecord.unreadable`` says why)."""
    ERROR = "error"
    """A stage raised while processing the frame (``SlamState.errors`` has the message)."""


@dataclass(eq=False)
class FrameRecord:
    """Pose bookkeeping of one frame: pose = rel_pose (cam_from_refcam) @ pose of the reference keyframe."""

    index: int
    frame_id: int
    timestamp: float
    status: FrameStatus
    segment: int = -1
    ref_image_id: int = -1
    rel_pose: np.ndarray | None = None
    keyframe_image_id: int = -1
    degenerate: bool = False
    unreadable: str = ""
    """Why the source could not deliver the frame (corrupt file, undecodable video frame, another image
    size), when it was skipped for that."""
    motion_model: str = ""
    """The motion model chosen for the frame (``stages.motion_model_selection``): "rotation", "general" or ""
    (not chosen)."""
    orientation: np.ndarray | None = None
    """(3, 3) rotation from the first frame of its rotation chain (``slamkit.rotation_phase``), or None."""
    rotation_chain: int = -1
    """Index of the first frame of the frame's rotation chain (-1: none)."""
    rotation_ref: int = -1
    """Index of the rotation keyframe its orientation was measured against (-1: none)."""
    file: str = ""
    """The frame's :class:`~slamkit.types.Fingerprint`, measured when it was read (issue 50): the file's name
    (a video's), "" when the source has none (rendered) or the frame could not be read; ..."""
    file_bytes: int = -1
    """... its size in bytes (-1: none); ..."""
    width: int = 0
    """... the image's width and height in pixels; ..."""
    height: int = 0
    sha256: str = ""
    """... and the SHA-256 of what was read ("" when none). Saved in sessions and ``frames.csv``; export and
    resume compare the source with it."""

    def __post_init__(self) -> None:
        self.status = FrameStatus(self.status)

    @classmethod
    def of_frame(cls, frame, status: FrameStatus) -> "FrameRecord":
        """The record of a :class:`~slamkit.types.Frame` just read, with its fingerprint."""
        record = cls(frame.index, frame.frame_id, frame.timestamp, status)
        record.read_from(frame.fingerprint)
        return record

    @property
    def fingerprint(self) -> Fingerprint | None:
        """What the frame was read from (None: nothing recorded)."""
        if not self.sha256:
            return None
        return Fingerprint(self.file, int(self.file_bytes), int(self.width), int(self.height), self.sha256)

    def read_from(self, fingerprint: Fingerprint | None) -> None:
        """Record what the frame was read from (nothing for None)."""
        if fingerprint is not None:
            self.file, self.file_bytes, self.sha256 = fingerprint.file, fingerprint.bytes, fingerprint.sha256
            self.width, self.height = fingerprint.width, fingerprint.height


@dataclass(eq=False)
class RecentPoints:
    """Map points created by local mapping (``slamkit.stages.local_mapper``) that have not passed ORB-SLAM's
    recent-point test yet: ids (K,) int64, the mapping step that created each (birth), and in how many tracked
    frames each was predicted visible (projected inside the image from the local map) and found (a pose
    inlier). ``steps``: keyframes local mapping has inserted in the segment."""

    ids: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    birth: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    visible: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    found: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    steps: int = 0

    def add(self, ids) -> None:
        """New points, born at the current step, seen and found by the keyframe that created them."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        ones = np.ones(len(ids), np.int64)
        self.ids = np.concatenate([self.ids, ids])
        self.birth = np.concatenate([self.birth, ones * self.steps])
        self.visible = np.concatenate([self.visible, ones])
        self.found = np.concatenate([self.found, ones])

    def keep(self, mask: np.ndarray) -> None:
        """Keep the points where ``mask`` (K,) is True."""
        self.ids, self.birth, self.visible, self.found = (a[mask] for a in (self.ids, self.birth, self.visible,
                                                                             self.found))

    def observe(self, visible_ids: np.ndarray, found_ids: np.ndarray) -> None:
        """Count a tracked frame: the points it predicted visible and the points it found (ids, any order)."""
        if len(self.ids):
            self.visible += np.isin(self.ids, visible_ids)
            self.found += np.isin(self.ids, found_ids)

    def as_array(self) -> np.ndarray:
        """(K, 4) int64 [id, birth, visible, found] (sessions)."""
        return np.stack([self.ids, self.birth, self.visible, self.found], axis=1).reshape(-1, 4)

    @classmethod
    def from_array(cls, a: np.ndarray, steps: int) -> "RecentPoints":
        a = np.asarray(a, np.int64).reshape(-1, 4)
        return cls(a[:, 0].copy(), a[:, 1].copy(), a[:, 2].copy(), a[:, 3].copy(), int(steps))


@dataclass(eq=False)
class Segment:
    """One map segment: its map, the frames posed in it, and the features of the frames posed at
    initialization (re-tracked against the final map by ``Slam.finish``)."""

    id: int
    slam_map: "SlamMap"
    frames: list[int] = field(default_factory=list)
    initial_frames: list["FrameFeatures"] = field(default_factory=list)
    signatures: dict[int, np.ndarray] = field(default_factory=dict)
    """Global image signature of each keyframe (image id), for relocalization."""
    relocalizations: int = 0
    keyframes_culled: int = 0
    """Keyframes removed from the map as redundant (``keyframes.cull_redundant``)."""
    recent_points: RecentPoints = field(default_factory=RecentPoints)
    """Points local mapping created recently and still tests (``mapper.method = "local"``)."""
    merged_into: int = -1
    """Id of the segment this one was merged into (``slamkit.merging.merge_segments``; it is then empty and
    kept only so segment ids stay indices), -1 while it is a map of its own."""
    prior: bool = False
    """Loaded from a saved run's map (``Slam(..., map=RUN_DIR)``, :mod:`slamkit.map_reuse`): its keyframes are
    no frames of this run (negative frame indices)."""
    rotation_only: bool = False
    """The frames only turned: one keyframe, no points, every frame posed by its orientation
    (``slamkit.rotation_phase.rotation_only_segment``)."""


def _matrix(rigid) -> np.ndarray:
    """(4, 4) of a pycolmap Rigid3d."""
    out = np.eye(4)
    out[:3] = rigid.matrix()
    return out


@dataclass(eq=False)
class SlamState:
    """Everything a run has done so far; saved and restored as a whole by :mod:`slamkit.session`."""

    records: list[FrameRecord] = field(default_factory=list)
    """One per processed frame, in order (``records[i].index == i``)."""
    segments: list[Segment] = field(default_factory=list)
    segment: Segment | None = None
    """The segment being tracked (None while initializing)."""
    local_map: "LocalMap | None" = None
    """The map points frames are tracked against (around ``last_keyframe``)."""
    cursor: int = 0
    """Frames consumed (the next frame's position in ``Slam.indices``)."""
    last_keyframe: int = -1
    """Image id of the last (reference) keyframe of the current segment."""
    points_at_last_keyframe: int = 0
    """Map points the last keyframe observed when it was inserted (the weak-tracking rule compares)."""
    consecutive_lost: int = 0
    last_ids: np.ndarray | None = None
    """(K,) map point ids tracked in the previous frame (the motion-model search looks for these)."""
    init_message: str = ""
    """The initializer's last failure (for the summary's ``not_initialized_reason``)."""
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per stage, summed over the run."""
    wall_time: float = 0.0
    cpu_time: float = 0.0
    errors: dict[int, str] = field(default_factory=dict)
    """Frame index -> the exception a stage raised on it (those frames have status ``error``)."""
    finished: bool = False
    """``Slam.finish`` ran (final global BA, initial frames re-tracked)."""
    loop_groups: tuple = ()
    """Loop-candidate groups of the last keyframe (``loop_verification.ConsistentGroup``; keys are keyframe
    frame indices), continued by the next keyframe's candidates (loop closing's consistency check)."""
    loop_closures: list[dict] = field(default_factory=list)
    """One entry per closed loop (``LoopClosure.to_dict()``: segment, keyframes, matches, inliers, correction)."""
    map_merges: list[dict] = field(default_factory=list)
    """One entry per map merge (segment merged, into which, the keyframes' frame indices, inliers, keyframes
    moved, points fused, the Sim(3)'s scale)."""
    last_loop_segment: int = -1
    last_loop_image_id: int = -1
    """Segment and image id of the keyframe that closed the last loop (-1: none yet)."""

    # ----------------------------------------------------------------- poses
    def pose_of(self, rec: FrameRecord | int) -> np.ndarray | None:
        """(4, 4) cam_from_world of a frame (record or index) in its segment's map, or None."""
        if isinstance(rec, (int, np.integer)):
            rec = self.records[int(rec)]
        if rec.rel_pose is None:
            return None
        slam_map = self.segments[rec.segment].slam_map
        ref = np.eye(4)
        ref[:3] = slam_map.reconstruction.frame(rec.ref_image_id).rig_from_world.matrix()
        return rec.rel_pose @ ref

    def set_pose(self, rec: FrameRecord, ref_image_id: int, pose: np.ndarray, status: FrameStatus,
                 absolute: bool = False) -> None:
        """Pose ``rec`` in the current segment relative to keyframe ``ref_image_id``; ``pose`` is
        cam_from_refcam, or cam_from_world when ``absolute``."""
        seg = self.segment
        if absolute:
            pose = pose @ np.linalg.inv(_matrix(seg.slam_map.cam_from_world(ref_image_id)))
        rec.ref_image_id = ref_image_id
        rec.rel_pose = pose
        rec.segment = seg.id
        rec.status = status
        if not seg.frames or seg.frames[-1] != rec.index:
            seg.frames.append(rec.index)

    def skip_unreadable(self, frame_id: int, timestamp: float, error: Exception) -> FrameRecord:
        """The frame at the cursor could not be read: its record ("skipped", ``unreadable`` = the source's
        message), the cursor past it; the map and the tracking state are untouched."""
        record = FrameRecord(self.cursor, frame_id, timestamp, FrameStatus.SKIPPED, unreadable=str(error))
        self.cursor += 1
        self.records.append(record)
        return record

    def mark_error(self, rec: FrameRecord, message: str, posed: bool = False) -> None:
        """A stage raised on frame ``rec``: status "error" and no pose (a keyframe keeps its pose: it is in
        the map), unless ``posed`` (the frame was complete; only what came after it failed)."""
        if not posed:
            if rec.rel_pose is not None and rec.keyframe_image_id < 0:
                if 0 <= rec.segment < len(self.segments) and rec.index in self.segments[rec.segment].frames:
                    self.segments[rec.segment].frames.remove(rec.index)
                rec.rel_pose, rec.ref_image_id, rec.segment = None, -1, -1
            rec.status = FrameStatus.ERROR
        self.errors[rec.index] = message

    def reanchor(self, seg: Segment, image_id: int, anchor: int, culled_from_anchor: np.ndarray) -> None:
        """Frames posed relative to keyframe ``image_id`` (and the keyframe's own frame) are posed relative
        to ``anchor`` instead, with the same absolute poses. culled_from_anchor: (4, 4)
        cam_from_world(image_id) @ inv(cam_from_world(anchor))."""
        for i in seg.frames:
            rec = self.records[i]
            if rec.ref_image_id == image_id and rec.rel_pose is not None:
                rec.rel_pose = rec.rel_pose @ culled_from_anchor
                rec.ref_image_id = anchor
            if rec.keyframe_image_id == image_id:
                rec.keyframe_image_id = -1

    def apply_normalization(self, seg: Segment, scale: float) -> None:
        """The segment's map was scaled by ``scale`` (``Reconstruction.normalize``): so are the relative
        translations of its frames."""
        for i in seg.frames:
            rel = self.records[i].rel_pose
            if rel is not None:
                rel[:3, 3] *= scale

    def apply_loop_correction(self, seg: Segment, scales: dict[int, float]) -> None:
        """Keyframes of ``seg`` were corrected by a Sim(3) pose graph: keyframe k's rigid pose is ``(R, t / s_k)``
        of its corrected similarity, so a frame posed relative to k keeps its relative rotation and its relative
        translation shrinks by ``s_k`` (``scales``: image id -> s_k)."""
        for i in seg.frames:
            rec = self.records[i]
            s = scales.get(rec.ref_image_id)
            if rec.rel_pose is not None and rec.segment == seg.id and s is not None:
                rec.rel_pose[:3, 3] /= s

    # ----------------------------------------------------------------- segments
    def start_segment(self, slam_map: "SlamMap", frames: Sequence["FrameFeatures"],
                      initial_frames: list["FrameFeatures"]) -> Segment:
        """A new segment around a freshly initialized map (it becomes the current one): its keyframes' frames
        are posed, with their signatures from ``frames``; tracking continues from the newest keyframe.
        ``initial_frames``: the frames to track again at the end (``Slam.finish``)."""
        seg = Segment(len(self.segments), slam_map, initial_frames=initial_frames)
        self.segments.append(seg)
        self.segment = seg
        by_index = {f.index: f for f in frames}
        for image_id, kf in sorted(slam_map.keyframes.items()):
            if by_index.get(kf.frame_index) is not None and by_index[kf.frame_index].signature is not None:
                seg.signatures[image_id] = by_index[kf.frame_index].signature
            self.add_keyframe(self.records[kf.frame_index], image_id)
        self.last_keyframe = max(slam_map.keyframes)
        self.points_at_last_keyframe = slam_map.reconstruction.image(self.last_keyframe).num_points3D
        self.consecutive_lost = 0
        return seg

    def add_keyframe(self, rec: FrameRecord, image_id: int) -> None:
        """Frame ``rec`` is keyframe ``image_id`` of the current segment (its own reference)."""
        self.set_pose(rec, image_id, np.eye(4), FrameStatus.TRACKED)
        rec.keyframe_image_id = image_id

    def end_segment(self) -> None:
        """Tracking is lost for good: the next frames initialize a new segment."""
        self.last_ids = None
        self.segment = None
        self.local_map = None
        self.last_keyframe = -1
        self.consecutive_lost = 0

    @property
    def main_segment(self) -> Segment | None:
        """The segment with the most posed frames (merged segments are part of their target)."""
        live = self.live_segments
        if not live:
            return None
        return max(live, key=lambda s: (len(s.frames), -s.id))

    @property
    def live_segments(self) -> list[Segment]:
        """The segments that are maps of their own (not merged into another)."""
        return [s for s in self.segments if s.merged_into < 0]

    def resolve_segment(self, segment: int) -> Segment:
        """Segment ``segment``, or the segment it was merged into (following merges)."""
        seg = self.segments[segment]
        while seg.merged_into >= 0:
            seg = self.segments[seg.merged_into]
        return seg

    @property
    def slam_map(self) -> "SlamMap | None":
        """The map of the current segment (or of the largest one once tracking ended)."""
        if self.segment is not None:
            return self.segment.slam_map
        main = self.main_segment
        return main.slam_map if main is not None else None

    def trajectory(self, keyframes_only: bool = False, segment: int | None = None) -> Trajectory:
        """Camera-to-world poses of the posed frames of a segment (default: the main one), source timestamps."""
        seg = self.main_segment if segment is None else self.resolve_segment(segment)
        if seg is None:
            return Trajectory(np.empty(0), np.empty((0, 4, 4)))
        ts, poses = [], []
        for i in seg.frames:
            rec = self.records[i]
            if rec.segment != seg.id or rec.rel_pose is None:
                continue
            if keyframes_only and rec.keyframe_image_id < 0:
                continue
            ts.append(rec.timestamp)
            poses.append(np.linalg.inv(self.pose_of(rec)))
        return Trajectory(np.array(ts), np.array(poses).reshape(-1, 4, 4))

    # ----------------------------------------------------------------- counters
    def add_timings(self, timings: dict[str, float]) -> None:
        for k, v in timings.items():
            self.timings[k] = self.timings.get(k, 0.0) + v

    def count(self, status: FrameStatus) -> int:
        return sum(r.status == status for r in self.records)

    def why_not_initialized(self) -> str:
        """Why no map exists yet (for the summary): featureless frames, or the initializer's last reason."""
        featureless = sum(r.status == FrameStatus.SKIPPED and not r.unreadable for r in self.records)
        if self.records and featureless == len(self.records):
            return (f"all {featureless} frames so far had fewer than 8 keypoints (featureless: black, blank or "
                    "badly blurred images?)")
        if self.init_message:
            return f"no initial pair found; last attempt: {self.init_message}"
        if not self.records:
            return "no frame processed yet"
        return f"no initial pair tried yet ({self.records[-1].status}: {len(self.records)} frames so far)"

    def summary(self, frames_total: int, not_initialized_reason: str | None) -> dict:
        """Counts, map size and timings of the run so far, JSON-serialisable (``Slam.summary`` adds the
        source and the config)."""
        n = len(self.records)
        posed = sum(r.rel_pose is not None for r in self.records)
        main = self.main_segment
        slam_map = main.slam_map if main else None
        n_kf = slam_map.num_keyframes if slam_map else 0
        return {
            "frames": n,
            "frames_total": int(frames_total),
            "frames_posed": int(posed),
            "frames_lost": int(self.count(FrameStatus.LOST)),
            "frames_skipped": int(self.count(FrameStatus.SKIPPED)),
            "frames_degenerate": int(sum(r.degenerate for r in self.records)),
            "frames_unreadable": int(sum(bool(r.unreadable) for r in self.records)),
            "unreadable_frames": [{"frame": r.index, "frame_id": r.frame_id, "error": r.unreadable}
                                  for r in self.records if r.unreadable],
            "not_initialized_reason": not_initialized_reason,
            "fraction_posed": posed / n if n else 0.0,
            "keyframes": n_kf,
            "points3D": slam_map.num_points if slam_map else 0,
            "points_per_image": slam_map.points_per_image() if slam_map else 0.0,
            "mean_reprojection_error_px": slam_map.mean_reprojection_error() if slam_map else 0.0,
            "segments": [{"id": s.id, "frames": len(s.frames), "first_frame": s.frames[0] if s.frames else None,
                          "last_frame": s.frames[-1] if s.frames else None, "relocalizations": s.relocalizations,
                          "keyframes": s.slam_map.num_keyframes, "points3D": s.slam_map.num_points}
                         for s in self.live_segments],
            "main_segment": main.id if main else None,
            "structure": ROTATION_ONLY if main is not None and main.rotation_only else ("3-D" if main else "none"),
            "frames_rotation_only": int(sum(r.motion_model == "rotation" for r in self.records)),
            "merges": int(sum(s.merged_into >= 0 for s in self.segments)),
            "map_merges": [dict(m) for m in self.map_merges],
            "relocalizations": int(sum(s.relocalizations for s in self.segments)),
            "keyframes_culled": int(sum(s.keyframes_culled for s in self.segments)),
            "loop_closures": len(self.loop_closures),
            "loop_closure_pairs": [{"segment": c["segment"], "query_frame": c["query_frame"],
                                    "candidate_frame": c["candidate_frame"], "inliers": c["inliers"],
                                    "translation_m": c["translation_m"], "rotation_deg": c["rotation_deg"],
                                    "scale": c["scale"]} for c in self.loop_closures],
            "cpu_time_s": self.cpu_time,
            "wall_time_s": self.wall_time,
            "fps": n / self.wall_time if self.wall_time > 0 else 0.0,
            "initialization_s": self.timings.get("initialize", 0.0),
            "seconds_per_frame": self.wall_time / n if n else 0.0,
            "seconds_per_keyframe": self.wall_time / n_kf if n_kf else 0.0,
            "timings_s": dict(self.timings),
            "stage_ms_per_frame": self.stage_ms_per_frame(),
        }

    def stage_ms_per_frame(self) -> dict[str, float]:
        """Milliseconds per frame of each stage so far, costliest first. ``read`` and ``features`` run on the
        prefetch thread (``SlamConfig.prefetch``), beside the others; the rest are the main thread's."""
        n = max(len(self.records), 1)
        return {k: 1e3 * v / n for k, v in sorted(self.timings.items(), key=lambda kv: (-kv[1], kv[0]))}

    def describe_speed(self, stages: int = 3) -> str:
        """``track 32, ba 24, features 18 ms/frame``: where the time goes so far (the costliest stages)."""
        return describe_stages(self.stage_ms_per_frame(), stages)


def describe_stages(ms_per_frame: dict[str, float], stages: int = 3) -> str:
    """The ``stages`` costliest stages of ``{stage: ms per frame}``: ``track 32, ba 24, features 18 ms/frame``."""
    top = sorted(ms_per_frame.items(), key=lambda kv: (-kv[1], kv[0]))[:stages]
    return ", ".join(f"{k} {v:.0f}" for k, v in top) + " ms/frame" if top else ""
