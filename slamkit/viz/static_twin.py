"""The app's static twin: a PNG of the 3D map (seen from above) and of the frame panel, and the status as
plain text, shown under the widgets and kept up to date.

Widgets live in the notebook's *widget state*, which JupyterLab's autosave drops, GitHub's viewer ignores
and an offline ``nbconvert --to html`` cannot render (the widget manager comes from a CDN). The twin's
outputs are ordinary ``image/png`` and ``text/plain`` display data (updated in place through their
``display_id``), which every notebook viewer shows with no kernel and no widget state.

The picture is drawn with matplotlib (Agg, no pyplot: no figure leaks into the notebook) from what the map
view holds: the points coloured by height, keyframes and path from green (first) to red (last), the
current frame in blue, in the view's display frame (x right, y forward, z up of the first keyframe).
"""

from __future__ import annotations

import io
import time
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .scene import CURRENT_COLOR, display_from_map, recency_colors

if TYPE_CHECKING:  # pragma: no cover
    from .app import SlamApp
    from .meshcat_view import MapView

PNG_DPI = 80
"""Resolution of the twin's picture (the figure is 12 x 4.6 inches: 960 x 368 pixels)."""


def _apply(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    return xyz @ T[:3, :3].T + T[:3, 3] if len(xyz) else np.empty((0, 3))


def draw_map_from_above(ax, view: "MapView", max_points: int = 30_000) -> dict[str, int]:
    """The map ``view`` holds, seen from above (display frame x right, y forward), on a matplotlib axis:
    points coloured by height, keyframe centres and the path by time (green → red), the current frame
    blue. Returns what was drawn (counts)."""
    shown = view._map
    ax.set_aspect("equal")
    ax.set_xticks([]), ax.set_yticks([])
    if shown.key is None or shown.fit is None:
        ax.text(0.5, 0.5, "no map yet", ha="center", va="center", transform=ax.transAxes, color="#777")
        return {"points": 0, "keyframes": 0, "path": 0, "current": 0}
    T = display_from_map(shown.fit)
    alive = shown.points.alive()
    pts = _apply(T, shown.points.xyz[alive].astype(np.float64))
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(0).choice(len(pts), max_points, replace=False)]
    drawn = {"points": len(pts), "keyframes": 0, "path": 0, "current": 0}
    if len(pts):
        lo, hi = np.percentile(pts[:, 2], [5, 95])
        ax.scatter(pts[:, 0], pts[:, 1], c=np.clip(pts[:, 2], lo, hi), cmap="viridis", s=1.5, lw=0,
                   rasterized=True)
    path = _apply(T, shown.path_c)
    if len(path) > 1:
        ax.plot(path[:, 0], path[:, 1], color="#444", lw=0.8)
        drawn["path"] = len(path)
    for other in shown.other_paths:  # another walk through the map, in its colour
        xy = _apply(T, other.centers)
        ax.plot(xy[:, 0], xy[:, 1], "o-", color=other.color, lw=1.0, ms=2.5, zorder=3)
    kf = _apply(T, shown.kf_centers())
    if len(kf):
        ax.scatter(kf[:, 0], kf[:, 1], c=recency_colors(shown.time_fractions(shown.kf_times)), s=14,
                   edgecolors="k", linewidths=0.3, zorder=3)
        drawn["keyframes"] = len(kf)
    if shown.current is not None:
        c = _apply(T, shown.current[None, :3, 3])[0]
        ax.plot(c[0], c[1], "o", ms=9, mfc="none", mec=CURRENT_COLOR, mew=2, zorder=4)
        drawn["current"] = 1
    cams = np.concatenate([path, kf, *(_apply(T, o.centers) for o in shown.other_paths), np.empty((0, 3))])
    box = [np.percentile(pts[:, :2], [2, 98], axis=0)] if len(pts) else []  # outliers aside
    box += [np.stack([cams[:, :2].min(0), cams[:, :2].max(0)])] if len(cams) else []  # every camera
    box = np.concatenate(box) if box else np.zeros((2, 2))
    lo, hi = box.min(0), box.max(0)
    pad = 0.08 * max(float((hi - lo).max()), 1e-6)
    ax.set_xlim(lo[0] - pad, hi[0] + pad), ax.set_ylim(lo[1] - pad, hi[1] + pad)
    return drawn


