"""Microsoft 7-Scenes sequences (Kinect v1 RGB, 640x480, 30 fps).

Layout (https://www.microsoft.com/en-us/research/project/rgb-d-dataset-7-scenes/)::

    redkitchen/                        # the scene folder ...
        camera-intrinsics.txt          # optional: 3x3 K (or "fx fy cx cy")
        seq-01/                        # ... or a sequence folder
            frame-000000.color.png     # (or .jpg)
            frame-000000.depth.png     # ignored
            frame-000000.pose.txt      # 4x4 camera-to-world (KinectFusion); some are -inf: tracking lost

There are no timestamps: frame number / 30 s. Poses with inf/NaN become NaN rows of ``gt_poses``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..camera import Intrinsics
from ..errors import CalibrationError, ConfigError, FormatError, SourceError
from .base import ImageListSource, select
from .calibration import find_camera_txt, read_camera_txt
from .folder import image_size, natural_sorted, resolve_camera
from .groundtruth import ROTATION_TOLERANCE, check_rotations
from .textfiles import convert_fields, data_lines, parse_rows, require_path, to_float

SEVENSCENES_NOMINAL = (585.0, 585.0, 320.0, 240.0)
"""Nominal (fx, fy, cx, cy) of 7-Scenes colour images, used when there is no camera-intrinsics.txt."""

SEVENSCENES_FPS = 30.0

_COLOR = re.compile(r"^frame-(\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)
_SEQ = re.compile(r"^seq-?\d+$", re.IGNORECASE)


def read_number_rows(path: str | Path) -> tuple[list[list[float]], np.ndarray]:
    """Every data line of a small numeric file as a list of floats (any count per line), with line numbers."""
    path = Path(path)
    rows, lines = [], []
    for number, fields in data_lines(path):
        rows.append(convert_fields(path, number, fields, [to_float] * len(fields)))
        lines.append(number)
    return rows, np.asarray(lines, dtype=np.int64)


def read_pose_matrix(path: str | Path) -> np.ndarray:
    """A 7-Scenes ``frame-NNNNNN.pose.txt`` -> (4, 4) float64 camera-to-world.

    Four lines of four numbers, a rotation in the upper left 3x3 and ``0 0 0 1`` last (FormatError naming the
    line otherwise). A pose with inf or NaN (tracking lost in the original recording) is returned as all-NaN.
    """
    path = Path(path)
    rows, lines = parse_rows(path, [to_float] * 4)
    if len(rows) != 4:
        raise FormatError(path, int(lines[4]) if len(rows) > 4 else None,
                          f"expected 4 lines of 4 numbers (a 4x4 matrix), got {len(rows)} lines")
    T = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(T).all():
        return np.full((4, 4), np.nan)
    check_rotations(path, T[:3, :3], lines[:1])
    if np.abs(T[3] - [0, 0, 0, 1]).max() > ROTATION_TOLERANCE:
        last = " ".join(f"{v:g}" for v in T[3])
        raise FormatError(path, int(lines[3]), f"the last row of a pose is 0 0 0 1, not {last}")
    return T


def read_sevenscenes_intrinsics(path: str | Path) -> tuple[float, float, float, float]:
    """``camera-intrinsics.txt`` -> (fx, fy, cx, cy): a 3x3 matrix K, or the four numbers on one line."""
    path = Path(path)
    rows, lines = read_number_rows(path)
    values = [v for r in rows for v in r]
    if len(values) == 9 and all(len(r) == 3 for r in rows):
        K = np.asarray(values).reshape(3, 3)
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    elif len(values) == 4:
        fx, fy, cx, cy = values
    else:
        raise FormatError(path, int(lines[-1]) if len(lines) else None,
                          f"expected a 3x3 matrix or 'fx fy cx cy', got {len(values)} numbers")
    out = (float(fx), float(fy), float(cx), float(cy))
    for row, line in zip(rows, lines):
        if not np.isfinite(row).all():
            raise CalibrationError(f"{path}:{line}: intrinsics {out} are not all finite")
    return out


def _seq_name(seq: str | int) -> str:
    return f"seq-{int(seq):02d}" if str(seq).isdigit() else str(seq)


def _choose_seq(root: Path, seq: str | int | None) -> Path:
    if any(_COLOR.match(p.name) for p in root.iterdir()):
        if seq is not None and _seq_name(seq).lower() != root.name.lower():
            raise ConfigError(f"seq={seq!r} but {root} is itself a sequence folder")
        return root
    seqs = natural_sorted(p for p in root.iterdir() if p.is_dir() and _SEQ.match(p.name))
    if not seqs:
        raise SourceError(f"{root} has no seq-XX folders and no frame-NNNNNN.color.png|jpg files")
    if seq is None:
        return seqs[0]
    name = _seq_name(seq)
    for p in seqs:
        if p.name.lower() == name.lower():
            return p
    raise SourceError(f"{root} has no {name} (available: {', '.join(p.name for p in seqs)})")


def open_sevenscenes(path: str | Path, *, seq: str | int | None = None,
                     camera: Intrinsics | float | str | None = None,
                     frame_skip: int = 1, max_frames: int | None = None) -> ImageListSource:
    """Open a 7-Scenes sequence.

    Args:
        path: a scene folder (holding ``seq-XX/``) or a sequence folder.
        seq: ``"seq-01"`` or ``1``; default the first sequence of the scene.
        camera: override the intrinsics (:class:`Intrinsics`, focal length or ``--camera`` text; default: a
            ``camera.txt`` in the sequence folder, else ``camera-intrinsics.txt`` of the sequence or scene
            folder, else :data:`SEVENSCENES_NOMINAL`; no distortion).
        frame_skip, max_frames: keep every ``frame_skip``-th frame, at most ``max_frames``.

    Timestamps are frame number / 30 s. Pose files are read for the kept frames only; a missing or
    non-finite pose is a NaN row (``gt_poses`` is None when the sequence has no pose file at all).
    """
    root = require_path(path, "7-Scenes folder", kind="dir")
    folder = _choose_seq(root, seq)
    files = []
    for p in folder.iterdir():
        m = _COLOR.match(p.name)
        if m is not None:
            files.append((int(m.group(1)), p))
    if not files:
        raise SourceError(f"no images in {folder} (looked for frame-NNNNNN.color.png|jpg)")
    files.sort()
    numbers = np.array([n for n, _ in files], dtype=np.int64)
    if len(set(numbers.tolist())) != len(numbers):
        raise SourceError(f"{folder} has several colour images with the same frame number")
    keep = select(len(files), frame_skip, max_frames)
    paths = [files[i][1] for i in keep]
    w, h = image_size(paths[0])
    calib_txt = find_camera_txt(folder) if camera is None else None
    if calib_txt is not None:
        camera = read_camera_txt(calib_txt, w, h)
    if camera is None:
        fx, fy, cx, cy = SEVENSCENES_NOMINAL
        origin = f"the nominal 7-Scenes intrinsics {SEVENSCENES_NOMINAL}"
        for candidate in (folder / "camera-intrinsics.txt", folder.parent / "camera-intrinsics.txt"):
            if candidate.is_file():
                fx, fy, cx, cy = read_sevenscenes_intrinsics(candidate)
                origin = str(candidate)
                break
        where = f"{origin} with the images of {folder}"
        try:
            camera = Intrinsics(w, h, fx, fy, cx, cy)
        except CalibrationError as e:
            raise CalibrationError(f"{where}: {e}") from None
        camera.check_centred(where)
    cam = resolve_camera(camera, w, h, where=str(paths[0]))
    gt = np.full((len(keep), 4, 4), np.nan)
    any_pose = False
    for k, i in enumerate(keep):
        pose_file = folder / (files[i][1].name.split(".")[0] + ".pose.txt")
        if pose_file.is_file():
            gt[k] = read_pose_matrix(pose_file)
            any_pose = True
    if not any_pose and not any(folder.glob("frame-*.pose.txt")):
        gt = None
    return ImageListSource(name=f"7scenes/{folder.parent.name}/{folder.name}", camera=cam, paths=paths,
                           timestamps=numbers[keep] / SEVENSCENES_FPS, frame_ids=numbers[keep], gt_poses=gt)
