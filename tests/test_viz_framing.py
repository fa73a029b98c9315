"""The map view's framing and the words of the notebooks, pure: no server, no browser.

The home camera must frame the 5-95 % box of a map with far outliers so that it fills the viewer (a few far
points may not shrink it to a corner), the point size must follow the scene's scale, and the one-line step
description must read as a sentence in every phase.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("meshcat")

from slamkit.pipeline import StepResult  # noqa: E402
from slamkit.viz.explain import describe_step, flow_help_html  # noqa: E402
from slamkit.viz.scene import (FIT_PERCENTILES, VIEW_DIRECTION, VIEWER_FOV_DEG, compute_fit,  # noqa: E402
                               display_from_map, home_camera_position, nearest_camera_distance,
                               view_centering)
from slamkit.viz.settings import POINT_FRACTION, ViewSettings  # noqa: E402


def _room(rng, n=5000, outliers=50):
    """Points on the walls of a 6 x 4 x 2.5 box, cameras on a loop inside it, and far outliers."""
    walls = rng.uniform([-3, -2, 0], [3, 2, 2.5], (n, 3))
    axis = rng.integers(0, 2, n)
    walls[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1, 1) * np.array([3.0, 2.0])[axis]
    far = rng.normal(0, 1, (outliers, 3)) * 200.0
    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    cams = np.stack([1.5 * np.cos(t), 1.0 * np.sin(t), np.full_like(t, 1.2)], axis=1)
    return walls, far, cams


def _project(xyz, position, aspect):
    """NDC (x, y) of display-frame points seen from ``position`` looking at the origin, z up (three.js)."""
    d = position / np.linalg.norm(position)
    right = np.cross(d, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, d)
    depth = np.linalg.norm(position) - xyz @ d
    t = np.tan(np.radians(VIEWER_FOV_DEG) / 2)
    return (xyz @ right) / (depth * t * aspect), (xyz @ up) / (depth * t), depth


@pytest.mark.parametrize("aspect", [4 / 3, 2.0])
def test_home_camera_frames_the_map_despite_outliers(aspect):
    rng = np.random.default_rng(0)
    walls, far, cams = _room(rng)
    pts = np.concatenate([walls, far])
    fit = compute_fit(pts, cams, cams)
    assert fit[1] == pytest.approx(6.0, rel=0.1)  # the room, not the outliers, sets the extent
    T = display_from_map(fit)
    offset = view_centering(pts @ T[:3, :3].T + T[:3, 3], cams @ T[:3, :3].T + T[:3, 3], aspect)
    disp = lambda x: x @ T[:3, :3].T + T[:3, 3] - offset  # noqa: E731  (the picture centred, as the view does)
    pos = home_camera_position(disp(pts), aspect, disp(cams))
    assert np.allclose(pos / np.linalg.norm(pos), VIEW_DIRECTION)
    x, y, depth = _project(disp(walls), pos, aspect)
    assert (depth > 0).mean() > 0.97  # the camera is in front of (nearly) every wall point
    (x0, x1), (y0, y1) = np.percentile(x, FIT_PERCENTILES), np.percentile(y, FIT_PERCENTILES)
    area = (min(x1, 1) - max(x0, -1)) * (min(y1, 1) - max(y0, -1)) / 4
    assert area >= 0.5, area  # the map covers at least half of the viewer
    cx, cy, _ = _project(disp(cams), pos, aspect)
    assert np.abs(cx).max() <= 0.86 and np.abs(cy).max() <= 0.86  # every camera is inside the viewer


def test_point_size_follows_the_scene_scale():
    rng = np.random.default_rng(1)
    walls, _, cams = _room(rng)
    d1 = nearest_camera_distance(walls, cams)
    assert 1.0 < d1 < 3.5  # walls 1.5 to 3 m from a loop inside the room
    d10 = nearest_camera_distance(walls * 10, cams * 10)
    assert d10 == pytest.approx(10 * d1, rel=0.05)  # a map ten times larger: points ten times larger
    s = ViewSettings(point_size=2.0)
    assert s.point_diameter(d1) == pytest.approx(2.0 * POINT_FRACTION * d1)
    assert np.isnan(nearest_camera_distance(np.empty((0, 3)), cams))


def _result(**kw):
    base = dict(frame_index=3, frame_id=3, timestamp=0.1, status="initializing", message="", segment=-1,
                timings={"features": 0.01})
    return StepResult(**{**base, **kw})


def test_describe_step_reads_in_every_phase():
    init = describe_step(_result(message="waiting for parallax"))
    assert "matches=" not in init and "inliers" not in init and "KEYFRAME" not in init
    assert "buffered for the two-view initialization" in init
    done = describe_step(_result(status="initialized", is_keyframe=True, num_keyframes=2, num_points=812,
                                 posed_frames=(0, 1, 2, 3)))
    assert "()" not in done and "first map: 2 keyframes, 812 points, 4 frames posed" in done
    tracked = describe_step(_result(status="tracked", flow=0.061, matches=240, inliers=230, is_keyframe=True,
                                    keyframe_reason="flow 0.061 > 0.05 with 240 tracked matches >= 50"))
    assert "flow score 0.061" in tracked and "KEYFRAME (flow 0.061 > 0.05" in tracked
    html = flow_help_html(525.0, 0.05, 50)
    assert "<b>26 px</b> here" in html and "5.0 % of the focal length" in html
