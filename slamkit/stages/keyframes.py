"""Keyframe selection (seed §3.4, with ORB-SLAM's "before tracking becomes weak" rule) and the
degenerate-motion test (too little parallax to the last keyframe, e.g. pure rotation). Culling redundant
keyframes is :mod:`slamkit.stages.culling`.

A frame whose flow or weak tracking asks for a keyframe is still refused when the median triangulation
angle of its tracked matches to the last keyframe (:func:`median_parallax_deg`, the relative rotation
removed, as in ORB-SLAM's and COLMAP's initialization checks) is below ``min_parallax_deg``: a keyframe
taken then would only add points triangulated from (nearly) parallel rays. Such frames stay tracked by PnP
against the existing points and their decision says ``degenerate``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import check_fields
from ..kernels.geometry import flow_score, parallax_deg, rotation_angle_deg


@dataclass(frozen=True)
class KeyframeConfig:
    flow_threshold: float = 0.05
    """A keyframe needs a flow score (median normalised flow to the last keyframe) above this."""
    min_tracked_matches: int = 50
    """...and at least this many tracked matches to the last keyframe (seed §3.4)."""
    weak_tracking_ratio: float = 0.5
    """Insert a keyframe anyway when the tracked map points fall below this fraction of those tracked at
    the last keyframe, so fast motion does not lose the map (0 disables)."""
    reference_min_observers: int = 1
    """The weak-tracking rule counts the last keyframe's map points that at least this many keyframes observe
    (ORB-SLAM: 3, its "tracked map points" of the reference keyframe; with ``weak_tracking_ratio`` 0.9 a
    keyframe comes as soon as tracking no longer finds most of them); 1: all of its points."""
    min_weak_tracked_matches: int = 20
    """The weak-tracking rule needs at least this many tracked matches to the last keyframe."""
    min_parallax_deg: float = 0.25
    """Degenerate motion: no keyframe (and so no new points) while the median parallax (triangulation
    angle, relative rotation removed) of the tracked matches to the last keyframe is below this, degrees;
    0 disables the test. The value sits between what pure rotation measures (keypoint noise) and the
    parallax at which real sequences take keyframes when the camera turns (figures: benchmarks/HISTORY.md,
    "Measurements moved from docstrings")."""
    cull_redundant: float = 0.9
    """Keyframe culling (ORB-SLAM): after each new keyframe's bundle adjustment, a keyframe of its local
    window is removed from the map when at least this fraction of its map points is observed by
    ``cull_min_observers`` other keyframes; its frames are re-anchored to a neighbour. Where the camera keeps
    revisiting a place, keyframes and track lengths then stop growing with time (0 disables)."""
    cull_min_observers: int = 3
    """See ``cull_redundant``."""
    cull_keep_recent: int = 5
    """The most recent keyframes are never culled: new keyframes triangulate with them (``mapper.neighbors``),
    and in a turn, where each keyframe adds few points, culling them starved the map until tracking was lost
    (benchmarks/HISTORY.md, "Measurements moved from docstrings")."""

    def validate(self) -> None:
        check_fields(self, "keyframes", {
            "flow_threshold": "[0, 100]", "min_tracked_matches": "[1, inf)", "weak_tracking_ratio": "[0, 1)",
            "reference_min_observers": "[1, inf)", "min_weak_tracked_matches": "[0, inf)",
            "min_parallax_deg": "[0, 45)", "cull_redundant": "[0, 1]", "cull_min_observers": "[1, inf)",
            "cull_keep_recent": "[0, inf)"})


@dataclass(frozen=True)
class KeyframeDecision:
    is_keyframe: bool
    reason: str
    flow: float
    tracked_matches: int
    parallax_deg: float = float("nan")
    """Median parallax to the last keyframe, degrees (NaN when not measured)."""
    degenerate: bool = False
    """A keyframe was due (flow or weak tracking) but refused: too little parallax (degenerate motion)."""


def median_parallax_deg(ref_xy: np.ndarray, cur_xy: np.ndarray, ref_from_world: np.ndarray,
                        cur_from_world: np.ndarray, K: np.ndarray) -> tuple[float, float]:
    """Median parallax of matches between the last keyframe and the current frame, and their rotation.

    ref_xy, cur_xy: (N, 2) undistorted pixels of the same map points in both; ref_from_world,
    cur_from_world: (4, 4) or (3, 4) poses; K: (3, 3). Returns (median triangulation angle of the viewing
    rays after removing the relative rotation, relative rotation angle), both in degrees; the median is NaN
    without matches. Independent of the map's scale; pure rotation gives ~0 whatever the rotation.
    """
    R = np.asarray(cur_from_world)[:3, :3] @ np.asarray(ref_from_world)[:3, :3].T  # cur_from_ref
    rotation = rotation_angle_deg(R)
    if len(ref_xy) == 0:
        return float("nan"), rotation
    angles = parallax_deg(np.asarray(ref_xy, np.float64), np.asarray(cur_xy, np.float64), R, np.asarray(K))
    return float(np.median(angles)), rotation


class KeyframeSelector:
    """Decides whether a tracked frame becomes a keyframe, and says why (or why not)."""

    def __init__(self, config: KeyframeConfig = KeyframeConfig()):
        config.validate()
        self.config = config

    def decide(self, ref_xy: np.ndarray, cur_xy: np.ndarray, ref_from_world: np.ndarray,
               cur_from_world: np.ndarray, K: np.ndarray, tracked_points: int, points_at_last_keyframe: int
               ) -> KeyframeDecision:
        """:meth:`step` on a tracked frame's matches to the last keyframe: ref_xy, cur_xy (M, 2) undistorted
        pixels of the same map points in both; ref_from_world, cur_from_world (4, 4) or (3, 4) poses; K (3, 3).
        Measures the flow score and the median parallax (both in the decision) first."""
        flow = flow_score(ref_xy, cur_xy, K[0, 0], K[1, 1])
        parallax, rotation = median_parallax_deg(ref_xy, cur_xy, ref_from_world, cur_from_world, K)
        return self.step(flow, len(ref_xy), tracked_points, points_at_last_keyframe, parallax, rotation)

    def step(self, flow: float, tracked_matches: int, tracked_points: int, points_at_last_keyframe: int,
             parallax_deg: float = float("nan"), rotation_deg: float = float("nan")) -> KeyframeDecision:
        """flow: score to the last keyframe; tracked_matches: inlier matches to points of the last keyframe;
        tracked_points: inlier map points of this frame; points_at_last_keyframe: those of the last keyframe;
        parallax_deg, rotation_deg: :func:`median_parallax_deg` to the last keyframe (NaN: not measured,
        no degenerate-motion test)."""
        d = self._decide(flow, tracked_matches, tracked_points, points_at_last_keyframe)
        c = self.config
        if d.is_keyframe and c.min_parallax_deg > 0 and parallax_deg < c.min_parallax_deg:  # NaN: False
            if math.isnan(rotation_deg):
                kind = "too little parallax"
            elif rotation_deg >= 2 * c.min_parallax_deg:
                kind = f"pure rotation: {rotation_deg:.1f}° rotation"
            else:
                kind = f"too little translation, {rotation_deg:.1f}° rotation"
            return KeyframeDecision(False, f"degenerate motion: median parallax {parallax_deg:.2f}° < "
                                           f"{c.min_parallax_deg:g}° ({kind}); would be a keyframe by "
                                           f"{d.reason}", flow, tracked_matches, parallax_deg, True)
        return KeyframeDecision(d.is_keyframe, d.reason, flow, tracked_matches, parallax_deg)

    def _decide(self, flow: float, tracked_matches: int, tracked_points: int, points_at_last_keyframe: int
                ) -> KeyframeDecision:
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
