"""The settings of a run in a saved map (:mod:`slamkit.map_reuse`), apart so that :mod:`slamkit.config` can
hold them without importing the map loader."""

from __future__ import annotations

from dataclasses import dataclass

from .errors import check_fields


@dataclass(frozen=True)
class MapReuseConfig:
    """A run in a saved map (``Slam(..., map=RUN_DIR)``); without a map these do nothing."""

    covisible_reference: bool = False
    """The keyframe decision's reference and the local map's centre is the keyframe sharing most of the frame's
    tracked points (ORB-SLAM's reference keyframe); False: the last inserted keyframe, as in a run of its own."""
    odometry_below: int = 150
    """Localizing only: a frame due for a keyframe that tracks fewer of the loaded map's points than this gets
    a temporary keyframe (visual odometry outside the map, dropped at the end); 0: never (frames outside the
    map are lost)."""

    odometry_relocalize_every: int = 5
    """Localizing only, on temporary keyframes: every this many frames the frame is relocalized among the loaded
    map's keyframes, and tracked there again when found with ``odometry_below`` inliers (0: never)."""

    def validate(self) -> None:
        check_fields(self, "map_reuse", {"odometry_below": "[0, inf)", "odometry_relocalize_every": "[0, inf)"})


__all__ = ["MapReuseConfig"]
