"""Self-calibration's estimate from the first frames' epipolar geometry (the focal length and one radial
coefficient; the package's docstring, phase 1) and what the package's other estimates share: the config, the
estimate, the focal grid and the lens's radial model."""


from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from ...errors import ConfigError, check_fields
from .corner_tracks import _pair_matches, track_corners


@dataclass(frozen=True)
class SelfCalibrationConfig:
    window_frames: int = 60
    """Frames (after frame skip) of the sequence start used for the first estimate."""
    max_pairs: int = 60
    """At most this many frame pairs enter the estimate (spread evenly over the window)."""
    min_flow: float = 0.04
    """A pair's frames are at least this far apart: median corner motion as a fraction of the image's
    larger side."""
    max_homography_ratio: float = 0.9
    """Pairs whose homography inliers are at least this fraction of their F inliers are left out (rotation
    or a plane: F says nothing about the focal length)."""
    min_fov_deg: float = 15.0
    """The focal lengths searched give fields of view (larger image side) from this ..."""
    max_fov_deg: float = 150.0
    """... to this."""
    fallback_fov_deg: float = 65.0
    """Field of view (degrees, across the larger image side) the run starts from when the first frames give no
    usable estimate; bundle adjustment then refines it. 65 degrees is the middle of today's video cameras
    (phones 60-75, KITTI's 82, action and dash cameras wider); 0: the sources' documented guess, focal
    1.2 x the larger image side (45 degrees, COLMAP's prior for still photographs). On the driving clip (true
    82 degrees, 721 px) the weak start from 65 degrees poses 85.1 % of the frames in each of 3 seeds, from 45
    degrees 71.3 ± 7.3 % (``--camera 721``: 75.5 ± 6.3 %; benchmarks/HISTORY.md, "Self-calibration")."""
    weak_uncertainty: float = 0.05
    """An estimate whose relative uncertainty (one standard deviation: the bootstrap over blocks of frame pairs
    with the model error, ``FocalEstimate.uncertainty``) is above this is weak; a weak estimate shows no ``±``."""
    min_refine_keyframes: int = 8
    """Bundle adjustment refines the focal length only in maps of at least this many keyframes (a younger map,
    built from little motion, pulls it anywhere)."""
    refine_keyframes: int = 8
    """When the first frames gave no usable estimate (weak): every keyframe's BA is global and refines the
    focal length, from ``min_refine_keyframes`` until the map has this many keyframes (8: once). Refined in
    every BA, a forward-moving map's focal length wanders and tracking is lost: at 20 the driving clip swung
    631-1196 px (47 % posed) and a rendered street was 27-50 % posed (8: 100 %, 80-100 %; HISTORY, "Session 21")."""
    refine_final: bool = True
    """The final global BA (``ba.final_global``) refines the focal length of the main map."""
    refine_radial: bool = True
    """The final global BA (with ``refine_final``) also estimates one radial distortion coefficient ``k1``: the
    map's camera is COLMAP's SIMPLE_RADIAL for that BA, then PINHOLE again with every keyframe's keypoints
    undistorted; the run's camera (``camera.txt``) carries ``k1``. A pinhole BA absorbs what it does not
    model into the focal length: on KITTI 07 (rectified images) it ends 3.7 % short of the true 707 px, with
    ``k1`` 0.4 ± 0.5 % over (benchmarks/HISTORY.md, "Self-calibration")."""
    max_radial: float = 0.5
    """A final BA whose ``k1`` is larger than this (in magnitude) is not believed: the focal length is refined
    by a pinhole BA instead (a map that does not constrain the camera drifts to absurd pairs such as
    f = 3x the truth with k1 = 1.3; ordinary lenses are within +-0.3, and this model cannot describe fisheyes)."""
    max_final_change: float = 0.2
    """The final BA moves the focal length by more than this fraction of the value the main map was built
    with: the estimate is reported weak (the map did not settle it). Measured final changes: 1-3 % on KITTI,
    the driving clip and rendered rooms, 9-14 % where distortion biased the first frames (7-Scenes, a rendered
    k1 = -0.1), +91 % on a city-block map of straight driving that ended at 3.6x the true focal length."""
    refine_principal_point: bool = False
    """Bundle adjustment refines the principal point too (else it stays at the image centre)."""
    first_radial: float = 0.3
    """The first frames' estimate also searches one radial coefficient (OpenCV's ``k1`` at a focal length of
    half the image's larger side, from ``-first_radial`` to ``first_radial``: 0.3 is k1 = 0.75 at 500 px for
    640x480), the one whose undistorted corners fit the frame pairs' fundamental matrices best (smallest
    Sampson error); the focal length is then estimated from the undistorted corners, and the run tracks
    with them (:attr:`FocalEstimate.k1`). 0: pinhole (the estimate of a lens with rendered k1 = 0.25 was then
    9-23 % short, and the map was built with it). Barrel distortion that folds back inside the image is not
    searched."""
    rotation_min_flow: float = 0.15
    """When the frame pairs' epipolar geometry gives a weak estimate (a camera that mostly turns), the focal
    length and radial coefficient are fitted to the pairs a rotation explains
    (:mod:`~slamkit.stages.self_calibration.rotation`): pairs whose corners moved this fraction of the image's
    larger side (median); 0: never."""
    rotation_max_residual: float = 1.0
    """... and that a rotation explains within this median reprojection error (pixels) at the estimate."""

    def validate(self) -> None:
        check_fields(self, "self_calibration", {
            "window_frames": ("[2, 1000]", "the window's frames are kept in memory"), "max_pairs": "[1, 10000]",
            "min_flow": "(0, 1)", "max_homography_ratio": "(0, 1]", "min_fov_deg": "[1, 170]",
            "max_fov_deg": "[1, 170]", "fallback_fov_deg": ("[0, 170]", "0 or 1 to 170 degrees"),
            "weak_uncertainty": "(0, 10]", "min_refine_keyframes": "[3, inf)", "refine_keyframes": "[0, 10000]",
            "max_radial": "(0, 10]", "max_final_change": "(0, 100]", "first_radial": "[0, 1]",
            "rotation_min_flow": "[0, 1)", "rotation_max_residual": "(0, 100]"})
        if not self.min_fov_deg < self.max_fov_deg:
            raise ConfigError("self_calibration needs 1 <= min_fov_deg < max_fov_deg <= 170 "
                              f"(got {self.min_fov_deg}, {self.max_fov_deg})")
        if self.fallback_fov_deg and not 1 <= self.fallback_fov_deg <= 170:
            raise ConfigError(f"self_calibration.fallback_fov_deg must be 0 or in [1, 170] (got {self.fallback_fov_deg})")


