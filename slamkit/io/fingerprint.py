"""Fingerprints of the files a run's frames were read from: recorded when the run is saved, checked by export.

A run folder holds no image: ``slamkit export`` reads the frames again from the source, so a source folder
changed after the run (an image replaced, renamed into another's place, re-encoded at another size) would
pair the run's poses with other pictures. Each row of the run's ``frames.csv`` therefore records the frame's
file (``file``: its name), its image size (``width``, ``height`` in pixels, from the file's header) and the
SHA-256 of the file's bytes (``sha256``). For a video, the file is the video itself (size of the decoded
frames, one SHA-256 for the file). A synthetic source (rendered) has no file: the columns stay empty.

Hashes are memoised per (path, size, modification time, inode), so saving a run again (an interrupted run,
a resume) does not read every file again.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

from .run_dir import file_sha256

__all__ = ["FINGERPRINT_COLUMNS", "frame_file", "frame_fingerprint", "changed"]

FINGERPRINT_COLUMNS = ("file", "width", "height", "sha256")


@functools.lru_cache(maxsize=1 << 16)
def _sha256(path: str, size: int, mtime_ns: int, ino: int) -> str:
    return file_sha256(Path(path))


def _file_sha256(path: Path) -> str:
    st = os.stat(path)
    return _sha256(str(path), st.st_size, st.st_mtime_ns, st.st_ino)


def frame_file(source, i: int) -> Path | None:
    """The file frame ``i`` of ``source`` is read from: its image file, or the video file; None for a
    rendered source."""
    paths = getattr(source, "paths", None)
    if paths is not None:
        return Path(paths[i]) if 0 <= i < len(paths) else None
    path = getattr(source, "path", None)
    return Path(path) if isinstance(path, (str, os.PathLike)) and Path(path).is_file() else None


def _size(source, path: Path) -> tuple[int, int]:
    if getattr(source, "paths", None) is None:  # a video: the decoded frames' size
        cam = source.camera
        return int(cam.width), int(cam.height)
    from ..sources.folder import image_size  # the header only

    return image_size(path)


def frame_fingerprint(source, i: int) -> dict[str, str]:
    """``{"file", "width", "height", "sha256"}`` of frame ``i`` of ``source`` as text (empty values for a
    rendered source, or a file that cannot be read now)."""
    empty = dict.fromkeys(FINGERPRINT_COLUMNS, "")
    path = frame_file(source, i)
    if path is None:
        return empty
    try:
        w, h = _size(source, path)
        return {"file": path.name, "width": str(w), "height": str(h), "sha256": _file_sha256(path)}
    except Exception:  # noqa: BLE001 - an unreadable file (the run skipped it): nothing to record
        return {**empty, "file": path.name}


def changed(recorded: dict, source, i: int) -> str | None:
    """Why frame ``i`` of ``source`` is not the frame whose fingerprint ``recorded`` (a ``frames.csv`` row)
    holds, or None when it is the same (or nothing was recorded: a run saved before fingerprints)."""
    sha = (recorded.get("sha256") or "").strip()
    if not sha:
        return None
    path = frame_file(source, i)
    if path is None:
        return "the source has no file for it now"
    if not path.is_file():
        return f"{path} is missing"
    if recorded.get("file") and path.name != recorded["file"]:
        return f"it is read from {path} now, the run read {recorded['file']}"
    try:
        w, h = _size(source, path)
        now = file_sha256(path)  # read again, never from the memo: this is the check
    except Exception as e:  # noqa: BLE001
        return f"{path} cannot be read now ({e})"
    if (str(w), str(h)) != (str(recorded.get("width")), str(recorded.get("height"))):
        return f"{path} is {w}x{h} pixels, the run saw {recorded.get('width')}x{recorded.get('height')}"
    if now != sha:
        return f"{path} has other content than the run read (SHA-256 differs)"
    return None
