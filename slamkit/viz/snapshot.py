"""Reading the map for the map view: :class:`MapState` snapshots and the points an update reads from them.

A :class:`MapState` is a read-only snapshot of a map (a pycolmap Reconstruction, its keyframes and the
posed frames' path), taken from a running :class:`~slamkit.pipeline.Slam` (:func:`state_from_slam`) or a
saved run (:func:`state_from_run`). An update reads from it either

- every point (:func:`read_every_point`), through pycolmap's PLY writer (one C++ pass; about 25x faster
  than reading 100k ``Point3D`` objects from Python), when the map is small, new or mostly moved; or
- only the points the new or moved keyframes observe (:func:`read_dirty_points`): local bundle adjustment
  adjusts exactly the points its window observes, and merges or filters only those. When the point count
  does not add up, every point id is read to reconcile.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pycolmap

from ..errors import SourceError
from ..io import read_tum
from ..io.saved import check_colmap_model
from .diff import PointsRead, isin_sorted
from .scene import Camera

if TYPE_CHECKING:  # pragma: no cover
    from ..pipeline import Slam


@dataclass(eq=False)
class MapState:
    """What the map view draws; references into a live map, read during :meth:`MapView.show`.

    reconstruction: the map (pycolmap); keyframe_ids: (K,) image ids of the keyframes to draw;
    keyframe_times: (K,) seconds; path_times: (N,) seconds and path_centers: (N, 3) world camera centres of
    the posed frames in time order; current: (4, 4) world_from_cam of the current non-key frame, or None;
    loop_edges: (L, 2, 3) world camera centres of the two keyframes of each loop closed (or place recognised
    by a merged segment) in this map;
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
    loop_edges: np.ndarray = field(default_factory=lambda: np.empty((0, 2, 3)))

    def __post_init__(self) -> None:
        self.keyframe_ids = np.asarray(self.keyframe_ids, np.int64).reshape(-1)
        self.keyframe_times = np.asarray(self.keyframe_times, np.float64).reshape(-1)
        self.path_times = np.asarray(self.path_times, np.float64).reshape(-1)
        self.path_centers = np.asarray(self.path_centers, np.float64).reshape(-1, 3)
        self.loop_edges = np.asarray(self.loop_edges, np.float64).reshape(-1, 2, 3)
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
    return MapState(m.reconstruction, ids, times, traj.timestamps, traj.positions, current_pose(slam, seg.id), key=m,
                    loop_edges=loop_edges(slam, seg.id))


def loop_edges(slam: "Slam", segment: int) -> np.ndarray:
    """(L, 2, 3) world camera centres of the query and candidate keyframes of every loop closure and map
    merge whose frames are now posed in ``segment`` (by frame index: culling and merging renumber images)."""
    st = slam.state
    edges = []
    for c in [*st.loop_closures, *st.map_merges]:
        ends = [st.records[int(c[k])] for k in ("query_frame", "candidate_frame")]
        if all(r.rel_pose is not None and r.segment == segment for r in ends):
            edges.append([np.linalg.inv(st.pose_of(r))[:3, 3] for r in ends])
    return np.array(edges, np.float64).reshape(-1, 2, 3)


def current_pose(slam: "Slam", segment: int) -> np.ndarray | None:
    """(4, 4) world_from_cam of the current frame for the map view, or None (not drawn).

    While running: the last step's pose when it is a tracked non-key frame of ``segment``. After
    ``finish()`` (whose global bundle adjustment moves and may rescale every pose) the last frame's *final*
    pose (``slam.pose_of``), so the marker sits at the end of the drawn path, keyframe or not."""
    r = slam.last_result
    if r is None or r.segment != segment:
        return None
    if slam.finished:
        last = len(slam.records) - 1
        pose = slam.pose_of(last) if last >= 0 else None
        return None if pose is None else np.linalg.inv(pose)
    if r.cam_from_world is None or r.is_keyframe:
        return None
    return np.linalg.inv(r.cam_from_world)


