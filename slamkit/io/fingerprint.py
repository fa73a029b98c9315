"""Fingerprints of what a run's frames were read from: measured when each frame is read, checked by export
and resume.

A run folder holds no image: ``slamkit export`` reads the frames again from the source, and ``--resume``
continues on it, so a source changed during or after the run (an image replaced, renamed into another's place,
re-encoded at another size, another folder of the same names) would pair the run's poses with other pictures.
The source measures each frame as it reads it (:class:`~slamkit.types.Fingerprint`, issue 50: the bytes are in
memory then, hashing them costs a fraction of a millisecond); the pipeline keeps it in the frame's
:class:`~slamkit.state.FrameRecord`, the session saves it, and each row of ``frames.csv`` holds it: ``file``
(the name), ``bytes`` (its size), ``width``, ``height`` (pixels of the decoded image) and ``sha256`` (of the
file's bytes). For a video, ``file`` and ``bytes`` are the video file's and ``sha256`` is that of the decoded
frame's pixels, so each frame is proven on its own. A rendered source has no file: the columns stay empty.
Nothing is hashed when the run is saved: a file changed since it was read is not recorded in its new state.
"""

from __future__ import annotations

import hashlib
import os
import struct
from pathlib import Path

import numpy as np

from ..errors import shown
from ..types import Fingerprint

__all__ = ["FINGERPRINT_COLUMNS", "MAX_NAMED", "also_changed", "changed", "csv_fields", "frame_file", "image_size_of",
           "measure"]

FINGERPRINT_COLUMNS = ("file", "bytes", "width", "height", "sha256")


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


def measure(source, i: int) -> Fingerprint | None:
    """Frame ``i`` of ``source`` as it is now, measured as the run measured it when it read it: an image file's
    bytes read and hashed (its size from the header: nothing decoded); any other frame (a video's) read from the
    source and its own fingerprint taken. None when the source says nothing of its frames (rendered). Raises
    OSError / ValueError / :class:`~slamkit.errors.ImageReadError` when the frame cannot be read now."""
    paths = getattr(source, "paths", None)
    if paths is not None:
        path = Path(paths[i])
        data = path.read_bytes()
        w, h = image_size_of(data)
        return Fingerprint(shown(path.name), len(data), w, h, hashlib.sha256(data).hexdigest())
    return source[i].fingerprint


def csv_fields(record, source=None, i: int | None = None) -> dict[str, str]:
    """``frames.csv``'s fingerprint columns of a :class:`~slamkit.state.FrameRecord` as text: what was measured
    when the frame was read; for a frame without one (unreadable, or a session of an older slamkit) only the
    name of its file in ``source`` (frame ``i``), never a hash of the file as it is at saving time."""
    fp = getattr(record, "fingerprint", None)
    if fp is not None:
        return {"file": fp.file, "bytes": str(fp.bytes), "width": str(fp.width), "height": str(fp.height),
                "sha256": fp.sha256}
    out = dict.fromkeys(FINGERPRINT_COLUMNS, "")
    path = frame_file(source, i) if source is not None and i is not None else None
    if path is not None:
        out["file"] = shown(path.name)
    return out


def changed(recorded: dict | Fingerprint, source, i: int, now: Fingerprint | None = None) -> str | None:
    """Why frame ``i`` of ``source`` is not the frame whose fingerprint ``recorded`` (a ``frames.csv`` row, or a
    :class:`~slamkit.types.Fingerprint`) holds, or None when it is the same (or nothing was recorded: a run saved
    before fingerprints). ``now``: the frame's fingerprint already measured (:func:`measure`), else measured here,
    from the file (never from a cache: this is the check)."""
    if isinstance(recorded, Fingerprint):
        recorded = {"file": recorded.file, "bytes": str(recorded.bytes), "width": str(recorded.width),
                    "height": str(recorded.height), "sha256": recorded.sha256}
    sha = (recorded.get("sha256") or "").strip()
    if not sha:
        return None
    path = frame_file(source, i)
    video = getattr(source, "paths", None) is None
    if path is not None and not path.is_file():
        return f"{path} is missing"
    if path is not None and recorded.get("file") and shown(path.name) != recorded["file"]:  # odd bytes as \xNN
        return f"it is read from {path} now, the run read {recorded['file']}"
    size = str(recorded.get("bytes") or "").strip()
    if video and not size and now is None and path is not None:  # before issue 50: the video file's SHA-256
        from .run_dir import file_sha256

        try:
            same = file_sha256(path) == sha
        except OSError as e:
            return f"{path} cannot be read now ({e.strerror or e})"
        return None if same else f"{path} has other content than the run read (SHA-256 differs)"
    try:
        now = now if now is not None else measure(source, i)
    except Exception as e:  # noqa: BLE001 - ImageReadError, OSError: named
        return f"{path if path is not None else 'it'} cannot be read now ({e})"
    if now is None:
        return "the source has no file for it now"
    if path is None and recorded.get("file") and now.file != recorded["file"]:
        return f"it is read from {now.file} now, the run read {recorded['file']}"
    path = path if path is not None else now.file
    where = f"frame {int(source.frame_ids[i])} of {path}" if video else str(path)
    if (str(now.width), str(now.height)) != (str(recorded.get("width")), str(recorded.get("height"))):
        return (f"{where} is {now.width}x{now.height} pixels, the run saw "
                f"{recorded.get('width')}x{recorded.get('height')}")
    other_size = bool(size) and size != "-1" and now.bytes >= 0 and str(now.bytes) != size
    if now.sha256 != sha or other_size:
        sizes = f"; {now.bytes} bytes, the run read {size}" if other_size else ""
        return f"{where} has other content than the run read (SHA-256 differs{sizes})"
    return None


MAX_NAMED = 5
"""Frames named one by one when several differ from their fingerprints (the rest are counted)."""


def also_changed(rest: list[tuple[object, str]]) -> str:
    """"; so are frames 7 (b.png), 9 (c.png) and 3 more" for the changed frames after the first, given as
    (frame index, file name) pairs; "" when there are none."""
    if not rest:
        return ""
    named = ", ".join(f"{index} ({name or '?'})" for index, name in rest[:MAX_NAMED])
    more = f" and {len(rest) - MAX_NAMED} more" if len(rest) > MAX_NAMED else ""
    return f"; so are frame{'s' if len(rest) > 1 else ''} {named}{more}"
