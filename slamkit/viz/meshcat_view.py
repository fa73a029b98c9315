"""The 3D map in meshcat: coloured map points, keyframe frustums, the camera path and the current frame.

:class:`MapView` draws a :class:`MapState` (a read-only snapshot of a map: a pycolmap Reconstruction, its
keyframes and the posed frames' path) and, on every :meth:`MapView.update`, sends only what changed:

- Map points are grouped by the keyframe that introduced them (one meshcat ``Points`` object per keyframe,
  ``points/kf000012``). A new keyframe sends its group; bundle adjustment re-sends only the groups with a
  point that moved by more than ``move_tolerance`` (relative to the map extent) or was added or removed.
  What is in the scene is always what was last sent, so small moves accumulate until they are re-sent.
- Which points can have changed is read from the keyframes whose pose changed or that are new (local BA
  adjusts exactly the points its window observes, and merges or filters only those). When most keyframes
  moved (global BA, normalization), the map was replaced (new segment, reset) or the point count does not
  add up, every point is read again, through pycolmap's PLY writer (one C++ pass; about 25x faster than
  reading 100k ``Point3D`` objects from Python).
- Frustums, path and viewing directions are one ``LineSegments`` object each (thousands of vertices, a few
  kB), re-sent when the keyframes move; the current frame is a fixed frustum moved by ``set_transform``.

Colours: recency from green (first keyframe) through yellow to red (last keyframe), by timestamp, for
frustums, path and viewing directions alike; the current frame is blue; the selected track is magenta.
The map is shown in a display frame (x right, y forward, z up of the first keyframe's camera) centred and
scaled so it spans about six units (one ``set_transform`` of the root), refitted when the map outgrows it
or is normalized (only the frustums are re-sent then); "Reset camera" refits it and puts the viewer's
camera back behind and above the first keyframe.

Geometry goes to meshcat as 3xN float32 (positions and colours in [0, 1]); ``Nx3`` would be drawn as garbage.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pycolmap

from .server import MeshcatServer, ViewerError

if TYPE_CHECKING:  # pragma: no cover
    from ..pipeline import Slam

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

_FRUSTUM_EDGES = [(0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 3), (3, 4), (4, 1)]
"""Apex 0 and image corners 1-4: four rays and the image rectangle (8 segments, 16 vertices)."""


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


# ---------------------------------------------------------------------------------------------- state


@dataclass(eq=False)
class MapState:
    """What the map view draws; references into a live map, read during :meth:`MapView.show`.

    reconstruction: the map (pycolmap); keyframe_ids: (K,) image ids of the keyframes to draw;
    keyframe_times: (K,) seconds; path_times: (N,) seconds and path_centers: (N, 3) world camera centres of
    the posed frames in time order; current: (4, 4) world_from_cam of the current non-key frame, or None;
    key: identity of the map — a different key means a different map (new segment, reset, loaded run)
    and everything is sent again.
    """

    reconstruction: pycolmap.Reconstruction
    keyframe_ids: np.ndarray
    keyframe_times: np.ndarray
    path_times: np.ndarray = field(default_factory=lambda: np.empty(0))
    path_centers: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    current: np.ndarray | None = None
    key: Any = None

    def __post_init__(self) -> None:
        self.keyframe_ids = np.asarray(self.keyframe_ids, np.int64).reshape(-1)
        self.keyframe_times = np.asarray(self.keyframe_times, np.float64).reshape(-1)
        self.path_times = np.asarray(self.path_times, np.float64).reshape(-1)
        self.path_centers = np.asarray(self.path_centers, np.float64).reshape(-1, 3)
        if len(self.keyframe_ids) != len(self.keyframe_times):
            raise ValueError(f"{len(self.keyframe_ids)} keyframe ids but {len(self.keyframe_times)} times")
        if len(self.path_times) != len(self.path_centers):
            raise ValueError(f"{len(self.path_times)} path times but {len(self.path_centers)} centres")
        order = np.argsort(self.keyframe_ids, kind="stable")
        self.keyframe_ids, self.keyframe_times = self.keyframe_ids[order], self.keyframe_times[order]
        if self.key is None:
            self.key = self.reconstruction


def state_from_slam(slam: "Slam") -> MapState | None:
    """The current segment's map of a running :class:`~slamkit.pipeline.Slam` (None before initialization)."""
    m = slam.slam_map
    if m is None or m.num_keyframes == 0:
        return None
    seg = slam.segment if slam.segment is not None else slam.main_segment
    traj = slam.trajectory(segment=seg.id)
    ids = np.array(sorted(m.keyframes), np.int64)
    times = np.array([m.keyframes[int(i)].timestamp for i in ids])
    current = None
    r = slam.last_result
    if r is not None and r.cam_from_world is not None and not r.is_keyframe and r.segment == seg.id:
        current = np.linalg.inv(r.cam_from_world)
    return MapState(m.reconstruction, ids, times, traj.timestamps, traj.positions, current, key=m)