@dataclass(frozen=True)
class FocalEstimate:
    """The focal length (pixels, both axes) estimated from frame pairs, with its uncertainty."""

    focal: float
    uncertainty: float
    """Relative standard deviation: the bootstrap over blocks of pairs combined with :data:`MODEL_ERROR`; inf
    with fewer than 3 pairs. The interval shown is :attr:`interval`."""
    num_pairs: int
    """Pairs that entered the estimate."""
    num_frames: int
    weak: bool
    reason: str = ""
    """Why the estimate is weak ("" when it is not)."""
    grid: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    cost: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    """The summed cost over the focal lengths of ``grid`` (for plots)."""
    k1: float = 0.0
    """The radial coefficient found with it (OpenCV's ``k1`` at :attr:`focal`; ``first_radial``), 0 when none."""
    model: str = "epipolar"
    """What fixed it: "epipolar" (fundamental matrices) or "rotation" (:mod:`.rotation`)."""

    @property
    def interval(self) -> float:
        """Relative half-width of the interval shown (``± x %``, :data:`COVERAGE` x :attr:`uncertainty`); inf
        for a weak estimate, which shows none."""
        return math.inf if self.weak else COVERAGE * self.uncertainty

    def describe(self) -> str:
        radial = f", k1={self.k1:.3f}" if self.k1 else ""
        if self.weak:  # no interval: the number is a starting point, not a measurement
            return f"f={self.focal:.1f} px{radial} from {self.num_pairs} frame pairs (weak: {self.reason})"
        lens = "a lens with one radial coefficient" if self.k1 else "an undistorted lens"
        turned = " turned" if self.model == "rotation" else ""
        return (f"f={self.focal:.1f} px ± {100 * self.interval:.1f} %{radial} (for {lens}) from {self.num_pairs}"
                f"{turned} frame pairs")


