"""Stage-level tests of the SLAM core against exact synthetic geometry."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pycolmap
import pytest

from slamkit.config import SlamConfig
from slamkit.errors import ConfigError
from slamkit.features import (FrameFeatures, MatchingConfig, available_extractors, create_extractor,
                              guided_match, match_descriptors)
from slamkit.map import SlamMap, matrix_from_rigid, rigid_from_matrix
from slamkit.sources import open_source
from slamkit.stages.flow import flow_score
from slamkit.stages.initializer import Initializer, InitializerConfig
from slamkit.stages.keyframes import KeyframeConfig, KeyframeSelector, median_parallax_deg
from slamkit.stages.mapper import Mapper, sampson_error_px
from slamkit.stages.tracker import LocalMap, Tracker, TrackerConfig

pycolmap.logging.minloglevel = 2


@pytest.fixture(scope="module")
def sideways():
    return open_source("synthetic:sideways?frames=40")


def features_of(source, i: int, extractor=None) -> FrameFeatures:
    extractor = extractor or create_extractor("orb")
    frame = source[i]
    f = extractor.extract(frame.gray)
    ij = np.round(f.keypoints).astype(int)
    return FrameFeatures(i, frame.frame_id, frame.timestamp, f, f.keypoints.copy(),
                         frame.color[ij[:, 1], ij[:, 0]])


def cam_from_world(source, i: int) -> np.ndarray:
    return np.linalg.inv(source.gt_poses[i])


def rotation_angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


# ----------------------------------------------------------------------------- flow and keyframes
def test_flow_score_is_median_normalised_flow():
    ref = np.array([[100.0, 100.0], [200.0, 50.0], [300.0, 300.0]])
    cur = ref + [[10.0, 0.0], [20.0, -5.0], [30.0, 50.0]]
    assert flow_score(ref, cur, fx=500.0, fy=250.0) == pytest.approx(20 / 500 + 5 / 250)
    assert flow_score(np.empty((0, 2)), np.empty((0, 2)), 500, 500) == 0.0


@pytest.mark.parametrize("flow,matches,points,at_kf,expected", [
    (0.06, 60, 300, 300, True),     # flow above threshold, enough matches
    (0.04, 200, 300, 300, False),   # flow below threshold
    (0.06, 40, 300, 300, False),    # flow above, too few tracked matches
    (0.02, 40, 100, 300, True),     # tracking weakening: 100 < 0.5 x 300
    (0.02, 10, 100, 300, False),    # weakening, but too few matches for a keyframe at all
])
def test_keyframe_decisions_follow_thresholds(flow, matches, points, at_kf, expected):
    d = KeyframeSelector(KeyframeConfig(flow_threshold=0.05, min_tracked_matches=50)).step(flow, matches, points, at_kf)
    assert d.is_keyframe is expected
    assert d.reason  # every decision says why


def test_keyframe_config_rejects_bad_values():
    with pytest.raises(ConfigError, match="flow_threshold"):
        KeyframeSelector(KeyframeConfig(flow_threshold=-0.1))
    with pytest.raises(ConfigError, match="min_tracked_matches"):
        KeyframeSelector(KeyframeConfig(min_tracked_matches=0))
    with pytest.raises(ConfigError, match="min_parallax_deg"):
        KeyframeSelector(KeyframeConfig(min_parallax_deg=-1.0))


@pytest.mark.parametrize("flow,points,parallax,rotation,keyframe,degenerate,words", [
    (0.2, 300, 0.08, 10.0, False, True, "pure rotation: 10.0° rotation"),   # flow from rotation only
    (0.02, 100, 0.1, 3.0, False, True, "tracking weakening"),              # weak tracking, no parallax
    (0.2, 300, 0.2, 0.3, False, True, "too little translation"),           # barely any motion at all
    (0.2, 300, 2.0, 10.0, True, False, "flow 0.200 > 0.05"),                # enough parallax
    (0.2, 300, float("nan"), float("nan"), True, False, "flow"),            # not measured: no test
    (0.02, 300, 0.05, 10.0, False, False, "flow 0.020 <= 0.05"),            # no keyframe due anyway
])
def test_degenerate_motion_refuses_keyframes_and_says_why(flow, points, parallax, rotation, keyframe, degenerate,
                                                          words):
    sel = KeyframeSelector(KeyframeConfig(flow_threshold=0.05, min_tracked_matches=50, min_parallax_deg=0.5))
    d = sel.step(flow, 60, points, 300, parallax, rotation)
    assert (d.is_keyframe, d.degenerate) == (keyframe, degenerate)
    assert words in d.reason
    if degenerate:
        assert d.reason.startswith(f"degenerate motion: median parallax {parallax:.2f}° < 0.5°")
    off = KeyframeSelector(KeyframeConfig(flow_threshold=0.05, min_tracked_matches=50, min_parallax_deg=0.0))
    assert not off.step(flow, 60, points, 300, parallax, rotation).degenerate  # 0 disables the test


def test_median_parallax_is_the_triangulation_angle_and_zero_for_pure_rotation():
    rng = np.random.default_rng(0)
    X = rng.uniform([-2, -1.5, 3], [2, 1.5, 6], (200, 3))  # world points in front of camera A = identity
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])

    def pose(rvec, centre):
        import cv2

        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float))[0]
        T[:3, 3] = -T[:3, :3] @ np.asarray(centre, float)
        return T

    def project(T):
        x = (X @ T[:3, :3].T + T[:3, 3]) @ K.T
        return x[:, :2] / x[:, 2:]

    A = np.eye(4)
    rot = pose([0.02, 0.25, 0.05], [0, 0, 0])  # 15 degrees of pure rotation
    par, angle = median_parallax_deg(project(A), project(rot), A, rot, K)
    assert par < 1e-6 and angle == pytest.approx(math.degrees(np.linalg.norm([0.02, 0.25, 0.05])), abs=1e-6)
    moved = pose([0.02, 0.25, 0.05], [0.3, 0.05, 0.1])  # the same rotation and a 0.3 m baseline
    c = -moved[:3, :3].T @ moved[:3, 3]
    cos = np.einsum("ij,ij->i", X, X - c) / (np.linalg.norm(X, axis=1) * np.linalg.norm(X - c, axis=1))
    exact = np.median(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    par, _ = median_parallax_deg(project(A), project(moved), A, moved, K)
    assert par == pytest.approx(exact, abs=1e-6) and par > 2
    assert math.isnan(median_parallax_deg(np.empty((0, 2)), np.empty((0, 2)), A, moved, K)[0])


# ----------------------------------------------------------------------------- features and matching
def test_extractor_registry_and_shapes(sideways):
    assert {"orb", "sift"} <= set(available_extractors())
    gray = sideways[0].gray
    orb = create_extractor("orb", num_features=1000).extract(gray)
    assert orb.binary and orb.descriptors.shape[1] == 32 and orb.descriptors.dtype == np.uint8
    assert 500 <= len(orb) <= 1100
    sift = create_extractor("sift", num_features=1000).extract(gray)
    assert not sift.binary and sift.descriptors.shape[1] == 128
    with pytest.raises(ConfigError, match="unknown extractor"):
        create_extractor("nope")


def test_matches_satisfy_ground_truth_epipolar_geometry(sideways):
    a, b = features_of(sideways, 0), features_of(sideways, 8)
    pairs = match_descriptors(a.features.descriptors, b.features.descriptors, True)
    assert len(pairs) > 300
    rel = cam_from_world(sideways, 8) @ sideways.gt_poses[0]
    err = sampson_error_px(a.keypoints[pairs[:, 0]], b.keypoints[pairs[:, 1]], rel, sideways.camera.K)
    assert np.mean(err < 1.5) > 0.9


def test_guided_match_finds_projected_points():
    rng = np.random.default_rng(0)
    kps = rng.uniform(0, 600, (500, 2))
    desc = rng.integers(0, 256, (500, 32), dtype=np.uint8)
    pick = rng.choice(500, 100, replace=False)
    proj = kps[pick] + rng.normal(0, 2.0, (100, 2))
    pairs = guided_match(proj, desc[pick], kps, desc, True, radius=8.0, cfg=MatchingConfig())
    assert len(pairs) >= 95
    assert np.all(pick[pairs[:, 0]] == pairs[:, 1])
    taken = np.zeros(500, bool)
    taken[pick] = True
    assert len(guided_match(proj, desc[pick], kps, desc, True, 8.0, MatchingConfig(), kp_taken=taken)) == 0


# ----------------------------------------------------------------------------- initialization
@pytest.mark.parametrize("strategy", ["best_pair", "first_inliers"])
def test_initializer_recovers_relative_pose_up_to_scale(sideways, strategy):
    cfg = InitializerConfig(strategy=strategy, init_frames=20)
    init = Initializer(sideways.camera, cfg)
    res = None
    for i in range(20):
        res = init.step(features_of(sideways, i))
        if res.initialized:
            break
    assert res is not None and res.initialized, res.reason
    slam_map = res.slam_map
    (id1, kf1), (id2, kf2) = sorted(slam_map.keyframes.items())
    est = matrix_from_rigid(slam_map.cam_from_world(id2)) @ np.linalg.inv(matrix_from_rigid(slam_map.cam_from_world(id1)))
    gt = cam_from_world(sideways, kf2.frame_index) @ sideways.gt_poses[kf1.frame_index]
    assert rotation_angle_deg(est[:3, :3] @ gt[:3, :3].T) < 0.2
    t_est, t_gt = est[:3, 3] / np.linalg.norm(est[:3, 3]), gt[:3, 3] / np.linalg.norm(gt[:3, 3])
    assert math.degrees(math.acos(np.clip(t_est @ t_gt, -1, 1))) < 2.5  # baseline direction, small parallax
    assert res.num_points >= cfg.min_points


def test_initializer_reports_no_parallax_for_pure_rotation():
    src = open_source("synthetic:rotation?frames=30")
    init = Initializer(src.camera, InitializerConfig(init_frames=10))
    statuses = [init.step(features_of(src, i)).status for i in range(10)]
    assert "initialized" not in statuses
    assert statuses[-1] == "failed"


def test_initializer_rejects_a_homography_pose_the_essential_matrix_contradicts(shared):
    """7-Scenes frames 28 and 35: 3 cm of baseline, 1.5 degrees of rotation. A homography fits the matches as
    well as the essential matrix; with some RANSAC seeds pycolmap classifies the pair as planar and its
    decomposition gives a pose 2.4 degrees off with 1.9 degrees of apparent parallax, which used to become
    the initial map (and later broke the map's scale). No seed may initialize from a wrong pose now."""
    src = open_source(str(shared("7scenes-redkitchen")), max_frames=36)
    fa, fb = features_of(src, 28), features_of(src, 35)
    poses = src.ground_truth().poses  # camera-to-world, one per frame
    gt = np.linalg.inv(poses[35]) @ poses[28]
    reasons = []
    for seed in range(6):
        res = Initializer(src.camera, InitializerConfig(random_seed=seed))._try_pair(fa, fb)
        reasons.append(res.reason)
        if res.initialized:
            (id1, _), (id2, _) = sorted(res.slam_map.keyframes.items())
            est = matrix_from_rigid(res.slam_map.cam_from_world(id2)) @ np.linalg.inv(
                matrix_from_rigid(res.slam_map.cam_from_world(id1)))
            assert rotation_angle_deg(est[:3, :3] @ gt[:3, :3].T) < 1.0, (seed, res.reason)
    assert any(r.startswith("ambiguous relative pose") for r in reasons), reasons


def test_initializer_config_validation():
    with pytest.raises(ConfigError, match="init_frames"):
        InitializerConfig(init_frames=1).validate()
    with pytest.raises(ConfigError, match="strategy"):
        InitializerConfig(strategy="magic").validate()
    with pytest.raises(ConfigError, match="max_pose_disagreement_deg"):
        InitializerConfig(max_pose_disagreement_deg=0).validate()


# ----------------------------------------------------------------------------- map, triangulation, tracking
@pytest.fixture(scope="module")
def exact_map(sideways):
    """A map of frames 0 and 10 at their exact poses (ground-truth scale), triangulated by pycolmap."""
    slam_map = SlamMap(sideways.camera)
    a, b = features_of(sideways, 0), features_of(sideways, 10)
    ia = slam_map.add_image(0, a.timestamp, a.keypoints, a.features, a.colors)
    ib = slam_map.add_image(10, b.timestamp, b.keypoints, b.features, b.colors)
    pairs = match_descriptors(a.features.descriptors, b.features.descriptors, True)
    rel = cam_from_world(sideways, 10) @ sideways.gt_poses[0]
    ok = sampson_error_px(a.keypoints[pairs[:, 0]], b.keypoints[pairs[:, 1]], rel, sideways.camera.K) < 1.0
    slam_map.add_matches(ia, ib, pairs[ok])
    slam_map.observe(ia, ib)
    slam_map.register(ia, rigid_from_matrix(cam_from_world(sideways, 0)))
    slam_map.register(ib, rigid_from_matrix(cam_from_world(sideways, 10)))
    slam_map.triangulate(ib)
    return slam_map


def test_triangulation_error_within_tolerance(sideways, exact_map):
    ids, xyz, rgb = exact_map.point_cloud()
    assert len(ids) > 200
    kf = exact_map.keyframes[1]
    pids = exact_map.point3D_ids(1)
    has = pids >= 0
    truth = sideways.points(0, kf.keypoints[has])          # exact surface points behind the keypoints
    est = exact_map.points_xyz(pids[has])
    err = np.linalg.norm(est - truth, axis=1)
    depth = np.linalg.norm(truth - sideways.gt_poses[0][:3, 3], axis=1)
    # a 0.15 m baseline at ~3 m with ~0.5 px keypoint noise gives ~Z / (b f) x 0.5 px = 2 % depth error
    assert np.median(err / depth) < 0.03
    assert np.percentile(err / depth, 90) < 0.1
    assert rgb.any(axis=1).mean() > 0.9                     # points are coloured


@pytest.mark.parametrize("pose_optimizer", ["ceres", "compiled", "orb"])
def test_tracker_recovers_pose_by_pnp(sideways, exact_map, pose_optimizer):
    local_map = LocalMap.build(exact_map, 2, num_covisible=5)
    assert len(local_map) > 200
    tracker = Tracker(TrackerConfig(pose_optimizer=pose_optimizer))
    for i, predicted in ((5, None), (14, cam_from_world(sideways, 12))):
        res = tracker.step(features_of(sideways, i), local_map, exact_map.pycolmap_camera, predicted)
        assert res.tracked, res.reason
        gt = cam_from_world(sideways, i)
        assert rotation_angle_deg(res.cam_from_world[:3, :3] @ gt[:3, :3].T) < 0.1
        centre_err = np.linalg.norm(np.linalg.inv(res.cam_from_world)[:3, 3] - sideways.gt_poses[i][:3, 3])
        assert centre_err < 0.005                            # metres (scene is metric here)
        assert res.num_inliers >= 100


@pytest.mark.parametrize("point_descriptor, keyframe", [("oldest", 1), ("newest", 2)])
def test_local_map_matches_points_by_the_chosen_keyframes_descriptors(exact_map, point_descriptor, keyframe):
    local_map = LocalMap.build(exact_map, 2, num_covisible=5, point_descriptor=point_descriptor)
    pids = exact_map.point3D_ids(keyframe)
    has = pids >= 0
    assert set(local_map.ids) == set(pids[has])           # both keyframes observe every point of this map
    want = exact_map.keyframes[keyframe].features.descriptors[has][np.argsort(pids[has])]
    np.testing.assert_array_equal(local_map.descriptors, want)
    other = exact_map.keyframes[3 - keyframe].features.descriptors
    other_pids = exact_map.point3D_ids(3 - keyframe)
    assert (other[other_pids >= 0][np.argsort(other_pids[other_pids >= 0])] != want).any(axis=1).mean() > 0.5
    with pytest.raises(ConfigError, match="point_descriptor"):
        LocalMap.build(exact_map, 2, point_descriptor="median")
    with pytest.raises(ConfigError, match="point_descriptor"):
        SlamConfig().with_overrides(**{"tracker.point_descriptor": "median"})
    xfeat = SlamConfig().with_overrides(features="xfeat").tracker
    assert (xfeat.point_descriptor, xfeat.local_keyframes) == ("oldest", 50)
    assert SlamConfig().with_overrides(features="xfeat").with_overrides(features="orb").tracker.point_descriptor \
        == "newest"


def test_tracker_takes_a_good_prediction_without_ransac_and_a_bad_one_with_it(sideways, exact_map):
    local_map = LocalMap.build(exact_map, 2, num_covisible=5)
    gt = cam_from_world(sideways, 14)
    off = np.eye(4)  # 5 mm and 0.3 degrees off: refined from the prediction
    off[:3, :3] = cv2.Rodrigues(np.array([0.0, np.radians(0.3), 0.0]))[0]
    off[:3, 3] = [0.005, 0.0, 0.0]
    # 1.5 degrees off (13 px): most narrow-radius matches are wrong, so RANSAC decides; its pose from ~100
    # matches sits in the rotation-translation ambiguity of this wall (0.6 degrees off, consistent with 240
    # points), and further rounds of local-map search and refinement pull it out
    bad = off.copy()
    bad[:3, :3] = cv2.Rodrigues(np.array([0.0, np.radians(1.5), 0.0]))[0]
    for predicted, method in ((off @ gt, "motion"), (bad @ gt, "motion+ransac")):
        res = Tracker().step(features_of(sideways, 14), local_map, exact_map.pycolmap_camera, predicted)
        assert res.tracked and res.method == method, (res.method, res.reason)
        assert rotation_angle_deg(res.cam_from_world[:3, :3] @ gt[:3, :3].T) < 0.1
        assert np.linalg.norm(np.linalg.inv(res.cam_from_world)[:3, 3] - sideways.gt_poses[14][:3, 3]) < 0.005
    # prediction_min_inlier_ratio > 1: RANSAC always
    res = Tracker(TrackerConfig(prediction_min_inlier_ratio=1.5)).step(
        features_of(sideways, 14), local_map, exact_map.pycolmap_camera, off @ gt)
    assert res.tracked and res.method == "motion+ransac"


def test_tracker_rematches_by_descriptor_when_the_motion_model_pose_is_weak():
    """A turn starts (or ends) between two frames: the constant-velocity prediction is 3 degrees off (26 px), beyond the
    search radius. Around it only 100 look-alike keypoints match, and they fit the wrong pose exactly (as
    repeated facades can). The motion model's pose keeps 100 inliers of the 600 points tracked in the last
    frame, so the frame is matched against the whole local map by descriptor, and the true pose wins."""
    from slamkit.features import Features
    rng = np.random.default_rng(7)
    camera = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500.0, 500.0, 320.0, 240.0])
    K = camera.calibration_matrix()
    gt = np.eye(4)
    gt[:3, :3] = cv2.Rodrigues(np.array([0.0, np.radians(4.0), 0.0]))[0]
    gt[:3, 3] = [0.05, 0.0, -0.25]
    wrong = np.eye(4)
    wrong[:3, :3] = cv2.Rodrigues(np.array([0.0, np.radians(-3.0), 0.0]))[0]
    wrong = wrong @ gt

    def pixels(cam_from_world, xyz):
        x = xyz @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        return x[:, :2] / x[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]

    xyz = rng.uniform([-3.0, -2.0, 6.0], [3.0, 2.0, 9.0], (600, 3))
    inside = lambda uv: ((uv >= 0) & (uv < [640, 480])).all(axis=1)  # noqa: E731
    xyz = xyz[inside(pixels(gt, xyz)) & inside(pixels(wrong, xyz))][:500]
    assert len(xyz) == 500
    desc = rng.integers(0, 256, (len(xyz), 32), dtype=np.uint8)
    ids = np.arange(1, len(xyz) + 1, dtype=np.int64)
    local_map = LocalMap(ids, xyz, desc, True, 1, np.empty(0, np.int64), np.empty((0, 2)), [1])
    kp = np.concatenate([pixels(gt, xyz), pixels(wrong, xyz[:100])])  # 100 look-alikes where the wrong pose says
    feats = Features(kp, np.concatenate([desc, desc[:100]]), np.ones(len(kp), np.float32), True)
    frame = FrameFeatures(1, 1, 0.1, feats, kp, np.zeros((len(kp), 3), np.uint8))
    for ratio, want, inliers in ((0.0, wrong, 100), (0.5, gt, 500)):
        res = Tracker(TrackerConfig(recheck_inlier_ratio=ratio)).step(frame, local_map, camera, wrong, ids)
        assert res.tracked, res.reason
        assert rotation_angle_deg(res.cam_from_world[:3, :3] @ want[:3, :3].T) < 0.01, (ratio, res.reason)
        assert np.linalg.norm(res.cam_from_world[:3, 3] - want[:3, 3]) < 1e-3, (ratio, res.reason)
        assert res.num_inliers == inliers, (ratio, res.reason)
    assert res.method == "local map" and "re-matched by descriptor" in res.reason
    # a pose keeping most of the last frame's points is not second-guessed
    res = Tracker().step(frame, local_map, camera, gt, ids)
    assert res.method == "motion" and "re-matched" not in res.reason and res.num_inliers == 500
    with pytest.raises(ConfigError, match="recheck_inlier_ratio"):
        TrackerConfig(recheck_inlier_ratio=2).validate()
    with pytest.raises(ConfigError, match="tracker.pose_optimizer must be one of ceres, compiled, orb"):
        SlamConfig().with_overrides(**{"tracker.pose_optimizer": "g2o"})