def state_from_run(run_dir: str | os.PathLike) -> MapState:
    """A saved run folder (``slam.save``): ``DIR/sparse`` (COLMAP model) and ``DIR/trajectory_tum.txt``.

    Keyframe times come from ``DIR/keyframes_tum.txt`` when it lists as many keyframes as the model has
    registered images; otherwise keyframes are coloured by image id order.
    """
    from ..errors import SourceError
    from ..io import read_tum

    run_dir = Path(run_dir)
    sparse = run_dir / "sparse"
    if not (sparse / "images.bin").is_file() and not (sparse / "images.txt").is_file():
        raise SourceError(f"{sparse}: no COLMAP model (images.bin) — is {run_dir} a folder written by slam.save?")
    if (sparse / "images.bin").is_file():
        from ..io.saved import check_colmap_model

        check_colmap_model(sparse)  # a damaged model would hang or abort pycolmap's reader
    rec = pycolmap.Reconstruction(str(sparse))
    ids = np.array(sorted(rec.reg_image_ids()), np.int64)
    times = None
    traj_path = run_dir / "trajectory_tum.txt"
    path_t, path_c = np.empty(0), np.empty((0, 3))
    if traj_path.is_file():
        traj = read_tum(traj_path)
        path_t, path_c = traj.timestamps, traj.positions
    kf_path = run_dir / "keyframes_tum.txt"
    if kf_path.is_file():
        kf = read_tum(kf_path)
        if len(kf) == len(ids):
            times = kf.timestamps
    if times is None:  # no keyframe times: image id order, spread over the path's time span if any
        span = (path_t[0], path_t[-1]) if len(path_t) else (0.0, float(max(len(ids) - 1, 1)))
        times = np.interp(np.arange(len(ids)), [0, max(len(ids) - 1, 1)], span)
    return MapState(rec, ids, times, path_t, path_c, None, key=rec)


# ---------------------------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class ViewSettings:
    """What the map view shows and how (all of it can change at any time with :meth:`MapView.configure`)."""

    background: str = "#ffffff"
    """Background colour, '#rrggbb'."""
    show_points: bool = True
    show_keyframes: bool = True
    """Keyframe frustums."""
    show_path: bool = True
    """The camera path through every posed frame."""
    show_current: bool = True
    """The current (tracked, non-key) frame's frustum, in blue."""
    show_directions: bool = False
    """A viewing-direction vector (optical axis) from every keyframe."""
    frustum_scale: float = 1.0
    """Frustum size as a multiple of 1/40 of the map extent."""
    point_size: float = 1.0
    """Point size as a multiple of 1/120 of the map extent (in the viewer: 0.05 of its 6 units)."""
    track_point: int = -1
    """Draw lines from this 3D point id to every keyframe observing it (-1 = none)."""
    clip: tuple[int, int] | None = None
    """(first, last) keyframe image ids, inclusive: only points, cameras and tracks introduced between them."""

    def validate(self) -> "ViewSettings":
        hex_to_rgb255(self.background)
        if not self.frustum_scale > 0 or not self.point_size > 0:
            raise ValueError("frustum_scale and point_size must be > 0")
        if self.clip is not None and (len(self.clip) != 2 or self.clip[0] > self.clip[1]):
            raise ValueError(f"clip must be (first, last) with first <= last, got {self.clip!r}")
        return self


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


# ---------------------------------------------------------------------------------------------- reading


def _observed_ids(image: pycolmap.Image) -> np.ndarray:
    """(M,) int64 ids of the 3D points an image observes."""
    return np.array([p.point3D_id for p in image.get_observation_points2D()], np.int64)


