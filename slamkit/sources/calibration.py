"""``camera.txt``: a one-line calibration file beside the images, read by every file-based source.

Format: one data line ``fx fy cx cy [k1 k2 p1 p2 [k3]]`` (pixels; OpenCV radial-tangential distortion),
numbers separated by spaces or commas; ``#`` starts a comment; blank lines are ignored. It is the calibration
of the images as stored (distortion included). Precedence in every source: an explicit ``camera=``
(``--camera``, ``SlamConfig.camera``) first, then ``camera.txt``, then the dataset's own calibration, then
the documented guess.
"""

from __future__ import annotations

from pathlib import Path

from ..camera import Intrinsics
from ..errors import CalibrationError, ConfigError, FormatError

CAMERA_TXT = "camera.txt"


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
    camera of that size."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise FormatError(path, None, f"cannot be read ({e})") from None
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
    is none."""
    p = Path(path)
    if p.is_dir():
        p = p / CAMERA_TXT
    if not p.is_file():
        raise CalibrationError(f"{where}={str(path)!r}: no {CAMERA_TXT} there (give a run folder that holds one, a "
                               "camera.txt file, 'auto', or the numbers F or FX,FY,CX,CY[,K1,K2,P1,P2[,K3]])")
    return read_camera_txt(p, width, height)


def write_camera_txt(path: str | Path, camera: Intrinsics, comment: str = "") -> None:
    """Write ``camera`` as a ``camera.txt`` (``fx fy cx cy k1 k2 p1 p2 k3``), with ``#`` comment lines first."""
    lines = [f"# {line}" for line in comment.splitlines() if line.strip()]
    lines.append(" ".join(repr(float(v)) for v in (camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist)))
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
