"""Sending for the map view: the one object that talks to a ``meshcat.Visualizer``.

:class:`SceneSender` owns the view's node ``/meshcat/<name>`` and the few scene-wide settings (background,
grid, the viewer's camera). It draws each part of a :class:`~slamkit.viz.shown.ShownMap` with the objects
of :mod:`.scene` and keeps what the scene holds (point groups, counts): paths are relative to the view's
node — ``points/kf000012``, ``keyframes/geom``, ``path/geom``, ``path/other0/line``, ``path/other0/dots``,
``directions/geom``, ``current/frame``, ``track/lines``, ``track/point``. Every command goes through it, so it
counts what one update sent (objects and geometry bytes) and what was sent since the view was created.
"""

from __future__ import annotations

import numpy as np

from .scene import (BACKGROUND_RADIUS, background_object, current_frame_object, directions_object, display_from_map,
                    geometry_bytes, height_colors, home_camera_position, keyframes_object, loop_band_object,
                    loop_edges_object, map_heights, other_path_objects, path_object, path_vertex_times, points_object,
                    recency_colors, track_lines_object, track_point_object)
from .settings import ViewSettings
from .shown import ShownMap

_VIEWER_CAMERA = "/Cameras/default/rotated/<object>"


class SceneSender:
    """Sends meshcat commands for one map view: ``vis`` a ``meshcat.Visualizer``, ``name`` the view's node."""

    def __init__(self, vis, name: str):
        self.vis = vis
        self.root = vis[name]
        self.objects = 0
        """Objects (set_object commands) sent since :meth:`start_update`."""
        self.bytes = 0
        """Geometry bytes (positions and colours) sent since :meth:`start_update`."""
        self.objects_total = 0
        """Objects sent since this sender was created."""
        self.forget()

    def forget(self) -> None:
        """Forget what the scene holds (after the view's node was cleared)."""
        self.chunks: dict[int, int] = {}
        """Point groups in the scene: introducing keyframe -> points."""
        self.counts: dict[str, int] = {}
        """Keyframe frustums, path vertices, current frame (0/1), track lines and directions in the scene."""
        self.directions_stale = False
        """The keyframes changed while the viewing directions were hidden (sent when they are shown)."""
        self.current_shown: bool | None = None
        self.point_size = float("nan")
        """The point diameter last sent, viewer units."""
        self.height_range: tuple[float, float] | None = None
        """The height scale of the point colours last sent to every group (map units)."""
        self.camera_position: np.ndarray | None = None
        """(3,) the viewer's camera position last sent, viewer axes (x right, y forward, z up)."""

    def start_update(self) -> None:
        """Start counting one update's objects and bytes."""
        self.objects, self.bytes = 0, 0

    # ------------------------------------------------------------------ commands
    def set_object(self, path: str, obj) -> None:
        """Replace the object at ``path`` (a ``Points`` or ``LineSegments`` from :mod:`.scene`)."""
        self.bytes += geometry_bytes(obj)
        self.root[path].set_object(obj)
        self.objects += 1
        self.objects_total += 1

    def delete(self, path: str) -> None:
        self.root[path].delete()

    def set_visible(self, path: str, visible: bool) -> None:
        self.root[path].set_property("visible", bool(visible))

    def static_html(self) -> str:
        """The scene as one self-contained HTML page (the server's copy of every command)."""
        return self.vis.static_html()

    @property
    def url(self) -> str:
        return self.vis.url()

    # ------------------------------------------------------------------ scene-wide settings
    def send_background(self, color: str) -> None:
        """The background sphere in ``color`` ('#rrggbb')."""
        self.vis["background"].set_object(*background_object(color))

    def send_scene_settings(self, settings: ViewSettings) -> None:
        """meshcat's own background and grid hidden, the far plane beyond the background sphere, the
        background colour and the visibility of each part."""
        self.vis["/Background"].set_property("visible", False)
        self.vis["/Grid"].set_property("visible", False)
        self.vis[_VIEWER_CAMERA].set_property("far", BACKGROUND_RADIUS * 4)
        self.send_background(settings.background)
        for name, on in settings.visibility().items():
            self.set_visible(name, on)

    def send_camera_home(self, shown: ShownMap, aspect: float, fill: float = 0.85) -> None:
        """The viewer's camera above the path, looking at the map's centre, as close as frames the 5-95 % box
        of the points and every camera within ``fill`` of the viewer (``aspect``: its width / height)."""
        points, cameras = shown.display_points()
        offset = home_camera_position(points, aspect, cameras, fill=fill)  # viewer axes: x right, y forward, z up
        self.camera_position = offset
        position = [float(offset[0]), float(offset[2]), float(-offset[1])]  # three.js is y-up
        self.vis[_VIEWER_CAMERA].set_property("position", position)

    def send_fit(self, shown: ShownMap) -> None:
        """The transform of the view's node: the map centred and scaled into the viewer."""
        self.root.set_transform(display_from_map(shown.fit))

    # ------------------------------------------------------------------ the map's parts
    def send_point_groups(self, shown: ShownMap, settings: ViewSettings, keys) -> tuple[int, int, int]:
        """Send the point groups ``keys`` as they are in the store (delete the empty or clipped ones);
        (groups sent, groups deleted, points sent)."""
        sent = removed = npts = 0
        if not keys:
            return 0, 0, 0
        store = shown.points
        keys = sorted(set(int(k) for k in keys))
        size = self.point_size = shown.point_size_units(settings)
        if set(keys) >= set(self.chunks) | set(store.groups()):
            self.height_range = shown.height_range  # every group now uses this colour scale
        for k, rows in store.group_rows(keys).items():
            path = f"points/kf{k:06d}"
            if len(rows) == 0 or not settings.in_clip(k):
                if k in self.chunks:
                    self.delete(path)
                    del self.chunks[k]
                    removed += 1
                continue
            xyz = store.xyz[rows]
            rgb = store.rgb[rows] if settings.color_by == "image" else height_colors(map_heights(xyz),
                                                                                      *shown.height_range)
            self.set_object(path, points_object(xyz, rgb, size))
            self.chunks[k] = len(rows)
            sent += 1
            npts += len(rows)
        return sent, removed, npts

    def send_cameras(self, shown: ShownMap, settings: ViewSettings) -> None:
        """Keyframe frustums, viewing directions (when shown) and the path (one LineSegments object each)."""
        sel = shown.clip_keyframes(settings.clip)
        poses = shown.kf_world_from_cam()[sel]
        colors = recency_colors(shown.time_fractions(shown.kf_times[sel]))
        if len(poses):
            depth = settings.frustum_depth(shown.map_extent)
            self.set_object("keyframes/geom", keyframes_object(poses, colors, shown.camera, depth))
        else:
            self.delete("keyframes/geom")
        self.counts["keyframes"] = len(poses)
        self.directions_stale = True
        if settings.show_directions:  # hidden by default: sent when switched on
            self.send_directions(shown, settings)
        self.send_path(shown, settings)

    def send_path(self, shown: ShownMap, settings: ViewSettings) -> None:
        """The camera path through the posed frames inside the clip range's times."""
        t0, t1 = shown.clip_times(settings.clip)
        keep = (shown.path_t >= t0) & (shown.path_t <= t1)
        c, t = shown.path_c[keep], shown.path_t[keep]
        if len(c) >= 2:
            self.set_object("path/geom", path_object(c, shown.time_fractions(path_vertex_times(t))))
        else:
            self.delete("path/geom")
        self.counts["path"] = int(len(c))
        if len(shown.loop_edges):  # loop closures: drawn with the path (shown and hidden with it)
            self.set_object("path/loops", loop_edges_object(shown.loop_edges))
            self.set_object("path/loop_band", loop_band_object(shown.loop_edges,
                                                               6 * shown.point_size_units(settings)))
        else:
            self.delete("path/loops")
            self.delete("path/loop_band")
        self.counts["loops"] = int(len(shown.loop_edges))
        self.send_other_paths(shown, settings)

    def send_other_paths(self, shown: ShownMap, settings: ViewSettings) -> None:
        """The other paths drawn through the map (:attr:`ShownMap.other_paths`), each a line and a dot at every
        frame in its colour, under the path (shown and hidden with it, not clipped: they are no frames of this
        map's run). The dots are 1.5 map points wide (their size is in viewer units: re-sent on a refit)."""
        for i, other in enumerate(shown.other_paths):
            line, dots = other_path_objects(other.centers, other.color, 1.5 * shown.point_size_units(settings))
            if line is not None:
                self.set_object(f"path/other{i}/line", line)
            self.set_object(f"path/other{i}/dots", dots)
        self.counts["other_paths"] = len(shown.other_paths)

    def send_directions(self, shown: ShownMap, settings: ViewSettings) -> None:
        """Viewing directions: a segment along each keyframe's optical axis (3 frustum depths long)."""
        sel = shown.clip_keyframes(settings.clip)
        poses = shown.kf_world_from_cam()[sel]
        if len(poses):
            colors = recency_colors(shown.time_fractions(shown.kf_times[sel]))
            depth = settings.frustum_depth(shown.map_extent)
            self.set_object("directions/geom", directions_object(poses, colors, depth))
        else:
            self.delete("directions/geom")
        self.counts["directions"] = len(poses)
        self.directions_stale = False

    def send_current_geometry(self, shown: ShownMap, settings: ViewSettings) -> None:
        """The current frame's frustum (1.5 keyframe frustums deep), placed by :meth:`send_current_pose`."""
        depth = settings.frustum_depth(shown.map_extent) * 1.5
        self.set_object("current/frame", current_frame_object(shown.camera, depth))
        self.current_shown = None  # the server forgets a node's properties when its object is replaced

    def send_current_pose(self, shown: ShownMap, settings: ViewSettings) -> None:
        """Move (or hide) the current frame: hidden without one or when the clip range ends before the
        newest keyframe."""
        visible = shown.current is not None
        if visible and settings.clip is not None and len(shown.kf_ids):
            visible = settings.clip[1] >= int(shown.kf_ids[-1])  # the present is inside the clip range
        if visible != self.current_shown:
            self.set_visible("current/frame", visible)
            self.current_shown = visible
        if visible:
            self.root["current/frame"].set_transform(np.asarray(shown.current, np.float64))
        self.counts["current"] = int(visible)

    def send_track(self, shown: ShownMap, settings: ViewSettings) -> None:
        """Lines from the selected point to every keyframe observing it (inside the clip range), and the
        point itself; nothing when no point is selected or it is not shown."""
        p = int(settings.track_point)
        self.counts["track"] = 0
        rec, store = shown.reconstruction, shown.points
        if p < 0 or rec is None or not rec.exists_point3D(p):
            self.delete("track")
            return
        row = np.searchsorted(store.pid, p)
        if (row >= len(store.pid) or store.pid[row] != p or store.intro[row] < 0
                or not settings.in_clip(int(store.intro[row]))):
            self.delete("track")
            return
        observers = sorted({int(el.image_id) for el in rec.point3D(p).track.elements})
        sel = shown.clip_keyframes(settings.clip) & np.isin(shown.kf_ids, observers)
        centers = shown.kf_world_from_cam()[sel][:, :3, 3]
        xyz = store.xyz[row].astype(np.float64)
        if len(centers):
            self.set_object("track/lines", track_lines_object(xyz, centers))
        else:
            self.delete("track/lines")
        self.set_object("track/point", track_point_object(xyz, shown.point_size_units(settings) * 3))
        self.counts["track"] = int(len(centers))


__all__ = ["SceneSender"]
