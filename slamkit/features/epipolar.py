"""Descriptor matching guided by a known relative pose: candidates only within an epipolar band.

Mapping matches a new keyframe with neighbouring keyframes whose poses are known. A brute-force match
compares every keypoint with every other (and its ratio test then competes with look-alikes anywhere in the
image); here a keypoint of the first image is compared only with the keypoints of the second that lie within
``band_px`` of its epipolar line and in front of both cameras (ORB-SLAM's SearchForTriangulation, with the
epipolar band in place of its vocabulary tree).

The search is vectorised without an (N1, N2) table: every epipolar line of the second image passes through
its epipole ``e``, so lines form a one-parameter pencil. With ``u, v`` an orthonormal basis of the plane
orthogonal to ``e`` (normalized camera coordinates), the line ``cos(t) u + sin(t) v`` has parameter ``t`` in
[0, pi); a keypoint ``y`` lies on the line ``t_y = atan2(-u.y, v.y)``, and its distance to the line of
parameter ``t`` is at least ``A_y |sin(t - t_y)|`` with ``A_y = hypot(u.y, v.y)`` (the line's unit
3-vector has a normal of length <= 1). So the keypoints within the band of a line are among those whose
``t_y`` is within ``asin(band / A_y)`` of it: a window in the keypoints sorted by ``t_y`` (keypoints near the
epipole, whose windows are wide, are grouped in rings of ``A_y`` growing by 2^(1/4), each searched with its own
window), checked exactly afterwards. The rings, their windows and the exact tests run in one compiled kernel
per call (:func:`_pencil_kernel`), and the choice among the candidates (distance, ratio test, one-to-one) in
another (:func:`_select`), with the numpy steps' results bit for bit.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from . import hamming
from .base import MatchingConfig, _max_distance, descriptor_distance

_COS_PARALLEL = np.cos(np.radians(1.0))
"""Rays within 1 degree of parallel pass the cheirality test whatever their depths: keypoint noise moves
the matches of distant points past the point at infinity of the epipolar line (a negative depth)."""


def _pencil_basis(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal (u, v) spanning the plane orthogonal to the unit 3-vector ``e``."""
    a = np.eye(3)[int(np.argmin(np.abs(e)))]
    u = np.cross(e, a)
    u /= np.linalg.norm(u)
    return u, np.cross(e, u)


@njit(cache=True, nogil=True)
def _window_bounds(t1, order1, ts, half, lo, hi):
    """``numpy.searchsorted(ts, t1 - half, "left")`` and ``(ts, t1 + half, "right")`` for sorted ``ts`` without
    NaN, into ``lo`` and ``hi``, in one sweep over ``t1`` in its ascending ``order1`` (NaN last, as numpy sorts;
    the queries ascend too): O(N + M) instead of N binary searches. A NaN in ``t1`` (not from finite
    keypoints) gets numpy's empty window at the end."""
    n, m = t1.shape[0], ts.shape[0]
    a = b = 0
    for k in range(n):
        i = order1[k]
        q = t1[i]
        if np.isnan(q):
            lo[i] = hi[i] = m
            continue
        while a < m and ts[a] < q - half:
            a += 1
        lo[i] = a
        while b < m and ts[b] <= q + half:
            b += 1
        hi[i] = b


@njit(cache=True, nogil=True)
def _band(lo, hi, js, L, Y, A, near, aa, bb, at, bt, cos_parallel, out_i, out_j, m):
    """The exact tests of :func:`epipolar_candidates` over the windows ``js[lo[i]:hi[i]]`` of each line i, pair
    by pair with the same float operations in the same order as the numpy expressions they replace (no (K,)
    temporaries): appends the pairs kept, in window order, to ``out_i``, ``out_j`` from ``m``; their new
    length."""
    for i in range(lo.shape[0]):
        l0, l1, l2, a0, a1, a2 = L[0, i], L[1, i], L[2, i], A[0, i], A[1, i], A[2, i]
        for k in range(lo[i], hi[i]):
            j = js[k]
            y0, y1, y2 = Y[0, j], Y[1, j], Y[2, j]
            if not abs(l0 * y0 + l1 * y1 + l2 * y2) < near[i]:  # the band
                continue
            ab = a0 * y0 + a1 * y1 + a2 * y2
            d1 = ab * bt[j] - at[i] * bb[j]
            d2 = aa[i] * bt[j] - ab * at[i]
            if not ((d1 > 0 and d2 > 0) or ab > cos_parallel * np.sqrt(aa[i] * bb[j])):  # cheirality
                continue
            if not aa[i] * bb[j] - ab * ab > 0:
                continue
            out_i[m] = i
            out_j[m] = j
            m += 1
    return m


