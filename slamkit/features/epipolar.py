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
window), checked exactly afterwards.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .base import MatchingConfig, _max_distance, _ratio_test, descriptor_distance

_COS_PARALLEL = np.cos(np.radians(1.0))
"""Rays within 1 degree of parallel pass the cheirality test whatever their depths: keypoint noise moves
the matches of distant points past the point at infinity of the epipolar line (a negative depth)."""


def _pencil_basis(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal (u, v) spanning the plane orthogonal to the unit 3-vector ``e``."""
    a = np.eye(3)[int(np.argmin(np.abs(e)))]
    u = np.cross(e, a)
    u /= np.linalg.norm(u)
    return u, np.cross(e, u)


def _window(t1: np.ndarray, order1: np.ndarray, t2: np.ndarray, j2: np.ndarray, half: float, period: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The keypoints ``j2`` whose ``t2`` lies within ``half`` of each ``t1[i]`` modulo ``period``, as windows
    (lo (N1,), hi (N1,), js (K,)): the candidates of line i are ``js[lo[i]:hi[i]]``, in ``t2`` order (ties in
    ``j2`` order). ``order1``: ``t1``'s ascending order. ``half`` >= pi / 2: every keypoint for every line, in
    ``j2`` order."""
    if half >= np.pi / 2 - 1e-9:
        return np.zeros(len(t1), np.int64), np.full(len(t1), len(j2), np.int64), j2
    o = np.argsort(t2, kind="stable")
    ts = np.concatenate([t2[o] - period, t2[o], t2[o] + period])  # wrap-around
    if np.isnan(ts).any() or np.isnan(t1).any():  # (not from finite keypoints) numpy's NaN order
        lo, hi = np.searchsorted(ts, t1 - half, "left"), np.searchsorted(ts, t1 + half, "right")
    else:
        lo, hi = _window_bounds(t1, order1, ts, half)
    return lo, hi, np.tile(j2[o], 3)


@njit(cache=True, nogil=True)
def _window_bounds(t1, order1, ts, half):
    """``numpy.searchsorted(ts, t1 - half, "left")`` and ``(ts, t1 + half, "right")`` for sorted ``ts`` and
    ``t1`` without NaN, in one sweep over ``t1`` in its ascending ``order1`` (the queries ascend too): O(N + M)
    instead of N binary searches."""
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


@njit(cache=True, nogil=True)
def _band_kernel(lo, hi, js, L, Y, A, near, aa, bb, at, bt, cos_parallel):
    """The exact tests of :func:`epipolar_candidates` over the windows of :func:`_window`, pair by pair with
    the same float operations in the same order as the numpy expressions they replace (no (K,) temporaries):
    returns ((M,) i, (M,) j) of the pairs kept, in window order."""
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
    return out_i[:m], out_j[:m]


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
    y1, y2 = _apply(Kinv, np.c_[x1, np.ones(len(x1))]), _apply(Kinv, np.c_[x2, np.ones(len(x2))])
    band = band_px / K[0, 0]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    lines = _apply(tx @ R, y1)  # (N1, 3) epipolar lines in image 2, all through the epipole
    t1, t2, amp, period, base = _line_parameters(y1, y2, lines, R, t, band)
    # rings of keypoints by amp, x 2^(1/4) outwards from `base`: each ring's window is asin(band / its inner
    # amp); ring 0 (within `base` of the epipole) holds candidates of every line
    ring = np.floor(4 * np.log2(np.maximum(amp / base, 1.0))).astype(np.int64) + (amp >= base)
    # exact band, then cheirality: d2 y2 = d1 R y1 + t with d1, d2 > 0 (least squares, Cramer's rule on
    # [aa, -ab; -ab, bb] [d1, d2] = [-at, bt], both sides times det >= 0), pair by pair in _band_kernel
    L, Y = lines.T.copy(), y2.T.copy()
    A = _apply(R, y1).T.copy()
    near = band * np.hypot(L[0], L[1])
    aa, bb = (A * A).sum(0), (Y * Y).sum(0)
    at, bt = (A * t[:, None]).sum(0), (Y * t[:, None]).sum(0)
    order1 = np.argsort(t1, kind="stable")
    ii, jj = [], []
    for r in np.unique(ring):
        members = np.flatnonzero(ring == r)
        half = float(np.arcsin(min(1.0, band / base * 2.0 ** (-0.25 * float(r - 1))))) if r > 0 else np.pi
        lo, hi, js = _window(t1, order1, t2[members], members, half, period)
        i, j = _band_kernel(lo, hi, js, L, Y, A, near, aa, bb, at, bt, _COS_PARALLEL)
        ii.append(i)
        jj.append(j)
    return np.concatenate(ii), np.concatenate(jj)


def _apply(M: np.ndarray, X: np.ndarray) -> np.ndarray:
    """X @ M.T for X (N, 3) and M (k, 3), one column at a time."""
    return np.stack([X[:, 0] * m[0] + X[:, 1] * m[1] + X[:, 2] * m[2] for m in M], axis=1)


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
    dist = descriptor_distance(desc1[i], desc2[j], binary)
    ok = dist <= _max_distance(binary, cfg)
    if not ok.any():
        return np.empty((0, 2), np.int64)
    i, j, dist = _ratio_test(i[ok], j[ok], dist[ok], cfg.ratio)
    o = np.lexsort((dist, j))  # one keypoint of image 2 per match: the closest descriptor
    i, j = i[o], j[o]
    first = np.r_[True, j[1:] != j[:-1]] if len(j) else np.zeros(0, bool)
    out = np.stack([i[first], j[first]], axis=1).astype(np.int64)
    return out[np.argsort(out[:, 0], kind="stable")]
