"""The 3D map in meshcat: coloured map points, keyframe frustums, the camera path and the current frame.

:class:`MapView` draws a :class:`MapState` (a read-only snapshot of a map: a pycolmap Reconstruction, its
keyframes and the posed frames' path) and, on every :meth:`MapView.update`, sends only what changed. One
update reads the snapshot (:mod:`.snapshot`), diffs it against what the scene shows (:mod:`.diff`, pure)
and sends the result (:mod:`.sender`) as objects built by :mod:`.scene`:

- Map points are grouped by the keyframe that introduced them (one meshcat ``Points`` object per keyframe,
  ``points/kf000012``). A new keyframe sends its group; bundle adjustment re-sends only the groups with a
  point that moved by more than ``move_tolerance`` (relative to the map extent) or was added or removed.
- Which points can have changed is read from the keyframes whose pose changed or that are new. When most
  keyframes moved (global BA, normalization), the map was replaced (new segment, reset) or the map is
  small, every point is read again.
- Frustums, path and viewing directions are one ``LineSegments`` object each (thousands of vertices, a few
  kB), re-sent when the keyframes move; the current frame is a fixed frustum moved by ``set_transform``.
- Other camera paths through the map (a second walk localized in a saved run's map) are a line and dots in one
  colour each (:meth:`MapView.add_path`), drawn with the path.

The map is shown in a display frame (x right, y forward, z up of the first keyframe's camera) centred and
scaled so it spans about six units (one ``set_transform`` of the root), refitted when the map outgrows it
or is normalized (only the frustums are re-sent then). The view follows the camera: when the current frame or
the newest keyframe nears the viewer's edge (:data:`FOLLOW_BOX`), it refits and puts the viewer's camera home
again (above the path, looking at the map's centre); "Reset camera" does the same at once. Points are coloured
by their height (or in their image colours: ``ViewSettings.color_by``); the legend (:mod:`.legend`), under the
viewer, lists only what the view draws.
"""

from __future__ import annotations

import html
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from IPython.display import HTML

from ..io import atomic_write_text
from .diff import KeyframeChanges, PointsRead, diff_keyframes, diff_points
from .legend import LEGEND, css_color, legend_html, legend_text
from .scene import (BACKGROUND_RADIUS, CURRENT_COLOR, DISPLAY_EXTENT, DISPLAY_FROM_OPENCV, OTHER_PATH_COLOR, TRACK_COLOR,
                    display_from_map, hex_to_rgb255, recency_colors, screen_box)
from .sender import SceneSender
from .server import MeshcatServer, ViewerError
from .settings import ViewSettings
from .shown import OtherPath, ShownMap
from .snapshot import (MapState, read_camera, read_dirty_points, read_every_point, read_poses, state_from_run,
                       state_from_slam)

if TYPE_CHECKING:  # pragma: no cover
    from ..pipeline import Slam


DEFAULT_TITLE = "slamkit map"
"""Title of an exported 3D view."""

FOLLOW_FILL = 0.7
"""How much of the viewer a reframe made to follow the camera fills (the home view fills 0.85)."""

FOLLOW_BOX = 0.92
"""The view reframes when a newest frame is seen beyond this fraction of the way from the viewer's centre to
its edge (normalized device coordinates; the home camera frames the map and every camera within 0.85): the
camera stays inside the view, clear of its edges."""


def captioned_html(page: str, title: str, caption: str, legend=("points-height", "keyframes", "current")) -> str:
    """meshcat's static page with ``title`` instead of "MeshCat" and ``caption`` (plain text, escaped) in a
    box over the top left of the viewer, followed by the colour legend of the entries ``legend``
    (:func:`legend_html`; none when empty or None)."""
    page = page.replace("<title>MeshCat</title>", f"<title>{html.escape(title)}</title>", 1)
    box = (f'<div class="slamkit-caption" style="position:fixed;top:8px;left:8px;max-width:45%;z-index:10;'
           f'font:12px sans-serif;background:rgba(255,255,255,0.85);padding:6px 10px;border-radius:4px">'
           f'<b>{html.escape(title)}</b><br>{html.escape(caption)}{legend_html(legend) if legend else ""}</div>')
    return page.replace("<body>", "<body>" + box, 1)


