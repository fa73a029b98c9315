"""Deferred triangulation of a keypoint of unknown depth (DT-SLAM: Herrera, Kim, Kannala, Pulli and Heikkilä,
"DT-SLAM: Deferred Triangulation for Robust SLAM", 3DV 2014).

A keypoint seen only from frames that turned in place (or moved too little for its depth) has no depth yet:
DT-SLAM keeps it as a 2-D feature, a ray from the camera centre (its bearing), instead of dropping it or
triangulating it badly. Each later observation from a posed frame extends its track; once the largest angle
between two of its rays in the world (the triangulation angle; 0 for a pure rotation, whatever the depth)
reaches ``min_parallax_deg`` it is triangulated by COLMAP's ``EstimateTriangulation``
(``pycolmap.estimate_triangulation``: LO-RANSAC over the observations, angular residuals), checked in front of
every camera and against the reprojection error, and can then join the map as an ordinary point (and BA).

:class:`DeferredTriangulator` ``step(feature, camera)`` says what became of one :class:`DeferredFeature`:
"deferred" (too little parallax so far, the numbers said), "triangulated" (``xyz``), or "rejected".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ..errors import check_fields

DEFERRED, TRIANGULATED, REJECTED = "deferred", "triangulated", "rejected"
"""The statuses of :class:`DeferredTriangulation`."""


@dataclass(frozen=True)
class DeferredTriangulationConfig:
    min_parallax_deg: float = 1.5
    """A feature is triangulated once two of its rays meet at least this angle (degrees; the initializer's
    parallax threshold); below it, its depth stays unknown."""
    max_reprojection_px: float = 2.0
    """Largest reprojection error of the triangulated point in any observation, pixels."""
    min_observations: int = 2

    def validate(self) -> "DeferredTriangulationConfig":
        check_fields(self, "deferred_triangulation", {"min_parallax_deg": "(0, 90]", "max_reprojection_px": "(0, 1e9]",
                                                      "min_observations": "[2, inf)"})
        return self


@dataclass(eq=False)
class DeferredFeature:
    """One keypoint's track over posed frames: ``xy`` (N, 2) undistorted pixels, ``cams_from_world`` (N, 3, 4),
    ``frames`` (N,) frame indices. Grown by :meth:`observe`."""

    xy: list[np.ndarray] = field(default_factory=list)
    cams_from_world: list[np.ndarray] = field(default_factory=list)
    frames: list[int] = field(default_factory=list)

    def observe(self, frame: int, cam_from_world: np.ndarray, xy: np.ndarray) -> "DeferredFeature":
        """Add an observation: ``cam_from_world`` (3, 4) or (4, 4), ``xy`` (2,) pixels. Returns self."""
        self.frames.append(int(frame))
        self.cams_from_world.append(np.asarray(cam_from_world, np.float64)[:3, :4].copy())
        self.xy.append(np.asarray(xy, np.float64).reshape(2).copy())
        return self

    def rays(self, K: np.ndarray) -> np.ndarray:
        """(N, 3) unit rays in the world frame (``R^T K^-1 [x, y, 1]``) of the observations."""
        T = np.asarray(self.cams_from_world)
        b = np.c_[np.asarray(self.xy), np.ones(len(self.xy))] @ np.linalg.inv(K).T
        r = np.einsum("nji,nj->ni", T[:, :, :3], b)
        return r / np.linalg.norm(r, axis=1, keepdims=True)

    def parallax_deg(self, K: np.ndarray) -> float:
        """The largest angle between two of the feature's rays, degrees (0 with fewer than two)."""
        if len(self.xy) < 2:
            return 0.0
        r = self.rays(K)
        return float(np.degrees(np.arccos(np.clip((r @ r.T).min(), -1.0, 1.0))))


@dataclass(frozen=True, eq=False)
class DeferredTriangulation:
    """What :meth:`DeferredTriangulator.step` did with a feature. ``xyz``: (3,) world point (triangulated only)."""

    status: str
    reason: str
    parallax_deg: float
    xyz: np.ndarray | None = None
    max_reprojection_px: float = math.nan

    @property
    def triangulated(self) -> bool:
        return self.status == TRIANGULATED


class DeferredTriangulator:
    """Triangulates a :class:`DeferredFeature` once its parallax allows (the module's docstring explains)."""

    def __init__(self, config: DeferredTriangulationConfig = DeferredTriangulationConfig()):
        self.config = config.validate()
        self._options = pycolmap.EstimateTriangulationOptions()
        self._options.ransac.random_seed = 0

    def step(self, feature: DeferredFeature, camera: pycolmap.Camera) -> DeferredTriangulation:
        """``feature``'s fate for a pinhole ``camera`` (its keypoints are undistorted pixels of it)."""
        c = self.config
        K = camera.calibration_matrix()
        n = len(feature.xy)
        parallax = feature.parallax_deg(K)
        if n < c.min_observations or parallax < c.min_parallax_deg:
            return DeferredTriangulation(DEFERRED, f"depth unknown: parallax {parallax:.2f} deg < "
                                         f"{c.min_parallax_deg} over {n} observations", parallax)
        poses = [pycolmap.Rigid3d(T) for T in feature.cams_from_world]
        est = pycolmap.estimate_triangulation(np.asarray(feature.xy), poses, [camera] * n, self._options)
        if est is None:
            return DeferredTriangulation(REJECTED, "no triangulation from the observations", parallax)
        X = np.asarray(est["xyz"], np.float64).reshape(3)
        T = np.asarray(feature.cams_from_world)
        p = np.einsum("nij,j->ni", T[:, :, :3], X) + T[:, :, 3]
        if (p[:, 2] <= 0).any():
            return DeferredTriangulation(REJECTED, "triangulated behind a camera", parallax)
        proj = (p @ K.T)[:, :2] / p[:, 2:]
        err = float(np.linalg.norm(proj - np.asarray(feature.xy), axis=1).max())
        if err > c.max_reprojection_px:
            return DeferredTriangulation(REJECTED, f"reprojection error {err:.2f} px > {c.max_reprojection_px}",
                                         parallax, max_reprojection_px=err)
        return DeferredTriangulation(TRIANGULATED, f"triangulated at parallax {parallax:.2f} deg from {n} "
                                     f"observations (reprojection <= {err:.2f} px)", parallax, X, err)


__all__ = ["DEFERRED", "REJECTED", "TRIANGULATED", "DeferredFeature", "DeferredTriangulation",
           "DeferredTriangulationConfig", "DeferredTriangulator"]
