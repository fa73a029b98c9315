"""The computations behind the course notebooks 04 (features and matching) and 05 (initialization and BA).

Each function does one thing a lesson shows, on frames of any source with ground truth (the embedded
sequence by default), with the same extractors, matchers, flow score and bundle adjustment the pipeline
uses; the notebooks only call them and draw. Pixels are undistorted pixels; poses are (4, 4) float64,
camera-to-world unless named ``cam_from_world``.

- :func:`compare_features`: keypoints, matches and their epipolar distances to the ground-truth geometry,
  per feature pipeline (:func:`fundamental_from_poses`, :func:`epipolar_distances`).
- :func:`flow_scores`: the flow score of the frames after a keyframe, and where the keyframe rule fires.
- :func:`two_view`: essential matrix (RANSAC), relative pose, triangulation, triangulation angles and
  reprojection errors of two frames, against ground truth.
- :func:`reprojection_errors`, :func:`perturb_and_adjust`: what bundle adjustment changes.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import pycolmap

from ..config import SlamConfig, feature_pipeline_status
from ..features import create_extractor, create_matcher, match_descriptors
from ..features.learned import INSTALL_HINT, torch_available
from ..stages.ba import bundle_adjustment_options
from ..stages.flow import flow_score
from ..types import Frame


# ---------------------------------------------------------------------------------------------- epipolar geometry


def skew(t: np.ndarray) -> np.ndarray:
    """(3,) -> (3, 3) the cross-product matrix [t]x (so that [t]x v = t x v)."""
    x, y, z = np.asarray(t, np.float64)
    return np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])


def relative_pose(world_from_cam1: np.ndarray, world_from_cam2: np.ndarray) -> np.ndarray:
    """(4, 4) cam2_from_cam1 of two camera-to-world poses."""
    return np.linalg.inv(world_from_cam2) @ world_from_cam1


def fundamental_from_poses(K: np.ndarray, world_from_cam1: np.ndarray, world_from_cam2: np.ndarray) -> np.ndarray:
    """(3, 3) F = K^-T [t]x R K^-1 from ground truth (R, t = cam2_from_cam1): x2^T F x1 = 0 for a true match."""
    T = relative_pose(world_from_cam1, world_from_cam2)
    E = skew(T[:3, 3]) @ T[:3, :3]
    Kinv = np.linalg.inv(K)
    return Kinv.T @ E @ Kinv


def epipolar_distances(x1: np.ndarray, x2: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(N,) pixels: distance of each x2 (N, 2) to the epipolar line F x1 of its match x1 (N, 2) in image 2,
    d = |x2^T F x1| / sqrt((F x1)_1^2 + (F x1)_2^2)."""
    h1 = np.c_[np.asarray(x1, np.float64), np.ones(len(x1))]
    h2 = np.c_[np.asarray(x2, np.float64), np.ones(len(x2))]
    lines = h1 @ F.T  # (N, 3) the epipolar lines in image 2
    return np.abs(np.einsum("ij,ij->i", h2, lines)) / np.maximum(np.hypot(lines[:, 0], lines[:, 1]), 1e-12)


# ---------------------------------------------------------------------------------------------- features


@dataclass
class FeatureComparison:
    """One feature pipeline on one image pair: what it found and how well it agrees with ground truth."""

    name: str
    keypoints1: np.ndarray
    """(N1, 2) undistorted pixels in image 1 (and ``keypoints2`` in image 2)."""
    keypoints2: np.ndarray
    pairs: np.ndarray
    """(M, 2) int64 matched keypoint indices."""
    epipolar_px: np.ndarray
    """(M,) pixels: each match's distance to its ground-truth epipolar line."""
    seconds: float
    """Extraction of both images and matching, wall-clock seconds, of a second run (the first, a warm-up that
    pays for one-time allocations and library initialisation, is not counted)."""
    tolerance_px: float = 2.0

    @property
    def inliers(self) -> np.ndarray:
        """(M,) bool: matches within ``tolerance_px`` of their epipolar line (consistent with the truth)."""
        return self.epipolar_px < self.tolerance_px

    def row(self) -> dict:
        """A table row: keypoints in image 1 / image 2, matches, those within the tolerance of their epipolar
        line (count and fraction), the median distance to it (pixels), the time."""
        m = len(self.pairs)
        return {"features": self.name, "keypoints 1 / 2": f"{len(self.keypoints1)} / {len(self.keypoints2)}",
                "matches": m, "epipolar inliers": int(self.inliers.sum()),
                "inlier ratio": float(self.inliers.mean()) if m else float("nan"),
                "median dist. (px)": float(np.median(self.epipolar_px)) if m else float("nan"),
                "time (ms)": int(round(1e3 * self.seconds))}


