"""Keyframe culling (ORB-SLAM's KeyFrameCulling): remove keyframes whose map points other keyframes see.

After each new keyframe's bundle adjustment, a keyframe of its local window (its ``window`` most covisible
keyframes) is removed from the map when at least ``redundant`` of its map points are observed by
``min_observers`` other keyframes. Where the camera keeps revisiting a place, keyframes and track lengths
then stop growing with time. The frames posed relative to a culled keyframe keep their absolute poses: each
culled keyframe comes with its most covisible remaining keyframe (the anchor) and the transform that
re-expresses those frames' relative poses (``SlamState.reanchor``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..map import SlamMap


@dataclass(frozen=True)
class KeyframeCullingConfig:
    redundant: float = 0.9
    """Fraction of a keyframe's map points seen by ``min_observers`` others that makes it redundant
    (``keyframes.cull_redundant``; 0 disables)."""
    min_observers: int = 3
    """``keyframes.cull_min_observers``."""
    keep_recent: int = 5
    """The newest keyframes are never culled (``keyframes.cull_keep_recent``)."""
    window: int = 6
    """Keyframes examined: the new keyframe's most covisible ones (``ba.local_window``)."""
    min_keyframes: int = 5
    """No culling while the map has fewer keyframes (young maps: their frames are re-tracked at the end)."""

    def validate(self) -> None:
        if not 0 <= self.redundant <= 1:
            raise ConfigError(f"keyframes.cull_redundant must be in [0, 1] (got {self.redundant})")
        if self.min_observers < 1:
            raise ConfigError(f"keyframes.cull_min_observers must be >= 1 (got {self.min_observers})")
        if self.keep_recent < 0:
            raise ConfigError(f"keyframes.cull_keep_recent must be >= 0 (got {self.keep_recent})")


@dataclass(frozen=True, eq=False)
class CulledKeyframe:
    """image_id: the removed keyframe; anchor: its most covisible remaining keyframe; culled_from_anchor:
    (4, 4) cam_from_world(image_id) @ inv(cam_from_world(anchor)), taken before the removal."""

    image_id: int
    anchor: int
    culled_from_anchor: np.ndarray


@dataclass(frozen=True, eq=False)
class CullingResult:
    culled: tuple[CulledKeyframe, ...]
    reason: str
    """Why nothing was examined, or how many keyframes were."""

    @property
    def image_ids(self) -> list[int]:
        return [c.image_id for c in self.culled]


def keyframe_redundancy(slam_map: SlamMap, image_id: int, min_observers: int) -> float:
    """ORB-SLAM's culling measure: the fraction of the keyframe's map points that ``min_observers`` other
    keyframes observe too (0 for a keyframe without map points)."""
    pids = slam_map.point3D_ids(image_id)
    pids = pids[pids >= 0].tolist()
    if not pids:
        return 0.0
    point3D = slam_map.reconstruction.point3D
    return sum(point3D(p).track.length() > min_observers for p in pids) / len(pids)


class KeyframeCuller:
    """Removes redundant keyframes from a :class:`SlamMap` around a new keyframe."""

    def __init__(self, config: KeyframeCullingConfig = KeyframeCullingConfig()):
        config.validate()
        self.config = config

    def step(self, slam_map: SlamMap, new_image_id: int, exclude: tuple[int, ...] = ()) -> CullingResult:
        """Cull over the local window of keyframe ``new_image_id``. Never the new keyframe, ``exclude``, the
        map's first two keyframes (they hold the gauge), the ``keep_recent`` newest, a loaded map's keyframes
        (negative frame indices, :mod:`slamkit.map_reuse`: they hold its frame), or while the map has fewer than
        ``min_keyframes`` keyframes."""
        c = self.config
        if c.redundant <= 0 or slam_map.num_keyframes < c.min_keyframes:
            return CullingResult((), "culling off" if c.redundant <= 0 else "young map")
        ids = sorted(slam_map.keyframes)
        protected = {new_image_id, *exclude, *ids[:2], *ids[len(ids) - c.keep_recent:],
                     *(i for i in ids if slam_map.keyframes[i].frame_index < 0)}
        culled = []
        window = slam_map.covisible(new_image_id, c.window)
        for iid, _ in window:
            if iid in protected or keyframe_redundancy(slam_map, iid, c.min_observers) < c.redundant:
                continue
            anchor = next((j for j, _ in slam_map.covisible(iid) if j != iid), None)
            if anchor is None:
                continue
            old = np.eye(4)
            old[:3] = slam_map.cam_from_world(iid).matrix()
            new = np.eye(4)
            new[:3] = slam_map.cam_from_world(anchor).matrix()
            culled.append(CulledKeyframe(iid, anchor, old @ np.linalg.inv(new)))
            slam_map.cull(iid)
        return CullingResult(tuple(culled), f"{len(window)} keyframes of the local window examined")
