"""Small value types shared by sources, stages, I/O and evaluation."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Intrinsics


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
