"""Local bundle adjustment's problem read from the map as arrays, and its solution written back
(``ba.engine = "compiled"``: :func:`slamkit.kernels.local_ba.local_bundle_adjustment` between the two).

The problem is COLMAP's local BA as :class:`~slamkit.stages.ba.BundleAdjuster` gives it to Ceres: the window's
keyframes variable, every observation in them; the window's points variable unless their track is longer than
``max_track_length`` (then held, and only their observations in the window enter); the observations of the
variable points in every other keyframe, whose poses are held (ORB-SLAM's fixed keyframes). When the window is
the whole map, COLMAP's TWO_CAMS_FROM_WORLD gauge: the lowest image id held, and of the next one the
translation coordinate along the largest component of their baseline in the first camera (``gauge``).

Reading is batched where the map keeps arrays: every keyframe's point ids (:meth:`SlamMap.point3D_ids`,
cached; the tracks of the window's points are read from them, not from pycolmap's ``Track`` objects, which
cost a few microseconds an element), the keypoints (``Keyframe.keypoints``, undistorted pixels) and their
scales (:func:`~slamkit.map.keypoint_scales`); each point's position is read once from pycolmap (it has no
batch read). Writing back sets the window's poses and the variable points' positions, one pycolmap call each.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from .map import CAMERA_ID, SlamMap, keypoint_scales


@dataclass(frozen=True, eq=False)
class LocalProblem:
    """A local BA problem in arrays.

    image_ids: (K,) keyframe ids, the window's first (variable unless ``pose_fixed``), then the held keyframes;
    cam_from_world: (K, 3, 4); pose_fixed: (K,) bool; point3D_ids: (P,) int64 sorted; points: (P, 3) world;
    point_fixed: (P,) bool (long tracks); obs_pose, obs_point: (N,) int64 indices; obs_point2D: (N,) int64 the
    keypoint's index in its keyframe; obs_xy: (N, 2) undistorted pixels; obs_scale: (N,) the keypoint's scale
    (sigma = 1.2^octave for ORB); camera: (4,) fx, fy, cx, cy; gauge: (pose index, axis) or None."""

    image_ids: np.ndarray
    cam_from_world: np.ndarray
    pose_fixed: np.ndarray
    point3D_ids: np.ndarray
    points: np.ndarray
    point_fixed: np.ndarray
    obs_pose: np.ndarray
    obs_point: np.ndarray
    obs_point2D: np.ndarray
    obs_xy: np.ndarray
    obs_scale: np.ndarray
    camera: np.ndarray
    gauge: tuple[int, int] | None


def compiled_camera(slam_map: SlamMap) -> np.ndarray | None:
    """(fx, fy, cx, cy) of the map's camera when it is PINHOLE (the compiled BA's model), else None."""
    cam = slam_map.reconstruction.camera(CAMERA_ID)
    if cam.model.name != "PINHOLE":
        return None
    return np.array(cam.params, np.float64)


def local_problem(slam_map: SlamMap, window: list[int], max_track_length: int) -> LocalProblem:
    """The local BA problem of ``window`` (keyframe ids, the new keyframe first); see the module docstring.
    ``max_track_length`` <= 0: every point variable. The map camera must be PINHOLE (:func:`compiled_camera`)."""
    rec = slam_map.reconstruction
    camera = compiled_camera(slam_map)
    if camera is None:
        raise ValueError("the compiled local BA needs the map's PINHOLE camera")
    window = [int(i) for i in window]
    in_window = set(window)
    ids = [slam_map.point3D_ids(i) for i in window]
    pids = np.unique(np.concatenate(ids)) if ids else np.empty(0, np.int64)
    pids = pids[pids >= 0]
    P = len(pids)
    # Every other keyframe's observations of the window's points, from the cached point id arrays (one
    # vectorized lookup per keyframe, no pycolmap track read): they give the track lengths and the held
    # keyframes' observations.
    obs_pose, obs_point, obs_p2 = [], [], []
    for k, pid in enumerate(ids):
        idx = np.flatnonzero(pid >= 0)
        obs_pose.append(np.full(len(idx), k, np.int64))
        obs_point.append(np.searchsorted(pids, pid[idx]))
        obs_p2.append(idx)
    others, other_rows, other_p2 = [], [], []
    for i in slam_map.keyframes:
        if i in in_window or not P:
            continue
        pid = slam_map.point3D_ids(i)
        rows = np.minimum(np.searchsorted(pids, pid), P - 1)
        hit = np.flatnonzero(pids[rows] == pid)
        if len(hit):
            others.append(i)
            other_rows.append(rows[hit])
            other_p2.append(hit)
    length = np.bincount(np.concatenate(obs_point + other_rows), minlength=P) if P else np.zeros(0, np.int64)
    fixed = (length > max_track_length) if max_track_length > 0 else np.zeros(P, bool)
    xyz = slam_map.points_xyz(pids)
    image_ids = list(window)
    for i, rows, p2 in zip(others, other_rows, other_p2):
        var = ~fixed[rows]  # a held point enters through its observations in the window only
        if var.any():
            obs_pose.append(np.full(int(var.sum()), len(image_ids), np.int64))
            obs_point.append(rows[var])
            obs_p2.append(p2[var])
            image_ids.append(i)
    obs_xy, obs_scale = [], []
    for k, i in enumerate(image_ids):
        kf = slam_map.keyframes[i]
        obs_xy.append(np.asarray(kf.keypoints, np.float64)[obs_p2[k]])
        obs_scale.append(keypoint_scales(kf.features)[obs_p2[k]])
    def cat(parts, dtype, shape):
        return np.concatenate(parts).astype(dtype) if parts else np.empty(shape, dtype)
    T = np.empty((len(image_ids), 3, 4))
    frame = rec.frame
    for k, i in enumerate(image_ids):
        T[k] = frame(i).rig_from_world.matrix()
    pose_fixed = np.arange(len(image_ids)) >= len(window)
    gauge = None
    if len(window) >= slam_map.num_keyframes and len(window) >= 2:  # nothing outside the window holds it
        # COLMAP's FixGaugeWithTwoCamsFromWorld: the lowest image id held; of the next one whose baseline to it
        # exceeds 1e-9, the translation coordinate along the largest component of cam1_from_cam2's translation
        order = sorted(range(len(window)), key=lambda k: window[k])
        first = order[0]
        R1, t1 = T[first, :, :3], T[first, :, 3]
        for second in order[1:]:
            baseline = t1 - R1 @ T[second, :, :3].T @ T[second, :, 3]
            if np.abs(baseline).max() > 1e-9:
                pose_fixed[first] = True
                gauge = (second, int(np.argmax(np.abs(baseline))))
                break
    return LocalProblem(np.array(image_ids, np.int64), T, pose_fixed, pids, xyz, fixed,
                        cat(obs_pose, np.int64, (0,)), cat(obs_point, np.int64, (0,)), cat(obs_p2, np.int64, (0,)),
                        cat(obs_xy, np.float64, (0, 2)), cat(obs_scale, np.float64, (0,)), camera, gauge)


def write_back(slam_map: SlamMap, problem: LocalProblem, cam_from_world: np.ndarray, points: np.ndarray) -> None:
    """Set the problem's variable poses (``cam_from_world`` (K, 3|4, 4)) and variable points (``points`` (P, 3))
    in the map's reconstruction."""
    rec = slam_map.reconstruction
    for k in np.flatnonzero(~problem.pose_fixed).tolist():
        T = cam_from_world[k]
        rec.frame(int(problem.image_ids[k])).rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(np.ascontiguousarray(T[:3, :3])), np.ascontiguousarray(T[:3, 3]))
    var = np.flatnonzero(~problem.point_fixed)
    slam_map.set_positions(problem.point3D_ids[var], points[var])
