"""Scene building for the map view: pure functions from arrays to meshcat objects (nothing is sent here).

Geometry goes to meshcat as 3xN float32 (positions, and colours in [0, 1]); ``Nx3`` would be drawn as
garbage. Keyframe frustums, the camera path, viewing directions and track lines are ``LineSegments``
(pairs of vertices); map points are ``Points``. Colours: recency from green (first keyframe) through
yellow to red (last keyframe), by timestamp; the current frame is blue; the selected track is magenta.

The map is shown in a display frame (x right, y forward, z up of the first keyframe's camera) centred and
scaled so it spans :data:`DISPLAY_EXTENT` units: :func:`compute_fit` finds the centre and extent, and
:func:`display_from_map` is the similarity the view sets on its root node.
"""

from __future__ import annotations

import warnings

import numpy as np

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    import meshcat.geometry as mg

DISPLAY_FROM_OPENCV = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
"""Rotation from OpenCV camera axes (x right, y down, z forward) to the viewer's z-up axes."""

DISPLAY_EXTENT = 6.0
"""Size of the fitted map in viewer units (the viewer's camera sits about this far from its centre)."""

BACKGROUND_RADIUS = 500.0
"""Radius of the background sphere, viewer units (the camera's far plane is set beyond it)."""

CURRENT_COLOR = (0.1, 0.45, 1.0)
TRACK_COLOR = (0.9, 0.0, 0.9)
LOOP_COLOR = (0.0, 0.75, 0.85)
"""Loop edges: the two keyframes of each loop closed or place recognised (cyan)."""
TRACK_POINT_RGB = (230, 0, 230)
"""The tracked point's colour, 0..255 (its lines are :data:`TRACK_COLOR`)."""

FRUSTUM_EDGES = [(0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 3), (3, 4), (4, 1)]
"""Apex 0 and image corners 1-4: four rays and the image rectangle (8 segments, 16 vertices)."""

Camera = tuple[float, float, float, float, int, int]
"""Pinhole intrinsics of the frustums: (fx, fy, cx, cy) pixels and (width, height) pixels."""

_UNIT_CAMERA: Camera = (1.0, 1.0, 0.5, 0.5, 1, 1)


def recency_colors(fractions: np.ndarray) -> np.ndarray:
    """(N,) values in [0, 1] (0 = first, 1 = last) -> (N, 3) float32 RGB in [0, 1], green -> yellow -> red."""
    f = np.clip(np.nan_to_num(np.asarray(fractions, np.float64).reshape(-1)), 0.0, 1.0)
    # hue from 120 (green) to 0 degrees (red) at full saturation: red rises first, then green falls
    v = 0.95
    r = np.where(f < 0.5, 2 * f, 1.0) * v
    g = np.where(f < 0.5, 1.0, 2 * (1 - f)) * v
    return np.stack([r, g, np.zeros_like(f)], axis=1).astype(np.float32)


HEIGHT_STOPS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], np.float64)
"""Colours of the height scale from low to high, 0..255 (viridis: dark blue, blue, teal, green, yellow)."""