TRUST_HINT = ("The interactive 3D view above needs a trusted notebook and its running kernel: run the cell, or "
              "trust the notebook (JupyterLab: command palette, Ctrl+Shift+C > Trust Notebook; a shell: "
              "`jupyter trust NOTEBOOK.ipynb`). The picture is the same map from the same camera, and shows "
              "anywhere (untrusted, without a kernel, on a notebook viewer, in nbconvert's HTML).")
"""The line shown under every 3D view's picture: why the interactive view can be missing and what to do."""


def _project(xyz: np.ndarray, position: np.ndarray, aspect: float) -> tuple[np.ndarray, np.ndarray]:
    """((N, 2) normalized device coordinates, (N,) depths) of display-frame points seen from ``position``
    looking at the origin, z up, with the viewer's field of view (:data:`scene.VIEWER_FOV_DEG`)."""
    from .scene import VIEWER_FOV_DEG, _view_axes

    d, right, up = _view_axes(position)
    depth = float(np.linalg.norm(position)) - xyz @ d
    t = np.tan(np.radians(VIEWER_FOV_DEG) / 2)
    safe = np.maximum(depth, 1e-6)
    # _view_axes' "right" is the viewer's left (cross(d, z) with d pointing back at the camera): screen x is minus it
    return np.stack([-(xyz @ right) / (safe * t * aspect), (xyz @ up) / (safe * t)], axis=1), depth