def state_from_run(run_dir: str | os.PathLike) -> MapState:
    """A saved run folder (``slam.save``): ``DIR/sparse`` (COLMAP model) and ``DIR/trajectory_tum.txt``.

    Keyframe times come from ``DIR/keyframes_tum.txt`` when it lists as many keyframes as the model has
    registered images; otherwise keyframes are coloured by image id order.
    """
    run_dir = Path(run_dir)
    sparse = run_dir / "sparse"
    if not (sparse / "images.bin").is_file() and not (sparse / "images.txt").is_file():
        raise SourceError(f"{sparse}: no COLMAP model (images.bin) — is {run_dir} a folder written by slam.save?")
    if (sparse / "images.bin").is_file():
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
    return MapState(rec, ids, times, path_t, path_c, None, key=rec,
                    loop_edges=_saved_loop_edges(run_dir, path_t, path_c))


def _saved_loop_edges(run_dir: Path, path_t: np.ndarray, path_c: np.ndarray) -> np.ndarray:
    """Loop edges of a saved run: the frames of ``summary.json``'s loop closures and merges, found on the
    trajectory by their timestamps in ``frames.csv`` (none when either file is missing or unreadable)."""
    try:
        summary = json.loads((run_dir / "summary.json").read_text())
        with open(run_dir / "frames.csv", newline="") as f:
            stamps = {int(row["index"]): float(row["timestamp"]) for row in csv.DictReader(f)}
    except (OSError, ValueError, KeyError):
        return np.empty((0, 2, 3))
    edges = []
    for c in [*summary.get("loop_closure_pairs", []), *summary.get("map_merges", [])]:
        at = [np.flatnonzero(np.isclose(path_t, stamps.get(int(c[k]), np.nan), atol=5e-7, rtol=0))
              for k in ("query_frame", "candidate_frame")]
        if all(len(a) for a in at):
            edges.append([path_c[a[0]] for a in at])
    return np.array(edges, np.float64).reshape(-1, 2, 3)


# ---------------------------------------------------------------------------------------------- keyframes


def read_camera(rec: pycolmap.Reconstruction, ids: np.ndarray) -> Camera | None:
    """The first keyframe's pinhole intrinsics (fx, fy, cx, cy, width, height), None without keyframes."""
    if len(ids) == 0:
        return None
    cam = rec.image(int(ids[0])).camera
    K = cam.calibration_matrix()
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(cam.width), int(cam.height)


def read_poses(rec: pycolmap.Reconstruction, ids: np.ndarray) -> np.ndarray:
    """(K, 3, 4) cam_from_world of the given images."""
    return np.array([rec.image(i).cam_from_world().matrix() for i in ids.tolist()]).reshape(-1, 3, 4)


def observed_ids(image: pycolmap.Image) -> np.ndarray:
    """(M,) int64 ids of the 3D points an image observes."""
    return np.array([p.point3D_id for p in image.get_observation_points2D()], np.int64)


def read_observers(rec: pycolmap.Reconstruction, ids: np.ndarray, new_ids: np.ndarray
                   ) -> tuple[dict[int, np.ndarray], bool]:
    """Keyframe -> observed point ids, for the new points: from their tracks when they are few
    (partial lists, False), else every keyframe's observations (complete lists, True)."""
    if len(new_ids) <= 2000 and len(new_ids) < 0.2 * max(rec.num_points3D(), 1):
        pts = rec.points3D
        out: dict[int, list[int]] = {}
        for p in new_ids.tolist():
            for el in pts[p].track.elements:
                out.setdefault(int(el.image_id), []).append(p)
        return {k: np.array(v, np.int64) for k, v in out.items()}, False
    return {int(k): observed_ids(rec.image(int(k))) for k in ids}, True


# ---------------------------------------------------------------------------------------------- points


