"""Incremental diffing for the map view: what changed between the map the scene shows and a new reading.

Pure numpy, no meshcat and no pycolmap, so every decision of an update can be tested without a server:

- :func:`diff_keyframes`: which keyframes are new, which moved (pose changed), whether anything drawn from
  the keyframes (frustums, path colours) must be re-sent.
- :class:`PointStore`: the points as the scene shows them, grouped by the keyframe that introduced them
  (one meshcat object per group); deleted points are tombstones until they pile up.
- :func:`diff_points`: given a :class:`PointsRead` (what was read from the map), the points added,
  removed and updated, and the groups to re-send. A group is re-sent when one of its points moved by more
  than the tolerance or was added or removed; what the scene shows is always what was last sent, so small
  moves accumulate until they are re-sent.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_NO_IDS = np.empty(0, np.int64)


def lookup(values: np.ndarray, sorted_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(found (M,) bool, positions (M,)) of ``values`` in the sorted array ``sorted_ref``."""
    if len(sorted_ref) == 0 or len(values) == 0:
        return np.zeros(len(values), bool), np.zeros(len(values), np.int64)
    pos = np.minimum(np.searchsorted(sorted_ref, values), len(sorted_ref) - 1)
    return sorted_ref[pos] == values, pos


def isin_sorted(values: np.ndarray, sorted_ref: np.ndarray) -> np.ndarray:
    """Boolean mask: which of ``values`` are in the sorted array ``sorted_ref``."""
    if len(sorted_ref) == 0 or len(values) == 0:
        return np.zeros(len(values), bool)
    pos = np.minimum(np.searchsorted(sorted_ref, values), len(sorted_ref) - 1)
    return sorted_ref[pos] == values


# ---------------------------------------------------------------------------------------------- keyframes


