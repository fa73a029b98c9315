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
from ..geometry import pose_from_tum
from .base import ImageListSource, select
from .folder import image_size, resolve_camera
from .textfiles import check_increasing, parse_float_rows, parse_rows, require_path, to_float, to_str

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


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM trajectory file -> (timestamps (N,) float64 s, poses (N, 4, 4) float64).

    Lines are ``timestamp tx ty tz qx qy qz qw`` (camera-to-world, quaternion normalised here); values must
    be finite, quaternions non-zero and timestamps strictly increasing (FormatError naming the line).
    """
    path = Path(path)
    rows, lines = parse_float_rows(path, 8, increasing=0, return_lines=True,
                                   what=("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"))
    norms = np.linalg.norm(rows[:, 4:8], axis=1)
    bad = norms < 1e-6
    if bad.any():
        raise FormatError(path, int(lines[np.argmax(bad)]), "quaternion (qx qy qz qw) has zero norm")
    if len(rows) == 0:
        return np.zeros(0), np.zeros((0, 4, 4))
    return rows[:, 0].copy(), pose_from_tum(rows[:, 1:4], rows[:, 4:8])


def associate_nearest(t_query: np.ndarray, t_ref: np.ndarray, max_dt: float) -> np.ndarray:
    """For each query time, the index of the nearest reference time within ``max_dt`` seconds, else -1.

    ``t_ref`` must be sorted ascending. Returns (len(t_query),) int64.
    """
    t_query = np.asarray(t_query, dtype=np.float64).reshape(-1)
    t_ref = np.asarray(t_ref, dtype=np.float64).reshape(-1)
    out = np.full(len(t_query), -1, dtype=np.int64)
    if len(t_ref) == 0 or len(t_query) == 0:
        return out
    right = np.clip(np.searchsorted(t_ref, t_query), 0, len(t_ref) - 1)
    left = np.clip(right - 1, 0, len(t_ref) - 1)
    pick = np.where(np.abs(t_ref[left] - t_query) <= np.abs(t_ref[right] - t_query), left, right)
    ok = np.abs(t_ref[pick] - t_query) <= max_dt
    out[ok] = pick[ok]
    return out


def _camera(folder: Path, calibration: str | Intrinsics | None) -> Intrinsics:
    if isinstance(calibration, Intrinsics):
        return calibration
    if calibration is None:
        name = calibration_from_name(folder)
        if name is None:
            raise CalibrationError(
                f"{folder}: cannot tell the TUM sensor (freiburg1/2/3) from the folder name; give the intrinsics with "
                "--camera fx,fy,cx,cy on the command line (Python: calibration='fr1', 'fr2', 'fr3' or an "
                "Intrinsics), or rename the folder to include freiburg1, freiburg2 or freiburg3")
        return TUM_CALIBRATIONS[name]
    return tum_calibration(calibration)


def open_tum(path: str | Path, *, calibration: str | Intrinsics | None = None, max_dt: float = 0.02,
             min_gt_fraction: float = 0.5, frame_skip: int = 1,
             max_frames: int | None = None) -> ImageListSource:
    """Open a TUM RGB-D sequence folder (the one holding ``rgb.txt``).

    Args:
        calibration: ``"fr1"``/``"fr2"``/``"fr3"``, an :class:`Intrinsics`, or None to choose from the
            folder name (``freiburg1``, ``fr1``...; CalibrationError when it does not say).
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
    cam = resolve_camera(_camera(folder, calibration), w, h, where=str(paths[keep[0]]))
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
