"""Keyframe selection (seed §3.4, with ORB-SLAM's "before tracking becomes weak" rule)."""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import ConfigError


@dataclass(frozen=True)
class KeyframeConfig:
    flow_threshold: float = 0.05
    """A keyframe needs a flow score (median normalised flow to the last keyframe) above this."""
    min_tracked_matches: int = 50
    """...and at least this many tracked matches to the last keyframe (seed §3.4)."""
    weak_tracking_ratio: float = 0.5
    """Insert a keyframe anyway when the tracked map points fall below this fraction of those tracked at
    the last keyframe, so fast motion does not lose the map (0 disables)."""
    min_weak_tracked_matches: int = 20
    """The weak-tracking rule needs at least this many tracked matches to the last keyframe."""

    def validate(self) -> None:
        if not self.flow_threshold >= 0:
            raise ConfigError(f"keyframes.flow_threshold must be >= 0 (got {self.flow_threshold})")
        if self.min_tracked_matches < 1:
            raise ConfigError(f"keyframes.min_tracked_matches must be >= 1 (got {self.min_tracked_matches})")
        if not 0 <= self.weak_tracking_ratio < 1:
            raise ConfigError(f"keyframes.weak_tracking_ratio must be in [0, 1) (got {self.weak_tracking_ratio})")


@dataclass(frozen=True)
class KeyframeDecision:
    is_keyframe: bool
    reason: str
    flow: float
    tracked_matches: int


class KeyframeSelector:
    """Decides whether a tracked frame becomes a keyframe, and says why (or why not)."""

    def __init__(self, config: KeyframeConfig = KeyframeConfig()):
        config.validate()
        self.config = config

    def step(self, flow: float, tracked_matches: int, tracked_points: int, points_at_last_keyframe: int
             ) -> KeyframeDecision:
        """flow: score to the last keyframe; tracked_matches: inlier matches to points of the last keyframe;
        tracked_points: inlier map points of this frame; points_at_last_keyframe: those of the last keyframe."""
        c = self.config
        enough = tracked_matches >= c.min_tracked_matches
        if flow > c.flow_threshold and enough:
            return KeyframeDecision(True, f"flow {flow:.3f} > {c.flow_threshold:g} with {tracked_matches} "
                                          f"tracked matches >= {c.min_tracked_matches}", flow, tracked_matches)
        weak_limit = c.weak_tracking_ratio * points_at_last_keyframe
        if (c.weak_tracking_ratio > 0 and tracked_points < weak_limit
                and tracked_matches >= c.min_weak_tracked_matches):
            return KeyframeDecision(True, f"tracking weakening: {tracked_points} map points < "
                                          f"{c.weak_tracking_ratio:g} x {points_at_last_keyframe} at last keyframe",
                                    flow, tracked_matches)
        if flow <= c.flow_threshold:
            why = f"flow {flow:.3f} <= {c.flow_threshold:g}"
        else:
            why = f"only {tracked_matches} tracked matches < {c.min_tracked_matches}"
        return KeyframeDecision(False, why, flow, tracked_matches)
