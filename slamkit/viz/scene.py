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


def compute_fit(points: np.ndarray, centers: np.ndarray, path_centers: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre (3,), extent) of the box around the points (2-98 percentile when 20 or more), the keyframe
    centres and the path; extent is the box's largest side in map units (1 when degenerate)."""
    pts = np.asarray(points, np.float64)
    if len(pts) >= 20:
        lo, hi = np.percentile(pts, [2, 98], axis=0)
        pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    allp = np.concatenate([pts, centers, path_centers]) if len(pts) + len(centers) else np.zeros((1, 3))
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    extent = float(np.max(hi - lo))
    if not np.isfinite(extent) or extent <= 1e-9:
        extent = 1.0
    return (lo + hi) / 2, extent


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


def track_point_object(xyz: np.ndarray, size: float) -> mg.Points:
    """The tracked point xyz (3,) as a single large point."""
    return points_object(xyz[None], np.array([TRACK_POINT_RGB]), size)


__all__ = ["DISPLAY_FROM_OPENCV", "DISPLAY_EXTENT", "BACKGROUND_RADIUS", "CURRENT_COLOR", "TRACK_COLOR",
           "Camera", "recency_colors", "hex_to_rgb255", "points_object", "lines_object", "background_object",
           "geometry_bytes", "world_from_cam", "time_fractions", "frustum_vertices", "compute_fit",
           "display_from_map", "keyframes_object", "path_object", "path_vertex_times", "directions_object",
           "current_frame_object", "track_lines_object", "track_point_object"]