def draw_map_from_camera(ax, view: "MapView", max_points: int = 40_000) -> dict[str, int]:
    """The map ``view`` holds as its 3D viewer shows it from its home camera (the position last sent to the
    viewer, looking at the map's centre, z up, the viewer's field of view and aspect), on a matplotlib axis
    spanning the viewer's picture: points in the view's colours (by height on the view's scale, or in their
    image colours), far ones drawn first; keyframe frustums and the path from green (first) to red (last);
    the current frame blue; loop closures cyan; other paths (:meth:`MapView.add_path`) in their colours, a
    line with a dot at every frame. Returns what was drawn (counts; ``other_paths``: their frames in the picture)."""
    from matplotlib.collections import LineCollection

    from .scene import (LOOP_COLOR, display_from_map, frustum_vertices, height_colors, home_camera_position,
                        map_heights, path_vertex_times)

    shown, settings = view._map, view.settings
    aspect = view.aspect
    ax.set_xlim(-1, 1), ax.set_ylim(-1, 1)
    ax.set_xticks([]), ax.set_yticks([])
    ax.set_facecolor(settings.background)
    drawn = {"points": 0, "keyframes": 0, "path": 0, "current": 0, "loops": 0, "other_paths": 0}
    if shown.key is None or shown.fit is None:
        ax.text(0, 0, "no map yet", ha="center", va="center", color="#777")
        return drawn
    T = display_from_map(shown.fit)
    position = view._out.camera_position
    if position is None:
        points, cameras = shown.display_points()
        position = home_camera_position(points, aspect, cameras)
    position = np.asarray(position, np.float64)

    def to_screen(xyz_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _project(_apply(T, np.asarray(xyz_map, np.float64).reshape(-1, 3)), position, aspect)

    def segments(vertices: np.ndarray, colors: np.ndarray, lw: float) -> int:
        """Line segments (pairs of map-frame vertices) in front of the camera."""
        xy, depth = to_screen(vertices)
        xy, depth = xy.reshape(-1, 2, 2), depth.reshape(-1, 2)
        keep = (depth > 1e-3).all(axis=1)
        if keep.any():
            ax.add_collection(LineCollection(xy[keep], colors=np.asarray(colors)[keep], linewidths=lw, zorder=3))
        return int(keep.sum())

    alive = shown.points.alive()
    pts = shown.points.xyz[alive]
    if settings.show_points and len(pts):
        rgb = (shown.points.rgb[alive].astype(np.float64) / 255 if settings.color_by == "image" else
               height_colors(map_heights(pts), *shown.height_range) / 255.0)
        if len(pts) > max_points:
            pick = np.random.default_rng(0).choice(len(pts), max_points, replace=False)
            pts, rgb = pts[pick], rgb[pick]
        xy, depth = to_screen(pts)
        keep = (depth > 1e-3) & (np.abs(xy) <= 1.05).all(axis=1)
        order = np.argsort(-depth[keep])  # far first: near points cover far ones, as in the viewer
        ax.scatter(xy[keep][order, 0], xy[keep][order, 1], c=rgb[keep][order], s=3.0, lw=0, rasterized=True,
                   zorder=2)
        drawn["points"] = int(keep.sum())
    depth_kf = settings.frustum_depth(shown.map_extent)
    sel = shown.clip_keyframes(settings.clip)
    if settings.show_keyframes and sel.any():
        poses = shown.kf_world_from_cam()[sel]
        colors = np.repeat(recency_colors(shown.time_fractions(shown.kf_times[sel])), 8, axis=0)
        segments(frustum_vertices(poses, shown.camera, depth_kf), colors, 0.8)
        drawn["keyframes"] = int(len(poses))
    if settings.show_path and len(shown.path_c) >= 2:
        t0, t1 = shown.clip_times(settings.clip)
        keep = (shown.path_t >= t0) & (shown.path_t <= t1)
        c, t = shown.path_c[keep], shown.path_t[keep]
        if len(c) >= 2:
            v = np.stack([c[:-1], c[1:]], axis=1).reshape(-1, 3)
            colors = recency_colors(shown.time_fractions(path_vertex_times(t)))[::2]
            segments(v, colors, 1.2)
            drawn["path"] = int(len(c))
        if len(shown.loop_edges):
            drawn["loops"] = segments(shown.loop_edges.reshape(-1, 3), np.tile(LOOP_COLOR, (len(shown.loop_edges), 1)),
                                      4.0)
    for other in shown.other_paths if settings.show_path else []:
        c = other.centers
        if len(c) >= 2:
            segments(np.stack([c[:-1], c[1:]], axis=1).reshape(-1, 3), np.tile(other.color, (len(c) - 1, 1)), 1.2)
        xy, depth = to_screen(c)
        keep = (depth > 1e-3) & (np.abs(xy) <= 1.05).all(axis=1)
        ax.scatter(xy[keep, 0], xy[keep, 1], color=other.color, s=7.0, lw=0, zorder=4)
        drawn["other_paths"] += int(keep.sum())
    if settings.show_current and shown.current is not None:
        v = frustum_vertices(np.asarray(shown.current, np.float64)[None], shown.camera, depth_kf * 1.5)
        drawn["current"] = int(segments(v, np.tile(CURRENT_COLOR, (8, 1)), 1.5) > 0)
    return drawn


def _color_name(rgb) -> str:
    """A word for a colour of another path in the picture's title ('black', else its '#rrggbb')."""
    from .legend import css_color

    return "black" if max(rgb) < 0.1 else css_color(rgb)


def map_picture(view: "MapView", height: int = 420, title: str | None = None) -> bytes:
    """PNG bytes: :func:`draw_map_from_camera` at the viewer's size (``height`` pixels, ``view.aspect`` times
    as wide), titled with what it shows."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    others = view._map.other_paths if view.settings.show_path else []  # a line of the title for them
    width, head_px = int(round(height * view.aspect)), 44 + 14 * bool(others)
    fig = Figure(figsize=(width / PNG_DPI, (height + head_px) / PNG_DPI), dpi=PNG_DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, height / (height + head_px)))
    drawn = draw_map_from_camera(ax, view)
    colouring = "their image colours" if view.settings.color_by == "image" else "height (dark blue low → yellow high)"
    lines = [title or "the 3D view as a picture: the same map from the same camera",
             f"{drawn['points']} points coloured by {colouring}",
             f"{drawn['keyframes']} keyframes and the path from green (first) to red (last)"
             + (", current frame blue" if drawn["current"] else "")
             + (f", {drawn['loops']} loop closure{'s' if drawn['loops'] != 1 else ''} cyan" if drawn["loops"] else "")]
    if others:
        lines.append("; ".join(f"{o.label}: {len(o.centers)} frames, {_color_name(o.color)}" for o in others))
    fig.text(0.01, 1 - 3 / (height + head_px), "\n".join(lines), va="top", fontsize=8.5)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=PNG_DPI)
    return buf.getvalue()


def picture_bundle(view: "MapView", height: int = 480, title: str | None = None) -> dict:
    """:func:`map_picture` as a display bundle (``image/png`` and a plain-text line) that every notebook front end
    shows, trusted or not, with a kernel or without one."""
    return {"image/png": map_picture(view, height, title),
            "text/plain": "the 3D view as a picture (the same map from the same camera)"}


def show_with_picture(view: "MapView", view_html: str, height: int):
    """Display a 3D view's HTML (live or frozen), its picture (:func:`picture_bundle`) and :data:`TRUST_HINT`;
    the display handles of the first two (to update them)."""
    from IPython.display import HTML, display

    shown = display(HTML(view_html), display_id=True)
    pic = display(picture_bundle(view, height), raw=True, display_id=True)
    display({"text/markdown": TRUST_HINT, "text/plain": TRUST_HINT}, raw=True)
    return shown, pic


def app_picture(app: "SlamApp") -> bytes:
    """PNG bytes: the app's map seen from above and its frame panel (the current frame with its flow lines),
    each with a title that says what it is."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 4.6), dpi=PNG_DPI)
    FigureCanvasAgg(fig)
    ax_map, ax_frame = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1, 1.25]})
    drawn = draw_map_from_above(ax_map, app.view)
    n = app._summary()
    ax_map.set_title(f"3D map from above: {n['keyframes']} keyframes (• green first → red last), path (grey),\n"
                     f"{drawn['points']} points (colour: height), current frame ○ blue", fontsize=9)
    frame = cv2.imdecode(np.frombuffer(app.f_cur.value, np.uint8), cv2.IMREAD_COLOR) if app.f_cur.value else None
    if frame is not None:
        ax_frame.imshow(frame[:, :, ::-1])
    ax_frame.set_xticks([]), ax_frame.set_yticks([])
    r = app.result
    ax_frame.set_title("current frame" + (f" {r.frame_index} ({r.status}" + (", keyframe" if r.is_keyframe else "")
                                          + "): flow lines from the last keyframe" if r is not None else ""),
                       fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=PNG_DPI)
    return buf.getvalue()


