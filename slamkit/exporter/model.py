"""The exported COLMAP model: the run's keyframes and points, plus the other posed frames when asked.

Keyframes keep their keypoints, poses and 2D-3D observations from the run's model (pixels mapped to the
exported camera, :class:`~slamkit.exporter.camera.ExportCamera`). A non-keyframe is registered with its pose
from ``trajectory_tum.txt``; its 2D-3D observations are recovered the cheap way slamkit's tracker finds
them: features are extracted again (the run's extractor), the map points are projected with the frame's
pose and matched by ORB-SLAM's search by projection (:func:`slamkit.features.base.guided_match`, the
tracker's ``refine_radius_px`` and matching thresholds, each point with the descriptor of the keyframe
nearest in time), and matches farther than ``tracker.max_error_px`` from the projection are dropped. They
are not the run's tracked matches (those are not saved) and they are not bundle-adjusted.
"""

from __future__ import annotations

import re

import numpy as np
import pycolmap

from ..config import SlamConfig
from ..errors import ConfigError
from ..features import Features
from ..features.base import guided_match
from .camera import CAMERA_ID, ExportCamera
from .runfolder import PosedFrame

_EVERY = re.compile(r"every=(\d+)$")


def select_frames(frames: list[PosedFrame], which: str) -> list[PosedFrame]:
    """``"keyframes"``, ``"all"`` (every posed frame) or ``"every=N"`` (every N-th posed frame plus the
    keyframes), in trajectory order; ConfigError naming ``frames`` for anything else."""
    if which == "keyframes":
        return [f for f in frames if f.is_keyframe]
    if which == "all":
        return list(frames)
    m = _EVERY.match(str(which))
    if m is None or int(m.group(1)) < 1:
        raise ConfigError(f"frames must be 'keyframes', 'all' or 'every=N' with N >= 1 (got {which!r})")
    n = int(m.group(1))
    return [f for k, f in enumerate(frames) if f.is_keyframe or k % n == 0]


