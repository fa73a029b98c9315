"""The compiled epipolar search and matching (``slamkit.features.epipolar``: one kernel per
``epipolar_candidates``, descriptor selection in one pass) against the implementation they replaced (a numpy
loop over the rings with one kernel call per ring, then ``descriptor_distance``, ``_ratio_test`` and a
lexsort), copied here as the reference: the same pairs in the same order, bit for bit, on random problems
(forward motion with the epipole in the image, sideways motion with the epipole at infinity, binary and float
descriptors, ties, duplicate, non-finite and no keypoints)."""

import numpy as np
import pytest
from numba import njit
from scipy.spatial.transform import Rotation

from slamkit.features import MatchingConfig
from slamkit.features import epipolar
from slamkit.features.base import _max_distance, _ratio_test, descriptor_distance
from slamkit.features.epipolar import epipolar_candidates, epipolar_match

K = np.array([[718.0, 0, 613], [0, 718, 185], [0, 0, 1]])


# ---- the reference: the implementation before the compiled ring loop (unchanged but for names) ----

def _ref_apply(M, X):
    return np.stack([X[:, 0] * m[0] + X[:, 1] * m[1] + X[:, 2] * m[2] for m in M], axis=1)


def _ref_line_parameters(y1, y2, lines, R, t, band):
    e = t / np.linalg.norm(t)
    if abs(e[2]) > 1e-3:
        ep = e[:2] / e[2]
        dx, dy = y2[:, 0] - ep[0], y2[:, 1] - ep[1]
        a = _ref_apply(R, y1)
        w = np.sign(t[2]) * (a[:, :2] * t[2] - a[:, 2:3] * t[:2])
        return (np.arctan2(w[:, 1], w[:, 0]), np.arctan2(dy, dx), np.hypot(dx, dy), 2 * np.pi,
                max(band, np.tan(np.radians(2.0))))
    u, v = epipolar._pencil_basis(e)
    t1 = np.mod(np.arctan2(_ref_apply(v[None], lines)[:, 0], _ref_apply(u[None], lines)[:, 0]), np.pi)
    a2, b2 = _ref_apply(u[None], y2)[:, 0], _ref_apply(v[None], y2)[:, 0]
    return t1, np.mod(np.arctan2(-a2, b2), np.pi), np.hypot(a2, b2), np.pi, band


def _ref_window(t1, order1, t2, j2, half, period):
    if half >= np.pi / 2 - 1e-9:
        return np.zeros(len(t1), np.int64), np.full(len(t1), len(j2), np.int64), j2
    o = np.argsort(t2, kind="stable")
    ts = np.concatenate([t2[o] - period, t2[o], t2[o] + period])  # wrap-around
    if np.isnan(ts).any() or np.isnan(t1).any():  # (not from finite keypoints) numpy's NaN order
        lo, hi = np.searchsorted(ts, t1 - half, "left"), np.searchsorted(ts, t1 + half, "right")
    else:
        lo, hi = _ref_window_bounds(t1, order1, ts, half)
    return lo, hi, np.tile(j2[o], 3)


@njit
def _ref_window_bounds(t1, order1, ts, half):
    n, m = t1.shape[0], ts.shape[0]
    lo = np.empty(n, np.int64)
    hi = np.empty(n, np.int64)
    a = b = 0
    for k in range(n):
        i = order1[k]
        q = t1[i] - half
        while a < m and ts[a] < q:
            a += 1
        lo[i] = a
        q = t1[i] + half
        while b < m and ts[b] <= q:
            b += 1
        hi[i] = b
    return lo, hi


@njit
def _ref_band_kernel(lo, hi, js, L, Y, A, near, aa, bb, at, bt, cos_parallel):
    total = 0
    for i in range(lo.shape[0]):
        total += hi[i] - lo[i]
    out_i = np.empty(total, np.int64)
    out_j = np.empty(total, np.int64)
    m = 0
    for i in range(lo.shape[0]):
        l0, l1, l2, a0, a1, a2 = L[0, i], L[1, i], L[2, i], A[0, i], A[1, i], A[2, i]
        for k in range(lo[i], hi[i]):
            j = js[k]
            y0, y1, y2 = Y[0, j], Y[1, j], Y[2, j]
            if not abs(l0 * y0 + l1 * y1 + l2 * y2) < near[i]:
                continue
            ab = a0 * y0 + a1 * y1 + a2 * y2
            d1 = ab * bt[j] - at[i] * bb[j]
            d2 = aa[i] * bt[j] - ab * at[i]
            if not ((d1 > 0 and d2 > 0) or ab > cos_parallel * np.sqrt(aa[i] * bb[j])):
                continue
            if not aa[i] * bb[j] - ab * ab > 0:
                continue
            out_i[m] = i
            out_j[m] = j
            m += 1
    return out_i[:m], out_j[:m]


