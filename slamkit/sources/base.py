"""The frame-source interface and the shared image-list implementation.

A source is a random-access, lazily-read sequence of :class:`~slamkit.types.Frame`. Frame skip and max
frames are applied when the source is opened, so ``len(source)`` is the number of frames SLAM will see.
Images are decoded on access only: memory does not grow with the length of the sequence.
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from ..camera import Intrinsics
from ..errors import C_INT_MAX, ConfigError, ImageReadError, SourceError, shown
from ..types import Fingerprint, Frame, Trajectory

CAMERA_IN_SPEC = "camera= cannot be given for synthetic sources (their camera is part of the spec)"
"""Why given intrinsics are refused for a source whose camera is part of its spec (``FrameSource.camera_in_spec``)."""


def check_skip_and_max(frame_skip: int, max_frames: int | None) -> None:
    if not 1 <= int(frame_skip) <= C_INT_MAX:
        raise ConfigError(f"frame_skip must be >= 1 and <= {C_INT_MAX} (got {frame_skip})")
    if max_frames is not None and not 1 <= int(max_frames) <= C_INT_MAX:
        raise ConfigError(f"max_frames must be >= 1 and <= {C_INT_MAX}, or None (got {max_frames})")


def select(n: int, frame_skip: int = 1, max_frames: int | None = None, start: int = 0) -> np.ndarray:
    """Indices kept from ``n`` items: every ``frame_skip``-th from ``start``, at most ``max_frames``."""
    check_skip_and_max(frame_skip, max_frames)
    idx = np.arange(int(start), n, int(frame_skip))
    return idx[:max_frames] if max_frames is not None else idx


class FrameSource:
    """Abstract frame source. Subclasses implement ``__len__``, ``_read(i)`` and set ``camera``/``name``.

    Attributes:
        name: short human-readable name (dataset and sequence).
        camera: intrinsics of every frame (of the images as delivered, distortion included).
        timestamps: (N,) float64 seconds of the delivered frames.
        frame_ids: (N,) int64 dataset frame numbers of the delivered frames.
        gt_poses: (N, 4, 4) camera-to-world ground truth or None; rows are NaN where a frame has none.
    """

    name: str
    camera: Intrinsics
    timestamps: np.ndarray
    frame_ids: np.ndarray
    gt_poses: np.ndarray | None = None
    camera_in_spec: bool = False
    """The camera is part of the source's definition (rendered sources): given intrinsics are refused
    (:data:`CAMERA_IN_SPEC`), by :func:`~slamkit.sources.open_source` and by every run on the source alike."""

    def __len__(self) -> int:
        return len(self.timestamps)

    def _read(self, i: int) -> tuple[np.ndarray, Path | None]:
        """Decode delivered frame ``i``: returns (image uint8 HxW or HxWx3 BGR, path or None)."""
        raise NotImplementedError

    def _read_fingerprinted(self, i: int) -> tuple[np.ndarray, Path | None, Fingerprint | None]:
        """:meth:`_read` and the frame's :class:`~slamkit.types.Fingerprint`, measured on what was read (None:
        this source does not say; sources of files and videos override it)."""
        image, path = self._read(i)
        return image, path, None

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for {self.name} with {n} frames")
        i = i % n
        image, path, fingerprint = self._read_fingerprinted(i)
        frame_id = int(self.frame_ids[i])
        check_frame_size(image.shape[1], image.shape[0], path or f"{self.name}, frame {frame_id}")
        gray, color = to_gray_and_rgb(image)
        self.camera.check_image(gray.shape, where=f"{path if path is not None else self.name}, frame {frame_id}")
        gt = None
        if self.gt_poses is not None and np.isfinite(self.gt_poses[i]).all():
            gt = self.gt_poses[i].copy()
        return Frame(index=i, frame_id=frame_id, timestamp=float(self.timestamps[i]),
                     gray=gray, color=color, camera=self.camera, gt_pose=gt, path=path, fingerprint=fingerprint)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def ground_truth(self) -> Trajectory | None:
        """Ground truth of the delivered frames that have one (camera-to-world, source timestamps)."""
        if self.gt_poses is None:
            return None
        ok = np.isfinite(self.gt_poses).all(axis=(1, 2))
        return Trajectory(self.timestamps[ok], self.gt_poses[ok])

    def __repr__(self) -> str:
        c = self.camera
        return (f"{type(self).__name__}({self.name!r}, {len(self)} frames, {c.width}x{c.height}, "
                f"gt={'yes' if self.gt_poses is not None else 'no'})")


MIN_FRAME_SIZE = 32
"""Frames narrower or lower than this (pixels) are refused: features need a neighbourhood to be found."""


def check_frame_size(width: int, height: int, where: str | Path) -> None:
    """ImageReadError naming ``where`` (a file, or a source and frame) when a frame is smaller than
    :data:`MIN_FRAME_SIZE` in either direction (the frame is then skipped, with this reason)."""
    if width < MIN_FRAME_SIZE or height < MIN_FRAME_SIZE:
        raise ImageReadError(where, f"is {width}x{height} pixels; slamkit needs frames of at least "
                                    f"{MIN_FRAME_SIZE}x{MIN_FRAME_SIZE}")


def to_gray_and_rgb(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """uint8 grey (H, W) or BGR(A) (H, W, 3|4) -> (grey (H, W), RGB (H, W, 3)); 16-bit is scaled to 8-bit."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.ndim == 2:
        return image, cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


