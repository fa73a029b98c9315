"""TUM RGB-D benchmark sequences: ``rgb.txt`` + ``rgb/*.png`` + ``groundtruth.txt``.

Layout (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    rgbd_dataset_freiburg1_desk/
        rgb.txt            # "timestamp filename" per image, '#' comments
        rgb/1305031453.359684.png
        groundtruth.txt    # "timestamp tx ty tz qx qy qz qw", camera-to-world, motion capture at 100 Hz

Image and ground-truth clocks differ: each image takes the ground-truth pose nearest in time within
``max_dt`` seconds (no interpolation); images with none get NaN rows in ``gt_poses``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..camera import Intrinsics
from ..errors import AssociationError, CalibrationError, ConfigError, FormatError, SourceError
from .base import ImageListSource, select
from .calibration import find_camera_txt, read_camera_txt
from .folder import image_size, resolve_camera
from .groundtruth import associate_nearest, read_tum_trajectory
from .textfiles import check_increasing, parse_rows, require_path, to_float, to_str

TUM_CALIBRATIONS: dict[str, Intrinsics] = {
    "fr1": Intrinsics(640, 480, 517.306408, 516.469215, 318.643040, 255.313989,
                      (0.262383, -0.953104, -0.005358, 0.002628, 1.163314)),
    "fr2": Intrinsics(640, 480, 520.908620, 521.007327, 325.141442, 249.701764,
                      (0.231222, -0.784899, -0.003257, -0.000105, 0.917205)),
    "fr3": Intrinsics(640, 480, 535.4, 539.2, 320.1, 247.6),
}
"""Colour-camera calibrations of the TUM RGB-D benchmark (640x480, pinhole + OpenCV k1 k2 p1 p2 k3).
fr3 images are already undistorted (zero distortion)."""

_FREIBURG = re.compile(r"(?:freiburg|(?<![a-z])fr)_?([123])(?!\d)")


def tum_calibration(name: str) -> Intrinsics:
    """Built-in calibration ``"fr1"``, ``"fr2"`` or ``"fr3"`` (also ``"freiburg1"``...)."""
    m = _FREIBURG.fullmatch(str(name).strip().lower())
    if m is None:
        raise ConfigError(f"calibration must be 'fr1', 'fr2', 'fr3' or Intrinsics (got {name!r})")
    return TUM_CALIBRATIONS[f"fr{m.group(1)}"]


def calibration_from_name(path: str | Path) -> str | None:
    """``"fr1"``/``"fr2"``/``"fr3"`` when the folder name (or its parent's) says which sensor, else None."""
    p = Path(path)
    for name in (p.name, p.parent.name):
        m = _FREIBURG.search(name.lower())
        if m is not None:
            return f"fr{m.group(1)}"
    return None


def read_rgb_list(path: str | Path) -> tuple[np.ndarray, list[str], np.ndarray]:
    """``rgb.txt`` -> (timestamps (N,) float64 seconds, file names relative to its folder, 1-based lines).

    Timestamps must be finite and strictly increasing (FormatError naming the line).
    """
    path = Path(path)
    rows, lines = parse_rows(path, [to_float, to_str], what=("timestamp", "filename"))
    t = np.asarray([r[0] for r in rows], dtype=np.float64)
    bad = ~np.isfinite(t)
    if bad.any():
        raise FormatError(path, int(lines[np.argmax(bad)]), "timestamp is not finite")
    check_increasing(path, t, lines)
    return t, [r[1] for r in rows], lines


def _is_camera_text(text: str) -> bool:
    """True for a ``--camera`` text of numbers (``"F"``, ``"FX,FY,CX,CY,..."``), False for a sensor name."""
    try:
        [float(f) for f in text.translate(str.maketrans(",()[]", "     ")).split()]
    except ValueError:
        return False
    return bool(text.strip())


def _camera(folder: Path, calibration: str | float | Intrinsics | None, width: int, height: int,
            image_dir: Path) -> Intrinsics:
    """The calibration given (sensor name, Intrinsics, focal length or ``--camera`` text), else a
    ``camera.txt`` in the sequence or image folder, else the sensor the folder name says."""
    if isinstance(calibration, Intrinsics):
        return calibration
    if isinstance(calibration, (int, float)) or (isinstance(calibration, str) and _is_camera_text(calibration)):
        return resolve_camera(calibration, width, height)
    if calibration is None:
        calib = find_camera_txt(folder, image_dir)
        if calib is not None:
            return read_camera_txt(calib, width, height)
        name = calibration_from_name(folder)
        if name is None:
            raise CalibrationError(
                f"{folder}: cannot tell the TUM sensor (freiburg1/2/3) from the folder name; give the intrinsics with "
                "--camera fx,fy,cx,cy on the command line (Python: calibration='fr1', 'fr2', 'fr3' or an "
                "Intrinsics), or rename the folder to include freiburg1, freiburg2 or freiburg3")
        return TUM_CALIBRATIONS[name]
    return tum_calibration(calibration)


def open_tum(path: str | Path, *, calibration: str | float | Intrinsics | None = None, max_dt: float = 0.02,
             min_gt_fraction: float = 0.5, frame_skip: int = 1,
             max_frames: int | None = None) -> ImageListSource:
    """Open a TUM RGB-D sequence folder (the one holding ``rgb.txt``).

    Args:
        calibration: ``"fr1"``/``"fr2"``/``"fr3"``, an :class:`Intrinsics`, a focal length or a ``--camera``
            text (``"FX,FY,CX,CY[,K1,K2,P1,P2[,K3]]"``), or None: then a ``camera.txt`` beside ``rgb.txt`` or
            the images (:mod:`~slamkit.sources.calibration`), else the sensor the folder name says
            (``freiburg1``, ``fr1``...; CalibrationError when it does not say).
        max_dt: largest |image time - ground-truth time| in seconds for an image to get a pose.
        min_gt_fraction: when ``groundtruth.txt`` exists but fewer than this fraction of the listed images
            get a pose, raise AssociationError (wrong ground-truth file?). Without ``groundtruth.txt``
            ``gt_poses`` is None.
        frame_skip, max_frames: keep every ``frame_skip``-th image of ``rgb.txt``, at most ``max_frames``.

    Images listed in ``rgb.txt`` must exist (SourceError listing the missing ones); they are decoded on
    access only.
    """
    folder = require_path(path, "TUM sequence folder", kind="dir")
    rgb_txt = require_path(folder / "rgb.txt", "TUM image list")
    t, names, _ = read_rgb_list(rgb_txt)
    if len(t) == 0:
        raise SourceError(f"{rgb_txt} lists no images")
    if max_dt < 0:
        raise ConfigError(f"max_dt must be >= 0 seconds (got {max_dt})")
    if not 0.0 <= min_gt_fraction <= 1.0:
        raise ConfigError(f"min_gt_fraction must be in [0, 1] (got {min_gt_fraction})")
    paths = [folder / n for n in names]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        raise SourceError(f"{rgb_txt} lists {len(missing)} images that do not exist: "
                          f"{', '.join(missing[:3])}{more}")
    keep = select(len(t), frame_skip, max_frames)
    w, h = image_size(paths[keep[0]])
    cam = resolve_camera(_camera(folder, calibration, w, h, paths[keep[0]].parent), w, h,
                         where=str(paths[keep[0]]))
    gt = None
    gt_file = folder / "groundtruth.txt"
    if gt_file.is_file():
        gt_t, gt_poses = read_tum_trajectory(gt_file)
        match = associate_nearest(t, gt_t, max_dt)
        fraction = float(np.mean(match >= 0))
        if fraction < min_gt_fraction:
            span = f"{gt_t[0]:.3f}..{gt_t[-1]:.3f} s" if len(gt_t) else "no poses"
            raise AssociationError(
                f"only {fraction:.0%} of the images in {rgb_txt} ({t[0]:.3f}..{t[-1]:.3f} s) have a "
                f"ground-truth pose in {gt_file} ({span}) within {max_dt} s; need {min_gt_fraction:.0%} "
                "(is it the ground truth of this sequence?)")
        m = match[keep]
        gt = np.full((len(keep), 4, 4), np.nan)
        gt[m >= 0] = gt_poses[m[m >= 0]]
    return ImageListSource(name=f"tum/{folder.name}", camera=cam, paths=[paths[i] for i in keep],
                           timestamps=t[keep], frame_ids=keep, gt_poses=gt)
