"""Deferred triangulation (issue 42, DT-SLAM): a point of unknown depth, seen while the camera turns in place,
stays a 2-D feature; it is triangulated once the walk gives its rays enough parallax, and lands within tolerance
of its true position on the rendered room's wall."""

import numpy as np
import pytest

from slamkit.errors import ConfigError
from slamkit.sources import open_source
from slamkit.sources.motions import TURN_FRAMES
from slamkit.stages.deferred_triangulation import (DEFERRED, TRIANGULATED, DeferredFeature,
                                                   DeferredTriangulationConfig, DeferredTriangulator)


def _camera(src):
    import pycolmap

    c = src.camera.pinhole
    return pycolmap.Camera(model="PINHOLE", width=c.width, height=c.height, params=[c.fx, c.fy, c.cx, c.cy])


def _track(src, X: np.ndarray, frames, noise_px: float, seed: int = 0):
    """(frame, cam_from_world (4, 4), pixel (2,)) of the true point X in each frame that sees it, the pixel with
    Gaussian noise of ``noise_px``."""
    rng = np.random.default_rng(seed)
    K, (w, h) = src.camera.K, (src.camera.width, src.camera.height)
    out = []
    for i in frames:
        T = np.linalg.inv(src.gt_poses[i])
        p = T[:3, :3] @ X + T[:3, 3]
        xy = (K @ p)[:2] / p[2]
        if p[2] > 0 and 0 <= xy[0] < w and 0 <= xy[1] < h:
            out.append((i, T, xy + rng.normal(0, noise_px, 2)))
    return out


@pytest.fixture(scope="module")
def walk():
    src = open_source("synthetic:turn-then-walk?frames=150&amplitude=45")
    pose = src.gt_poses[TURN_FRAMES]  # the last frame that only turned
    X, depth, quad = src.scene.raycast(pose, src.camera.pinhole, np.array([[420.0, 300.0]]))
    assert quad[0] >= 0 and 1.0 < depth[0] < 6.0  # a point on the room's wall, metres
    return src, X[0]


def test_a_point_seen_while_turning_is_deferred_then_triangulated_once_the_walk_gives_parallax(walk):
    src, X = walk
    camera = _camera(src)
    tri = DeferredTriangulator(DeferredTriangulationConfig(min_parallax_deg=1.5))
    feature, statuses, truth = DeferredFeature(), [], DeferredFeature()
    for i, T, xy in _track(src, X, range(TURN_FRAMES - 20, 150), noise_px=0.3):
        feature.observe(i, T, xy)
        truth.observe(i, T, (src.camera.K @ (T[:3, :3] @ X + T[:3, 3]))[:2] / (T[2, :3] @ X + T[2, 3]))
        res = tri.step(feature, camera)
        statuses.append((i, res, truth.parallax_deg(src.camera.K)))
        if res.triangulated:
            break
    turning = [(i, r) for i, r, _ in statuses if i <= TURN_FRAMES]
    assert len(turning) >= 10 and all(r.status == DEFERRED for _, r in turning)
    assert max(r.parallax_deg for _, r in turning) < 0.2  # a turn in place: no parallax, whatever the depth
    i, res, true_parallax = statuses[-1]
    assert res.status == TRIANGULATED, statuses[-1][1].reason
    first_enough = next(j for j, _, p in statuses if p >= 1.5)  # where the noise-free rays reach the threshold
    assert abs(i - first_enough) <= 2 and i > TURN_FRAMES
    T = src.gt_poses[i]
    ray = (X - T[:3, 3]) / np.linalg.norm(X - T[:3, 3])
    e = res.xyz - X
    depth = np.linalg.norm(X - T[:3, 3])
    # at 1.5 deg of parallax the depth is known to a few per cent (0.3 px of noise is 0.6 mrad a ray, against
    # 26 mrad of parallax), the direction to a few millimetres
    assert abs(e @ ray) < 0.05 * depth, (e @ ray, depth)
    assert np.linalg.norm(e - (e @ ray) * ray) < 0.01
    assert res.max_reprojection_px < 2.0
    # more walking, more parallax: the same feature triangulated again lands closer
    for j, T, xy in _track(src, X, range(i + 1, 150), noise_px=0.3, seed=1):
        feature.observe(j, T, xy)
        if feature.parallax_deg(src.camera.K) >= 5.0:
            break
    again = tri.step(feature, camera)
    assert again.triangulated and again.parallax_deg >= 5.0
    assert np.linalg.norm(again.xyz - X) < 0.03  # metres


def test_a_point_seen_only_while_turning_keeps_its_depth_unknown(walk):
    src, X = walk
    tri = DeferredTriangulator()
    feature = DeferredFeature()
    track = _track(src, X, range(0, TURN_FRAMES + 1), noise_px=0.3)
    assert len(track) >= 10
    for i, T, xy in track:
        res = tri.step(feature.observe(i, T, xy), _camera(src))
        assert res.status == DEFERRED and res.xyz is None and "depth unknown" in res.reason


def test_bad_deferred_triangulation_settings():
    with pytest.raises(ConfigError, match="min_parallax_deg"):
        DeferredTriangulator(DeferredTriangulationConfig(min_parallax_deg=0))
    with pytest.raises(ConfigError, match="min_observations"):
        DeferredTriangulator(DeferredTriangulationConfig(min_observations=1))
