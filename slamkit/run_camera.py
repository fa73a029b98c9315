"""The camera of a run: which intrinsics it starts with, and self-calibration's hand-offs inside the run.

:func:`choose_camera` picks the camera from the config and the source (the source's calibration, ``--camera``
numbers, another run's ``camera.txt``, or estimated: ``camera="auto"`` or a source without a calibration).
With an estimated camera, :func:`first_estimate` runs :class:`~slamkit.stages.self_calibration.SelfCalibrator`
over the first frames; :func:`clamped` is the focal length (and principal point) the run then uses;
:func:`refines` says whether a bundle adjustment refines it; :func:`refined_camera` takes what a refining BA
found back into the run's camera; and :func:`final_global_ba` is the last global BA of a segment, with one
radial coefficient (COLMAP's SIMPLE_RADIAL) when the main map's camera is estimated. The pipeline keeps only
the calls (:meth:`slamkit.Slam.calibrate`, ``Slam._use_camera``); the estimate itself lives in
:mod:`slamkit.stages.self_calibration`.
"""

from __future__ import annotations

import copy
import math
from dataclasses import replace
from pathlib import Path
from typing import Sequence

from .camera import Intrinsics, focal_range
from .config import SlamConfig, is_camera_path
from .errors import CalibrationError, ConfigError, ImageReadError
from .map import SlamMap, undistort_radial
from .sources import open_source
from .sources.base import CAMERA_IN_SPEC, FrameSource
from .sources.calibration import camera_from_path
from .state import Segment, SlamState
from .stages.ba import BundleAdjuster
from .stages.self_calibration import SelfCalibrator


def open_for_config(spec: str | Path, config: SlamConfig) -> FrameSource:
    """Open the source ``spec`` for a run of ``config`` as every entry point does (``slamkit run``, ``Slam``,
    ``ablate``, the notebook app): the config's camera numbers are applied before it opens (so a TUM folder
    whose name does not say fr1/2/3 opens with them; a synthetic source refuses them, ConfigError
    :data:`~slamkit.sources.base.CAMERA_IN_SPEC`); ``"auto"`` and another run's camera are applied by
    :meth:`slamkit.Slam.reset`, which refuses given numbers for a source opened otherwise in the same words."""
    numbers = config.camera if config.camera and config.camera != "auto" and not is_camera_path(
        config.camera) else None
    return open_source(str(spec), camera=numbers)


def choose_camera(config: SlamConfig, source_camera: Intrinsics,
                  camera_in_spec: bool = False) -> tuple[Intrinsics, str, SelfCalibrator | None]:
    """(camera, how it was obtained, the self-calibrator or None) for a run of ``config`` on a source whose
    calibration is ``source_camera``. An estimated camera starts at the sources' documented guess (no
    distortion is known) until :func:`first_estimate`. ``camera_in_spec``: the source's camera is part of its
    spec (``FrameSource.camera_in_spec``): given intrinsics are refused, ConfigError :data:`CAMERA_IN_SPEC`, the
    words ``open_source`` refuses them in, so a source opened first (``ablate``, the app) is refused as ``run``'s."""
    c = config
    w, h = source_camera.width, source_camera.height
    if camera_in_spec and c.camera and c.camera != "auto" and not is_camera_path(c.camera):
        raise ConfigError(CAMERA_IN_SPEC)  # the words open_source says it in: one rule for every entry point
    if c.camera == "auto" or (not c.camera and source_camera.is_guess):
        return Intrinsics.from_focal(w, h), "estimated", SelfCalibrator(c.self_calibration, c.seed)
    if c.camera and is_camera_path(c.camera):  # a run folder or camera.txt: another run's camera
        return camera_from_path(c.camera, w, h, "camera"), f"from {c.camera}", None
    if c.camera:  # the user's intrinsics instead of the source's
        return Intrinsics.parse(c.camera, w, h), "given (camera=...)", None
    return source_camera, "the source's calibration", None