NO_KERNEL_TEXT = ("The live 3D view needs the running kernel (it is served by this notebook's Python process); "
                  "run the notebook to see it.")
"""What a saved live view shows without a kernel when no snapshot was kept."""


def snapshot_iframe(page: str, width: str, height: int, lazy: bool = False) -> str:
    """``page`` (a whole HTML document) in an ``<iframe srcdoc>``: renders with no server and no kernel,
    in JupyterLab, ``jupyter nbconvert --to html`` and notebook viewers that keep iframes."""
    lazy_attr = ' loading="lazy"' if lazy else ""
    return (f'<iframe class="slamkit-snapshot" srcdoc="{html.escape(page, quote=True)}"{lazy_attr}'
            f' style="width:{width};height:{int(height)}px;border:none"></iframe>')


@dataclass
class UpdateStats:
    """What one :meth:`MapView.show` did and how long it took (seconds)."""

    mode: str = "none"
    """"incremental" (dirty keyframes read), "full" (every point read), "empty" or "none"."""
    read_s: float = 0.0
    diff_s: float = 0.0
    send_s: float = 0.0
    total_s: float = 0.0
    keyframes: int = 0
    dirty_keyframes: int = 0
    points: int = 0
    points_read: int = 0
    chunks_sent: int = 0
    chunks_deleted: int = 0
    points_sent: int = 0
    objects_sent: int = 0
    bytes_sent: int = 0
    refit: bool = False
    """The display fit (centre and scale of the map in the viewer) was recomputed."""

    def __str__(self) -> str:
        return (f"{self.mode}: {self.total_s * 1e3:.1f} ms (read {self.read_s * 1e3:.1f}, diff "
                f"{self.diff_s * 1e3:.1f}, send {self.send_s * 1e3:.1f}); {self.keyframes} keyframes "
                f"({self.dirty_keyframes} dirty), {self.points} points ({self.points_read} read, "
                f"{self.points_sent} sent in {self.chunks_sent} groups), {self.objects_sent} objects"
                + (", refitted" if self.refit else ""))


@dataclass(frozen=True)
class _Diff:
    """What one update must send: the point groups to re-send and which other parts changed."""

    groups: frozenset[int]
    keyframes_changed: bool
    path_changed: bool
    refit: bool
    new_map: bool


