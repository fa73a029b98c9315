"""Motion model selection (issue 42): GRIC picks rotation-only on a pan and general motion on a walk,
on exact projections of the rendered room and on ORB matches of rendered frames."""

import numpy as np
import pytest

from slamkit import open_source
from slamkit.errors import ConfigError
from slamkit.features import MatchingConfig, NearestNeighborMatcher, create_extractor
from slamkit.frames import FrameLoader
from slamkit.geometry import rotation_angle_deg
from slamkit.stages.motion_model_selection import (GENERAL, ROTATION, MotionModelSelectionConfig, MotionModelSelector,
                                                   gric)


def _exact_matches(src, i: int, j: int, noise_px: float, seed: int = 0):
    """Pixels of a grid in frame i and the exact projections in frame j of the scene points they see, with
    Gaussian noise; and the true cam_j_from_cam_i rotation."""
    u, v = np.meshgrid(np.arange(20, 640, 40.0), np.arange(20, 480, 40.0))
    xy_i = np.stack([u.ravel(), v.ravel()], axis=1)
    X = src.points(i, xy_i)
    cam_j = np.linalg.inv(src.gt_poses[j])
    p = X @ cam_j[:3, :3].T + cam_j[:3, 3]
    xy_j = p[:, :2] / p[:, 2:] * [src.camera.fx, src.camera.fy] + [src.camera.cx, src.camera.cy]
    ok = np.isfinite(xy_j).all(1) & (p[:, 2] > 0) & (xy_j[:, 0] >= 0) & (xy_j[:, 0] < 640) & (xy_j[:, 1] >= 0) \
        & (xy_j[:, 1] < 480)
    rng = np.random.default_rng(seed)
    noisy = lambda a: a + rng.normal(0, noise_px, a.shape)  # noqa: E731
    R = (cam_j @ src.gt_poses[i])[:3, :3]
    return noisy(xy_i[ok]), noisy(xy_j[ok]), R


@pytest.mark.parametrize("i, j", [(0, 3), (40, 50), (100, 104)])
def test_exact_pan_is_rotation_with_its_true_rotation(i, j):
    src = open_source("synthetic:pure-rotation?frames=150")
    a, b, R = _exact_matches(src, i, j, 0.5)
    choice = MotionModelSelector().step(a, b, src.camera.K)
    assert choice.model == ROTATION and choice.is_rotation, choice.reason
    assert rotation_angle_deg(choice.rotation @ R.T) < 0.05
    assert choice.inliers.mean() > 0.95


def test_exact_walk_is_general_motion():
    src = open_source("synthetic:sideways?frames=120")
    a, b, _ = _exact_matches(src, 0, 8, 0.5)  # 12 cm sideways, the wall 3 m away
    choice = MotionModelSelector().step(a, b, src.camera.K)
    assert choice.model == GENERAL, choice.reason
    assert choice.gric_general < choice.gric_rotation


def _orb_matches(spec: str, i: int, j: int):
    src = open_source(spec)
    loader = FrameLoader(src)
    loader.configure(np.array([i, j]), create_extractor("orb", num_features=2000), src.camera, False)
    fa, fb = loader.next(0)[1], loader.next(1)[1]
    m = NearestNeighborMatcher(MatchingConfig()).match(fa.features, fb.features)
    R = (np.linalg.inv(src.gt_poses[j]) @ src.gt_poses[i])[:3, :3]
    return src, fa.keypoints[m[:, 0]], fb.keypoints[m[:, 1]], R


def test_rendered_pan_picks_rotation_and_rendered_walk_picks_general_motion():
    src, a, b, R = _orb_matches("synthetic:pure-rotation?frames=150&noise=1", 40, 45)
    pan = MotionModelSelector().step(a, b, src.camera.K)
    assert pan.model == ROTATION, pan.reason
    assert rotation_angle_deg(pan.rotation @ R.T) < 0.1
    src, a, b, _ = _orb_matches("synthetic:sideways?frames=120&noise=1", 0, 8)
    walk = MotionModelSelector().step(a, b, src.camera.K)
    assert walk.model == GENERAL, walk.reason


def test_too_few_matches_choose_nothing_and_config_is_checked():
    choice = MotionModelSelector().step(np.zeros((5, 2)), np.zeros((5, 2)), np.eye(3))
    assert choice.model == "" and "5 matches" in choice.reason
    with pytest.raises(ConfigError, match="sigma_px"):
        MotionModelSelectionConfig(sigma_px=0).validate()


def test_gric_penalises_the_larger_model():
    e = np.zeros(100)
    assert gric(e, 1.0, d=2, k=3) < gric(e, 1.0, d=3, k=5)
    assert gric(np.full(100, 1e9), 1.0, d=2, k=3) == pytest.approx(100 * 4 + 200 * np.log(4) + 3 * np.log(400))
