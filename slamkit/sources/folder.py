"""A folder of images (any camera), plus the image-listing helpers every layout shares.

Files are taken in time order when their names are numbers (``0.05.png 0.1.png 0.15.png``: timestamps as
names, decimals included), else in *natural* order (``frame2`` before ``frame10``). Each frame's time comes
from what the frame is, never from its position among the frames that happened to be there or readable
(:func:`frame_times`): a name that is a decimal number is its time in seconds, an integer is a frame number
(time = number / fps), so a missing number or a file of another kind in the sequence shifts no other frame;
only names that are not numbers fall back to their place in the sorted list of image files (an image that
cannot be decoded keeps its place: it is skipped when read). Opening reads no pixel: the image size comes from
the PNG/JPEG header of the first file (a full decode only for other formats).
"""

from __future__ import annotations

import math
import re
import struct
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..camera import Intrinsics
from ..errors import CalibrationError, ConfigError, SourceError
from .base import ImageListSource, read_image, select
from .calibration import find_camera_txt, read_camera_txt
from .groundtruth import associate_nearest, read_tum_trajectory
from .textfiles import require_path

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".pnm")
"""Extensions (lower case) recognised as images when no glob pattern is given."""

_GLOB_CHARS = set("*?[")


def natural_key(name: str) -> tuple:
    """Sort key comparing runs of digits as numbers: ``frame2 < frame10``, case-insensitive otherwise."""
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in parts), name


def natural_sorted(paths: Iterable[Path]) -> list[Path]:
    """``paths`` sorted by :func:`natural_key` of their names."""
    return sorted(paths, key=lambda p: natural_key(p.name))


_NUMBERED = re.compile(r"^(.*?)(\d+(?:\.\d+)?)$")


def time_sorted(paths: Iterable[Path]) -> list[Path]:
    """``paths`` in the order of the numbers their names hold when every name is one prefix (possibly
    empty) followed by a decimal number (``0.05.png``, ``frame_1305031453.359684.jpg``: timestamps as names,
    ``0.1`` before ``0.15`` before ``0.2``), with :func:`natural_key` between equal numbers; otherwise
    :func:`natural_sorted` (which orders integer numbers the same way)."""
    paths = list(paths)
    numbered = [_NUMBERED.match(p.name[: len(p.name) - len(p.suffix)] if p.suffix else p.name) for p in paths]
    if (paths and all(m is not None for m in numbered) and len({m.group(1) for m in numbered}) == 1
            and any("." in m.group(2) for m in numbered)):
        order = sorted(range(len(paths)), key=lambda k: (float(numbered[k].group(2)), natural_key(paths[k].name)))
        return [paths[k] for k in order]
    return natural_sorted(paths)


def frame_times(paths: Sequence[Path], fps: float) -> tuple[np.ndarray, np.ndarray, str]:
    """(timestamps (N,) seconds, frame ids (N,), how) of image files in :func:`time_sorted` order, each from
    what the file is (its name), never from which other files are there.

    - every name one prefix followed by a number, no two numbers equal, one of them with a decimal point
      (``0.05.png``, ``frame_1305031453.359684.jpg``): the number is the time in seconds ("names as
      timestamps"); frame ids are the places in the list;
    - every name one prefix followed by an integer, no two equal (``000123.png``, ``frame-7.jpg``): the number is
      the frame number, the time ``number / fps`` ("names as frame numbers"), frame ids the numbers;
    - otherwise (names that are not numbers): the place in the sorted list of image files, which counts the
      files that cannot be decoded too, at the nominal ``fps`` ("places in natural order").
    """
    paths = list(paths)
    n = len(paths)
    numbered = [_NUMBERED.match(p.name[: len(p.name) - len(p.suffix)] if p.suffix else p.name) for p in paths]
    if n and all(m is not None for m in numbered) and len({m.group(1) for m in numbered}) == 1:
        text = [m.group(2) for m in numbered]
        if any("." in t for t in text):
            values = np.array([float(t) for t in text])
            if len(np.unique(values)) == n:
                return values, np.arange(n, dtype=np.int64), "names as timestamps"
        else:
            numbers = np.array([int(t) for t in text], dtype=np.int64)
            if len(np.unique(numbers)) == n:
                return numbers / fps, numbers, "names as frame numbers"
    return np.arange(n) / fps, np.arange(n, dtype=np.int64), "places in natural order"


