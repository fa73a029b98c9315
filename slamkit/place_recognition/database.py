"""A keyframe database for place recognition: bags of words in an inverted file (DBoW2 / ORB-SLAM style).

Each keyframe is stored as its TF-IDF bag of words (:meth:`Vocabulary.bow`). The inverted file holds, for
every word, the keyframes that contain it with their weights, so a query only visits the keyframes that
share a word with it; scores are DBoW2's L1 score ``s(v, w) = 1 - |v - w|_1 / 2`` of L1-normalised vectors,
which equals ``sum_i min(v_i, w_i)``: 1 for identical bags, 0 for bags without a common word.

The inverted file alone makes a query cost proportional to the number of (keyframe, word) entries it
visits, which grows with the database. ``max_postings`` bounds it: when the query's words would visit more
entries, only its rarest words in the database (shortest posting lists, the most discriminative ones, as a
stop list drops the most frequent words in Sivic and Zisserman's Video Google) are scored until the budget is
spent, so the query time stays bounded and the scores become partial sums (lower bounds of the full score).
"""

from __future__ import annotations

from typing import Collection, Iterable

import numpy as np

from ..errors import ConfigError
from .vocabulary import Vocabulary

_FORMAT_VERSION = 1


class _Postings:
    """Growable (slot, weight) list of one word; removal swaps with the last entry (order is irrelevant)."""

    __slots__ = ("slots", "weights", "n")

    def __init__(self) -> None:
        self.slots = np.empty(8, np.int32)
        self.weights = np.empty(8, np.float32)
        self.n = 0

    def append(self, slot: int, weight: float) -> None:
        if self.n == len(self.slots):
            self.slots = np.resize(self.slots, 2 * self.n)
            self.weights = np.resize(self.weights, 2 * self.n)
        self.slots[self.n] = slot
        self.weights[self.n] = weight
        self.n += 1

    def discard(self, slot: int) -> None:
        hit = np.flatnonzero(self.slots[:self.n] == slot)
        if len(hit):
            last = self.n - 1
            self.slots[hit[0]] = self.slots[last]
            self.weights[hit[0]] = self.weights[last]
            self.n = last