def test_tracker_reports_lost_on_unrelated_image(exact_map):
    rng = np.random.default_rng(1)
    from slamkit.features import Features
    kp = rng.uniform(0, 600, (400, 2))
    feats = Features(kp, rng.integers(0, 256, (400, 32), dtype=np.uint8), np.ones(400, np.float32), True)
    ff = FrameFeatures(99, 99, 3.3, feats, kp, np.zeros((400, 3), np.uint8))
    res = Tracker().step(ff, LocalMap.build(exact_map, 2), exact_map.pycolmap_camera, None)
    assert not res.tracked and res.reason


def test_mapper_registers_keyframe_and_triangulates(sideways, exact_map):
    # a copy of the map grows by one keyframe at frame 20, tracked with its exact pose
    slam_map = exact_map
    before = slam_map.num_points
    local_map = LocalMap.build(slam_map, 2)
    ff = features_of(sideways, 20)
    tr = Tracker().step(ff, local_map, slam_map.pycolmap_camera, cam_from_world(sideways, 20))
    assert tr.tracked
    res = Mapper().step(slam_map, ff, tr.cam_from_world, tr.point2D_idxs, tr.point3D_ids, ref_image_id=2)
    assert res.registered, res.reason
    assert res.num_points >= 50 and slam_map.num_points > before
    assert slam_map.num_keyframes == 3
    covis = dict(slam_map.covisible(res.image_id))
    assert covis.get(2, 0) > 50