@dataclass(frozen=True)
class KeyframeChanges:
    """Keyframes of a new reading against those shown: ``new`` and ``moved`` image ids (ascending);
    ``changed``: the keyframe set, a pose or a timestamp differs (frustums and colours must be re-sent)."""

    new: list[int]
    moved: list[int]
    changed: bool
    first_new: int
    """The smallest new keyframe id (else the newest keyframe; 0 without keyframes): no point added now
    is introduced before it."""
    newest: int
    """The largest keyframe id (0 without keyframes)."""

    @property
    def dirty(self) -> list[int]:
        """New then moved keyframes: those whose observations can have changed."""
        return self.new + self.moved

    def many_moved(self, num_keyframes: int) -> bool:
        """More than half the keyframes (and more than 8) moved: a global adjustment, read every point."""
        return len(self.moved) > max(8, num_keyframes // 2)


def diff_keyframes(old_ids: np.ndarray, old_poses: np.ndarray, old_times: np.ndarray, ids: np.ndarray,
                   poses: np.ndarray, times: np.ndarray) -> KeyframeChanges:
    """Shown keyframes (old_ids (K,) sorted, old_poses (K, 3, 4) cam_from_world, old_times (K,) seconds)
    against a new reading of the same arrays: which are new and which moved (exact comparison)."""
    found, rows = lookup(ids, old_ids)
    moved_mask = np.zeros(len(ids), bool)
    moved_mask[found] = np.any(poses[found] != old_poses[rows[found]], axis=(1, 2))
    new = ids[~found].tolist()
    moved = ids[moved_mask].tolist()
    changed = bool(new or moved) or len(ids) != len(old_ids) or not np.array_equal(times, old_times)
    first_new = min(new) if new else (int(ids[-1]) if len(ids) else 0)
    newest = int(ids[-1]) if len(ids) else 0
    return KeyframeChanges(new, moved, changed, first_new, newest)


def introductions(new_ids: np.ndarray, observers: dict[int, np.ndarray], first_new_keyframe: int,
                  newest_keyframe: int) -> np.ndarray:
    """The keyframe that introduced each new point: the second-smallest keyframe observing it (a point
    needs two views), never earlier than the first keyframe that is new in this update; the newest
    keyframe when no observer is known."""
    out = np.full(len(new_ids), newest_keyframe, np.int64)
    if len(new_ids) == 0 or not observers:
        return out
    pid = np.concatenate([v for v in observers.values()])
    iid = np.concatenate([np.full(len(v), k, np.int64) for k, v in observers.items()])
    keep = np.isin(pid, new_ids)
    pid, iid = pid[keep], iid[keep]
    if len(pid):
        order = np.lexsort((iid, pid))
        pid, iid = pid[order], iid[order]
        starts = np.flatnonzero(np.r_[True, pid[1:] != pid[:-1]])
        counts = np.diff(np.r_[starts, len(pid)])
        second = np.where(counts >= 2, iid[np.minimum(starts + 1, len(pid) - 1)], iid[starts])
        pos = np.searchsorted(new_ids, pid[starts])
        out[pos] = second
    return np.maximum(out, first_new_keyframe)


# ---------------------------------------------------------------------------------------------- points


@dataclass(frozen=True)
class PointsRead:
    """Map points read for one update.

    ids: (M,) sorted int64 point ids read; xyz: (M, 3) float32 map units; rgb: (M, 3) uint8, read for the
    points the store does not hold (zeros elsewhere); observers: keyframe id -> (P,) ids of points it
    observes (for the introductions of new points); complete: the observer lists are whole observation
    lists (kept to find deleted points next time); deleted: (D,) ids of points the store holds that are
    no longer in the map.
    """

    ids: np.ndarray
    xyz: np.ndarray
    rgb: np.ndarray
    observers: dict[int, np.ndarray] = field(default_factory=dict)
    complete: bool = False
    deleted: np.ndarray = field(default_factory=lambda: _NO_IDS)


@dataclass(frozen=True)
class PointChanges:
    """What an update changes in the :class:`PointStore` and which point groups it re-sends.

    added_*: (N,) ids, (N, 3) float32 xyz, (N, 3) uint8 rgb and (N,) introducing keyframes of new points;
    removed_rows: (D,) store rows of deleted points; updated_rows / updated_xyz: (U,) store rows and
    (U, 3) positions of known points in re-sent groups (shown as read now); moved_ids: (V,) ids of the
    points that moved beyond the tolerance; groups: introducing keyframes of the groups to re-send.
    """

    added_ids: np.ndarray
    added_xyz: np.ndarray
    added_rgb: np.ndarray
    added_groups: np.ndarray
    removed_rows: np.ndarray
    removed_ids: np.ndarray
    updated_rows: np.ndarray
    updated_xyz: np.ndarray
    moved_ids: np.ndarray
    groups: frozenset[int]


class PointStore:
    """The map points as the scene shows them, sorted by id: ids (N,) int64, xyz (N, 3) float32, rgb
    (N, 3) uint8 and the introducing keyframe (N,) int64, -1 for a deleted point (a tombstone)."""

    def __init__(self) -> None:
        self.pid = np.empty(0, np.int64)
        self.xyz = np.empty((0, 3), np.float32)
        self.rgb = np.empty((0, 3), np.uint8)
        self.intro = np.empty(0, np.int64)
        self.n_dead = 0

    @property
    def num_points(self) -> int:
        """Live points (tombstones excluded)."""
        return len(self.pid) - self.n_dead

    def alive(self) -> np.ndarray:
        """(N,) bool: the rows that are not tombstones."""
        return self.intro >= 0

    def live_ids(self) -> np.ndarray:
        """(N,) sorted ids of the live points."""
        return self.pid[self.intro >= 0]

    def groups(self) -> set[int]:
        """Introducing keyframes of the live points (the point groups)."""
        return set(np.unique(self.intro[self.intro >= 0]).tolist())

    def lookup(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(found (M,) bool, rows (M,)) of point ids among the live rows of the store."""
        found, rows = lookup(ids, self.pid)
        if len(rows) and self.n_dead:
            found &= self.intro[rows] >= 0
        return found, rows

    def apply(self, changes: PointChanges) -> None:
        """Update positions, mark deleted points as tombstones, add new points; compact when more than
        1000 (and 5 %) are tombstones."""
        self.xyz[changes.updated_rows] = changes.updated_xyz
        if len(changes.removed_rows):
            self.intro[changes.removed_rows] = -1
            self.n_dead += len(changes.removed_rows)
        if len(changes.added_ids):
            self.append(changes.added_ids, changes.added_xyz, changes.added_rgb, changes.added_groups)
        if self.n_dead > max(1000, len(self.pid) // 20):
            self.compact()

    def append(self, ids: np.ndarray, xyz: np.ndarray, rgb: np.ndarray, intro: np.ndarray) -> None:
        """Add new points; the store stays sorted by id (new points usually have the largest ids)."""
        if self.n_dead and isin_sorted(ids, self.pid).any():  # an id came back: drop its tombstone first
            self.compact()
        pid = np.concatenate([self.pid, ids])
        xyz = np.concatenate([self.xyz, np.asarray(xyz, np.float32)])
        rgb = np.concatenate([self.rgb, rgb])
        intro = np.concatenate([self.intro, intro])
        if len(self.pid) and len(ids) and ids[0] < self.pid[-1]:
            order = np.argsort(pid, kind="stable")
            pid, xyz, rgb, intro = pid[order], xyz[order], rgb[order], intro[order]
        self.pid, self.xyz, self.rgb, self.intro = pid, xyz, rgb, intro

    def compact(self) -> None:
        """Drop the tombstones."""
        keep = self.intro >= 0
        self.pid, self.xyz, self.rgb, self.intro = self.pid[keep], self.xyz[keep], self.rgb[keep], self.intro[keep]
        self.n_dead = 0

    def group_rows(self, keys: list[int]) -> dict[int, np.ndarray]:
        """Introducing keyframe -> (R,) store rows of its live points, for each of ``keys`` (ascending)."""
        if len(keys) <= 16:
            return {k: np.flatnonzero(self.intro == k) for k in keys}
        order = np.argsort(self.intro, kind="stable")
        sorted_intro = self.intro[order]
        out = {}
        for k in keys:
            lo, hi = np.searchsorted(sorted_intro, [k, k + 1])
            out[k] = order[lo:hi]
        return out


def diff_points(store: PointStore, read: PointsRead, keyframes: KeyframeChanges, tolerance: float
                ) -> PointChanges:
    """What ``read`` changes in ``store``: points added (with their introducing keyframes), removed,
    moved by more than ``tolerance`` (map units, max over x, y, z); the groups holding any of them are
    re-sent, with every known point of those groups updated to its position as read."""
    is_known, known_rows = store.lookup(read.ids)
    new_ids = read.ids[~is_known]
    new_intro = introductions(new_ids, read.observers, keyframes.first_new, keyframes.newest)
    found, del_rows = store.lookup(read.deleted)
    del_rows = del_rows[found]
    krows = known_rows[is_known]
    k_xyz = read.xyz[is_known]
    delta = np.abs(k_xyz - store.xyz[krows]).max(axis=1) if len(krows) else np.empty(0)
    moved = delta > tolerance
    groups = (set(store.intro[krows[moved]].tolist()) | set(store.intro[del_rows].tolist())
              | set(new_intro.tolist()))
    upd = np.isin(store.intro[krows], np.fromiter(groups, np.int64)) if groups else np.zeros(len(krows), bool)
    return PointChanges(added_ids=new_ids, added_xyz=read.xyz[~is_known], added_rgb=read.rgb[~is_known],
                        added_groups=new_intro, removed_rows=del_rows, removed_ids=store.pid[del_rows],
                        updated_rows=krows[upd], updated_xyz=k_xyz[upd], moved_ids=read.ids[is_known][moved],
                        groups=frozenset(int(k) for k in groups))


__all__ = ["lookup", "isin_sorted", "KeyframeChanges", "diff_keyframes", "introductions", "PointsRead",
           "PointChanges", "PointStore", "diff_points"]