_DECODER_MESSAGE = re.compile(r"(libpng|libjpeg|libtiff|libwebp|jpeg|png|tiff|webp|corrupt|premature|"
                              r"extraneous|marker|huffman|warning)", re.I)
_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def decoder_messages_named(path: Path) -> Iterator[None]:
    """Prefix the file name to what the image libraries print on the process's stderr while ``path`` is
    decoded ("Corrupt JPEG data: premature end of data segment", "libpng warning: ..."): libjpeg and libpng
    write from C, so file descriptor 2 is captured for the call; lines that are not such messages (another
    thread's output meanwhile) are passed on unchanged."""
    with _STDERR_LOCK:
        try:
            saved = os.dup(2)
        except OSError:  # no stderr: nothing to capture
            yield
            return
        with tempfile.TemporaryFile() as tmp:
            try:
                os.dup2(tmp.fileno(), 2)
                yield
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                tmp.seek(0)
                text = tmp.read().decode("utf-8", "replace")
                if text:
                    lines = text.splitlines(keepends=True)
                    out = "".join(f"slamkit: {shown(path)}: {ln.rstrip()}\n" if _DECODER_MESSAGE.search(ln)
                                  else ln for ln in lines)
                    with contextlib.suppress(OSError):
                        os.write(2, out.encode("utf-8", "backslashreplace"))


MAX_IMAGE_BYTES = 2**30
"""Largest image file read (bytes): the file is read whole before it is decoded."""


def read_image(path: Path) -> np.ndarray:
    """Decode an image file; :class:`ImageReadError` names the file when it fails.

    The bytes are read by Python and decoded from memory (``cv2.imdecode``): a file name reaches the OS only,
    never OpenCV, whatever bytes it holds (OpenCV's own reader crashes on names that are not UTF-8).
    """
    return read_image_file(path)[0]


def read_image_file(path: Path) -> tuple[np.ndarray, Fingerprint]:
    """:func:`read_image` and the file's :class:`~slamkit.types.Fingerprint` (name, size in bytes, decoded
    width and height, SHA-256 of the bytes just decoded: what the frame was, at no second read)."""
    path = Path(path)
    if not path.is_file():
        raise ImageReadError(path, "is not a regular file" if os.path.exists(path) else "file does not exist")
    try:
        size = path.stat().st_size
        if size > MAX_IMAGE_BYTES:
            raise ImageReadError(path, f"is {size / 2**30:.1f} GiB, larger than any image slamkit reads "
                                       f"({MAX_IMAGE_BYTES / 2**30:g} GiB)")
        data = np.fromfile(path, dtype=np.uint8)
    except (OSError, ValueError) as e:
        raise ImageReadError(path, f"cannot be read ({getattr(e, 'strerror', None) or e})") from None
    if data.size == 0:
        raise ImageReadError(path, "is empty (0 bytes)")
    try:
        with decoder_messages_named(path):
            image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error as e:  # pragma: no cover - OpenCV raises only for exotic files
        raise ImageReadError(path, f"could not be decoded ({e})") from None
    if image is None or image.size == 0:
        raise ImageReadError(path)
    return image, Fingerprint.of_file(path, data, image.shape[1], image.shape[0])


