"""Self-calibration: the focal length of an unknown camera, from the first frames and then the map.

For videos and image folders without a calibration (``--camera auto``, the default when none is given or
found). Two phases:

1. **Before initialization** (:meth:`SelfCalibrator.step` on the first ``window_frames`` frames, then
   :meth:`SelfCalibrator.estimate`): corners are tracked through the window with pyramidal Lucas-Kanade
   (forward-backward checked), so any feature type works. Frame pairs far enough apart get a fundamental
   matrix F (MAGSAC, then least squares on its inliers, which halves the bias of RANSAC's F on rendered
   sequences); with the principal point at the image centre and square pixels, the right focal length
   ``f`` makes ``E = K^T F K`` an essential matrix, whose two non-zero singular values are equal (Mendonca
   and Cipolla 1999). Each pair's cost ``(s1 - s2) / (s1 + s2)`` is summed over a logarithmic grid of
   focal lengths; the minimum is the estimate. Before that, one radial distortion coefficient is chosen
   (``first_radial``): the one whose undistorted corners fit the pairs' fundamental matrices best (smallest
   Sampson error, measured in the images' pixels), and the corners are undistorted with it; a pinhole model
   would absorb the distortion into the focal length (a rendered k1 = 0.25 gave 7-23 % short, k1 = -0.1
   9-20 % long). Its uncertainty is the spread over pairs resampled with
   replacement in blocks of 10 frames (bootstrap), combined with a model error calibrated on rendered
   cameras; the ``± x %`` shown is twice that, and covers the true focal length in at least 90 % of the
   rendered cases measured (a weak estimate shows none). Pairs explained as well by a homography (rotation
   about the centre, or a plane), and pairs whose optical axes meet (circling what the camera looks at), say
   nothing about ``f`` through F and are left out. When that leaves the estimate weak, the frame pairs that
   a rotation explains (a camera that mostly turns) give it instead, through the infinite homography
   (:mod:`~slamkit.stages.self_calibration.rotation`, ``rotation_min_flow``; :attr:`FocalEstimate.model`).
2. **While mapping** (:meth:`SelfCalibrator.refining`, :meth:`SelfCalibrator.refined`): the final global
   bundle adjustment refines the focal length with the whole map (COLMAP's ``refine_focal_length``), and one
   radial distortion coefficient with it (``refine_radial``: a SIMPLE_RADIAL camera for that BA); after
   a weak first estimate, every keyframe's BA does from ``min_refine_keyframes`` to ``refine_keyframes``
   keyframes. An estimate from the first frames that is not weak stays fixed while tracking: refined at
   every keyframe, the focal length of a forward-moving map wanders by percents and tracking is lost.

Degenerate motions: pure translation (driving straight ahead, a forward walk) gives an F that is
skew-symmetric for every focal length, and pure rotation gives a homography, which says nothing about ``f``
through F; turns with translation, and many views in BA, fix it. A rotation's homography ``K R K^-1`` does fix
``f`` (Hartley 1997), when the camera turns far enough: the rotation estimate above. A window with none of
these yields a **weak** estimate (:attr:`FocalEstimate.weak` with its reason) rather than a confident wrong
one; BA may still fix it later.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .corner_tracks import track_corners
from .epipolar import (BLOCK_FRAMES, COVERAGE, MIN_AXIS_GAP, MIN_RADIAL_GAIN, MODEL_ERROR, FocalEstimate,
                       SelfCalibrationConfig, axis_gap, choose_pairs, choose_radial, essential_cost, focal_from_costs,
                       focal_grid, pair_costs, radial_candidates, undistort_half)
from .rotation import ROTATION_MODEL_ERROR, estimate_rotation, rotation_errors


def estimate_focal(grays: list[np.ndarray], config: SelfCalibrationConfig = SelfCalibrationConfig(),
                   seed: int = 0) -> FocalEstimate:
    """The focal length of the camera of ``grays`` (consecutive grey frames), principal point at the centre;
    see the module docstring. When that is weak, the pairs a rotation explains (``rotation_min_flow``)."""
    tracks = track_corners(grays)
    pairs, costs, grid, gaps, radial = pair_costs(grays, config, tracks)
    est = focal_from_costs(pairs, costs, grid, gaps, len(grays), config, seed)
    if radial and math.isfinite(est.focal):  # OpenCV's k1 at the estimated focal length
        est = replace(est, k1=radial * (est.focal / (max(grays[0].shape[:2]) / 2.0)) ** 2)
    if est.weak and config.rotation_min_flow:
        turned = estimate_rotation(grays, config, seed, tracks)
        return turned if not turned.weak else replace(est, reason=f"{est.reason}; from rotation: {turned.reason}")
    return est


WEAK_FALLBACK_UNCERTAINTY = 0.2
"""A weak estimate more uncertain than this (or outside the range searched) is not used: the run starts from
``fallback_fov_deg`` and bundle adjustment refines from there."""


@dataclass(frozen=True)
class CalibrationStep:
    """The focal length after one keyframe's bundle adjustment (for plots of the estimate converging)."""

    num_keyframes: int
    focal: float


