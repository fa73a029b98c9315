"""Keyframe matching guided by known poses (``slamkit.features.epipolar``): the pencil search against a
brute-force enumeration of the epipolar band, and the guided matches of a real image pair with exact poses
against brute-force descriptor matching filtered by the same epipolar constraint."""

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from slamkit.config import SlamConfig
from slamkit.features import MatchingConfig, match_descriptors
from slamkit.features.epipolar import epipolar_candidates, epipolar_match
from slamkit.pipeline import Slam
from slamkit.sources import open_source
from slamkit.stages.mapper import sampson_error_px

pycolmap.logging.minloglevel = 2
K = np.array([[718.0, 0, 613], [0, 718, 185], [0, 0, 1]])


def brute_force_candidates(x1, x2, cam2_from_cam1, K, band_px):
    """Every pair within the band of the epipolar line, rays meeting in front of both cameras or within
    1 degree of parallel, from the full (N1, N2) tables."""
    R, t = cam2_from_cam1[:3, :3], cam2_from_cam1[:3, 3]
    y1 = np.c_[x1, np.ones(len(x1))] @ np.linalg.inv(K).T
    y2 = np.c_[x2, np.ones(len(x2))] @ np.linalg.inv(K).T
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    lines = y1 @ (tx @ R).T
    dist = np.abs(lines @ y2.T) / np.hypot(lines[:, 0], lines[:, 1])[:, None]
    i, j = np.nonzero(dist < band_px / K[0, 0])
    out = set()
    for a, b in zip(i.tolist(), j.tolist()):  # depths by least squares: d2 y2 = d1 R y1 + t
        ray1, ray2 = R @ y1[a], y2[b]
        (d1, d2), *_ = np.linalg.lstsq(np.c_[ray1, -ray2], -t, rcond=None)
        cos = ray1 @ ray2 / np.linalg.norm(ray1) / np.linalg.norm(ray2)
        if (d1 > 0 and d2 > 0) or cos > np.cos(np.radians(1.0)):
            out.add((a, b))
    return out


@pytest.mark.parametrize("rotvec, t", [
    ((0, 0.05, 0), (0.02, 0, -1.0)),     # forward: the epipole inside the image
    ((0, 0.03, 0), (1.0, 0.1, 0.2)),     # sideways: the epipole far outside
    ((0, 0, 0), (0, 0, 1.0)),            # backward, no rotation
    ((0.1, 0.1, 0.02), (0.3, 0.3, 0.5)),
    ((0, 0.02, 0), (1.0, 0, 0)),         # epipole at infinity
])
def test_pencil_search_finds_exactly_the_pairs_in_the_epipolar_band(rotvec, t):
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_rotvec(rotvec).as_matrix(), t
    x1 = rng.uniform([-5, -5], [1230, 375], (300, 2))
    x2 = rng.uniform([-5, -5], [1230, 375], (300, 2))
    x2[:5] = K[:2, 2] + 0.5 * rng.normal(size=(5, 2))  # near the forward epipole
    i, j = epipolar_candidates(x1, x2, T, K, 4.0)
    got = set(zip(i.tolist(), j.tolist()))
    assert len(got) == len(i)  # no pair twice
    assert got == brute_force_candidates(x1, x2, T, K, 4.0)


def test_no_baseline_no_candidates():
    x = np.random.default_rng(0).uniform(0, 300, (50, 2))
    assert len(epipolar_candidates(x, x, np.eye(4), K, 4.0)[0]) == 0


@pytest.fixture(scope="module")
def synthetic_pair():
    """Two frames of the synthetic hand-held sequence 12 frames apart, ORB features, exact poses."""
    src = open_source("synthetic:handheld?frames=40&noise=1&seed=0")
    slam = Slam(src, SlamConfig())
    a, b = slam.loader.load(10)[1], slam.loader.load(22)[1]
    cam_from_world = [np.linalg.inv(src.gt_poses[i]) for i in (10, 22)]
    return a, b, cam_from_world[1] @ np.linalg.inv(cam_from_world[0]), slam.camera.K


def test_guided_matches_contain_the_brute_force_matches_that_fit_the_poses(synthetic_pair):
    a, b, rel, K_ = synthetic_pair
    cfg = MatchingConfig(ratio=0.8, mutual=True)
    bf = match_descriptors(a.features.descriptors, b.features.descriptors, True, cfg)
    bf = bf[sampson_error_px(a.keypoints[bf[:, 0]], b.keypoints[bf[:, 1]], rel, K_) < 2.0]
    guided = epipolar_match(a.keypoints, a.features.descriptors, b.keypoints, b.features.descriptors, True,
                            rel, K_, 4.0, cfg)
    assert len(bf) > 200
    g = guided[sampson_error_px(a.keypoints[guided[:, 0]], b.keypoints[guided[:, 1]], rel, K_) < 2.0]
    lost = {tuple(p) for p in bf.tolist()} - {tuple(p) for p in g.tolist()}
    assert len(lost) <= 0.02 * len(bf), len(lost)  # at most 2 % of the brute-force matches are lost
    assert len(g) >= len(bf), (len(g), len(bf))
    # one-to-one
    assert len(np.unique(guided[:, 0])) == len(guided) == len(np.unique(guided[:, 1]))


def test_no_descriptor_close_enough_no_matches():
    rng = np.random.default_rng(1)
    x = rng.uniform([0, 0], [1226, 370], (40, 2))
    d1 = np.zeros((40, 32), np.uint8)
    d2 = np.full((40, 32), 255, np.uint8)  # 256 bits from every descriptor of image 1
    T = np.eye(4)
    T[:3, 3] = (0.1, 0, -1.0)
    assert epipolar_match(x, d1, x, d2, True, T, K, 4.0).shape == (0, 2)
