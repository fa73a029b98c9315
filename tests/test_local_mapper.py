"""Local mapping of our own (slamkit.stages.local_mapper) against exact geometry: a scene of known 3D points,
keyframes at known poses, keypoints at the exact projections, one random descriptor per scene point."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from slamkit.camera import Intrinsics
from slamkit.errors import ConfigError
from slamkit.features import Features, FrameFeatures
from slamkit.map import SlamMap, rigid_from_matrix
from slamkit.stages.local_mapper import (LocalMapper, LocalMappingConfig, check_new_points, triangulate_matches)
from slamkit.state import RecentPoints

pycolmap.logging.minloglevel = 2

CAMERA = Intrinsics(640, 480, 500.0, 500.0, 320.0, 240.0)


def pose_at(x: float, z: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """cam_from_world of a camera at (x, 0, z) looking along +z, turned by yaw about y."""
    a = np.radians(yaw_deg)
    R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ np.array([x, 0.0, z])
    return T


class World:
    """Scene points with one descriptor each; frames see the points in view at their exact projections."""

    def __init__(self, n: int = 800, depth=(8.0, 12.0), seed: int = 0):
        rng = np.random.default_rng(seed)
        self.xyz = rng.uniform([-6.0, -3.0, depth[0]], [8.0, 3.0, depth[1]], (n, 3))
        self.desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        self.rng = rng

    def view(self, index: int, T: np.ndarray, extra_xy=None, extra_desc=None, drop=()):
        """(FrameFeatures, scene id of each keypoint (-1: an extra keypoint, not a scene point)); the scene
        points ``drop`` are not seen."""
        Xc = self.xyz @ T[:3, :3].T + T[:3, 3]
        uv = Xc[:, :2] / Xc[:, 2:] * [CAMERA.fx, CAMERA.fy] + [CAMERA.cx, CAMERA.cy]
        inside = (Xc[:, 2] > 0) & (uv >= 0).all(axis=1) & (uv < [CAMERA.width, CAMERA.height]).all(axis=1)
        inside[list(drop)] = False
        sid = np.flatnonzero(inside)
        kp, desc = uv[sid], self.desc[sid]
        if extra_xy is not None:
            kp, desc = np.concatenate([kp, extra_xy]), np.concatenate([desc, extra_desc])
            sid = np.concatenate([sid, -np.ones(len(extra_xy), np.int64)])
        feats = Features(kp, desc, np.ones(len(kp), np.float32), True)
        return FrameFeatures(index, index, index / 10, feats, kp, np.full((len(kp), 3), 128, np.uint8)), sid


def seed_map(world: World, poses: list[np.ndarray]):
    """A map of the first two poses as keyframes with every scene point both see (exact positions)."""
    slam_map = SlamMap(CAMERA)
    views = []
    for i, T in enumerate(poses[:2]):
        ff, sid = world.view(i, T)
        views.append((ff, sid))
        slam_map.add_image(i, ff.timestamp, ff.keypoints, ff.features, ff.colors)
    (fa, sa), (fb, sb) = views
    common, ia, ib = np.intersect1d(sa, sb, return_indices=True)
    slam_map.add_matches(1, 2, np.stack([ia, ib], axis=1))
    slam_map.observe(1, 2)
    for iid, T in ((1, poses[0]), (2, poses[1])):
        slam_map.register(iid, rigid_from_matrix(T))
    for s, a, b in zip(common.tolist(), ia.tolist(), ib.tolist()):
        slam_map.add_point(world.xyz[s], ((1, a), (2, b)), np.zeros(3, np.uint8))
    return slam_map, {1: sa, 2: sb}


def scene_of(slam_map: SlamMap, sids: dict) -> dict[int, set]:
    """Map point id -> the scene ids its observations stand for."""
    out = {}
    for pid in slam_map.reconstruction.point3D_ids():
        out[int(pid)] = {int(sids[el.image_id][el.point2D_idx])
                         for el in slam_map.reconstruction.point3D(pid).track.elements}
    return out


def tracked(slam_map: SlamMap, sids: dict, frame_sid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact tracking: (keypoints, map points) of the frame's keypoints whose scene point is mapped by a
    point all of whose observations are that scene point."""
    by_scene = {}
    for pid, scenes in scene_of(slam_map, sids).items():
        if len(scenes) == 1 and -1 not in scenes:
            by_scene.setdefault(next(iter(scenes)), pid)
    kps = [j for j, s in enumerate(frame_sid.tolist()) if s in by_scene]
    return np.asarray(kps, np.int64), np.asarray([by_scene[frame_sid[j]] for j in kps], np.int64)


