"""Frames that only turn before a map exists (issue 42): their orientations, and what becomes of them.

A clip that starts by panning gives the two-view initializer no parallax: it refuses every pair. Meanwhile
each buffered frame is compared with a *rotation keyframe* (a frame of the same chain, still in the
initializer's window; the previous frame when the keyframe has too few matches left) by
:class:`~slamkit.stages.motion_model_selection.MotionModelSelector`. When GRIC picks rotation-only, the frame
joins the keyframe's *rotation chain*: ``FrameRecord.orientation`` is its rotation from the chain's first
frame (``FrameRecord.rotation_chain``, that frame's index), the camera centre held (PTAM's and DT-SLAM's
rotation-only tracking). Rotation keyframes hold parallax back from accumulating between consecutive frames:
once the camera walks, the parallax to the keyframe grows until GRIC picks general motion, and the chain ends.

- when the initializer succeeds, :func:`anchor_rotation_chains` poses the chain frames that tracking against
  the new map could not pose (they looked elsewhere) in the same map: the chain's orientation aligned to its
  frames that the map did pose, the centre theirs (the median);
- when no map is ever made (a pure rotation), :func:`rotation_only_segment` makes a map of one keyframe and no
  points, and every frame of the longest chain gets its orientation: "rotation only: no 3-D structure".

After initialization a frame that tracking loses is posed by its rotation to the last keyframe, or, when it
has turned too far from it, to the previous posed frame (:meth:`RotationPhase.track_lost`: a chain of 2-D-only
references, DT-SLAM's rotation keyframes in their smallest form), the position held. Once PnP poses a frame
again, the held frames before it get centres interpolated in time between the two 6-DoF poses
(:func:`interpolate_held_centres`), again on the final poses at the end of the run
(:func:`recentre_held_frames`). Their keypoints are not triangulated into the map yet
(:mod:`slamkit.stages.deferred_triangulation` is the stage that would).
"""

from __future__ import annotations

import numpy as np
import pycolmap

from dataclasses import dataclass

from .features import FrameFeatures, MatchingConfig, NearestNeighborMatcher, PairMatcher
from .kernels.geometry import rotation_angle_deg
from .map import SlamMap
from .stages.initializer import Initializer
from .stages.motion_model_selection import (GENERAL, ROTATION, MotionModelChoice, MotionModelSelectionConfig,
                                            MotionModelSelector, rotation_from_bearings)
from .state import ROTATION_ONLY, FrameRecord, FrameStatus, SlamState

MIN_KEYFRAME_INLIERS = 100
"""A rotation keyframe is replaced by the previous frame when fewer of the frame's matches to it are inliers."""

MAX_REFERENCES = 5
"""Buffered frames of its chain a frame's orientation is measured against (the reference and older ones)."""


@dataclass(frozen=True, eq=False)
class RotationStep:
    """What :meth:`RotationPhase.step` did with a buffered frame: the motion model chosen (or None), and
    whether the frame got an orientation."""

    choice: MotionModelChoice | None = None
    oriented: bool = False
    note: str = ""
    """The step message's prefix: "" unless the frame got an orientation."""

    @property
    def fields(self) -> dict:
        """The frame's ``StepResult`` fields (``motion_model``, ``motion_model_reason``)."""
        c = self.choice
        return {"motion_model": c.model if c else "", "motion_model_reason": c.reason if c else ""}


