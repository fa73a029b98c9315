"""Feature types, the extractor registry, and descriptor matching (brute force and guided by projection)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Protocol

import cv2
import numpy as np

from ..errors import ConfigError
from . import hamming


@dataclass(frozen=True, eq=False)
class Features:
    """Local features of one image.

    keypoints: (N, 2) float64 pixels as detected (distorted image).
    descriptors: (N, D) uint8 (binary, packed bits) or float32.
    scores: (N,) float32 detector response; sizes: (N,) float32 keypoint diameter in pixels.
    binary: True for packed binary descriptors (Hamming distance), False for float (L2).
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    scores: np.ndarray
    binary: bool
    sizes: np.ndarray | None = None
    image_size: tuple[int, int] | None = None
    """(width, height) of the image, for matchers that normalise keypoints (LightGlue)."""

    def __len__(self) -> int:
        return len(self.keypoints)

    def subset(self, idx: np.ndarray) -> "Features":
        """The features at indices ``idx`` (same order)."""
        return Features(self.keypoints[idx], self.descriptors[idx], self.scores[idx], self.binary,
                        None if self.sizes is None else self.sizes[idx], self.image_size)


class Extractor(Protocol):
    """Anything with ``extract(gray (H, W) uint8) -> Features``."""

    name: str

    def extract(self, gray: np.ndarray) -> Features: ...


@dataclass(frozen=True)
class MatchingConfig:
    """Descriptor matching parameters."""

    ratio: float = 0.8
    """Lowe's ratio test: best distance < ratio x second best (1.0 disables it)."""
    mutual: bool = True
    """Keep only mutual nearest neighbours."""
    max_hamming: int = 80
    """Largest Hamming distance (of 256 bits) accepted for binary descriptors."""
    max_l2: float = 0.9
    """Largest L2 distance accepted for unit-normalised float descriptors."""

    RANGES = {"ratio": ("(0, 1]", "1 disables the ratio test"), "max_hamming": ("[0, 256]", "of 256 bits"),
              "max_l2": ("(0, 10]", "unit-normalised descriptors are at most 2 apart")}
    """Range of each field, checked with the config that holds this one (``slamkit.errors.check_fields``)."""


_REGISTRY: dict[str, Callable[..., Extractor]] = {}
_MATCHERS: dict[str, Callable[..., "PairMatcher"]] = {}


class PairMatcher(Protocol):
    """Matches the features of two images: ``match(a, b) -> (M, 2) int64`` index pairs (i in a, j in b).

    Used for initialization and for keyframe-to-keyframe correspondences; frame tracking always uses
    descriptor distances (guided by projection), which every extractor provides.
    """

    name: str

    def match(self, a: Features, b: Features) -> np.ndarray: ...


def register_matcher(name: str) -> Callable:
    """Class decorator: make a pair matcher available under ``name``."""

    def deco(factory):
        _MATCHERS[name] = factory
        return factory

    return deco


def available_matchers() -> list[str]:
    return sorted(_MATCHERS)


def create_matcher(name: str, **options) -> "PairMatcher":
    if name not in _MATCHERS:
        raise ConfigError(f"features: unknown matcher {name!r}; available: {', '.join(available_matchers())}")
    return _MATCHERS[name](**options)


def register_extractor(name: str) -> Callable:
    """Class decorator: make an extractor available under ``name`` (config, CLI and notebook dropdowns)."""

    def deco(factory):
        _REGISTRY[name] = factory
        return factory

    return deco


def available_extractors() -> list[str]:
    return sorted(_REGISTRY)


def create_extractor(name: str, **options) -> Extractor:
    if name not in _REGISTRY:
        raise ConfigError(f"features: unknown extractor {name!r}; available: {', '.join(available_extractors())}")
    return _REGISTRY[name](**options)


