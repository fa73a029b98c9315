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
import hashlib
import os
import struct
from pathlib import Path

import numpy as np

from ..errors import shown
from .run_dir import file_sha256

__all__ = ["FINGERPRINT_COLUMNS", "changed", "frame_file", "frame_fingerprint", "image_size_of"]

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


_JPEG_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's frame header (SOFn), walking the segments before it."""
    pos = 2
    for _ in range(1000):  # a bound against garbage
        while pos < len(data) and data[pos] == 0xFF:
            pos += 1
        if pos + 3 > len(data):
            return None
        marker = data[pos]
        pos += 1
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            continue
        length = struct.unpack(">H", data[pos:pos + 2])[0]
        if marker in _JPEG_SOF and pos + 7 <= len(data):
            h, w = struct.unpack(">HH", data[pos + 3:pos + 7])
            return (int(w), int(h)) if w > 0 and h > 0 else None
        if length < 2:
            return None
        pos += length
    return None


def image_size_of(data: bytes) -> tuple[int, int]:
    """(width, height) of an encoded image in pixels: from a PNG's or JPEG's header, else decoded from memory
    (OpenCV never sees the file's name, which may not be UTF-8). ValueError when it is not an image."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 24:
        w, h = struct.unpack(">II", data[16:24])
        return int(w), int(h)
    if data[:2] == b"\xff\xd8":
        size = _jpeg_size(data)
        if size is not None:
            return size
    import cv2

    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if image is None:
        raise ValueError("not an image OpenCV can decode")
    return int(image.shape[1]), int(image.shape[0])


def _measure(source, path: Path, memo: bool) -> tuple[int, int, str]:
    """(width, height, SHA-256) of frame file ``path``: a video's decoded frame size and whole-file hash
    (streamed), an image file's header size and hash (read once)."""
    if getattr(source, "paths", None) is None:  # a video: the decoded frames' size
        cam = source.camera
        return int(cam.width), int(cam.height), _file_sha256(path) if memo else file_sha256(path)
    if memo:
        st = os.stat(path)
        return _image_measure(str(path), st.st_size, st.st_mtime_ns, st.st_ino)
    return _image_measure.__wrapped__(str(path), 0, 0, 0)


@functools.lru_cache(maxsize=1 << 16)
def _image_measure(path: str, size: int, mtime_ns: int, ino: int) -> tuple[int, int, str]:
    data = Path(path).read_bytes()
    w, h = image_size_of(data)
    return w, h, hashlib.sha256(data).hexdigest()


def frame_fingerprint(source, i: int) -> dict[str, str]:
    """``{"file", "width", "height", "sha256"}`` of frame ``i`` of ``source`` as text (empty values for a
    rendered source, or a file that cannot be read now)."""
    empty = dict.fromkeys(FINGERPRINT_COLUMNS, "")
    path = frame_file(source, i)
    if path is None:
        return empty
    try:
        w, h, sha = _measure(source, path, memo=True)
        return {"file": shown(path.name), "width": str(w), "height": str(h), "sha256": sha}
    except Exception:  # noqa: BLE001 - an unreadable file (the run skipped it): nothing to record
        return {**empty, "file": shown(path.name)}


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
    if recorded.get("file") and shown(path.name) != recorded["file"]:  # names as text, odd bytes as \xNN
        return f"it is read from {path} now, the run read {recorded['file']}"
    try:
        w, h, now = _measure(source, path, memo=False)  # read again, never from the memo: this is the check
    except Exception as e:  # noqa: BLE001
        return f"{path} cannot be read now ({e})"
    if (str(w), str(h)) != (str(recorded.get("width")), str(recorded.get("height"))):
        return f"{path} is {w}x{h} pixels, the run saw {recorded.get('width')}x{recorded.get('height')}"
    if now != sha:
        return f"{path} has other content than the run read (SHA-256 differs)"
    return None
