"""Keyframe matching guided by known poses (``slamkit.features.epipolar``): the pencil search against a
brute-force enumeration of the epipolar band, and the guided matches of a real image pair with exact poses
against brute-force descriptor matching filtered by the same epipolar constraint."""

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from slamkit.config import SlamConfig
from slamkit.features import MatchingConfig, match_descriptors
from slamkit.features import epipolar
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


def numpy_candidates(x1, x2, cam2_from_cam1, K, band_px):
    """epipolar_candidates as numpy code (before the compiled kernels): binary searches for each line's
    window, every window pair gathered into (K,) arrays, then the band and cheirality tests on them."""
    R, t = cam2_from_cam1[:3, :3], cam2_from_cam1[:3, 3]
    Kinv = np.linalg.inv(K)
    y1 = epipolar._apply(Kinv, np.c_[x1, np.ones(len(x1))])
    y2 = epipolar._apply(Kinv, np.c_[x2, np.ones(len(x2))])
    band = band_px / K[0, 0]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    lines = epipolar._apply(tx @ R, y1)
    t1, t2, amp, period, base = epipolar._line_parameters(y1, y2, lines, R, t, band)
    ring = np.floor(4 * np.log2(np.maximum(amp / base, 1.0))).astype(np.int64) + (amp >= base)
    ii, jj = [], []
    for r in np.unique(ring):
        members = np.flatnonzero(ring == r)
        half = float(np.arcsin(min(1.0, band / base * 2.0 ** (-0.25 * float(r - 1))))) if r > 0 else np.pi
        if half >= np.pi / 2 - 1e-9:
            ii.append(np.repeat(np.arange(len(x1)), len(members)))
            jj.append(np.tile(members, len(x1)))
            continue
        o = np.argsort(t2[members], kind="stable")
        ts = np.concatenate([t2[members][o] - period, t2[members][o], t2[members][o] + period])
        js = np.tile(members[o], 3)
        lo, hi = np.searchsorted(ts, t1 - half, "left"), np.searchsorted(ts, t1 + half, "right")
        ii.append(np.repeat(np.arange(len(t1)), hi - lo))
        jj.append(np.concatenate([js[a:b] for a, b in zip(lo, hi)]))
    i, j = np.concatenate(ii), np.concatenate(jj)
    L, Y = lines.T.copy(), y2.T.copy()
    dist = np.abs(L[0][i] * Y[0][j] + L[1][i] * Y[1][j] + L[2][i] * Y[2][j])
    ok = dist < band * np.hypot(L[0], L[1])[i]
    i, j = i[ok], j[ok]
    A = epipolar._apply(R, y1).T.copy()
    aa, bb = (A * A).sum(0)[i], (Y * Y).sum(0)[j]
    at, bt = (A * t[:, None]).sum(0)[i], (Y * t[:, None]).sum(0)[j]
    ab = A[0][i] * Y[0][j] + A[1][i] * Y[1][j] + A[2][i] * Y[2][j]
    d1, d2 = ab * bt - at * bb, aa * bt - ab * at
    ok = ((d1 > 0) & (d2 > 0)) | (ab > epipolar._COS_PARALLEL * np.sqrt(aa * bb))
    ok &= aa * bb - ab * ab > 0
    return i[ok], j[ok]


@pytest.mark.parametrize("rotvec, t", [
    ((0, 0.05, 0), (0.02, 0, -1.0)), ((0, 0.03, 0), (1.0, 0.1, 0.2)), ((0, 0, 0), (0, 0, 1.0)),
    ((0.1, 0.1, 0.02), (0.3, 0.3, 0.5)), ((0, 0.02, 0), (1.0, 0, 0)), ((0.01, -0.02, 0), (0.001, 0, 0.2)),
])
def test_compiled_kernels_return_the_numpy_pairs_in_their_order(rotvec, t):
    rng = np.random.default_rng(3)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_rotvec(rotvec).as_matrix(), t
    x1 = rng.uniform([-5, -5], [1230, 375], (900, 2))
    x2 = rng.uniform([-5, -5], [1230, 375], (1100, 2))
    x2[:5] = K[:2, 2] + 0.5 * rng.normal(size=(5, 2))
    i, j = epipolar_candidates(x1, x2, T, K, 4.0)
    ri, rj = numpy_candidates(x1, x2, T, K, 4.0)
    assert len(i) > 1000
    assert np.array_equal(i, ri) and np.array_equal(j, rj)


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


def test_window_sweep_equals_binary_searches_ties_included():
    rng = np.random.default_rng(4)
    t1 = rng.integers(-6, 7, 500).astype(np.float64)  # integer values: queries equal to window ends
    ts = np.sort(rng.integers(-9, 10, 200).astype(np.float64))
    for nan in (False, True):
        if nan:
            t1[::50] = np.nan  # (not from finite keypoints) numpy's windows: empty, after every number
        lo, hi = np.empty(len(t1), np.int64), np.empty(len(t1), np.int64)
        epipolar._window_bounds(t1, np.argsort(t1, kind="stable"), ts, 1.0, lo, hi)
        assert np.array_equal(lo, np.searchsorted(ts, t1 - 1.0, "left"))
        assert np.array_equal(hi, np.searchsorted(ts, t1 + 1.0, "right"))