def descriptor_distance(d1: np.ndarray, d2: np.ndarray, binary: bool) -> np.ndarray:
    """Row-wise distance of paired descriptors (N, D), (N, D) -> (N,) float32 (Hamming bits or L2)."""
    if binary:
        x = np.bitwise_xor(d1, d2)
        if x.shape[1] % 8 == 0 and x.flags.c_contiguous:  # 64 bits at a time
            x = x.view(np.uint64)
        return np.bitwise_count(x).sum(axis=1, dtype=np.int32).astype(np.float32)
    diff = d1.astype(np.float32) - d2.astype(np.float32)
    return np.sqrt(np.einsum("ij,ij->i", diff, diff))


def _max_distance(binary: bool, cfg: MatchingConfig) -> float:
    return float(cfg.max_hamming) if binary else float(cfg.max_l2)


def match_descriptors(desc1: np.ndarray, desc2: np.ndarray, binary: bool,
                      cfg: MatchingConfig = MatchingConfig()) -> np.ndarray:
    """Nearest-neighbour matching with ratio test and mutual check.

    Returns (M, 2) int64 index pairs (i in desc1, j in desc2), sorted by i.
    """
    if len(desc1) < 2 or len(desc2) < 2:
        return np.empty((0, 2), np.int64)
    if binary:  # compiled brute force: OpenCV's BFMatcher(NORM_HAMMING) results, ties included, ~6x faster
        w1, w2 = hamming.words(desc1), hamming.words(desc2)
        nn, d_best, d_second = hamming.knn2(w1, w2)
        keep = (d_best < cfg.ratio * d_second.astype(np.float64)) & (d_best <= _max_distance(binary, cfg))
        pairs = np.stack([np.flatnonzero(keep), nn[keep]], axis=1).astype(np.int64)
        if cfg.mutual and len(pairs):  # the reverse nearest neighbour, of the matched desc2 rows only
            js = np.unique(pairs[:, 1])
            best_back = np.full(len(desc2), -1, np.int64)
            best_back[js] = hamming.nearest(np.ascontiguousarray(w2[js]), w1)
            pairs = pairs[best_back[pairs[:, 1]] == pairs[:, 0]]
        return pairs
    d1, d2 = desc1.astype(np.float32), desc2.astype(np.float32)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    knn = bf.knnMatch(d1, d2, k=2)
    rows = [(m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance) for m in knn if len(m) == 2]
    if not rows:
        return np.empty((0, 2), np.int64)
    a = np.array(rows, dtype=np.float64)
    keep = (a[:, 2] < cfg.ratio * a[:, 3]) & (a[:, 2] <= _max_distance(binary, cfg))
    pairs = a[keep, :2].astype(np.int64)
    if cfg.mutual and len(pairs):  # the reverse nearest neighbour, of the matched desc2 rows only
        js = np.unique(pairs[:, 1])
        best_back = np.full(len(desc2), -1, np.int64)
        for m in bf.match(np.ascontiguousarray(d2[js]), d1):
            best_back[js[m.queryIdx]] = m.trainIdx
        pairs = pairs[best_back[pairs[:, 1]] == pairs[:, 0]]
    return pairs


@register_matcher("nn")
class NearestNeighborMatcher:
    """Nearest-neighbour descriptor matching (Hamming for binary, L2 for float) with ratio test and
    optional mutual check."""

    name = "nn"

    def __init__(self, config: MatchingConfig | None = None, **overrides):
        self.config = replace(config or MatchingConfig(), **overrides)

    def match(self, a: Features, b: Features) -> np.ndarray:
        return match_descriptors(a.descriptors, b.descriptors, a.binary, self.config)


_CELL_DY, _CELL_DX = np.repeat([-1, 0, 1], 3), np.tile([-1, 0, 1], 3)  # offsets of a cell's 3x3 neighbourhood


