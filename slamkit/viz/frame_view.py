"""What a frame looked like to the tracker: OpenCV drawings and short HTML summaries. No widgets here.

- :func:`flow_lines` gives a step's tracked matches to the last keyframe, as the step result carries them
  (``StepResult.tracked``): the very matches the flow score and the keyframe decision used. Nothing is
  re-derived.
- :func:`draw_flow` draws them like the seed's Figure 2: a line from each point's position in the last
  keyframe to its position in the current frame, a dot at the current one.
- :func:`keyframe_matches` / :func:`draw_matches`: the keypoints two keyframes share through 3D points.
- :func:`step_html` / :func:`summary_html`: the numbers of a step next to the thresholds they are compared
  with, and the running summary of the run.
"""

from __future__ import annotations

import html
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from ..config import SlamConfig
    from ..map import SlamMap
    from ..pipeline import Slam, StepResult

FLOW_LINE = (40, 200, 40)
"""RGB of the flow lines (keyframe -> current position)."""
FLOW_DOT = (230, 30, 30)
"""RGB of the dots at the current positions."""


# ---------------------------------------------------------------------------------------------- matches


def flow_lines(result: "StepResult | None") -> tuple[np.ndarray, np.ndarray]:
    """(ref_xy (M, 2), cur_xy (M, 2)) undistorted pixels of the step's tracked matches to the last keyframe
    (M = ``result.matches``), from the result itself; empty arrays without a result or a tracked frame."""
    if result is None:
        return np.empty((0, 2)), np.empty((0, 2))
    return result.tracked.flow_lines()


def keyframe_matches(slam_map: "SlamMap", image_id1: int, image_id2: int) -> np.ndarray:
    """(M, 2) int64 keypoint index pairs of two keyframes that observe the same 3D point."""
    p1, p2 = slam_map.point3D_ids(image_id1), slam_map.point3D_ids(image_id2)
    common, i1, i2 = np.intersect1d(p1[p1 >= 0], p2[p2 >= 0], return_indices=True)
    idx1 = np.flatnonzero(p1 >= 0)[i1]
    idx2 = np.flatnonzero(p2 >= 0)[i2]
    return np.stack([idx1, idx2], axis=1).astype(np.int64)


# ---------------------------------------------------------------------------------------------- drawing


