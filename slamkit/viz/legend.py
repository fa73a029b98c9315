"""The colour legend of the 3D view: what each colour means, as one line of text or a small HTML box.

A view lists only what it draws (:meth:`~slamkit.viz.meshcat_view.MapView.legend_items`): keys of
:data:`LEGEND` for its own parts, and ``(CSS colour, meaning)`` pairs for the other paths drawn through its map
(:meth:`~slamkit.viz.meshcat_view.MapView.add_path`).
"""

from __future__ import annotations

import html

import numpy as np

from .scene import CURRENT_COLOR, HEIGHT_STOPS, LOOP_COLOR, TRACK_COLOR, recency_colors


def legend_text() -> str:
    """What the colours of the 3D view mean (one line, plain text)."""
    return ("map points coloured by height (dark blue low → yellow high) or in their image colours · keyframe "
            "frustums and camera path from green (first) through yellow to red (last) · current frame blue · "
            "selected track magenta · loop closures cyan · drag to orbit, scroll to zoom")


def css_color(rgb: tuple[float, float, float]) -> str:
    """(r, g, b) in [0, 1] -> '#rrggbb'."""
    return "#%02x%02x%02x" % tuple(int(round(255 * c)) for c in rgb)


LEGEND = {
    "points-height": ("linear-gradient(90deg,{})".format(",".join(css_color(c / 255) for c in HEIGHT_STOPS)),
                      "points by height: low → high"),
    "points-image": ("linear-gradient(90deg,#b08060,#6080b0,#c0c0a0)", "points in their image colours"),
    "keyframes": ("linear-gradient(90deg,{},{},{})".format(
        *(css_color(c) for c in recency_colors(np.array([0.0, 0.5, 1.0])))), "keyframes and path: first → last"),
    "current": (css_color(CURRENT_COLOR), "current frame"),
    "track": (css_color(TRACK_COLOR), "selected track"),
    "loops": (css_color(LOOP_COLOR), "loop closure"),
}
"""Legend entry -> (CSS colour, meaning) of each colour of the 3D view; a view lists only what it draws
(:meth:`MapView.legend_items`)."""


def legend_html(items=("points-height", "keyframes", "current")) -> str:
    """The colour legend of the 3D view as a small HTML box (swatches and words) for the entries ``items``:
    keys of :data:`LEGEND`, or ``(CSS colour, meaning)`` pairs (another path drawn through the map)."""
    entries = [LEGEND[k] if isinstance(k, str) else k for k in items]
    spans = "".join(f'<span style="white-space:nowrap;margin-right:8px"><span style="display:inline-block;'
                    f'width:18px;height:4px;vertical-align:middle;background:{html.escape(css)}"></span> '
                    f'{html.escape(meaning)}</span> ' for css, meaning in entries)
    return f'<div class="slamkit-legend" style="font:11px sans-serif;line-height:1.5">{spans}</div>'


__all__ = ["LEGEND", "legend_html", "legend_text", "css_color"]