def test_config_contradictions_are_errors():
    with pytest.raises(ConfigError, match="min_tri_angle"):
        SlamConfig().with_overrides(**{"initializer.min_tri_angle_deg": 1.0, "ba.min_tri_angle_deg": 1.5})
    with pytest.raises(ConfigError, match="init_frames"):
        SlamConfig().with_overrides(init_frames=1)
    with pytest.raises(ConfigError, match="not a valid"):
        SlamConfig().with_overrides(flow_threshold="fast")
    with pytest.raises(ConfigError, match="unknown configuration parameter"):
        SlamConfig().with_overrides(flow_treshold=0.1)
    with pytest.raises(ConfigError, match="unknown preset"):
        SlamConfig.preset("nope")


# ----------------------------------------------------------------------------- bundle adjustment
@pytest.fixture()
def built_map():
    """The map of a 60-frame run on the synthetic "sideways" sequence (exact ground truth)."""
    from slamkit.pipeline import Slam

    slam = Slam("synthetic:sideways?frames=60", SlamConfig())
    slam.run()
    assert slam.slam_map is not None and slam.slam_map.num_keyframes >= 6
    return slam.slam_map


def test_local_ba_pulls_a_perturbed_keyframe_back_and_holds_long_tracks(built_map):
    from slamkit.stages.ba import BundleAdjuster, BundleAdjustmentConfig

    slam_map = built_map
    rec = slam_map.reconstruction
    kf = max(slam_map.keyframes)
    true_pose = matrix_from_rigid(slam_map.cam_from_world(kf))
    xyz = {p: rec.point3D(p).xyz.copy() for p in rec.point3D_ids()}
    track = {p: rec.point3D(p).track.length() for p in xyz}
    baseline = np.median(np.linalg.norm(np.diff(np.array(
        [np.linalg.inv(matrix_from_rigid(slam_map.cam_from_world(k)))[:3, 3] for k in sorted(slam_map.keyframes)]),
        axis=0), axis=1))
    moved = true_pose.copy()
    moved[:3, 3] += [0.05 * baseline, -0.05 * baseline, 0.0]    # 5 % of a keyframe step off
    rec.frame(rec.image(kf).frame_id).rig_from_world = rigid_from_matrix(moved)
    max_track = 3
    window = {kf} | {i for i, _ in slam_map.covisible(kf, 2)}
    outside = {p: any(el.image_id not in window for el in rec.point3D(p).track.elements) for p in xyz}
    ba = BundleAdjuster(BundleAdjustmentConfig(local_window=2, local_max_track_length=max_track, max_reproj_error_px=1e9,
                                               min_tri_angle_deg=0.0))
    res = ba.adjust_local(slam_map, kf)
    assert res.kind == "local" and res.num_images == 3
    after = matrix_from_rigid(slam_map.cam_from_world(kf))
    # back to where the map (built from these very observations) puts it: 10x closer than perturbed
    assert np.linalg.norm(after[:3, 3] - true_pose[:3, 3]) < 0.1 * np.linalg.norm(moved[:3, 3] - true_pose[:3, 3])
    window_points = set(slam_map.point3D_ids(kf)[slam_map.point3D_ids(kf) >= 0].tolist())
    # long tracks reaching outside the window are held; tracks all inside the window are adjusted anyway
    long_ = [p for p in window_points if track[p] > max_track and outside[p] and rec.exists_point3D(p)]
    short = [p for p in window_points if track[p] <= max_track and rec.exists_point3D(p)]
    assert long_ and short
    assert all(np.array_equal(rec.point3D(p).xyz, xyz[p]) for p in long_)      # held constant
    assert np.mean([not np.array_equal(rec.point3D(p).xyz, xyz[p]) for p in short]) > 0.9  # adjusted


