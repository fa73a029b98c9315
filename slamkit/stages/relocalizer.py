"""Relocalization: find a frame the local map lost among all keyframes of the segment (ORB-SLAM's
Relocalization, with a global image signature in place of a bag of words).

The keyframes are ranked by the similarity of their global image signature to the frame's (a dot product
of unit vectors, ``slamkit.features.image_signature``); the ``candidates`` most similar ones are tried in
that order, then the last keyframe if it is not among them, each with a local map built around it, by the
tracker itself without a predicted pose (a search by descriptor). The last keyframe is a candidate too:
tracking failed with the motion model's prediction, which a fast turn or jump makes wrong, while the frame
may still see the last keyframe's points. The first that tracks the frame wins: tracking resumes from there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import pycolmap

from ..errors import ConfigError
from ..features import FrameFeatures
from ..local_map import POINT_DESCRIPTORS, LocalMap
from ..map import SlamMap


class FrameTracker(Protocol):
    """What the relocalizer needs of a tracker (``slamkit.stages.tracker.Tracker``)."""

    def step(self, frame: FrameFeatures, local_map: LocalMap, camera: pycolmap.Camera,
             predicted: np.ndarray | None = None): ...


@dataclass(frozen=True)
class RelocalizerConfig:
    candidates: int = 3
    """Most similar keyframes tried, then the last keyframe (``SlamConfig.relocalization_candidates``; 0
    disables)."""
    local_keyframes: int = 30
    """Covisible keyframes in each candidate's local map (``tracker.local_keyframes``)."""
    point_descriptor: str = "newest"
    """As ``tracker.point_descriptor``."""

    def validate(self) -> None:
        if self.candidates < 0:
            raise ConfigError(f"relocalization_candidates must be >= 0 (got {self.candidates})")
        if self.point_descriptor not in POINT_DESCRIPTORS:
            raise ConfigError(f"point_descriptor must be one of {', '.join(POINT_DESCRIPTORS)}")


@dataclass(frozen=True, eq=False)
class RelocalizationResult:
    """status: "relocalized", "failed" or "skipped" (nothing to try). On success ``keyframe`` is the image id
    of the keyframe that found the frame, ``local_map`` its local map and ``tracking`` the tracker's result
    (``slamkit.stages.tracker.TrackingResult``); ``tried``: the keyframes tried, most similar first."""

    status: str
    reason: str
    keyframe: int = -1
    local_map: LocalMap | None = None
    tracking: object | None = None
    tried: tuple[int, ...] = ()

    @property
    def relocalized(self) -> bool:
        return self.status == "relocalized"


class Relocalizer:
    """Localizes a lost frame against the keyframes that look most alike."""

    def __init__(self, config: RelocalizerConfig = RelocalizerConfig()):
        config.validate()
        self.config = config

    def step(self, frame: FrameFeatures, slam_map: SlamMap, signatures: dict[int, np.ndarray],
             last: int, tracker: FrameTracker) -> RelocalizationResult:
        """Try the keyframes of ``slam_map`` whose ``signatures`` (image id -> (D,) unit vector) are most
        like the frame's, then ``last`` (the last keyframe; -1: none) if not among them, tracking with
        ``tracker``."""
        if self.config.candidates <= 0:
            return RelocalizationResult("skipped", "relocalization disabled")
        if frame.signature is None or not signatures:
            return RelocalizationResult("skipped", "no image signatures")
        ids = [i for i in signatures if i in slam_map.keyframes]
        if not ids:
            return RelocalizationResult("skipped", "no keyframe")
        scores = np.array([float(signatures[i] @ frame.signature) for i in ids])
        order = [ids[k] for k in np.argsort(-scores, kind="stable")[: self.config.candidates]]
        if last in slam_map.keyframes and last not in order:
            order.append(last)
        camera = slam_map.pycolmap_camera
        tried = []
        for iid in order:
            tried.append(iid)
            local_map = LocalMap.build(slam_map, iid, self.config.local_keyframes, self.config.point_descriptor)
            tr = tracker.step(frame, local_map, camera, None)
            if tr.tracked:
                return RelocalizationResult("relocalized", f"relocalized against keyframe {iid}", iid,
                                            local_map, tr, tuple(tried))
        return RelocalizationResult("failed", f"none of keyframes {', '.join(map(str, tried))} tracks the frame",
                                    tried=tuple(tried))