class PlaceDatabase:
    """Keyframes as bags of words, queried through an inverted file.

    ``add(image_id, descriptors)`` a keyframe, ``remove(image_id)`` it when culled, ``query(descriptors, k,
    exclude)`` the most similar keyframes. Image ids are any non-negative integers (e.g. pycolmap image ids).
    ``max_postings``: most (keyframe, word) entries one query visits (None: no bound); see the module doc.
    """

    def __init__(self, vocabulary: Vocabulary, max_postings: int | None = 200_000):
        if max_postings is not None and (int(max_postings) != max_postings or max_postings < 1):
            raise ConfigError(f"max_postings must be a positive integer or None (got {max_postings!r})")
        self.vocabulary = vocabulary
        self.max_postings = max_postings
        self._slot_of: dict[int, int] = {}
        self._image_of_slot: list[int] = []
        self._bows: list[tuple[np.ndarray, np.ndarray] | None] = []
        self._free: list[int] = []
        self._postings: dict[int, _Postings] = {}

    def __len__(self) -> int:
        return len(self._slot_of)

    def __contains__(self, image_id: int) -> bool:
        return int(image_id) in self._slot_of

    @property
    def image_ids(self) -> list[int]:
        """Ids of the stored keyframes, ascending."""
        return sorted(self._slot_of)

    def __repr__(self) -> str:
        return f"PlaceDatabase({len(self)} keyframes, {self.vocabulary!r})"

    def add(self, image_id: int, descriptors: np.ndarray) -> None:
        """Store keyframe ``image_id`` with its descriptors (N, D) (replacing an entry of the same id)."""
        self.add_bow(image_id, *self.vocabulary.bow(descriptors))

    def add_bow(self, image_id: int, words: np.ndarray, weights: np.ndarray) -> None:
        """Store a precomputed bag of words (from :meth:`Vocabulary.bow` of the same vocabulary)."""
        image_id = _check_id(image_id)
        words = np.asarray(words, np.int32)
        weights = np.asarray(weights, np.float32)
        if words.shape != weights.shape or words.ndim != 1:
            raise ConfigError(f"image {image_id}: words and weights must be (M,) arrays of the same length")
        if len(words) and (words.min() < 0 or words.max() >= self.vocabulary.num_words):
            raise ConfigError(f"image {image_id}: word id outside the vocabulary of {self.vocabulary.num_words}")
        if image_id in self._slot_of:
            self.remove(image_id)
        slot = self._free.pop() if self._free else len(self._bows)
        if slot == len(self._bows):
            self._bows.append(None)
            self._image_of_slot.append(-1)
        self._bows[slot] = (words, weights)
        self._image_of_slot[slot] = image_id
        self._slot_of[image_id] = slot
        for w, v in zip(words.tolist(), weights.tolist()):
            post = self._postings.get(w)
            if post is None:
                post = self._postings[w] = _Postings()
            post.append(slot, v)

    def remove(self, image_id: int) -> None:
        """Forget keyframe ``image_id`` (keyframe culling); KeyError when it is not stored."""
        image_id = _check_id(image_id)
        slot = self._slot_of.pop(image_id, None)
        if slot is None:
            raise KeyError(f"image {image_id} is not in the place database")
        words, _ = self._bows[slot]
        for w in words.tolist():
            self._postings[w].discard(slot)
        self._bows[slot] = None
        self._image_of_slot[slot] = -1
        self._free.append(slot)

    def query(self, descriptors: np.ndarray, k: int = 10,
              exclude: Collection[int] = ()) -> list[tuple[int, float]]:
        """The ``k`` stored keyframes most similar to ``descriptors`` (N, D): ``[(image_id, score)]`` by
        decreasing score in (0, 1], ties by ascending id; keyframes in ``exclude`` and those sharing no word
        with the query are left out."""
        return self.query_bow(*self.vocabulary.bow(descriptors), k=k, exclude=exclude)

    def query_bow(self, words: np.ndarray, weights: np.ndarray, k: int = 10,
                  exclude: Collection[int] = ()) -> list[tuple[int, float]]:
        """:meth:`query` for a precomputed bag of words."""
        if int(k) != k or k < 1:
            raise ConfigError(f"query: k must be a positive integer (got {k!r})")
        scores = self._scores(np.asarray(words, np.int32), np.asarray(weights, np.float32))
        for image_id in exclude:
            slot = self._slot_of.get(int(image_id))
            if slot is not None:
                scores[slot] = 0.0
        candidates = np.flatnonzero(scores > 0)
        if len(candidates) > k:
            candidates = candidates[np.argpartition(-scores[candidates], k - 1)[:k]]
        ids = np.array([self._image_of_slot[s] for s in candidates], np.int64)
        order = np.lexsort((ids, -scores[candidates]))
        return [(int(ids[i]), float(scores[candidates[i]])) for i in order[:k]]

    def score(self, image_a: int, image_b: int) -> float:
        """L1 score between two stored keyframes (e.g. to take the lowest score of a keyframe's covisible
        neighbours as the acceptance threshold of its loop candidates, as ORB-SLAM does)."""
        (wa, va), (wb, vb) = self._bow_of(image_a), self._bow_of(image_b)
        _, ia, ib = np.intersect1d(wa, wb, assume_unique=True, return_indices=True)
        return float(np.minimum(va[ia], vb[ib]).sum())

    def _bow_of(self, image_id: int) -> tuple[np.ndarray, np.ndarray]:
        slot = self._slot_of.get(int(image_id))
        if slot is None:
            raise KeyError(f"image {image_id} is not in the place database")
        return self._bows[slot]

    def _scores(self, words: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """(num_slots,) float64 L1 scores of every slot against the query bag (0 for free slots)."""
        hits = [(post, v) for post, v in ((self._postings.get(w), v) for w, v in zip(words.tolist(), weights.tolist()))
                if post is not None and post.n > 0]
        if self.max_postings is not None and sum(post.n for post, _ in hits) > self.max_postings:
            hits.sort(key=lambda item: item[0].n)  # rarest words first
            lengths = np.cumsum([post.n for post, _ in hits])
            hits = hits[:max(1, int(np.searchsorted(lengths, self.max_postings, side="right")))]
        slots = [post.slots[:post.n] for post, _ in hits]
        mins = [np.minimum(post.weights[:post.n], v) for post, v in hits]
        if not slots:
            return np.zeros(len(self._bows))
        return np.bincount(np.concatenate(slots), weights=np.concatenate(mins), minlength=len(self._bows))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays (``np.savez``-able, no pickle): the vocabulary plus the stored bags as CSR rows."""
        ids = self.image_ids
        bows = [self._bow_of(i) for i in ids]
        lengths = [len(w) for w, _ in bows]
        out = self.vocabulary.to_arrays()
        out.update({
            "database_format": np.array(_FORMAT_VERSION, np.int64),
            "database_max_postings": np.array(-1 if self.max_postings is None else self.max_postings, np.int64),
            "database_image_ids": np.array(ids, np.int64),
            "database_indptr": np.concatenate([[0], np.cumsum(lengths, dtype=np.int64)]).astype(np.int64),
            "database_words": np.concatenate([w for w, _ in bows] or [np.zeros(0, np.int32)]).astype(np.int32),
            "database_weights": np.concatenate([v for _, v in bows] or [np.zeros(0, np.float32)]).astype(np.float32),
        })
        return out

    @classmethod
    def from_arrays(cls, arrays) -> "PlaceDatabase":
        """Inverse of :meth:`to_arrays` (``arrays`` may be an opened ``.npz``); ConfigError when incomplete."""
        keys = ("database_format", "database_image_ids", "database_indptr", "database_words", "database_weights")
        missing = [key for key in keys if key not in arrays]
        if missing:
            raise ConfigError(f"place database arrays: missing {', '.join(missing)}")
        if int(arrays["database_format"]) != _FORMAT_VERSION:
            raise ConfigError(f"place database arrays: format {int(arrays['database_format'])}, "
                              f"expected {_FORMAT_VERSION}")
        budget = int(arrays["database_max_postings"]) if "database_max_postings" in arrays else -1
        db = cls(Vocabulary.from_arrays(arrays), None if budget < 0 else budget)
        ids, ptr = np.asarray(arrays["database_image_ids"]), np.asarray(arrays["database_indptr"])
        words, weights = np.asarray(arrays["database_words"]), np.asarray(arrays["database_weights"])
        if len(ptr) != len(ids) + 1 or ptr[-1] != len(words) or len(words) != len(weights):
            raise ConfigError("place database arrays: indptr, words and weights do not fit together")
        for i, image_id in enumerate(ids.tolist()):
            db.add_bow(image_id, words[ptr[i]:ptr[i + 1]], weights[ptr[i]:ptr[i + 1]])
        return db

    def add_many(self, items: Iterable[tuple[int, np.ndarray]]) -> None:
        """``add`` each ``(image_id, descriptors)`` in turn."""
        for image_id, descriptors in items:
            self.add(image_id, descriptors)


def _check_id(image_id) -> int:
    if isinstance(image_id, (bool, np.bool_)) or int(image_id) != image_id or image_id < 0:
        raise ConfigError(f"image_id must be a non-negative integer (got {image_id!r})")
    return int(image_id)
