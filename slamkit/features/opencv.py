"""OpenCV extractors: ORB (binary, the default) and SIFT (float, L2)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .base import Features, register_extractor


def _grid_cap(kps, n_cells: tuple[int, int], shape: tuple[int, int], total: int):
    """Keep the ``total`` strongest keypoints spread over the image: at most total / cells per grid cell
    first, then the strongest of the rest until ``total`` (empty cells, e.g. sky, leave their share)."""
    if total <= 0 or len(kps) <= total:
        return kps
    h, w = shape
    gx, gy = n_cells
    per_cell = int(np.ceil(total / (gx * gy)))
    xy = cv2.KeyPoint_convert(kps).reshape(-1, 2)
    resp = np.fromiter((k.response for k in kps), np.float32, len(kps))
    cell = np.minimum((xy[:, 1] * gy / h).astype(np.int64), gy - 1) * gx + np.minimum(
        (xy[:, 0] * gx / w).astype(np.int64), gx - 1)
    order = np.lexsort((-resp, cell))
    c = cell[order]
    rank = np.empty(len(c), np.int64)
    rank[order] = np.arange(len(c)) - np.searchsorted(c, c, side="left")
    first = np.flatnonzero(rank < per_cell)
    if len(first) < total:
        rest = np.flatnonzero(rank >= per_cell)
        rest = rest[np.argsort(-resp[rest], kind="stable")][: total - len(first)]
        first = np.concatenate([first, rest])
    elif len(first) > total:
        first = first[np.argsort(-resp[first], kind="stable")][:total]
    return [kps[i] for i in np.sort(first)]


@register_extractor("orb")
@dataclass
class OrbExtractor:
    """ORB (oriented FAST + rotated BRIEF), 256-bit descriptors, as in ORB-SLAM.

    Detects ``oversample`` x ``num_features`` FAST corners over an image pyramid, then keeps the strongest
    per cell of a grid so that keypoints spread over the image (ORB-SLAM's octree distribution, simplified).
    """

    num_features: int = 2000
    scale_factor: float = 1.2
    num_levels: int = 8
    fast_threshold: int = 12
    grid: tuple[int, int] = (8, 6)
    oversample: float = 2.0
    name: str = "orb"

    def __post_init__(self) -> None:
        self._orb = cv2.ORB_create(nfeatures=int(self.num_features * self.oversample),
                                   scaleFactor=self.scale_factor, nlevels=self.num_levels,
                                   fastThreshold=self.fast_threshold, edgeThreshold=19, patchSize=31)

    def extract(self, gray: np.ndarray) -> Features:
        kps = self._orb.detect(gray, None)
        kps = _grid_cap(list(kps), self.grid, gray.shape[:2], self.num_features)
        kps, desc = self._orb.compute(gray, kps)
        return _to_features(kps, desc, True, gray.shape)


@register_extractor("sift")
@dataclass
class SiftExtractor:
    """SIFT (OpenCV), 128-d float descriptors normalised to unit length (RootSIFT-like L2 matching)."""

    num_features: int = 2000
    contrast_threshold: float = 0.02
    name: str = "sift"

    def __post_init__(self) -> None:
        self._sift = cv2.SIFT_create(nfeatures=self.num_features, contrastThreshold=self.contrast_threshold)

    def extract(self, gray: np.ndarray) -> Features:
        kps, desc = self._sift.detectAndCompute(gray, None)
        if desc is not None and len(desc):
            desc = np.sqrt(desc / np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)).astype(np.float32)  # RootSIFT
        feats = _to_features(kps, desc, False, gray.shape)
        if len(feats) > self.num_features:  # OpenCV keeps the keypoints that tie with the last one's response
            feats = feats.subset(np.sort(np.argsort(-feats.scores, kind="stable")[: self.num_features]))
        return feats


def _to_features(kps, desc, binary: bool, shape: tuple[int, ...]) -> Features:
    size = (int(shape[1]), int(shape[0]))
    if desc is None or not kps:
        d = 32 if binary else 128
        return Features(np.empty((0, 2)), np.empty((0, d), np.uint8 if binary else np.float32),
                        np.empty(0, np.float32), binary, np.empty(0, np.float32), size)
    xy = cv2.KeyPoint_convert(kps).reshape(-1, 2).astype(np.float64)
    scores = np.fromiter((k.response for k in kps), np.float32, len(kps))
    sizes = np.fromiter((k.size for k in kps), np.float32, len(kps))
    return Features(xy, np.ascontiguousarray(desc), scores, binary, sizes, size)
