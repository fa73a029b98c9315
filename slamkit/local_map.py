"""The local map: the map points around the last keyframe as arrays, what tracking and relocalization match
a frame against (ORB-SLAM's local map). Built from a :class:`~slamkit.map.SlamMap`; read-only afterwards."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import ConfigError
from .map import SlamMap

POINT_DESCRIPTORS = ("oldest", "newest")
"""Which keyframe's descriptor a local-map point is matched by (see ``TrackerConfig.point_descriptor``)."""


@dataclass(eq=False)
class LocalMap:
    """Map points near the last keyframe, as arrays for vectorised matching.

    ids: (M,) int64 point ids; xyz: (M, 3) world positions; descriptors: (M, D), each point's from the
    reference keyframe or the latest keyframe observing it ("newest"), or from the earliest ("oldest");
    ref_ids / ref_xy: points observed by the reference (last) keyframe, sorted by id, with their
    (undistorted) pixel positions there.
    """

    ids: np.ndarray
    xyz: np.ndarray
    descriptors: np.ndarray
    binary: bool
    ref_image_id: int
    ref_ids: np.ndarray
    ref_xy: np.ndarray
    keyframe_ids: list[int]

    @classmethod
    def build(cls, slam_map: SlamMap, ref_image_id: int, num_covisible: int = 10,
              point_descriptor: str = "newest") -> "LocalMap":
        """The points of keyframe ``ref_image_id`` and of its ``num_covisible`` most covisible keyframes;
        ``point_descriptor``: see :attr:`TrackerConfig.point_descriptor`."""
        if point_descriptor not in POINT_DESCRIPTORS:
            raise ConfigError(f"point_descriptor must be one of {', '.join(POINT_DESCRIPTORS)}")
        kf_ids = [ref_image_id] + [i for i, _ in slam_map.covisible(ref_image_id, num_covisible)]
        all_ids, all_desc = [], []
        ref_ids = ref_xy = None
        # keyframes in the order whose first observation of a point wins
        if point_descriptor == "oldest":
            order = sorted(kf_ids, key=lambda i: slam_map.keyframes[i].frame_index)
        else:
            order = sorted(kf_ids, key=lambda i: (i != ref_image_id, -slam_map.keyframes[i].frame_index))
        for iid in order:
            pids = slam_map.point3D_ids(iid)
            has = pids >= 0
            kf = slam_map.keyframes[iid]
            all_ids.append(pids[has])
            all_desc.append(kf.features.descriptors[has])
            if iid == ref_image_id:
                o = np.argsort(pids[has])
                ref_ids, ref_xy = pids[has][o], kf.keypoints[has][o]
        ids, first = np.unique(np.concatenate(all_ids), return_index=True)  # first: the chosen keyframe's
        desc = np.concatenate(all_desc)
        binary = slam_map.keyframes[ref_image_id].features.binary
        return cls(ids, slam_map.points_xyz(ids), desc[first], binary, ref_image_id, ref_ids, ref_xy, kf_ids)

    def __len__(self) -> int:
        return len(self.ids)

    def project(self, cam_from_world: np.ndarray, K: np.ndarray, size: tuple[int, int]
                ) -> tuple[np.ndarray, np.ndarray]:
        """Project into a camera: returns (indices of points in front and inside the image, (K, 2) pixels)."""
        Xc = self.xyz @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        z = Xc[:, 2]
        front = z > 1e-6
        uv = np.full((len(Xc), 2), -1.0)
        uv[front] = Xc[front, :2] / z[front, None] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        w, h = size
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        idx = np.flatnonzero(inside)
        return idx, uv[idx]
