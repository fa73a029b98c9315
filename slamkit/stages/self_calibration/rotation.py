"""Self-calibration from rotation: the focal length and one radial coefficient of a camera that mostly turns.

A camera that turns about its centre (looking round a room, a hand-held pan) maps its frames onto each other
by the infinite homography ``H = K R K^-1`` (Hartley 1997, "Self-calibration of stationary cameras"): the
fundamental matrix of such a pair is undefined, so :mod:`~slamkit.stages.self_calibration.epipolar`'s estimate
leaves those pairs out (and calls a window of them weak), but the pair itself fixes the focal length: only at
the right ``f`` do the corners of both frames, turned into rays, differ by one rotation. Radial distortion
breaks that model as much as a wrong focal length does (the rendered pan with k1 = 0.25 fitted as a pinhole:
392-396 px for 500, seeds 0-2), so both are searched together: for each radial coefficient of
:func:`~slamkit.stages.self_calibration.radial_candidates` (OpenCV's ``k1`` at a focal length of half the
image's larger side) and each focal length of a grid, the corners are undistorted, the best rotation between
the two frames' rays is found in closed form (Kabsch), and the cost is the mean squared reprojection error in
the image's own pixels (capped: robust to the few bad tracks a loose homography left). The least total cost
over the frame pairs is the start of a least-squares refinement of both (soft L1 loss; each pair's rotation
in closed form), which is the estimate. One radial coefficient, as the run's camera has: a first version fitted
a second one (``k2``) too, and on freiburg1's lens (k1 0.262, k2 -0.953, k3 1.163; seed 0) gave k1 0.118 with
k2 -0.157; the run, which tracks with ``k1`` alone, then built a map of a camera that only turned and ended 24 %
short. With one coefficient: 503.0 px, k1 0.033.

Frame pairs are far apart (``rotation_min_flow`` of the image, several degrees of turn: a small rotation
hardly depends on ``f``); those that a rotation does not explain within ``rotation_max_residual`` pixels at
the estimate (a walk, a plane seen while moving) are left out and the fit repeated. The uncertainty is the
spread of the estimate over pairs resampled in blocks of frames (bootstrap, as the epipolar estimate) combined
with :data:`ROTATION_MODEL_ERROR` (the bias of the small baseline a hand-held camera always has).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.optimize import least_squares

from .corner_tracks import _pair_matches, track_corners
from .epipolar import (BLOCK_FRAMES, FocalEstimate, SelfCalibrationConfig, _magnification, focal_grid,
                       radial_candidates, undistort_half)

ROTATION_MODEL_ERROR = 0.02
"""Relative error of the rotation estimate that no resampling shows: a hand-held camera's centre moves by
centimetres, which a rotation model absorbs partly into the focal length (and a lens with more than one radial
coefficient into ``k1``). On the rendered hand-held pans (``synthetic:handheld-pan``, 60 frames, 5 seeds each of
no distortion, k1 = 0.25 and freiburg1's lens; ``benchmarks/bench_self_calibration.py --cases 'syn-pan*'
--first-frames --seeds 5``) the estimate was off by -0.6 to +2.4 % (long in 11 of 15) with a bootstrap spread of
0.1-1.0 %: 0.015 would have covered all 15 (± 3.0-3.6 %), 0.02 does with a margin (± 4.0-4.4 %), kept because
those are one rendered motion and the error is a bias, not noise (benchmarks/HISTORY.md, "self-calibration of a turning camera")."""


MAX_PAIRS = 24
"""At most this many frame pairs (spread evenly over the window) enter the fit: each costs a least-squares
problem per bootstrap resampling."""

CAP_PX2 = 9.0
"""Squared reprojection errors are capped at this (3 px): the few bad tracks count, but no more than that."""

BOOTSTRAP = 20
"""Resamplings of the frame pairs (in blocks) for the spread of the refined estimate."""


def rotation_pairs(tracks: list[dict[int, np.ndarray]], size: int, config: SelfCalibrationConfig
                   ) -> list[tuple[int, int]]:
    """Frame pairs (a, b): for each first frame a the nearest b whose corners moved ``rotation_min_flow`` of
    the image's larger side (median) while at least 50 corners are common; at most ``max_pairs`` and
    :data:`MAX_PAIRS`, spread evenly."""
    pairs = []
    for a in range(len(tracks)):
        for b in range(a + 1, len(tracks)):
            x1, x2 = _pair_matches(tracks[a], tracks[b])
            if len(x1) < 50:
                break
            if float(np.median(np.linalg.norm(x2 - x1, axis=1))) >= config.rotation_min_flow * size:
                pairs.append((a, b))
                break
    if len(pairs) > min(config.max_pairs, MAX_PAIRS):
        keep = np.unique(np.linspace(0, len(pairs) - 1, min(config.max_pairs, MAX_PAIRS)).round().astype(int))
        pairs = [pairs[i] for i in keep]
    return pairs


def rotated(u1: np.ndarray, u2: np.ndarray, focals: np.ndarray, cx: float, cy: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """``u1`` ((N, 2) pinhole pixels) carried onto ``u2`` by the best rotation (Kabsch on the unit rays) at each
    focal length of ``focals`` (G,): ((G, N, 2) projected pixels, (G, N) whether in front of the camera)."""
    f = np.asarray(focals, np.float64).reshape(-1)[:, None, None]

    def rays(u):
        r = np.concatenate([np.broadcast_to((u - (cx, cy))[None], (len(f), len(u), 2)) / f,
                            np.ones((len(f), len(u), 1))], axis=2)
        return r / np.linalg.norm(r, axis=2, keepdims=True)
    r1, r2 = rays(u1), rays(u2)
    U, _, Vt = np.linalg.svd(np.transpose(r2, (0, 2, 1)) @ r1)
    U[:, :, 2] *= np.sign(np.linalg.det(U @ Vt))[:, None]
    p = r1 @ np.transpose(U @ Vt, (0, 2, 1))
    ahead = p[:, :, 2] > 1e-9
    return f * p[:, :, :2] / np.where(ahead, p[:, :, 2], 1e-9)[:, :, None] + (cx, cy), ahead


def rotation_errors(u1: np.ndarray, u2: np.ndarray, grid: np.ndarray, cx: float, cy: float) -> np.ndarray:
    """(len(grid), N) squared reprojection errors (pixels) of ``u1`` -> ``u2`` ((N, 2) pinhole pixels) by the
    best rotation at each focal length of ``grid`` (:func:`rotated`); a corner carried behind the camera counts
    :data:`CAP_PX2`."""
    proj, ahead = rotated(u1, u2, grid, cx, cy)
    return np.where(ahead, ((proj - u2[None]) ** 2).sum(axis=2), CAP_PX2)


def _pair_cost(x1: np.ndarray, x2: np.ndarray, grid: np.ndarray, cx: float, cy: float, half: float,
               candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pair's (len(candidates), len(grid)) mean squared reprojection error (capped at :data:`CAP_PX2`,
    in the distorted image's pixels) and its median (uncapped) for each radial coefficient and focal length."""
    cost = np.zeros((len(candidates), len(grid)))
    med = np.zeros_like(cost)
    for i, k in enumerate(candidates):
        u1, u2 = undistort_half(x1, cx, cy, half, k), undistort_half(x2, cx, cy, half, k)
        err = rotation_errors(u1, u2, grid, cx, cy) / _magnification(u2, cx, cy, half, k)[None]
        cost[i], med[i] = np.minimum(err, CAP_PX2).mean(axis=1), np.median(err, axis=1)
    return cost, med


