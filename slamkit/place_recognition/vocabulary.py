"""A visual vocabulary: a hierarchical k-majority (binary) or k-means (float) tree of visual words.

The bag-of-words scheme of DBoW2 (Gálvez-López and Tardós, 2012), as used by ORB-SLAM: descriptors are
clustered recursively into ``branching`` groups per node for ``depth`` levels; the leaves are the words.
A descriptor is quantised by descending the tree (``depth x branching`` distance computations), so its cost
does not depend on the vocabulary size. Words are weighted by TF-IDF, the IDF learned from the training
images; a bag of words is an L1-normalised sparse vector.

Descriptor kinds (:data:`DESCRIPTOR_KINDS`):

* ``binary``: (N, B) uint8, packed bits (ORB: B = 32, 256 bits); Hamming distance; centres are bitwise
  majorities (k-majority, "k-medians" of bits).
* ``float``: (N, D) float32/float64 (SIFT, XFeat, ...); L2 distance; centres are means (k-means).

Anything else raises ConfigError. COLMAP's own vocabulary tree (``pycolmap.VisualIndex``) is not used: in
pycolmap 4.2.1 it only takes 128-d float descriptors and its ``query`` returns no results to Python.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Iterable, Literal

import numpy as np

from ..errors import ConfigError
from ..features import hamming

DescriptorKind = Literal["binary", "float"]
DESCRIPTOR_KINDS: tuple[str, ...] = ("binary", "float")

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)
_FORMAT_VERSION = 1


@dataclass(frozen=True)
class VocabularyConfig:
    """Shape and training of a vocabulary tree."""

    branching: int = 10
    """Children per node (k of the k-majority / k-means clustering), >= 2."""
    depth: int = 4
    """Levels below the root; at most ``branching ** depth`` words."""
    iterations: int = 10
    """Largest number of clustering iterations per node (stops earlier when assignments settle)."""
    seed: int = 0
    """Seed of the k-means++ seeding: the same descriptors and seed give the same vocabulary."""

    def __post_init__(self) -> None:
        for name, low in (("branching", 2), ("depth", 1), ("iterations", 1)):
            value = getattr(self, name)
            if int(value) != value or value < low:
                raise ConfigError(f"VocabularyConfig.{name} must be an integer >= {low} (got {value!r})")


def descriptor_kind(descriptors: np.ndarray, where: str = "descriptors") -> DescriptorKind:
    """``binary`` for uint8 (packed bits), ``float`` for float32/64; ConfigError otherwise (naming ``where``)."""
    d = np.asarray(descriptors)
    if d.ndim != 2:
        raise ConfigError(f"{where}: expected an (N, D) array, got shape {d.shape}")
    if d.dtype == np.uint8:
        return "binary"
    if d.dtype in (np.float32, np.float64):
        return "float"
    raise ConfigError(f"{where}: dtype {d.dtype} is not a supported descriptor kind "
                      f"(uint8 packed binary such as ORB, or float32 such as SIFT/XFeat)")


def _distances(x: np.ndarray, centers: np.ndarray, kind: DescriptorKind) -> np.ndarray:
    """(N, K) distances of descriptors ``x`` (N, D) to ``centers`` (K, D): Hamming bits or squared L2."""
    if kind == "binary":
        return np.concatenate([_POPCOUNT[x[i:i + 8192, None, :] ^ centers[None, :, :]].sum(axis=2, dtype=np.int32)
                               for i in range(0, len(x), 8192)] or [np.zeros((0, len(centers)), np.int32)])
    x = x.astype(np.float32, copy=False)
    c = centers.astype(np.float32, copy=False)
    d2 = (x * x).sum(1)[:, None] + (c * c).sum(1)[None, :] - 2.0 * x @ c.T
    return np.maximum(d2, 0.0)


def _centroids(x: np.ndarray, labels: np.ndarray, k: int, old: np.ndarray, kind: DescriptorKind) -> np.ndarray:
    """New centres: bitwise majority (binary) or mean (float) of each cluster; an empty cluster keeps its
    old centre."""
    new = old.copy()
    for j in range(k):
        members = x[labels == j]
        if len(members) == 0:
            continue
        if kind == "binary":
            bits = np.unpackbits(members, axis=1)
            new[j] = np.packbits(2 * bits.sum(0, dtype=np.int64) >= len(members))
        else:
            new[j] = members.mean(0)
    return new


def _cluster(x: np.ndarray, k: int, iterations: int, rng: np.random.Generator,
             kind: DescriptorKind) -> np.ndarray:
    """Labels (N,) of a k-means++-seeded k-majority / k-means clustering of ``x`` (N > k) into k groups."""
    centers = np.empty((k, x.shape[1]), x.dtype)
    centers[0] = x[rng.integers(len(x))]
    nearest = _distances(x, centers[:1], kind)[:, 0].astype(np.float64)
    for j in range(1, k):
        p = nearest ** 2
        total = p.sum()
        pick = rng.integers(len(x)) if total <= 0 else rng.choice(len(x), p=p / total)
        centers[j] = x[pick]
        nearest = np.minimum(nearest, _distances(x, centers[j:j + 1], kind)[:, 0])
    labels = np.full(len(x), -1, np.int64)
    for _ in range(iterations):
        new = np.argmin(_distances(x, centers, kind), axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        centers = _centroids(x, labels, k, centers, kind)
    return labels


class Vocabulary:
    """A trained vocabulary tree (read-only once built).

    Arrays (node 0 is the root):
        centers: (num_nodes, D) uint8 or float32 cluster centres (the root's is unused).
        children: (num_nodes, branching) int32 child node ids, -1 where absent (all -1 at a leaf).
        node_word: (num_nodes,) int32 word id of a leaf node, -1 for inner nodes.
        idf: (num_words,) float32 inverse document frequency ``log(N_images / N_images_with_word)``.
    """

    def __init__(self, kind: DescriptorKind, centers: np.ndarray, children: np.ndarray, node_word: np.ndarray,
                 idf: np.ndarray):
        if kind not in DESCRIPTOR_KINDS:
            raise ConfigError(f"vocabulary kind must be one of {DESCRIPTOR_KINDS} (got {kind!r})")
        self.kind: DescriptorKind = kind
        self.centers = np.ascontiguousarray(centers, np.uint8 if kind == "binary" else np.float32)
        self.children = np.asarray(children, np.int32)
        self.node_word = np.asarray(node_word, np.int32)
        self.idf = np.asarray(idf, np.float32)
        self._center_words = hamming.words(self.centers) if kind == "binary" else None  # for the compiled descent
        if self.children.shape[0] != len(self.centers) or len(self.node_word) != len(self.centers):
            raise ConfigError("vocabulary arrays disagree on the number of nodes")
        if len(self.idf) != int(self.node_word.max()) + 1:
            raise ConfigError("vocabulary idf length differs from the number of words")

    @property
    def num_words(self) -> int:
        return len(self.idf)

    @property
    def descriptor_size(self) -> int:
        """Bytes (binary) or dimensions (float) of the descriptors this vocabulary quantises."""
        return self.centers.shape[1]

    def __repr__(self) -> str:
        return (f"Vocabulary({self.kind}, {self.num_words} words, branching {self.children.shape[1]}, "
                f"descriptor size {self.descriptor_size})")

    @classmethod
    def train(cls, descriptors_per_image: Iterable[np.ndarray], config: VocabularyConfig | None = None,
              max_descriptors: int = 100_000) -> "Vocabulary":
        """Build the tree from the descriptors of several training images and learn the IDF from them.

        descriptors_per_image: one (N_i, D) array per image, all of the same kind and size.
        max_descriptors: a deterministic random subset of at most this many descriptors builds the tree
            (the IDF uses every descriptor).
        """
        cfg = config or VocabularyConfig()
        images = [np.asarray(d) for d in descriptors_per_image]
        images = [d for d in images if len(d)]
        if len(images) < 2:
            raise ConfigError("Vocabulary.train needs descriptors of at least 2 images")
        kind = descriptor_kind(images[0], "training descriptors")
        for i, d in enumerate(images):
            if descriptor_kind(d, f"training descriptors of image {i}") != kind or d.shape[1] != images[0].shape[1]:
                raise ConfigError(f"training descriptors of image {i}: kind or size differs from image 0")
        x = np.concatenate(images)
        if kind == "float":
            x = x.astype(np.float32)
        rng = np.random.default_rng(cfg.seed)
        if len(x) > max_descriptors:
            x = x[np.sort(rng.choice(len(x), max_descriptors, replace=False))]
        centers, children, node_word = _build_tree(x, cfg, rng, kind)
        num_words = int(node_word.max()) + 1
        vocabulary = cls(kind, centers, children, node_word, np.zeros(num_words, np.float32))
        seen = np.zeros(num_words, np.int64)
        for d in images:
            seen[np.unique(vocabulary.transform(d))] += 1
        vocabulary.idf = np.log(len(images) / np.maximum(seen, 1)).astype(np.float32)
        return vocabulary

    def transform(self, descriptors: np.ndarray) -> np.ndarray:
        """Word ids (N,) int32 of descriptors (N, D): descend the tree to the nearest child at each level."""
        d = self._check(descriptors)
        if self.kind == "binary" and len(d):  # compiled descent: the same words as the steps below
            return hamming.descend(hamming.words(d), self._center_words, self.children, self.node_word)
        return self._transform_arrays(d)

    def _transform_arrays(self, d: np.ndarray) -> np.ndarray:
        """:meth:`transform` level by level in numpy (float descriptors; the reference of the compiled path)."""
        node = np.zeros(len(d), np.int64)
        while len(d):
            ch = self.children[node]
            active = (ch >= 0).any(axis=1)
            if not active.any():
                break
            idx = np.flatnonzero(active)
            cand = ch[idx]
            dist = _distances_to_children(d[idx], self.centers[np.maximum(cand, 0)], self.kind)
            dist = np.where(cand >= 0, dist, np.inf)
            node[idx] = cand[np.arange(len(idx)), np.argmin(dist, axis=1)]
        return self.node_word[node]

    def bow(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The TF-IDF bag of words of one image: (word ids (M,) int32 ascending, weights (M,) float32 summing
        to 1). Words with zero weight (present in every training image) are left out; empty when none."""
        words = self.transform(descriptors)
        if len(words) == 0:
            return np.zeros(0, np.int32), np.zeros(0, np.float32)
        ids, counts = np.unique(words, return_counts=True)
        w = counts / len(words) * self.idf[ids]
        keep = w > 0
        ids, w = ids[keep], w[keep]
        total = w.sum()
        return ids.astype(np.int32), (w / total if total > 0 else w).astype(np.float32)

    def _check(self, descriptors: np.ndarray) -> np.ndarray:
        d = np.asarray(descriptors)
        if d.ndim == 2 and len(d) == 0:
            return d.reshape(0, self.descriptor_size)
        kind = descriptor_kind(d)
        if kind != self.kind or d.shape[1] != self.descriptor_size:
            raise ConfigError(f"descriptors: {kind} of size {d.shape[1]} do not fit this {self.kind} vocabulary "
                              f"of descriptor size {self.descriptor_size}")
        return d if kind == "binary" else d.astype(np.float32, copy=False)

    def to_arrays(self, prefix: str = "vocabulary_") -> dict[str, np.ndarray]:
        """Plain arrays (``np.savez``-able, no pickle) from which :meth:`from_arrays` rebuilds the vocabulary."""
        return {f"{prefix}format": np.array(_FORMAT_VERSION, np.int64),
                f"{prefix}binary": np.array(self.kind == "binary"),
                f"{prefix}centers": self.centers, f"{prefix}children": self.children,
                f"{prefix}node_word": self.node_word, f"{prefix}idf": self.idf}

    @classmethod
    def from_arrays(cls, arrays, prefix: str = "vocabulary_") -> "Vocabulary":
        """Inverse of :meth:`to_arrays` (``arrays`` may be an opened ``.npz``); ConfigError when incomplete."""
        keys = ("format", "binary", "centers", "children", "node_word", "idf")
        missing = [k for k in keys if f"{prefix}{k}" not in arrays]
        if missing:
            raise ConfigError(f"vocabulary arrays: missing {', '.join(prefix + k for k in missing)}")
        if int(arrays[f"{prefix}format"]) != _FORMAT_VERSION:
            raise ConfigError(f"vocabulary arrays: format {int(arrays[f'{prefix}format'])}, "
                              f"expected {_FORMAT_VERSION}")
        kind: DescriptorKind = "binary" if bool(arrays[f"{prefix}binary"]) else "float"
        return cls(kind, arrays[f"{prefix}centers"], arrays[f"{prefix}children"], arrays[f"{prefix}node_word"],
                   arrays[f"{prefix}idf"])


def _distances_to_children(x: np.ndarray, centers: np.ndarray, kind: DescriptorKind) -> np.ndarray:
    """(N, K) distances of each descriptor x[i] (N, D) to its own candidate centres (N, K, D)."""
    if kind == "binary":
        return _POPCOUNT[x[:, None, :] ^ centers].sum(axis=2, dtype=np.int32).astype(np.float64)
    diff = centers - x[:, None, :]
    return np.einsum("nkd,nkd->nk", diff, diff)


def _build_tree(x: np.ndarray, cfg: VocabularyConfig, rng: np.random.Generator,
                kind: DescriptorKind) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Breadth-first hierarchical clustering; returns (centers, children, node_word) as in :class:`Vocabulary`."""
    k = cfg.branching
    centers = [np.zeros(x.shape[1], x.dtype)]
    children = [np.full(k, -1, np.int32)]
    queue = deque([(0, np.arange(len(x)), 0)])
    while queue:
        node, members, level = queue.popleft()
        if level >= cfg.depth or len(members) <= k:
            continue
        labels = _cluster(x[members], k, cfg.iterations, rng, kind)
        for j in range(k):
            sub = members[labels == j]
            if len(sub) == 0:
                continue
            child = len(centers)
            centers.append(_centroids(x[sub], np.zeros(len(sub), np.int64), 1, x[sub[:1]], kind)[0])
            children.append(np.full(k, -1, np.int32))
            children[node][j] = child
            queue.append((child, sub, level + 1))
    children_arr = np.stack(children)
    leaf = children_arr.max(axis=1) < 0
    node_word = np.full(len(centers), -1, np.int32)
    node_word[leaf] = np.arange(int(leaf.sum()), dtype=np.int32)
    return np.stack(centers), children_arr, node_word
