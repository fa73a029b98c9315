"""A video file read with OpenCV (``cv2.VideoCapture``, FFmpeg), forward only.

Opening makes one pass over the video without converting frames (``grab``): it counts the frames that
decode and records each one's presentation time from the container (``CAP_PROP_POS_MSEC``), so
``timestamps`` are the true times of a variable-frame-rate video, not frame number / mean fps. Frames are
then decoded on access, reading forward; every frame read is checked against the first pass's time for its
number, so a frame is never replaced by another. A frame before the current position is taken from the last
few decoded, else sought back only when the frame the seek delivers has that frame's time (seeking in a
transport stream or a file with a damaged index lands on another frame), else the file is reopened and read
forward again. The self-calibration pass and the run therefore see the same frames.

A video cut short (a download or copy that stopped, the index of an mp4 at the front announcing more frames
than the file holds) is read up to its first frame that does not decode; when the container announced more,
the missing frames are kept in the sequence and each one raises :class:`ImageReadError` saying so (a run
skips them with that reason). The name of the file never reaches FFmpeg: it opens an ASCII-named link
(:func:`~slamkit.sources.base.plain_name`), so any bytes in the name are fine.
"""

from __future__ import annotations

import math
import os
import threading
from pathlib import Path

import cv2
import numpy as np

from ..camera import Intrinsics
from ..errors import ImageReadError, SourceError, missing_reason, shown
from ..types import Fingerprint
from .base import FrameSource, plain_name, select
from .calibration import find_camera_txt, read_camera_txt
from .folder import check_fps, resolve_camera
from .textfiles import require_path

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".ts",
                    ".mts", ".3gp", ".ogv")
"""Extensions (lower case) that :func:`~slamkit.sources.open.open_source` treats as video files."""

DEFAULT_FPS = 30.0

TIME_TOLERANCE_S = 1e-4
"""Largest difference (seconds) between a frame's time when read and in the first pass for the same frame."""

MAX_ANNOUNCED = 10_000_000
"""Largest frame count of a container taken as true when fewer frames decode (46 hours at 60 fps)."""

RECENT_FRAMES = 4
"""Decoded frames kept (the last ones read): a frame asked for again soon is not decoded again."""


