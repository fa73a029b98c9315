"""Bundle adjustment, track maintenance and filtering (seed §3.6, COLMAP's iterative refinement).

After each keyframe: local BA over the new keyframe and its most covisible keyframes (points they observe
are variable; other keyframes observing those points are constant), or global BA when the map has grown
by ``global_growth`` since the last one. Then merge and complete the modified tracks, filter points with
large reprojection error or too small triangulation angle, and (after global BA) normalize the map.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pycolmap

from ..errors import ConfigError, check_fields
from ..kernels.local_ba import LOSSES as _COMPILED_LOSSES, local_bundle_adjustment
from ..local_ba_problem import compiled_camera, local_problem, write_back
from ..map import BA_LOSSES as _LOSSES, CAMERA_ID, SlamMap, bundle_adjustment_options, keypoint_scales
from ..weighted_ba import weighted_adjust

_EPS = float(np.finfo(np.float64).eps)
"""COLMAP's reprojection cost is 0 for a point at depth below this (its behind-the-camera test)."""
_COLMAP_SOLVER = {"parameter_tolerance": 0.0, "gradient_tolerance": 1e-4}
"""COLMAP's BundleAdjustmentOptions' Ceres tolerances (pycolmap 4.2), which the compiled engine stops by too."""
ENGINES = ("ceres", "compiled")
"""Local BA's solvers: pycolmap's Ceres bundle adjuster, or :mod:`slamkit.kernels.local_ba`."""


