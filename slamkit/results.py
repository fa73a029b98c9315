"""What one step did, for callers and views: :class:`StepResult` and the frame's :class:`TrackedMatches`.

Views draw from these alone (flow lines, inliers, reasons); none of them runs a stage again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .state import FrameStatus

if TYPE_CHECKING:  # pragma: no cover
    from .merging import MergeResult
    from .stages.loop_closer import LoopClosure, MergeCandidate


@dataclass(frozen=True)
class MappingResult:
    """What the mapper did with a keyframe (``stages.mapper``, ``stages.local_mapper``: a subclass with its
    counts); ``StepResult.mapping``."""

    status: str
    """"registered" or "rejected"."""
    reason: str
    image_id: int
    num_points: int
    """Map points the keyframe observes."""
    new_points: int
    """Observations added by triangulation (new and continued tracks)."""
    neighbors: tuple[int, ...]
    num_correspondences: int
    starved: bool = False
    """The keyframe was triangulated again with ``starved_tri_angle_deg`` (see ``starved_points``)."""

    @property
    def registered(self) -> bool:
        return self.status == "registered"


@dataclass(frozen=True, eq=False)
class TrackedMatches:
    """The frame's 2D-3D matches to the local map in the tracker's last round (what the pose was refined on).

    xy: (K, 2) float32 undistorted pixels in the frame; point3D_ids: (K,) int64 map points; inliers: (K,)
    bool reprojection inliers of the final pose; ref_xy: (K, 2) float32 undistorted pixels of the same
    points in the reference (last) keyframe, NaN where that keyframe does not observe the point. float32:
    for drawing (the pipeline computes with the float64 keypoints).
    """

    xy: np.ndarray
    point3D_ids: np.ndarray
    inliers: np.ndarray
    ref_xy: np.ndarray

    @classmethod
    def empty(cls) -> "TrackedMatches":
        return cls(np.empty((0, 2), np.float32), np.empty(0, np.int64), np.empty(0, bool),
                   np.empty((0, 2), np.float32))

    def __len__(self) -> int:
        return len(self.point3D_ids)

    @property
    def in_reference(self) -> np.ndarray:
        """(K,) bool: inliers whose point the reference keyframe observes (the flow score's matches)."""
        return self.inliers & ~np.isnan(self.ref_xy[:, 0])

    def flow_lines(self) -> tuple[np.ndarray, np.ndarray]:
        """(ref_xy (M, 2), cur_xy (M, 2)): the tracked matches to the last keyframe, in the order the flow
        score and the keyframe decision used them (M = ``StepResult.matches``)."""
        m = self.in_reference
        return self.ref_xy[m], self.xy[m]


@dataclass(frozen=True, eq=False)
class StepResult:
    """What happened to one frame. ``cam_from_world`` is (4, 4) in the frame's segment, or None."""

    frame_index: int
    frame_id: int
    timestamp: float
    status: FrameStatus
    message: str
    segment: int
    is_keyframe: bool = False
    keyframe_reason: str = ""
    """Why the frame became a keyframe, or why not (the keyframe selector's decision, or the mapper's
    rejection)."""
    flow: float = float("nan")
    matches: int = 0
    """Tracked matches to the last keyframe (the number compared with min_tracked_matches)."""
    inliers: int = 0
    """Pose inliers (2D-3D) of the frame."""
    cam_from_world: np.ndarray | None = None
    num_keyframes: int = 0
    num_points: int = 0
    ba: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    posed_frames: tuple[int, ...] = ()
    """Frames that received a pose with this step (the initialization window on success)."""
    relocalized: bool = False
    """The local map lost the frame and relocalization against all keyframes found it."""
    degenerate: bool = False
    """Degenerate motion (e.g. pure rotation): a keyframe was due but refused for too little parallax to
    the last keyframe; the frame is tracked by PnP only (``keyframe_reason`` gives the numbers)."""
    parallax_deg: float = float("nan")
    """Median parallax (triangulation angle, rotation removed) of the tracked matches to the last keyframe."""
    tracked: TrackedMatches = field(default_factory=TrackedMatches.empty)
    """The frame's matches to the local map (empty unless tracked), for views: ``tracked.flow_lines()``."""
    reference_keyframe: int = -1
    """Image id of the keyframe the frame was tracked against (the last keyframe; -1 when not tracked)."""
    loop_closure: "LoopClosure | None" = None
    """The loop this keyframe closed (keyframes, matches, inliers, size of the correction), or None."""
    merge_candidate: "MergeCandidate | None" = None
    """A verified place of an earlier map segment (what merging the two segments needs), or None."""
    map_merge: "MergeResult | None" = None
    """The current map segment merged into the earlier one whose place it recognised (``merge_candidate``):
    keyframes and points moved, points fused, the Sim(3)'s scale; or None."""
    motion_model: str = ""
    """The motion model chosen for the frame (GRIC, ``stages.motion_model_selection``): "rotation" (it only
    turned: position held, orientation tracked), "general" (6-DoF), or "" (none chosen)."""
    motion_model_reason: str = ""
    """Why: the two models' GRIC scores, inliers and transfer error."""
    mapping: MappingResult | None = None
    """What the mapper did with the keyframe (``MappingResult``, or ``LocalMappingResult`` with the points local
    mapping created, culled and fused), or None when the frame did not become one."""

    @property
    def has_pose(self) -> bool:
        return self.cam_from_world is not None

    @property
    def world_from_cam(self) -> np.ndarray | None:
        return None if self.cam_from_world is None else np.linalg.inv(self.cam_from_world)

    def __str__(self) -> str:
        if self.is_keyframe:
            kf = f"KEYFRAME ({self.keyframe_reason})" if self.keyframe_reason else "KEYFRAME"
        else:
            kf = f"no keyframe ({self.keyframe_reason})" if self.keyframe_reason else ""
        flow = "" if np.isnan(self.flow) else f" flow={self.flow:.3f}"
        # matches and inliers are the tracker's: while initializing there are none to speak of
        counts = f" matches={self.matches} inliers={self.inliers}" if self.status == "tracked" else ""
        ms = sum(self.timings.values()) * 1e3
        loop = f"; {self.loop_closure}" if self.loop_closure is not None else ""
        if self.merge_candidate is not None:
            m = self.merge_candidate
            loop += (f"; place of segment {m.candidate_segment} recognised (keyframe {m.query_image_id} ~ "
                     f"{m.candidate_image_id}, {m.inliers}/{m.matches} inliers)")
        if self.map_merge is not None:
            loop += f"; {self.map_merge.reason}"
        return (f"frame {self.frame_index} [{self.status}]{flow}{counts} "
                f"kf={self.num_keyframes} pts={self.num_points} {ms:.0f} ms {kf} {self.message}{loop}".rstrip())
