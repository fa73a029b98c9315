"""KITTI odometry sequences.

Layout (http://www.cvlibs.net/datasets/kitti/eval_odometry.php)::

    dataset/                      # the dataset root ...
        sequences/07/             # ... or this sequence folder
            image_0/000000.png    # left grey camera (image_1 right grey, image_2/3 colour)
            calib.txt             # "P0: 12 numbers" (3x4 projection matrices, row-major), P1..P3, Tr
            times.txt             # one timestamp in seconds per image
        poses/07.txt              # 12 numbers per image: row-major 3x4 camera-to-world of camera 0

Poses exist for sequences 00-10 only; other sequences open without ground truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Intrinsics
from ..errors import CalibrationError, ConfigError, FormatError, SourceError
from ..kernels.geometry import pose_from_rows
from .base import ImageListSource, select
from .calibration import find_camera_txt, read_camera_txt
from .folder import image_size, list_images, resolve_camera
from .groundtruth import check_rotations
from .textfiles import parse_float_rows, parse_keyed_rows, require_path


def read_kitti_calib(path: str | Path) -> dict[str, np.ndarray]:
    """``calib.txt`` -> ``{"P0": (3, 4) float64, ...}``: the ``P*`` keys as 3x4 matrices, others as read.

    A ``P*`` line without 12 numbers raises FormatError; a non-finite number CalibrationError naming the line.
    """
    path = Path(path)
    out: dict[str, np.ndarray] = {}
    for key, (line, values) in parse_keyed_rows(path).items():
        if not np.isfinite(values).all():
            raise CalibrationError(f"{path}:{line}: {key} has non-finite values")
        if key.startswith("P") and key[1:].isdigit():
            if len(values) != 12:
                raise FormatError(path, line, f"{key} needs 12 numbers (a 3x4 matrix), got {len(values)}")
            out[key] = values.reshape(3, 4)
        else:
            out[key] = values
    return out


def check_projection(path: Path, line: int, key: str, P: np.ndarray) -> None:
    """CalibrationError naming the file and line unless the 3x4 projection matrix ``P`` is ``K [I | t]`` with
    ``K`` a pinhole matrix (no skew: P[0, 1] = 0; P[1, 0] = P[2, 0] = P[2, 1] = 0, P[2, 2] = 1), the form of
    KITTI's rectified cameras. Anything else (skew, a rotation) cannot be read as fx, fy, cx, cy without
    losing part of it."""
    scale = max(abs(P[0, 0]), abs(P[1, 1]), 1.0)
    problems = []
    if abs(P[0, 1]) > 1e-6 * scale:
        problems.append(f"skew P[0,1]={P[0, 1]:g} (slamkit's camera model has none)")
    if abs(P[1, 0]) > 1e-6 * scale or abs(P[2, 0]) > 1e-6 or abs(P[2, 1]) > 1e-6 or abs(P[2, 2] - 1) > 1e-6:
        problems.append("its left 3x3 is not an upper-triangular K with K[2,2] = 1 (rows "
                        f"[{P[1, 0]:g} {P[1, 1]:g} {P[1, 2]:g}], [{P[2, 0]:g} {P[2, 1]:g} {P[2, 2]:g}])")
    if problems:
        raise CalibrationError(f"{path}:{line}: {key} is not the projection matrix of a rectified pinhole camera "
                               f"K [I | t]: {'; '.join(problems)}; give the intrinsics with --camera "
                               "fx,fy,cx,cy (Python: camera=Intrinsics(...)) if you know them")


def kitti_intrinsics(P: np.ndarray, width: int, height: int, where: str = "calib.txt") -> Intrinsics:
    """Pinhole intrinsics (no distortion: KITTI images are rectified) from a 3x4 projection matrix:
    fx = P[0, 0], fy = P[1, 1], cx = P[0, 2], cy = P[1, 2]."""
    P = np.asarray(P, dtype=np.float64).reshape(3, 4)
    try:
        return Intrinsics(int(width), int(height), float(P[0, 0]), float(P[1, 1]), float(P[0, 2]),
                          float(P[1, 2]))
    except CalibrationError as e:
        raise CalibrationError(f"{where}: {e}") from None


def read_kitti_times(path: str | Path) -> np.ndarray:
    """``times.txt`` -> (N,) float64 seconds, finite and strictly increasing (FormatError otherwise)."""
    return parse_float_rows(path, 1, increasing=0, what=("timestamp",))[:, 0]


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """``poses/NN.txt`` -> (N, 4, 4) float64 camera-to-world (12 finite numbers per line, row-major 3x4, the
    left 3x3 a rotation: FormatError naming the line otherwise)."""
    rows, lines = parse_float_rows(path, 12, return_lines=True)
    poses = pose_from_rows(rows)
    check_rotations(path, poses[:, :3, :3], lines)
    return poses


def _sequence_folder(root: Path, sequence: str | int | None) -> tuple[Path, Path | None]:
    """(sequence folder, poses file or None) for a dataset root or a sequence folder."""
    seq_root = root / "sequences"
    if seq_root.is_dir():
        available = sorted(p.name for p in seq_root.iterdir() if p.is_dir())
        listed = ", ".join(available) or "none"
        if sequence is None:
            if len(available) != 1:
                raise SourceError(f"{seq_root} holds {len(available)} sequences ({listed}): "
                                  "choose one with sequence='NN'")
            name = available[0]
        else:
            name = str(sequence).zfill(2) if str(sequence).isdigit() else str(sequence)
            if name not in available:
                raise SourceError(f"sequence {name!r} not in {seq_root} (available: {listed})")
        folder = seq_root / name
        poses_root = root
    else:
        folder = root
        name = root.name
        if sequence is not None and str(sequence).zfill(2) != name.zfill(2):
            raise ConfigError(f"sequence={sequence!r} but {root} is the folder of sequence {name!r}")
        poses_root = root.parent.parent  # dataset/sequences/NN -> dataset
    poses = poses_root / "poses" / f"{name}.txt"
    return folder, (poses if poses.is_file() else None)


def open_kitti(path: str | Path, *, sequence: str | int | None = None, camera_index: int | None = None,
               camera: Intrinsics | float | str | None = None, frame_skip: int = 1,
               max_frames: int | None = None) -> ImageListSource:
    """Open a KITTI odometry sequence.

    Args:
        path: the dataset root (holding ``sequences/`` and ``poses/``) or a sequence folder.
        sequence: ``"07"`` or ``7``; may be omitted when the root holds a single sequence.
        camera_index: which ``image_<i>`` folder (0-3); default 0, or 2 when only colour images exist.
            Ground truth is moved from camera 0 to camera ``i`` with the baseline in ``P<i>``.
        camera: override the intrinsics of ``calib.txt`` (:class:`Intrinsics`, focal length or ``--camera``
            text); without it a ``camera.txt`` in the image folder or the sequence folder does.
        frame_skip, max_frames: keep every ``frame_skip``-th image, at most ``max_frames``.

    ``times.txt`` and the poses file must have one line per image (FormatError otherwise). Images are
    decoded on access; only the header of the first one is read here (for the image size).
    """
    root = require_path(path, "KITTI folder", kind="dir")
    folder, poses_file = _sequence_folder(root, sequence)
    if camera_index is None:
        camera_index = 0 if (folder / "image_0").is_dir() or not (folder / "image_2").is_dir() else 2
    if camera_index not in (0, 1, 2, 3):
        raise ConfigError(f"camera_index must be 0, 1, 2 or 3 (got {camera_index!r})")
    image_dir = require_path(folder / f"image_{camera_index}", "KITTI image folder", kind="dir")
    files = list_images(image_dir, extensions=(".png",))
    calib_file = folder / "calib.txt"
    if not calib_file.is_file():
        raise SourceError(f"{calib_file}: missing; a KITTI sequence folder holds calib.txt (its P0..P3 projection "
                          f"matrices, from the odometry calibration download) next to {image_dir.name}/")
    calib = read_kitti_calib(calib_file)
    key = f"P{camera_index}"
    if key not in calib:
        raise FormatError(calib_file, None, f"no '{key}:' line (the projection matrix of image_{camera_index})")
    P = calib[key]
    check_projection(calib_file, parse_keyed_rows(calib_file)[key][0], key, P)
    times_file = require_path(folder / "times.txt", "KITTI timestamps")
    times = read_kitti_times(times_file)
    if len(times) != len(files):
        raise FormatError(times_file, None, f"has {len(times)} timestamps but {image_dir} has {len(files)} images")
    w, h = image_size(files[0])
    calib_txt = find_camera_txt(image_dir, folder) if camera is None else None
    if calib_txt is not None:
        camera = read_camera_txt(calib_txt, w, h)
    calib_cam = kitti_intrinsics(P, w, h, where=str(calib_file))
    if camera is None:
        calib_cam.check_centred(where=f"{calib_file} ({key}) with the images of {image_dir}")
    cam = resolve_camera(calib_cam if camera is None else camera, w, h, where=str(files[0]))
    gt = None
    if poses_file is not None:
        gt = read_kitti_poses(poses_file)
        if len(gt) != len(files):
            raise FormatError(poses_file, None, f"has {len(gt)} poses but {image_dir} has {len(files)} images")
        # P_i = K [I | t_i]: a point x0 of camera 0 is x0 + t_i in camera i, so cam_i-to-cam_0 = [I | -t_i]
        t_i = np.linalg.solve(calib_cam.K, P[:, 3])
        if np.abs(t_i).max() > 0:
            T_0i = np.eye(4)
            T_0i[:3, 3] = -t_i
            gt = gt @ T_0i
    keep = select(len(files), frame_skip, max_frames)
    ids = np.array([int(p.stem) if p.stem.isdigit() else i for i, p in enumerate(files)], dtype=np.int64)
    return ImageListSource(name=f"kitti/{folder.name}", camera=cam, paths=[files[i] for i in keep],
                           timestamps=times[keep], frame_ids=ids[keep],
                           gt_poses=None if gt is None else gt[keep])