def _lens_residuals(x: np.ndarray, pixels: list[tuple[np.ndarray, np.ndarray]], cx: float, cy: float,
                    half: float) -> np.ndarray:
    """Reprojection errors (pixels of the distorted image, to first order) of every pair's best rotation for
    ``x`` = (log f, radial coefficient at focal ``half``)."""
    f, k = math.exp(x[0]), float(x[1])
    out = []
    for x1, x2 in pixels:
        u1, u2 = undistort_half(x1, cx, cy, half, k), undistort_half(x2, cx, cy, half, k)
        proj = rotated(u1, u2, np.array([f]), cx, cy)[0][0]
        out.append(((proj - u2) / np.sqrt(_magnification(u2, cx, cy, half, k))[:, None]).ravel())
    return np.concatenate(out)


def refine_lens(pixels: list[tuple[np.ndarray, np.ndarray]], x0: np.ndarray, cx: float, cy: float, half: float,
                max_nfev: int = 50) -> np.ndarray:
    """(log f, radial coefficient at focal ``half``) minimising the pairs' reprojection errors (a trust region,
    soft L1 loss at 1 px) from ``x0``; each pair's rotation is the best one in closed form (Kabsch)."""
    res = least_squares(_lens_residuals, np.asarray(x0, float), args=(pixels, cx, cy, half), loss="soft_l1",
                        f_scale=1.0, x_scale=np.array([0.01, 0.01]), max_nfev=max_nfev)
    return res.x


