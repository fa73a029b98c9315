"""The map view's incremental diffing (slamkit.viz.diff), pure: two snapshots of a small map written by hand,
and exactly the keyframes and points added, removed and updated, and the point groups to re-send. No
meshcat server and no pycolmap: what the view sends is checked in tests/test_viz.py."""

from __future__ import annotations

import numpy as np

from slamkit.viz.diff import PointsRead, PointStore, diff_keyframes, diff_points, introductions


def _poses(*tx: float) -> np.ndarray:
    """(K, 3, 4) cam_from_world: identity rotations, translations (tx, 0, 0)."""
    out = np.tile(np.eye(3, 4), (len(tx), 1, 1))
    out[:, 0, 3] = tx
    return out


def _read(ids, xyz, observers, deleted=(), rgb=None) -> PointsRead:
    ids = np.asarray(ids, np.int64)
    rgb = np.zeros((len(ids), 3), np.uint8) if rgb is None else np.asarray(rgb, np.uint8)
    return PointsRead(ids, np.asarray(xyz, np.float32), rgb,
                      {k: np.asarray(v, np.int64) for k, v in observers.items()}, True,
                      np.asarray(deleted, np.int64))


# snapshot A: keyframes 1, 2, 3; points 10-15 all seen by keyframe 1, 10-12 by 2 and 13-15 by 3
IDS_A = np.array([1, 2, 3])
POSES_A = _poses(0.0, -1.0, -2.0)
TIMES_A = np.array([0.0, 0.5, 1.0])
XYZ_A = np.array([[i, 0.0, 5.0] for i in range(10, 16)])
OBS_A = {1: [10, 11, 12, 13, 14, 15], 2: [10, 11, 12], 3: [13, 14, 15]}
RGB_A = [[10 * i, 0, 0] for i in range(6)]


def _store_after_a() -> PointStore:
    store = PointStore()
    kfs = diff_keyframes(np.empty(0, np.int64), np.empty((0, 3, 4)), np.empty(0), IDS_A, POSES_A, TIMES_A)
    store.apply(diff_points(store, _read(range(10, 16), XYZ_A, OBS_A, rgb=RGB_A), kfs, 0.01))
    return store


def test_keyframes_new_moved_and_unchanged():
    kfs = diff_keyframes(np.empty(0, np.int64), np.empty((0, 3, 4)), np.empty(0), IDS_A, POSES_A, TIMES_A)
    assert (kfs.new, kfs.moved, kfs.changed, kfs.first_new, kfs.newest) == ([1, 2, 3], [], True, 1, 3)
    same = diff_keyframes(IDS_A, POSES_A, TIMES_A, IDS_A, POSES_A.copy(), TIMES_A.copy())
    assert (same.new, same.moved, same.changed, same.first_new, same.newest) == ([], [], False, 3, 3)
    # keyframe 4 added, keyframe 2 moved (a local bundle adjustment)
    ids_b = np.array([1, 2, 3, 4])
    poses_b = _poses(0.0, -1.001, -2.0, -3.0)
    kfs = diff_keyframes(IDS_A, POSES_A, TIMES_A, ids_b, poses_b, np.array([0.0, 0.5, 1.0, 1.5]))
    assert (kfs.new, kfs.moved, kfs.dirty, kfs.changed, kfs.first_new, kfs.newest) == (
        [4], [2], [4, 2], True, 4, 4)
    # only a timestamp changed: nothing dirty, but the colours (recency) change
    retimed = diff_keyframes(IDS_A, POSES_A, TIMES_A, IDS_A, POSES_A, np.array([0.0, 0.7, 1.0]))
    assert (retimed.dirty, retimed.changed) == ([], True)
    # a keyframe removed: no point can have changed through it, but the frustums change
    culled = diff_keyframes(IDS_A, POSES_A, TIMES_A, IDS_A[[0, 2]], POSES_A[[0, 2]], TIMES_A[[0, 2]])
    assert (culled.dirty, culled.changed) == ([], True)


def test_many_moved_means_a_global_adjustment():
    ids = np.arange(1, 21)
    poses = _poses(*np.zeros(20))
    moved = poses.copy()
    moved[:11, 0, 3] = 1.0
    assert diff_keyframes(ids, poses, ids * 1.0, ids, moved, ids * 1.0).many_moved(20)  # 11 > max(8, 10)
    moved[10, 0, 3] = 0.0
    assert not diff_keyframes(ids, poses, ids * 1.0, ids, moved, ids * 1.0).many_moved(20)


def test_first_snapshot_adds_every_point_in_its_introducing_group():
    store = PointStore()
    kfs = diff_keyframes(np.empty(0, np.int64), np.empty((0, 3, 4)), np.empty(0), IDS_A, POSES_A, TIMES_A)
    ch = diff_points(store, _read(range(10, 16), XYZ_A, OBS_A, rgb=RGB_A), kfs, 0.01)
    assert ch.added_ids.tolist() == [10, 11, 12, 13, 14, 15]
    assert ch.added_groups.tolist() == [2, 2, 2, 3, 3, 3]  # the second keyframe observing each point
    assert ch.removed_ids.tolist() == [] and ch.moved_ids.tolist() == [] and len(ch.updated_rows) == 0
    assert ch.groups == {2, 3}
    store.apply(ch)
    assert store.live_ids().tolist() == [10, 11, 12, 13, 14, 15] and store.num_points == 6
    assert np.array_equal(store.rgb, np.array(RGB_A, np.uint8)) and store.groups() == {2, 3}