class VideoSource(FrameSource):
    """Frames of a video file.

    Attributes (besides those of :class:`FrameSource`):
        path: the video file.
        fps: the container's frame rate (``DEFAULT_FPS`` when it reports none), or the ``fps`` given.
        n_video_frames: number of frames of the whole video (before frame skip / max frames): the frames that
            decode, or the container's count when the file ends early (see ``n_decodable``).
        n_decodable: number of frames that decode (frames ``0 .. n_decodable - 1``).
        n_announced: the container's frame count (may be an estimate from duration x fps: variable frame rate).
        frame_times: (n_video_frames,) float64 seconds: each frame's presentation time in the container
            (first frame 0); past ``n_decodable`` extrapolated at ``fps``.
        timestamps_from: ``"container"`` (presentation times), ``"fps"`` (frame number / ``fps``: an ``fps``
            was given, or the container's times do not increase).
    """

    def __init__(self, path: str | Path, *, camera: Intrinsics | float | str | None = None,
                 fps: float | None = None,
                 exact_count: bool = True, frame_skip: int = 1, max_frames: int | None = None):
        self.path = require_path(path, "video file")
        select(0, frame_skip, max_frames)  # validate early
        fps = check_fps(fps) if fps is not None else None
        self._cap, self._pos, self._recent, self._lock = None, 0, [], threading.Lock()
        cap = self._open()
        try:
            container_fps = cap.get(cv2.CAP_PROP_FPS)
            announced = cap.get(cv2.CAP_PROP_FRAME_COUNT)
            times, size = self._scan(cap)
        finally:
            self.close()
        self.n_announced = int(announced) if math.isfinite(announced) and announced > 0 else 0
        self.n_decodable = len(times)
        if self.n_decodable == 0:
            raise SourceError(f"video file {shown(self.path)} has no frame that can be decoded")
        self.fps = fps if fps is not None else (
            float(container_fps) if math.isfinite(container_fps) and 0 < container_fps < 1000 else DEFAULT_FPS)
        step = 1.0 / self.fps
        self.n_video_frames = self.n_decodable
        if (self.n_decodable < self.n_announced <= MAX_ANNOUNCED
                and self.n_announced * step > times[-1] + 2.5 * step):
            # the container announced frames beyond the last that decodes (not an estimate of a VFR video's
            # count: that covers its duration; not a damaged header's absurd count): the file is cut short or
            # damaged there
            self.n_video_frames = self.n_announced
        extra = np.arange(1, self.n_video_frames - self.n_decodable + 1) * step + times[-1]
        self.frame_times = np.concatenate([times, extra])
        increasing = bool(np.all(np.diff(times) > 0))
        self._unique_times = increasing
        self.timestamps_from = "container" if fps is None and increasing else "fps"
        width, height = size
        self.name = f"video/{shown(self.path.stem)}"
        calib = find_camera_txt(self.path.parent) if camera is None else None
        if calib is not None:
            camera = read_camera_txt(calib, width, height)
        self.camera = resolve_camera(camera, width, height, where=shown(self.path))
        self.frame_ids = select(self.n_video_frames, frame_skip, max_frames).astype(np.int64)
        self.timestamps = (self.frame_times[self.frame_ids] if self.timestamps_from == "container"
                           else self.frame_ids / self.fps)
        self.gt_poses = None

    # -- capture handling ------------------------------------------------------------------------------
    def _open(self):
        if not self.path.is_file():
            reason = missing_reason(self.path) or "is not a file"
            raise SourceError(f"video file {shown(self.path)} {reason} (any more)")
        with plain_name(self.path) as name:
            cap = cv2.VideoCapture(name)
        if not cap.isOpened():
            cap.release()
            raise SourceError(f"video file {shown(self.path)} cannot be opened (not a video, or no decoder for it)")
        self._cap, self._pos = cap, 0
        return cap

    def _scan(self, cap) -> tuple[np.ndarray, tuple[int, int]]:
        """The first pass: (presentation time in seconds of every frame that decodes, (width, height))."""
        times = []
        while cap.grab():
            times.append(cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
        width = int(round(cap.get(cv2.CAP_PROP_FRAME_WIDTH)))
        height = int(round(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        if times and (width <= 0 or height <= 0):  # some backends report the size only from a frame
            cap.release()
            cap = self._open()
            ok, image = cap.read()
            if not ok or image is None:
                raise ImageReadError(self.path, "frame 0 could not be decoded")
            height, width = image.shape[:2]
        t = np.asarray(times, dtype=np.float64)
        self.time_origin = float(t[0]) if len(t) else 0.0
        """The container's time of frame 0 as OpenCV reports it (seconds; frame times count from it)."""
        return t - self.time_origin, (width, height)

    @property
    def counted(self) -> bool:
        """The frames were counted by decoding them (always: the container's count is kept as ``n_announced``)."""
        return True

    def close(self) -> None:
        """Release the capture (it is reopened on the next access)."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None
        self._pos = 0

    def __enter__(self) -> "VideoSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_cap"] = None  # a capture cannot be pickled; reopened lazily
        state["_pos"], state["_recent"] = 0, []
        del state["_lock"]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, _lock=threading.Lock())

    def _read(self, i: int) -> tuple[np.ndarray, Path | None]:
        k = int(self.frame_ids[i])
        if k >= self.n_decodable:
            raise ImageReadError(self.path, f"frame {k} could not be decoded: the video ends after frame "
                                            f"{self.n_decodable - 1} although its container announces "
                                            f"{self.n_announced} frames (the file is cut short or damaged)")
        with self._lock:  # one capture: a viewer's read and the prefetch thread's take turns
            for number, image in self._recent:
                if number == k:
                    return image, self.path
            image = self._seek(k) if self._cap is not None and k < self._pos else None
            if image is None:
                image = self._forward(k)
            self._recent = [(k, image)] + [r for r in self._recent if r[0] != k][: RECENT_FRAMES - 1]
            return image, self.path

    def _read_fingerprinted(self, i: int) -> tuple[np.ndarray, Path | None, Fingerprint | None]:
        """The frame and its fingerprint: the video file's name and size in bytes, the SHA-256 of the decoded
        frame's pixels (each frame its own; 0.8 ms for a 1242x375 frame, ``benchmarks/bench_fingerprints.py``)."""
        image, path = self._read(i)
        try:
            size = os.stat(self.path).st_size
        except OSError:  # gone since (the frame was decoded before): the frame's pixels still say what it was
            size = -1
        return image, path, Fingerprint.of_bytes(self.path.name, np.ascontiguousarray(image), image.shape[1],
                                                 image.shape[0], size)

    def _forward(self, k: int) -> np.ndarray:
        """Frame ``k`` read forward: from the open capture, or from a new one when ``k`` is behind it."""
        if self._cap is None or k < self._pos:
            self.close()
            try:
                self._open()
            except SourceError as e:  # moved or deleted since it was opened: this frame is skipped, named
                raise ImageReadError(self.path, f"frame {k} cannot be read: {e}") from None
        cap = self._cap
        while self._pos < k:
            if not cap.grab():
                self.close()
                raise ImageReadError(self.path, f"frame {k}: the stream ended at frame {self._pos} on this "
                                                f"reading, although frames 0 to {self.n_decodable - 1} decoded "
                                                "when the video was opened")
            self._pos += 1
        ok, image = cap.read()
        if not ok or image is None or image.size == 0:
            self.close()
            raise ImageReadError(self.path, f"frame {k} could not be decoded on this reading, although it "
                                            "decoded when the video was opened")
        self._pos = k + 1
        t = self._time(cap)
        if abs(t - self.frame_times[k]) > TIME_TOLERANCE_S:
            self.close()
            raise ImageReadError(self.path, f"frame {k}: the decoder delivered the frame of time {t:.4f} s where "
                                            f"the first pass found {self.frame_times[k]:.4f} s; refusing to "
                                            "use another frame in its place")
        return image

    def _seek(self, k: int) -> np.ndarray | None:
        """Frame ``k`` by seeking the open capture back, when the frame it delivers has frame ``k``'s time (the
        times are unique); None otherwise (a transport stream, a damaged index: read forward instead)."""
        if not self._unique_times:
            return None
        cap = self._cap
        try:
            ok = cap.set(cv2.CAP_PROP_POS_FRAMES, k)
            ok, image = cap.read() if ok else (False, None)
        except cv2.error:  # pragma: no cover - OpenCV raises only for exotic files
            ok, image = False, None
        if ok and image is not None and image.size and abs(self._time(cap) - self.frame_times[k]) <= TIME_TOLERANCE_S:
            self._pos = k + 1
            return image
        self.close()
        return None

    def _time(self, cap) -> float:
        return cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0 - self.time_origin

    __repr__ = FrameSource.__repr__


def open_video(path: str | Path, *, camera: Intrinsics | float | str | None = None, fps: float | None = None,
               exact_count: bool = True, frame_skip: int = 1, max_frames: int | None = None) -> VideoSource:
    """Open a video file as a frame source.

    Args:
        camera: :class:`Intrinsics`, a focal length in pixels or a ``--camera`` text; else a ``camera.txt``
            beside the video file, else the documented guess ``Intrinsics.from_focal(w, h)`` (focal
            1.2 x max(w, h), principal point at the centre), which ``Slam`` replaces by an estimate
            (:mod:`slamkit.stages.self_calibration`).
        fps: timestamps ``frame number / fps`` instead of the container's presentation times (which are
            used otherwise, variable frame rate included).
        exact_count: kept for compatibility; frames are always counted by decoding them once when the video
            is opened (the container's count can be wrong).
        frame_skip, max_frames: keep every ``frame_skip``-th frame, at most ``max_frames``.

    Raises SourceError when the file is missing, cannot be opened or has no frame that decodes. Frames are
    decoded on access, forward: a frame that cannot be decoded raises ImageReadError (file and frame
    number), a frame of another size than the first CalibrationError.
    """
    return VideoSource(path, camera=camera, fps=fps, exact_count=exact_count, frame_skip=frame_skip,
                       max_frames=max_frames)