def insert(mapper: LocalMapper, slam_map, sids, recent, world, index, T, extra=(None, None), drop=()):
    ff, sid = world.view(index, T, *extra, drop=drop)
    kps, pids = tracked(slam_map, sids, sid)
    # the frame counts for the recent-point test as tracking counts it: projected inside = visible
    ids = np.asarray(sorted(slam_map.reconstruction.point3D_ids()), np.int64)
    if len(ids):
        Xc = slam_map.points_xyz(ids) @ T[:3, :3].T + T[:3, 3]
        uv = Xc[:, :2] / np.maximum(Xc[:, 2:], 1e-9) * [CAMERA.fx, CAMERA.fy] + [CAMERA.cx, CAMERA.cy]
        inside = (Xc[:, 2] > 0) & (uv >= 0).all(axis=1) & (uv < [CAMERA.width, CAMERA.height]).all(axis=1)
        recent.observe(ids[inside], pids)
    res = mapper.step(slam_map, ff, T, kps, pids, recent)
    sids[res.image_id] = sid
    return res


def test_triangulated_points_pass_the_checks_and_sit_on_the_scene():
    world = World()
    T1, T2 = pose_at(0.0), pose_at(0.6)
    f1, s1 = world.view(0, T1)
    f2, s2 = world.view(1, T2)
    common, i1, i2 = np.intersect1d(s1, s2, return_indices=True)
    K = CAMERA.K
    X = triangulate_matches(f1.keypoints[i1], f2.keypoints[i2], T1, T2, K)
    np.testing.assert_allclose(X, world.xyz[common], atol=1e-6)
    ones = np.ones(len(common))
    ok = check_new_points(X, f1.keypoints[i1], f2.keypoints[i2], ones, ones, T1, T2, K, 1.0, 1.8)
    assert ok.all()
    # behind a camera, off by 3 px, or below the parallax: refused
    bad = X.copy()
    bad[:5] = 2 * np.array([0.0, 0.0, 0.0]) - X[:5]
    assert not check_new_points(bad[:5], f1.keypoints[i1[:5]], f2.keypoints[i2[:5]], ones[:5], ones[:5], T1, T2, K,
                                1.0, 1.8).any()
    off = f2.keypoints[i2] + [3.0, 0.0]
    assert not check_new_points(X, f1.keypoints[i1], off, ones, ones, T1, T2, K, 1.0, 1.8).any()
    assert not check_new_points(X, f1.keypoints[i1], f2.keypoints[i2], ones, ones, T1, T2, K, 10.0, 1.8).any()
    # scale consistency: the same depths seen at scales 1 and 4 are refused, at 1 and 1.5 kept
    assert not check_new_points(X, f1.keypoints[i1], f2.keypoints[i2], ones, 4 * ones, T1, T2, K, 1.0, 1.8).any()
    assert check_new_points(X, f1.keypoints[i1], f2.keypoints[i2], ones, 1.5 * ones, T1, T2, K, 1.0, 1.8).all()


def check_points_of_the_pair(slam_map, sids, world, new_id: int, creates: bool) -> None:
    """The points of keyframe 2 and keyframe ``new_id`` alone: none, or (``creates``) nearly every scene point
    the two see and keyframe 1 does not, each at its exact position."""
    rec = slam_map.reconstruction
    with_2 = [p for p in rec.point3D_ids() if {el.image_id for el in rec.point3D(p).track.elements} == {2, new_id}]
    if not creates:
        assert with_2 == []
        return
    only_2 = np.setdiff1d(np.intersect1d(sids[2], sids[new_id]), sids[1])  # what the pair can map
    assert len(with_2) >= 0.95 * len(only_2) and len(only_2) > 50
    scenes = scene_of(slam_map, sids)
    err = [np.linalg.norm(rec.point3D(p).xyz - world.xyz[next(iter(scenes[p]))]) for p in with_2]
    assert max(err) < 1e-6 and all(len(scenes[p]) == 1 and -1 not in scenes[p] for p in with_2)