def guided_match(proj: np.ndarray, point_desc: np.ndarray, keypoints: np.ndarray, kp_desc: np.ndarray,
                 binary: bool, radius: float, cfg: MatchingConfig = MatchingConfig(),
                 kp_taken: np.ndarray | None = None) -> np.ndarray:
    """Match projected map points to keypoints within ``radius`` pixels (ORB-SLAM's SearchByProjection).

    proj: (M, 2) predicted pixel positions of map points; point_desc: (M, D) their descriptors.
    keypoints: (N, 2) pixels; kp_desc: (N, D). kp_taken: (N,) bool, keypoints not to use.
    Returns (K, 2) int64 pairs (map point index, keypoint index), one-to-one, best distance wins.
    """
    M, N = len(proj), len(keypoints)
    if M == 0 or N == 0:
        return np.empty((0, 2), np.int64)
    if binary:  # compiled: the same pairs as the steps below, one pass per point
        cell, ox, oy, width, height, order, start, count = _keypoint_grid(keypoints, radius)
        px, py = proj[:, 0], proj[:, 1]
        pcx, pcy = (np.floor(px / cell) - ox).astype(np.int64), (np.floor(py / cell) - oy).astype(np.int64)
        taken = np.zeros(N, bool) if kp_taken is None else np.asarray(kp_taken, bool)
        return hamming.guided_match(np.ascontiguousarray(px), np.ascontiguousarray(py), pcx, pcy,
                                    hamming.words(point_desc), np.ascontiguousarray(keypoints[:, 0]),
                                    np.ascontiguousarray(keypoints[:, 1]), hamming.words(kp_desc),
                                    (order, start, count, width, height), radius, cfg.max_hamming, cfg.ratio,
                                    taken)
    return _guided_match_arrays(proj, point_desc, keypoints, kp_desc, binary, radius, cfg, kp_taken)


def _guided_match_arrays(proj: np.ndarray, point_desc: np.ndarray, keypoints: np.ndarray, kp_desc: np.ndarray,
                         binary: bool, radius: float, cfg: MatchingConfig, kp_taken: np.ndarray | None
                         ) -> np.ndarray:
    """:func:`guided_match` in numpy, step by step over every candidate pair (float descriptors; the
    reference the compiled binary path is tested against)."""
    pt, kp = _candidates_within(proj, keypoints, radius, kp_taken)
    if len(pt) == 0:
        return np.empty((0, 2), np.int64)
    dist = descriptor_distance(point_desc[pt], kp_desc[kp], binary)
    ok = dist <= _max_distance(binary, cfg)
    pt, kp, dist = pt[ok], kp[ok], dist[ok]
    if len(pt) == 0:
        return np.empty((0, 2), np.int64)
    pt, kp, dist = _ratio_test(pt, kp, dist, cfg.ratio)
    if len(pt) == 0:
        return np.empty((0, 2), np.int64)
    # one map point per keypoint: keep the closest descriptor
    o = np.lexsort((dist, kp))
    pt, kp = pt[o], kp[o]
    first = np.r_[True, kp[1:] != kp[:-1]]
    return np.stack([pt[first], kp[first]], axis=1).astype(np.int64)


def _keypoint_grid(keypoints: np.ndarray, radius: float) -> tuple:
    """Keypoints bucketed in square cells of side ``radius``, with two empty cells around them: (cell side,
    grid origin x and y in cells, width, height, keypoint indices by cell (by index within a cell), each
    cell's start in that order, each cell's count)."""
    cell = max(float(radius), 1.0)
    kx, ky = keypoints[:, 0], keypoints[:, 1]
    ox, oy = np.floor(kx.min() / cell) - 2, np.floor(ky.min() / cell) - 2
    cx, cy = (np.floor(kx / cell) - ox).astype(np.int64), (np.floor(ky / cell) - oy).astype(np.int64)
    width, height = int(cx.max()) + 3, int(cy.max()) + 3
    key = cy * width + cx
    order = np.argsort(key, kind="stable")
    count = np.bincount(key, minlength=width * height)
    start = np.cumsum(count) - count
    return cell, ox, oy, width, height, order, start, count