class RotationPhase:
    """Frames that only turn before a map exists: :meth:`step` per buffered frame, :meth:`anchor` once the
    initializer made a map, :meth:`finish` when none was ever made (the module's docstring explains)."""

    def __init__(self, config: MotionModelSelectionConfig = MotionModelSelectionConfig(),
                 matcher: PairMatcher | None = None):
        self.config = config
        self.selector = MotionModelSelector(config)
        self.matcher = matcher if matcher is not None else NearestNeighborMatcher(MatchingConfig())
        """Matches a lost frame with the last keyframe (:meth:`track_lost`): the run's matcher, else NN."""
        self.previous: FrameFeatures | None = None
        """The last frame posed in a map segment (by PnP or by rotation): the next lost frame's second rotation
        reference, DT-SLAM's 2-D-only keyframe in its smallest form. Saved in sessions (:meth:`state`,
        :meth:`restore`): a run resumed in the middle of a pan chains its next frame to it as the running one does."""

    def state(self) -> FrameFeatures | None:
        """What a session saves of the phase: :attr:`previous` (the only state it keeps between frames)."""
        return self.previous

    def restore(self, previous: FrameFeatures | None) -> None:
        """The phase as :meth:`state` saved it."""
        self.previous = previous

    def posed_by_pnp(self, state: SlamState, ff: FrameFeatures, record: FrameRecord, num_inliers: int) -> dict:
        """A frame tracking (or relocalization) posed by PnP against the map: its motion model is "general"
        (6-DoF) by construction, so ``record.motion_model`` says so without running GRIC (whose two RANSACs would
        cost every frame ~10 ms). The frames just before it that rotation held in place get their centres
        interpolated (:func:`interpolate_held_centres`). Returns the frame's ``StepResult`` fields."""
        record.motion_model, self.previous = GENERAL, ff
        held = interpolate_held_centres(state, record) if self.config.enabled else 0
        return {"motion_model": GENERAL, "motion_model_reason": f"general motion: 6-DoF pose by PnP against the map "
                f"({num_inliers} inliers; no GRIC needed)" + (f"; {held} frames held by rotation before it "
                                                              "re-centred on the way here" if held else "")}

    def step(self, state: SlamState, initializer: Initializer, ff: FrameFeatures, record: FrameRecord,
             K: np.ndarray) -> RotationStep:
        if not self.config.enabled:
            return RotationStep()
        choice = track_rotation(state, initializer, self.selector, ff, record, K)
        oriented = record.orientation is not None
        return RotationStep(choice, oriented, f"{ROTATION_ONLY} yet, orientation tracked; " if oriented else "")

    def track_lost(self, state: SlamState, ff: FrameFeatures, record: FrameRecord, K: np.ndarray) -> RotationStep:
        """A frame of a segment that neither the local map nor relocalization posed (too few map points in
        view, as when turning fast into the unmapped): when its matches to the last keyframe are a rotation
        only, it is posed in the same map by that rotation with the position held (the previous frame's
        centre, else the keyframe's): status tracked, ``motion_model`` "rotation", no keyframe."""
        seg = state.segment
        if not self.config.enabled or seg is None or state.last_keyframe not in seg.slam_map.keyframes:
            return RotationStep()
        kf = seg.slam_map.keyframes[state.last_keyframe]
        prev = state.records[record.index - 1] if record.index > 0 else None
        held = state.pose_of(prev) if prev is not None and prev.segment == seg.id else None
        T_kf = np.eye(4)
        T_kf[:3] = seg.slam_map.cam_from_world(state.last_keyframe).matrix()
        refs = [(f"keyframe {state.last_keyframe}", kf.features, kf.keypoints, T_kf)]
        p = self.previous
        if held is not None and p is not None and p.index == prev.index and p.index != kf.frame_index:
            refs.append((f"frame {p.index}", p.features, p.keypoints, held))  # turned too far from the keyframe
        for name, features, keypoints, T_ref in refs:
            m = self.matcher.match(features, ff.features)
            choice = self.selector.step(keypoints[m[:, 0]], ff.keypoints[m[:, 1]], K)
            record.motion_model = choice.model
            if choice.is_rotation and choice.inliers.sum() >= MIN_KEYFRAME_INLIERS // 2:
                break
        else:
            return RotationStep(choice)
        held = T_kf if held is None else held
        centre = -held[:3, :3].T @ held[:3, 3]
        T = np.eye(4)
        T[:3, :3] = choice.rotation @ T_ref[:3, :3]
        T[:3, 3] = -T[:3, :3] @ centre
        state.set_pose(record, state.last_keyframe, T, FrameStatus.TRACKED, absolute=True)
        state.consecutive_lost, state.last_ids, self.previous = 0, None, ff
        return RotationStep(choice, True, f"rotation only against {name} (position held); ")

    def anchor(self, state: SlamState) -> list[int]:
        """:func:`anchor_rotation_chains` in the current segment (none when tracking lost it again)."""
        return anchor_rotation_chains(state) if self.config.enabled and state.segment is not None else []

    def finish(self, state: SlamState, initializer: Initializer, camera) -> int:
        """At the end of the run (after the final bundle adjustment): :func:`rotation_only_segment` when the run
        has no map segment at all, else :func:`recentre_held_frames` on the final poses. Returns the frames
        posed or moved."""
        if not self.config.enabled:
            return 0
        if state.segments:
            return recentre_held_frames(state)
        return rotation_only_segment(state, initializer, camera, self.config.min_rotation_only_deg)