def test_global_ba_reduces_reprojection_error_of_a_noisy_map(built_map):
    from slamkit.stages.ba import BundleAdjuster, BundleAdjustmentConfig

    slam_map = built_map
    rec = slam_map.reconstruction
    rng = np.random.default_rng(0)
    before_err = slam_map.mean_reprojection_error()
    ids = rec.point3D_ids()
    sigma = 0.01 * np.median(np.std(slam_map.points_xyz(ids), axis=0))    # 1 % of the scene's extent
    for p in ids:
        rec.point3D(p).xyz = rec.point3D(p).xyz + rng.normal(0, sigma, 3)
    rec.update_point_3d_errors()
    noisy_err = slam_map.mean_reprojection_error()
    assert noisy_err > 2 * before_err
    res = BundleAdjuster(BundleAdjustmentConfig(normalize=False)).adjust_global(slam_map)
    assert res.kind == "global" and res.num_images == slam_map.num_keyframes
    rec.update_point_3d_errors()
    assert slam_map.mean_reprojection_error() < 1.2 * before_err


def test_sift_respects_its_keypoint_cap():
    """OpenCV's SIFT keeps keypoints that tie with the last one's response (501 for a cap of 500 on this frame;
    2,001 for 2,000 on frame 0 of the default sequence, notebook 04): the extractor keeps the strongest
    ``num_features``."""
    from slamkit.sources import open_source

    gray = open_source("synthetic:default?frames=2")[0].gray
    feats = create_extractor("sift", num_features=2000).extract(gray)
    assert len(feats) == 2000
    weaker = create_extractor("sift", num_features=500).extract(gray)
    assert len(weaker) == 500 and weaker.scores.min() >= np.sort(feats.scores)[-500] - 1e-6
