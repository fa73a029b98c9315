"""Local BA weighted by each keypoint's pyramid level (``ba.weighting = "level"``, issue 39), against exact geometry.

Eight keyframes 0.25 m apart look at 1,000 known points; every keypoint sits at its exact projection plus
noise of 1.2^octave px per axis, its octave drawn per observation (a point is seen at different levels from
different keyframes, as the camera moves). The newest keyframe's local BA (window of five, the three oldest
keyframes held at their true poses, so both solutions share the gauge) is run with COLMAP's BA (every
observation alike, soft L1 at 1 px: the default) and with ORB-SLAM's weighting (information 1/sigma^2, Huber
at sqrt(5.991) on the whitened error).
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from conftest import pyramid_noise_map

from slamkit.config import SlamConfig
from slamkit.errors import ConfigError
from slamkit.stages.ba import BundleAdjuster, BundleAdjustmentConfig

pycolmap.logging.minloglevel = 2
SEEDS = range(6)


def _adjusted(weighting: str, seed: int) -> tuple[float, float]:
    """(RMS point error m, mean position error of the adjusted keyframes m) after the newest keyframe's local BA."""
    slam_map, X, poses, _ = pyramid_noise_map(num_keyframes=8, n=1000, seed=seed, per_observation=True)
    before = {i: slam_map.cam_from_world(i).matrix() for i in slam_map.keyframes}
    ba = BundleAdjuster(BundleAdjustmentConfig(local_window=4, outlier_chi2=0.0, local_passes=1, min_tri_angle_deg=0.0,
                                               max_reproj_error_px=1e9, normalize=False, weighting=weighting))
    ba.adjust_local(slam_map, max(slam_map.keyframes))
    ids = np.array(sorted(slam_map.reconstruction.points3D))
    point_rms = float(np.sqrt(np.mean(np.sum((slam_map.points_xyz(ids) - X[ids - 1]) ** 2, axis=1))))
    moved = [i for i in slam_map.keyframes if not np.allclose(slam_map.cam_from_world(i).matrix(), before[i])]
    assert len(moved) == 5  # the window: the newest and its four most covisible keyframes
    position = np.mean([np.linalg.norm(slam_map.cam_from_world(i).matrix()[:, 3] - poses[i - 1][:3, 3])
                        for i in moved])
    return point_rms, float(position)


def test_level_weighted_ba_recovers_points_and_poses_closer_to_the_truth():
    """Measured over 6 seeds: point RMS 6.0-6.3 cm weighted against 7.0-7.5 cm (13-17 % closer in every seed);
    keyframe positions 1.20 cm against 1.36 cm on average (closer in 5 seeds of 6)."""
    flat = np.array([_adjusted("none", s) for s in SEEDS])
    weighted = np.array([_adjusted("level", s) for s in SEEDS])
    assert np.all(weighted[:, 0] < 0.92 * flat[:, 0])  # every seed's points at least 8 % closer
    assert weighted[:, 1].mean() < 0.95 * flat[:, 1].mean()  # poses closer on average
    assert (weighted[:, 1] < flat[:, 1]).sum() >= 4


def test_weighted_solve_moves_nothing_held_and_keeps_rotations_rigid():
    """The gauge (nothing outside the window) holds the two oldest keyframes; every adjusted rotation stays a
    rotation (the quaternion's unit-norm residual)."""
    slam_map, _, poses, _ = pyramid_noise_map(num_keyframes=4, n=300, seed=3, per_observation=True)
    ba = BundleAdjuster(BundleAdjustmentConfig(local_window=6, outlier_chi2=0.0, local_passes=1, min_tri_angle_deg=0.0,
                                               max_reproj_error_px=1e9, normalize=False, weighting="level",
                                               engine="ceres"))  # slamkit.weighted_ba (pyceres), its gauge
    res = ba.adjust_local(slam_map, 4)
    assert res.termination == "CONVERGENCE"
    for i in (1, 2):
        assert np.allclose(slam_map.cam_from_world(i).matrix(), poses[i - 1][:3], atol=1e-12)
    for i in (3, 4):
        R = slam_map.cam_from_world(i).matrix()[:, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-9)
        assert 0 < np.linalg.norm(slam_map.cam_from_world(i).matrix()[:, 3] - poses[i - 1][:3, 3]) < 0.05


def test_weighting_is_a_checked_option_and_the_default_is_colmaps():
    """Level weighting lost on the real rows (7-Scenes, KITTI: benchmarks/HISTORY.md), so it is an option."""
    assert SlamConfig().ba.weighting == "none"
    assert SlamConfig().with_overrides(**{"ba.weighting": "level"}).ba.weighting == "level"
    with pytest.raises(ConfigError, match="ba.weighting"):
        BundleAdjustmentConfig(weighting="octave").validate()


def test_importing_the_pipeline_leaves_sigterm_to_terminate_quietly():
    """pyceres' import installs glog's failure handler for SIGTERM (a stack trace on stderr); slamkit puts the
    default back, so a worker stopped by its parent ends with SIGTERM's status and says nothing."""
    code = "import os, signal, slamkit.pipeline, slamkit.weighted_ba; os.kill(os.getpid(), signal.SIGTERM)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == -signal.SIGTERM, proc.stderr[-2000:]
    assert b"stack trace" not in proc.stderr and b"SIGTERM" not in proc.stderr, proc.stderr[-2000:]