def track_rotation(state: SlamState, initializer: Initializer, selector: MotionModelSelector, ff: FrameFeatures,
                   record: FrameRecord, K: np.ndarray) -> MotionModelChoice | None:
    """The motion model of a buffered frame (no map yet) against its rotation keyframe; on rotation-only the
    frame joins the chain (``record.orientation``, ``record.rotation_chain``, ``record.motion_model``).
    ``K``: (3, 3) intrinsics of the keypoints. Returns the choice, or None when no earlier frame is buffered."""
    window = [f for f in initializer.frames if f.index < ff.index]
    if not window:
        return None
    prev = window[-1]
    in_window = {f.index: f for f in window}
    refs = [prev]
    p = state.records[prev.index]
    if p.orientation is not None and p.rotation_ref in in_window and p.rotation_ref != prev.index:
        refs.insert(0, in_window[p.rotation_ref])  # the chain's keyframe first
    choice = None
    for ref in refs:
        m = initializer.window_matches(ref, ff)
        choice = selector.step(ref.keypoints[m[:, 0]], ff.keypoints[m[:, 1]], K)
        if choice.model == GENERAL or (choice.is_rotation and choice.inliers.sum() >= MIN_KEYFRAME_INLIERS):
            break
    record.motion_model = choice.model
    if not choice.is_rotation:
        return choice
    r = state.records[ref.index]
    if r.orientation is None:  # a new chain starts at the reference
        r.orientation, r.rotation_chain, r.rotation_ref = np.eye(3), r.index, r.index
    record.orientation = _averaged(state, initializer, selector, ff, r, choice, K)
    record.rotation_chain, record.rotation_ref = r.rotation_chain, ref.index
    return choice


def _averaged(state: SlamState, initializer: Initializer, selector: MotionModelSelector, ff: FrameFeatures,
              ref: FrameRecord, choice: MotionModelChoice, K: np.ndarray) -> np.ndarray:
    """The frame's orientation in its chain: the rotation average (inlier-weighted) of what the reference and up
    to :data:`MAX_REFERENCES` - 1 older frames of the chain still buffered say (the oldest first: their
    longer arcs drift less than a chain of short steps)."""
    sums = choice.inliers.sum() * (choice.rotation @ ref.orientation)
    others = [f for f in initializer.frames if f.index < ff.index and f.index != ref.index
              and state.records[f.index].rotation_chain == ref.rotation_chain
              and state.records[f.index].orientation is not None]
    for f in others[: MAX_REFERENCES - 1]:
        m = initializer.window_matches(f, ff)
        if len(m) < MIN_KEYFRAME_INLIERS:
            continue
        R, _, inliers = selector.estimate_rotation(f.keypoints[m[:, 0]], ff.keypoints[m[:, 1]], K)
        if inliers.sum() >= MIN_KEYFRAME_INLIERS:
            sums = sums + inliers.sum() * (R @ state.records[f.index].orientation)
    return rotation_from_bearings(np.eye(3), sums.T)  # the rotation nearest to the weighted sum


def _chains(state: SlamState) -> dict[int, list[FrameRecord]]:
    out: dict[int, list[FrameRecord]] = {}
    for rec in state.records:
        if rec.orientation is not None and rec.rotation_chain >= 0:
            out.setdefault(rec.rotation_chain, []).append(rec)
    return out


def interpolate_held_centres(state: SlamState, record: FrameRecord) -> int:
    """``record`` was just posed in 6-DoF: the frames right before it that :meth:`RotationPhase.track_lost` posed
    by rotation with the position held (``motion_model`` "rotation") get centres interpolated linearly in time
    between the 6-DoF-posed frame before them and ``record`` (the camera kept walking while it turned; their
    orientations stay). Returns the frames moved (0 when the run has no 6-DoF frame before it)."""
    seg, run = state.segments[record.segment], []
    i = record.index - 1
    while i >= 0 and (r := state.records[i]).motion_model == ROTATION and r.rel_pose is not None \
            and r.segment == seg.id and r.keyframe_image_id <= 0:
        run.append(r)
        i -= 1
    before = state.records[i] if i >= 0 and run else None
    if before is None or before.rel_pose is None or before.segment != seg.id or not _six_dof(before):
        return 0
    (T0, T1) = state.pose_of(before), state.pose_of(record)
    c0, c1 = -T0[:3, :3].T @ T0[:3, 3], -T1[:3, :3].T @ T1[:3, 3]
    for r in run:
        w = (r.timestamp - before.timestamp) / (record.timestamp - before.timestamp)
        T = state.pose_of(r)
        T[:3, 3] = -T[:3, :3] @ ((1 - w) * c0 + w * c1)
        ref = np.eye(4)
        ref[:3] = seg.slam_map.cam_from_world(r.ref_image_id).matrix()
        r.rel_pose = T @ np.linalg.inv(ref)
    return len(run)


