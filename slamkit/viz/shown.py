"""The map as the map view's scene shows it: the state the next snapshot is diffed against.

:class:`ShownMap` holds what was last read and sent for one map — keyframe ids, times and poses, the
camera path, the current frame, the points (a :class:`~slamkit.viz.diff.PointStore`), the last full
observation lists of the keyframes, the display fit and other paths drawn through the map (:class:`OtherPath`) —
and derives the geometry the scene draws from it
(keyframe poses and centres, recency fractions, the keyframes and times inside a clip range, the fit).
No meshcat and no server: the sender draws from it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pycolmap

from .diff import PointStore
from .scene import (DISPLAY_EXTENT, DISPLAY_FROM_OPENCV, Camera, compute_fit, display_from_map, map_heights,
                    nearest_camera_distance, time_fractions, view_centering, world_from_cam)
from .settings import ViewSettings


@dataclass(frozen=True, eq=False)
class OtherPath:
    """Another camera path drawn through the map shown, in one colour: e.g. a second walk localized in a saved
    run's map (``slamkit run --map``), whose positions are in that map's frame and scale."""

    label: str
    """What it is, for the legend and the picture's title."""
    centers: np.ndarray
    """(N, 3) camera centres in the map's frame, map units, in time order."""
    color: tuple[float, float, float]
    """RGB in [0, 1]."""