def _read_points(rec: pycolmap.Reconstruction, ids: np.ndarray, with_color: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """xyz (M, 3) float32 of the given points and rgb (M, 3) uint8 where ``with_color`` (else zeros)."""
    pts = rec.points3D
    n = len(ids)
    xyz = np.empty((n, 3), np.float32)
    rgb = np.zeros((n, 3), np.uint8)
    idl = ids.tolist()
    if with_color is None:
        for j, i in enumerate(idl):
            xyz[j] = pts[i].xyz
    else:
        wc = with_color.tolist()
        for j, i in enumerate(idl):
            p = pts[i]
            xyz[j] = p.xyz
            if wc[j]:
                rgb[j] = p.color
    return xyz, rgb


_PLY_DTYPE = np.dtype([("xyz", "<f4", 3), ("rgb", "u1", 3)])


def _read_all_points(rec: pycolmap.Reconstruction) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ids (N,) int64 sorted, xyz (N, 3) float32, rgb (N, 3) uint8) of every point.

    Through ``Reconstruction.export_PLY`` (C++) into a temporary file: points come in the order of
    ``points3D.keys()`` (the same container, unchanged in between); checked on a few points, else the
    slow per-point read is used.
    """
    n = rec.num_points3D()
    if n == 0:
        return np.empty(0, np.int64), np.empty((0, 3), np.float32), np.empty((0, 3), np.uint8)
    pts = rec.points3D
    tmp_dir = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None
    fd, tmp = tempfile.mkstemp(suffix=".ply", dir=tmp_dir)
    os.close(fd)
    try:
        rec.export_PLY(tmp)
        ids = np.fromiter(pts.keys(), np.int64, n)
        with open(tmp, "rb") as f:
            data = f.read()
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    end = data.find(b"end_header\n")
    header = data[:end].decode("ascii", "replace").split("\n")
    layout = [ln.split()[-1] for ln in header if ln.startswith("property")]
    ok = end > 0 and layout == ["x", "y", "z", "red", "green", "blue"]
    if ok:
        body = np.frombuffer(data, _PLY_DTYPE, count=n, offset=end + len(b"end_header\n"))
        xyz, rgb = body["xyz"].copy(), body["rgb"].copy()
        probe = np.unique(np.linspace(0, n - 1, min(n, 8)).astype(int))
        ref = np.array([pts[int(ids[j])].xyz for j in probe], np.float32)
        ok = np.allclose(ref, xyz[probe], rtol=1e-6, atol=1e-6)
    if not ok:  # layout or order not as expected: read point by point
        xyz, rgb = _read_points(rec, ids, np.ones(n, bool))
    order = np.argsort(ids)
    return ids[order], xyz[order], rgb[order]


def _introductions(new_ids: np.ndarray, observers: dict[int, np.ndarray], first_new_keyframe: int,
                   newest_keyframe: int) -> np.ndarray:
    """The keyframe that introduced each new point: the second-smallest keyframe observing it (a point
    needs two views), never earlier than the first keyframe that is new in this update; the newest
    keyframe when no observer is known."""
    out = np.full(len(new_ids), newest_keyframe, np.int64)
    if len(new_ids) == 0 or not observers:
        return out
    pid = np.concatenate([v for v in observers.values()])
    iid = np.concatenate([np.full(len(v), k, np.int64) for k, v in observers.items()])
    keep = np.isin(pid, new_ids)
    pid, iid = pid[keep], iid[keep]
    if len(pid):
        order = np.lexsort((iid, pid))
        pid, iid = pid[order], iid[order]
        starts = np.flatnonzero(np.r_[True, pid[1:] != pid[:-1]])
        counts = np.diff(np.r_[starts, len(pid)])
        second = np.where(counts >= 2, iid[np.minimum(starts + 1, len(pid) - 1)], iid[starts])
        pos = np.searchsorted(new_ids, pid[starts])
        out[pos] = second
    return np.maximum(out, first_new_keyframe)


# ---------------------------------------------------------------------------------------------- the view


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
                 move_tolerance: float = 1e-4, server: MeshcatServer | None = None, name: str = "slamkit"):
        self._server: MeshcatServer | None = None
        if vis is None:
            if server is None:
                server = self._server = MeshcatServer()
            vis = server.visualizer()
        self.vis = vis
        self.root = vis[name]
        self.settings = (settings or ViewSettings()).validate()
        self.full_read_points = int(full_read_points)
        self.move_tolerance = float(move_tolerance)
        self.stats = UpdateStats()
        self.closed = False
        self._sent_bytes = 0
        self._objects = 0
        self.objects_sent_total = 0
        """Objects (set_object commands) sent since the view was created."""
        self._reset_state()
        self._send_scene_settings()

    # ------------------------------------------------------------------ lifecycle
    def _reset_state(self) -> None:
        self._key: Any = None
        self._rec: pycolmap.Reconstruction | None = None
        self._kf_ids = np.empty(0, np.int64)
        self._kf_times = np.empty(0)
        self._kf_pose = np.empty((0, 3, 4))  # cam_from_world as last read
        self._path_t = np.empty(0)
        self._path_c = np.empty((0, 3))
        self._current: np.ndarray | None = None
        self._pid = np.empty(0, np.int64)
        self._xyz = np.empty((0, 3), np.float32)
        self._rgb = np.empty((0, 3), np.uint8)
        self._intro = np.empty(0, np.int64)  # introducing keyframe; -1 = deleted (a tombstone)
        self._n_dead = 0
        self._obs: dict[int, np.ndarray] = {}
        self._chunks: dict[int, int] = {}  # introducing keyframe -> points in the scene
        self._fit: tuple[np.ndarray, float] | None = None  # (centre (3,), map extent)
        self._camera: tuple[float, float, float, float, int, int] | None = None
        self._scene: dict[str, int] = {}
        self._directions_stale = False
        self._current_shown: bool | None = None

    def close(self) -> None:
        """Stop the server this view started (a view drawing into a given ``vis`` leaves it running)."""
        self.closed = True
        if self._server is not None:
            self._server.close()

    @property
    def server(self) -> MeshcatServer | None:
        return self._server

    @property
    def url(self) -> str:
        return self.vis.url()

    def iframe_html(self, height: int = 480) -> str:
        """An ``<iframe>`` showing the live viewer (for an ipywidgets HTML widget)."""
        return (f'<div style="height:{int(height)}px;width:100%;overflow:hidden;resize:both">'
                f'<iframe class="slamkit-map" src="{self.url}" style="width:100%;height:100%;border:none">'
                f'</iframe></div>')

    def display(self, height: int = 480):
        """The live viewer, inline in a notebook (the last expression of a cell)."""
        from IPython.display import HTML

        return HTML(self.iframe_html(height))

    def static_html(self) -> str:
        """The current scene as one self-contained HTML page (the viewer's JavaScript included)."""
        return self.vis.static_html()

    def export_html(self, path: str | os.PathLike) -> Path:
        """Write :meth:`static_html` to ``path`` (atomically) for reports; opens from file:// offline."""
        from ..io import atomic_write_text

        path = Path(path)
        atomic_write_text(path, self.static_html())
        return path

    # ------------------------------------------------------------------ sending
    def _send(self, node, obj) -> None:
        node.set_object(obj)
        self._objects += 1
        self.objects_sent_total += 1

    def _points_object(self, xyz: np.ndarray, rgb: np.ndarray, size: float):
        pos = np.ascontiguousarray(xyz, np.float32).T  # 3xN (F-contiguous view: packed without a copy)
        col = (np.asarray(rgb, np.float32) / 255.0).T
        self._sent_bytes += pos.nbytes + col.nbytes
        return mg.PointCloud(pos, col, size=float(size))

    def _lines_object(self, vertices: np.ndarray, colors: np.ndarray):
        """vertices (2M, 3), colors (2M, 3) in [0, 1] -> LineSegments (pairs of vertices)."""
        pos = np.ascontiguousarray(vertices, np.float32).T
        col = np.ascontiguousarray(colors, np.float32).T
        self._sent_bytes += pos.nbytes + col.nbytes
        return mg.LineSegments(mg.PointsGeometry(pos, col), mg.LineBasicMaterial(vertexColors=True))

    def _send_background(self) -> None:
        """meshcat 0.3.2's gradient background renders black (its three.js dropped RGBFormat textures), so
        the background is a large sphere seen from inside, in an unlit material."""
        rgb = hex_to_rgb255(self.settings.background)
        color = (rgb[0] << 16) | (rgb[1] << 8) | rgb[2]
        self.vis["background"].set_object(mg.Sphere(BACKGROUND_RADIUS),
                                          mg.MeshBasicMaterial(color=color, side=1))  # 1 = THREE.BackSide

    def _send_scene_settings(self) -> None:
        s = self.settings
        self.vis["/Background"].set_property("visible", False)
        self.vis["/Grid"].set_property("visible", False)
        self.vis["/Cameras/default/rotated/<object>"].set_property("far", BACKGROUND_RADIUS * 4)
        self._send_background()
        for name, on in (("points", s.show_points), ("keyframes", s.show_keyframes), ("path", s.show_path),
                         ("current", s.show_current), ("directions", s.show_directions)):
            self.root[name].set_property("visible", bool(on))

    # ------------------------------------------------------------------ public drawing API
    def update(self, slam: "Slam") -> UpdateStats:
        """Draw the running SLAM's current map, sending only what changed since the last call."""
        return self.show(state_from_slam(slam))

    def on_step(self, slam: "Slam", result) -> None:
        """A ``slam.callbacks`` hook: redraw after keyframes and initialization, else move the current frame."""
        if slam.slam_map is None and self._key is None:
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

    def show(self, state: MapState | None) -> UpdateStats:
        """Draw ``state`` (None clears the map), sending only what differs from what is in the scene."""
        if self.closed:
            raise ViewerError("the map view is closed")
        t0 = time.perf_counter()
        self._objects, self._sent_bytes = 0, 0
        st = UpdateStats()
        if state is None:
            if self._key is not None:
                self.clear()
            st.mode = "empty"
            st.total_s = time.perf_counter() - t0
            self.stats = st
            return st
        new_map = state.key is not self._key
        if new_map:
            self.clear()
            self._key = state.key
        rec = self._rec = state.reconstruction
        self._camera = self._camera_of(rec, state.keyframe_ids)

        # ---- keyframes: which are new or moved
        t_read = time.perf_counter()
        ids = state.keyframe_ids
        poses = np.array([rec.image(i).cam_from_world().matrix() for i in ids.tolist()]).reshape(-1, 3, 4)
        found, rows = _lookup(ids, self._kf_ids)
        moved_mask = np.zeros(len(ids), bool)
        moved_mask[found] = np.any(poses[found] != self._kf_pose[rows[found]], axis=(1, 2))
        new_kf = ids[~found].tolist()
        moved = ids[moved_mask].tolist()
        dirty = new_kf + moved
        kf_changed = bool(dirty) or len(ids) != len(self._kf_ids) or not np.array_equal(
            state.keyframe_times, self._kf_times)
        self._kf_ids, self._kf_times, self._kf_pose = ids, state.keyframe_times.copy(), poses
        first_new = min(new_kf) if new_kf else (int(ids[-1]) if len(ids) else 0)
        newest = int(ids[-1]) if len(ids) else 0
        st.keyframes, st.dirty_keyframes = len(ids), len(dirty)
        many_moved = len(moved) > max(8, len(ids) // 2)

        # ---- points: read what can have changed
        n_points = rec.num_points3D()
        full = new_map or n_points <= self.full_read_points or many_moved
        if full:
            st.mode = "full"
            r_ids, r_xyz, r_rgb = _read_all_points(rec)
            is_known, known_rows = self._lookup_points(r_ids)
            alive_rows = np.flatnonzero(self._intro >= 0)
            gone = ~_isin_sorted(self._pid[alive_rows], r_ids)
            del_rows = alive_rows[gone]
            new_ids = r_ids[~is_known]
            observers, complete = ({}, False) if len(new_ids) == 0 else self._read_observers(rec, ids, new_ids)
        else:
            st.mode = "incremental"
            observers, complete = {k: _observed_ids(rec.image(k)) for k in dirty}, True
            r_ids = np.unique(np.concatenate([*observers.values(), np.empty(0, np.int64)]))
            is_known, known_rows = self._lookup_points(r_ids)
            prev = [self._obs[k] for k in dirty if k in self._obs]
            gone = np.setdiff1d(np.concatenate([*prev, np.empty(0, np.int64)]), r_ids)
            g_known, g_rows = self._lookup_points(gone)
            gone, g_rows = gone[g_known], g_rows[g_known]
            exists = np.array([rec.exists_point3D(p) for p in gone.tolist()], bool)
            del_rows = g_rows[~exists]
            new_ids = r_ids[~is_known]
            r_xyz, r_rgb = _read_points(rec, r_ids, ~is_known)
            if self.num_points - len(del_rows) + len(new_ids) != n_points:
                # something no dirty keyframe observes changed (an edge case): reconcile by ids
                all_ids = np.sort(np.fromiter(rec.points3D.keys(), np.int64, n_points))
                alive_rows = np.flatnonzero(self._intro >= 0)
                del_rows = alive_rows[~_isin_sorted(self._pid[alive_rows], all_ids)]
                extra = all_ids[~self._lookup_points(all_ids)[0] & ~_isin_sorted(all_ids, new_ids)]
                if len(extra):
                    e_xyz, e_rgb = _read_points(rec, extra, np.ones(len(extra), bool))
                    r_ids = np.concatenate([r_ids, extra])
                    r_xyz = np.concatenate([r_xyz, e_xyz])
                    r_rgb = np.concatenate([r_rgb, e_rgb])
                    order = np.argsort(r_ids)
                    r_ids, r_xyz, r_rgb = r_ids[order], r_xyz[order], r_rgb[order]
                    is_known, known_rows = self._lookup_points(r_ids)
                    new_ids = r_ids[~is_known]
                complete = False
        if complete:  # full observation lists: kept to find deleted points next time
            self._obs.update(observers)
        current_ids = set(ids.tolist())
        for k in [k for k in self._obs if k not in current_ids]:
            del self._obs[k]
        st.points_read = len(r_ids)
        st.read_s = time.perf_counter() - t_read

        # ---- diff against what the scene shows
        t_diff = time.perf_counter()
        new_intro = _introductions(new_ids, observers, first_new, newest)
        tol = self.move_tolerance * (self._fit[1] if self._fit is not None else 1.0)
        krows = known_rows[is_known]
        k_xyz = r_xyz[is_known]
        delta = np.abs(k_xyz - self._xyz[krows]).max(axis=1) if len(krows) else np.empty(0)
        changed = (set(self._intro[krows[delta > tol]].tolist()) | set(self._intro[del_rows].tolist())
                   | set(new_intro.tolist()))
        if changed:  # the groups re-sent show the points as read now
            upd = np.isin(self._intro[krows], np.fromiter(changed, np.int64))
            self._xyz[krows[upd]] = k_xyz[upd]
        if len(del_rows):  # tombstones; compacted when they pile up
            self._intro[del_rows] = -1
            self._n_dead += len(del_rows)
        if len(new_ids):
            self._append_points(new_ids, r_xyz[~is_known], r_rgb[~is_known], new_intro)
        if self._n_dead > max(1000, len(self._pid) // 20):
            self._compact()
        st.points = self.num_points
        path_changed = (len(state.path_times) != len(self._path_t)
                        or not np.array_equal(state.path_centers, self._path_c))
        self._path_t, self._path_c = state.path_times.copy(), state.path_centers.copy()
        refit = self._refit_needed(full)
        if refit:
            self._fit = refit if isinstance(refit, tuple) else self._compute_fit()
            st.refit = True
        st.diff_s = time.perf_counter() - t_diff

        # ---- send
        t_send = time.perf_counter()
        if refit:
            self._send_fit()
        if changed:
            sent, removed, npts = self._send_chunks(changed)
            st.chunks_sent, st.chunks_deleted, st.points_sent = sent, removed, npts
        if kf_changed or path_changed or refit:
            self._send_cameras()
        if new_map or refit:
            self._send_current_geometry()
        if new_map:
            self._send_camera_home()
        self._current = state.current
        self._send_current_pose()
        if self.settings.track_point >= 0 and (changed or kf_changed):
            self._send_track()
        st.send_s = time.perf_counter() - t_send
        st.objects_sent, st.bytes_sent = self._objects, self._sent_bytes
        st.total_s = time.perf_counter() - t0
        self.stats = st
        return st

    # ------------------------------------------------------------------ the point store
    @property
    def num_points(self) -> int:
        """Map points the view holds (drawn unless clipped or hidden)."""
        return len(self._pid) - self._n_dead

    def _groups(self) -> set[int]:
        """Introducing keyframes of the live points (the point groups)."""
        return set(np.unique(self._intro[self._intro >= 0]).tolist())

    def _lookup_points(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(found (M,) bool, rows (M,)) of point ids among the live rows of the store."""
        found, rows = _lookup(ids, self._pid)
        if len(rows) and self._n_dead:
            found &= self._intro[rows] >= 0
        return found, rows

    def _append_points(self, ids: np.ndarray, xyz: np.ndarray, rgb: np.ndarray, intro: np.ndarray) -> None:
        """Add new points; the store stays sorted by id (new points usually have the largest ids)."""
        if self._n_dead and _isin_sorted(ids, self._pid).any():  # an id came back: drop its tombstone first
            self._compact()
        pid = np.concatenate([self._pid, ids])
        xyz = np.concatenate([self._xyz, np.asarray(xyz, np.float32)])
        rgb = np.concatenate([self._rgb, rgb])
        intro = np.concatenate([self._intro, intro])
        if len(self._pid) and len(ids) and ids[0] < self._pid[-1]:
            order = np.argsort(pid, kind="stable")
            pid, xyz, rgb, intro = pid[order], xyz[order], rgb[order], intro[order]
        self._pid, self._xyz, self._rgb, self._intro = pid, xyz, rgb, intro

    def _compact(self) -> None:
        keep = self._intro >= 0
        self._pid, self._xyz, self._rgb, self._intro = (self._pid[keep], self._xyz[keep], self._rgb[keep],
                                                        self._intro[keep])
        self._n_dead = 0

    def show_current(self, world_from_cam: np.ndarray | None) -> None:
        """Move the current-frame frustum (None hides it); one small message."""
        self._current = None if world_from_cam is None else np.asarray(world_from_cam, np.float64)
        if self._key is not None:
            self._send_current_pose()

    def clear(self) -> None:
        """Remove the map from the scene (the viewer settings stay)."""
        for name in ("points", "keyframes", "path", "directions", "current", "track"):
            self.root[name].delete()
        self._reset_state()
        self._send_scene_settings()

    # ------------------------------------------------------------------ settings
    def configure(self, **changes) -> ViewSettings:
        """Change view settings (fields of :class:`ViewSettings`); re-sends only what depends on them."""
        old = self.settings
        new = replace(old, **changes).validate()
        self.settings = new
        if new.background != old.background:
            self._send_background()
        for name in ("points", "keyframes", "path", "current", "directions"):
            if getattr(new, f"show_{name}") != getattr(old, f"show_{name}"):
                self.root[name].set_property("visible", bool(getattr(new, f"show_{name}")))
        if new.show_directions and self._directions_stale and self._key is not None:
            self._send_directions()
        if self._key is None:
            return new
        if new.point_size != old.point_size:
            self._send_chunks(set(self._chunks) | self._groups())
        elif new.clip != old.clip:
            self._send_chunks({k for k in self._groups() | set(self._chunks)
                               if self._within(k, old.clip) != self._within(k, new.clip)})
        if new.frustum_scale != old.frustum_scale or new.clip != old.clip:
            self._send_cameras()
            self._send_current_geometry()
            self._send_current_pose()
        if (new.track_point != old.track_point or new.clip != old.clip or new.point_size != old.point_size
                or new.frustum_scale != old.frustum_scale):
            self._send_track()
        return new

    def reset_camera(self) -> None:
        """Fit the whole map into the viewer and put the viewer's camera back to its overview position."""
        if self._key is not None:
            self._fit = self._compute_fit()
            self._send_fit()
            self._send_cameras()
            self._send_current_geometry()
            self._send_current_pose()
            self._send_track()
        self._send_camera_home()

    def _send_camera_home(self) -> None:
        """The viewer's camera behind and above the first keyframe, looking at the map's centre."""
        cam = self.vis["/Cameras/default/rotated/<object>"]
        offset = DISPLAY_EXTENT * np.array([0.25, -0.9, 0.55])  # viewer axes: x right, y forward, z up
        cam.set_property("position", [float(offset[0]), float(offset[2]), float(-offset[1])])  # three.js is y-up

    # ------------------------------------------------------------------ what is in the scene
    def scene_counts(self) -> dict[str, int]:
        """Objects in the scene as sent: points, keyframe frustums, path vertices, current frame (0/1),
        track lines and point groups."""
        return dict(self._scene, point_groups=len(self._chunks), points=sum(self._chunks.values()))

    @property
    def keyframe_ids(self) -> np.ndarray:
        """(K,) image ids of the keyframes of the map shown (clipped ones included)."""
        return self._kf_ids.copy()

    def shows(self, key: Any) -> bool:
        """Whether the map identified by ``key`` (a SlamMap or Reconstruction) is the one in the scene."""
        return key is not None and key is self._key

    def point_ids(self) -> np.ndarray:
        """(N,) sorted ids of the map points the view holds (drawn unless clipped)."""
        return self._pid[self._intro >= 0]

    def point_positions(self, ids) -> np.ndarray:
        """(M, 3) float32 positions of the given points as the scene shows them (KeyError for unknown ids)."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        found, rows = self._lookup_points(ids)
        if not found.all():
            raise KeyError(f"points not in the view: {ids[~found][:10].tolist()}")
        return self._xyz[rows]

    def point_introductions(self) -> dict[int, int]:
        """Point id -> the keyframe image id that introduced it (its group)."""
        alive = self._intro >= 0
        return dict(zip(self._pid[alive].tolist(), self._intro[alive].tolist()))

    @property
    def display_from_map(self) -> np.ndarray:
        """(4, 4) the similarity from map coordinates to the viewer's (the transform of ``/slamkit``)."""
        c, extent = self._fit if self._fit is not None else (np.zeros(3), DISPLAY_EXTENT)
        s = DISPLAY_EXTENT / extent
        T = np.eye(4)
        T[:3, :3] = s * DISPLAY_FROM_OPENCV
        T[:3, 3] = -s * DISPLAY_FROM_OPENCV @ c
        return T

    # ------------------------------------------------------------------ internals
    @staticmethod
    def _camera_of(rec: pycolmap.Reconstruction, ids: np.ndarray):
        if len(ids) == 0:
            return None
        cam = rec.image(int(ids[0])).camera
        K = cam.calibration_matrix()
        return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(cam.width), int(cam.height)

    @staticmethod
    def _read_observers(rec, ids, new_ids) -> tuple[dict[int, np.ndarray], bool]:
        """Keyframe -> observed point ids, for the new points: from their tracks when they are few
        (partial lists), else every keyframe's observations (complete lists)."""
        if len(new_ids) <= 2000 and len(new_ids) < 0.2 * max(rec.num_points3D(), 1):
            pts = rec.points3D
            out: dict[int, list[int]] = {}
            for p in new_ids.tolist():
                for el in pts[p].track.elements:
                    out.setdefault(int(el.image_id), []).append(p)
            return {k: np.array(v, np.int64) for k, v in out.items()}, False
        return {int(k): _observed_ids(rec.image(int(k))) for k in ids}, True

    def _compute_fit(self) -> tuple[np.ndarray, float]:
        centers = self._kf_centers()
        pts = self._xyz[self._intro >= 0].astype(np.float64)
        if len(pts) >= 20:
            lo, hi = np.percentile(pts, [2, 98], axis=0)
            pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
        allp = np.concatenate([pts, centers, self._path_c]) if len(pts) + len(centers) else np.zeros((1, 3))
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        extent = float(np.max(hi - lo))
        if not np.isfinite(extent) or extent <= 1e-9:
            extent = 1.0
        return (lo + hi) / 2, extent

    def _refit_needed(self, full: bool) -> bool | tuple[np.ndarray, float]:
        """Whether the display fit no longer frames the map: none yet; or (every point read) the map's
        extent changed by more than -40 % / +25 % or its centre moved by a quarter of it (growth, bundle
        adjustment's normalization); or (incremental) a camera left the fitted box by 20 %.
        Returns the new fit when it was computed."""
        if self._fit is None:
            return True
        c, ext = self._fit
        if full:
            cand = self._compute_fit()
            if not (0.6 * ext <= cand[1] <= 1.25 * ext) or np.abs(cand[0] - c).max() > 0.25 * ext:
                return cand
            return False
        centres = np.concatenate([self._kf_centers(), self._path_c])
        return bool(len(centres)) and bool(np.abs(centres - c).max() > 0.6 * ext)

    def _send_fit(self) -> None:
        self.root.set_transform(self.display_from_map)

    @property
    def _map_extent(self) -> float:
        return self._fit[1] if self._fit is not None else 1.0

    @property
    def _frustum_depth(self) -> float:
        return self._map_extent / 40.0 * self.settings.frustum_scale

    @property
    def _point_size(self) -> float:
        """In viewer units (point sizes ignore the scale of the ``/slamkit`` transform)."""
        return DISPLAY_EXTENT / 120.0 * self.settings.point_size

    @staticmethod
    def _within(k: int, clip: tuple[int, int] | None) -> bool:
        return clip is None or clip[0] <= k <= clip[1]

    def _in_clip(self, k: int) -> bool:
        return self._within(k, self.settings.clip)

    def _send_chunks(self, keys: set[int]) -> tuple[int, int, int]:
        """Send the point groups ``keys`` as they are in the store (delete the empty or clipped ones)."""
        sent = removed = npts = 0
        if not keys:
            return 0, 0, 0
        keys = set(int(k) for k in keys)
        few = len(keys) <= 16
        if not few:
            order = np.argsort(self._intro, kind="stable")
            sorted_intro = self._intro[order]
        size = self._point_size
        for k in sorted(keys):
            if few:
                rows = np.flatnonzero(self._intro == k)
            else:
                lo, hi = np.searchsorted(sorted_intro, [k, k + 1])
                rows = order[lo:hi]
            node = self.root["points"][f"kf{k:06d}"]
            if len(rows) == 0 or not self._in_clip(k):
                if k in self._chunks:
                    node.delete()
                    del self._chunks[k]
                    removed += 1
                continue
            self._send(node, self._points_object(self._xyz[rows], self._rgb[rows], size))
            self._chunks[k] = len(rows)
            sent += 1
            npts += len(rows)
        return sent, removed, npts

    def _kf_world_from_cam(self) -> np.ndarray:
        """(K, 4, 4) world_from_cam of the keyframes."""
        n = len(self._kf_pose)
        R = self._kf_pose[:, :, :3]
        t = self._kf_pose[:, :, 3]
        out = np.tile(np.eye(4), (n, 1, 1))
        out[:, :3, :3] = np.transpose(R, (0, 2, 1))
        out[:, :3, 3] = -np.einsum("nji,nj->ni", R, t)
        return out

    def _kf_centers(self) -> np.ndarray:
        return self._kf_world_from_cam()[:, :3, 3] if len(self._kf_pose) else np.empty((0, 3))

    def _time_fractions(self, times: np.ndarray) -> np.ndarray:
        """0 at the first keyframe, 1 at the last (path frames outside that span are clipped to 0 / 1)."""
        span = self._kf_times if len(self._kf_times) >= 2 else np.concatenate([self._kf_times, self._path_t])
        if len(span) == 0:
            return np.zeros(len(times))
        t0, t1 = float(span.min()), float(span.max())
        return np.clip((times - t0) / (t1 - t0), 0, 1) if t1 > t0 else np.ones(len(times))

    def _frustum_vertices(self, world_from_cam: np.ndarray, depth: float) -> np.ndarray:
        """(K, 4, 4) poses -> (K * 16, 3) line-segment vertices of the frustums."""
        fx, fy, cx, cy, w, h = self._camera or (1.0, 1.0, 0.5, 0.5, 1, 1)
        corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
        local = np.zeros((5, 3))
        local[1:, 0] = (corners[:, 0] - cx) / fx
        local[1:, 1] = (corners[:, 1] - cy) / fy
        local[1:, 2] = 1.0
        local *= depth
        pts = np.einsum("kij,pj->kpi", world_from_cam[:, :3, :3], local) + world_from_cam[:, None, :3, 3]
        idx = np.array(_FRUSTUM_EDGES).reshape(-1)
        return pts[:, idx, :].reshape(-1, 3)

    def _clip_keyframes(self) -> np.ndarray:
        clip = self.settings.clip
        if clip is None:
            return np.ones(len(self._kf_ids), bool)
        return (self._kf_ids >= clip[0]) & (self._kf_ids <= clip[1])

    def _clip_times(self) -> tuple[float, float]:
        clip = self.settings.clip
        if clip is None or len(self._kf_ids) == 0:
            return -np.inf, np.inf
        sel = self._clip_keyframes()
        if not sel.any():
            return np.inf, -np.inf
        t = self._kf_times[sel]
        return float(t.min()), float(t.max())

    def _send_cameras(self) -> None:
        """Keyframe frustums, viewing directions and the path (one LineSegments object each)."""
        sel = self._clip_keyframes()
        poses = self._kf_world_from_cam()[sel]
        colors = recency_colors(self._time_fractions(self._kf_times[sel]))
        depth = self._frustum_depth
        if len(poses):
            v = self._frustum_vertices(poses, depth)
            self._send(self.root["keyframes"]["geom"], self._lines_object(v, np.repeat(colors, 16, axis=0)))
        else:
            self.root["keyframes"]["geom"].delete()
        self._scene["keyframes"] = len(poses)
        self._directions_stale = True
        if self.settings.show_directions:  # hidden by default: sent when switched on
            self._send_directions()
        t0, t1 = self._clip_times()
        keep = (self._path_t >= t0) & (self._path_t <= t1)
        c, t = self._path_c[keep], self._path_t[keep]
        if len(c) >= 2:
            v = np.stack([c[:-1], c[1:]], axis=1).reshape(-1, 3)
            col = recency_colors(self._time_fractions(np.stack([t[:-1], t[1:]], axis=1).reshape(-1)))
            self._send(self.root["path"]["geom"], self._lines_object(v, col))
        else:
            self.root["path"]["geom"].delete()
        self._scene["path"] = int(len(c))

    def _send_directions(self) -> None:
        """Viewing directions: a segment along each keyframe's optical axis (3 frustum depths long)."""
        sel = self._clip_keyframes()
        poses = self._kf_world_from_cam()[sel]
        if len(poses):
            colors = recency_colors(self._time_fractions(self._kf_times[sel]))
            c = poses[:, :3, 3]
            v = np.stack([c, c + poses[:, :3, 2] * self._frustum_depth * 3], axis=1).reshape(-1, 3)
            self._send(self.root["directions"]["geom"], self._lines_object(v, np.repeat(colors, 2, axis=0)))
        else:
            self.root["directions"]["geom"].delete()
        self._scene["directions"] = len(poses)
        self._directions_stale = False

    def _send_current_geometry(self) -> None:
        v = self._frustum_vertices(np.eye(4)[None], self._frustum_depth * 1.5)
        col = np.tile(np.array(CURRENT_COLOR, np.float32), (len(v), 1))
        self._send(self.root["current"]["frame"], self._lines_object(v, col))
        self._current_shown = None  # the server forgets a node's properties when its object is replaced

    def _send_current_pose(self) -> None:
        shown = self._current is not None
        if shown and self.settings.clip is not None and len(self._kf_ids):
            shown = self.settings.clip[1] >= int(self._kf_ids[-1])  # the present is inside the clip range
        node = self.root["current"]["frame"]
        if shown != self._current_shown:
            node.set_property("visible", bool(shown))
            self._current_shown = shown
        if shown:
            node.set_transform(np.asarray(self._current, np.float64))
        self._scene["current"] = int(shown)

    def _send_track(self) -> None:
        p = int(self.settings.track_point)
        node = self.root["track"]
        self._scene["track"] = 0
        if p < 0 or self._rec is None or not self._rec.exists_point3D(p):
            node.delete()
            return
        row = np.searchsorted(self._pid, p)
        if (row >= len(self._pid) or self._pid[row] != p or self._intro[row] < 0
                or not self._in_clip(int(self._intro[row]))):
            node.delete()
            return
        observers = sorted({int(el.image_id) for el in self._rec.point3D(p).track.elements})
        sel = self._clip_keyframes() & np.isin(self._kf_ids, observers)
        centers = self._kf_world_from_cam()[sel][:, :3, 3]
        xyz = self._xyz[row].astype(np.float64)
        if len(centers):
            v = np.stack([np.tile(xyz, (len(centers), 1)), centers], axis=1).reshape(-1, 3)
            col = np.tile(np.array(TRACK_COLOR, np.float32), (len(v), 1))
            self._send(node["lines"], self._lines_object(v, col))
        else:
            node["lines"].delete()
        self._send(node["point"], self._points_object(xyz[None], np.array([[230, 0, 230]]), self._point_size * 4))
        self._scene["track"] = int(len(centers))


def _lookup(values: np.ndarray, sorted_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(found (M,) bool, positions (M,)) of ``values`` in the sorted array ``sorted_ref``."""
    if len(sorted_ref) == 0 or len(values) == 0:
        return np.zeros(len(values), bool), np.zeros(len(values), np.int64)
    pos = np.minimum(np.searchsorted(sorted_ref, values), len(sorted_ref) - 1)
    return sorted_ref[pos] == values, pos


def _isin_sorted(values: np.ndarray, sorted_ref: np.ndarray) -> np.ndarray:
    """Boolean mask: which of ``values`` are in the sorted array ``sorted_ref``."""
    if len(sorted_ref) == 0 or len(values) == 0:
        return np.zeros(len(values), bool)
    pos = np.minimum(np.searchsorted(sorted_ref, values), len(sorted_ref) - 1)
    return sorted_ref[pos] == values


__all__ = ["MapView", "MapState", "ViewSettings", "UpdateStats", "state_from_slam", "state_from_run",
           "recency_colors", "DISPLAY_FROM_OPENCV"]
