"""Small value types shared by sources, stages, I/O and evaluation."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Intrinsics


@dataclass(frozen=True)
class Fingerprint:
    """What a frame was read from, measured when it was read (issue 50): the file's name (``file``, printable:
    :func:`slamkit.errors.shown`), its size in bytes, the image's ``width`` x ``height`` in pixels and a SHA-256.

    An image file: the SHA-256 of the file's bytes, hashed from the bytes the source decoded (no second read).
    A video: ``file`` and ``bytes`` are the video file's, the SHA-256 is that of the decoded frame's pixels
    (uint8 BGR as FFmpeg delivered them), so every frame has its own (the container holds all frames; its
    frame's time is the frame's timestamp). Export and resume compare these with the source as it is then.
    """

    file: str
    bytes: int
    width: int
    height: int
    sha256: str

    @classmethod
    def of_bytes(cls, name: str, data, width: int, height: int, size: int | None = None) -> "Fingerprint":
        """Of ``data`` (bytes or a contiguous array), ``size`` bytes on disk (default: ``len(data)``)."""
        from .errors import shown

        digest = hashlib.sha256(memoryview(data).cast("B")).hexdigest()
        nbytes = int(size) if size is not None else memoryview(data).nbytes
        return cls(shown(name), nbytes, int(width), int(height), digest)

    @classmethod
    def of_file(cls, path: str | os.PathLike, data, width: int, height: int) -> "Fingerprint":
        """Of an image file whose bytes are ``data`` (as read for decoding)."""
        return cls.of_bytes(os.path.basename(os.fspath(path)), data, width, height)


@dataclass(frozen=True, eq=False)
class Frame:
    """One image of a sequence.

    ``index`` counts frames as delivered (after frame skip), ``frame_id`` is the frame's number in the
    dataset. ``color`` is (H, W, 3) uint8 RGB, ``gray`` (H, W) uint8. ``gt_pose`` is the (4, 4)
    camera-to-world ground-truth pose when the dataset has one for this frame, else None.
    """

    index: int
    frame_id: int
    timestamp: float
    gray: np.ndarray
    color: np.ndarray
    camera: Intrinsics
    gt_pose: np.ndarray | None = None
    path: Path | None = None
    fingerprint: Fingerprint | None = None
    """What the frame was read from, measured as it was read (None: a rendered frame, or a source that does
    not say)."""

    def __repr__(self) -> str:
        h, w = self.gray.shape[:2]
        return (f"Frame(index={self.index}, frame_id={self.frame_id}, t={self.timestamp:.6f}, {w}x{h}, "
                f"gt={'yes' if self.gt_pose is not None else 'no'})")


@dataclass(eq=False)
class Trajectory:
    """A sequence of timestamped camera-to-world poses.

    ``timestamps``: (N,) float64 seconds, ``poses``: (N, 4, 4) float64 camera-to-world.
    """

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise ValueError(f"{len(self.timestamps)} timestamps but {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in world coordinates."""
        return self.poses[:, :3, 3].copy()

    def subset(self, mask_or_index) -> "Trajectory":
        return Trajectory(self.timestamps[mask_or_index], self.poses[mask_or_index])

    @property
    def path_length(self) -> float:
        """Length of the camera path in world units."""
        p = self.positions
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0
