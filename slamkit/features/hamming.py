"""Compiled Hamming-distance kernels for binary descriptors (ORB, BRISK, AKAZE), with numba.

Brute-force nearest neighbours (``knn2``: the best and second-best of each query row, ``nearest``: the best)
with OpenCV ``BFMatcher(NORM_HAMMING)``'s results exactly, ties included (the lowest train index wins a
tie, as in OpenCV's k-nearest insertion), at about a sixth of its single-thread time: 64 bits at a time
with the CPU's popcount instruction; guided matching by projection (``guided_match``) and the descent of a
vocabulary tree (``descend``) likewise return what the numpy code does. Each call runs on the calling
thread and releases the GIL (``nogil``), so the result never depends on threads. (Splitting a large brute
force over two threads was measured and dropped: on two cores, beside the prefetch thread's extraction,
mapping got slower.) Kernels compile on first use and are cached on disk by numba (in ``__pycache__``
beside this file, or numba's per-user cache when that is read-only)."""

from __future__ import annotations

import numpy as np
from numba import njit, types
from numba.extending import intrinsic

_FAR = 1 << 30


@intrinsic
def _popcount64(typingctx, x):
    """The number of set bits of a uint64 (LLVM's ``ctpop``: one POPCNT instruction)."""
    sig = types.uint64(types.uint64)

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic("llvm.ctpop", [args[0].type])
        return builder.call(fn, args)

    return sig, codegen


def words(descriptors: np.ndarray) -> np.ndarray:
    """(N, D) uint8 packed bits as (N, ceil(D / 8)) uint64 words (zero padding: no effect on distances)."""
    d = np.ascontiguousarray(descriptors, dtype=np.uint8)
    if d.ndim != 2:
        raise ValueError(f"binary descriptors must be (N, D) uint8, got shape {d.shape}")
    if d.shape[1] % 8:
        d = np.concatenate([d, np.zeros((len(d), 8 - d.shape[1] % 8), np.uint8)], axis=1)
    return d.view(np.uint64)


@njit(cache=True, nogil=True)
def _distance(a: np.ndarray, i: int, b: np.ndarray, j: int) -> int:
    d = 0
    for k in range(a.shape[1]):
        d += _popcount64(a[i, k] ^ b[j, k])
    return d


@njit(cache=True, nogil=True)
def _knn2_kernel(a, b, best, d_best, d_second):
    m = b.shape[0]
    if a.shape[1] == 4:  # 256-bit descriptors (ORB, BRISK's half): the words of the query row in registers
        for i in range(a.shape[0]):
            a0, a1, a2, a3 = a[i, 0], a[i, 1], a[i, 2], a[i, 3]
            d0, d1, j0 = _FAR, _FAR, -1
            for j in range(m):
                d = np.int64(_popcount64(a0 ^ b[j, 0]) + _popcount64(a1 ^ b[j, 1])
                             + _popcount64(a2 ^ b[j, 2]) + _popcount64(a3 ^ b[j, 3]))
                if d < d1:
                    if d < d0:
                        d1, d0, j0 = d0, d, j
                    else:
                        d1 = d
            best[i], d_best[i], d_second[i] = j0, d0, d1
        return
    for i in range(a.shape[0]):
        d0, d1, j0 = _FAR, _FAR, -1
        for j in range(m):
            d = _distance(a, i, b, j)
            if d < d1:
                if d < d0:
                    d1, d0, j0 = d0, d, j
                else:
                    d1 = d
        best[i], d_best[i], d_second[i] = j0, d0, d1