def keyframe_descriptors(model: pycolmap.Reconstruction, image_id: int, features: Features,
                         keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(point ids (K,), descriptors (K, D)) of the map points a keyframe observes, from its features
    extracted again; None when they are not the run's keypoints (``keypoints``: (N, 2) undistorted pixels,
    compared with the model's points2D to 1e-3 px)."""
    image = model.image(image_id)
    xy = np.array([p.xy for p in image.points2D], np.float64).reshape(-1, 2)
    if len(xy) != len(keypoints) or (len(xy) and np.abs(xy - keypoints).max() > 1e-3):
        return None
    idx = np.asarray(image.get_observation_point2D_idxs(), np.int64)
    pids = np.array([image.point2D(int(j)).point3D_id for j in idx], np.int64)
    return pids, features.descriptors[idx]


class PointDescriptors:
    """Descriptors of the map points per keyframe, and the points' positions, for guided matching.

    num_keyframes: how many keyframes nearest in time supply points (the tracker's local map holds a
    keyframe and its 10 most covisible ones), which bounds the work per frame on long runs.
    """

    def __init__(self, model: pycolmap.Reconstruction, num_keyframes: int = 10):
        self.keyframes: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}  # image id -> (index, pids, desc)
        self.binary = True
        self.num_keyframes = num_keyframes
        self._ids = np.array(sorted(model.point3D_ids()), np.int64)
        self._xyz = np.array([model.point3D(int(p)).xyz for p in self._ids], np.float64).reshape(-1, 3)

    def add(self, index: int, image_id: int, pids: np.ndarray, desc: np.ndarray, binary: bool) -> None:
        self.keyframes[image_id] = (index, pids, desc)
        self.binary = binary

    def nearest(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(point ids (M,), positions (M, 3), descriptors (M, D)): the points of the keyframes nearest to
        frame ``index``, each with the descriptor of the nearest keyframe observing it."""
        order = sorted(self.keyframes.values(), key=lambda k: abs(k[0] - index))[: self.num_keyframes]
        if not order:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 32), np.uint8)
        pids = np.concatenate([k[1] for k in order])
        desc = np.concatenate([k[2] for k in order])
        pids, first = np.unique(pids, return_index=True)
        return pids, self._xyz[np.searchsorted(self._ids, pids)], desc[first]


def match_frame(points: PointDescriptors, frame: PosedFrame, features: Features, keypoints: np.ndarray,
                K: np.ndarray, size: tuple[int, int], config: SlamConfig) -> tuple[np.ndarray, np.ndarray]:
    """2D-3D observations of a non-keyframe: ((K, 2) undistorted pixels of the run's camera, (K,) point
    ids), one per point and keypoint (see the module docstring)."""
    pids, xyz, desc = points.nearest(frame.index)
    cam_from_world = np.linalg.inv(frame.world_from_cam)
    Xc = xyz @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    front = Xc[:, 2] > 1e-9
    uv = Xc[:, :2] / np.where(front, Xc[:, 2], 1.0)[:, None] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < size[0]) & (uv[:, 1] >= 0) & (uv[:, 1] < size[1])
    idx = np.flatnonzero(inside)
    c = config.tracker
    pairs = guided_match(uv[idx], desc[idx], keypoints, features.descriptors, points.binary,
                         c.refine_radius_px, c.matching)
    if len(pairs) == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int64)
    xy = keypoints[pairs[:, 1]]
    err = np.linalg.norm(xy - uv[idx[pairs[:, 0]]], axis=1)
    ok = err <= c.max_error_px
    return xy[ok], pids[idx[pairs[ok, 0]]]


def build_model(run_model: pycolmap.Reconstruction, frames: list[PosedFrame], camera: ExportCamera,
                names: dict[int, str], extra: dict[int, tuple[np.ndarray, np.ndarray]]) -> pycolmap.Reconstruction:
    """A new Reconstruction with ``camera`` and one registered image per frame (named ``names[index]``,
    ids 1.. in order), the run's 3D points (ids, positions, colours kept) with their keyframe
    observations and the non-keyframe observations ``extra[index] = (undistorted pixels, point ids)``."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(camera.camera)
    new_id: dict[int, int] = {}  # run image id -> exported image id
    tracks: dict[int, list[tuple[int, int]]] = {}  # point id -> [(exported image id, point2D idx)]
    for iid, f in enumerate(frames, start=1):
        if f.is_keyframe:
            image = run_model.image(f.image_id)
            xy = np.array([p.xy for p in image.points2D], np.float64).reshape(-1, 2)
            obs = []  # the run's tracks carry them
            new_id[f.image_id] = iid
        else:
            xy, pids = extra.get(f.index, (np.zeros((0, 2)), np.zeros(0, np.int64)))
            obs = list(enumerate(np.asarray(pids, np.int64).tolist()))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=names[f.index], camera_id=CAMERA_ID, image_id=iid,
                                                        keypoints=np.ascontiguousarray(camera.from_model(xy))))
        cam_from_world = np.linalg.inv(f.world_from_cam)
        if f.is_keyframe:  # the model's own pose, bit for bit
            pose = run_model.image(f.image_id).cam_from_world()
        else:
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_world[:3, :3]), cam_from_world[:3, 3].copy())
        rec.frame(iid).rig_from_world = pose
        rec.register_frame(iid)
        for j, pid in obs:
            tracks.setdefault(pid, []).append((iid, j))
    for pid in sorted(run_model.point3D_ids()):
        p = run_model.point3D(pid)
        track = pycolmap.Track()
        for el in p.track.elements:
            if el.image_id in new_id:
                track.add_element(new_id[el.image_id], el.point2D_idx)
        for iid, j in tracks.get(int(pid), []):
            track.add_element(iid, j)
        if track.length() == 0:
            continue
        point = pycolmap.Point3D(xyz=p.xyz, color=p.color, error=p.error, track=track)
        rec.add_point3D_with_id(int(pid), point)
    rec.update_point_3d_errors()  # in the exported camera's pixels
    return rec