def choose_pairs(tracks: list[dict[int, np.ndarray]], size: int, config: SelfCalibrationConfig
                 ) -> list[tuple[int, int]]:
    """Frame pairs (a, b), a < b: for each first frame a the nearest b whose corners moved ``min_flow`` of
    the image (median) while at least 30 corners are common, and the one twice as far; at most
    ``max_pairs``, spread evenly."""
    pairs = []
    for a in range(len(tracks)):
        wanted = [config.min_flow * size, 2 * config.min_flow * size]
        for b in range(a + 1, len(tracks)):
            x1, x2 = _pair_matches(tracks[a], tracks[b])
            if len(x1) < 30:
                break
            flow = float(np.median(np.linalg.norm(x2 - x1, axis=1)))
            if wanted and flow >= wanted[0]:
                pairs.append((a, b))
                wanted.pop(0)
                if not wanted:
                    break
    if len(pairs) > config.max_pairs:
        keep = np.unique(np.linspace(0, len(pairs) - 1, config.max_pairs).round().astype(int))
        pairs = [pairs[i] for i in keep]
    return pairs


def focal_grid(width: int, height: int, config: SelfCalibrationConfig, num: int = 600) -> np.ndarray:
    """Focal lengths searched, log-spaced between the fields of view of ``config``."""
    half = max(width, height) / 2.0
    lo = half / math.tan(math.radians(config.max_fov_deg / 2))
    hi = half / math.tan(math.radians(config.min_fov_deg / 2))
    return np.geomspace(lo, hi, num)


def essential_cost(F: np.ndarray, grid: np.ndarray, cx: float, cy: float) -> np.ndarray:
    """(len(grid),) cost of each focal length for one fundamental matrix: ``(s1 - s2) / (s1 + s2)`` of the
    singular values of ``K^T F K`` (0 for an essential matrix)."""
    K = np.zeros((len(grid), 3, 3))
    K[:, 0, 0] = K[:, 1, 1] = grid
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = cx, cy, 1.0
    E = np.transpose(K, (0, 2, 1)) @ F @ K
    s = np.linalg.svd(E, compute_uv=False)
    return (s[:, 0] - s[:, 1]) / np.maximum(s[:, 0] + s[:, 1], 1e-300)