def has_glob(text: str) -> bool:
    return any(c in _GLOB_CHARS for c in text)


def list_images(folder: str | Path, pattern: str | None = None,
                extensions: Iterable[str] = IMAGE_EXTENSIONS) -> list[Path]:
    """Image files of ``folder`` in time order (:func:`time_sorted`: numbers as names, decimals included),
    else natural order (not recursive).

    With ``pattern`` (a glob relative to ``folder``, e.g. ``"left_*.png"``) every matching file is taken;
    otherwise files whose extension is in ``extensions`` (case-insensitive). An empty result raises
    :class:`SourceError` saying which folder and which pattern or extensions were looked for.
    """
    folder = require_path(folder, "image folder", kind="dir")
    exts = tuple(e.lower() for e in extensions)
    if pattern is not None:
        files = [p for p in folder.glob(pattern) if p.is_file()]
        if not files:
            raise SourceError(f"no files in {folder} match the pattern {pattern!r}")
    else:
        files = [p for p in folder.iterdir() if p.suffix.lower() in exts and p.is_file()]
        if not files:
            raise SourceError(f"no images in {folder} (looked for files ending in {', '.join(exts)})")
    return time_sorted(files)


def _png_size(head: bytes) -> tuple[int, int] | None:
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and len(head) >= 24:
        w, h = struct.unpack(">II", head[16:24])
        return int(w), int(h)
    return None


def _jpeg_size(path: Path) -> tuple[int, int] | None:
    sof = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
    with open(path, "rb") as f:
        if f.read(2) != b"\xff\xd8":
            return None
        for _ in range(1000):  # segments before the frame header; a bound against garbage
            b = f.read(1)
            while b == b"\xff":
                b = f.read(1)
            if not b:
                return None
            marker = b[0]
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                continue
            seg = f.read(2)
            if len(seg) < 2:
                return None
            length = struct.unpack(">H", seg)[0]
            if marker in sof:
                data = f.read(5)
                if len(data) < 5:
                    return None
                h, w = struct.unpack(">HH", data[1:5])
                return (int(w), int(h)) if w > 0 and h > 0 else None
            if length < 2:
                return None
            f.seek(length - 2, 1)
    return None


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file in pixels, from the PNG/JPEG header without decoding the pixels.

    Other formats, or headers that cannot be parsed, are decoded with OpenCV (ImageReadError names the file).
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(32)
        size = _png_size(head) or (_jpeg_size(path) if head[:2] == b"\xff\xd8" else None)
    except OSError:
        size = None
    if size is not None and size[0] > 0 and size[1] > 0:
        return size
    image = read_image(path)
    return int(image.shape[1]), int(image.shape[0])


def resolve_camera(camera: Intrinsics | float | str | None, width: int, height: int,
                   default: Intrinsics | None = None, where: str = "images") -> Intrinsics:
    """The intrinsics of ``width`` x ``height`` images from what the user gave.

    ``camera`` may be an :class:`Intrinsics` (must be for that size: CalibrationError otherwise), a focal
    length in pixels (principal point at the centre, no distortion), a camera text as ``--camera`` takes
    it (``"F"``, ``"FX,FY,CX,CY[,K1,K2,P1,P2[,K3]]"``, :meth:`Intrinsics.parse`), or None for ``default``
    when given, else ``Intrinsics.from_focal(width, height)`` (focal 1.2 x max(width, height)). Distortion
    that no lens produces over the image is refused (:meth:`Intrinsics.check_distortion`).
    """
    if camera is None:
        camera = default if default is not None else Intrinsics.from_focal(width, height)
    elif isinstance(camera, str):
        camera = Intrinsics.parse(camera, width, height)
    elif isinstance(camera, (int, float)) and not isinstance(camera, bool):
        camera = Intrinsics.from_focal(width, height, float(camera))
    elif not isinstance(camera, Intrinsics):
        raise ConfigError(f"camera must be Intrinsics, a focal length in pixels or None (got {camera!r})")
    if (camera.width, camera.height) != (int(width), int(height)):
        raise CalibrationError(f"{where}: images are {width}x{height} but the intrinsics are for "
                               f"{camera.width}x{camera.height}")
    camera.check_distortion(where)
    return camera


