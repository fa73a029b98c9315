"""Map initialization from the first frames (seed §3.3, and the seed-2 strategy as an option).

``best_pair`` (default): buffer ``init_frames`` frames and match them exhaustively; the first image is the
one with the most correspondences, the second the image with the most correspondences to it whose
two-view geometry (``pycolmap.estimate_calibrated_two_view_geometry``) has enough inliers and a large
enough triangulation angle. Register the pair, triangulate, run global BA and filter; if too few map
points remain, try the next candidate; after the window, slide it and report the failure.

``first_inliers``: the first buffered frame with the first later frame whose essential matrix explains at
least ``min_inlier_ratio`` of the matches (with enough parallax).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np
import pycolmap

from ..camera import Intrinsics
from ..errors import ConfigError, check_fields, native_seed
from ..kernels.geometry import flow_score, parallax_deg, rotation_angle_deg
from ..features import FrameFeatures, MatchingConfig, NearestNeighborMatcher, PairMatcher
from ..map import SlamMap, bundle_adjustment_options, pycolmap_camera
from ..state import GENERAL, FrameStatus

if TYPE_CHECKING:  # pragma: no cover
    from ..results import StepResult
    from ..state import SlamState

STRATEGIES = ("best_pair", "first_inliers")


@dataclass(frozen=True)
class InitializerConfig:
    strategy: str = "best_pair"
    """"best_pair" (seed §3.3) or "first_inliers" (seed 2: first frame + first frame with >= 90 % E inliers)."""
    init_frames: int = 20
    """Largest size of the initialization window N (frames); with ``window_overlap`` the window closes
    earlier when the camera moves fast, and at the end of the sequence it is tried with what it holds."""
    window_overlap: float = 0.3
    """best_pair's motion window (benchmarks/HISTORY.md, "Local mapping"; the ``seed`` preset has it off): the window is tried
    as soon as the newest frame shares fewer window matches with the window's first frame than this fraction of
    what the first two frames share (fast motion: a fixed window of N frames would span so much that the map
    made from it is out of view by its end). 0: always N frames. At 0.3 KITTI 07 and 7-Scenes at their natural
    rates keep the same pair (3 seeds each), and the street at 1.5 m/frame and the corridor at 0.1 m/frame are
    posed 100 % with either mapper (the driving clip: measured with local mapping only)."""
    verify_frames: int = 4
    """The two-view map of a candidate pair must explain up to this many other window frames (the nearest to
    the pair's second frame, after it first): each frame that shares at least ``min_verify_inliers`` window
    matches with the map's points needs ``min_verify_ratio`` of them as PnP inliers, else the pair is
    rejected as a wrong two-view geometry (repeated texture, a look-alike). 0: no check."""
    min_verify_ratio: float = 0.5
    """See ``verify_frames``."""
    min_verify_inliers: int = 30
    """See ``verify_frames``."""
    min_matches: int = 100
    """Inlier matches a pair needs."""
    min_tri_angle_deg: float = 1.5
    """Parallax a match needs to count towards ``min_points``, degrees (ORB-SLAM's criterion; the median
    angle would reject forward motion, where points near the focus of expansion have none)."""
    min_inlier_ratio: float = 0.9
    """first_inliers: essential-matrix inliers / matches a pair needs."""
    min_points: int = 80
    """Map points the initial map needs after BA and filtering."""
    min_points_at_end: int = 50
    """What ``min_points`` becomes when the sequence ends before a map was made (no better pair will come):
    ORB-SLAM's minimum for a monocular initialization."""
    max_pair_trials: int = 6
    """Candidate second images tried per window."""
    max_error_px: float = 2.0
    """RANSAC threshold of the two-view geometry, pixels."""
    max_pose_disagreement_deg: float = 1.0
    """When the two-view geometry prefers a homography (pycolmap's PLANAR / PANORAMIC configurations), the
    essential matrix's relative pose must agree with the homography's within this rotation angle, and
    within 10x this in translation direction; else the pair is ambiguous and rejected. With a small
    baseline a homography fits a 3D scene as well as the essential matrix does, and its decomposition can
    give a wrong pose with apparent parallax, and a map whose scale breaks later."""
    max_reproj_error_px: float = 4.0
    min_track_angle_deg: float = 1.5
    window_features: int = 1000
    """Pair selection matches the window exhaustively on each frame's strongest keypoints, this many
    (the chosen pair is matched in full); 0 = all. The counts rank the pairs and gate them at
    ``min_matches``. Fewer would initialize faster but rank pairs differently on hard windows (a new map
    started much later after a lost stretch; benchmarks/HISTORY.md, "Measurements moved from docstrings")."""
    max_history: int = 300
    """Frames that slid out of the window are kept (features only) up to this many, so they can be
    tracked once the map exists: every frame gets a pose, not only those after initialization."""
    matching: MatchingConfig = field(default_factory=lambda: MatchingConfig(mutual=False))
    """Exhaustive window matching: ratio test only (a mutual check would double the cost)."""
    random_seed: int = 0

    def validate(self) -> None:
        if self.strategy not in STRATEGIES:
            raise ConfigError(f"initializer.strategy must be one of {STRATEGIES} (got {self.strategy!r})")
        check_fields(self, "initializer", {
            "init_frames": ("[2, 1000]", "frames kept in memory while the initial pair is sought"), "window_overlap": "[0, 1)", "verify_frames": "[0, 1000]",
            "min_verify_ratio": "[0, 1]", "min_verify_inliers": "[4, inf)", "min_matches": "[8, inf)",
            "min_tri_angle_deg": "[0, 45)", "min_inlier_ratio": "(0, 1]", "min_points": "[8, inf)",
            "min_points_at_end": "[8, inf)", "max_pair_trials": "[1, 1000]", "max_error_px": "(0, 1e9]",
            "max_pose_disagreement_deg": "(0, 180]", "max_reproj_error_px": "(0, 1e9]",
            "min_track_angle_deg": "[0, 45)", "window_features": ("[0, 1000000]", "0: all"), "max_history": "[0, 100000]",
            "random_seed": "[0, inf)"})
        if self.min_points_at_end > self.min_points:
            raise ConfigError("initializer.min_points_at_end must be in [8, min_points] "
                              f"(got {self.min_points_at_end})")


@dataclass(frozen=True, eq=False)
class InitResult:
    """status: "collecting", "initialized" or "failed". On success ``slam_map`` holds the two keyframes
    (image ids 1 and 2 for frames ``first`` and ``second``) and ``frames`` every kept frame (the window and
    the frames that slid out of earlier windows), oldest first."""

    status: str
    reason: str
    slam_map: SlamMap | None = None
    first: int | None = None
    second: int | None = None
    tri_angle_deg: float = 0.0
    num_points: int = 0
    frames: tuple[FrameFeatures, ...] = ()

    @property
    def initialized(self) -> bool:
        return self.status == "initialized"


@dataclass(eq=False)
class InitializerWindow:
    """What the initializer holds between frames: the buffered window, the frames that slid out of earlier
    windows (kept to be posed once a map exists), and the window matches computed so far, keyed by the
    frames' indices ((M, 2) keypoint indices)."""

    frames: list[FrameFeatures]
    history: list[FrameFeatures]
    matches: dict[tuple[int, int], np.ndarray]


class Initializer:
    """Buffers frames until an initial map can be built from a pair of them."""

    def __init__(self, camera: Intrinsics, config: InitializerConfig = InitializerConfig(),
                 matcher: PairMatcher | None = None):
        config.validate()
        self.config = config
        self.matcher = matcher if matcher is not None else NearestNeighborMatcher(config.matching)
        self.camera = camera.pinhole
        self._pycamera = pycolmap_camera(self.camera)
        self.frames: list[FrameFeatures] = []
        self.history: list[FrameFeatures] = []
        self._matches: dict[tuple[int, int], np.ndarray] = {}
        opts = pycolmap.TwoViewGeometryOptions()
        opts.compute_relative_pose = True
        opts.ransac.max_error = config.max_error_px
        opts.ransac.random_seed = native_seed(config.random_seed)
        opts.min_num_inliers = config.min_matches
        self._tvg_options = opts
        essential = pycolmap.RANSACOptions()
        essential.max_error = config.max_error_px
        essential.random_seed = native_seed(config.random_seed)
        self._essential_ransac = essential
        pnp = pycolmap.AbsolutePoseEstimationOptions()
        pnp.ransac.max_error = 4 * config.max_error_px
        pnp.ransac.random_seed = native_seed(config.random_seed)
        self._pnp_options = pnp

    def set_camera(self, camera: Intrinsics) -> None:
        """Initialize the next maps with this camera (self-calibration refined it)."""
        self.camera = camera.pinhole
        self._pycamera = pycolmap_camera(self.camera)

    @property
    def window(self) -> InitializerWindow:
        """The buffered frames and window matches (live lists, for sessions: do not change them)."""
        return InitializerWindow(self.frames, self.history, self._matches)

    def restore(self, window: InitializerWindow) -> None:
        """Continue from another initializer's :attr:`window` (a resumed session)."""
        self.frames, self.history, self._matches = list(window.frames), list(window.history), dict(window.matches)

    def reset(self) -> None:
        self.frames.clear()
        self.history.clear()
        self._matches.clear()

    def _strongest(self, f: FrameFeatures) -> np.ndarray:
        """Indices of the frame's strongest ``window_features`` keypoints."""
        n = self.config.window_features
        if n <= 0 or len(f) <= n:
            return np.arange(len(f))
        return np.sort(np.argsort(-f.features.scores, kind="stable")[:n])

    def _match(self, a: FrameFeatures, b: FrameFeatures) -> np.ndarray:
        """Window matches on the strongest keypoints, as (M, 2) indices into the full keypoint lists."""
        key = (a.index, b.index)
        if key not in self._matches:
            ia, ib = self._strongest(a), self._strongest(b)
            m = self.matcher.match(a.features.subset(ia), b.features.subset(ib))
            self._matches[key] = np.stack([ia[m[:, 0]], ib[m[:, 1]]], axis=1) if len(m) else m
        return self._matches[key]

    def window_matches(self, a: FrameFeatures, b: FrameFeatures) -> np.ndarray:
        """(M, 2) window matches (keypoint indices of ``a``, of ``b``) of two buffered frames, ``a`` first in
        time: computed once, then kept with the window."""
        return self._match(a, b)

    def step(self, frame: FrameFeatures, last: bool = False) -> InitResult:
        """Buffer ``frame`` and try to initialize when the window is complete: ``init_frames`` frames, the
        motion window closed (``window_overlap``), or ``last`` (no frame follows: a sequence shorter than the
        window is tried with what it has)."""
        c = self.config
        self.frames.append(frame)
        for other in self.frames[:-1]:  # match exhaustively as frames arrive
            if c.strategy == "best_pair" or other is self.frames[0]:
                self._match(other, frame)
        if c.strategy == "first_inliers":
            result = self._try_first_inliers()
        elif len(self.frames) < c.init_frames and not last and not self._moved_on():
            return InitResult("collecting", f"buffered {len(self.frames)}/{c.init_frames} frames")
        else:
            result = self._try_best_pair(c.min_points_at_end if last else c.min_points)
        if result.initialized:
            result = InitResult(**{**result.__dict__, "frames": tuple(self.history + self.frames)})
            self.reset()
            return result
        if last:
            return InitResult("failed", f"{result.reason}; the sequence ended")
        if len(self.frames) >= c.init_frames:  # slide the window
            drop = max(1, len(self.frames) // 2) if c.strategy == "best_pair" else 1
            gone = {f.index for f in self.frames[:drop]}
            self.history = (self.history + self.frames[:drop])[-self.config.max_history:] \
                if self.config.max_history > 0 else []
            self.frames = self.frames[drop:]
            self._matches = {k: v for k, v in self._matches.items() if k[0] not in gone and k[1] not in gone}
            return InitResult("failed", f"{result.reason}; window slides by {drop} frames")
        return InitResult("collecting", f"{result.reason}; buffered {len(self.frames)}/{c.init_frames} frames")

    def _moved_on(self) -> bool:
        """The motion window is closed: the newest frame shares fewer window matches with the first than
        ``window_overlap`` of what the first two share (at least 3 frames buffered)."""
        c, f = self.config, self.frames
        if c.window_overlap <= 0 or len(f) < 3:
            return False
        return len(self._match(f[0], f[-1])) < c.window_overlap * len(self._match(f[0], f[1]))

    # ------------------------------------------------------------------ strategies
    def _try_best_pair(self, min_points: int) -> InitResult:
        frames = self.frames
        n = len(frames)
        counts = np.zeros((n, n), np.int64)
        for i in range(n):
            for j in range(i + 1, n):
                counts[i, j] = counts[j, i] = len(self._matches[(frames[i].index, frames[j].index)])
        first = int(np.argmax(counts.sum(axis=1)))
        # candidates with enough correspondences, the most apparent motion (flow) first
        flows = {}
        for j in range(n):
            if j != first and counts[first, j] >= self.config.min_matches:
                a, b = (first, j) if first < j else (j, first)
                m = self._matches[(frames[a].index, frames[b].index)]
                flows[j] = flow_score(frames[a].keypoints[m[:, 0]], frames[b].keypoints[m[:, 1]],
                                      self.camera.fx, self.camera.fy)
        order = sorted(flows, key=lambda j: (-flows[j], j))
        reasons = []
        for j in order[: self.config.max_pair_trials]:
            a, b = (first, int(j)) if first < j else (int(j), first)
            res = self._try_pair(frames[a], frames[b], min_points=min_points)
            if res.initialized:
                contradiction = self._verify(res, frames[a], frames[b])
                if not contradiction:
                    return res
                res = InitResult("failed", contradiction)
            reasons.append(f"{frames[a].index}-{frames[b].index}: {res.reason}")
        why = "; ".join(reasons[:3]) or "no matches in the window"
        return InitResult("failed", f"no initial pair in frames {frames[0].index}-{frames[-1].index} ({why})")

    def _try_first_inliers(self) -> InitResult:
        if len(self.frames) < 2:
            return InitResult("collecting", "waiting for a second frame")
        return self._try_pair(self.frames[0], self.frames[-1], need_ratio=self.config.min_inlier_ratio)

    def _try_pair(self, fa: FrameFeatures, fb: FrameFeatures, need_ratio: float = 0.0,
                  min_points: int | None = None) -> InitResult:
        c = self.config
        min_points = c.min_points if min_points is None else min_points
        if len(self._match(fa, fb)) < c.min_matches:
            return InitResult("failed", f"{len(self._match(fa, fb))} matches < {c.min_matches}")
        matches = self.matcher.match(fa.features, fb.features)
        if len(matches) < c.min_matches:
            return InitResult("failed", f"{len(matches)} matches < {c.min_matches}")
        tvg = pycolmap.estimate_calibrated_two_view_geometry(
            self._pycamera, fa.keypoints, self._pycamera, fb.keypoints,
            np.ascontiguousarray(matches, np.uint32), self._tvg_options)
        inl = np.asarray(tvg.inlier_matches)
        if tvg.cam2_from_cam1 is None or len(inl) < c.min_matches:
            return InitResult("failed", f"{len(inl)} two-view inliers < {c.min_matches}")
        ratio = len(inl) / len(matches)
        if ratio < need_ratio:
            return InitResult("failed", f"inlier ratio {ratio:.2f} < {need_ratio:g}")
        parallax = parallax_deg(fa.keypoints[inl[:, 0]], fb.keypoints[inl[:, 1]], tvg.cam2_from_cam1.rotation.matrix(),
                                self.camera.K)
        n_good = int((parallax >= c.min_tri_angle_deg).sum())
        angle = float(np.median(parallax))
        if n_good < min_points:
            return InitResult("failed", f"{n_good} matches with parallax >= {c.min_tri_angle_deg:g} deg "
                                        f"< {min_points} (median {angle:.2f} deg)")
        ambiguity = self._ambiguity(fa, fb, matches, tvg)  # after the parallax test: a still camera fails that
        if ambiguity:
            return InitResult("failed", ambiguity)
        slam_map = SlamMap(self.camera)
        ia = slam_map.add_image(fa.index, fa.timestamp, fa.keypoints, fa.features, fa.colors, fa.thumbnail)
        ib = slam_map.add_image(fb.index, fb.timestamp, fb.keypoints, fb.features, fb.colors, fb.thumbnail)
        slam_map.add_matches(ia, ib, inl)
        slam_map.observe(ia, ib)
        slam_map.register(ia, pycolmap.Rigid3d())
        slam_map.register(ib, tvg.cam2_from_cam1)
        slam_map.triangulate(ib)
        slam_map.color_new_points(ia)
        self._global_ba(slam_map)
        slam_map.observations.filter_all_points3D(c.max_reproj_error_px, c.min_track_angle_deg)
        slam_map.changed()
        n_points = slam_map.num_points
        if n_points < min_points:
            return InitResult("failed", f"{n_points} map points after BA < {min_points}")
        return InitResult("initialized", f"frames {fa.index} and {fb.index}: {len(inl)} inliers, "
                                         f"{n_good} with parallax >= {c.min_tri_angle_deg:g} deg (median "
                                         f"{angle:.1f} deg), {n_points} points",
                          slam_map, fa.index, fb.index, angle, n_points)

    def _verify(self, res: InitResult, fa: FrameFeatures, fb: FrameFeatures) -> str:
        """"" when the two-view map of ``fa``, ``fb`` explains the window's other frames (``verify_frames``),
        else why not: each checked frame is posed by PnP (LO-RANSAC) on its window matches to the keypoints of
        the pair that have a map point."""
        c = self.config
        if c.verify_frames <= 0:
            return ""
        others = [f for f in self.frames if f.index not in (fa.index, fb.index)]
        others.sort(key=lambda f: (f.index < fb.index, abs(f.index - fb.index)))  # after the pair first
        slam_map = res.slam_map
        for f in others[: c.verify_frames]:
            xy, pids = [], []
            for image_id, kf in ((1, fa), (2, fb)):
                m = self._match(kf, f) if kf.index < f.index else self._match(f, kf)[:, ::-1]
                p = slam_map.point3D_ids(image_id)[m[:, 0]]
                xy.append(f.keypoints[m[p >= 0, 1]])
                pids.append(p[p >= 0])
            kp_xy, pids = np.concatenate(xy), np.concatenate(pids)
            _, first = np.unique(kp_xy[:, 0] * 1e5 + kp_xy[:, 1], return_index=True)  # one per keypoint
            kp_xy, pids = kp_xy[first], pids[first]
            if len(pids) < c.min_verify_inliers:
                continue  # too little in common to say
            est = pycolmap.estimate_and_refine_absolute_pose(kp_xy, slam_map.points_xyz(pids), self._pycamera,
                                                              self._pnp_options)
            inliers = 0 if est is None else int(est["num_inliers"])
            if inliers < max(c.min_verify_inliers, c.min_verify_ratio * len(pids)):
                return (f"the two-view map explains only {inliers} of frame {f.index}'s {len(pids)} matches to it "
                        f"(< {c.min_verify_ratio:g}): a wrong two-view geometry")
        return ""

    def _ambiguity(self, fa: FrameFeatures, fb: FrameFeatures, matches: np.ndarray, tvg) -> str:
        """"" when the relative pose is unambiguous, else why not: a homography-based pose (planar or
        panoramic configuration) that the essential matrix's pose contradicts (ORB-SLAM compares its
        homography and fundamental-matrix reconstructions the same way)."""
        cfg = pycolmap.TwoViewGeometryConfiguration
        if tvg.config not in (cfg.PLANAR, cfg.PANORAMIC, cfg.PLANAR_OR_PANORAMIC):
            return ""
        alt = pycolmap.estimate_essential_matrix(fa.keypoints[matches[:, 0]], fb.keypoints[matches[:, 1]],
                                                 self._pycamera, self._pycamera, self._essential_ransac)
        name = str(tvg.config).rsplit(".", 1)[-1].lower()
        if alt is None:
            return f"{name} two-view geometry and no essential matrix to confirm its pose"
        h, e = tvg.cam2_from_cam1, alt["cam2_from_cam1"]
        d_rot = rotation_angle_deg(h.rotation.matrix() @ e.rotation.matrix().T)
        th, te = np.asarray(h.translation), np.asarray(e.translation)
        cos = float(th @ te) / max(float(np.linalg.norm(th) * np.linalg.norm(te)), 1e-12)
        d_dir = math.degrees(math.acos(min(1.0, max(-1.0, cos))))
        tol = self.config.max_pose_disagreement_deg
        if d_rot > tol or d_dir > 10 * tol:
            return (f"ambiguous relative pose: the {name} homography's and the essential matrix's differ by "
                    f"{d_rot:.1f} deg in rotation and {d_dir:.0f} deg in translation direction")
        return ""

    @staticmethod
    def _global_ba(slam_map: SlamMap) -> None:
        opts = bundle_adjustment_options(100, loss="trivial", num_threads=1)
        cfg = pycolmap.BundleAdjustmentConfig()
        for i in slam_map.keyframes:
            cfg.add_image(i)
        cfg.set_constant_cam_intrinsics(1)
        cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
        slam_map.bundle_adjust(opts, cfg)


def track_window(state: "SlamState", res: "InitResult", tracker, track_frame: Callable[..., "StepResult"],
                 timings: dict) -> tuple[list[int], str]:
    """The rest of the initialization window, once ``state`` has a segment of the initial pair.

    Frames between the initial pair, then those before it, are posed against the two-keyframe map by
    ``tracker`` (a :class:`~slamkit.stages.tracker.Tracker`; each frame predicted by its already-posed
    neighbour). Frames after the pair go through ``track_frame(features, record, timings)`` (the pipeline's
    tracking, keyframes and mapping included) as if they came now: the map grows up to the current frame
    (with fast motion a map of the pair alone may no longer be in view). Returns the posed frames and a
    note for the result's message ("" or why the new map was lost again)."""
    t = time.perf_counter()
    frames = sorted(res.frames, key=lambda f: f.index)
    camera = res.slam_map.pycolmap_camera
    posed = [res.first, res.second]
    for i in posed:  # the initial pair: 6-DoF, whatever GRIC said while the map did not exist
        state.records[i].motion_model = GENERAL
    between = [f for f in frames if res.first < f.index < res.second]
    before = [f for f in reversed(frames) if f.index < res.first]
    for seq in (between, before):
        neighbour = state.pose_of(state.records[res.first])
        for f in seq:
            tr = tracker.step(f, state.local_map, camera, neighbour)
            rec = state.records[f.index]
            if tr.tracked:
                state.set_pose(rec, state.last_keyframe, tr.cam_from_world, FrameStatus.TRACKED, absolute=True)
                rec.motion_model = GENERAL  # posed by PnP
                posed.append(f.index)
                neighbour = tr.cam_from_world
            else:
                rec.status = FrameStatus.LOST
    state.segment.frames.sort()
    timings["track"] = timings.get("track", 0.0) + time.perf_counter() - t
    seg = state.segment
    for f in (f for f in frames if f.index > res.second):
        step_timings: dict = {}
        result = track_frame(f, state.records[f.index], step_timings)
        for k, v in step_timings.items():
            timings[k] = timings.get(k, 0.0) + v
        if result.has_pose:
            posed.append(f.index)
        if state.segment is not seg:  # lost again at once: the next frame starts a new window
            return posed, f"; frame {f.index}: {result.message}"
    seg.frames.sort()
    return posed, ""
