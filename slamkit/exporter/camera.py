"""The exported camera, and the map from the run's pixels to the exported images' pixels.

A run's model uses an ideal PINHOLE camera K of *undistorted* pixels (:mod:`slamkit.camera`); its images on
disk are the source's, distortion included. The export chooses one of three cameras:

- the source has no distortion: PINHOLE with the run's K, images as they are, pixels unchanged;
- distortion kept (default): OPENCV (``fx fy cx cy k1 k2 p1 p2``; FULL_OPENCV when k3 != 0, which COLMAP
  needs for OpenCV's five-coefficient model), images as they are, observations re-distorted;
- ``undistort=True``: the images are resampled by COLMAP's undistorter (``pycolmap.undistort_image``, the
  ``colmap image_undistorter`` step) onto the PINHOLE camera ``pycolmap.undistort_camera`` chooses (same
  focal lengths, size and principal point covering the valid pixels); observations become K' K^-1 p.

Pixel convention: slamkit's (and OpenCV's) pixel centres are at integer coordinates; COLMAP, gsplat, 3DGS
and nerfstudio put them at +0.5. The exported camera and observations are in COLMAP's convention: principal
point and 2D points are the run's plus 0.5 px (``PIXEL_CENTER``), so a tool reading the export projects each
point onto the same image pixel as slamkit does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from ..camera import Intrinsics

CAMERA_ID = 1

PIXEL_CENTER = 0.5
"""COLMAP's coordinate of the centre of the top-left pixel (slamkit's and OpenCV's is 0)."""


def _colmap_distorted(camera: Intrinsics, shift: float = 0.0) -> pycolmap.Camera:
    """The source camera as a COLMAP OPENCV / FULL_OPENCV camera (principal point + ``shift`` pixels)."""
    k1, k2, p1, p2, k3 = camera.dist
    base = [camera.fx, camera.fy, camera.cx + shift, camera.cy + shift, k1, k2, p1, p2]
    if k3 != 0.0:
        return pycolmap.Camera(model="FULL_OPENCV", width=camera.width, height=camera.height,
                               params=base + [k3, 0.0, 0.0, 0.0], camera_id=CAMERA_ID)
    return pycolmap.Camera(model="OPENCV", width=camera.width, height=camera.height, params=base,
                           camera_id=CAMERA_ID)


@dataclass(frozen=True, eq=False)
class ExportCamera:
    """The camera of the exported images.

    source: the images' intrinsics as read (distortion included); camera: the exported pycolmap camera;
    undistort: images are resampled by COLMAP's undistorter; K_model: (3, 3) the run model's PINHOLE matrix.
    """

    source: Intrinsics
    camera: pycolmap.Camera
    undistort: bool
    K_model: np.ndarray

    @classmethod
    def create(cls, source: Intrinsics, undistort: bool = False) -> "ExportCamera":
        """PINHOLE when ``source`` has no distortion; else OPENCV, or PINHOLE after undistortion."""
        if not source.has_distortion:
            cam = pycolmap.Camera(model="PINHOLE", width=source.width, height=source.height,
                                  params=[source.fx, source.fy, source.cx + PIXEL_CENTER, source.cy + PIXEL_CENTER],
                                  camera_id=CAMERA_ID)
            return cls(source, cam, False, source.K)
        distorted = _colmap_distorted(source, PIXEL_CENTER)
        if not undistort:
            return cls(source, distorted, False, source.K)
        new = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), distorted)
        cam = pycolmap.Camera(model="PINHOLE", width=new.width, height=new.height,
                              params=[float(v) for v in new.params[:4]], camera_id=CAMERA_ID)
        return cls(source, cam, True, source.K)

    @property
    def model_name(self) -> str:
        return self.camera.model.name

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the exported images, pixels."""
        return int(self.camera.width), int(self.camera.height)

    def from_model(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) pixels of the run's PINHOLE model -> (N, 2) float64 pixels of the exported images (COLMAP's
        convention: the exported camera's principal point carries the +0.5 px)."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        if len(xy) == 0:
            return xy.copy()
        K = self.K_model
        rays = np.column_stack([(xy[:, 0] - K[0, 2]) / K[0, 0], (xy[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(xy))])
        if self.model_name == "PINHOLE":
            fx, fy, cx, cy = (float(v) for v in self.camera.params[:4])
            return np.column_stack([fx * rays[:, 0] + cx, fy * rays[:, 1] + cy])
        return np.asarray(self.camera.img_from_cam(rays), np.float64).reshape(-1, 2)

    def undistort_image(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB source image -> the exported image (resampled when ``undistort``)."""
        if not self.undistort:
            return rgb
        bitmap = pycolmap.Bitmap.from_array(np.ascontiguousarray(rgb))
        out, _ = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), bitmap,
                                          _colmap_distorted(self.source, PIXEL_CENTER))
        return np.asarray(out.to_array(), np.uint8).reshape(self.size[1], self.size[0], -1)
