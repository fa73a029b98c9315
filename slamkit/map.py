"""The map: pycolmap's Reconstruction and CorrespondenceGraph, grown keyframe by keyframe in memory.

Wiring (no database file): ``Reconstruction`` holds cameras, keyframe images with poses and 3D points;
``CorrespondenceGraph`` holds verified 2D-2D matches between keyframes; ``ObservationManager`` keeps the
two consistent; ``IncrementalTriangulator`` creates, continues, merges and completes tracks from them
(COLMAP's incremental mapper does the same with a ``DatabaseCache``). Keyframe bookkeeping that pycolmap
does not keep (descriptors, keypoint colours, source frame index) lives in :class:`Keyframe`.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import pycolmap

from .camera import Intrinsics
from .features import Features
from .map_graph import graph_pairs  # noqa: F401  (re-exported: merging, session and compact use it)
from .point_ids import PointIdCache, PointPositionCache, track_of

CAMERA_ID = 1

BA_LOSSES = {"trivial": "TRIVIAL", "soft_l1": "SOFT_L1", "cauchy": "CAUCHY", "huber": "HUBER"}
"""Robust losses of bundle adjustment by config name -> ``pycolmap.LossFunctionType`` member."""


@dataclass(eq=False)
class Keyframe:
    """A keyframe's data beside its pycolmap Image.

    keypoints: (N, 2) float64 undistorted pixels (the Image's points2D); features: as extracted (distorted
    pixels, descriptors); colors: (N, 3) uint8 RGB at the keypoints; thumbnail: small RGB image for viewers.
    """

    image_id: int
    frame_index: int
    timestamp: float
    keypoints: np.ndarray
    features: Features
    colors: np.ndarray
    thumbnail: np.ndarray | None = None


def rigid_from_matrix(m: np.ndarray) -> pycolmap.Rigid3d:
    """(3, 4) or (4, 4) [R|t] -> pycolmap.Rigid3d."""
    m = np.asarray(m, dtype=np.float64)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(m[:3, :3]), m[:3, 3].copy())


def matrix_from_rigid(r: pycolmap.Rigid3d) -> np.ndarray:
    """pycolmap.Rigid3d -> (4, 4) float64."""
    out = np.eye(4)
    out[:3] = r.matrix()
    return out


def bundle_adjustment_options(iterations: int, loss: str = "soft_l1", refine_intrinsics: bool = False,
                              function_tolerance: float = 1e-6, num_threads: int = 1,
                              refine_principal_point: bool = False,
                              refine_extra_params: bool = False) -> pycolmap.BundleAdjustmentOptions:
    """pycolmap BA options: robust loss (scale 1 px), intrinsics fixed unless asked, quiet. Shared by the
    bundle adjuster and the initializer's two-view BA."""
    o = pycolmap.BundleAdjustmentOptions()
    o.print_summary = False
    o.refine_focal_length = refine_intrinsics
    o.refine_principal_point = refine_principal_point
    o.refine_extra_params = refine_extra_params
    o.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, BA_LOSSES[loss])
    o.ceres.loss_function_scale = 1.0
    o.ceres.solver_options.max_num_iterations = iterations
    o.ceres.solver_options.function_tolerance = function_tolerance
    o.ceres.solver_options.num_threads = num_threads
    return o


def keypoint_scales(features) -> np.ndarray:
    """(N,) scale of each keypoint: its size over the smallest size in the image (ORB: 1.2^octave, so a
    level's noise in pixels); ones without sizes."""
    sizes = getattr(features, "sizes", None)
    if sizes is None or len(sizes) == 0:
        return np.ones(len(features))
    s = np.asarray(sizes, np.float64)
    return s / max(float(s[s > 0].min()) if (s > 0).any() else 1.0, 1e-9)


def pycolmap_camera(camera: Intrinsics) -> pycolmap.Camera:
    """PINHOLE camera of the undistorted keypoints."""
    return pycolmap.Camera(model="PINHOLE", width=camera.width, height=camera.height,
                           params=[camera.fx, camera.fy, camera.cx, camera.cy], camera_id=CAMERA_ID)


MIN_RADIAL_SHIFT_PX = 0.1
"""A radial coefficient estimated by self-calibration is kept when it moves the farthest pixel from the
principal point by at least this much (pixels)."""


