"""The compiled Hamming brute force (slamkit.features.hamming) against OpenCV's BFMatcher(NORM_HAMMING):
the same neighbours and distances, ties included, and match_descriptors' pairs as OpenCV's knnMatch gives
them (ratio test, maximum distance, mutual check)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from slamkit.features import MatchingConfig, match_descriptors
from slamkit.features import hamming


def _opencv_pairs(d1: np.ndarray, d2: np.ndarray, cfg: MatchingConfig) -> np.ndarray:
    """match_descriptors' rule on OpenCV's brute force (the implementation the kernel replaced)."""
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    knn = bf.knnMatch(d1, d2, k=2)
    a = np.array([(m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance) for m in knn], np.float64)
    pairs = a[(a[:, 2] < cfg.ratio * a[:, 3]) & (a[:, 2] <= cfg.max_hamming), :2].astype(np.int64)
    if cfg.mutual and len(pairs):
        js = np.unique(pairs[:, 1])
        back = np.full(len(d2), -1, np.int64)
        for m in bf.match(np.ascontiguousarray(d2[js]), d1):
            back[js[m.queryIdx]] = m.trainIdx
        pairs = pairs[back[pairs[:, 1]] == pairs[:, 0]]
    return pairs


def _orb(seed: int, n: int = 1500) -> np.ndarray:
    """ORB descriptors of a random textured image (blurred noise, shifted per seed)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (480, 640), np.uint8), (0, 0), 2.0)
    _, desc = cv2.ORB_create(n).detectAndCompute(cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX), None)
    return desc


@pytest.mark.parametrize("width", [32, 61, 64])
def test_knn2_equals_opencv_with_ties(width):
    rng = np.random.default_rng(width)
    # few distinct rows and few bits set: many equal distances, so tie-breaking is exercised
    base = rng.integers(0, 256, (40, width), np.uint8) & rng.integers(0, 256, (40, width), np.uint8) & 0x11
    a, b = base[rng.integers(0, 40, 300)], base[rng.integers(0, 40, 500)]
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(a, b, k=2)
    best, d0, d1 = hamming.knn2(hamming.words(a), hamming.words(b))
    assert np.array_equal(best, [m[0].trainIdx for m in knn])
    assert np.array_equal(d0, [m[0].distance for m in knn])
    assert np.array_equal(d1, [m[1].distance for m in knn])
    ties = sum(m[0].distance == m[1].distance for m in knn)
    assert ties > 50  # the case this test is for
    nn = cv2.BFMatcher(cv2.NORM_HAMMING).match(b, a)
    assert np.array_equal(hamming.nearest(hamming.words(b), hamming.words(a)), [m.trainIdx for m in nn])


@pytest.mark.parametrize("cfg", [MatchingConfig(), MatchingConfig(ratio=0.6, max_hamming=50),
                                 MatchingConfig(ratio=1.0, mutual=False)])
def test_match_descriptors_equals_opencvs_pairs_on_orb(cfg):
    d1, d2 = _orb(0), _orb(0)[::-1].copy()
    d3 = _orb(1)
    for a, b in ((d1, d2), (d1, d3), (d3[:7], d1), (d1[:2], d3)):
        got = match_descriptors(a, b, True, cfg)
        assert got.dtype == np.int64 and got.shape[1] == 2
        assert np.array_equal(got, _opencv_pairs(a, b, cfg))
    assert len(match_descriptors(d1, d2, True, cfg)) > 0.9 * len(d1)  # a permutation of itself: all found


def test_empty_and_single_rows():
    d = _orb(2)
    assert match_descriptors(d[:1], d, True).shape == (0, 2)
    best, d0, d1 = hamming.knn2(hamming.words(d[:3]), hamming.words(d[:1]))
    assert best.tolist() == [0, 0, 0] and (d1 == 1 << 30).all()
    assert hamming.knn2(hamming.words(d[:0]), hamming.words(d))[0].shape == (0,)
    with pytest.raises(ValueError, match="binary descriptors"):
        hamming.words(d[0])


@pytest.mark.parametrize("radius", [3.0, 10.0, 0.5])
@pytest.mark.parametrize("cfg", [MatchingConfig(), MatchingConfig(ratio=0.6, max_hamming=50)])
def test_compiled_guided_match_equals_the_numpy_steps(radius, cfg):
    from slamkit.features.base import _guided_match_arrays, guided_match

    rng = np.random.default_rng(int(radius * 10) + int(cfg.ratio * 100))
    n, m = 1200, 900
    keypoints = rng.uniform(0, 640, (n, 2))
    keypoints[:200] = np.round(keypoints[:200])  # keypoints on the same pixel and exactly on the radius
    kp_desc = rng.integers(0, 256, (n, 32), np.uint8)
    src = rng.integers(0, n, m)
    proj = keypoints[src] + rng.normal(0, radius / 2, (m, 2))
    proj[:100] = np.round(proj[:100])
    point_desc = kp_desc[src].copy()
    flips = rng.integers(0, 256, point_desc.shape, np.uint8) & rng.integers(0, 256, point_desc.shape, np.uint8) \
        & rng.integers(0, 256, point_desc.shape, np.uint8)
    point_desc ^= flips  # near, not equal, descriptors: ratio test and distance limit both decide
    point_desc[::7] = point_desc[0]  # duplicated descriptors: ties for one keypoint
    for taken in (None, rng.random(n) < 0.3):
        got = guided_match(proj, point_desc, keypoints, kp_desc, True, radius, cfg, taken)
        ref = _guided_match_arrays(proj, point_desc, keypoints, kp_desc, True, radius, cfg, taken)
        assert got.dtype == np.int64 and np.array_equal(got, ref)
        assert len(ref) > (20 if radius >= 3 else 0)


def test_compiled_vocabulary_descent_equals_the_numpy_levels():
    from slamkit.place_recognition.vocabulary import Vocabulary, VocabularyConfig

    images = [_orb(s, 400) for s in range(6)]
    voc = Vocabulary.train(images, VocabularyConfig(branching=4, depth=3, iterations=3))
    queries = np.concatenate([_orb(11, 600), images[0][:50],
                              np.zeros((3, 32), np.uint8)])  # all-zero rows: many equal distances
    words = voc.transform(queries)
    assert words.dtype == np.int32 and (words >= 0).all()
    assert np.array_equal(words, voc._transform_arrays(queries))
    assert len(np.unique(words)) > 10

