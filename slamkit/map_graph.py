"""The correspondence graph replayed: its image pairs in the order that rebuilds it exactly (compaction, sessions).

Moved out of :mod:`slamkit.map` (which re-exports :func:`graph_pairs`) to keep that module small."""

from __future__ import annotations

import heapq
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

if TYPE_CHECKING:  # pragma: no cover
    from .map import SlamMap


def graph_pairs(slam_map: "SlamMap") -> tuple[list[tuple[int, int]], list[np.ndarray]]:
    """The correspondence graph as image pairs (older, newer) in an order that, replayed with
    ``SlamMap.add_matches``, gives every keypoint the same correspondence list (same order) as the original.

    Pairs are grouped by the newer image (ascending: each keyframe is matched when it is inserted); within a
    group the order is recovered from the correspondence lists of the newer image's keypoints, which list the
    older images in insertion order. Returns (pairs, (M, 2) uint32 matches of each pair).
    """
    g = slam_map.graph
    groups: dict[int, list[int]] = {}
    for pair_id in g.num_matches_between_all_images():
        a, b = sorted(pycolmap.pair_id_to_image_pair(pair_id))
        groups.setdefault(int(b), []).append(int(a))
    pairs: list[tuple[int, int]] = []
    for b in sorted(groups):
        older = sorted(groups[b])
        if len(older) > 1:
            older = _insertion_order(g, b, older, slam_map.reconstruction.image(b).num_points2D())
        pairs.extend((a, b) for a in older)
    matches = [np.asarray(g.extract_matches_between_images(a, b), np.uint32).reshape(-1, 2) for a, b in pairs]
    return pairs, matches


def _insertion_order(g: pycolmap.CorrespondenceGraph, image_id: int, older: list[int], num_points2D: int
                     ) -> list[int]:
    """Order of the pairs (a, image_id), a in ``older``: each keypoint's correspondence list gives a partial
    order; a topological sort (ties by image id) completes it — unordered pairs never share a list."""
    after: dict[int, set[int]] = {a: set() for a in older}
    indegree = dict.fromkeys(older, 0)
    for j in range(num_points2D):
        seq = [c.image_id for c in g.extract_correspondences(image_id, j) if c.image_id < image_id]
        for x, y in zip(seq, seq[1:]):
            if x != y and y not in after[x]:
                after[x].add(y)
                indegree[y] += 1
    heap = [a for a in older if indegree[a] == 0]
    heapq.heapify(heap)
    out = []
    while heap:
        a = heapq.heappop(heap)
        out.append(a)
        for y in after[a]:
            indegree[y] -= 1
            if indegree[y] == 0:
                heapq.heappush(heap, y)
    if len(out) != len(older):  # pragma: no cover - contradictory lists cannot come from one insertion order
        out += [a for a in older if a not in out]
    return out