def _six_dof(rec: FrameRecord) -> bool:
    """Posed in 6-DoF: by PnP ("general") or as a keyframe (bundle-adjusted)."""
    return rec.motion_model == GENERAL or rec.keyframe_image_id > 0


def recentre_held_frames(state: SlamState) -> int:
    """:func:`interpolate_held_centres` before every 6-DoF-posed frame of every segment, on the poses as they are
    now (after the final bundle adjustment the frames they lie between may have moved since they were tracked).
    Returns the frames moved."""
    return sum(interpolate_held_centres(state, rec) for rec in state.records[1:]
               if rec.rel_pose is not None and _six_dof(rec) and state.records[rec.index - 1].motion_model == ROTATION)


def anchor_rotation_chains(state: SlamState) -> list[int]:
    """After initialization: the chain frames still without a pose are posed in the current segment. For each
    chain with posed frames (its keyframes when it has any, else the frames PnP posed against the new map),
    chain_from_world is the rotation average of ``orientation^T cam_from_world`` over them and the centre
    their median; a frame's pose is then
    ``orientation @ chain_from_world`` about that centre, relative to the segment's first keyframe (frames
    follow it through bundle adjustment). Returns the frames posed."""
    seg = state.segment
    posed: list[int] = []
    ref = min(seg.slam_map.keyframes)
    for chain in _chains(state).values():
        anchors = [(rec, state.pose_of(rec)) for rec in chain if rec.rel_pose is not None and rec.segment == seg.id]
        if not anchors or all(rec.rel_pose is not None for rec in chain):
            continue
        keyframes = [(rec, T) for rec, T in anchors if rec.keyframe_image_id > 0]
        anchors = keyframes or anchors  # a keyframe's pose is bundle-adjusted; PnP on a young map is rough
        # rotation average: the rotation nearest to the sum (Kabsch on the rows of the rotations)
        M = sum(rec.orientation.T @ T[:3, :3] for rec, T in anchors)
        chain_from_world = rotation_from_bearings(np.eye(3), M.T)
        centre = np.median([-T[:3, :3].T @ T[:3, 3] for _, T in anchors], axis=0)
        for rec in chain:
            if rec.rel_pose is None:
                T = np.eye(4)
                T[:3, :3] = rec.orientation @ chain_from_world
                T[:3, 3] = -T[:3, :3] @ centre
                state.set_pose(rec, ref, T, FrameStatus.TRACKED, absolute=True)
                posed.append(rec.index)
    seg.frames.sort()
    return posed


def rotation_only_segment(state: SlamState, initializer: Initializer, camera, min_rotation_deg: float = 0.0) -> int:
    """No map was made: the longest rotation chain becomes a segment whose map has one keyframe (its first
    frame still buffered, at the identity) and no points; every frame of the chain is posed by its
    orientation with the keyframe's centre (``Segment.rotation_only``). ``camera``: the run's Intrinsics.
    Returns the frames posed (0 without a chain, or when the chain turns less than ``min_rotation_deg`` from
    its first frame: a still camera is not a rotation)."""
    buffered = {f.index: f for f in initializer.history + initializer.frames}
    best = max(_chains(state).values(), key=len, default=[])
    first = next((r for r in best if r.index in buffered), None)
    if first is None or len(best) < 2:
        return 0
    if max(rotation_angle_deg(r.orientation @ first.orientation.T) for r in best) < min_rotation_deg:
        return 0
    kf = buffered[first.index]
    slam_map = SlamMap(camera)
    image_id = slam_map.add_image(kf.index, kf.timestamp, kf.keypoints, kf.features, kf.colors, kf.thumbnail)
    slam_map.register(image_id, pycolmap.Rigid3d())
    seg = state.start_segment(slam_map, [kf], [])
    seg.rotation_only = True
    for rec in best:
        if rec is not first:
            T = np.eye(4)
            T[:3, :3] = rec.orientation @ first.orientation.T
            state.set_pose(rec, image_id, T, FrameStatus.TRACKED)
    seg.frames.sort()
    state.end_segment()
    return len(seg.frames)


__all__ = ["MIN_KEYFRAME_INLIERS", "ROTATION_ONLY", "RotationPhase", "RotationStep", "anchor_rotation_chains",
           "interpolate_held_centres", "recentre_held_frames", "rotation_only_segment", "track_rotation"]
