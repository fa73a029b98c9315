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
    kf = _apply(T, shown.kf_centers())
    if len(kf):
        ax.scatter(kf[:, 0], kf[:, 1], c=recency_colors(shown.time_fractions(shown.kf_times)), s=14,
                   edgecolors="k", linewidths=0.3, zorder=3)
        drawn["keyframes"] = len(kf)
    if shown.current is not None:
        c = _apply(T, shown.current[None, :3, 3])[0]
        ax.plot(c[0], c[1], "o", ms=9, mfc="none", mec=CURRENT_COLOR, mew=2, zorder=4)
        drawn["current"] = 1
    cams = np.concatenate([path, kf, np.empty((0, 3))])
    box = [np.percentile(pts[:, :2], [2, 98], axis=0)] if len(pts) else []  # outliers aside
    box += [np.stack([cams[:, :2].min(0), cams[:, :2].max(0)])] if len(cams) else []  # every camera
    box = np.concatenate(box) if box else np.zeros((2, 2))
    lo, hi = box.min(0), box.max(0)
    pad = 0.08 * max(float((hi - lo).max()), 1e-6)
    ax.set_xlim(lo[0] - pad, hi[0] + pad), ax.set_ylim(lo[1] - pad, hi[1] + pad)
    return drawn


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

    def refresh(self, force: bool = False) -> bool:
        """Redraw every shown twin if the app changed (and ``min_interval`` has passed, unless ``force``)."""
        if not self._handles or not self.dirty or (not force and time.monotonic() - self._drawn_at < self.min_interval):
            return False
        png, text = self._bundles()
        for h_png, h_text in self._handles:
            h_png.update(png, raw=True)
            h_text.update(text, raw=True)
        return True


__all__ = ["StaticTwin", "app_picture", "app_text", "draw_map_from_above"]
