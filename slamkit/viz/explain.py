"""Words for the notebooks: what a step did, what the numbers measure and in which units, what colours mean.

Plain text or small HTML strings for the app and the course notebooks; no widgets, no pipeline state
beyond what is passed in.

- :func:`describe_step`: one line per step that reads as a sentence in every phase (no "matches=0" while
  the initializer is still buffering, no empty keyframe reason at initialization).
- :func:`flow_help_html`: the flow score and its threshold, with the pixels they mean for this camera.
- :func:`scale_html`: frustum depth and point size in map units; :func:`legend_html`: the colours.
"""

from __future__ import annotations

import html
from typing import TYPE_CHECKING

import numpy as np

from .settings import POINT_FRACTION

if TYPE_CHECKING:  # pragma: no cover
    from ..pipeline import StepResult

FLOW_SCORE = ("flow score = median |Δx| / fx + median |Δy| / fy over the tracked matches (Δ: a point's move from "
              "the last keyframe to the current frame, pixels): the typical optical flow since the last keyframe "
              "as a fraction of the focal length (dimensionless)")
"""What the flow score is, in one line."""


def pose_counts(r: "StepResult") -> str:
    """The tracker's counts of a tracked step, each a subset of the one before it: the 2D-3D matches to the
    local map (the last round, ``r.tracked``), the pose inliers among them, and the tracked matches (the inliers
    on points the last keyframe observes, compared with ``min_tracked_matches``). A frame matched against the
    whole local map has more pose inliers than tracked matches: the two are different sets, so the words say
    which contains which."""
    total = max(len(r.tracked), r.inliers)  # a result without its match list (rotation phase): the inliers
    head = f"{r.inliers} pose inliers of {total} local-map matches"
    if r.matches <= r.inliers:
        return f"{head}, {r.matches} of them tracked from the last keyframe"
    return f"{head}; {r.matches} tracked matches to the last keyframe"


def describe_step(r: "StepResult") -> str:
    """One plain-text line for a step result, worded for the phase the pipeline is in."""
    head = f"frame {r.frame_index} [{r.status}]"
    ms = f"{sum(r.timings.values()) * 1e3:.0f} ms"
    motion = f"; motion model: {r.motion_model_reason}" if r.motion_model else ""
    if r.status == "initializing":
        return f"{head} buffered for the two-view initialization; {r.message or 'no map yet'}{motion} ({ms})".strip()
    if r.status == "initialized":
        posed = f", {len(r.posed_frames)} frames posed" if r.posed_frames else ""
        return (f"{head} first map: {r.num_keyframes} keyframes, {r.num_points} points{posed}"
                + (f"; {r.message}" if r.message else "") + f" ({ms})")
    if r.status != "tracked":
        return f"{head} {r.message}".rstrip() + f" ({ms})"
    parts = [head]
    if not np.isnan(r.flow):
        parts.append(f"flow score {r.flow:.3f}")
    parts.append(pose_counts(r))
    if r.motion_model:
        parts.append(f"motion model: {r.motion_model_reason}")
    if r.is_keyframe:
        parts.append(f"KEYFRAME ({r.keyframe_reason})" if r.keyframe_reason else "KEYFRAME")
    elif r.keyframe_reason:
        parts.append(f"no keyframe ({r.keyframe_reason})")
    m = r.mapping
    if m is not None and hasattr(m, "culled"):  # local mapping's counts (mapper.method = "local")
        parts.append(f"local mapping: {m.created} points created, {m.culled} recent points culled, "
                     f"{m.fused} duplicates fused, {m.observations_added} observations added "
                     f"({len(m.neighbors)} covisible keyframes)")
    parts.append(f"map {r.num_keyframes} keyframes, {r.num_points} points")
    if r.ba:
        parts.append(f"BA: {r.ba}")
    if r.loop_closure is not None:
        c = r.loop_closure
        parts.append(f"LOOP CLOSED with the keyframe of frame {c.candidate_frame} ({c.inliers} of {c.matches} "
                     f"matched map points agree on one Sim(3); this keyframe moved {c.translation_m:.3g} map units, "
                     f"{c.rotation_deg:.2f} deg, scale {c.scale:.3f}; {c.fused_points} duplicate points fused)")
    if r.map_merge is not None:
        parts.append(f"MAPS MERGED: {r.map_merge.reason}")
    return " · ".join(parts) + f" ({ms})"


def flow_help_html(focal_px: float, threshold: float, min_matches: int) -> str:
    """The keyframe rule in words, with the threshold converted to pixels for a focal length ``focal_px``."""
    px = threshold * focal_px
    return (f'<div class="slamkit-help" style="color:#444;font-size:90%;max-width:640px">'
            f'<b>keyframe rule</b>: a tracked frame becomes a keyframe when its flow score &gt; '
            f'<b>{threshold:.3f}</b> and it keeps &ge; <b>{int(min_matches)}</b> tracked matches (or when tracking '
            f'weakens). {html.escape(FLOW_SCORE)}: {threshold:.3f} means {100 * threshold:.1f} % of the focal '
            f'length, <b>{px:.0f} px</b> here (f = {focal_px:.0f} px).</div>')


def camera_html(description: str) -> str:
    """The camera used and how it was obtained (given, found in a file, or estimated), one line."""
    return (f'<div class="slamkit-camera" style="color:#444;font-size:90%;max-width:640px"><b>camera</b>: '
            f'{html.escape(description)}</div>')


def scale_html(extent: float, frustum_depth: float, point_diameter: float, view_depth: float) -> str:
    """Frustum depth and point diameter in map units, and what a map unit is (all arguments map units)."""
    return (f'<div class="slamkit-units" style="color:#444;font-size:90%;max-width:640px">'
            f'frustum depth <b>{frustum_depth:.3g}</b> map units (frustum scale &times; 1/40 of the map extent, '
            f'{extent:.3g}); point diameter <b>{point_diameter:.3g}</b> map units (point size &times; '
            f'{100 * POINT_FRACTION:.1f} % of the median distance from a point to its nearest camera, '
            f'{view_depth:.3g}). A monocular map has no metric scale: a map unit is not a metre until the '
            f'trajectory is aligned to ground truth (Sim(3)).</div>')


def legend_html(view_legend: str = "") -> str:
    """The colours of the frame view, followed by ``view_legend`` (the 3D view's legend of what it draws,
    ``meshcat_view.legend_html(view.legend_items())``)."""
    def sw(color: str, shape: str = "line") -> str:
        style = ("display:inline-block;width:18px;height:3px;vertical-align:middle;" if shape == "line" else
                 "display:inline-block;width:8px;height:8px;border-radius:4px;vertical-align:middle;")
        return f'<span style="{style}background:{color}"></span>'

    return (f'<div class="slamkit-legend" style="color:#444;font-size:90%;max-width:640px">'
            f'<b>3D view</b>: {view_legend}'
            f'<b>frames</b>: {sw("rgb(40,200,40)")} flow line from a tracked point\'s position in the last '
            f'keyframe to the current frame, {sw("rgb(230,30,30)", "dot")} its current position.</div>')


__all__ = ["describe_step", "pose_counts", "flow_help_html", "scale_html", "legend_html", "FLOW_SCORE"]