class ShownMap:
    """What the scene shows of one map (empty until the first update; a new map starts a new one)."""

    def __init__(self) -> None:
        self.key: Any = None
        """Identity of the map shown (None: nothing shown)."""
        self.reconstruction: pycolmap.Reconstruction | None = None
        self.kf_ids = np.empty(0, np.int64)
        """(K,) sorted keyframe image ids."""
        self.kf_times = np.empty(0)
        """(K,) keyframe timestamps, seconds."""
        self.kf_pose = np.empty((0, 3, 4))
        """(K, 3, 4) cam_from_world as last read."""
        self.path_t = np.empty(0)
        """(N,) seconds of the posed frames, in time order."""
        self.path_c = np.empty((0, 3))
        """(N, 3) world camera centres of the posed frames."""
        self.current: np.ndarray | None = None
        """(4, 4) world_from_cam of the current non-key frame, or None."""
        self.loop_edges = np.empty((0, 2, 3))
        """(L, 2, 3) world centres of the keyframe pairs of the loops closed."""
        self.points = PointStore()
        self.observations: dict[int, np.ndarray] = {}
        """Keyframe -> the point ids it observed when last read in full (to find deleted points)."""
        self.fit: tuple[np.ndarray, float] | None = None
        """(centre (3,), extent) of the display fit, map units."""
        self.fit_box: tuple[np.ndarray, float] | None = None
        """(centre (3,), extent) of the 5-95 % box the fit was made from (before centring the picture)."""
        self.view_depth = 1.0
        """Median distance from a map point to its nearest camera, map units (set with the fit)."""
        self.camera: Camera | None = None
        self.height_range: tuple[float, float] = (0.0, 1.0)
        """(low, high) map units: the 5-95 % range of the points' heights at the last fit (their colour scale)."""
        self.other_paths: list[OtherPath] = []
        """Other camera paths drawn through this map, in the order they were added."""

    @property
    def map_extent(self) -> float:
        """The fitted map's extent, map units (1 before the first fit)."""
        return self.fit[1] if self.fit is not None else 1.0

    def keep_observations(self, observers: dict[int, np.ndarray]) -> None:
        """Remember complete observation lists; forget those of keyframes no longer in the map."""
        self.observations.update(observers)
        current_ids = set(self.kf_ids.tolist())
        for k in [k for k in self.observations if k not in current_ids]:
            del self.observations[k]

    # ------------------------------------------------------------------ keyframes
    def kf_world_from_cam(self) -> np.ndarray:
        """(K, 4, 4) world_from_cam of the keyframes."""
        return world_from_cam(self.kf_pose)

    def kf_centers(self) -> np.ndarray:
        """(K, 3) world centres of the keyframes."""
        return self.kf_world_from_cam()[:, :3, 3] if len(self.kf_pose) else np.empty((0, 3))

    def time_fractions(self, times: np.ndarray) -> np.ndarray:
        """0 at the first keyframe, 1 at the last (path frames outside that span are clipped to 0 / 1)."""
        return time_fractions(times, self.kf_times, self.path_t)

    def clip_keyframes(self, clip: tuple[int, int] | None) -> np.ndarray:
        """(K,) bool: the keyframes inside the clip range (all without one)."""
        if clip is None:
            return np.ones(len(self.kf_ids), bool)
        return (self.kf_ids >= clip[0]) & (self.kf_ids <= clip[1])

    def clip_times(self, clip: tuple[int, int] | None) -> tuple[float, float]:
        """(first, last) timestamps of the keyframes inside the clip range, seconds (an empty interval
        when none is; unbounded without a range)."""
        if clip is None or len(self.kf_ids) == 0:
            return -np.inf, np.inf
        sel = self.clip_keyframes(clip)
        if not sel.any():
            return np.inf, -np.inf
        t = self.kf_times[sel]
        return float(t.min()), float(t.max())

    # ------------------------------------------------------------------ display fit
    def camera_centers(self) -> np.ndarray:
        """(C, 3) world centres of the keyframes, the path's frames, the current frame and the other paths'
        frames (the fit and the home camera frame them all)."""
        cur = self.current[None, :3, 3] if self.current is not None else np.empty((0, 3))
        return np.concatenate([self.kf_centers(), self.path_c, cur, *(o.centers for o in self.other_paths)])

    def compute_fit(self) -> tuple[np.ndarray, float]:
        """(centre (3,), extent) around the points, keyframe centres, path and current frame."""
        pts = self.points.xyz[self.points.alive()].astype(np.float64)
        return compute_fit(pts, self.kf_centers(), self.camera_centers())

    def set_fit(self, fit: tuple[np.ndarray, float], aspect: float | None = None) -> None:
        """Use ``fit`` and measure the depth the points were seen at (for their size) on the same map; with
        the viewer's ``aspect`` (width / height), move the centre so the home camera's picture is centred."""
        self.fit = self.fit_box = fit
        if aspect is not None:
            points, cameras = self.display_points()
            offset = view_centering(points, cameras, aspect)
            R = DISPLAY_FROM_OPENCV * (DISPLAY_EXTENT / fit[1])
            self.fit = (fit[0] + np.linalg.solve(R, offset), fit[1])
        pts = self.points.xyz[self.points.alive()]
        if len(pts):  # the colour scale of heights, kept unless the map's range changed by 15 % of it
            lo, hi = np.percentile(map_heights(pts), [5, 95])
            new = (float(lo), float(hi)) if hi > lo else (float(lo) - 0.5, float(lo) + 0.5)
            old = self.height_range
            if max(abs(new[0] - old[0]), abs(new[1] - old[1])) > 0.15 * max(old[1] - old[0], 1e-12):
                self.height_range = new
        depth = nearest_camera_distance(pts, np.concatenate([self.kf_centers(), self.path_c]))
        self.view_depth = depth if np.isfinite(depth) and depth > 0 else fit[1] / 3

    @property
    def display_scale(self) -> float:
        """Viewer units per map unit."""
        return DISPLAY_EXTENT / self.map_extent

    def point_size_units(self, settings: ViewSettings) -> float:
        """The points' diameter in viewer units (point sizes ignore the scale of the view's transform)."""
        return settings.point_diameter(self.view_depth) * self.display_scale

    def display_points(self, sample: int = 4000) -> tuple[np.ndarray, np.ndarray]:
        """((M, 3) up to ``sample`` map points, (C, 3) every camera centre) in viewer coordinates (framing)."""
        pts = self.points.xyz[self.points.alive()].astype(np.float64)
        if len(pts) > sample:
            pts = pts[np.random.default_rng(0).choice(len(pts), sample, replace=False)]
        cams = self.camera_centers()
        T = display_from_map(self.fit)
        return pts @ T[:3, :3].T + T[:3, 3], cams @ T[:3, :3].T + T[:3, 3]

    def refit_needed(self, full: bool) -> bool | tuple[np.ndarray, float]:
        """Whether the display fit no longer frames the map: none yet; or (every point read) the map's
        extent changed by more than -40 % / +25 % or its centre moved by a quarter of it (growth, bundle
        adjustment's normalization); or (incremental) a camera left the fitted box by 20 %.
        Returns the new fit when it was computed."""
        if self.fit is None:
            return True
        c, ext = self.fit_box if self.fit_box is not None else self.fit
        if full:
            cand = self.compute_fit()
            if not (0.6 * ext <= cand[1] <= 1.25 * ext) or np.abs(cand[0] - c).max() > 0.25 * ext:
                return cand
            return False
        centres = np.concatenate([self.kf_centers(), self.path_c])
        return bool(len(centres)) and bool(np.abs(centres - c).max() > 0.6 * ext)


__all__ = ["ShownMap", "OtherPath"]
