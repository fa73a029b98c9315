"""``camera.txt``: a one-line calibration file beside the images, read by every file-based source.

Format: one data line ``fx fy cx cy [k1 k2 p1 p2 [k3]]`` (pixels; OpenCV radial-tangential distortion),
numbers separated by spaces or commas; ``#`` starts a comment; blank lines are ignored. It is the calibration
of the images as stored (distortion included); a comment line ``# image size: WxH`` (runs write it) says
which images: images of another size are then refused, naming both sizes. Precedence in every source: an
explicit ``camera=`` (``--camera``, ``SlamConfig.camera``) first, then ``camera.txt``, then the dataset's own
calibration, then the documented guess.
"""

from __future__ import annotations

import re
from pathlib import Path

from ..camera import Intrinsics
from ..errors import CalibrationError, ConfigError, FormatError

CAMERA_TXT = "camera.txt"

_SIZE = re.compile(r"^\s*#\s*image size\s*:?\s*(\d+)\s*[x\u00d7]\s*(\d+)\b", re.I)


def find_camera_txt(*folders: str | Path) -> Path | None:
    """The first ``camera.txt`` in ``folders`` (in the order given), or None."""
    for folder in folders:
        candidate = Path(folder) / CAMERA_TXT
        if candidate.is_file():
            return candidate
    return None


def read_camera_txt(path: str | Path, width: int, height: int) -> Intrinsics:
    """The intrinsics of ``width`` x ``height`` images from a ``camera.txt``; FormatError naming the file and
    line for anything but one line of 4, 8 or 9 numbers, CalibrationError for values that cannot be a
    camera of that size (another recorded image size, a principal point outside, distortion no lens
    produces)."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise FormatError(path, None, f"cannot be read ({e})") from None
    for k, line in enumerate(lines, start=1):
        m = _SIZE.match(line)
        if m is not None and (int(m.group(1)), int(m.group(2))) != (int(width), int(height)):
            raise CalibrationError(f"{path}:{k}: the calibration is for {m.group(1)}x{m.group(2)} images but the "
                                   f"images are {width}x{height}; use a calibration of this camera at this size")
    data = [(k, line.split("#", 1)[0].strip()) for k, line in enumerate(lines, start=1)]
    data = [(k, text) for k, text in data if text]
    if len(data) != 1:
        raise FormatError(path, data[1][0] if len(data) > 1 else None,
                          "needs exactly one line 'fx fy cx cy [k1 k2 p1 p2 [k3]]'")
    line, text = data[0]
    if len(text.replace(",", " ").split()) == 1:
        raise FormatError(path, line, "needs fx fy cx cy [k1 k2 p1 p2 [k3]] (4, 8 or 9 numbers), got 1")
    try:
        return Intrinsics.parse(text, width, height, where=f"{path}:{line}")
    except ConfigError as e:
        raise FormatError(path, line, str(e).split(": ", 1)[-1]) from None


def camera_from_path(path: str | Path, width: int, height: int, where: str = "camera") -> Intrinsics:
    """The intrinsics in a ``camera.txt``, given as the file or as the folder holding it (a run folder: runs
    write the camera they used or estimated there); CalibrationError naming ``where`` and the path when there
    is none, when it records another image size, or (a file without the size) when its principal point is
    far from the centre of ``width`` x ``height`` images (:meth:`Intrinsics.check_centred`)."""
    p = Path(path)
    if p.is_dir():
        p = p / CAMERA_TXT
    if not p.is_file():
        raise CalibrationError(f"{where}={str(path)!r}: no {CAMERA_TXT} there (give a run folder that holds one, a "
                               "camera.txt file, 'auto', or the numbers F or FX,FY,CX,CY[,K1,K2,P1,P2[,K3]])")
    camera = read_camera_txt(p, width, height)
    if not has_size(p):  # written before runs recorded the size: the principal point tells a size far off
        camera.check_centred(where=f"{where}={str(path)!r} ({p})")
    return camera


def has_size(path: str | Path) -> bool:
    """Whether a ``camera.txt`` records the image size (``# image size: WxH``)."""
    try:
        return any(_SIZE.match(line) for line in Path(path).read_text(encoding="utf-8").splitlines())
    except (OSError, UnicodeDecodeError):
        return False


def write_camera_txt(path: str | Path, camera: Intrinsics, comment: str = "") -> None:
    """Write ``camera`` as a ``camera.txt`` (``fx fy cx cy k1 k2 p1 p2 k3``), with ``#`` comment lines first and
    the image size it is for (``# image size: WxH``)."""
    lines = [f"# {line}" for line in comment.splitlines() if line.strip()]
    lines.append(f"# image size: {camera.width}x{camera.height}")
    lines.append(" ".join(repr(float(v)) for v in (camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist)))
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