def reference_candidates(x1, x2, cam2_from_cam1, K, band_px):
    R, t = np.asarray(cam2_from_cam1)[:3, :3], np.asarray(cam2_from_cam1)[:3, 3]
    if float(np.linalg.norm(t)) < 1e-12 or len(x1) == 0 or len(x2) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    Kinv = np.linalg.inv(K)
    y1 = _ref_apply(Kinv, np.c_[x1, np.ones(len(x1))])
    y2 = _ref_apply(Kinv, np.c_[x2, np.ones(len(x2))])
    band = band_px / K[0, 0]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    lines = _ref_apply(tx @ R, y1)
    t1, t2, amp, period, base = _ref_line_parameters(y1, y2, lines, R, t, band)
    ring = np.floor(4 * np.log2(np.maximum(amp / base, 1.0))).astype(np.int64) + (amp >= base)
    L, Y = lines.T.copy(), y2.T.copy()
    A = _ref_apply(R, y1).T.copy()
    near = band * np.hypot(L[0], L[1])
    aa, bb = (A * A).sum(0), (Y * Y).sum(0)
    at, bt = (A * t[:, None]).sum(0), (Y * t[:, None]).sum(0)
    order1 = np.argsort(t1, kind="stable")
    ii, jj = [], []
    for r in np.unique(ring):
        members = np.flatnonzero(ring == r)
        half = float(np.arcsin(min(1.0, band / base * 2.0 ** (-0.25 * float(r - 1))))) if r > 0 else np.pi
        lo, hi, js = _ref_window(t1, order1, t2[members], members, half, period)
        i, j = _ref_band_kernel(lo, hi, js, L, Y, A, near, aa, bb, at, bt, epipolar._COS_PARALLEL)
        ii.append(i)
        jj.append(j)
    return np.concatenate(ii), np.concatenate(jj)


def reference_match(x1, desc1, x2, desc2, binary, cam2_from_cam1, K, band_px, cfg=MatchingConfig()):
    i, j = reference_candidates(x1, x2, cam2_from_cam1, K, band_px)
    if len(i) == 0:
        return np.empty((0, 2), np.int64)
    dist = descriptor_distance(desc1[i], desc2[j], binary)
    ok = dist <= _max_distance(binary, cfg)
    if not ok.any():
        return np.empty((0, 2), np.int64)
    i, j, dist = _ratio_test(i[ok], j[ok], dist[ok], cfg.ratio)
    o = np.lexsort((dist, j))
    i, j = i[o], j[o]
    first = np.r_[True, j[1:] != j[:-1]] if len(j) else np.zeros(0, bool)
    out = np.stack([i[first], j[first]], axis=1).astype(np.int64)
    return out[np.argsort(out[:, 0], kind="stable")]


# ---- random problems ----