@dataclass(frozen=True)
class BundleAdjustmentConfig:
    local_window: int = 6
    """Keyframes adjusted with the new one: its most covisible keyframes."""
    local_iterations: int = 20
    local_max_track_length: int = 12
    """In local BA, points observed by more keyframes than this are held constant: they are well
    constrained already, and their observations in every other keyframe would otherwise all enter the
    problem, so local BA would grow with the map wherever the camera revisits (0: all points variable)."""
    global_growth: float = 1.0
    """Global BA when the number of keyframes has grown by this fraction since the last global BA (1.0: at
    8, 16, 32, 64, ... keyframes): the cost of global BA stays proportional to the map built; more frequent
    global BA was no more accurate (benchmarks/HISTORY.md, "Measurements moved from docstrings")."""
    radial_keyframes: int = 0
    """A given camera (no self-calibration; one focal length): when a map reaches this many keyframes (20 is
    measured), one global BA estimates the radial distortion left in the images, as COLMAP refines a given
    camera's extra parameters (:func:`~slamkit.run_camera.calibrate_radial`). 0 (default): never. KITTI 07
    (rectified, k1 = 0.015 left) 0.373 -> 0.146 m, but 7-Scenes 2.93 -> 3.29 cm and a rendered pinhole street
    0.35 -> 0.50 m (a spurious k1 of +-0.03); benchmarks/HISTORY.md, "Session 21"."""
    global_min_keyframes: int = 8
    """No periodic global BA before the map has this many keyframes (early maps are ill-conditioned)."""
    global_max_keyframes: int = 250
    """No periodic global BA beyond this many keyframes (keeps per-frame time flat); see ``final_global``."""
    global_iterations: int = 50
    final_global: bool = True
    """Global BA once more when the run ends (in ``Slam.finish``)."""
    max_reproj_error_px: float = 4.0
    """Points with a larger reprojection error are filtered after BA."""
    min_tri_angle_deg: float = 1.5
    """Points with a smaller triangulation angle are filtered after BA (after a starving keyframe's BA:
    ``mapper.starved_tri_angle_deg``, so its points survive it)."""
    outlier_chi2: float = 5.991
    """ORB-SLAM's outlier test after each BA: an observation whose squared reprojection error exceeds this
    times its keypoint's scale squared (sigma = 1.2^octave for ORB; :func:`~slamkit.map.keypoint_scales`) is
    removed from its track (5.991: chi-square with two degrees of freedom at 95 %, ORB-SLAM's), so a fine-level
    keypoint is held to 2.4 px and a coarse one to its level's noise; points are then filtered by
    triangulation angle only. 0: COLMAP's flat ``max_reproj_error_px`` for every observation (the ``seed``
    preset). With ``local_passes`` = 2 it took 7-Scenes at every 5th frame from 5.03 +- 0.77 to 2.93 +- 0.04
    cm and cost KITTI 07 0.347 -> 0.373 m (3 seeds each; benchmarks/HISTORY.md, "Local mapping by default (issue
    39)")."""
    local_passes: int = 2
    """Local BA runs this many times, with the outlier test between the passes (ORB-SLAM runs two: the
    second adjusts without the outliers the first exposed)."""
    confirm_outliers: bool = False
    """ORB-SLAM's local BA leaves the first pass's outliers out of the second and erases only those the second
    pass confirms; with this set, the observations removed between the passes are given back to their points
    when the second pass's solution brings them within the bound. Off: it changed KITTI 07 skip 1 by nothing
    (0.384, 0.362, 0.378 m against 0.382, 0.358, 0.378) and lost 7-Scenes skip 5 seed 2 (3.01, 3.52, 7.75 cm
    against 2.86, 3.00, 2.92; benchmarks/HISTORY.md)."""
    loss: str = "soft_l1"
    """Robust loss of COLMAP's BA: trivial, soft_l1, cauchy or huber (scale 1 px)."""
    weighting: str = "none"
    """Local BA's observation weights. "none": COLMAP's BA, every observation alike with ``loss``. "level":
    ORB-SLAM's, each observation's information 1/sigma^2 of its keypoint's level
    (:func:`~slamkit.map.keypoint_scales`), Huber at sqrt(``outlier_chi2``) on the whitened error
    (:mod:`slamkit.weighted_ba`); it recovers a synthetic scene with pyramid noise closer to the truth
    (tests/test_weighted_ba.py) but lost on the real rows, at 2-3x local BA's time: KITTI 07 skip 1 0.396 m
    against 0.373, 7-Scenes skip 5 3.36 against 2.93 cm (3 seeds; benchmarks/HISTORY.md). Falls back
    to "none" when intrinsics are refined."""
    normalize: bool = True
    """Normalize the map (COLMAP ``Reconstruction.normalize``) after global BA."""
    refine_intrinsics: bool = False
    """Intrinsics are fixed (calibrated cameras) unless this is set."""
    function_tolerance: float = 1e-6
    """Ceres stops when an iteration lowers the cost by less than this fraction (Ceres' default; COLMAP's
    0 always runs ``*_iterations``, which local BA then never converges within)."""
    num_threads: int = 1
    """Ceres threads (-1: all cores). One thread keeps runs bit-identical: with more, Ceres adds up
    per-thread partial sums in the order the threads happen to finish, so results differ in the last bits
    from run to run, and over hundreds of BAs the trajectory diverges (benchmarks/HISTORY.md, "Measurements
    moved from docstrings"). -1 is faster on a multi-core machine when determinism does not matter."""

    engine: str = "ceres"
    """Local BA's solver. "compiled": the problem, loss and weights read from the map as arrays
    (:mod:`slamkit.local_ba_problem`) and solved by the compiled kernel (:mod:`slamkit.kernels.local_ba`:
    Ceres' Levenberg-Marquardt with the Schur complement on the poses, nogil), the solution written back; the
    outlier test, second pass and track maintenance as with Ceres. "ceres" (default): pycolmap's bundle adjuster,
    or :mod:`slamkit.weighted_ba` with ``weighting`` "level". Every loss of ``loss``; a map
    camera that is not PINHOLE (self-calibration's radial BA) or ``refine_intrinsics`` goes to Ceres. Global BA
    is always Ceres'. The kernel takes Ceres' steps and stops by its rules, so both end on the same state: on the
    112 local BAs of KITTI 07 at every 2nd frame, solved by both from the same state, 108 agree to 1e-13 and
    the largest camera gap is 2.4e-4 map units, at half the time (18 against 37 ms a solve, read and write
    included; benchmarks/bench_local_ba.py). Not the default: over whole runs the last bits still diverge, and
    the suite's rows with it and the compiled refinement (3 seeds) are not all within a standard error of
    Ceres' (the rendered block loop 0.26 against 0.16 m): benchmarks/HISTORY.md, "A mapping engine of our own
    (issue 48)"."""

    def validate(self) -> None:
        check_fields(self, "ba", {
            "local_window": "[1, 10000]", "local_iterations": "[1, 10000]", "local_max_track_length": "[0, inf)",
            "global_growth": "(0, 100]", "global_min_keyframes": "[0, inf)", "global_max_keyframes": "[0, inf)",
            "global_iterations": "[1, 10000]", "max_reproj_error_px": "(0, 1e9]", "min_tri_angle_deg": "[0, 45)",
            "outlier_chi2": ("[0, 1e9]", "0: COLMAP's flat max_reproj_error_px"), "local_passes": "[1, 5]",
            "function_tolerance": "[0, 1)", "radial_keyframes": "[0, inf)",
            "num_threads": ("[-1, 1024]", "-1: all cores, else 1 to 1024 threads")})
        if self.num_threads == 0:
            raise ConfigError("ba.num_threads must be -1 (all cores) or a number of threads >= 1 (got 0)")
        if self.weighting not in ("level", "none"):
            raise ConfigError(f"ba.weighting must be 'level' or 'none' (got {self.weighting!r})")
        if self.loss not in _LOSSES:
            raise ConfigError(f"ba.loss must be one of {sorted(_LOSSES)} (got {self.loss!r})")
        if self.engine not in ENGINES:
            raise ConfigError(f"ba.engine must be one of {list(ENGINES)} (got {self.engine!r})")
        if self.engine == "compiled" and self.loss not in _COMPILED_LOSSES:
            raise ConfigError(f"ba.engine 'compiled' takes ba.loss {sorted(_COMPILED_LOSSES)} (got {self.loss!r})")