def height_colors(heights: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(N,) heights -> (N, 3) uint8 colours of :data:`HEIGHT_STOPS`, ``lo`` (and below) to ``hi`` (and above)."""
    h = np.asarray(heights, np.float64).reshape(-1)
    f = np.clip((h - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.full(len(h), 0.5)
    x = np.nan_to_num(f, nan=0.5) * (len(HEIGHT_STOPS) - 1)
    i = np.minimum(x.astype(int), len(HEIGHT_STOPS) - 2)
    w = (x - i)[:, None]
    return np.round(HEIGHT_STOPS[i] * (1 - w) + HEIGHT_STOPS[i + 1] * w).astype(np.uint8)


def map_heights(xyz: np.ndarray) -> np.ndarray:
    """(N,) the height of map points (N, 3) in the view (its z up: minus the first keyframe camera's y), map
    units."""
    return -np.asarray(xyz, np.float64).reshape(-1, 3)[:, 1]


def hex_to_rgb255(color: str) -> list[int]:
    """'#rrggbb' (or 'rrggbb', '#rgb') -> [r, g, b] ints 0..255; ValueError on anything else."""
    c = color.strip().lstrip("#")
    if len(c) == 3:
        c = "".join(ch * 2 for ch in c)
    if len(c) != 6:
        raise ValueError(f"background colour must be '#rrggbb', got {color!r}")
    return [int(c[i:i + 2], 16) for i in (0, 2, 4)]


# ---------------------------------------------------------------------------------------------- objects


def points_object(xyz: np.ndarray, rgb: np.ndarray, size: float) -> mg.Points:
    """xyz (N, 3) map units, rgb (N, 3) 0..255, size in viewer units -> a meshcat ``Points`` object."""
    pos = np.ascontiguousarray(xyz, np.float32).T  # 3xN (F-contiguous view: packed without a copy)
    col = (np.asarray(rgb, np.float32) / 255.0).T
    return mg.PointCloud(pos, col, size=float(size))


def lines_object(vertices: np.ndarray, colors: np.ndarray) -> mg.LineSegments:
    """vertices (2M, 3), colors (2M, 3) in [0, 1] -> LineSegments (pairs of vertices)."""
    pos = np.ascontiguousarray(vertices, np.float32).T
    col = np.ascontiguousarray(colors, np.float32).T
    return mg.LineSegments(mg.PointsGeometry(pos, col), mg.LineBasicMaterial(vertexColors=True))


def background_object(color: str) -> tuple[mg.Sphere, mg.MeshBasicMaterial]:
    """The background: a large sphere seen from inside, in an unlit material of ``color`` ('#rrggbb').

    meshcat 0.3.2's gradient background renders black (its three.js dropped RGBFormat textures)."""
    rgb = hex_to_rgb255(color)
    value = (rgb[0] << 16) | (rgb[1] << 8) | rgb[2]
    return mg.Sphere(BACKGROUND_RADIUS), mg.MeshBasicMaterial(color=value, side=1)  # 1 = THREE.BackSide


def geometry_bytes(obj) -> int:
    """Bytes of the position and colour arrays of a ``Points`` or ``LineSegments`` object."""
    geom = obj.geometry
    return int(geom.position.nbytes + geom.color.nbytes)


# ---------------------------------------------------------------------------------------------- geometry


def world_from_cam(cam_from_world: np.ndarray) -> np.ndarray:
    """(K, 3, 4) cam_from_world -> (K, 4, 4) world_from_cam."""
    n = len(cam_from_world)
    R = cam_from_world[:, :, :3]
    t = cam_from_world[:, :, 3]
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = np.transpose(R, (0, 2, 1))
    out[:, :3, 3] = -np.einsum("nji,nj->ni", R, t)
    return out


def time_fractions(times: np.ndarray, keyframe_times: np.ndarray, path_times: np.ndarray) -> np.ndarray:
    """(N,) seconds -> (N,) 0 at the first keyframe, 1 at the last (clipped to [0, 1]); with fewer than two
    keyframes the span also covers the path's times."""
    span = keyframe_times if len(keyframe_times) >= 2 else np.concatenate([keyframe_times, path_times])
    if len(span) == 0:
        return np.zeros(len(times))
    t0, t1 = float(span.min()), float(span.max())
    return np.clip((times - t0) / (t1 - t0), 0, 1) if t1 > t0 else np.ones(len(times))


def frustum_vertices(world_from_cam: np.ndarray, camera: Camera | None, depth: float) -> np.ndarray:
    """(K, 4, 4) poses -> (K * 16, 3) line-segment vertices of the frustums, ``depth`` map units deep."""
    fx, fy, cx, cy, w, h = camera or _UNIT_CAMERA
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
    local = np.zeros((5, 3))
    local[1:, 0] = (corners[:, 0] - cx) / fx
    local[1:, 1] = (corners[:, 1] - cy) / fy
    local[1:, 2] = 1.0
    local *= depth
    pts = np.einsum("kij,pj->kpi", world_from_cam[:, :3, :3], local) + world_from_cam[:, None, :3, 3]
    idx = np.array(FRUSTUM_EDGES).reshape(-1)
    return pts[:, idx, :].reshape(-1, 3)


FIT_PERCENTILES = (5.0, 95.0)
"""The display fit frames this percentile range of the points (and of the camera centres): a few far
points (a window, the sky, a bad triangulation) do not shrink the map to a corner of the viewer."""


def robust_box(xyz: np.ndarray, percentiles: tuple[float, float] = FIT_PERCENTILES) -> tuple[np.ndarray, np.ndarray]:
    """(lo (3,), hi (3,)) the per-axis percentile box of (N, 3) positions (min / max below 20 of them)."""
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
    if len(xyz) == 0:
        return np.full(3, np.inf), np.full(3, -np.inf)
    if len(xyz) < 20:
        return xyz.min(axis=0), xyz.max(axis=0)
    lo, hi = np.percentile(xyz, percentiles, axis=0)
    return lo, hi


def compute_fit(points: np.ndarray, centers: np.ndarray, path_centers: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre (3,), extent) of the box around the 5-95 percentile range of the points and of the camera
    centres (keyframes and path); extent is the box's largest side in map units (1 when degenerate)."""
    cams = np.concatenate([np.asarray(centers, np.float64).reshape(-1, 3),
                           np.asarray(path_centers, np.float64).reshape(-1, 3)])
    boxes = [robust_box(points), robust_box(cams)]
    lo = np.minimum(boxes[0][0], boxes[1][0])
    hi = np.maximum(boxes[0][1], boxes[1][1])
    if not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)):
        return np.zeros(3), 1.0
    extent = float(np.max(hi - lo))
    if not np.isfinite(extent) or extent <= 1e-9:
        extent = 1.0
    return (lo + hi) / 2, extent