@njit(cache=True, nogil=True)
def _ties_in_index_order(t, order):
    """Make an argsort ``order`` of ``t`` (NaN last, as numpy sorts) stable, in place: each run of equal values
    (or of NaN) in ascending index order."""
    a, n = 0, order.shape[0]
    while a < n:
        b, v = a + 1, t[order[a]]
        while b < n and (t[order[b]] == v or (np.isnan(t[order[b]]) and np.isnan(v))):
            b += 1
        if b - a > 1:
            order[a:b] = np.sort(order[a:b])
        a = b


@njit(cache=True, nogil=True)
def _pencil_kernel(t1, order1, t2, by_t2, ring, rings, halves, period, L, Y, A, near, aa, bb, at, bt,
                   cos_parallel):
    """The search of :func:`epipolar_candidates`, ring by ring (``rings``: ascending, ``halves``: each one's
    window half-width): a ring's keypoints in ``t2`` order (``by_t2``: an argsort of ``t2``, its ties put in
    index order here: numpy's stable argsort, about 6 times slower, sorts the same), repeated at -period, 0,
    +period (wrap-around), each line's window found by :func:`_window_bounds` (``order1``: an argsort of
    ``t1``, made stable likewise), then the exact tests of :func:`_band`. A half-width >= pi / 2: every
    keypoint of the ring for every line, in index order. Returns ((M,) i, (M,) j), ring by ring, line by
    line, in window order. (A ring that is windowed has keypoints of finite amp, hence finite ``t2``: no NaN
    in its ``ts``.)"""
    n1, n2, g = t1.shape[0], t2.shape[0], rings.shape[0]
    _ties_in_index_order(t1, order1)
    _ties_in_index_order(t2, by_t2)
    group = np.searchsorted(rings, ring)
    start = np.zeros(g + 1, np.int64)
    for j in range(n2):
        start[group[j] + 1] += 1
    for r in range(g):
        start[r + 1] += start[r]
    by_index, by_angle = np.empty(n2, np.int64), np.empty(n2, np.int64)  # each ring's keypoints, in 2 orders
    fill_index, fill_angle = start[:g].copy(), start[:g].copy()
    for k in range(n2):
        by_index[fill_index[group[k]]] = k
        fill_index[group[k]] += 1
        j = by_t2[k]
        by_angle[fill_angle[group[j]]] = j
        fill_angle[group[j]] += 1
    ts, js = np.empty(3 * n2), np.empty(3 * n2, np.int64)
    lo, hi = np.empty(n1, np.int64), np.empty(n1, np.int64)
    out_i, out_j = np.empty(n2, np.int64), np.empty(n2, np.int64)
    m = 0
    for r in range(g):
        s, n = start[r], start[r + 1] - start[r]
        if halves[r] >= np.pi / 2 - 1e-9:
            js[:n] = by_index[s:s + n]
            lo[:] = 0
            hi[:] = n
        else:
            for k in range(n):
                j = by_angle[s + k]
                ts[k], ts[n + k], ts[2 * n + k] = t2[j] - period, t2[j], t2[j] + period
                js[k] = js[n + k] = js[2 * n + k] = j
            _window_bounds(t1, order1, ts[:3 * n], halves[r], lo, hi)
        total = m
        for i in range(n1):
            total += hi[i] - lo[i]
        if total > out_i.shape[0]:
            grown = max(total, 2 * out_i.shape[0])
            out_i, out_j = np.concatenate((out_i[:m], np.empty(grown - m, np.int64))), \
                np.concatenate((out_j[:m], np.empty(grown - m, np.int64)))
        m = _band(lo, hi, js, L, Y, A, near, aa, bb, at, bt, cos_parallel, out_i, out_j, m)
    return out_i[:m].copy(), out_j[:m].copy()