@dataclass(frozen=True)
class BundleAdjustmentResult:
    kind: str
    """"local" or "global"."""
    num_images: int
    num_points: int
    termination: str
    merged: int
    completed: int
    filtered: int
    seconds: float
    normalization: pycolmap.Sim3d | None
    """The similarity applied by normalization (new_from_old world), or None."""


class BundleAdjuster:
    """Local / global bundle adjustment of a :class:`SlamMap`, then track maintenance and filtering."""

    def __init__(self, config: BundleAdjustmentConfig = BundleAdjustmentConfig(), refine_principal_point: bool = False):
        config.validate()
        self.config = config
        self._keyframes_at_last_global = 0
        self._steps = 0  # keyframes adjusted (step calls)
        self._starved = (0, 0.0)  # (step of the last starving keyframe, its angle)
        self.refine_principal_point = refine_principal_point
        """With ``refine_focal``: refine the principal point too (self-calibration)."""

    def state(self) -> dict[str, float]:
        """What the adjuster remembers between keyframes (when the last global BA ran, the last starving
        keyframe), for sessions."""
        return {"keyframes_at_last_global": int(self._keyframes_at_last_global),
                "steps": int(self._steps), "last_starved_step": int(self._starved[0]),
                "starved_tri_angle_deg": float(self._starved[1])}

    def restore(self, state: dict[str, float]) -> None:
        """Continue from :meth:`state` of another adjuster (a resumed session)."""
        self._keyframes_at_last_global = int(state["keyframes_at_last_global"])
        self._steps = int(state.get("steps", 0))  # sessions saved before these keys: no starving keyframe
        self._starved = (int(state.get("last_starved_step", 0)), float(state.get("starved_tri_angle_deg", 0)))

    def filter_angle(self, starved_angle: float | None = None) -> float:
        """The triangulation angle points are filtered by after this BA, degrees: ``config.min_tri_angle_deg``,
        or a starving keyframe's smaller angle (``starved_angle``, ``mapper.starved_tri_angle_deg``) for the
        BAs of the ``local_window`` keyframes from it, so its points live until later keyframes see them
        with more parallax. Counts one more keyframe."""
        self._steps += 1
        if starved_angle is not None:
            self._starved = (self._steps, float(starved_angle))
        last, angle = self._starved
        if last > 0 and self._steps - last < self.config.local_window:
            return min(angle, self.config.min_tri_angle_deg)
        return self.config.min_tri_angle_deg

    def _options(self, iterations: int, refine_focal: bool = False,
                 refine_radial: bool = False) -> pycolmap.BundleAdjustmentOptions:
        c = self.config
        return bundle_adjustment_options(iterations, c.loss, c.refine_intrinsics or refine_focal,
                                         c.function_tolerance, c.num_threads,
                                         refine_principal_point=refine_focal and self.refine_principal_point,
                                         refine_extra_params=refine_radial)

    def global_due(self, slam_map: SlamMap) -> bool:
        n = slam_map.num_keyframes
        c = self.config
        return (c.global_min_keyframes <= n <= c.global_max_keyframes
                and n >= (1 + c.global_growth) * max(self._keyframes_at_last_global, 1))

    def step(self, slam_map: SlamMap, image_id: int, starved_angle: float | None = None,
             refine_focal: bool = False) -> BundleAdjustmentResult:
        """Adjust after keyframe ``image_id`` was inserted: global when due, else local. starved_angle: the
        keyframe's smaller triangulation angle when it was starving (see :meth:`filter_angle`), else None.
        refine_focal: a global BA that refines the focal length too (self-calibration: a local window
        constrains it too little), whatever ``refine_intrinsics`` says."""
        min_tri_angle_deg = self.filter_angle(starved_angle)
        if refine_focal or self.global_due(slam_map):
            return self.adjust_global(slam_map, min_tri_angle_deg=min_tri_angle_deg, refine_focal=refine_focal)
        return self.adjust_local(slam_map, image_id, min_tri_angle_deg)

    def adjust_local(self, slam_map: SlamMap, image_id: int, min_tri_angle_deg: float | None = None
                     ) -> BundleAdjustmentResult:
        t0 = time.perf_counter()
        held = held_keyframes(slam_map)  # outside the window: observers held constant
        window = [image_id] + [i for i, _ in slam_map.covisible(image_id, self.config.local_window) if i not in held]
        removed, excluded = 0, []
        chi2 = self.config.outlier_chi2  # 0: COLMAP's flat bound, unscaled
        bound = chi2 or self.config.max_reproj_error_px ** 2
        for _ in range(self.config.local_passes - 1):  # ORB-SLAM: adjust, drop the outliers, adjust again
            self._solve_local(slam_map, window)
            removed += remove_outlier_observations(slam_map, window, bound, scaled=chi2 > 0, removed=excluded)
        termination, num_points = self._solve_local(slam_map, window)
        if self.config.confirm_outliers and excluded:
            removed -= restore_observations(slam_map, excluded, bound, scaled=chi2 > 0)
        merged, completed, filtered = self._maintain(slam_map, set(window), min_tri_angle_deg)
        filtered += removed
        return BundleAdjustmentResult("local", len(window), num_points, termination,
                                      merged, completed, filtered, time.perf_counter() - t0, None)

    def _solve_local(self, slam_map: SlamMap, window: list[int]) -> tuple[str, int]:
        """One local BA solve over ``window``; returns (termination, number of the window's points)."""
        c = self.config
        if c.engine == "compiled" and not c.refine_intrinsics and compiled_camera(slam_map) is not None:
            return self._solve_local_compiled(slam_map, window)
        if c.weighting == "level" and not c.refine_intrinsics:
            var, const = self._local_points(slam_map, window)
            gauge = sorted(window)[:2] if len(window) >= slam_map.num_keyframes else ()
            chi2 = c.outlier_chi2 or 5.991
            res = weighted_adjust(slam_map, window, var, const, gauge, c.local_iterations, float(np.sqrt(chi2)),
                                  c.function_tolerance, c.num_threads)
            return res.termination, len(var) + len(const)
        cfg, points = self._local_config(slam_map, window)
        summary = slam_map.bundle_adjust(self._options(c.local_iterations), cfg)
        return str(summary.termination_type).split(".")[-1], len(points)

    def _solve_local_compiled(self, slam_map: SlamMap, window: list[int]) -> tuple[str, int]:
        """:meth:`_solve_local` by the compiled kernel on the map's arrays (``engine`` "compiled")."""
        c = self.config
        problem = local_problem(slam_map, window, c.local_max_track_length)
        if c.weighting == "level":  # ORB-SLAM's: information 1/sigma^2, Huber at sqrt(chi2) on the whitened error
            weight, loss, scale = 1.0 / problem.obs_scale ** 2, "huber", float(np.sqrt(c.outlier_chi2 or 5.991))
        else:  # COLMAP's: every observation alike, the robust loss at 1 px
            weight, loss, scale = None, c.loss, 1.0
        res = local_bundle_adjustment(problem.cam_from_world, problem.points, problem.obs_pose, problem.obs_point,
                                      problem.obs_xy, problem.camera, weight, problem.pose_fixed,
                                      problem.point_fixed, problem.gauge, loss, scale, c.local_iterations,
                                      c.function_tolerance, _COLMAP_SOLVER["parameter_tolerance"],
                                      _COLMAP_SOLVER["gradient_tolerance"], min_depth=_EPS, behind_camera="zero")
        if res.success:
            write_back(slam_map, problem, res.cam_from_world, res.points)
        return res.termination, len(problem.point3D_ids)

    def _local_points(self, slam_map: SlamMap, window: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """The window's points: (variable, held constant: tracks longer than ``local_max_track_length``)."""
        points = np.unique(np.concatenate([slam_map.point3D_ids(i) for i in window]))
        points = points[points >= 0]
        max_track = self.config.local_max_track_length
        if max_track <= 0:
            return points, points[:0]
        point3D = slam_map.reconstruction.point3D
        long = np.array([point3D(int(p)).track.length() > max_track for p in points.tolist()], bool)
        return points[~long], points[long]

    def _local_config(self, slam_map: SlamMap, window: list[int]) -> tuple[pycolmap.BundleAdjustmentConfig, list]:
        """Local BA's problem: the window's keyframes, their points (long tracks held), the gauge when nothing
        outside the window holds it. Returns (config, the window's point ids)."""
        cfg = pycolmap.BundleAdjustmentConfig()
        for i in window:
            cfg.add_image(i)
        points = np.unique(np.concatenate([slam_map.point3D_ids(i) for i in window]))
        points = points[points >= 0].tolist()
        max_track = self.config.local_max_track_length
        point3D = slam_map.reconstruction.point3D
        for p in points:
            # A long-track point is left out of the config: COLMAP then keeps the observations in the
            # window and holds the point constant (its track is not all in the problem). Listing it as a
            # constant point would also add its observations in every other keyframe, residuals with
            # nothing variable that Ceres drops, but only after building them (and destroying them after
            # the solve): on a 3,000-frame revisiting sequence that was most of local BA's time.
            if max_track <= 0 or point3D(p).track.length() <= max_track:
                cfg.add_variable_point(p)
        if not self.config.refine_intrinsics:
            cfg.set_constant_cam_intrinsics(CAMERA_ID)
        if len(window) >= slam_map.num_keyframes:  # nothing outside the window holds the gauge
            cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
        return cfg, points

    def adjust_global(self, slam_map: SlamMap, normalize: bool | None = None,
                      min_tri_angle_deg: float | None = None, refine_focal: bool = False,
                      refine_radial: bool = False) -> BundleAdjustmentResult:
        """Every keyframe, two poses fixed (the gauge). ``refine_focal``: the focal length too (and the principal
        point when the adjuster was made with ``refine_principal_point``); ``refine_radial``: the radial
        coefficient of a SIMPLE_RADIAL map camera (:meth:`SlamMap.use_radial_camera`), with or without the focal
        length."""
        t0 = time.perf_counter()
        rec = slam_map.reconstruction
        cfg = pycolmap.BundleAdjustmentConfig()
        held = held_keyframes(slam_map)
        for i in slam_map.keyframes:
            cfg.add_image(i)
            if i in held:
                cfg.set_constant_rig_from_world_pose(i)
        if not (self.config.refine_intrinsics or refine_focal or refine_radial):
            cfg.set_constant_cam_intrinsics(CAMERA_ID)
        if not held:  # else the held poses are the gauge
            cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
        summary = slam_map.bundle_adjust(self._options(self.config.global_iterations, refine_focal, refine_radial), cfg)
        merged, completed, filtered = self._maintain(slam_map, None, min_tri_angle_deg)
        self._keyframes_at_last_global = slam_map.num_keyframes
        sim = None
        if self.config.normalize if normalize is None else normalize:
            sim = rec.normalize()
            slam_map.moved()
        return BundleAdjustmentResult("global", slam_map.num_keyframes, rec.num_points3D(),
                                      str(summary.termination_type).split(".")[-1], merged, completed, filtered,
                                      time.perf_counter() - t0, sim)

    def _maintain(self, slam_map: SlamMap, image_ids: set[int] | None, min_tri_angle_deg: float | None = None
                  ) -> tuple[int, int, int]:
        """Complete and merge modified tracks, then filter (COLMAP's IterativeLocalRefinement order)."""
        angle = self.config.min_tri_angle_deg if min_tri_angle_deg is None else min_tri_angle_deg
        tri, opts = slam_map.triangulator, slam_map.triangulation
        modified = set(sorted(tri.get_modified_points3D()))  # order independent of the set's history
        completed = tri.complete_tracks(opts, modified) if modified else 0
        merged = tri.merge_tracks(opts, modified) if modified else 0
        tri.clear_modified_points3D()
        slam_map.changed()  # completion and merging changed observations behind the map's back
        obs = slam_map.observations
        max_error, chi2 = self.config.max_reproj_error_px, self.config.outlier_chi2
        removed = 0
        if chi2 > 0:  # per observation at its keypoint's scale; then the angle filter alone
            removed = remove_outlier_observations(slam_map, slam_map.keyframes if image_ids is None else image_ids,
                                                  chi2)
            max_error = 1e6
        if image_ids is None:
            filtered = obs.filter_all_points3D(max_error, angle)
        else:
            filtered = obs.filter_points3D_in_images(max_error, angle, image_ids)
        filtered += removed
        slam_map.changed()
        return merged, completed, filtered


def remove_outlier_observations(slam_map: SlamMap, image_ids, chi2: float, scaled: bool = True,
                                removed: list | None = None) -> int:
    """Remove every observation in ``image_ids`` whose squared reprojection error (pixels) exceeds ``chi2``
    times its keypoint's scale squared (``scaled``; else ``chi2`` flat), or that lies behind its camera
    (ORB-SLAM's outlier classification after BA). A point left with fewer than two observations is deleted
    (COLMAP's ``ObservationManager.delete_observation``). Returns the observations removed; ``removed``, when
    given, gets (image id, point2D index, point3D id) of each. The map's cached point ids must be current
    (:meth:`SlamMap.changed` after changes made outside it)."""
    K = slam_map.pycolmap_camera.calibration_matrix()
    removed_list, removed = removed, 0
    image_ids = [i for i in sorted(int(i) for i in image_ids) if i in slam_map.keyframes]
    pids = np.unique(np.concatenate([slam_map.point3D_ids(i) for i in image_ids] or [np.empty(0, np.int64)]))
    pids = pids[pids >= 0]
    xyz = slam_map.points_xyz(pids)  # each point read once: removing observations moves none
    for image_id in image_ids:
        ids = slam_map.point3D_ids(image_id)  # without the points removed with earlier images' observations
        idx = np.flatnonzero(ids >= 0)
        if not len(idx):
            continue
        kf = slam_map.keyframes[image_id]
        T = slam_map.cam_from_world(image_id).matrix()
        X = xyz[np.searchsorted(pids, ids[idx])] @ T[:, :3].T + T[:, 3]
        z = X[:, 2]
        uv = (X @ K.T)[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None]
        err2 = ((uv - kf.keypoints[idx]) ** 2).sum(axis=1)
        bound = chi2 * (keypoint_scales(kf.features)[idx] ** 2 if scaled else 1.0)
        bad = idx[(err2 > bound) | (z <= 0)]
        for p2 in bad.tolist():
            point3D_id = slam_map.delete_observation(image_id, p2)  # -1: an earlier deletion took its point
            if point3D_id >= 0:
                if removed_list is not None:
                    removed_list.append((image_id, p2, point3D_id))
                removed += 1
    return removed


def held_keyframes(slam_map: SlamMap) -> set[int]:
    """Keyframes bundle adjustment holds constant: a loaded map's (negative frame indices,
    :mod:`slamkit.map_reuse`), as ORB-SLAM3's welding BA holds the old map's keyframes; none in a run of its own."""
    return {i for i, kf in slam_map.keyframes.items() if kf.frame_index < 0}


def restore_observations(slam_map: SlamMap, excluded, chi2: float, scaled: bool = True) -> int:
    """Give back to their points the ``excluded`` observations ((image id, point2D index, point3D id), as
    :func:`remove_outlier_observations` lists them) whose point still exists and whose squared reprojection
    error is now within ``chi2`` (times the keypoint's scale squared when ``scaled``), in front of the camera.
    Returns the observations restored."""
    rec, obs = slam_map.reconstruction, slam_map.observations
    K = slam_map.pycolmap_camera.calibration_matrix()
    restored, scales = 0, {}
    for image_id, p2, point3D_id in excluded:
        if image_id not in slam_map.keyframes or not rec.exists_point3D(point3D_id):
            continue
        point2D = rec.image(image_id).point2D(p2)
        if point2D.has_point3D() or rec.point3D(point3D_id).track.length() < 2:
            continue
        kf = slam_map.keyframes[image_id]
        X = slam_map.cam_from_world(image_id) * rec.point3D(point3D_id).xyz
        if X[2] <= 0:
            continue
        uv = (K @ X)[:2] / X[2]
        if scaled and image_id not in scales:
            scales[image_id] = keypoint_scales(kf.features)
        scale = scales[image_id][p2] if scaled else 1.0
        if float(((uv - kf.keypoints[p2]) ** 2).sum()) <= chi2 * scale ** 2:
            obs.add_observation(point3D_id, pycolmap.TrackElement(image_id, p2))
            restored += 1
    if restored:
        slam_map.changed()
    return restored


def filter_angle_after(starved: bool, local: bool, mapper, local_mapping, ba: BundleAdjustmentConfig) -> float | None:
    """The triangulation angle (degrees) by which the BAs after a new keyframe filter points, or None for
    ``ba.min_tri_angle_deg``: a starving keyframe's smaller angle (either mapper: ``mapper.starved_tri_angle_deg``,
    ``local_mapping.starved_parallax_deg``), else local mapping's parallax floor when it is below BA's angle
    (or BA would delete the points local mapping just made). ``mapper``: a MapperConfig, ``local_mapping``: a
    LocalMappingConfig."""
    if not local:
        return mapper.starved_tri_angle_deg if starved else None
    if starved:
        return local_mapping.starved_parallax_deg
    return local_mapping.min_parallax_deg if local_mapping.min_parallax_deg < ba.min_tri_angle_deg else None