@contextlib.contextmanager
def plain_name(path: Path) -> Iterator[str]:
    """A name for ``path`` that OpenCV and FFmpeg take as a plain file, whatever bytes the real name holds
    (not UTF-8, ``%`` patterns, a ``protocol:`` prefix): a symbolic link with an ASCII name in a private
    temporary folder, removed on exit (open the file inside the ``with``; an open file stays readable).
    Where no link can be made, the real name when it is plain ASCII, else :class:`SourceError` naming it."""
    target = os.path.abspath(path)
    suffix = path.suffix if path.suffix.isascii() and path.suffix[1:].isalnum() else ""
    folder = link = None
    try:
        folder = tempfile.mkdtemp(prefix="slamkit-name-")
        link = os.path.join(folder, "input" + suffix)
        os.symlink(target, link)
    except OSError:
        _remove_link(folder, link)
        folder = None
    if folder is None:
        if target.isascii() and target.isprintable() and "%" not in target and ":" not in target:
            yield target
            return
        raise SourceError(f"{shown(path)}: its name cannot be passed to the video decoder and no temporary link "
                          "to it can be made; rename the file (plain letters and digits)")
    try:
        yield link
    finally:
        _remove_link(folder, link)


def _remove_link(folder: str | None, link: str | None) -> None:
    for remove, name in ((os.unlink, link), (os.rmdir, folder)):
        if name is not None:
            with contextlib.suppress(OSError):
                remove(name)


@dataclass
class ImageListSource(FrameSource):
    """Frames read from a list of image files (the common case of every dataset layout)."""

    name: str
    camera: Intrinsics
    paths: Sequence[Path]
    timestamps: np.ndarray
    frame_ids: np.ndarray
    gt_poses: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.name = shown(self.name)  # printable whatever bytes the folder names hold
        self.paths = [Path(p) for p in self.paths]
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64)
        self.frame_ids = np.asarray(self.frame_ids, dtype=np.int64)
        if self.gt_poses is not None:
            self.gt_poses = np.asarray(self.gt_poses, dtype=np.float64).reshape(-1, 4, 4)
        assert len(self.paths) == len(self.timestamps) == len(self.frame_ids)
        if self.paths and min(self.camera.width, self.camera.height) < MIN_FRAME_SIZE:  # every frame is this size
            raise SourceError(f"{self.paths[0]}: frames of {self.name} are {self.camera.width}x{self.camera.height} "
                              f"pixels; slamkit needs at least {MIN_FRAME_SIZE}x{MIN_FRAME_SIZE}")

    def _read(self, i: int) -> tuple[np.ndarray, Path | None]:
        return read_image(self.paths[i]), self.paths[i]

    def _read_fingerprinted(self, i: int) -> tuple[np.ndarray, Path | None, Fingerprint | None]:
        image, fingerprint = read_image_file(self.paths[i])
        return image, self.paths[i], fingerprint

    __repr__ = FrameSource.__repr__


class FrameRange(FrameSource):
    """Frames ``start`` to ``stop`` (exclusive) of another source, with their own timestamps, ids and ground truth:
    the two parts of one video as two runs (a map made of the first, the second localized in it)."""

    def __init__(self, inner: FrameSource, start: int, stop: int):
        self.inner, self.start = inner, int(start)
        self.name = f"{inner.name}[{start}:{stop}]"
        self.camera, self.camera_in_spec = inner.camera, getattr(inner, "camera_in_spec", False)
        self.timestamps = np.asarray(inner.timestamps)[start:stop]
        self.frame_ids = np.asarray(inner.frame_ids)[start:stop]
        self.gt_poses = None if inner.gt_poses is None else np.asarray(inner.gt_poses)[start:stop]

    def _read_fingerprinted(self, i: int) -> tuple[np.ndarray, Path | None, Fingerprint | None]:
        return self.inner._read_fingerprinted(self.start + i)

    __repr__ = FrameSource.__repr__