def _line_parameters(y1: np.ndarray, y2: np.ndarray, lines: np.ndarray, R: np.ndarray, t: np.ndarray,
                     band: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """Where the lines and keypoints lie in the pencil through the epipole: (t1 (N1,) per line, t2 (N2,)
    per keypoint, amp (N2,) with distance(keypoint j, line i) >= amp_j |sin(t1_i - t2_j)|, the period of
    the parameter, the amp below which a keypoint is a candidate of every line).

    Finite epipole: the parameter is the direction (2 pi) from the epipole ``e'`` and amp the distance to
    it, and only the half-line from ``e'`` on which the points in front of both cameras project is kept
    (along ``sign(t_z) (a_xy t_z - a_z t_xy)``, a = R y1). Keypoints within ~2 degrees of the epipole are
    candidates of every line (the parallel-ray tolerance reaches there). Epipole at or near infinity: the
    unoriented pencil (period pi) of the module docstring."""
    e = t / np.linalg.norm(t)
    if abs(e[2]) > 1e-3:
        ep = e[:2] / e[2]
        dx, dy = y2[:, 0] - ep[0], y2[:, 1] - ep[1]
        a = _apply(R, y1)
        w = np.sign(t[2]) * (a[:, :2] * t[2] - a[:, 2:3] * t[:2])
        return (np.arctan2(w[:, 1], w[:, 0]), np.arctan2(dy, dx), np.hypot(dx, dy), 2 * np.pi,
                max(band, np.tan(np.radians(2.0))))
    u, v = _pencil_basis(e)
    t1 = np.mod(np.arctan2(_apply(v[None], lines)[:, 0], _apply(u[None], lines)[:, 0]), np.pi)
    a2, b2 = _apply(u[None], y2)[:, 0], _apply(v[None], y2)[:, 0]
    return t1, np.mod(np.arctan2(-a2, b2), np.pi), np.hypot(a2, b2), np.pi, band


def epipolar_candidates(x1: np.ndarray, x2: np.ndarray, cam2_from_cam1: np.ndarray, K: np.ndarray,
                        band_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Every keypoint pair (i in image 1, j in image 2) with x2[j] within ``band_px`` pixels of the epipolar
    line of x1[i] and both rays meeting in front of both cameras (or within 1 degree of parallel: distant
    points).

    x1: (N1, 2), x2: (N2, 2) undistorted pixels; cam2_from_cam1: (4, 4) or (3, 4) relative pose; K: (3, 3)
    (one focal length for the band: ``K[0, 0]``). Returns ((K,) int64 i, (K,) int64 j). Empty when the
    baseline is zero (no epipolar geometry).
    """
    R, t = np.asarray(cam2_from_cam1)[:3, :3], np.asarray(cam2_from_cam1)[:3, 3]
    if float(np.linalg.norm(t)) < 1e-12 or len(x1) == 0 or len(x2) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    # (small matrix products written out: numpy's matmul of (N, 3) by (3, 3) is slow on some BLAS builds)
    Kinv = np.linalg.inv(K)
    y1, y2 = _apply(Kinv, x1), _apply(Kinv, x2)
    band = band_px / K[0, 0]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    lines = _apply(tx @ R, y1)  # (N1, 3) epipolar lines in image 2, all through the epipole
    t1, t2, amp, period, base = _line_parameters(y1, y2, lines, R, t, band)
    # rings of keypoints by amp, x 2^(1/4) outwards from `base`: each ring's window is asin(band / its inner
    # amp); ring 0 (within `base` of the epipole) holds candidates of every line
    ring = np.floor(4 * np.log2(np.maximum(amp / base, 1.0))).astype(np.int64) + (amp >= base)
    # exact band, then cheirality: d2 y2 = d1 R y1 + t with d1, d2 > 0 (least squares, Cramer's rule on
    # [aa, -ab; -ab, bb] [d1, d2] = [-at, bt], both sides times det >= 0), pair by pair in _band
    L, Y = lines.T.copy(), y2.T.copy()
    A = _apply(R, y1).T.copy()
    near = band * np.hypot(L[0], L[1])
    aa, bb = (A * A).sum(0), (Y * Y).sum(0)
    at, bt = (A * t[:, None]).sum(0), (Y * t[:, None]).sum(0)
    rings = np.unique(ring)
    halves = np.array([float(np.arcsin(min(1.0, band / base * 2.0 ** (-0.25 * float(r - 1))))) if r > 0
                       else np.pi for r in rings.tolist()])
    return _pencil_kernel(t1, np.argsort(t1), t2, np.argsort(t2), ring, rings, halves, float(period), L, Y, A,
                          near, aa, bb, at, bt, _COS_PARALLEL)


@njit(cache=True, nogil=True)
def _apply(M, X):
    """X @ M.T for X (N, 3), or (N, 2) with a third coordinate 1, and M (k, 3): (N, k) float64, each element
    ``(x0 m0 + x1 m1) + x2 m2`` as numpy computes it column by column (BLAS's matmul would round otherwise)."""
    out = np.empty((X.shape[0], M.shape[0]))
    for a in range(X.shape[0]):
        x0, x1 = X[a, 0], X[a, 1]
        x2 = X[a, 2] if X.shape[1] == 3 else 1.0
        for r in range(M.shape[0]):
            out[a, r] = x0 * M[r, 0] + x1 * M[r, 1] + x2 * M[r, 2]
    return out


def epipolar_match(x1: np.ndarray, desc1: np.ndarray, x2: np.ndarray, desc2: np.ndarray, binary: bool,
                   cam2_from_cam1: np.ndarray, K: np.ndarray, band_px: float,
                   cfg: MatchingConfig = MatchingConfig()) -> np.ndarray:
    """Match keypoints of two images with a known relative pose, each only among its
    :func:`epipolar_candidates`: nearest descriptor within ``cfg``'s maximum distance, Lowe's ratio test
    against the second-nearest candidate (a lone candidate passes), then one-to-one (the closest descriptor
    keeps a keypoint of image 2).

    x1 (N1, 2), x2 (N2, 2): undistorted pixels; desc1 (N1, D), desc2 (N2, D). Returns (M, 2) int64 pairs
    (i in image 1, j in image 2), sorted by i.
    """
    i, j = epipolar_candidates(x1, x2, cam2_from_cam1, K, band_px)
    if len(i) == 0:
        return np.empty((0, 2), np.int64)
    if binary and desc1.dtype == np.uint8 and desc2.dtype == np.uint8:  # Hamming distances, compiled
        dist = _hamming_pairs(hamming.words(desc1), hamming.words(desc2), i, j)
    else:
        dist = descriptor_distance(desc1[i], desc2[j], binary)
    return _select(i, j, dist, len(x1), len(x2), np.float32(_max_distance(binary, cfg)), np.float32(cfg.ratio))


@njit(cache=True, nogil=True)
def _hamming_pairs(w1, w2, i, j):
    """(K,) float32 Hamming distances of the descriptor words ``w1[i[k]]``, ``w2[j[k]]``."""
    out = np.empty(i.shape[0], np.float32)
    for k in range(i.shape[0]):
        out[k] = hamming._distance(w1, i[k], w2, j[k])
    return out


@njit(cache=True, nogil=True)
def _select(i, j, dist, n1, n2, max_dist, ratio):
    """The matches of :func:`epipolar_match` among the candidate pairs (i, j) with float32 descriptor
    distances ``dist``, in one pass (``base._ratio_test`` then ``np.lexsort((dist, j))``'s one-to-one, ties
    included): pairs within ``max_dist`` (float32 comparisons, as numpy's with a Python float), each i's
    nearest (the first of equals, in candidate order) kept when below ``ratio`` x the second nearest (the
    second of equals counts) or alone, then each j to its nearest i (the lowest i of equals). (M, 2) int64
    sorted by i."""
    d0, d1 = np.full(n1, np.inf, np.float32), np.full(n1, np.inf, np.float32)
    j0 = np.full(n1, -1, np.int64)
    for k in range(i.shape[0]):
        d, a = dist[k], i[k]
        if not d <= max_dist:  # (NaN too)
            continue
        if d < d0[a]:
            d1[a], d0[a], j0[a] = d0[a], d, j[k]
        elif d < d1[a]:
            d1[a] = d
    best_i, best_d = np.full(n2, -1, np.int64), np.full(n2, np.inf, np.float32)
    for a in range(n1):
        if j0[a] < 0 or not (d1[a] == np.inf or d0[a] < ratio * d1[a]):
            j0[a] = -1
        elif d0[a] < best_d[j0[a]]:
            best_i[j0[a]], best_d[j0[a]] = a, d0[a]
    out = np.empty((n1, 2), np.int64)
    m = 0
    for a in range(n1):
        if j0[a] >= 0 and best_i[j0[a]] == a:
            out[m, 0], out[m, 1] = a, j0[a]
            m += 1
    return out[:m].copy()