class SelfCalibrator:
    """The two phases of the module docstring for one run: :meth:`step` collects the first frames,
    :meth:`estimate` gives the starting focal length, then :meth:`refining` says whether a keyframe's bundle
    adjustment refines it, and :meth:`refined` records the result until :attr:`frozen`."""

    def __init__(self, config: SelfCalibrationConfig = SelfCalibrationConfig(), seed: int = 0):
        config.validate()
        self.config, self.seed = config, seed
        self.grays: list[np.ndarray] = []
        self.initial: FocalEstimate | None = None
        """The estimate from the first frames (phase 1), once made."""
        self.focal: float | None = None
        """The focal length in use (pixels)."""
        self.k1 = 0.0
        """The radial distortion coefficient in use (OpenCV's ``k1`` at :attr:`focal`): the first frames' estimate
        (``first_radial``), then what the final BA added to it (``refine_radial``)."""
        self.unsettled = ""
        """Why the final BA's focal length is not believed ("" when it is): ``max_final_change``."""
        self.history: list[CalibrationStep] = []
        self.frozen = False

    def step(self, gray: np.ndarray) -> bool:
        """Take the next frame of the window (grey); True when the window is full."""
        if len(self.grays) < self.config.window_frames:
            self.grays.append(gray)
        return len(self.grays) >= self.config.window_frames

    def estimate(self, guess: float) -> FocalEstimate:
        """Phase 1 over the frames given to :meth:`step`; :attr:`focal` becomes the estimate, or ``guess``
        when it is too weak to use (:data:`WEAK_FALLBACK_UNCERTAINTY`)."""
        if len(self.grays) < 2:
            est = FocalEstimate(float("nan"), math.inf, 0, len(self.grays), True, "fewer than 2 frames")
        else:
            est = estimate_focal(self.grays, self.config, self.seed)
        self.grays = []
        self.initial = est
        usable = math.isfinite(est.focal) and est.uncertainty <= WEAK_FALLBACK_UNCERTAINTY and (
            "end of the range" not in est.reason)
        self.focal = est.focal if usable else float(guess)
        self.k1 = est.k1 if usable else 0.0
        self.history = [CalibrationStep(0, self.focal)]
        self.frozen = False
        return est

    @property
    def used_initial(self) -> bool:
        """Whether the run started from the first frames' estimate (else from the guess)."""
        return self.initial is not None and len(self.history) > 0 and self.history[0].focal == self.initial.focal

    def refining(self, num_keyframes: int, final: bool = False) -> bool:
        """Whether a bundle adjustment of a map of ``num_keyframes`` refines the focal length: while
        tracking only when the first frames gave no usable estimate, until ``refine_keyframes``; the
        ``final`` global BA when ``refine_final``."""
        if num_keyframes < self.config.min_refine_keyframes or self.initial is None:
            return False
        if final:
            return self.config.refine_final
        return not self.frozen and not (self.used_initial and not self.initial.weak)

    def refined(self, focal: float, num_keyframes: int, final: bool = False, k1: float = 0.0,
                before: float | None = None) -> None:
        """Record the focal length (and the radial coefficient ``k1`` of the final BA) after a refining
        bundle adjustment; refinement while tracking stops from ``refine_keyframes`` on, and after the
        ``final`` one. ``before``: the focal length the final BA started from (the main map's)."""
        if final and before and abs(focal / before - 1) > self.config.max_final_change:
            self.unsettled = (f"the final bundle adjustment moved it from {before:.0f} to {focal:.0f} px: the "
                              "map does not settle the focal length")
        self.focal = float(focal)
        self.k1 = float(k1)
        self.history.append(CalibrationStep(int(num_keyframes), self.focal))
        if final or num_keyframes >= self.config.refine_keyframes:
            self.frozen = True

    @property
    def weak(self) -> bool:
        """The estimate is weak: phase 1 was, and bundle adjustment has not refined it over at least
        ``min_refine_keyframes`` keyframes; or the final BA moved it too far (:attr:`unsettled`)."""
        return self.initial is None or (self.initial.weak and len(self.history) <= 1) or bool(self.unsettled)

    def describe(self) -> str:
        """One line: the focal length in use and how it was obtained."""
        if self.initial is None:
            return "to be estimated from the first frames"
        est = self.initial
        first = est.describe() if math.isfinite(est.focal) else f"no estimate (weak: {est.reason})"
        if len(self.history) <= 1:
            used = "" if self.focal == est.focal else f"; not used: starting from f={self.focal:.1f} px"
            return f"estimated {first}{used}"
        n = self.history[-1].num_keyframes
        state = "frozen" if self.frozen else "refining"
        radial = f", k1={self.k1:.4f}" if self.k1 else ""
        weak = f" (weak: {self.unsettled})" if self.unsettled else ""
        return (f"estimated f={self.focal:.1f} px{radial}{weak} (bundle adjustment over {n} keyframes, {state}; "
                f"first frames: {first})")

    def state(self) -> dict:
        """What a session saves."""
        est = self.initial
        return {"initial": None if est is None else {
                    "focal": _finite(est.focal), "uncertainty": None if est.weak else _finite(est.uncertainty),
                    "interval": None if est.weak else _finite(est.interval), "num_pairs": est.num_pairs,
                    "num_frames": est.num_frames, "weak": est.weak, "reason": est.reason, "k1": est.k1,
                    "model": est.model},
                "focal": self.focal, "k1": self.k1, "unsettled": self.unsettled, "frozen": self.frozen,
                "history": [[s.num_keyframes, s.focal] for s in self.history]}

    def restore(self, state: dict) -> None:
        init = state.get("initial")
        self.initial = None if init is None else FocalEstimate(
            _number(init["focal"], math.nan), _number(init["uncertainty"], math.inf), int(init["num_pairs"]),
            int(init["num_frames"]), bool(init["weak"]), str(init["reason"]),
            k1=float(init.get("k1", 0.0)), model=str(init.get("model", "epipolar")))  # older sessions: neither
        self.focal = None if state.get("focal") is None else float(state["focal"])
        self.k1 = float(state.get("k1", 0.0))  # sessions before the radial coefficient: none
        self.unsettled = str(state.get("unsettled", ""))
        self.frozen = bool(state.get("frozen", False))
        self.history = [CalibrationStep(int(k), float(f)) for k, f in state.get("history", [])]
        self.grays = []


def _finite(x: float) -> float | None:
    """``x``, or None when it is not finite (strict JSON has no inf or NaN)."""
    return float(x) if math.isfinite(x) else None


def _number(x: float | None, default: float) -> float:
    return default if x is None else float(x)


__all__ = ["SelfCalibrator", "SelfCalibrationConfig", "FocalEstimate", "CalibrationStep", "estimate_focal",
           "estimate_rotation", "track_corners", "pair_costs", "focal_from_costs", "focal_grid", "essential_cost",
           "axis_gap", "choose_pairs", "choose_radial", "radial_candidates", "undistort_half", "rotation_errors",
           "BLOCK_FRAMES", "COVERAGE", "MIN_AXIS_GAP", "MIN_RADIAL_GAIN", "MODEL_ERROR", "ROTATION_MODEL_ERROR",
           "WEAK_FALLBACK_UNCERTAINTY"]