def _as_rgb(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    return np.ascontiguousarray(image[..., :3])


def fit_width(image: np.ndarray, width: int | None) -> tuple[np.ndarray, float]:
    """Resize to ``width`` pixels (keeping the aspect); returns (image, scale)."""
    if width is None or image.shape[1] == width:
        return image, 1.0
    scale = width / image.shape[1]
    size = (int(width), max(1, int(round(image.shape[0] * scale))))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return cv2.resize(image, size, interpolation=interp), scale


def draw_flow(image: np.ndarray, ref_xy: np.ndarray, cur_xy: np.ndarray, width: int | None = None) -> np.ndarray:
    """The seed's Figure 2: lines from each keypoint's position in the last keyframe to the current one.

    image: (H, W, 3) uint8 RGB (or (H, W) grey) current frame; ref_xy, cur_xy: (M, 2) pixels. Returns an
    RGB uint8 copy, resized to ``width`` pixels when given.
    """
    out, s = fit_width(_as_rgb(image).copy(), width)
    ref = np.round(np.asarray(ref_xy, np.float64).reshape(-1, 2) * s * 16).astype(np.int32)
    cur = np.round(np.asarray(cur_xy, np.float64).reshape(-1, 2) * s * 16).astype(np.int32)
    for a, b in zip(ref, cur):
        cv2.line(out, tuple(int(v) for v in a), tuple(int(v) for v in b), FLOW_LINE, 1, cv2.LINE_AA, shift=4)
    for b in cur:
        cv2.circle(out, tuple(int(v) for v in b), 2 * 16, FLOW_DOT, -1, cv2.LINE_AA, shift=4)
    return out


def draw_matches(image1: np.ndarray, xy1: np.ndarray, image2: np.ndarray, xy2: np.ndarray,
                 pairs: np.ndarray, width: int | None = None, max_lines: int = 300) -> np.ndarray:
    """Two images side by side with lines between matched keypoints (``cv2.drawMatches``).

    xy1, xy2: (N1, 2), (N2, 2) keypoint pixels in each image; pairs: (M, 2) indices. Draws at most
    ``max_lines`` matches (evenly subsampled). Returns RGB uint8, resized to ``width`` when given.
    """
    im1, im2 = _as_rgb(image1), _as_rgb(image2)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    if len(pairs) > max_lines:
        pairs = pairs[np.linspace(0, len(pairs) - 1, max_lines).astype(int)]
    kp1 = [cv2.KeyPoint(float(x), float(y), 3) for x, y in np.asarray(xy1, np.float64).reshape(-1, 2)]
    kp2 = [cv2.KeyPoint(float(x), float(y), 3) for x, y in np.asarray(xy2, np.float64).reshape(-1, 2)]
    dm = [cv2.DMatch(int(a), int(b), 0.0) for a, b in pairs]
    out = cv2.drawMatches(im1, kp1, im2, kp2, dm, None, matchColor=FLOW_LINE, singlePointColor=FLOW_DOT,
                          flags=cv2.DrawMatchesFlags_NOT_DRAW_SINGLE_POINTS)
    return fit_width(out, width)[0]


def encode_image(rgb: np.ndarray, fmt: str = "jpeg", quality: int = 90) -> bytes:
    """RGB uint8 -> JPEG or PNG bytes (for an ``ipywidgets.Image``)."""
    bgr = cv2.cvtColor(_as_rgb(rgb), cv2.COLOR_RGB2BGR)
    if fmt == "png":
        ok, buf = cv2.imencode(".png", bgr)
    else:
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV fails only on empty images
        raise ValueError(f"could not encode a {rgb.shape} image as {fmt}")
    return buf.tobytes()


def placeholder(text: str, size: tuple[int, int] = (320, 240)) -> np.ndarray:
    """A grey RGB image with a line of text (before there is anything to show)."""
    w, h = size
    img = np.full((h, w, 3), 235, np.uint8)
    cv2.putText(img, text, (10, h // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (90, 90, 90), 1, cv2.LINE_AA)
    return img


# ---------------------------------------------------------------------------------------------- text


def _cmp(value: float, threshold: float, fmt: str, strict: bool) -> str:
    """``value > threshold`` (strict) or ``value >= threshold``, coloured green when it holds."""
    ok = value > threshold if strict else value >= threshold
    sign = (">" if ok else "&le;") if strict else ("&ge;" if ok else "&lt;")
    color = "#1a7f37" if ok else "#b35900"
    return f'<b style="color:{color}">{fmt.format(value)}</b> {sign} {fmt.format(threshold)}'


def step_html(result: "StepResult | None", config: "SlamConfig", drawn: int | None = None) -> str:
    """The step's status, flow score and tracked matches next to the thresholds they were compared with."""
    if result is None:
        return '<span class="slamkit-step">no frame processed yet</span>'
    r = result
    kf = config.keyframes
    parts = [f"frame <b>{r.frame_index}</b> (source frame {r.frame_id}, t={r.timestamp:.3f} s) "
             f"<b>[{html.escape(r.status)}]</b>"]
    if not np.isnan(r.flow):
        parts.append(f"flow score {_cmp(r.flow, kf.flow_threshold, '{:.3f}', True)} (flow threshold)")
    if r.status in ("tracked",):
        parts.append(f"tracked matches to the last keyframe {_cmp(r.matches, kf.min_tracked_matches, '{:d}', False)} "
                     f"(min tracked matches); {r.inliers} pose inliers"
                     + (f"; {drawn} lines drawn" if drawn is not None else ""))
    if r.keyframe_reason:
        parts.append(("<b>KEYFRAME</b>: " if r.is_keyframe else "no keyframe: ") + html.escape(r.keyframe_reason))
    if r.message:
        parts.append(html.escape(r.message))
    if r.ba:
        parts.append(f"bundle adjustment: {html.escape(r.ba)}")
    if r.timings:
        ms = ", ".join(f"{k} {v * 1e3:.0f}" for k, v in r.timings.items())
        parts.append(f"stages (ms): {ms}")
    return '<div class="slamkit-step">' + "<br>".join(parts) + "</div>"


def summary_numbers(slam: "Slam", reprojection_error: float | None = None) -> dict:
    """Frames, keyframes, points, mean reprojection error (px), lost frames, fps and the costliest stages
    (``stages``: ms per frame) of the run so far."""
    m = slam.slam_map
    n = len(slam.records)
    if reprojection_error is None:
        reprojection_error = m.mean_reprojection_error() if m is not None and m.num_points else float("nan")
    return {
        "frames": n,
        "frames_total": len(slam),
        "keyframes": m.num_keyframes if m is not None else 0,
        "points": m.num_points if m is not None else 0,
        "reprojection_error_px": float(reprojection_error),
        "lost": sum(r.status == "lost" for r in slam.records),
        "segments": len(slam.state.live_segments),
        "fps": n / slam.wall_time if slam.wall_time > 0 else 0.0,
        "stages": slam.state.describe_speed(),
    }


def summary_html(numbers: dict[str, float], scene: dict[str, int] | None = None) -> str:
    """The running summary (and what the 3D view holds, when given)."""
    n = numbers
    err = n["reprojection_error_px"]
    err_s = "–" if np.isnan(err) else f"{err:.2f} px"
    text = (f'frames <b class="frames">{n["frames"]}</b>/{n["frames_total"]} · keyframes '
            f'<b class="keyframes">{n["keyframes"]}</b> · points <b class="points">{n["points"]}</b> · '
            f'mean reprojection error <b>{err_s}</b> · lost frames <b>{n["lost"]}</b> · '
            f'segments {n["segments"]} · <b>{n["fps"]:.1f}</b> fps'
            + (f' <span class="slamkit-stages">({html.escape(n["stages"])})</span>' if n.get("stages") else ""))
    if scene is not None:
        text += (f'<br><span class="slamkit-scene">3D view: <b class="scene-points">{scene.get("points", 0)}'
                 f'</b> points in {scene.get("point_groups", 0)} groups, <b class="scene-keyframes">'
                 f'{scene.get("keyframes", 0)}</b> keyframe frustums, path of {scene.get("path", 0)} frames'
                 f'</span>')
    return f'<div class="slamkit-summary">{text}</div>'


__all__ = ["flow_lines", "keyframe_matches", "draw_flow", "draw_matches", "encode_image", "placeholder",
           "fit_width", "step_html", "summary_numbers", "summary_html"]