def nearest_camera_distance(points: np.ndarray, centers: np.ndarray, sample: int = 2000, seed: int = 0) -> float:
    """Median distance (map units) from a map point to its nearest camera centre, over a random sample of
    ``sample`` points: the depth at which the map was seen, so a point size relative to it looks the same
    on any map whatever its (arbitrary, monocular) scale. NaN without points or cameras."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    cams = np.asarray(centers, np.float64).reshape(-1, 3)
    if len(pts) == 0 or len(cams) == 0:
        return float("nan")
    if len(pts) > sample:
        pts = pts[np.random.default_rng(seed).choice(len(pts), sample, replace=False)]
    d2 = ((pts[:, None, :] - cams[None, :, :]) ** 2).sum(axis=2).min(axis=1)
    return float(np.median(np.sqrt(d2)))


VIEW_DIRECTION = np.array([0.2, -0.5, 0.85]) / np.linalg.norm([0.2, -0.5, 0.85])
"""Direction from the map's centre to the viewer's home camera (display axes): from above the path (about 58
degrees up), a little behind the first keyframe and to its right, so the layout (walls, facades) reads as a
plan while the frustums keep some depth."""

VIEWER_FOV_DEG = 75.0
"""Vertical field of view of meshcat's default camera, degrees."""


def _view_axes(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(d, right, up) unit vectors of a camera looking at the origin from ``direction``, z up."""
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    right = np.cross(d, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return d, right, np.cross(right, d)


def screen_box(points: np.ndarray, cameras: np.ndarray, position: np.ndarray, aspect: float,
               fov_deg: float = VIEWER_FOV_DEG) -> tuple[np.ndarray, np.ndarray]:
    """(lo (2,), hi (2,)) normalized device coordinates (the viewer spans -1..1) of the 5-95 percentile box
    of the projected ``points`` (N, 3) joined with every camera centre ``cameras`` (M, 3), seen from
    ``position`` looking at the origin, z up."""
    d, right, up = _view_axes(position)
    dist, t = float(np.linalg.norm(position)), np.tan(np.radians(fov_deg) / 2)
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for xyz, q in ((points, FIT_PERCENTILES), (cameras, (0.0, 100.0))):
        if len(xyz):
            depth = np.maximum(dist - xyz @ d, 1e-3)
            xy = np.stack([(xyz @ right) / (depth * t * aspect), (xyz @ up) / (depth * t)], axis=1)
            a, b = np.percentile(xy, q, axis=0)
            lo, hi = np.minimum(lo, a), np.maximum(hi, b)
    return lo, hi


def home_camera_position(points_display: np.ndarray, aspect: float, cameras_display: np.ndarray | None = None,
                         fill: float = 0.85, direction: np.ndarray = VIEW_DIRECTION,
                         fov_deg: float = VIEWER_FOV_DEG) -> np.ndarray:
    """(3,) display-frame position of the viewer's camera, looking at the origin along ``-direction`` with z
    up, at the distance where the 5-95 percentile box of the projected ``points_display`` (N, 3) and every
    camera centre ``cameras_display`` (M, 3) reach ``fill`` of the way from the viewer's centre to its edge
    (on the side and axis that bind; ``aspect`` = width / height), and in front of 98 % of the points and of
    every camera."""
    pts = np.asarray(points_display, np.float64).reshape(-1, 3)
    cams = np.empty((0, 3)) if cameras_display is None else np.asarray(cameras_display, np.float64).reshape(-1, 3)
    d = _view_axes(direction)[0]
    if len(pts) + len(cams) == 0:
        return d * DISPLAY_EXTENT * 1.1
    # in front of 98 % of the points and of every camera: no point a few pixels from the eye
    near = float(np.percentile(pts @ d, 98)) if len(pts) else -np.inf
    if len(cams):
        near = max(near, float(np.max(cams @ d)))
    near += 0.05 * DISPLAY_EXTENT
    lo, hi = near, near + 100 * DISPLAY_EXTENT
    for _ in range(50):  # what the viewer sees shrinks as the camera backs away: bisect on it
        mid = (lo + hi) / 2
        box = screen_box(pts, cams, d * mid, aspect, fov_deg)
        lo, hi = (mid, hi) if float(np.max(np.abs(box))) > fill else (lo, mid)
    return d * hi


def view_centering(points_display: np.ndarray, cameras_display: np.ndarray, aspect: float,
                   direction: np.ndarray = VIEW_DIRECTION, fov_deg: float = VIEWER_FOV_DEG) -> np.ndarray:
    """(3,) display-frame offset of the middle of what the home camera sees (:func:`screen_box`) from the
    origin it looks at; moving the map by minus it centres the picture, so the map can fill more of the
    viewer. Zero without points."""
    pts = np.asarray(points_display, np.float64).reshape(-1, 3)
    cams = np.asarray(cameras_display, np.float64).reshape(-1, 3)
    if len(pts) + len(cams) == 0:
        return np.zeros(3)
    offset = np.zeros(3)
    for _ in range(3):  # re-centre from the new camera distance (converges in two or three rounds)
        pos = home_camera_position(pts - offset, aspect, cams - offset, direction=direction, fov_deg=fov_deg)
        d, right, up = _view_axes(pos)
        lo, hi = screen_box(pts - offset, cams - offset, pos, aspect, fov_deg)
        depth = float(np.median(np.linalg.norm(pos) - np.concatenate([pts, cams]) @ d))
        t = np.tan(np.radians(fov_deg) / 2)
        offset = offset + (lo[0] + hi[0]) / 2 * depth * t * aspect * right + (lo[1] + hi[1]) / 2 * depth * t * up
    return offset


def display_from_map(fit: tuple[np.ndarray, float] | None) -> np.ndarray:
    """(4, 4) the similarity from map coordinates to the viewer's: centred, scaled to DISPLAY_EXTENT, z up."""
    c, extent = fit if fit is not None else (np.zeros(3), DISPLAY_EXTENT)
    s = DISPLAY_EXTENT / extent
    T = np.eye(4)
    T[:3, :3] = s * DISPLAY_FROM_OPENCV
    T[:3, 3] = -s * DISPLAY_FROM_OPENCV @ c
    return T


# ---------------------------------------------------------------------------------------------- the map's parts


def keyframes_object(poses: np.ndarray, colors: np.ndarray, camera: Camera | None, depth: float
                     ) -> mg.LineSegments:
    """Keyframe frustums: poses (K, 4, 4) world_from_cam, colors (K, 3) in [0, 1], depth map units."""
    v = frustum_vertices(poses, camera, depth)
    return lines_object(v, np.repeat(colors, 16, axis=0))


def path_object(centers: np.ndarray, fractions: np.ndarray) -> mg.LineSegments:
    """The camera path: centers (N, 3) map units in time order, N >= 2, and (2 (N - 1),) recency fractions
    of the segments' vertices."""
    v = np.stack([centers[:-1], centers[1:]], axis=1).reshape(-1, 3)
    return lines_object(v, recency_colors(fractions))


def path_vertex_times(times: np.ndarray) -> np.ndarray:
    """(N,) path times -> (2 (N - 1),) the times of the path segments' vertices (for their colours)."""
    return np.stack([times[:-1], times[1:]], axis=1).reshape(-1)


def directions_object(poses: np.ndarray, colors: np.ndarray, depth: float) -> mg.LineSegments:
    """Viewing directions: a segment along each pose's optical axis (camera z), three frustum ``depth``
    (map units) long; poses (K, 4, 4) world_from_cam, colors (K, 3) in [0, 1]."""
    c = poses[:, :3, 3]
    v = np.stack([c, c + poses[:, :3, 2] * depth * 3], axis=1).reshape(-1, 3)
    return lines_object(v, np.repeat(colors, 2, axis=0))


def current_frame_object(camera: Camera | None, depth: float) -> mg.LineSegments:
    """The current frame's frustum at the origin (moved by ``set_transform``), in CURRENT_COLOR."""
    v = frustum_vertices(np.eye(4)[None], camera, depth)
    col = np.tile(np.array(CURRENT_COLOR, np.float32), (len(v), 1))
    return lines_object(v, col)


def track_lines_object(xyz: np.ndarray, centers: np.ndarray) -> mg.LineSegments:
    """Lines from a point xyz (3,) to each observing keyframe's centre (K, 3), K >= 1, in TRACK_COLOR."""
    v = np.stack([np.tile(xyz, (len(centers), 1)), centers], axis=1).reshape(-1, 3)
    col = np.tile(np.array(TRACK_COLOR, np.float32), (len(v), 1))
    return lines_object(v, col)


def loop_edges_object(edges: np.ndarray) -> mg.LineSegments:
    """Loop edges: (L, 2, 3) pairs of keyframe centres, L >= 1, map units, in LOOP_COLOR."""
    v = np.asarray(edges, np.float64).reshape(-1, 3)
    return lines_object(v, np.tile(np.array(LOOP_COLOR, np.float32), (len(v), 1)))


LOOP_RGB = tuple(int(round(255 * c)) for c in LOOP_COLOR)


def loop_band_object(edges: np.ndarray, size: float, per_edge: int = 48) -> mg.Points:
    """Loop edges drawn to stand out (WebGL lines are 1 px wide whatever their width): ``per_edge`` large
    points in LOOP_COLOR along each edge (L, 2, 3), map units, L >= 1; ``size`` in viewer units."""
    e = np.asarray(edges, np.float64).reshape(-1, 2, 3)
    f = np.linspace(0.0, 1.0, int(per_edge))[None, :, None]
    xyz = (e[:, :1] * (1 - f) + e[:, 1:] * f).reshape(-1, 3)
    return points_object(xyz, np.tile(np.array(LOOP_RGB), (len(xyz), 1)), size)


OTHER_PATH_COLOR = (0.0, 0.0, 0.0)
"""The default colour of another path drawn through the map (black: none of the map's own colours)."""


def other_path_objects(centers: np.ndarray, color: tuple[float, float, float], size: float
                       ) -> tuple[mg.LineSegments | None, mg.Points]:
    """Another camera path in one ``color`` (RGB in [0, 1]): a line through its centers (N, 3), map units in time
    order (None when N < 2), and a dot of ``size`` viewer units at every frame (WebGL lines are 1 px wide whatever
    their width: the dots make it stand out)."""
    c = np.asarray(centers, np.float64).reshape(-1, 3)
    line = None
    if len(c) >= 2:
        v = np.stack([c[:-1], c[1:]], axis=1).reshape(-1, 3)
        line = lines_object(v, np.tile(np.array(color, np.float32), (len(v), 1)))
    rgb = np.tile(np.round(255 * np.asarray(color, np.float64)), (len(c), 1))
    return line, points_object(c, rgb, size)


def track_point_object(xyz: np.ndarray, size: float) -> mg.Points:
    """The tracked point xyz (3,) as a single large point."""
    return points_object(xyz[None], np.array([TRACK_POINT_RGB]), size)


__all__ = ["DISPLAY_FROM_OPENCV", "DISPLAY_EXTENT", "BACKGROUND_RADIUS", "CURRENT_COLOR", "TRACK_COLOR", "LOOP_COLOR",
           "Camera", "recency_colors", "hex_to_rgb255", "height_colors", "map_heights", "HEIGHT_STOPS", "points_object", "lines_object", "background_object",
           "geometry_bytes", "world_from_cam", "time_fractions", "frustum_vertices", "compute_fit", "robust_box",
           "nearest_camera_distance", "home_camera_position", "view_centering", "screen_box", "VIEW_DIRECTION",
           "FIT_PERCENTILES",
           "display_from_map", "keyframes_object", "path_object", "path_vertex_times", "directions_object",
           "current_frame_object", "track_lines_object", "track_point_object",
           "loop_edges_object", "loop_band_object", "OTHER_PATH_COLOR", "other_path_objects"]
