"""Motion prediction: the constant-velocity model (ORB-SLAM's motion model) that gives the tracker the pose
to search around.

The pose of frame n is predicted from the two posed frames of the current segment before it: with both
one frame apart, cam_from_world(n) = velocity @ cam_from_world(n-1), velocity = cam_from_world(n-1) @
inv(cam_from_world(n-2)); with a gap between them (a lost or skipped frame), the last pose itself (a
velocity over several frames is not simply divisible); with one posed frame, its pose; else no prediction
(the tracker then matches the whole local map).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ..errors import ConfigError
from ..state import FrameRecord, FrameStatus


@dataclass(frozen=True)
class MotionModelConfig:
    max_gap: int = 5
    """The search for posed frames stops at the first frame more than this many frames back."""

    def validate(self) -> None:
        if self.max_gap < 1:
            raise ConfigError(f"motion.max_gap must be >= 1 (got {self.max_gap})")


@dataclass(frozen=True, eq=False)
class MotionPrediction:
    """cam_from_world: (4, 4) predicted pose, or None; kind: "constant velocity", "last pose" or "none";
    frames: the indices of the posed frames it came from (newest first)."""

    cam_from_world: np.ndarray | None
    kind: str
    reason: str
    frames: tuple[int, ...] = ()


class MotionModel:
    """Constant-velocity prediction of a frame's pose from the posed frames before it."""

    def __init__(self, config: MotionModelConfig = MotionModelConfig()):
        config.validate()
        self.config = config

    def step(self, records: Sequence[FrameRecord], index: int, segment: int,
             pose_of: Callable[[FrameRecord], np.ndarray]) -> MotionPrediction:
        """Predict frame ``index`` from ``records[:index]`` posed in segment ``segment``; ``pose_of`` gives a
        record's (4, 4) cam_from_world. Stops at a frame lost outside the segment (tracking was lost
        before it began) and at the first frame more than ``max_gap`` frames back."""
        posed = []
        for rec in reversed(records[:index]):
            if rec.status == FrameStatus.LOST and rec.segment != segment:
                break
            if rec.rel_pose is not None and rec.segment == segment:
                posed.append(rec)
                if len(posed) == 2:
                    break
            if index - rec.index > self.config.max_gap:
                break
        if not posed:
            return MotionPrediction(None, "none", f"no posed frame within {self.config.max_gap} frames")
        last = pose_of(posed[0])
        if len(posed) == 1:
            return MotionPrediction(last, "last pose", f"one posed frame ({posed[0].index})", (posed[0].index,))
        prev = pose_of(posed[1])
        frames = (posed[0].index, posed[1].index)
        steps = max(posed[0].index - posed[1].index, 1)
        velocity = last @ np.linalg.inv(prev)
        if steps > 1:  # velocity per frame is not simply divisible; use it once per gap
            return MotionPrediction(last, "last pose", f"frames {frames[1]} and {frames[0]} are {steps} apart",
                                    frames)
        return MotionPrediction(velocity @ last, "constant velocity", f"from frames {frames[1]} and {frames[0]}",
                                frames)