def read_points(rec: pycolmap.Reconstruction, ids: np.ndarray, with_color: np.ndarray | None = None
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


def _export_ply(rec: pycolmap.Reconstruction) -> tuple[np.ndarray, bytes]:
    """(ids (N,) in ``points3D.keys()`` order, the bytes of ``Reconstruction.export_PLY``), through a
    temporary file (in /dev/shm when writable)."""
    tmp_dir = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None
    fd, tmp = tempfile.mkstemp(suffix=".ply", dir=tmp_dir)
    os.close(fd)
    try:
        rec.export_PLY(tmp)
        ids = np.fromiter(rec.points3D.keys(), np.int64, rec.num_points3D())
        with open(tmp, "rb") as f:
            return ids, f.read()
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def read_all_points(rec: pycolmap.Reconstruction) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ids (N,) int64 sorted, xyz (N, 3) float32, rgb (N, 3) uint8) of every point.

    Through ``Reconstruction.export_PLY`` (C++): points come in the order of ``points3D.keys()`` (the
    same container, unchanged in between); checked on a few points, else the slow per-point read is used.
    """
    n = rec.num_points3D()
    if n == 0:
        return np.empty(0, np.int64), np.empty((0, 3), np.float32), np.empty((0, 3), np.uint8)
    pts = rec.points3D
    ids, data = _export_ply(rec)
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
        xyz, rgb = read_points(rec, ids, np.ones(n, bool))
    order = np.argsort(ids)
    return ids[order], xyz[order], rgb[order]


def read_every_point(rec: pycolmap.Reconstruction, keyframe_ids: np.ndarray, known_ids: np.ndarray
                     ) -> PointsRead:
    """Every point of the map; ``known_ids``: (N,) sorted ids of the points the view holds (those not
    read are deleted). Observers are read only when there are new points."""
    ids, xyz, rgb = read_all_points(rec)
    new_ids = ids[~isin_sorted(ids, known_ids)]
    observers, complete = ({}, False) if len(new_ids) == 0 else read_observers(rec, keyframe_ids, new_ids)
    deleted = known_ids[~isin_sorted(known_ids, ids)]
    return PointsRead(ids, xyz, rgb, observers, complete, deleted)


def read_dirty_points(rec: pycolmap.Reconstruction, dirty: list[int], known_ids: np.ndarray,
                      previous: dict[int, np.ndarray]) -> PointsRead:
    """The points the ``dirty`` keyframes observe (colours of those not in ``known_ids``, the view's
    sorted point ids); ``previous``: keyframe -> the observations read last time, so that points a dirty
    keyframe stopped observing and the map no longer has are found deleted. When the count does not add
    up (a change no dirty keyframe observes), every point id is read to reconcile."""
    observers = {k: observed_ids(rec.image(k)) for k in dirty}
    ids = np.unique(np.concatenate([*observers.values(), np.empty(0, np.int64)]))
    is_known = isin_sorted(ids, known_ids)
    prev = [previous[k] for k in dirty if k in previous]
    gone = np.setdiff1d(np.concatenate([*prev, np.empty(0, np.int64)]), ids)
    gone = gone[isin_sorted(gone, known_ids)]
    exists = np.array([rec.exists_point3D(p) for p in gone.tolist()], bool)
    deleted = gone[~exists]
    xyz, rgb = read_points(rec, ids, ~is_known)
    read = PointsRead(ids, xyz, rgb, observers, True, deleted)
    if len(known_ids) - len(deleted) + int((~is_known).sum()) != rec.num_points3D():
        read = _reconcile(rec, read, known_ids, is_known)
    return read


def _reconcile(rec: pycolmap.Reconstruction, read: PointsRead, known_ids: np.ndarray, is_known: np.ndarray
               ) -> PointsRead:
    """``read`` completed by every point id of the map: the view's points the map lacks are deleted, the
    map's points neither known nor read are read (observer lists are then incomplete)."""
    all_ids = np.sort(np.fromiter(rec.points3D.keys(), np.int64, rec.num_points3D()))
    deleted = known_ids[~isin_sorted(known_ids, all_ids)]
    ids, xyz, rgb = read.ids, read.xyz, read.rgb
    extra = all_ids[~isin_sorted(all_ids, known_ids) & ~isin_sorted(all_ids, ids[~is_known])]
    if len(extra):
        e_xyz, e_rgb = read_points(rec, extra, np.ones(len(extra), bool))
        ids = np.concatenate([ids, extra])
        xyz = np.concatenate([xyz, e_xyz])
        rgb = np.concatenate([rgb, e_rgb])
        order = np.argsort(ids)
        ids, xyz, rgb = ids[order], xyz[order], rgb[order]
    return PointsRead(ids, xyz, rgb, read.observers, False, deleted)


__all__ = ["MapState", "state_from_slam", "state_from_run", "read_camera", "read_poses", "observed_ids",
           "read_observers", "read_points", "read_all_points", "read_every_point", "read_dirty_points"]