def _argmin2(cost: np.ndarray, grid: np.ndarray, candidates: np.ndarray) -> tuple[float, float]:
    """(focal, radial) at the least of ``cost`` (len(candidates), len(grid)), refined by parabolas in log f and
    in the coefficient."""
    i, j = np.unravel_index(int(np.argmin(cost)), cost.shape)
    def vertex(y, at, step):
        if 0 < at < len(y) - 1:
            den = y[at - 1] - 2 * y[at] + y[at + 1]
            if den > 0:
                return float(np.clip(0.5 * (y[at - 1] - y[at + 1]) / den, -0.5, 0.5)) * step
        return 0.0
    f = float(grid[j] * math.exp(vertex(cost[i], j, math.log(grid[1] / grid[0])) if len(grid) > 1 else 0.0))
    step = candidates[1] - candidates[0] if len(candidates) > 1 else 0.0
    k = float(candidates[i] + (vertex(cost[:, j], i, step) if len(candidates) > 1 else 0.0))
    return f, k


def estimate_rotation(grays: list[np.ndarray], config: SelfCalibrationConfig = SelfCalibrationConfig(),
                      seed: int = 0, tracks: list[dict[int, np.ndarray]] | None = None) -> FocalEstimate:
    """The focal length and radial coefficient of the camera of ``grays`` (consecutive grey frames, principal
    point at the centre) from the frame pairs a rotation explains; see the module docstring. Its ``k1`` is
    OpenCV's at the estimated focal length; ``reason`` says why it is weak."""
    h, w = grays[0].shape[:2]
    cx, cy, half = (w - 1) / 2.0, (h - 1) / 2.0, max(w, h) / 2.0
    tracks = track_corners(grays) if tracks is None else tracks
    candidates = radial_candidates(w, h, config)[::2]  # steps of 0.05: the least squares refine it
    matches = []
    for a, b in rotation_pairs(tracks, max(w, h), config):
        x1, x2 = _pair_matches(tracks[a], tracks[b])
        try:  # a loose homography: distortion bends the corners off it by pixels
            H, inl = cv2.findHomography(x1, x2, cv2.USAC_MAGSAC, 8.0, confidence=0.999, maxIters=10000)
        except cv2.error:
            continue
        if H is not None and inl is not None and int(inl.sum()) >= 30:
            matches.append((a, x1[inl.ravel() == 1], x2[inl.ravel() == 1]))

    def weak(reason: str, n: int = 0) -> FocalEstimate:
        return FocalEstimate(float("nan"), math.inf, n, len(grays), True, reason)
    if len(matches) < 3:
        return weak(f"only {len(matches)} frame pairs turned far enough apart", len(matches))
    coarse = focal_grid(w, h, config, 80)
    both = [_pair_cost(x1, x2, coarse, cx, cy, half, candidates) for _, x1, x2 in matches]
    costs, medians = np.array([c for c, _ in both]), np.array([m for _, m in both])
    for _ in range(2):  # pairs a rotation does not explain at the estimate (a walk, a plane) are left out
        i, j = np.unravel_index(int(np.argmin(costs.sum(0))), costs.shape[1:])
        keep = medians[:, i, j] <= config.rotation_max_residual ** 2
        if keep.sum() < 3:
            return weak(f"a rotation explains only {int(keep.sum())} of {len(matches)} frame pairs turned far "
                        "enough apart (the camera moves as much as it turns)", int(keep.sum()))
        if keep.all():
            break
        costs, medians = costs[keep], medians[keep]
        matches = [m for m, k in zip(matches, keep) if k]
    focal, radial = _argmin2(costs.sum(0), coarse, candidates)
    pixels = [(x1, x2) for _, x1, x2 in matches]
    x = refine_lens(pixels, np.array([math.log(focal), radial]), cx, cy, half)
    focal, radial = math.exp(x[0]), float(x[1])
    blocks = np.array([a for a, _, _ in matches]) // BLOCK_FRAMES
    members = [np.flatnonzero(blocks == b) for b in np.unique(blocks)]
    spread = math.inf
    if len(members) >= 2:
        rng = np.random.default_rng(seed)
        boot = [refine_lens([pixels[i] for k in rng.integers(0, len(members), len(members)) for i in members[k]],
                            x, cx, cy, half, max_nfev=8)[0] for _ in range(BOOTSTRAP)]
        spread = float(np.std(boot))
    uncertainty = math.hypot(spread, ROTATION_MODEL_ERROR)
    n = len(matches)
    reason = ""
    if len(members) < 2:
        reason = f"its {n} frame pairs all start within {BLOCK_FRAMES} frames"
    elif not coarse[1] < focal < coarse[-2]:
        reason = "the best focal length is at the end of the range searched"
    elif uncertainty > config.weak_uncertainty:
        reason = f"the turned frame pairs disagree by {100 * spread:.0f} % (one standard deviation)"
    return FocalEstimate(focal, uncertainty, n, len(grays), bool(reason), reason, k1=radial * (focal / half) ** 2,
                         model="rotation")


__all__ = ["estimate_rotation", "refine_lens", "rotated", "rotation_errors", "rotation_pairs", "ROTATION_MODEL_ERROR"]