@pytest.mark.parametrize("baseline, creates", [(0.12, False), (0.6, True)])
def test_a_pair_below_the_parallax_threshold_creates_no_points(baseline, creates):
    """Points 8-12 m away: a 0.12 m baseline to keyframe 2 gives them at most 0.9 degrees of parallax (below
    1 degree, though the baseline is above 1 % of the depth): the pair makes no point; 0.6 m gives 3-4 degrees
    and the pair maps the points keyframe 2 alone saw, at their exact positions."""
    world = World()
    slam_map, sids = seed_map(world, [pose_at(0.0), pose_at(1.0)])
    mapper = LocalMapper(LocalMappingConfig(neighbors=2, fuse=False))
    res = insert(mapper, slam_map, sids, RecentPoints(), world, 2, pose_at(1.0 + baseline))
    assert res.registered and sorted(res.neighbors) == [1, 2]
    check_points_of_the_pair(slam_map, sids, world, res.image_id, creates)


@pytest.mark.parametrize("starved_points, starving", [(10**6, True), (50, False), (0, False)])
def test_a_starving_keyframe_keeps_its_low_parallax_points(starved_points, starving):
    """The pair of the test above at 0.12 m (0.5-0.9 degrees): a keyframe that would see fewer than
    ``starved_points`` map points (here: always) keeps the pair's candidates down to ``starved_parallax_deg``
    (0.3), at their exact positions, and says so; one that sees enough (more than 50), or with the rule off,
    makes none."""
    world = World()
    slam_map, sids = seed_map(world, [pose_at(0.0), pose_at(1.0)])
    config = LocalMappingConfig(neighbors=2, fuse=False, starved_points=starved_points, starved_parallax_deg=0.3)
    res = insert(LocalMapper(config), slam_map, sids, RecentPoints(), world, 2, pose_at(1.12))
    assert res.registered and res.starved == starving and ("starving" in res.reason) == starving
    check_points_of_the_pair(slam_map, sids, world, res.image_id, starving)


def test_wrong_correspondences_are_culled_by_the_recent_point_test_while_true_points_stay():
    """A keyframe carries 30 look-alike keypoints: each has the descriptor of a keypoint of its neighbour that
    no map point covers, and sits on that keypoint's epipolar line at the wrong depth, so it triangulates into a
    wrong point that passes every geometric check. Later keyframes never see them (nothing there has that
    descriptor): two keyframes later every wrong point is gone, and the true points made with them stay."""
    world = World(n=900, seed=3)
    poses = [pose_at(0.4 * i) for i in range(7)]
    slam_map, sids = seed_map(world, poses)
    # the neighbour (keyframe 2) keypoints without a map point, and a false position for each on its epipolar
    # line seen from pose 2: the point at 0.6 x its true depth from keyframe 2's camera
    kf2 = slam_map.keyframes[2]
    free = np.flatnonzero(slam_map.point3D_ids(2) < 0)[:30]
    assert len(free) == 30
    T_b, T_c = poses[1], poses[2]
    s = sids[2][free]
    C_b = -T_b[:3, :3].T @ T_b[:3, 3]
    fake = C_b + 0.6 * (world.xyz[s] - C_b)
    Xc = fake @ T_c[:3, :3].T + T_c[:3, 3]
    fake_xy = Xc[:, :2] / Xc[:, 2:] * [CAMERA.fx, CAMERA.fy] + [CAMERA.cx, CAMERA.cy]
    assert ((fake_xy >= 0) & (fake_xy < [640, 480])).all()
    mapper = LocalMapper(LocalMappingConfig(neighbors=2))
    recent = RecentPoints()
    # in the new frame the look-alikes stand where the true keypoints of those scene points would be seen
    extra = (fake_xy, kf2.features.descriptors[free])
    res = insert(mapper, slam_map, sids, recent, world, 2, T_c, extra, drop=s)
    wrong = [p for p, sc in scene_of(slam_map, sids).items() if -1 in sc]
    assert len(wrong) >= 25, res.reason                       # the look-alikes were triangulated
    insert(mapper, slam_map, sids, recent, world, 3, poses[3])
    true_new = [p for p, sc in scene_of(slam_map, sids).items() if -1 not in sc and p in set(recent.ids.tolist())]
    assert len(true_new) >= 15                                  # the strip that came into view
    insert(mapper, slam_map, sids, recent, world, 4, poses[4])
    scenes = scene_of(slam_map, sids)
    assert not [p for p in wrong if p in scenes], "wrong points left after two keyframes"
    assert all(-1 not in sc for sc in scenes.values())
    insert(mapper, slam_map, sids, recent, world, 5, poses[5])       # two keyframes after the true points' birth
    scenes = scene_of(slam_map, sids)
    survivors = [p for p in true_new if p in scenes]
    assert len(survivors) >= 0.9 * len(true_new)
    assert all(len(sc) == 1 for sc in scenes.values())           # no point mixes two scene points