class MapView:
    """The 3D map in meshcat, updated incrementally.

    ``vis``: a ``meshcat.Visualizer`` to draw into; by default a :class:`MeshcatServer` on 127.0.0.1 is
    started and owned (stopped by :meth:`close`). ``full_read_points``: maps up to this many points are read
    whole on every update (exact and cheap); above it only the points of new or moved keyframes are read.
    ``move_tolerance``: a point group is re-sent when one of its points moved more than this fraction of the
    map extent (or was added or removed). ``name``: the scene path of this view's objects (two views sharing
    a server need different names; background and viewer camera are shared).

    >>> view = MapView()                    # doctest: +SKIP
    >>> slam.callbacks.append(view.on_step) # redraw after every keyframe (and move the current frame)
    >>> view.display()                      # the viewer, inline in the notebook
    """

    def __init__(self, vis=None, settings: ViewSettings | None = None, *, full_read_points: int = 20_000,
                 move_tolerance: float = 1e-4, server: MeshcatServer | None = None, name: str = "slamkit",
                 aspect: float = 4 / 3):
        self._server: MeshcatServer | None = None
        if vis is None:
            if server is None:
                server = self._server = MeshcatServer()
            vis = server.visualizer()
        self.vis = vis
        self._out = SceneSender(vis, name)
        self.root = self._out.root
        self.settings = (settings or ViewSettings()).validate()
        self.full_read_points = int(full_read_points)
        self.move_tolerance = float(move_tolerance)
        self.aspect = float(aspect)
        """Width / height of the viewer (:meth:`iframe_html` draws it so); the home camera frames the map for it."""
        self.stats = UpdateStats()
        self.reframes = 0
        """How many times the view reframed to follow the camera."""
        self.follow = True
        """Reframe as the camera moves on: refit and re-home when the newest frames leave :data:`FOLLOW_BOX`
        (the viewer's camera is set again then, so an orbit made by hand is undone)."""
        self.closed = False
        self._map = ShownMap()
        self._outputs: list[tuple[Any, Any, int]] = []
        """(display handles of the view and of its picture, height) of every live view :meth:`display` showed."""
        self._out.send_scene_settings(self.settings)

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Stop the server this view started (a view drawing into a given ``vis`` leaves it running)."""
        self.closed = True
        if self._server is not None:
            self._server.close()

    @property
    def server(self) -> MeshcatServer | None:
        return self._server

    @property
    def objects_sent_total(self) -> int:
        """Objects (set_object commands) sent since the view was created."""
        return self._out.objects_total

    @property
    def url(self) -> str:
        return self._out.url

    def iframe_html(self, height: int = 480, snapshot: bool = False, legend: bool = True) -> str:
        """The live viewer (for an ipywidgets HTML widget or a cell output), ``height`` pixels high and
        :attr:`aspect` times as wide (the home camera frames the map for that shape), with the colour legend
        of what it draws *under* the viewer (never over the map) unless ``legend`` is False.

        The viewer is an ``<object>`` loading the live page from this kernel's server; when it cannot load
        (a saved notebook reopened without the kernel, ``nbconvert --to html``) the browser shows what the
        object holds instead: with ``snapshot``, the current scene frozen (:meth:`snapshot_html`), else a
        sentence saying the view needs the kernel."""
        width = int(round(height * self.aspect))
        inner = (snapshot_iframe(self.static_html(legend=False), "100%", height, lazy=True) if snapshot else
                 f'<div class="slamkit-no-kernel" style="padding:2em;font:13px sans-serif;color:#555">'
                 f'{html.escape(NO_KERNEL_TEXT)}</div>')
        # the height is the object's: an untrusted notebook strips object and iframe, and the box collapses
        box = (f'<div class="slamkit-map-box" style="width:{width}px;max-width:100%;position:relative">'
               f'<object class="slamkit-map" type="text/html" data="{self.url}" '
               f'style="display:block;width:100%;height:{int(height)}px;border:none">{inner}</object></div>')
        if not legend:
            return box
        legend_box = f'<div style="max-width:{width}px;padding:2px 0">{legend_html(self.legend_items())}</div>'
        return f"<div>{box}{legend_box}</div>"

    def legend_items(self) -> list[str | tuple[str, str]]:
        """The legend entries (keys of :data:`LEGEND`) of what this view draws with its settings: the
        points' colouring, keyframes and path, the current frame, and a selected track or loop closures only
        when the scene holds one; then a (CSS colour, label) pair for each other path (:meth:`add_path`)."""
        s, counts = self.settings, self._out.counts
        items = [f"points-{s.color_by}"] if s.show_points else []
        if s.show_keyframes or s.show_path:
            items.append("keyframes")
        if s.show_current:
            items.append("current")
        if s.track_point >= 0 and counts.get("track", 0):
            items.append("track")
        if s.show_path and counts.get("loops", 0):
            items.append("loops")
        return items + [(css_color(o.color), o.label) for o in self._map.other_paths if s.show_path]

    def display(self, height: int = 480) -> None:
        """Show the live viewer, then the same map as a picture (a PNG: shown untrusted, without a kernel, on a
        viewer, by nbconvert) and a line on what the live view needs; :meth:`keep_snapshot` updates both."""
        from .static_twin import show_with_picture

        self._outputs.append((*show_with_picture(self, self.iframe_html(height), height), int(height)))

    def keep_snapshot(self) -> int:
        """Store the current scene frozen in every view :meth:`display` made (a trusted notebook shows it without
        a kernel; the live view stays live, its page reloads once) and redraw their pictures. Call it when the
        map is final, e.g. after ``slam.run()``; returns the outputs updated."""
        from .static_twin import picture_bundle

        for handle, pic, height in self._outputs:
            handle.update(HTML(self.iframe_html(height, snapshot=True)))
            pic.update(picture_bundle(self, height), raw=True)
        return len(self._outputs)

    def snapshot_html(self, height: int = 480, title: str = DEFAULT_TITLE, caption: str | None = None) -> str:
        """The current scene frozen in an ``<iframe srcdoc>`` (:meth:`static_html`, legend): no server, no kernel."""
        return snapshot_iframe(self.static_html(title, caption), f"{int(round(height * self.aspect))}px", height)

    def snapshot(self, height: int = 480, title: str = DEFAULT_TITLE, caption: str | None = None) -> None:
        """Display :meth:`snapshot_html` (in a ``<div>``: IPython's "use IFrame" warning stays away), then the same
        map as a picture and the trust line (an untrusted notebook drops the iframe, shows the picture)."""
        from .static_twin import show_with_picture

        show_with_picture(self, f"<div>{self.snapshot_html(height, title, caption)}</div>", height)

    def static_html(self, title: str = DEFAULT_TITLE, caption: str | None = None, legend: bool = True) -> str:
        """The current scene as one self-contained HTML page (the viewer's JavaScript included), titled
        ``title``, with ``caption`` (default: "drag to orbit, scroll to zoom") and the colour legend (unless
        ``legend`` is False: :meth:`iframe_html` draws its own) over the top left of the viewer."""
        return captioned_html(self._out.static_html(), title,
                              "drag to orbit, scroll to zoom" if caption is None else caption,
                              self.legend_items() if legend else None)

    def export_html(self, path: str | os.PathLike, title: str = DEFAULT_TITLE, caption: str | None = None) -> Path:
        """Write :meth:`static_html` to ``path`` (atomically) for reports; opens from file:// offline."""
        path = Path(path)
        atomic_write_text(path, self.static_html(title, caption))
        return path

    # ------------------------------------------------------------------ public drawing API
    def update(self, slam: "Slam") -> UpdateStats:
        """Draw the running SLAM's current map, sending only what changed since the last call."""
        return self.show(state_from_slam(slam))

    def on_step(self, slam: "Slam", result) -> None:
        """A ``slam.callbacks`` hook: redraw after keyframes and initialization, else move the current frame."""
        if slam.slam_map is None and self._map.key is None:
            return
        if result.is_keyframe or result.status == "initialized" or not self.shows(slam.slam_map):
            self.update(slam)
        else:
            self.show_current(None if result.cam_from_world is None or result.is_keyframe
                              else np.linalg.inv(result.cam_from_world))

    def load_run(self, run_dir: str | os.PathLike) -> UpdateStats:
        """Show a saved run (``DIR/sparse`` and ``DIR/trajectory_tum.txt``) without rerunning it."""
        stats = self.show(state_from_run(run_dir))
        self.reset_camera()
        return stats

    def add_path(self, centers, label: str, color: tuple[float, float, float] = OTHER_PATH_COLOR) -> None:
        """Draw another camera path through the map shown, in one ``color`` (RGB in [0, 1]), listed in the legend
        and the picture as ``label``: e.g. a second walk localized in this saved run's map (``centers``: (N, 3)
        camera centres in the map's frame, map units, in time order, such as ``slam.trajectory().positions``). It
        stays until the view shows another map; call :meth:`reset_camera` to frame it with the map."""
        if self._map.key is None:
            raise ViewerError("no map shown yet: draw one (load_run, update) before adding a path through it")
        self._map.other_paths.append(OtherPath(str(label), np.asarray(centers, np.float64).reshape(-1, 3).copy(),
                                               tuple(float(c) for c in color)))
        self._out.send_other_paths(self._map, self.settings)

    def show(self, state: MapState | None) -> UpdateStats:
        """Draw ``state`` (None clears the map), sending only what differs from what is in the scene:
        read the snapshot, diff it against the scene, send the difference."""
        if self.closed:
            raise ViewerError("the map view is closed")
        t0 = time.perf_counter()
        self._out.start_update()
        st = UpdateStats()
        if state is None:
            if self._map.key is not None:
                self.clear()
            st.mode = "empty"
        else:
            new_map = self._enter(state)
            t = time.perf_counter()
            keyframes, read, full = self._read(state, new_map, st)
            st.read_s, t = time.perf_counter() - t, time.perf_counter()
            diff = self._diff(state, keyframes, read, full, new_map, st)
            st.diff_s, t = time.perf_counter() - t, time.perf_counter()
            self._send_diff(diff, state.current, st)
            if not diff.new_map and not diff.refit:
                st.refit = self._follow()
            st.send_s = time.perf_counter() - t
            st.objects_sent, st.bytes_sent = self._out.objects, self._out.bytes
        st.total_s = time.perf_counter() - t0
        self.stats = st
        return st

    # ------------------------------------------------------------------ one update: read, diff, send
    def _enter(self, state: MapState) -> bool:
        """Start drawing ``state``'s map (the scene is cleared for another map); True when it is new."""
        new_map = state.key is not self._map.key
        if new_map:
            self.clear()
            self._map.key = state.key
        self._map.reconstruction = state.reconstruction
        self._map.camera = read_camera(state.reconstruction, state.keyframe_ids)
        return new_map

    def _read(self, state: MapState, new_map: bool, st: UpdateStats) -> tuple[KeyframeChanges, PointsRead, bool]:
        """The keyframes' poses and what changed in them, then the points that can have changed (every
        point when the map is new, small or mostly moved: ``full``)."""
        shown, rec, ids = self._map, state.reconstruction, state.keyframe_ids
        poses = read_poses(rec, ids)
        keyframes = diff_keyframes(shown.kf_ids, shown.kf_pose, shown.kf_times, ids, poses, state.keyframe_times)
        shown.kf_ids, shown.kf_times, shown.kf_pose = ids, state.keyframe_times.copy(), poses
        st.keyframes, st.dirty_keyframes = len(ids), len(keyframes.dirty)
        full = new_map or rec.num_points3D() <= self.full_read_points or keyframes.many_moved(len(ids))
        known = shown.points.live_ids()
        if full:
            read = read_every_point(rec, ids, known)
        else:
            read = read_dirty_points(rec, keyframes.dirty, known, shown.observations)
        st.mode = "full" if full else "incremental"
        st.points_read = len(read.ids)
        return keyframes, read, full

    def _diff(self, state: MapState, keyframes: KeyframeChanges, read: PointsRead, full: bool, new_map: bool,
              st: UpdateStats) -> _Diff:
        """Apply the reading to what the view holds (points, path, display fit); what must be sent."""
        shown = self._map
        shown.keep_observations(read.observers if read.complete else {})
        changes = diff_points(shown.points, read, keyframes, self.move_tolerance * shown.map_extent)
        shown.points.apply(changes)
        st.points = self.num_points
        path_changed = (len(state.path_times) != len(shown.path_t)
                        or not np.array_equal(state.path_centers, shown.path_c)
                        or not np.array_equal(state.loop_edges, shown.loop_edges))
        shown.path_t, shown.path_c = state.path_times.copy(), state.path_centers.copy()
        shown.loop_edges = state.loop_edges.copy()
        refit = shown.refit_needed(full)
        if refit:
            shown.set_fit(refit if isinstance(refit, tuple) else shown.compute_fit(), self.aspect)
            st.refit = True
        return _Diff(changes.groups, keyframes.changed, path_changed, bool(refit), new_map)

    def _send_diff(self, diff: _Diff, current: np.ndarray | None, st: UpdateStats) -> None:
        """Send what changed: fit, point groups, cameras and path, the current frame, the track."""
        out, shown, settings = self._out, self._map, self.settings
        groups = diff.groups
        if diff.refit:
            out.send_fit(shown)
            if (not np.isclose(shown.point_size_units(settings), out.point_size, rtol=0.15)
                    or (settings.color_by == "height" and shown.height_range != out.height_range)):
                # the points' size and height scale follow the scene
                groups = frozenset(shown.points.groups() | set(out.chunks))
        if groups:
            st.chunks_sent, st.chunks_deleted, st.points_sent = out.send_point_groups(shown, settings, groups)
        if diff.keyframes_changed or diff.path_changed or diff.refit:
            out.send_cameras(shown, settings)
        if diff.new_map or diff.refit:
            out.send_current_geometry(shown, settings)
        if diff.new_map or (diff.refit and self.follow):  # the viewer's camera follows the refitted map
            out.send_camera_home(shown, self.aspect)
        shown.current = current
        out.send_current_pose(shown, settings)
        if settings.track_point >= 0 and (diff.groups or diff.keyframes_changed):
            out.send_track(shown, settings)

    # ------------------------------------------------------------------ the point store
    @property
    def num_points(self) -> int:
        """Map points the view holds (drawn unless clipped or hidden)."""
        return self._map.points.num_points

    def _compact(self) -> None:
        """Drop the tombstones of deleted points (what is shown does not change)."""
        self._map.points.compact()

    def show_current(self, world_from_cam: np.ndarray | None) -> None:
        """Move the current-frame frustum (None hides it); one small message."""
        self._map.current = None if world_from_cam is None else np.asarray(world_from_cam, np.float64)
        if self._map.key is not None:
            self._out.send_current_pose(self._map, self.settings)
            self._follow()

    def newest_on_screen(self) -> np.ndarray:
        """(M, 2) where the home camera sees the current frame, the newest keyframe and the newest path frame,
        normalized device coordinates (the viewer spans -1..1; M = 0 before the first update)."""
        shown, out = self._map, self._out
        if shown.fit is None or out.camera_position is None:
            return np.empty((0, 2))
        newest = [shown.current[:3, 3]] if shown.current is not None else []
        if len(shown.kf_ids):
            newest.append(shown.kf_centers()[int(np.argmax(shown.kf_times))])
        if len(shown.path_c):
            newest.append(shown.path_c[-1])
        if not newest:
            return np.empty((0, 2))
        T = display_from_map(shown.fit)
        xyz = np.array(newest, np.float64) @ T[:3, :3].T + T[:3, 3]
        return np.array([np.concatenate(screen_box(np.empty((0, 3)), p[None], out.camera_position, self.aspect))[:2]
                         for p in xyz])

    def _follow(self) -> bool:
        """Reframe (refit the map and put the viewer's camera home) when the current frame, the newest
        keyframe or the newest path frame has left the middle :data:`FOLLOW_BOX` of the viewer (the camera
        has moved on past what the view framed); True when it did. Off with ``follow = False``."""
        if not self.follow:
            return False
        ndc = self.newest_on_screen()
        if len(ndc) == 0 or float(np.abs(ndc).max()) <= FOLLOW_BOX:
            return False
        out, shown, settings = self._out, self._map, self.settings
        shown.set_fit(shown.compute_fit(), self.aspect)
        out.send_fit(shown)
        if (not np.isclose(shown.point_size_units(settings), out.point_size, rtol=0.15)
                or (settings.color_by == "height" and shown.height_range != out.height_range)):
            out.send_point_groups(shown, settings, shown.points.groups() | set(out.chunks))
        out.send_cameras(shown, settings)
        out.send_current_geometry(shown, settings)
        out.send_current_pose(shown, settings)
        out.send_track(shown, settings)
        out.send_camera_home(shown, self.aspect, fill=FOLLOW_FILL)  # room to move on before the next reframe
        self.reframes += 1
        return True

    def clear(self) -> None:
        """Remove the map from the scene (the viewer settings stay)."""
        for name in ("points", "keyframes", "path", "directions", "current", "track"):
            self._out.delete(name)
        self._map = ShownMap()
        self._out.forget()
        self._out.send_scene_settings(self.settings)

    # ------------------------------------------------------------------ settings
    def configure(self, **changes) -> ViewSettings:
        """Change view settings (fields of :class:`ViewSettings`); re-sends only what depends on them."""
        old = self.settings
        new = self.settings = replace(old, **changes).validate()
        out, shown = self._out, self._map
        if new.color_by != old.color_by and shown.key is not None:
            out.send_point_groups(shown, new, shown.points.groups() | set(out.chunks))
        if new.background != old.background:
            out.send_background(new.background)
        for name, visible in new.visibility().items():
            if visible != old.visibility()[name]:
                out.set_visible(name, visible)
        if new.show_directions and out.directions_stale and shown.key is not None:
            out.send_directions(shown, new)
        if shown.key is None:
            return new
        groups = shown.points.groups() | set(out.chunks)
        if new.point_size != old.point_size:
            out.send_point_groups(shown, new, groups)
        elif new.clip != old.clip:
            out.send_point_groups(shown, new, {k for k in groups if old.in_clip(k) != new.in_clip(k)})
        if new.frustum_scale != old.frustum_scale or new.clip != old.clip:
            out.send_cameras(shown, new)
            out.send_current_geometry(shown, new)
            out.send_current_pose(shown, new)
        if (new.track_point != old.track_point or new.clip != old.clip or new.point_size != old.point_size
                or new.frustum_scale != old.frustum_scale):
            out.send_track(shown, new)
        return new

    def reset_camera(self) -> None:
        """Fit the whole map into the viewer and put the viewer's camera back to its overview position."""
        out, shown = self._out, self._map
        if shown.key is not None:
            shown.set_fit(shown.compute_fit(), self.aspect)
            out.send_fit(shown)
            out.send_point_groups(shown, self.settings, shown.points.groups() | set(out.chunks))
            out.send_cameras(shown, self.settings)
            out.send_current_geometry(shown, self.settings)
            out.send_current_pose(shown, self.settings)
            out.send_track(shown, self.settings)
        out.send_camera_home(shown, self.aspect)

    # ------------------------------------------------------------------ what is in the scene
    def scene_counts(self) -> dict[str, int]:
        """Objects in the scene as sent: points, keyframe frustums, path vertices, current frame (0/1),
        track lines and point groups."""
        chunks = self._out.chunks
        return dict(self._out.counts, point_groups=len(chunks), points=sum(chunks.values()))

    @property
    def keyframe_ids(self) -> np.ndarray:
        """(K,) image ids of the keyframes of the map shown (clipped ones included)."""
        return self._map.kf_ids.copy()

    def shows(self, key: Any) -> bool:
        """Whether the map identified by ``key`` (a SlamMap or Reconstruction) is the one in the scene."""
        return key is not None and key is self._map.key

    def point_ids(self) -> np.ndarray:
        """(N,) sorted ids of the map points the view holds (drawn unless clipped)."""
        return self._map.points.live_ids()

    def point_positions(self, ids) -> np.ndarray:
        """(M, 3) float32 positions of the given points as the scene shows them (KeyError for unknown ids)."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        found, rows = self._map.points.lookup(ids)
        if not found.all():
            raise KeyError(f"points not in the view: {ids[~found][:10].tolist()}")
        return self._map.points.xyz[rows]

    def point_introductions(self) -> dict[int, int]:
        """Point id -> the keyframe image id that introduced it (its group)."""
        points = self._map.points
        alive = points.alive()
        return dict(zip(points.pid[alive].tolist(), points.intro[alive].tolist()))

    def scale_numbers(self) -> dict[str, float]:
        """Map units: the fitted extent, the keyframe frustums' depth, the points' diameter and the median
        distance from a point to its nearest camera (what the point size is relative to)."""
        shown = self._map
        return {"extent": shown.map_extent, "frustum_depth": self.settings.frustum_depth(shown.map_extent),
                "point_diameter": self.settings.point_diameter(shown.view_depth), "view_depth": shown.view_depth}

    def longest_tracks(self, n: int = 30) -> list[tuple[int, int]]:
        """(point id, number of images observing it) of the ``n`` map points in the view seen by most images,
        longest first (ties: lower id first)."""
        rec = self._map.reconstruction
        if rec is None or self.num_points == 0:
            return []
        ids = self.point_ids()
        lengths = np.array([rec.point3D(int(p)).track.length() if rec.exists_point3D(int(p)) else 0 for p in ids])
        order = np.lexsort((ids, -lengths))[:n]
        return [(int(ids[i]), int(lengths[i])) for i in order if lengths[i] > 0]

    @property
    def display_from_map(self) -> np.ndarray:
        """(4, 4) the similarity from map coordinates to the viewer's (the transform of ``/slamkit``)."""
        return display_from_map(self._map.fit)


__all__ = ["MapView", "MapState", "legend_text", "legend_html", "LEGEND", "captioned_html", "snapshot_iframe", "DEFAULT_TITLE", "ViewSettings", "UpdateStats",
           "state_from_slam", "state_from_run",
           "recency_colors", "DISPLAY_FROM_OPENCV", "DISPLAY_EXTENT", "BACKGROUND_RADIUS", "CURRENT_COLOR",
           "TRACK_COLOR", "hex_to_rgb255"]
