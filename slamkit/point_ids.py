"""Each image's 3D point ids as one array, read from pycolmap once and kept while they hold.

pycolmap has no batch read of an image's observations: the ids come one ``Point2D`` object at a time, about
0.5 us an observation, and the stages ask for the same keyframes' ids again and again within one keyframe
step (local mapping's neighbours, the bundle adjustment window, its outlier test, the local map). So
:class:`~slamkit.map.SlamMap` keeps them in a :class:`PointIdCache`: an image's array is read on first use
and kept until its observations change. Changes made through ``SlamMap`` (new points, added, deleted or
merged observations) are written into the cached arrays, the same values pycolmap just set; changes made
elsewhere (pycolmap's triangulator, track completion and merging, filtering) make the caller forget the
arrays (``SlamMap.changed``), which are then read again.
"""

from __future__ import annotations

import numpy as np
import pycolmap


def read_point3D_ids(image: pycolmap.Image) -> np.ndarray:
    """(N,) int64 3D point id of each of the image's keypoints, -1 where none, from pycolmap (read-only)."""
    out = np.full(image.num_points2D(), -1, np.int64)
    points2D = image.get_observation_points2D()
    if points2D:
        out[image.get_observation_point2D_idxs()] = [p.point3D_id for p in points2D]
    out.flags.writeable = False
    return out


def track_of(reconstruction: pycolmap.Reconstruction, point3D_id: int) -> tuple[list[int], list[int]]:
    """(image ids, point2D indices) of a point's observations, as ints: pycolmap's ``TrackElement`` objects
    are live references into the track and do not survive a change of it."""
    track = reconstruction.point3D(int(point3D_id)).track.elements
    return [el.image_id for el in track], [el.point2D_idx for el in track]


class PointIdCache:
    """Point id arrays by image id (see the module docstring). An array handed out is never changed: it is
    made read-only, and a change to it is written into a copy that replaces it here (one copy per image until
    the array is handed out again), so a caller's array stays what it was."""

    def __init__(self):
        self._ids: dict[int, np.ndarray] = {}

    def get(self, reconstruction: pycolmap.Reconstruction, image_id: int) -> np.ndarray:
        """The image's (N,) int64 point ids (-1: none), read on first use; read-only."""
        out = self._ids.get(image_id)
        if out is None:
            out = self._ids[image_id] = read_point3D_ids(reconstruction.image(image_id))
        out.flags.writeable = False  # handed out: the next change copies it
        return out

    def forget(self, image_ids=None) -> None:
        """Drop the arrays of ``image_ids`` (None: of every image); they are read again when asked for."""
        if image_ids is None:
            self._ids.clear()
        else:
            for i in image_ids:
                self._ids.pop(int(i), None)

    def write(self, image_ids: list[int], point2D_idxs: list[int], point3D_ids: list[int] | int) -> None:
        """Record that keypoint ``point2D_idxs[k]`` of image ``image_ids[k]`` now observes ``point3D_ids[k]``
        (-1: nothing), as pycolmap was just told; images not cached are left to be read. One id (an int)
        applies to every keypoint."""
        if isinstance(point3D_ids, int):
            point3D_ids = [point3D_ids] * len(image_ids)
        for i, j, p in zip(image_ids, point2D_idxs, point3D_ids):
            ids = self._ids.get(int(i))
            if ids is None:
                continue
            if not ids.flags.writeable:  # handed out (or just read): change a copy
                ids = self._ids[int(i)] = ids.copy()
            ids[j] = p

    def cached(self) -> dict[int, np.ndarray]:
        """{image id: array} of the images cached now (a copy of the mapping; for tests)."""
        return dict(self._ids)


class PointPositionCache:
    """3D point positions by point id, as one array: read from pycolmap on first use (one ``Point3D`` object at a
    time, about 1 us a point) and kept until the point may have moved. Bundle adjustment, the loop correction and
    normalization move points: they make :class:`~slamkit.map.SlamMap` forget them (``SlamMap.moved``), or write
    the values they set (``SlamMap.set_positions``, the compiled local BA's write-back). New points get new ids
    (pycolmap never gives an id twice), so they are read at their first use. A new Reconstruction behind the map
    (compaction, a loaded session) starts an empty cache."""

    def __init__(self):
        self._xyz = np.zeros((0, 3))
        self._known = np.zeros(0, bool)
        self._owner: pycolmap.Reconstruction | None = None

    def _reserve(self, reconstruction: pycolmap.Reconstruction, top: int) -> None:
        if self._owner is not reconstruction:  # another Reconstruction: nothing cached holds
            self._owner = reconstruction
            self._known[:] = False
        if top > len(self._known):
            size = max(top, 2 * len(self._known), 1024)
            self._xyz = np.concatenate([self._xyz, np.zeros((size - len(self._xyz), 3))])
            self._known = np.concatenate([self._known, np.zeros(size - len(self._known), bool)])

    def get(self, reconstruction: pycolmap.Reconstruction, point3D_ids: np.ndarray) -> np.ndarray:
        """(M, 3) positions of existing points ``point3D_ids`` (M,), a new array."""
        ids = np.asarray(point3D_ids, np.int64).reshape(-1)
        if not len(ids):
            return np.empty((0, 3))
        self._reserve(reconstruction, int(ids.max()) + 1)
        missing = ids[~self._known[ids]]
        if len(missing):
            missing = np.unique(missing)
            point3D = reconstruction.point3D  # (one concatenation: a third faster than an array of rows)
            self._xyz[missing] = np.concatenate([point3D(p).xyz for p in missing.tolist()]).reshape(-1, 3)
            self._known[missing] = True
        return self._xyz[ids]

    def set(self, reconstruction: pycolmap.Reconstruction, point3D_ids: np.ndarray, xyz: np.ndarray) -> None:
        """Record that points ``point3D_ids`` were just set to ``xyz`` ((M, 3)) in ``reconstruction``."""
        ids = np.asarray(point3D_ids, np.int64).reshape(-1)
        if len(ids):
            self._reserve(reconstruction, int(ids.max()) + 1)
            self._xyz[ids] = np.asarray(xyz, np.float64).reshape(-1, 3)
            self._known[ids] = True

    def forget(self, point3D_ids=None) -> None:
        """Forget the positions of ``point3D_ids`` (None: of every point); they are read again when asked for."""
        if point3D_ids is None:
            self._known[:] = False
            return
        ids = np.asarray(point3D_ids, np.int64).reshape(-1)
        self._known[ids[ids < len(self._known)]] = False

    def cached(self) -> dict[int, np.ndarray]:
        """{point id: position} of the points cached now (for tests)."""
        return {int(i): self._xyz[i].copy() for i in np.flatnonzero(self._known)}