def test_two_copies_of_one_scene_point_are_fused():
    """Keyframes 1-2 and 3-4, 2.5 m apart, each made their own copy of every scene point they see (as after a
    tracking gap). A new keyframe between them tracks one copy of each (the first made); fusion projects its
    points into keyframes 3-4, where they meet the second copies: each pair becomes one point with all five
    observations, at the scene point."""
    world = World(seed=5)
    poses = [pose_at(0.0), pose_at(0.5), pose_at(2.5), pose_at(3.0)]
    slam_map, sids = seed_map(world, poses)
    for i, T in ((3, poses[2]), (4, poses[3])):
        ff, sids[i] = world.view(i, T)
        slam_map.add_image(i, ff.timestamp, ff.keypoints, ff.features, ff.colors)
    common, i3, i4 = np.intersect1d(sids[3], sids[4], return_indices=True)
    slam_map.add_matches(3, 4, np.stack([i3, i4], axis=1))
    slam_map.observe(3, 4)
    for i in (3, 4):
        slam_map.register(i, rigid_from_matrix(poses[i - 1]))
    for sc, a, b in zip(common.tolist(), i3.tolist(), i4.tolist()):
        slam_map.add_point(world.xyz[sc] + 1e-3, ((3, a), (4, b)), np.zeros(3, np.uint8))

    def doubled():
        counts = {}
        for sc in scene_of(slam_map, sids).values():
            assert len(sc) == 1
            counts[next(iter(sc))] = counts.get(next(iter(sc)), 0) + 1
        return {k for k, v in counts.items() if v > 1}

    T_new = pose_at(1.5)
    _, seen = world.view(5, T_new)
    twice = doubled() & set(seen.tolist())
    assert len(twice) > 200
    res = insert(LocalMapper(LocalMappingConfig(neighbors=4)), slam_map, sids, RecentPoints(), world, 5, T_new)
    assert sorted(res.neighbors) == [1, 2, 3, 4]
    assert res.fused >= 0.98 * len(twice), res.reason
    assert len(doubled() & twice) <= 0.02 * len(twice)
    rec, scenes = slam_map.reconstruction, scene_of(slam_map, sids)
    fused = [p for p, sc in scenes.items() if next(iter(sc)) in twice]
    assert np.median([rec.point3D(p).track.length() for p in fused]) == 5
    err = [np.linalg.norm(rec.point3D(p).xyz - world.xyz[next(iter(scenes[p]))]) for p in fused]
    assert max(err) < 2e-3


def test_local_mapping_config_validation():
    with pytest.raises(ConfigError, match="neighbors"):
        LocalMappingConfig(neighbors=0).validate()
    with pytest.raises(ConfigError, match="min_found_ratio"):
        LocalMappingConfig(min_found_ratio=2).validate()
    with pytest.raises(ConfigError, match="min_observers"):
        LocalMappingConfig(min_observers=1).validate()
    with pytest.raises(ConfigError, match="starved_parallax_deg"):
        LocalMappingConfig(min_parallax_deg=1.0, starved_parallax_deg=1.5, starved_points=300).validate()
    LocalMappingConfig(min_parallax_deg=0.5).validate()  # the starving rule off: its angle is not checked
    with pytest.raises(ConfigError, match="starved_points"):
        LocalMappingConfig(starved_points=-1).validate()
