"""nerfstudio's dataset format: ``transforms.json`` beside ``images/`` and a sparse point cloud.

Schema (nerfstudio's ``nerfstudio-data`` parser, as written by its ``colmap_to_json``): shared intrinsics
``w h fl_x fl_y cx cy camera_model`` (``"PINHOLE"``, or ``"OPENCV"`` with ``k1 k2 k3 p1 p2``), one entry per
frame ``{"file_path": "images/NAME", "transform_matrix": 4x4}``, and ``ply_file_path`` naming the point
cloud splatfacto initializes its Gaussians from. ``transform_matrix`` is camera-to-world in nerfstudio's
OpenGL camera convention (x right, y up, z backwards): slamkit's (OpenCV: x right, y down, z forwards)
camera-to-world times ``diag(1, -1, -1, 1)``. The world frame is the run's (no axis swap, no
``applied_transform``): nerfstudio re-orients and re-centres the poses itself when it loads them.
"""

from __future__ import annotations

import json

import numpy as np
import pycolmap

from ..io.atomic import atomic_write_bytes, atomic_write_text
from .camera import ExportCamera

OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplying a camera-to-world by this flips the camera's y and z axes (OpenCV <-> OpenGL)."""

PLY_NAME = "sparse_pc.ply"


def opengl_from_opencv(world_from_cam: np.ndarray) -> np.ndarray:
    """(..., 4, 4) camera-to-world, OpenCV camera axes -> OpenGL camera axes (its own inverse)."""
    return np.asarray(world_from_cam, np.float64) @ OPENGL_FROM_OPENCV


def intrinsics_json(camera: ExportCamera) -> dict:
    """The shared intrinsics block of ``transforms.json``."""
    cam = camera.camera
    fx, fy, cx, cy = (float(v) for v in cam.params[:4])
    out = {"w": int(cam.width), "h": int(cam.height), "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy}
    if camera.model_name == "PINHOLE":
        return {**out, "camera_model": "PINHOLE"}
    k1, k2, p1, p2 = (float(v) for v in cam.params[4:8])
    k3 = float(cam.params[8]) if len(cam.params) > 8 else 0.0
    return {**out, "camera_model": "OPENCV", "k1": k1, "k2": k2, "k3": k3, "k4": 0.0, "p1": p1, "p2": p2}


def write_transforms(path, camera: ExportCamera, rec: pycolmap.Reconstruction) -> None:
    """``transforms.json`` of every registered image of ``rec`` (file paths ``images/<name>``), in id order."""
    frames = []
    for iid in sorted(rec.reg_image_ids()):
        image = rec.image(iid)
        world_from_cam = np.eye(4)
        world_from_cam[:3] = image.cam_from_world().inverse().matrix()
        frames.append({"file_path": f"images/{image.name}",
                       "transform_matrix": opengl_from_opencv(world_from_cam).tolist(), "colmap_im_id": int(iid)})
    doc = {**intrinsics_json(camera), "frames": frames, "ply_file_path": PLY_NAME}
    atomic_write_text(path, json.dumps(doc, indent=2))


def write_ply(path, rec: pycolmap.Reconstruction) -> int:
    """Binary little-endian PLY of the points of ``rec`` (float x y z, uchar red green blue); returns the
    number of points."""
    ids = sorted(rec.point3D_ids())
    data = np.zeros(len(ids), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                     ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    if ids:
        xyz = np.array([rec.point3D(i).xyz for i in ids], np.float64)
        rgb = np.array([rec.point3D(i).color for i in ids], np.uint8)
        for k, name in enumerate("xyz"):
            data[name] = xyz[:, k]
        for k, name in enumerate(("red", "green", "blue")):
            data[name] = rgb[:, k]
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(ids)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    atomic_write_bytes(path, [header.encode("ascii"), data.tobytes()])
    return len(ids)