def knn2(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each row of ``a`` (N, W) uint64 words (:func:`words`): the index of its nearest row of ``b``
    (M, W), that Hamming distance, and the second-nearest distance (``1 << 30`` when M < 2). (N,) int64,
    int64, int64."""
    n = len(a)
    best, d_best, d_second = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
    if not (n and len(b)):
        best[:], d_best[:], d_second[:] = -1, _FAR, _FAR
    else:
        _knn2_kernel(a, b, best, d_best, d_second)
    return best, d_best, d_second


def nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each row of ``a``: the index of its nearest row of ``b`` (-1 when ``b`` is empty)."""
    return knn2(a, b)[0]


@njit(cache=True, nogil=True)
def _guided_kernel(px, py, pcx, pcy, pw, kx, ky, kw, order, start, count, width, height, radius, max_dist,
                   ratio, taken, out_pt, out_kp):
    """See :func:`guided_match`; writes the pairs into out_pt / out_kp (sorted by keypoint), returns their
    number."""
    n_kp = kx.shape[0]
    best_pt = np.full(n_kp, -1, np.int64)
    best_d = np.full(n_kp, _FAR, np.int64)
    r2 = radius * radius
    ratio32 = np.float32(ratio)
    for i in range(px.shape[0]):
        cx, cy = pcx[i], pcy[i]
        if cx < 1 or cx > width - 2 or cy < 1 or cy > height - 2:
            continue
        d0, d1, j0 = _FAR, _FAR, -1
        for dy in range(-1, 2):  # the 3x3 cells, row by row; in a cell, keypoints by index (the numpy order)
            for dx in range(-1, 2):
                key = (cy + dy) * width + cx + dx
                for s in range(start[key], start[key] + count[key]):
                    j = order[s]
                    ex, ey = kx[j] - px[i], ky[j] - py[i]
                    if ex * ex + ey * ey > r2 or taken[j]:
                        continue
                    d = _distance(pw, i, kw, j)
                    if d > max_dist:
                        continue
                    if d < d1:
                        if d < d0:
                            d1, d0, j0 = d0, d, j
                        else:
                            d1 = d
        if j0 < 0:
            continue
        if d1 < _FAR and not np.float32(d0) < ratio32 * np.float32(d1):  # Lowe's ratio (float32, as numpy's)
            continue
        if d0 < best_d[j0]:  # one map point per keypoint: the closest descriptor, ties to the first point
            best_d[j0], best_pt[j0] = d0, i
    k = 0
    for j in range(n_kp):
        if best_pt[j] >= 0:
            out_pt[k], out_kp[k] = best_pt[j], j
            k += 1
    return k


def guided_match(px, py, pcx, pcy, point_words, kx, ky, kp_words, grid, radius: float, max_dist: float,
                 ratio: float, taken: np.ndarray) -> np.ndarray:
    """Guided matching of binary descriptors (``slamkit.features.guided_match``'s rule, compiled): for each
    projected point (px, py) in grid cell (pcx, pcy), the keypoints within ``radius`` in its 3x3 cells
    (``grid`` = (order, start, count, width, height) of the keypoints' cells), nearest descriptor within
    ``max_dist`` bits, Lowe's ratio against the second nearest, then one point per keypoint. (K, 2) int64
    pairs (point index, keypoint index) sorted by keypoint."""
    order, start, count, width, height = grid
    n = min(len(px), len(kx))
    out_pt, out_kp = np.empty(n, np.int64), np.empty(n, np.int64)
    k = _guided_kernel(px, py, pcx, pcy, point_words, kx, ky, kp_words, order, start, count, width, height,
                       float(radius), int(max_dist), float(ratio), taken, out_pt, out_kp)
    return np.stack([out_pt[:k], out_kp[:k]], axis=1)


@njit(cache=True, nogil=True)
def _descend_kernel(dw, cw, children, node_word, out):
    for i in range(dw.shape[0]):
        node = 0
        while True:
            best, d_best = -1, _FAR
            for c in range(children.shape[1]):
                child = children[node, c]
                if child < 0:
                    continue
                d = _distance(dw, i, cw, child)
                if d < d_best:  # the first nearest child, as numpy's argmin
                    best, d_best = child, d
            if best < 0:
                break
            node = best
        out[i] = node_word[node]


def descend(descriptor_words: np.ndarray, center_words: np.ndarray, children: np.ndarray,
            node_word: np.ndarray) -> np.ndarray:
    """Word of each descriptor in a vocabulary tree of binary centres (``slamkit.place_recognition``): from
    the root, the nearest child (Hamming; the first of equals) until a leaf. (N,) of ``node_word``'s dtype."""
    out = np.empty(len(descriptor_words), node_word.dtype)
    if len(out):
        _descend_kernel(descriptor_words, center_words, children, node_word, out)
    return out