def _candidates_within(proj: np.ndarray, keypoints: np.ndarray, radius: float,
                       kp_taken: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Every (map point, keypoint) pair with the keypoint within ``radius`` pixels of the projection
    ``proj`` (M, 2) and not ``kp_taken``: ((K,) int64 map point indices, (K,) int64 keypoint indices)."""
    # keypoints bucketed in square cells of side `radius`: a point's candidates lie in its 3x3 cells. Two
    # empty cells around the keypoints: any projection with candidates falls inside the grid. (x and y are
    # kept apart: gathering 1-D arrays is faster than gathering rows of an (N, 2) array.)
    cell, ox, oy, width, height, order, start, count = _keypoint_grid(keypoints, radius)
    kx, ky, px, py = keypoints[:, 0], keypoints[:, 1], proj[:, 0], proj[:, 1]
    pcx, pcy = (np.floor(px / cell) - ox).astype(np.int64), (np.floor(py / cell) - oy).astype(np.int64)
    inside = (pcx >= 1) & (pcx <= width - 2) & (pcy >= 1) & (pcy <= height - 2)
    pts = np.flatnonzero(inside)
    ckey = ((pcy[pts] * width + pcx[pts])[:, None] + (_CELL_DY * width + _CELL_DX)).ravel()
    counts = count[ckey]
    total = int(counts.sum())
    if total == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    pt = np.repeat(np.repeat(pts, 9), counts)
    kp = order[np.repeat(start[ckey] - (np.cumsum(counts) - counts), counts) + np.arange(total)]
    dx, dy = kx[kp] - px[pt], ky[kp] - py[pt]
    ok = dx * dx + dy * dy <= radius * radius
    if kp_taken is not None:
        ok &= ~kp_taken[kp]
    return pt[ok], kp[ok]


def _ratio_test(pt: np.ndarray, kp: np.ndarray, dist: np.ndarray, ratio: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The best candidate (pt, kp, dist) of each map point ``pt``, kept when its descriptor distance is below
    ``ratio`` x that of the second best (Lowe's ratio test) or when it is the only candidate."""
    o = np.lexsort((dist, pt))
    pt, kp, dist = pt[o], kp[o], dist[o]
    first = np.r_[True, pt[1:] != pt[:-1]]
    idx_first = np.flatnonzero(first)
    has_second = np.r_[idx_first[1:], len(pt)] - idx_first > 1
    second = np.full(len(idx_first), np.inf, np.float32)
    second[has_second] = dist[idx_first[has_second] + 1]
    best = idx_first[(dist[idx_first] < ratio * second) | ~has_second]
    return pt[best], kp[best], dist[best]


@dataclass(frozen=True, eq=False)
class FrameFeatures:
    """A frame as the SLAM stages see it: features, undistorted keypoints and their colours.

    keypoints: (N, 2) float64 undistorted pixels (ideal pinhole camera); colors: (N, 3) uint8 RGB;
    thumbnail: small RGB copy of the image for viewers (None when not kept).
    """

    index: int
    frame_id: int
    timestamp: float
    features: Features
    keypoints: np.ndarray
    colors: np.ndarray
    thumbnail: np.ndarray | None = None
    signature: np.ndarray | None = None
    """(D,) float32 unit-norm global image signature (a tiny zero-mean thumbnail), for relocalization."""

    def __len__(self) -> int:
        return len(self.keypoints)


def image_signature(gray: np.ndarray, size: tuple[int, int] = (32, 24)) -> np.ndarray:
    """Global signature of an image for place recognition: the (w x h) area-downsampled grey image,
    blurred, zero-mean and unit-norm, as (w*h,) float32. Similar views have a dot product near 1."""
    small = cv2.resize(gray, size, interpolation=cv2.INTER_AREA).astype(np.float32)
    small = cv2.GaussianBlur(small, (3, 3), 0).ravel()
    small -= small.mean()
    n = float(np.linalg.norm(small))
    return small / n if n > 1e-6 else small