def random_pose(rng, kind):
    """cam2_from_cam1 (4, 4): forward / backward motion (epipole in the image), sideways (t_z = 0: epipole at
    infinity), nearly sideways (epipole far outside) or any direction; small random rotations."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(scale=0.04, size=3)).as_matrix()
    t = {"forward": [0, 0, -1.0], "backward": [0, 0, 1.0], "sideways": [1.0, 0, 0],
         "nearly_sideways": [1.0, 0.2, 5e-4], "any": rng.normal(size=3)}[kind]
    t = np.asarray(t, float) + (0 if kind in ("sideways", "any") else rng.normal(scale=0.05, size=3))
    if kind == "sideways":
        t[1] += rng.normal(scale=0.2)
    T[:3, 3] = t * rng.uniform(0.01, 2.0)
    return T


def random_keypoints(rng, n, integer):
    x = rng.uniform([-5, -5], [1230, 375], (n, 2))
    if n >= 10:
        x[:5] = K[:2, 2] + rng.normal(scale=2.0, size=(5, 2))  # near a forward epipole
        x[5:10] = x[:5]  # duplicates
    return np.round(x) if integer else x  # integer pixels: ties of the angles


def random_descriptors(rng, n1, n2, binary, dims):
    """Descriptors of two images sharing a pool (near neighbours, exact duplicates: distance ties)."""
    pool = rng.integers(0, 256, (max(n1, n2) // 2 + 1, dims), np.uint8) if binary else \
        rng.normal(size=(max(n1, n2) // 2 + 1, dims)).astype(np.float32)
    d1, d2 = pool[rng.integers(0, len(pool), n1)], pool[rng.integers(0, len(pool), n2)]
    if binary:
        flips = rng.random((n2, dims * 8)) < rng.uniform(0, 0.2)
        d2 = d2 ^ np.packbits(flips, axis=1)
    else:
        d2 = d2 + rng.normal(scale=rng.uniform(0, 0.3), size=d2.shape).astype(np.float32)
        d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
        d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
        if n2:
            d2[rng.random(n2) < 0.1] = d2[0]
    return np.ascontiguousarray(d1), np.ascontiguousarray(d2)


KINDS = ["forward", "backward", "sideways", "nearly_sideways", "any"]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("binary", [True, False])
def test_compiled_matching_equals_the_reference_bit_for_bit(kind, binary):
    rng = np.random.default_rng(KINDS.index(kind) + 10 * binary)
    matched = 0
    for trial in range(40):
        T = random_pose(rng, kind)
        n1, n2 = rng.integers(0, 400, 2) if trial % 10 else (0, 50) if trial % 20 else (50, 0)
        x1, x2 = random_keypoints(rng, n1, trial % 3 == 0), random_keypoints(rng, n2, trial % 3 == 0)
        if trial % 7 == 6 and n2 > 20:  # the same keypoints in both images
            x2[:20] = x1[:20] if n1 >= 20 else x2[:20]
        dims = int(rng.choice([32, 5])) if binary else int(rng.choice([128, 4]))
        d1, d2 = random_descriptors(rng, n1, n2, binary, dims)
        band = float(rng.choice([4.0, 0.5, 40.0]))
        cfg = MatchingConfig(ratio=float(rng.choice([0.8, 1.0, 0.6])), max_hamming=int(rng.choice([80, 256])),
                             max_l2=float(rng.choice([0.9, 0.1, 2.0])))
        i, j = epipolar_candidates(x1, x2, T, K, band)
        ri, rj = reference_candidates(x1, x2, T, K, band)
        assert i.dtype == j.dtype == np.int64 and np.array_equal(i, ri) and np.array_equal(j, rj)
        got = epipolar_match(x1, d1, x2, d2, binary, T, K, band, cfg)
        ref = reference_match(x1, d1, x2, d2, binary, T, K, band, cfg)
        assert got.dtype == ref.dtype and got.shape == ref.shape and np.array_equal(got, ref), (trial, kind)
        matched += len(ref)
    assert matched > 200, matched  # the problems have matches (the comparison is not of empty arrays)


def test_non_finite_keypoints_change_nothing_else():
    rng = np.random.default_rng(7)
    for kind in KINDS:
        T = random_pose(rng, kind)
        x1, x2 = random_keypoints(rng, 300, False), random_keypoints(rng, 300, False)
        x1[[3, 50]], x2[[7, 60]] = np.nan, np.inf
        x2[61, 1] = np.nan
        d1, d2 = random_descriptors(rng, 300, 300, True, 32)
        with np.errstate(invalid="ignore"):
            i, j = epipolar_candidates(x1, x2, T, K, 4.0)
            ri, rj = reference_candidates(x1, x2, T, K, 4.0)
            got = epipolar_match(x1, d1, x2, d2, True, T, K, 4.0)
            ref = reference_match(x1, d1, x2, d2, True, T, K, 4.0)
        assert len(ri) > 100 and np.array_equal(i, ri) and np.array_equal(j, rj)
        assert np.array_equal(got, ref) and not {3, 50} & set(got[:, 0]) and not {7, 60, 61} & set(got[:, 1])


def test_descriptors_at_nan_distance_never_match():
    rng = np.random.default_rng(8)
    T = random_pose(rng, "forward")
    x1, x2 = random_keypoints(rng, 300, False), random_keypoints(rng, 300, False)
    d1, d2 = random_descriptors(rng, 300, 300, False, 8)
    d2[::3] = np.nan
    got = epipolar_match(x1, d1, x2, d2, False, T, K, 40.0)
    assert np.array_equal(got, reference_match(x1, d1, x2, d2, False, T, K, 40.0))
    assert len(got) > 20 and not (got[:, 1] % 3 == 0).any()


def test_argsort_with_ties_in_index_order_is_numpys_stable_argsort():
    rng = np.random.default_rng(9)
    for n in (0, 1, 2, 17, 1000, 5000):
        t = rng.integers(-20, 20, n).astype(np.float64) / 4  # many ties
        t[rng.random(n) < 0.05] = np.nan
        t[rng.random(n) < 0.05] = -0.0  # equal to 0.0
        t[rng.random(n) < 0.02] = np.inf
        order = np.argsort(t)
        epipolar._ties_in_index_order(t, order)
        assert np.array_equal(order, np.argsort(t, kind="stable"))