def first_estimate(cal: SelfCalibrator, source, indices: Sequence[int], camera: Intrinsics) -> Intrinsics:
    """Self-calibration's first phase: ``camera`` with the focal length (pixels) from the first
    ``window_frames`` frames of ``indices`` (unreadable ones left to the run, which skips them with their
    reason) and the radial coefficient found with it (``first_radial``: the keypoints are undistorted with it
    from now on); a weak estimate falls back to ``fallback_fov_deg`` (or the sources' guess when it is 0),
    without distortion."""
    for cursor in range(min(len(indices), cal.config.window_frames)):
        try:
            frame = source[int(indices[cursor])]
        except (ImageReadError, CalibrationError):
            continue
        cal.step(frame.gray)
    w, h, fov = camera.width, camera.height, cal.config.fallback_fov_deg
    guess = Intrinsics.from_focal(w, h).fx if not fov else max(w, h) / 2 / math.tan(math.radians(fov / 2))
    cal.estimate(guess)
    return with_radial(clamped(camera, float(cal.focal)), cal.k1)


def with_radial(camera: Intrinsics, k1: float) -> Intrinsics:
    """``camera`` with the one radial coefficient ``k1`` (OpenCV's, at its focal length) and no other."""
    return replace(camera, dist=(float(k1), 0.0, 0.0, 0.0, 0.0))


def clamped(camera: Intrinsics, focal: float, cx: float | None = None, cy: float | None = None) -> Intrinsics:
    """``camera`` with one focal length for both axes (kept inside the sane range of
    :func:`~slamkit.camera.focal_range`) and, when given, a new principal point. A radial coefficient ``k1``
    scales with the focal length squared, so the keypoints are undistorted to the same pixels as before (the
    map's keypoints and the next frames' agree)."""
    lo, hi = focal_range(camera.width, camera.height)
    focal = min(max(float(focal), lo * 1.001), hi * 0.999)
    out = replace(camera, fx=focal, fy=focal, cx=camera.cx if cx is None else float(cx),
                  cy=camera.cy if cy is None else float(cy))
    return with_radial(out, camera.dist[0] * (focal / camera.fx) ** 2) if camera.dist[0] else out


def refines(cal: SelfCalibrator | None, slam_map: SlamMap, final: bool = False) -> bool:
    """Whether a BA of ``slam_map`` refines the focal length (self-calibration's second phase)."""
    return cal is not None and cal.refining(slam_map.num_keyframes, final)


def refined_camera(camera: Intrinsics, slam_map: SlamMap, k1: float = 0.0) -> Intrinsics:
    """After a refining BA (its map's camera PINHOLE again): one focal length for both axes, written back to
    the map, with the radial coefficient ``k1`` the final BA estimated on the keypoints (already undistorted
    with the camera's own ``k1``: to first order the two add up), which the run's camera carries
    (``camera.txt``, export, ``--camera RUN_DIR``; no frame is read after the final BA)."""
    fx, fy, cx, cy = (float(v) for v in slam_map.pycolmap_camera.params)
    camera = clamped(camera, 0.5 * (fx + fy), cx, cy)
    slam_map.set_focal(camera.fx)
    return with_radial(camera, camera.dist[0] + k1) if k1 else camera


def use_radial(seg: Segment, max_radial: float) -> float | None:
    """After the final BA estimated ``k1`` in ``seg``'s SIMPLE_RADIAL camera: the map is PINHOLE again with
    undistorted keypoints, and so are the frames still to be tracked again (``initial_frames``); returns
    ``k1`` (0 when negligible). None (camera PINHOLE again, nothing else changed) when ``|k1|`` is beyond
    ``max_radial``."""
    radial = copy.copy(seg.slam_map.pycolmap_camera)  # the map's own is replaced by its PINHOLE part below
    if abs(float(radial.params[3])) > max_radial:
        seg.slam_map.drop_radial()
        return None
    k1 = seg.slam_map.undistort_observations()
    if k1:
        seg.initial_frames = [replace(f, keypoints=undistort_radial(radial, f.keypoints))
                              for f in seg.initial_frames]
    return k1