def check_fps(fps: float) -> float:
    try:
        value = float(fps)
    except (TypeError, ValueError):
        raise ConfigError(f"fps must be a positive number (got {fps!r})") from None
    if not math.isfinite(value) or value <= 0:
        raise ConfigError(f"fps must be a positive number (got {fps!r})")
    return value


def open_folder(path: str | Path, *, camera: Intrinsics | float | str | None = None, fps: float = 30.0,
                pattern: str | None = None, groundtruth: str | Path | None = None, max_dt: float = 0.02,
                frame_skip: int = 1, max_frames: int | None = None) -> ImageListSource:
    """Open a folder of images as a frame source.

    Args:
        path: the folder. Images are files with an extension of :data:`IMAGE_EXTENSIONS`, or the files
            matching ``pattern``, in the order of :func:`list_images` (time order for names that are numbers,
            else natural order).
        camera: :class:`Intrinsics`, a focal length in pixels, a ``--camera`` text, or None: then the
            folder's ``camera.txt`` when there is one (:mod:`~slamkit.sources.calibration`), else **a
            guess**: ``Intrinsics.from_focal(w, h)`` (focal 1.2 x max(w, h), principal point at the centre,
            no distortion) with (w, h) read off the first image, which ``Slam`` replaces by an estimate
            (:mod:`slamkit.stages.self_calibration`).
        fps: frame rate. Each frame's time comes from its name (:func:`frame_times`): a decimal number is
            its time in seconds (``fps`` unused), an integer its frame number (time = number / ``fps``),
            other names their place among the folder's image files (time = place / ``fps``, files that cannot
            be decoded counted). A missing number or a file of another kind shifts no other frame's time.
        pattern: optional glob relative to the folder (``"*.png"``, ``"cam0/*.jpg"``).
        groundtruth: optional TUM-format file (``timestamp tx ty tz qx qy qz qw``, camera-to-world) in the
            frames' time base (above); each frame takes the pose nearest in time within ``max_dt``
            seconds, NaN rows where none. Without it there is no ground truth.
        frame_skip, max_frames: keep every ``frame_skip``-th image, at most ``max_frames``.
    """
    folder = require_path(path, "image folder", kind="dir")
    fps = check_fps(fps)
    files = list_images(folder, pattern)
    keep = select(len(files), frame_skip, max_frames)
    w, h = image_size(files[0])
    calib = find_camera_txt(folder) if camera is None else None
    if calib is not None:
        camera = read_camera_txt(calib, w, h)
    cam = resolve_camera(camera, w, h, where=str(files[0]))
    times, ids, _ = frame_times(files, fps)
    timestamps = times[keep]
    gt = None
    if groundtruth is not None:
        gt_t, gt_poses = read_tum_trajectory(groundtruth)
        match = associate_nearest(timestamps, gt_t, max_dt)
        gt = np.full((len(keep), 4, 4), np.nan)
        gt[match >= 0] = gt_poses[match[match >= 0]]
    return ImageListSource(name=f"folder/{folder.name}", camera=cam, paths=[files[i] for i in keep],
                           timestamps=timestamps, frame_ids=ids[keep], gt_poses=gt)
