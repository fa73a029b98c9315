"""Reading frames for the pipeline: each frame read from the source and its features extracted, optionally
one frame ahead on a background thread (``SlamConfig.prefetch``: OpenCV's decoding and ORB release the GIL,
so that time overlaps with tracking and mapping; the result is the same either way)."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import cv2
import numpy as np

from .camera import Intrinsics
from .errors import CalibrationError, ImageReadError
from .features import Extractor, FrameFeatures, image_signature
from .sources.base import FrameSource
from .types import Frame


class FrameLoader:
    """Loads frame ``cursor`` (the position in ``indices``) of a source: (frame, features, read s, features s),
    or (the source's ImageReadError / CalibrationError, read s) for a frame it cannot deliver."""

    def __init__(self, source: FrameSource):
        self.source = source
        self.prefetched: tuple | None = None
        """(cursor, Future of :meth:`load`) of the frame being read ahead."""
        self._executor: ThreadPoolExecutor | None = None
        self.configure(np.arange(0), None, source.camera, False)

    def configure(self, indices: np.ndarray, extractor: Extractor | None, camera: Intrinsics, prefetch: bool) -> None:
        """(Re)start on these source indices with this extractor and camera (a pending read-ahead is dropped)."""
        self.drain()
        self.indices, self.extractor, self.camera, self.prefetch = indices, extractor, camera, prefetch

    def load(self, cursor: int) -> tuple:
        t = time.perf_counter()
        try:
            frame = self.source[int(self.indices[cursor])]
        except (ImageReadError, CalibrationError) as e:
            return e, time.perf_counter() - t
        frame = frame if frame.index == cursor else replace(frame, index=cursor)
        t_read = time.perf_counter() - t
        t = time.perf_counter()
        ff = self.features(frame)
        return frame, ff, t_read, time.perf_counter() - t

    def next(self, cursor: int) -> tuple:
        """:meth:`load` of frame ``cursor``, done ahead on the prefetch thread when ``prefetch`` (then the
        next frame's load starts here, before this one is processed)."""
        job, self.prefetched = self.prefetched, None
        if job is not None and job[0] == cursor:
            loaded = job[1].result()  # the worker's exception, if any, is raised here
        else:
            self._wait(job)
            loaded = self.load(cursor)
        if self.prefetch and cursor + 1 < len(self.indices):
            if self._executor is None:
                self._executor = ThreadPoolExecutor(1, thread_name_prefix="slamkit-prefetch")
            self.prefetched = (cursor + 1, self._executor.submit(self.load, cursor + 1))
        return loaded

    def drain(self) -> None:
        """Wait for a read-ahead that will not be used (the source is read by one thread at a time)."""
        job, self.prefetched = getattr(self, "prefetched", None), None
        self._wait(job)

    @staticmethod
    def _wait(job) -> None:
        if job is not None:
            try:
                job[1].result()
            except Exception:  # noqa: BLE001 - the frame is read again when it is due
                pass

    def features(self, frame: Frame) -> FrameFeatures:
        """The frame's features, keypoints undistorted, their colours, and its global image signature."""
        feats = self.extractor.extract(frame.gray)
        kp = self.camera.undistort_points(feats.keypoints)
        h, w = frame.gray.shape
        ij = np.clip(np.round(feats.keypoints).astype(np.int64), 0, [w - 1, h - 1])
        colors = frame.color[ij[:, 1], ij[:, 0]]
        return FrameFeatures(frame.index, frame.frame_id, frame.timestamp, feats, kp, colors,
                             signature=image_signature(frame.gray))


def thumbnail(frame: Frame | None, frame_index: int, width: int) -> np.ndarray | None:
    """A ``width`` pixels wide RGB copy of ``frame`` for viewers (keyframe thumbnails), or None (width 0, or
    ``frame`` is not frame ``frame_index``)."""
    if width <= 0 or frame is None or frame.index != frame_index:
        return None
    img = frame.color
    scale = width / img.shape[1]
    return cv2.resize(img, (width, max(1, int(img.shape[0] * scale))), interpolation=cv2.INTER_AREA)
