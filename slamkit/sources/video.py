"""A video file read with OpenCV (``cv2.VideoCapture``), frame by frame and on demand.

One capture stays open. Frames are read forward sequentially (skipped frames are grabbed, not converted);
the capture re-seeks (``CAP_PROP_POS_FRAMES``) only when a frame before the current position is asked for.

The number of frames comes from the container (``CAP_PROP_FRAME_COUNT``), which **can be wrong** (variable
frame rate, broken index, some codecs report an estimate from duration x fps). When it is missing or not
positive the frames are counted by grabbing through the whole video once; pass ``exact_count=True`` to
always do so. A frame that the container announced but the stream does not deliver raises
:class:`ImageReadError` naming the file and the frame number.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from ..camera import Intrinsics
from ..errors import ImageReadError, SourceError
from .base import FrameSource, select
from .calibration import find_camera_txt, read_camera_txt
from .folder import check_fps, resolve_camera
from .textfiles import require_path

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".ts",
                    ".mts", ".3gp", ".ogv")
"""Extensions (lower case) that :func:`~slamkit.sources.open.open_source` treats as video files."""

DEFAULT_FPS = 30.0


class VideoSource(FrameSource):
    """Frames of a video file.

    Attributes (besides those of :class:`FrameSource`):
        path: the video file.
        fps: frames per second used for the timestamps (container value, or ``DEFAULT_FPS``).
        n_video_frames: number of frames of the whole video (before frame skip / max frames).
    """

    def __init__(self, path: str | Path, *, camera: Intrinsics | float | str | None = None,
                 fps: float | None = None,
                 exact_count: bool = False, frame_skip: int = 1, max_frames: int | None = None):
        self.path = require_path(path, "video file")
        select(0, frame_skip, max_frames)  # validate early
        self._cap = None
        cap = self._open()
        width = int(round(cap.get(cv2.CAP_PROP_FRAME_WIDTH)))
        height = int(round(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        container_fps = cap.get(cv2.CAP_PROP_FPS)
        count = cap.get(cv2.CAP_PROP_FRAME_COUNT)
        if width <= 0 or height <= 0:  # some backends report the size only after the first frame
            ok, image = cap.read()
            if not ok or image is None:
                raise ImageReadError(self.path, "frame 0 could not be decoded")
            height, width = image.shape[:2]
            self._rewind(cap)
        self.counted = bool(exact_count or not math.isfinite(count) or count <= 0)
        """The number of frames was counted by grabbing (else it is the container's claim)."""
        if self.counted:
            count = self._count_frames(cap)
        self.n_video_frames = int(count)
        if self.n_video_frames == 0:
            raise SourceError(f"video file {self.path} has no frames")
        if fps is not None:
            self.fps = check_fps(fps)
        elif math.isfinite(container_fps) and 0 < container_fps < 1000:
            self.fps = float(container_fps)
        else:
            self.fps = DEFAULT_FPS
        self.name = f"video/{self.path.stem}"
        calib = find_camera_txt(self.path.parent) if camera is None else None
        if calib is not None:
            camera = read_camera_txt(calib, width, height)
        self.camera = resolve_camera(camera, width, height, where=str(self.path))
        self.frame_ids = select(self.n_video_frames, frame_skip, max_frames).astype(np.int64)
        self.timestamps = self.frame_ids / self.fps
        self.gt_poses = None

    # -- capture handling ------------------------------------------------------------------------------
    def _open(self):
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            cap.release()
            raise SourceError(f"video file {self.path} cannot be opened (not a video, or no decoder for it)")
        self._cap, self._pos = cap, 0
        return cap

    def _rewind(self, cap) -> None:
        cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        self._pos = 0

    def _count_frames(self, cap) -> int:
        n = 0
        while cap.grab():
            n += 1
        self._rewind(cap)
        return n

    def close(self) -> None:
        """Release the capture (it is reopened on the next access)."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None

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
        state["_pos"] = 0
        return state

    def _read(self, i: int) -> tuple[np.ndarray, Path | None]:
        k = int(self.frame_ids[i])
        cap = self._cap if self._cap is not None else self._open()
        if k < self._pos:
            cap.set(cv2.CAP_PROP_POS_FRAMES, k)
            self._pos = k
        while self._pos < k:
            if not cap.grab():
                self._pos = self.n_video_frames  # force a re-seek next time
                raise ImageReadError(self.path, f"frame {self._pos_msg(k)}: the stream ended early")
            self._pos += 1
        ok, image = cap.read()
        if not ok or image is None or image.size == 0:
            self._pos = self.n_video_frames
            raise ImageReadError(self.path, f"frame {self._pos_msg(k)} could not be decoded")
        self._pos = k + 1
        return image, self.path

    def _pos_msg(self, k: int) -> str:
        if getattr(self, "counted", False):  # the frame was grabbed while counting: decoding it failed
            return f"{k} of {self.n_video_frames} (damaged, or the stream changes resolution or codec there)"
        return (f"{k} (the container reports {self.n_video_frames} frames, which can be wrong; "
                "open with exact_count=True to count them)")

    __repr__ = FrameSource.__repr__


def open_video(path: str | Path, *, camera: Intrinsics | float | str | None = None, fps: float | None = None,
               exact_count: bool = False, frame_skip: int = 1, max_frames: int | None = None) -> VideoSource:
    """Open a video file as a frame source.

    Args:
        camera: :class:`Intrinsics`, a focal length in pixels or a ``--camera`` text; else a ``camera.txt``
            beside the video file, else the documented guess ``Intrinsics.from_focal(w, h)`` (focal
            1.2 x max(w, h), principal point at the centre), which ``Slam`` replaces by an estimate
            (:mod:`slamkit.stages.self_calibration`).
        fps: override the container's frame rate; timestamps are ``frame number / fps`` seconds (fallback
            30 fps when the container reports none).
        exact_count: count frames by grabbing through the video instead of trusting the container.
        frame_skip, max_frames: keep every ``frame_skip``-th frame, at most ``max_frames``.

    Raises SourceError when the file is missing or cannot be opened. Frames are decoded on access: a frame
    that cannot be decoded raises ImageReadError (file and frame number), a frame of another size than the
    first CalibrationError.
    """
    return VideoSource(path, camera=camera, fps=fps, exact_count=exact_count, frame_skip=frame_skip,
                       max_frames=max_frames)