def app_text(app: "SlamApp") -> str:
    """The app's status, last step and running summary as plain text."""
    from .explain import describe_step

    n = app._summary()
    err = n["reprojection_error_px"]
    lines = [f"status: {app.status_text or 'ready'}"]
    if app.result is not None:
        lines.append(f"last step: {describe_step(app.result)}")
    err_s = "–" if np.isnan(err) else f"{err:.2f} px"
    lines.append(f"frames {n['frames']} of {n['frames_total']} · keyframes {n['keyframes']} · points {n['points']}"
                 f" · mean reprojection error {err_s} · lost frames {n['lost']}")
    return "\n".join(lines)


MOVED_TEXT = ("The app moved to a later cell (it was displayed again there); below, its picture and status as they "
              "were when it left this one, which the cells that follow here describe.")
"""What an earlier place of the app shows once the app is displayed again further down."""


class StaticTwin:
    """The twin outputs of an app: shown by :meth:`show` (under the widgets), redrawn by :meth:`refresh`
    when the app changed (at most every ``min_interval`` seconds unless forced)."""

    def __init__(self, app: "SlamApp", min_interval: float = 2.0):
        self.app = app
        self.min_interval = float(min_interval)
        self._handles: list = []
        self._drawn_at = -np.inf
        self.dirty = True
        self.png: bytes = b""
        self.text: str = ""

    def _bundles(self) -> tuple[dict, dict]:
        self.png, self.text = app_picture(self.app), app_text(self.app)
        self._drawn_at, self.dirty = time.monotonic(), False
        return ({"image/png": self.png, "text/plain": "the app's map and current frame (a picture)"},
                {"text/plain": self.text})

    def show(self) -> None:
        """Display the twin outputs (a picture and the status text) in the current cell."""
        from IPython.display import display

        png, text = self._bundles()
        self._handles.append((display(png, raw=True, display_id=True), display(text, raw=True, display_id=True)))

    def detach(self) -> None:
        """Stop updating the twin outputs shown so far: they keep the state they show now (the app was displayed
        again further down, where :meth:`show` starts new ones)."""
        self._handles.clear()

    def refresh(self, force: bool = False) -> bool:
        """Redraw every shown twin if the app changed (and ``min_interval`` has passed, unless ``force``)."""
        if not self._handles or not self.dirty or (not force and time.monotonic() - self._drawn_at < self.min_interval):
            return False
        png, text = self._bundles()
        for h_png, h_text in self._handles:
            h_png.update(png, raw=True)
            h_text.update(text, raw=True)
        return True


__all__ = ["StaticTwin", "TRUST_HINT", "app_picture", "picture_bundle", "show_with_picture", "app_text", "draw_map_from_above", "draw_map_from_camera",
           "map_picture"]