def _pipeline(name: str) -> tuple[object, object | None, SlamConfig]:
    config = SlamConfig().with_overrides(features=name)
    extractor = create_extractor(config.features, **config.extractor_options())
    matcher = None if config.matcher == "nn" else create_matcher(config.matcher, **config.matcher_options())
    return extractor, matcher, config


def detect_and_match(frame1: Frame, frame2: Frame, name: str = "orb"
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(keypoints1 (N1, 2), keypoints2 (N2, 2) undistorted pixels, pairs (M, 2), seconds) of a feature
    pipeline (``orb``, ``sift``, ``xfeat``, ...) with the matcher the pipeline uses at initialization."""
    extractor, matcher, config = _pipeline(name)
    t = time.perf_counter()
    f1, f2 = extractor.extract(frame1.gray), extractor.extract(frame2.gray)
    if matcher is not None:
        pairs = matcher.match(f1, f2)
    else:
        pairs = match_descriptors(f1.descriptors, f2.descriptors, f1.binary, config.initializer.matching)
    seconds = time.perf_counter() - t
    und = frame1.camera.undistort_points
    return und(f1.keypoints), und(f2.keypoints), np.asarray(pairs, np.int64).reshape(-1, 2), seconds


def compare_features(frame1: Frame, frame2: Frame, names=("orb", "sift"), tolerance_px: float = 2.0
                     ) -> list[FeatureComparison]:
    """Each feature pipeline of ``names`` on the pair, its matches checked against the ground-truth
    epipolar geometry (frames need ``gt_pose``). Each pipeline runs twice; the second run is kept and timed."""
    if frame1.gt_pose is None or frame2.gt_pose is None:
        raise ValueError("compare_features needs frames with ground-truth poses (gt_pose)")
    F = fundamental_from_poses(frame1.camera.K, frame1.gt_pose, frame2.gt_pose)
    out = []
    for name in names:
        detect_and_match(frame1, frame2, name)  # warm-up: the first call of a pipeline is slower (not timed)
        k1, k2, pairs, seconds = detect_and_match(frame1, frame2, name)
        d = epipolar_distances(k1[pairs[:, 0]], k2[pairs[:, 1]], F) if len(pairs) else np.empty(0)
        out.append(FeatureComparison(name, k1, k2, pairs, d, seconds, tolerance_px))
    return out


def learned_pipelines() -> tuple[list[str], str]:
    """(the learned feature pipelines that can run here, what to do for the others: an empty string when
    every one can run)."""
    status = feature_pipeline_status()
    learned = [n for n in status if n not in ("orb", "sift")]
    ready = [n for n in learned if status[n] is None]
    if not torch_available():
        return [], f"learned features need torch: {INSTALL_HINT}"
    missing = "; ".join(f"{n}: {status[n]}" for n in learned if status[n] is not None)
    return ready, missing


# ---------------------------------------------------------------------------------------------- flow score


@dataclass
class FlowScores:
    """The flow score of each frame against the keyframe before it, as the keyframe selector computes it:
    when the rule fires, that frame becomes the keyframe the next frames are measured against."""

    frame_indices: np.ndarray
    """(F,) source indices of the frames scored."""
    scores: np.ndarray
    """(F,) dimensionless: median |dx| / fx + median |dy| / fy of the matches to the current keyframe."""
    matches: np.ndarray
    """(F,) matches to the current keyframe."""
    threshold: float
    min_matches: int
    flows: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    """Per frame: (keyframe pixels (M, 2), current pixels (M, 2)) of the matches."""
    references: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    """(F,) source index of the keyframe each frame was measured against."""

    @property
    def due(self) -> np.ndarray:
        """(F,) bool: the rule makes the frame a keyframe (flow > threshold with enough matches)."""
        return (self.scores > self.threshold) & (self.matches >= self.min_matches)

    @property
    def keyframes(self) -> list[int]:
        """Source indices of the frames the rule makes keyframes, in order."""
        return [int(i) for i in self.frame_indices[self.due]]

    @property
    def first_keyframe(self) -> int | None:
        """Source index of the first frame the rule makes a keyframe (None if none)."""
        return self.keyframes[0] if self.keyframes else None


def flow_scores(source, keyframe_index: int, frame_indices, features: str = "orb",
                config: SlamConfig | None = None) -> FlowScores:
    """The flow score of ``frame_indices`` (increasing source indices) against the keyframe before them,
    starting from ``keyframe_index``; a frame the rule makes a keyframe is the reference of the frames after
    it, as in the pipeline. Matched by descriptors (the pipeline matches through the local map instead; the
    score is the same formula)."""
    config = config or SlamConfig().with_overrides(features=features)
    extractor, _, _ = _pipeline(config.feature_pipeline)
    kcfg = config.keyframes

    def keyframe(index: int):
        frame = source[int(index)]
        f = extractor.extract(frame.gray)
        return f, frame.camera.undistort_points(f.keypoints)

    ref = int(keyframe_index)
    fk, xk = keyframe(ref)
    cam = source[ref].camera
    scores, matches, flows, refs = [], [], [], []
    for i in frame_indices:
        fr = source[int(i)]
        fc = extractor.extract(fr.gray)
        pairs = match_descriptors(fk.descriptors, fc.descriptors, fk.binary, config.tracker.matching)
        xc = fr.camera.undistort_points(fc.keypoints)
        a, b = xk[pairs[:, 0]], xc[pairs[:, 1]]
        score = flow_score(a, b, cam.fx, cam.fy)
        scores.append(score)
        matches.append(len(pairs))
        flows.append((a, b))
        refs.append(ref)
        if score > kcfg.flow_threshold and len(pairs) >= kcfg.min_tracked_matches:
            ref, fk, xk = int(i), fc, xc  # this frame is the new keyframe
    return FlowScores(np.asarray(list(frame_indices), np.int64), np.asarray(scores), np.asarray(matches),
                      kcfg.flow_threshold, kcfg.min_tracked_matches, flows, np.asarray(refs, np.int64))


# ---------------------------------------------------------------------------------------------- two views


@dataclass
class TwoView:
    """Two-view reconstruction of a frame pair (the initializer's problem), with ground-truth errors."""

    x1: np.ndarray
    """(M, 2) undistorted pixels of the matches in frame 1 (and ``x2`` in frame 2)."""
    x2: np.ndarray
    E: np.ndarray
    """(3, 3) essential matrix (x2n^T E x1n = 0 in normalized coordinates)."""
    inliers: np.ndarray
    """(M,) bool: RANSAC inliers of E that triangulate in front of both cameras."""
    cam2_from_cam1: np.ndarray
    """(4, 4) estimated relative pose; its translation has unit length (scale is unobservable)."""
    points: np.ndarray
    """(I, 3) triangulated inliers in camera 1's frame, units of the baseline."""
    tri_angle_deg: np.ndarray
    """(I,) triangulation angle of each point: the angle between the rays from the two camera centres."""
    reproj_px: np.ndarray
    """(I, 2) reprojection error of each point in frame 1 and frame 2, pixels."""
    rotation_error_deg: float
    """Angle between the estimated and the ground-truth relative rotation."""
    translation_error_deg: float
    """Angle between the estimated and the ground-truth translation direction."""


def triangulation_angles(points: np.ndarray, c1: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """(N,) degrees: angle at each point (N, 3) between the rays to camera centres c1 and c2 (3,)."""
    r1, r2 = c1 - points, c2 - points
    cos = np.einsum("ij,ij->i", r1, r2) / (np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def _project(K: np.ndarray, cam_from_world: np.ndarray, X: np.ndarray) -> np.ndarray:
    Xc = X @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    x = Xc @ K.T
    return x[:, :2] / x[:, 2:3]


def two_view(frame1: Frame, frame2: Frame, features: str = "orb", ransac_px: float = 1.0) -> TwoView:
    """Match two frames, estimate E with RANSAC (OpenCV's five-point solver), recover (R, t), triangulate
    the inliers and measure angles and reprojection errors; errors against the frames' ``gt_pose``."""
    k1, k2, pairs, _ = detect_and_match(frame1, frame2, features)
    x1, x2 = k1[pairs[:, 0]], k2[pairs[:, 1]]
    K = frame1.camera.K
    E, mask = cv2.findEssentialMat(x1, x2, K, cv2.RANSAC, 0.999, ransac_px)
    _, R, t, mask2 = cv2.recoverPose(E, x1, x2, K, mask=mask.copy())
    inl = mask2.ravel() > 0
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t.ravel()
    P1, P2 = K @ np.eye(4)[:3], K @ T[:3]
    Xh = cv2.triangulatePoints(P1, P2, x1[inl].T, x2[inl].T)
    X = (Xh[:3] / Xh[3]).T
    c2 = -R.T @ t.ravel()
    angles = triangulation_angles(X, np.zeros(3), c2)
    err = np.stack([np.linalg.norm(_project(K, np.eye(4), X) - x1[inl], axis=1),
                    np.linalg.norm(_project(K, T, X) - x2[inl], axis=1)], axis=1)
    rot_err = t_err = float("nan")
    if frame1.gt_pose is not None and frame2.gt_pose is not None:
        G = relative_pose(frame1.gt_pose, frame2.gt_pose)
        c = (np.trace(G[:3, :3].T @ R) - 1) / 2
        rot_err = float(np.degrees(np.arccos(np.clip(c, -1, 1))))
        g = G[:3, 3] / np.linalg.norm(G[:3, 3])
        t_err = float(np.degrees(np.arccos(np.clip(g @ t.ravel() / np.linalg.norm(t), -1, 1))))
    return TwoView(x1, x2, E, inl, T, X, angles, err, rot_err, t_err)


# ---------------------------------------------------------------------------------------------- bundle adjustment


def reprojection_errors(rec: pycolmap.Reconstruction) -> np.ndarray:
    """(O,) pixels: the reprojection error |pi(K, T_i, X_j) - x_ij| of every observation of every 3D point
    in the registered images (the residuals bundle adjustment minimizes)."""
    out = []
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        cam = rec.camera(image.camera_id)
        T = image.cam_from_world().matrix()
        idx = image.get_observation_point2D_idxs()
        if not len(idx):
            continue
        obs = image.get_observation_points2D()
        X = np.array([rec.point3D(p.point3D_id).xyz for p in obs])
        xy = np.array([p.xy for p in obs])
        Xc = X @ T[:, :3].T + T[:, 3]
        front = Xc[:, 2] > 1e-9
        proj = cam.img_from_cam(Xc[front])
        out.append(np.linalg.norm(proj - xy[front], axis=1))
    return np.concatenate(out) if out else np.empty(0)


@dataclass
class AdjustmentDemo:
    """Bundle adjustment of a perturbed copy of a map: residuals and point errors before and after."""

    errors_before: np.ndarray
    """(O,) reprojection errors of the perturbed map, pixels."""
    errors_after: np.ndarray
    point_error_before: float
    """Median distance of the points from their unperturbed positions, map units."""
    point_error_after: float
    summary: str


def perturb_and_adjust(rec: pycolmap.Reconstruction, sigma: float, iterations: int = 30, seed: int = 0
                       ) -> AdjustmentDemo:
    """Add Gaussian noise of ``sigma`` map units to every 3D point of a *copy* of ``rec``, then run global
    bundle adjustment (pycolmap, poses and points free, two cameras fixed for the gauge) and compare."""
    work = copy.deepcopy(rec)
    rng = np.random.default_rng(seed)
    ids = list(work.point3D_ids())
    truth = np.array([work.point3D(p).xyz for p in ids])
    for p, x in zip(ids, truth + rng.normal(0, sigma, truth.shape)):
        work.point3D(p).xyz = x
    before = reprojection_errors(work)
    moved_before = float(np.median(np.linalg.norm(truth - np.array([work.point3D(p).xyz for p in ids]), axis=1)))
    opts = bundle_adjustment_options(int(iterations), loss="trivial")  # the plain least-squares BA cost
    cfg = pycolmap.BundleAdjustmentConfig()
    for image_id in work.reg_image_ids():
        cfg.add_image(image_id)
    cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    summary = pycolmap.create_default_bundle_adjuster(opts, cfg, work).solve()
    after = reprojection_errors(work)
    moved_after = float(np.median(np.linalg.norm(truth - np.array([work.point3D(p).xyz for p in ids]), axis=1)))
    return AdjustmentDemo(before, after, moved_before, moved_after, summary.brief_report())


# ---------------------------------------------------------------------------------------------- loop closure


@dataclass
class LoopCorrection:
    """What one loop closure changed, against ground truth: the trajectory just before the closing step and
    just after it, each Sim(3)-aligned to the ground truth over the same frames (those posed before).

    ``*_xyz``: (N, 3) metres, aligned; ``gt_xyz`` (N, 3) the ground truth of those frames; ``query`` and
    ``candidate``: indices into them of the newest frame before the closure and of the candidate keyframe's
    frame (the place returned to); ``gap_*``: metres between those two frames' positions (ground truth,
    the map before, the map after); ``ate_*``: ATE RMSE over the N frames, metres."""

    gt_xyz: np.ndarray
    before_xyz: np.ndarray
    after_xyz: np.ndarray
    query: int
    candidate: int
    query_frame: int
    candidate_frame: int
    gap_gt: float
    gap_before: float
    gap_after: float
    ate_before: float
    ate_after: float


def loop_correction(gt, before, after, closure, frame_times: np.ndarray) -> LoopCorrection:
    """Compare the trajectories ``before`` and ``after`` a loop closure (``slam.trajectory()`` at the steps
    around it) with the ground truth ``gt``; ``closure``: the step's ``loop_closure``; ``frame_times``:
    (F,) the timestamp of every frame index (to find the candidate's frame on the trajectories)."""
    from ..eval import ate

    common = np.isin(np.round(after.timestamps, 6), np.round(before.timestamps, 6))
    after = after.subset(common)
    ra, rb = ate(gt, after), ate(gt, before)
    a_xyz = ra.alignment.apply(after.subset(ra.idx_est)).positions
    b_xyz = rb.alignment.apply(before.subset(rb.idx_est)).positions
    g_xyz = gt.positions[ra.idx_gt]
    t = after.timestamps[ra.idx_est]
    n = min(len(a_xyz), len(b_xyz))
    q = n - 1  # the newest frame posed before the closing step
    c = int(np.argmin(np.abs(t[:n] - frame_times[int(closure.candidate_frame)])))
    qf = int(np.argmin(np.abs(frame_times - t[q])))

    def gap(x):
        return float(np.linalg.norm(x[q] - x[c]))

    return LoopCorrection(g_xyz[:n], b_xyz[:n], a_xyz[:n], q, c, qf, int(closure.candidate_frame),
                          gap(g_xyz), gap(b_xyz), gap(a_xyz), rb.rmse, ra.rmse)


def lap_of(spec: str, source_index: int) -> int | None:
    """The lap (1, 2, ...) a frame of a synthetic sequence driven round several times belongs to (its spec
    gives ``laps`` and ``frames``: frame ``j * (frames - 1) / laps`` ends lap j); None for other sources."""
    from ..sources.synthetic import parse_spec

    if not str(spec).startswith("synthetic:"):
        return None
    params = parse_spec(spec)[1]
    if "laps" not in params or "frames" not in params:
        return None
    per_lap = (int(params["frames"]) - 1) / int(params["laps"])
    return min(int(source_index // per_lap) + 1, int(params["laps"]))


def plot_loop_correction(ax, lc: LoopCorrection, unit: str = "m") -> None:
    """Top view (axes in metres) of the ground truth, the map before the loop closure and after it, and the
    closure: the two frames the loop joins, before (dashed) and after (thick) the correction; the gaps and
    ATE in the legend and title in ``unit`` ("m" or "cm")."""
    k = {"m": 1.0, "cm": 100.0}[unit]
    from ..eval.plots import view_axes
    from .scene import LOOP_COLOR

    (i, j, name), _ = view_axes(lc.gt_xyz)
    ax.plot(lc.gt_xyz[:, i], lc.gt_xyz[:, j], color="0.3", lw=2.5, alpha=0.5, label="ground truth")
    ax.plot(lc.before_xyz[:, i], lc.before_xyz[:, j], color="tab:red", lw=1.2, label="map before the loop closure")
    ax.plot(lc.after_xyz[:, i], lc.after_xyz[:, j], color="tab:blue", lw=1.2, label="map after the correction")
    for xyz, style, lw, label in ((lc.before_xyz, "--", 2, f"frames {lc.query_frame} and {lc.candidate_frame} "
                                   f"before: {k * lc.gap_before:.3g} {unit} apart"),
                                  (lc.after_xyz, "-", 5, f"after: {k * lc.gap_after:.3g} {unit} apart "
                                   f"(truth: {k * lc.gap_gt:.3g} {unit})")):
        ax.plot(xyz[[lc.query, lc.candidate], i], xyz[[lc.query, lc.candidate], j], style, color=LOOP_COLOR,
                lw=lw, label="loop closure: " + label if style == "--" else label)
    ax.plot(*lc.gt_xyz[0, [i, j]], "o", color="green", ms=8, label="start")
    ax.set_xlabel("xyz"[i] + " [m]")
    ax.set_ylabel("xyz"[j] + " [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.set_title(f"{name}, Sim(3)-aligned: ATE {k * lc.ate_before:.3g} {unit} before, "
                 f"{k * lc.ate_after:.3g} {unit} after")
    ax.legend(fontsize=8, loc="best")


def describe_focal(estimate, true_focal: float | None = None) -> str:
    """One line for a focal-length estimate (``stages.self_calibration.FocalEstimate``) that claims no more
    than it knows: a weak estimate gets no ± (it is not a measurement); otherwise the same ± as the run's camera
    line (``FocalEstimate.interval``: two standard deviations), with the bootstrap spread it contains named for
    what it is (how closely the frame pairs agree), beside the error against ``true_focal`` (pixels) when it is
    known and whether the ± covers it."""
    if not math.isfinite(estimate.focal):
        return f"no estimate ({estimate.reason or 'no usable frame pair'})"
    head = f"f = {estimate.focal:.1f} px from {estimate.num_pairs} frame pairs"
    if estimate.weak:
        return f"{head} — weak, not a measurement: {estimate.reason or 'the frames barely constrain it'}"
    from ..stages.self_calibration import MODEL_ERROR

    spread = math.sqrt(max(estimate.uncertainty ** 2 - MODEL_ERROR ** 2, 0.0))  # uncertainty = hypot(spread, model)
    text = (f"{head} ± {100 * estimate.interval:.1f} % (2 sd: bootstrap spread {100 * spread:.1f} %, model error "
            f"{100 * MODEL_ERROR:g} %)")
    if true_focal:
        err = estimate.focal / true_focal - 1
        text += (f"; the error is {100 * err:+.1f} % (true f = {true_focal:g} px), "
                 + ("inside" if abs(err) <= estimate.interval else "outside") + " the ±")
    return text


# ---------------------------------------------------------------------------------------------- a sweep's ranking


@dataclass(frozen=True)
class SweepRanking:
    """The settings of a parameter sweep ranked by mean ATE (notebook 03), with the ties named.

    ``best``: the parameter values (a dict) of the lowest mean ATE; ``seed``: a seed it was run with;
    ``ate_m``: (settings, mean ATE in metres, standard deviation over repeats or NaN, runs) per setting,
    lowest first; ``tied``: the settings that cannot be told apart from ``best``; ``rule``: how a tie was
    decided, in words."""

    best: dict
    seed: int
    ate_m: list
    tied: list
    rule: str

    def describe(self) -> str:
        """One line: the lowest mean ATE, the settings tied with it and the rule that says so."""
        def name(p: dict) -> str:
            return ", ".join(f"{k}={v:g}" if isinstance(v, (int, float)) else f"{k}={v}" for k, v in p.items())

        head = f"lowest mean ATE: {name(self.best)}, {100 * self.ate_m[0][1]:.2f} cm"
        if not self.tied:
            return f"{head}; no other setting is tied with it ({self.rule})"
        return (f"{head}; tied with {'; '.join(name(p) for p in self.tied)} ({self.rule}): a tie, not a ranking")


def rank_settings(df, names, precision_m: float = 1e-4) -> SweepRanking:
    """Rank the settings of a sweep (``ablate.sweep``'s DataFrame, parameter columns ``names``) by their mean ATE
    over the runs that succeeded. With at least two runs (seeds) of every setting, a setting is tied with the
    best when its mean is within two combined standard errors of the best's; with one run of some setting
    there is no spread to compare with, and only means equal to ``precision_m`` (metres; the notebook shows
    centimetres with two decimals) are called tied."""
    ok = df[(df["status"] == "ok") & df["ate_rmse_m"].notna()]
    if ok.empty:
        raise ValueError("no successful run to rank")
    names = list(names)
    g = ok.groupby(names, sort=False)["ate_rmse_m"]
    mean, sd, n = g.mean(), g.std(ddof=1), g.size()
    order = mean.sort_values(kind="stable").index
    keys = [k if isinstance(k, tuple) else (k,) for k in order]
    params = [dict(zip(names, (v.item() if hasattr(v, "item") else v for v in k))) for k in keys]
    rows = [(p, float(mean[k]), float(sd[k]) if n[k] >= 2 else float("nan"), int(n[k])) for p, k in zip(params, order)]
    best_key = order[0]
    if (n >= 2).all():
        se = sd / np.sqrt(n)
        margin = 2 * np.sqrt(se[best_key] ** 2 + se ** 2)
        tied = [p for p, k in zip(params[1:], order[1:]) if mean[k] - mean[best_key] <= margin[k]]
        rule = "within two standard errors of the mean over repeats"
    else:
        tied = [p for p, k in zip(params[1:], order[1:])
                if round(mean[k] / precision_m) == round(mean[best_key] / precision_m)]
        rule = (f"equal to the {100 * precision_m:g} cm shown: with one run per setting there is no spread to "
                "compare a difference with")
    best_runs = ok.set_index(names).loc[[best_key]] if len(names) > 1 else ok[ok[names[0]] == best_key]
    return SweepRanking(params[0], int(best_runs["seed"].iloc[0]), rows, tied, rule)


# ---------------------------------------------------------------------------------------------- drawing


def plot_matches(ax, frame1: Frame, frame2: Frame, comparison: FeatureComparison, max_lines: int = 200) -> None:
    """The two frames side by side on a matplotlib axis, matches as lines: green within the epipolar
    tolerance of the ground truth, red beyond it (at most ``max_lines``, evenly sampled)."""
    im = np.concatenate([frame1.color, frame2.color], axis=1)
    ax.imshow(im)
    w = frame1.color.shape[1]
    pairs = comparison.pairs
    keep = np.linspace(0, len(pairs) - 1, min(max_lines, len(pairs))).astype(int) if len(pairs) else []
    for i in keep:
        a, b = comparison.keypoints1[pairs[i, 0]], comparison.keypoints2[pairs[i, 1]]
        ax.plot([a[0], b[0] + w], [a[1], b[1]], "-", lw=0.6, color="tab:green" if comparison.inliers[i] else "red")
    ax.set_title(f"{comparison.name}: {len(pairs)} matches, {int(comparison.inliers.sum())} within "
                 f"{comparison.tolerance_px:g} px of their epipolar line (green)")
    ax.axis("off")


__all__ = ["describe_focal", "lap_of", "plot_matches", "skew", "relative_pose", "fundamental_from_poses", "epipolar_distances", "FeatureComparison",
           "detect_and_match", "compare_features", "learned_pipelines", "FlowScores", "flow_scores", "TwoView",
           "triangulation_angles", "two_view", "reprojection_errors", "AdjustmentDemo", "perturb_and_adjust",
           "LoopCorrection", "loop_correction", "plot_loop_correction", "SweepRanking", "rank_settings"]