def final_global_ba(state: SlamState, seg: Segment, adjuster: BundleAdjuster, refine: bool, radial: bool,
                    max_radial: float) -> tuple[float, float]:
    """The last global BA of ``seg`` (normalization applied to the state's frame poses); with ``refine`` it
    refines the focal length, with ``radial`` one radial coefficient (with the focal length or alone: a given
    camera's, :func:`calibrate_radial`; a pinhole BA again when that coefficient is beyond ``max_radial``). Returns (the focal length the map was built with, k1 or 0)."""
    before = float(seg.slam_map.pycolmap_camera.params[0])
    if radial:
        seg.slam_map.use_radial_camera()
    bres = adjuster.adjust_global(seg.slam_map, refine_focal=refine, refine_radial=radial)
    if bres.normalization is not None:
        state.apply_normalization(seg, float(bres.normalization.scale))
    k1 = use_radial(seg, max_radial) if radial else 0.0
    if k1 is None:  # an implausible k1: a pinhole BA instead
        k1, bres = 0.0, adjuster.adjust_global(seg.slam_map, refine_focal=refine)
        if bres.normalization is not None:
            state.apply_normalization(seg, float(bres.normalization.scale))
    return before, float(k1)


def radial_due(cal: SelfCalibrator | None, camera: Intrinsics, slam_map: SlamMap, config: SlamConfig) -> bool:
    """Whether :func:`calibrate_radial` follows this BA of ``slam_map``: the camera is given (no
    self-calibration) with one focal length (COLMAP's SIMPLE_RADIAL has one), and the map has just reached
    ``ba.radial_keyframes`` keyframes (0: never)."""
    keyframes = config.ba.radial_keyframes
    return (cal is None and keyframes > 0 and slam_map.num_keyframes == keyframes
            and abs(camera.fx / camera.fy - 1) < 1e-6)


def calibrate_radial(state: SlamState, seg: Segment, adjuster: BundleAdjuster, camera: Intrinsics,
                     config: SlamConfig) -> Intrinsics:
    """The radial distortion a given camera's calibration leaves in the images: one global BA of ``seg`` with
    SIMPLE_RADIAL, focal length and principal point held, estimates ``k1``; the map's keypoints (and the
    frames to track again) are undistorted with it. Returns ``camera`` with ``k1`` added to its own first
    coefficient (to first order the two add up), so that the next frames' keypoints are undistorted too; the
    camera unchanged when ``k1`` moves no pixel or is beyond ``self_calibration.max_radial``."""
    _, k1 = final_global_ba(state, seg, adjuster, False, True, config.self_calibration.max_radial)
    return replace(camera, dist=(camera.dist[0] + k1, *camera.dist[1:])) if k1 else camera


def camera_report(camera: Intrinsics, origin: str, cal: SelfCalibrator | None) -> dict:
    """The camera used and how it was obtained (with self-calibration: its estimate, uncertainty and
    history), JSON-serialisable."""
    out = {**camera.to_dict(), "origin": origin, "description": describe_camera(camera, origin, cal)}
    if cal is not None:
        out["self_calibration"] = {**cal.state(), "weak": cal.weak}
    return out


def describe_camera(camera: Intrinsics, origin: str, cal: SelfCalibrator | None) -> str:
    """One line: the intrinsics used and where they come from."""
    how = cal.describe() if cal is not None else origin
    return f"fx={camera.fx:.1f} fy={camera.fy:.1f} cx={camera.cx:.1f} cy={camera.cy:.1f}, {how}"


__all__ = ["open_for_config", "choose_camera", "first_estimate", "with_radial", "clamped", "refines", "refined_camera", "use_radial",
           "final_global_ba", "radial_due",
           "calibrate_radial", "camera_report", "describe_camera"]