def undistort_radial(camera: pycolmap.Camera, xy: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of a distorted pycolmap ``camera`` -> (N, 2) pixels of its pinhole part (same focal
    length and principal point, no distortion), with COLMAP's own inverse of the distortion."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if len(xy) == 0:
        return xy.copy()
    rays = np.asarray(camera.cam_from_img(xy), np.float64).reshape(len(xy), -1)[:, :2]
    f, cx, cy = camera.focal_length_x, camera.principal_point_x, camera.principal_point_y
    return np.column_stack([f * rays[:, 0] + cx, camera.focal_length_y * rays[:, 1] + cy])


class SlamMap:
    """One map segment: a pycolmap Reconstruction grown in memory, plus keyframe data.

    Image ids are assigned in insertion order starting at 1; ``keyframes`` holds every registered keyframe.
    """

    def __init__(self, camera: Intrinsics, triangulation: pycolmap.IncrementalTriangulatorOptions | None = None):
        self.camera = camera.pinhole
        self.reconstruction = pycolmap.Reconstruction()
        self.reconstruction.add_camera_with_trivial_rig(pycolmap_camera(self.camera))
        self.graph = pycolmap.CorrespondenceGraph()
        self.observations = pycolmap.ObservationManager(self.reconstruction, self.graph)
        self.triangulator = pycolmap.IncrementalTriangulator(self.graph, self.reconstruction, self.observations)
        if triangulation is None:
            triangulation = pycolmap.IncrementalTriangulatorOptions()
            triangulation.ignore_two_view_tracks = False  # default True triangulates nothing when streaming
        self.triangulation = triangulation
        self.keyframes: dict[int, Keyframe] = {}
        self._pending: dict[int, Keyframe] = {}
        self._observed: set[int] = set()
        self._next_image_id = 1
        self._point3D_ids = PointIdCache()
        self._xyz = PointPositionCache()
        self._covisible: dict[int, list[tuple[int, int]]] = {}

    def moved(self, point3D_ids=None) -> None:
        """Forget the cached positions of ``point3D_ids`` (None: of every point): call after anything outside
        :meth:`set_positions` that moves points (bundle adjustment, a loop correction, normalization)."""
        self._xyz.forget(point3D_ids)

    def bundle_adjust(self, options: pycolmap.BundleAdjustmentOptions, config: pycolmap.BundleAdjustmentConfig):
        """pycolmap's (Ceres') bundle adjustment of ``config`` on this map; returns its summary. The points it
        may have moved are forgotten by the cached positions (every BA of the map goes through here)."""
        summary = pycolmap.create_default_bundle_adjuster(options, config, self.reconstruction).solve()
        self.moved()
        return summary

    def set_positions(self, point3D_ids, xyz: np.ndarray) -> None:
        """Move points ``point3D_ids`` to ``xyz`` ((M, 3)) in the reconstruction, and in the cached positions."""
        point3D = self.reconstruction.point3D
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        for p, X in zip(np.asarray(point3D_ids, np.int64).tolist(), xyz):
            point3D(p).xyz = X
        self._xyz.set(self.reconstruction, point3D_ids, xyz)

    def changed(self, image_ids=None) -> None:
        """Forget the cached per-keyframe point ids and covisibility: call after anything that adds,
        merges or removes observations (registration, triangulation, track maintenance, filtering).
        image_ids: only these images' observations changed (their point ids are forgotten, and every
        covisibility); None: any may have."""
        self._point3D_ids.forget(image_ids)
        self._covisible.clear()

    def _observed_as(self, image_ids, point2D_idxs, point3D_ids) -> None:
        """Keypoints that now observe other points (-1: none) through a change made here: written into the
        cached point ids (:class:`~slamkit.point_ids.PointIdCache`) instead of forgotten."""
        self._point3D_ids.write(image_ids, point2D_idxs, point3D_ids)
        self._covisible.clear()

    # ----------------------------------------------------------------- keyframes
    @property
    def pycolmap_camera(self) -> pycolmap.Camera:
        return self.reconstruction.camera(CAMERA_ID)

    def set_focal(self, focal: float | None = None) -> float:
        """Set fx = fy = ``focal`` in the map's camera (default: the mean of the fx and fy bundle adjustment
        refined: one focal length for both axes); returns it. :attr:`camera` follows."""
        cam = self.reconstruction.camera(CAMERA_ID)
        fx, fy, cx, cy = (float(v) for v in cam.params)
        f = 0.5 * (fx + fy) if focal is None else float(focal)
        cam.params = [f, f, cx, cy]
        self.camera = Intrinsics(self.camera.width, self.camera.height, f, f, cx, cy)
        return f

    def use_radial_camera(self) -> None:
        """The map's camera becomes COLMAP's SIMPLE_RADIAL (``f, cx, cy, k1``) with ``k1 = 0``: the same
        projections, and a bundle adjustment with ``refine_extra_params`` can then estimate one radial
        distortion coefficient of the keypoints (self-calibration's final BA). :meth:`undistort_observations`
        makes it PINHOLE again."""
        cam = self.reconstruction.camera(CAMERA_ID)
        fx, fy, cx, cy = (float(v) for v in cam.params)
        self.reconstruction.cameras[CAMERA_ID] = pycolmap.Camera(
            model="SIMPLE_RADIAL", width=cam.width, height=cam.height, params=[0.5 * (fx + fy), cx, cy, 0.0],
            camera_id=CAMERA_ID)

    def drop_radial(self) -> None:
        """The camera becomes PINHOLE ``(f, f, cx, cy)`` again, its radial coefficient dropped (observations
        left as they are): after a bundle adjustment whose ``k1`` is not believed."""
        cam = self.reconstruction.camera(CAMERA_ID)
        f, cx, cy = (float(v) for v in cam.params[:3])
        self.reconstruction.cameras[CAMERA_ID] = pycolmap.Camera(
            model="PINHOLE", width=cam.width, height=cam.height, params=[f, f, cx, cy], camera_id=CAMERA_ID)

    def undistort_observations(self) -> float:
        """After :meth:`use_radial_camera` and a bundle adjustment: every keyframe's 2D points are undistorted
        with the estimated ``k1`` (COLMAP's own inverse, ``Camera.cam_from_img``) and the camera is PINHOLE
        ``(f, f, cx, cy)`` again, so each point projects where it did and the map keeps ideal-pinhole keypoints
        like every other map. Returns ``k1``: 0 when the camera was not SIMPLE_RADIAL, or when ``k1`` moves no
        pixel by :data:`MIN_RADIAL_SHIFT_PX` (a pinhole camera's BA finds a k1 of about 1e-5: the points are
        then left as they are, and the camera stays an exact pinhole for export)."""
        cam = self.reconstruction.camera(CAMERA_ID)
        if cam.model.name != "SIMPLE_RADIAL":
            return 0.0
        f, cx, cy, k1 = (float(v) for v in cam.params)
        r = math.hypot(max(cx, cam.width - cx), max(cy, cam.height - cy)) / f  # the farthest pixel, normalized
        if abs(k1) * r ** 3 * f < MIN_RADIAL_SHIFT_PX:
            k1 = 0.0
        for image in self.reconstruction.images.values() if k1 else ():
            points = image.points2D
            if len(points):
                xy = undistort_radial(cam, np.array([p.xy for p in points]))
                for point, q in zip(points, xy):
                    point.xy = q
        self.reconstruction.cameras[CAMERA_ID] = pycolmap.Camera(
            model="PINHOLE", width=cam.width, height=cam.height, params=[f, f, cx, cy], camera_id=CAMERA_ID)
        self.camera = Intrinsics(self.camera.width, self.camera.height, f, f, cx, cy)
        return k1

    def add_image(self, frame_index: int, timestamp: float, keypoints: np.ndarray, features: Features,
                  colors: np.ndarray, thumbnail: np.ndarray | None = None) -> int:
        """Add a keyframe candidate (image + correspondence-graph node); returns its image id.

        Add its two-view matches next (:meth:`add_matches`), then :meth:`register` it with a pose.
        """
        iid = self._next_image_id
        self._next_image_id += 1
        image = pycolmap.Image(name=f"frame_{frame_index:06d}", keypoints=np.ascontiguousarray(keypoints, np.float64),
                               camera_id=CAMERA_ID, image_id=iid)
        self.reconstruction.add_image_with_trivial_frame(image)
        self.graph.add_image(iid, len(keypoints))
        self._pending[iid] = Keyframe(iid, frame_index, timestamp, np.asarray(keypoints, np.float64), features,
                                      colors, thumbnail)
        return iid

    def add_matches(self, image_id1: int, image_id2: int, matches: np.ndarray) -> None:
        """Add verified keypoint matches (M, 2) (index in image 1, index in image 2) to the graph."""
        if len(matches) == 0:
            return
        tvg = pycolmap.TwoViewGeometry()
        tvg.config = int(pycolmap.TwoViewGeometryConfiguration.CALIBRATED)
        tvg.inlier_matches = np.ascontiguousarray(matches, dtype=np.uint32)
        self.graph.add_two_view_geometry(image_id1, image_id2, tvg)

    def observe(self, *image_ids: int) -> None:
        """Hand pending images, with all their matches added, to the ObservationManager.

        Must happen before any of them (or a matched image) is registered: registering an image updates
        the statistics of the images it has correspondences with.
        """
        for iid in image_ids:
            self.observations.add_image(iid)
            self._observed.add(iid)

    def register(self, image_id: int, cam_from_world: pycolmap.Rigid3d) -> None:
        """Give a pending image its pose and register it (it becomes a keyframe)."""
        if image_id not in self._observed:
            self.observe(image_id)
        self.reconstruction.frame(image_id).rig_from_world = copy.copy(cam_from_world)
        self.observations.register_frame(image_id)
        self.keyframes[image_id] = self._pending.pop(image_id)
        self.changed([image_id])  # no observation changes; the covisibility now lists it

    def deregister(self, image_id: int) -> None:
        """Remove a keyframe's observations and registration (seed §3.5: too few map points)."""
        self.observations.deregister_frame(image_id)
        self.keyframes.pop(image_id, None)
        self.changed()

    def cull(self, image_id: int) -> None:
        """Remove a redundant keyframe from the map (keyframe culling): its observations are deleted
        (points left with fewer than two observations too) and it is no longer registered.

        Not :meth:`deregister`: ``ObservationManager.deregister_frame`` also un-counts the keyframe's
        correspondences as "visible" in every matched image, and the images observed after this one was
        registered never counted them (``add_image`` catches up only on triangulated correspondences), so
        it fails with "Visible correspondences underflow". Those counts only rank next-best views, which
        slamkit does not use; the triangulation counts that matter are kept exact here."""
        image = self.reconstruction.image(image_id)
        for j in list(image.get_observation_point2D_idxs()):
            if image.point2D(j).has_point3D():  # deleting a two-view point may have taken another one
                self.observations.delete_observation(image_id, j)
        self.reconstruction.deregister_frame(image_id)
        self.keyframes.pop(image_id, None)
        self.changed()

    def add_observations(self, image_id: int, point2D_idxs: np.ndarray, point3D_ids: np.ndarray) -> int:
        """Add tracked 2D-3D observations to existing tracks; returns how many were added."""
        image = self.reconstruction.image(image_id)
        added_j, added_p = [], []
        for j, p in zip(np.asarray(point2D_idxs).tolist(), np.asarray(point3D_ids).tolist()):
            if not self.reconstruction.exists_point3D(p) or image.point2D(j).has_point3D():
                continue
            if image.has_point3D(p):  # one observation per image and track
                continue
            self.observations.add_observation(p, pycolmap.TrackElement(image_id, j))
            added_j.append(j)
            added_p.append(p)
        self._observed_as([image_id] * len(added_j), added_j, added_p)
        return len(added_j)

    def add_point(self, xyz: np.ndarray, observations, color: np.ndarray) -> int:
        """Create a 3D point at ``xyz`` (3,) observed by ``observations`` ((image id, keypoint index), ...) of
        registered keyframes, coloured ``color`` (3,) uint8; returns its id. Track maintenance after the next
        bundle adjustment (completion and merging through the correspondence graph) includes it."""
        track = pycolmap.Track()
        for image_id, j in observations:
            track.add_element(int(image_id), int(j))
        pid = int(self.observations.add_point3D(np.asarray(xyz, np.float64), track, np.asarray(color, np.uint8)))
        self.triangulator.add_modified_point3D(pid)
        self._observed_as([i for i, _ in observations], [j for _, j in observations], pid)
        return pid

    def delete_point(self, point3D_id: int) -> None:
        """Remove a 3D point and its observations."""
        images, idxs = track_of(self.reconstruction, point3D_id)
        self.observations.delete_point3D(int(point3D_id))
        self._observed_as(images, idxs, -1)

    def delete_observation(self, image_id: int, point2D_idx: int) -> int:
        """Remove one observation (``ObservationManager.delete_observation``: a point left with fewer than two
        observations is deleted with them); returns its point id, -1 (nothing done) when the keypoint has none."""
        rec = self.reconstruction
        point2D = rec.image(image_id).point2D(point2D_idx)
        if not point2D.has_point3D():
            return -1
        pid = int(point2D.point3D_id)
        images, idxs = track_of(rec, pid)
        self.observations.delete_observation(image_id, point2D_idx)
        if rec.exists_point3D(pid):  # else the point went with it, and all its observations
            images, idxs = [image_id], [point2D_idx]
        self._observed_as(images, idxs, -1)
        return pid

    def merge_points(self, point3D_id1: int, point3D_id2: int) -> int:
        """Fuse two 3D points that are the same scene point into one (``ObservationManager.merge_points3D``:
        tracks joined, position averaged by track length); returns its id, or -1 (nothing changed) when either
        no longer exists or a keyframe observes both (one track may hold one observation per image)."""
        rec = self.reconstruction
        if point3D_id1 == point3D_id2 or not (rec.exists_point3D(point3D_id1) and rec.exists_point3D(point3D_id2)):
            return -1
        track1, track2 = rec.point3D(point3D_id1).track.elements, rec.point3D(point3D_id2).track.elements
        images1 = {el.image_id for el in track1}
        if any(el.image_id in images1 for el in track2):
            return -1
        images, idxs = ([el.image_id for el in track1 + track2], [el.point2D_idx for el in track1 + track2])
        pid = int(self.observations.merge_points3D(int(point3D_id1), int(point3D_id2)))
        self.triangulator.add_modified_point3D(pid)
        self._observed_as(images, idxs, pid)  # every observation of either now observes the merged point
        return pid

    def triangulate(self, image_id: int) -> int:
        """Continue and create tracks through the new keyframe (COLMAP ``triangulate_image``)."""
        n = self.triangulator.triangulate_image(self.triangulation, image_id)
        self.changed()
        self.color_new_points(image_id)
        return n

    def color_new_points(self, image_id: int) -> None:
        kf = self.keyframes.get(image_id)
        if kf is None:
            return
        image = self.reconstruction.image(image_id)
        for j in image.get_observation_point2D_idxs():
            p = self.reconstruction.point3D(image.point2D(j).point3D_id)
            if not p.color.any():
                p.color = kf.colors[j]

    # ----------------------------------------------------------------- queries
    def cam_from_world(self, image_id: int) -> pycolmap.Rigid3d:
        """A copy of a keyframe's pose (pycolmap returns live references)."""
        return copy.copy(self.reconstruction.frame(image_id).rig_from_world)

    def point3D_ids(self, image_id: int) -> np.ndarray:
        """(N,) int64 3D point id of each keypoint of the keyframe, -1 where none (read-only, cached
        until :meth:`changed`)."""
        return self._point3D_ids.get(self.reconstruction, image_id)

    def points_xyz(self, point3D_ids) -> np.ndarray:
        """(M, 3) positions of the given (existing) points, a new array (cached until :meth:`moved`)."""
        ids = point3D_ids if isinstance(point3D_ids, np.ndarray) else np.fromiter(point3D_ids, np.int64)  # a set too
        return self._xyz.get(self.reconstruction, ids)

    def num_points_observed(self, image_id: int, min_observers: int = 1) -> int:
        """Map points of the keyframe that at least ``min_observers`` keyframes observe (ORB-SLAM's
        ``TrackedMapPoints(nMinObs)``); 1: all of its points."""
        if min_observers <= 1:
            return int(self.reconstruction.image(image_id).num_points3D)
        pids = self.point3D_ids(image_id)
        point3D = self.reconstruction.point3D
        return sum(point3D(p).track.length() >= min_observers for p in pids[pids >= 0].tolist())

    def covisible_with(self, point3D_ids: np.ndarray, limit: int | None = None) -> list[tuple[int, int]]:
        """Keyframes observing the given points: [(image id, points among them it observes)], most first, ties
        by image id (the covisibility of a frame that is not a keyframe yet, from its tracked points)."""
        point3D, exists = self.reconstruction.point3D, self.reconstruction.exists_point3D
        ids = [el.image_id for p in np.unique(np.asarray(point3D_ids, np.int64)).tolist() if p >= 0 and exists(p)
               for el in point3D(p).track.elements]
        counts = np.bincount(np.asarray(ids, np.int64)) if ids else np.zeros(1, np.int64)
        ranked = [(int(i), int(counts[i])) for i in np.lexsort((np.arange(len(counts)), -counts))
                  if counts[i] > 0 and int(i) in self.keyframes]
        return ranked[:limit] if limit is not None else ranked

    def covisible(self, image_id: int, limit: int | None = None) -> list[tuple[int, int]]:
        """Keyframes sharing 3D points with ``image_id``: [(image id, shared points)], most shared first
        (cached until :meth:`changed`)."""
        ranked = self._covisible.get(image_id)
        if ranked is None:
            point3D = self.reconstruction.point3D
            ids = [el.image_id for p in self.point3D_ids(image_id)[self.point3D_ids(image_id) >= 0].tolist()
                   for el in point3D(p).track.elements]
            counts = np.bincount(np.asarray(ids, np.int64)) if ids else np.zeros(1, np.int64)
            counts[image_id:image_id + 1] = 0
            ranked = [(int(i), int(counts[i])) for i in np.lexsort((np.arange(len(counts)), -counts))
                      if counts[i] > 0 and int(i) in self.keyframes]
            self._covisible[image_id] = ranked
        return ranked[:limit] if limit is not None else list(ranked)

    @property
    def next_image_id(self) -> int:
        """The id :meth:`add_image` gives next (ids of rejected and culled keyframes are not reused)."""
        return self._next_image_id

    @next_image_id.setter
    def next_image_id(self, value: int) -> None:  # a session restores it
        self._next_image_id = int(value)

    @property
    def pending_image_ids(self) -> list[int]:
        """Images added but not registered yet (between :meth:`add_image` and :meth:`register`), ascending."""
        return sorted(self._pending)

    @property
    def num_keyframes(self) -> int:
        return len(self.keyframes)

    @property
    def num_points(self) -> int:
        return self.reconstruction.num_points3D()

    def mean_reprojection_error(self) -> float:
        self.reconstruction.update_point_3d_errors()
        return float(self.reconstruction.compute_mean_reprojection_error())

    def points_per_image(self) -> float:
        return float(self.reconstruction.compute_mean_observations_per_reg_image())

    def point_cloud(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids (M,), xyz (M, 3), rgb (M, 3) uint8) of every 3D point."""
        pts = self.reconstruction.points3D
        ids = np.fromiter(pts.keys(), dtype=np.int64, count=len(pts))
        xyz = np.array([pts[int(i)].xyz for i in ids]).reshape(-1, 3)
        rgb = np.array([pts[int(i)].color for i in ids], dtype=np.uint8).reshape(-1, 3)
        return ids, xyz, rgb

    def num_dropped_images(self) -> int:
        """Images of the reconstruction that are neither keyframes nor pending: culled or rejected ones."""
        return self.reconstruction.num_images() - len(self.keyframes) - len(self._pending)

    def compact_when(self, every: int) -> None:
        """:meth:`compact` once ``every`` (> 0) images or more are no longer keyframes, and at least as many as
        there are keyframes (amortized O(1) per keyframe; ``mapper.compact_dropped``)."""
        if every > 0 and self.num_dropped_images() >= max(every, self.num_keyframes):
            self.compact()

    def compact(self) -> int:
        """Rebuild the Reconstruction, CorrespondenceGraph and ObservationManager without the images that are
        no longer keyframes (culled or rejected), so memory follows the map, not the frames; returns how
        many images were dropped (0 while a keyframe candidate is pending). Image and point ids, poses,
        tracks, the keyframes' correspondences (in the same order) and the triangulator's modified points
        are kept; the ObservationManager's statistics are recounted (as after a session is loaded)."""
        old, dropped = self.reconstruction, self.num_dropped_images()
        if dropped <= 0 or self._pending:  # pending images are between add_image and register: not now
            return 0
        pairs, matches = graph_pairs(self)
        modified = sorted(self.triangulator.get_modified_points3D())
        max_id = max_point3D_id(old)
        self.reconstruction = pycolmap.Reconstruction()
        self.reconstruction.add_camera_with_trivial_rig(old.camera(CAMERA_ID))
        self.graph = pycolmap.CorrespondenceGraph()
        self.refill(old, sorted(self.keyframes), pairs, matches, list(old.reg_frame_ids()), max_id, modified)
        return dropped

    def refill(self, source: pycolmap.Reconstruction, image_ids, pairs, matches, registration_order,
               max_point3D_id: int, modified_points3D) -> None:
        """Fill this map's empty Reconstruction and graph from ``source``: the images ``image_ids`` (ascending)
        with their keypoints, the graph ``pairs`` (older, newer) with their ``matches`` replayed in order
        (pairs with another image are skipped), the frames of ``registration_order`` registered with their
        poses, every 3D point with its id; new points get ids above ``max_point3D_id``. Then the
        ObservationManager and triangulator are rewired, with ``modified_points3D`` still to be maintained.
        Used by :meth:`compact` and when a session is loaded."""
        rec, wanted = self.reconstruction, set(image_ids)
        by_newer: dict[int, list[int]] = {}
        for k, (a, b) in enumerate(pairs):
            if a in wanted and b in wanted:
                by_newer.setdefault(int(b), []).append(k)
        for iid in image_ids:
            image = source.image(iid)
            xy = np.array([p.xy for p in image.points2D], np.float64).reshape(-1, 2)
            rec.add_image_with_trivial_frame(pycolmap.Image(name=image.name, keypoints=xy, camera_id=CAMERA_ID,
                                                            image_id=iid))
            self.graph.add_image(iid, len(xy))
            for k in by_newer.get(iid, []):
                self.add_matches(int(pairs[k][0]), int(pairs[k][1]), matches[k])
        for fid in registration_order:
            rec.frame(fid).rig_from_world = copy.copy(source.frame(fid).rig_from_world)
            rec.register_frame(fid)
        for pid in sorted(source.point3D_ids()):
            rec.add_point3D_with_id(pid, source.point3D(pid))
        if max_point3D_id > 0 and not rec.exists_point3D(max_point3D_id):  # ids after every id ever given
            rec.add_point3D_with_id(max_point3D_id, pycolmap.Point3D())
            rec.delete_point3D(max_point3D_id)
        self.rewire()
        for pid in modified_points3D:  # tracks bundle adjustment will complete and merge next
            if rec.exists_point3D(pid):
                self.triangulator.add_modified_point3D(pid)
        self.changed()

    # ----------------------------------------------------------------- sessions
    def rewire(self) -> None:
        """Recreate the ObservationManager and IncrementalTriangulator around the current reconstruction and
        graph, after both were filled from outside (``slamkit.session`` rebuilding a saved map): the
        ObservationManager initializes its statistics from them; the triangulator starts with empty caches."""
        self.observations = pycolmap.ObservationManager(self.reconstruction, self.graph)
        self.triangulator = pycolmap.IncrementalTriangulator(self.graph, self.reconstruction, self.observations)
        self._observed = set(int(i) for i in self.reconstruction.images)
        self.changed()


def shared_observations(slam_map: SlamMap, image_id: int, point2D_idxs: np.ndarray, point3D_ids: np.ndarray
                        ) -> np.ndarray:
    """Correspondences of a frame with keyframe ``image_id`` through the map points both observe: (M, 2) int64
    (keypoint in the keyframe, keypoint in the frame) for the frame's tracked observations ``point2D_idxs``,
    ``point3D_ids`` (K,) whose point the keyframe observes too, one per point."""
    n_pids = slam_map.point3D_ids(image_id)
    has = np.flatnonzero(n_pids >= 0)
    if len(has) == 0 or len(point3D_ids) == 0:
        return np.empty((0, 2), np.int64)
    o = np.argsort(n_pids[has])
    sorted_pids, sorted_kp = n_pids[has][o], has[o]
    point3D_ids = np.asarray(point3D_ids, np.int64)
    _, first = np.unique(point3D_ids, return_index=True)
    first = np.sort(first)
    pids, kps = point3D_ids[first], np.asarray(point2D_idxs, np.int64)[first]
    pos = np.minimum(np.searchsorted(sorted_pids, pids), len(sorted_pids) - 1)
    seen = sorted_pids[pos] == pids
    return np.stack([sorted_kp[pos[seen]], kps[seen]], axis=1).astype(np.int64)


def max_point3D_id(rec: pycolmap.Reconstruction) -> int:
    """The largest 3D point id the reconstruction ever gave (deleted points included), without changing it:
    a copy is asked for its next id."""
    probe = copy.copy(rec)
    return int(probe.add_point3D(np.zeros(3), pycolmap.Track(), np.zeros(3, np.uint8))) - 1