def test_second_snapshot_yields_exactly_what_changed():
    store = _store_after_a()
    kfs = diff_keyframes(IDS_A, POSES_A, TIMES_A, np.array([1, 2, 3, 4]), _poses(0.0, -1.001, -2.0, -3.0),
                         np.array([0.0, 0.5, 1.0, 1.5]))
    # snapshot B, read through the dirty keyframes 4 and 2: point 11 moved by 0.5 (beyond the tolerance),
    # point 10 by 0.001 (within it), point 12 was deleted; points 16 (seen by 4 only) and 20 (by 3 and 4)
    # are new; 13-15 (group 3) were not read
    xyz_b = {10: [10.001, 0, 5], 11: [11.5, 0, 5], 16: [16, 0, 5], 20: [20, 1, 5]}
    read = _read(list(xyz_b), list(xyz_b.values()), {4: [16, 20], 2: [10, 11], 3: [20]}, deleted=[12],
                 rgb=[[0, 0, 0], [0, 0, 0], [1, 2, 3], [4, 5, 6]])
    ch = diff_points(store, read, kfs, 0.01)
    assert ch.added_ids.tolist() == [16, 20]
    assert ch.added_groups.tolist() == [4, 4]  # never before the first new keyframe
    assert ch.added_rgb.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert ch.removed_ids.tolist() == [12]
    assert ch.moved_ids.tolist() == [11]
    assert ch.groups == {2, 4}  # group 2 moved and lost a point, group 4 is new; group 3 is untouched
    # every known point of a re-sent group is updated to its position as read (10 too, within tolerance)
    assert store.pid[ch.updated_rows].tolist() == [10, 11]
    assert np.allclose(ch.updated_xyz, [[10.001, 0, 5], [11.5, 0, 5]])

    store.apply(ch)
    assert store.live_ids().tolist() == [10, 11, 13, 14, 15, 16, 20] and store.n_dead == 1
    found, rows = store.lookup(np.array([10, 11, 12, 14]))
    assert found.tolist() == [True, True, False, True]
    assert np.allclose(store.xyz[rows[[0, 1, 3]]], [[10.001, 0, 5], [11.5, 0, 5], [14, 0, 5]], atol=1e-6)
    assert store.groups() == {2, 3, 4}


def test_sub_tolerance_moves_accumulate_until_sent():
    store = _store_after_a()
    same_kfs = diff_keyframes(IDS_A, POSES_A, TIMES_A, IDS_A, POSES_A, TIMES_A)
    xyz = XYZ_A.copy()
    xyz[0, 0] += 0.006  # point 10: within the tolerance, nothing is sent and the store keeps what was sent
    ch = diff_points(store, _read(range(10, 16), xyz, {}), same_kfs, 0.01)
    assert ch.groups == frozenset() and ch.moved_ids.tolist() == [] and len(ch.updated_rows) == 0
    store.apply(ch)
    assert store.xyz[0, 0] == np.float32(10.0)
    xyz[0, 0] += 0.006  # now 0.012 from what the scene shows: group 2 is re-sent
    ch = diff_points(store, _read(range(10, 16), xyz, {}), same_kfs, 0.01)
    assert ch.moved_ids.tolist() == [10] and ch.groups == {2}
    assert store.pid[ch.updated_rows].tolist() == [10, 11, 12]


def test_point_without_observers_goes_to_the_newest_keyframe():
    out = introductions(np.array([5, 6, 7]), {3: np.array([5, 6]), 9: np.array([6])}, 2, 9)
    assert out.tolist() == [3, 9, 9]  # 5: only keyframe 3; 6: second observer 9; 7: unknown -> newest


def test_tombstones_compact_and_a_returning_id_replaces_its_tombstone():
    store = _store_after_a()
    kfs = diff_keyframes(IDS_A, POSES_A, TIMES_A, IDS_A, POSES_A, TIMES_A)
    store.apply(diff_points(store, _read([], np.empty((0, 3)), {}, deleted=[11, 14]), kfs, 0.01))
    assert store.n_dead == 2 and store.live_ids().tolist() == [10, 12, 13, 15]
    # point id 11 comes back: its tombstone goes first, so the store stays sorted with unique ids
    ch = diff_points(store, _read([11], [[0.0, 0, 0]], {3: [11]}), kfs, 0.01)
    assert ch.added_ids.tolist() == [11] and ch.added_groups.tolist() == [3]
    store.apply(ch)
    assert store.pid.tolist() == [10, 11, 12, 13, 15] and store.n_dead == 0


def test_group_rows_same_for_few_and_many_groups():
    store = PointStore()
    rng = np.random.default_rng(0)
    intro = rng.integers(1, 30, 500)
    store.append(np.arange(500), rng.normal(size=(500, 3)), np.zeros((500, 3), np.uint8), intro)
    keys = list(range(0, 32))
    many = store.group_rows(keys)  # > 16 groups: one sort
    for k in keys:
        assert np.array_equal(np.sort(many[k]), np.flatnonzero(intro == k))
        assert np.array_equal(store.group_rows([k])[k], np.flatnonzero(intro == k))