def _argmin_log(grid: np.ndarray, cost: np.ndarray) -> float:
    """The minimum of ``cost`` over ``grid``, refined by a parabola through its neighbours in log f."""
    k = int(np.argmin(cost))
    if 0 < k < len(grid) - 1:
        y0, y1, y2 = cost[k - 1], cost[k], cost[k + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            step = math.log(grid[k + 1] / grid[k])
            return float(grid[k] * math.exp(0.5 * (y0 - y2) / den * step))
    return float(grid[k])


def undistort_half(xy: np.ndarray, cx: float, cy: float, half: float, radial: float) -> np.ndarray:
    """(N, 2) pixels of a lens with OpenCV's ``k1 = radial`` at focal length ``half`` -> (N, 2) pixels of its
    pinhole part (Newton on the radius; ``radial`` must not fold back inside the image)."""
    if not radial or len(xy) == 0:
        return np.asarray(xy, np.float64)
    d = (np.asarray(xy, np.float64) - (cx, cy)) / half
    rd = np.hypot(d[:, 0], d[:, 1])
    r = rd.copy()
    for _ in range(20):
        r -= (radial * r ** 3 + r - rd) / (3 * radial * r * r + 1)
    scale = np.divide(r, rd, out=np.ones_like(rd), where=rd > 0)
    return d * scale[:, None] * half + (cx, cy)


def radial_candidates(width: int, height: int, config: SelfCalibrationConfig) -> np.ndarray:
    """The radial coefficients searched (``first_radial``, steps of 0.025; barrel only until it folds back)."""
    if not config.first_radial:
        return np.zeros(1)
    r2 = (width ** 2 + height ** 2) / max(width, height) ** 2  # the corner, normalized
    lo = max(-config.first_radial, -0.8 * 4 / 27 / r2)  # r (1 + k r^2) folds at r^2 = -1 / (3 k)
    step = 0.025
    return np.concatenate([-np.arange(0, -lo, step)[:0:-1], np.arange(0, config.first_radial + 1e-9, step)])


def _magnification(xy: np.ndarray, cx: float, cy: float, half: float, radial: float) -> np.ndarray:
    """(N,) squared local scale of :func:`undistort_half` at its output ``xy`` (radial x tangential scale)."""
    r2 = (((np.asarray(xy, np.float64) - (cx, cy)) / half) ** 2).sum(axis=1)
    return 1.0 / ((1 + 3 * radial * r2) * (1 + radial * r2))


def _sampson(x1: np.ndarray, x2: np.ndarray, scale: np.ndarray | None = None) -> float:
    """Mean squared Sampson distance (px^2, capped at 9) of the least-squares F, in the images' pixels (/ scale)."""
    F, _ = cv2.findFundamentalMat(x1, x2, cv2.FM_8POINT)
    if F is None or F.shape[0] < 3:
        return math.inf
    F = F[:3]
    h1, h2 = np.column_stack([x1, np.ones(len(x1))]), np.column_stack([x2, np.ones(len(x2))])
    a, b = h1 @ F.T, h2 @ F
    err = (h2 * a).sum(1) ** 2 / np.maximum(a[:, 0] ** 2 + a[:, 1] ** 2 + b[:, 0] ** 2 + b[:, 1] ** 2, 1e-300)
    return float(np.minimum(err if scale is None else err / scale, 9.0).mean())


MIN_RADIAL_GAIN = 0.05
"""A radial coefficient is used only when the pinhole model's Sampson error exceeds its by this fraction. On the
rendered room (60 frames) the pinhole's was 0-0.4 % above the best coefficient for undistorted lenses (320,
500 and 1280 px; a telephoto's focal length moved 5 % with a coefficient of no significance) and 15-18 % for
k1 = -0.1 and 0.25."""


def choose_radial(matches: list[tuple[np.ndarray, np.ndarray]], cx: float, cy: float, half: float,
                  candidates: np.ndarray) -> float:
    """The radial coefficient of ``candidates`` (at focal ``half``) whose undistorted corners fit the pairs'
    fundamental matrices best: the smallest Sampson error summed over ``matches`` (each pair's (N, 2)
    corners, MAGSAC inliers), refined by a parabola through its neighbours."""
    if len(candidates) < 3 or not matches:
        return 0.0
    cost = np.zeros(len(candidates))
    for i, k in enumerate(candidates):
        for x1, x2 in matches:
            u1, u2 = undistort_half(x1, cx, cy, half, k), undistort_half(x2, cx, cy, half, k)
            scale = 0.5 * (_magnification(u1, cx, cy, half, k) + _magnification(u2, cx, cy, half, k))
            cost[i] += _sampson(u1, u2, scale)
    k = int(np.argmin(cost))
    if not cost[int(np.argmin(np.abs(candidates)))] > (1 + MIN_RADIAL_GAIN) * cost[k]:
        return 0.0  # no lens distortion shows
    if 0 < k < len(cost) - 1 and np.isfinite(cost[k - 1:k + 2]).all():
        y0, y1, y2 = cost[k - 1], cost[k], cost[k + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            return float(candidates[k] + 0.5 * (y0 - y2) / den * (candidates[k + 1] - candidates[k]))
    return float(candidates[k])


def pair_costs(grays: list[np.ndarray], config: SelfCalibrationConfig = SelfCalibrationConfig(),
               tracks: list[dict[int, np.ndarray]] | None = None
               ) -> tuple[list[tuple[int, int]], np.ndarray, np.ndarray, np.ndarray, float]:
    """(the informative frame pairs (a, b), their (n, len(grid)) costs, the focal lengths of the grid, each
    pair's :func:`axis_gap`, the radial coefficient at focal half the larger side) of consecutive grey frames;
    see the module docstring. ``tracks``: their :func:`track_corners`, when already made."""
    h, w = grays[0].shape[:2]
    cx, cy, half = (w - 1) / 2.0, (h - 1) / 2.0, max(w, h) / 2.0
    grid = focal_grid(w, h, config)
    tracks = track_corners(grays) if tracks is None else tracks
    chosen = [(a, b, *_pair_matches(tracks[a], tracks[b])) for a, b in choose_pairs(tracks, max(w, h), config)]
    candidates = radial_candidates(w, h, config)
    radial = 0.0
    if len(candidates) > 1:  # inliers of a loose F (distortion moves corners by pixels), then the best k1
        loose = []
        for a, b, x1, x2 in chosen:
            try:
                F, inl = cv2.findFundamentalMat(x1, x2, cv2.USAC_MAGSAC, 5.0, 0.999, 10000)
            except cv2.error:
                continue
            if F is not None and inl is not None and int(inl.sum()) >= 20:
                loose.append((x1[inl.ravel() == 1], x2[inl.ravel() == 1]))
        radial = choose_radial(loose, cx, cy, half, candidates)
    pairs, costs, gaps = [], [], []
    for a, b, x1, x2 in chosen:
        x1, x2 = undistort_half(x1, cx, cy, half, radial), undistort_half(x2, cx, cy, half, radial)
        try:
            F, inl = cv2.findFundamentalMat(x1, x2, cv2.USAC_MAGSAC, 1.0, 0.999, 10000)
        except cv2.error:  # OpenCV 5's MAGSAC asserts on some degenerate pairs instead of returning None
            continue
        if F is None or F.shape != (3, 3) or inl is None or int(inl.sum()) < 20:
            continue
        try:
            H, hin = cv2.findHomography(x1, x2, cv2.USAC_MAGSAC, 1.0, confidence=0.999, maxIters=10000)
        except cv2.error:
            H, hin = None, None
        if H is not None and hin is not None and hin.sum() >= config.max_homography_ratio * inl.sum():
            continue
        inliers = inl.ravel() == 1  # least squares on the inliers (normalized 8-point): less biased than RANSAC's F
        F8, _ = cv2.findFundamentalMat(x1[inliers], x2[inliers], cv2.FM_8POINT)
        F = F8[:3] if F8 is not None and F8.shape[0] >= 3 else F
        costs.append(essential_cost(F, grid, cx, cy))
        gaps.append(axis_gap(F, cx, cy) / max(w, h))
        pairs.append((a, b))
    return pairs, np.array(costs).reshape(len(costs), len(grid)), grid, np.array(gaps), radial


def axis_gap(F: np.ndarray, cx: float, cy: float) -> float:
    """Distance (pixels) of the principal point from its epipolar line in the other image: 0 when the two
    optical axes meet (a camera circling what it looks at), where F does not fix the focal length (Bougnoux's
    formula divides by it; Sturm's critical motions)."""
    p = np.array([cx, cy, 1.0])
    line = F @ p
    return float(abs(p @ line) / max(math.hypot(line[0], line[1]), 1e-300))


MIN_AXIS_GAP = 0.002
"""Frame pairs whose :func:`axis_gap` is below this fraction of the image's larger side (1.3 px at 640) are left
out: their optical axes (nearly) meet, and F then says nothing about the focal length. Circling the cube of
the rendered room while looking at it, every pair is below 0.001, and the estimate without this rule was 40 %
short with a bootstrap spread of 2 %; moving straight ahead, every pair is near 0 (benchmarks/HISTORY.md,
"Self-calibration", "Session of issue 40: an honest interval")."""

BLOCK_FRAMES = 10
"""The bootstrap resamples the pairs in blocks by their first frame, this many frames a block: pairs that share
frames and corner tracks err together, and resampling them one by one gave spreads 2-3x too small."""

MODEL_ERROR = 0.01
"""Relative error of the estimate that no resampling of the pairs shows (the bias of F from tracked corners
and of the pinhole model at the image centre): combined with the bootstrap spread in
:attr:`FocalEstimate.uncertainty`, calibrated on rendered cameras (the HISTORY section of
:data:`MIN_AXIS_GAP`)."""

COVERAGE = 2.0
"""The interval shown is ``±`` this many :attr:`FocalEstimate.uncertainty`. On the rendered hand-held room at
320, 640 and 1280 px (10 seeds each) it covered the true focal length in 22 of the 22 estimates that were not
weak (8 weak); an orbit round the cube and a drive round the city block are weak in every seed. It was
calibrated without the radial search (``first_radial``): rendered barrel distortion (k1 = -0.1) then biased
the estimate by +9 to +20 %, which it covered in 1 of 9 seeds; with the search, one seed each of k1 = 0.25,
-0.1 and 0 on the hand-held room (60 frames) was within 0.5 %, a lens like TUM freiburg1's (k1, k2, k3) too."""


def focal_from_costs(pairs: list[tuple[int, int]], costs: np.ndarray, grid: np.ndarray, gaps: np.ndarray,
                     num_frames: int, config: SelfCalibrationConfig = SelfCalibrationConfig(),
                     seed: int = 0) -> FocalEstimate:
    """The estimate and its uncertainty from the pairs' costs and axis gaps (:func:`pair_costs`): pairs whose
    optical axes meet left out (:data:`MIN_AXIS_GAP`), the minimum of the summed cost, a bootstrap over
    blocks of pairs (:data:`BLOCK_FRAMES`) combined with :data:`MODEL_ERROR`."""
    keep = np.asarray(gaps, float) >= MIN_AXIS_GAP
    circling = int((~keep).sum())
    pairs, costs = np.asarray(pairs, int).reshape(-1, 2)[keep], np.asarray(costs, float)[keep]
    n = len(costs)
    circled = (f" ({circling} left out: their optical axes meet, as when moving along them or circling what the "
               "camera looks at)" if circling else "")
    if n == 0:
        why = (f"the optical axes meet in all {circling} frame pairs (moving along them, or circling what the "
               "camera looks at)" if circling else "no frame pair with enough motion that is not a rotation or a plane")
        return FocalEstimate(float("nan"), math.inf, 0, num_frames, True, why, grid, np.zeros(len(grid)))
    total = costs.sum(axis=0)
    focal = _argmin_log(grid, total)
    blocks = pairs[:, 0] // BLOCK_FRAMES
    members = [np.flatnonzero(blocks == b) for b in np.unique(blocks)]
    spread = math.inf
    if n >= 3 and len(members) >= 2:
        rng = np.random.default_rng(seed)
        boot = [_argmin_log(grid, costs[np.concatenate([members[k] for k in rng.integers(0, len(members),
                                                                                        len(members))])].sum(0))
                for _ in range(200)]
        spread = float(np.std(np.log(boot)))
    uncertainty = math.hypot(spread, MODEL_ERROR)
    reason = ""
    if n < 3:
        reason = f"only {n} informative frame pair{'s' if n != 1 else ''}"
    elif len(members) < 2:
        reason = f"its {n} frame pairs all start within {BLOCK_FRAMES} frames"
    elif not grid[1] < focal < grid[-2]:
        reason = (f"the best focal length is at the end of the range searched ({config.min_fov_deg:g}-"
                  f"{config.max_fov_deg:g} degrees of view)")
    elif uncertainty > config.weak_uncertainty:
        reason = (f"the frame pairs disagree by {100 * spread:.0f} % (one standard deviation): motion mostly "
                  "straight ahead or mostly rotation")
    reason += circled if reason else ""
    return FocalEstimate(focal, uncertainty, n, num_frames, bool(reason), reason, grid, total)
