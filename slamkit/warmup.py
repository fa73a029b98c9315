"""Compile slamkit's numba kernels once per install: ``python -m slamkit.warmup`` (``make install`` runs it).

Every kernel (descriptor matching, the epipolar search, pose optimization, loop verification, local BA) is
``@njit(cache=True)``: numba compiles it at its first call and writes the machine code beside its source
(``__pycache__/*.nbi``, ``*.nbc``), where every later process finds it. Without this step the first run after an
install spends about a minute compiling, and says nothing. The warm-up runs the pipeline on a short rendered
sequence (which calls every kernel of tracking and mapping with the types a real run uses), then on random
geometry loop verification (a short sequence closes no loop), the pose optimizations and the compiled local
bundle adjustment with each of its losses, with and without per-observation weights (the default
``ba.engine`` and ``tracker.pose_optimizer`` are Ceres, so the run calls neither); its own timing is printed.
"""

from __future__ import annotations

import time

import numpy as np


def warm_up(frames: int = 30) -> float:
    """Call every numba kernel once (compiling and caching it when no cache is there); seconds taken."""
    from .config import SlamConfig
    from .kernels.absolute_pose import refine_absolute_pose
    from .loop_verification import LoopVerificationConfig, verify_loop_by_reprojection
    from .pipeline import Slam
    from .pose_optimization import optimize_pose
    from .sources import open_source

    import pycolmap  # after slamkit (slamkit/__init__.py says why)

    pycolmap.logging.minloglevel = 2
    t = time.perf_counter()
    Slam(open_source(f"synthetic:handheld?frames={int(frames)}"), SlamConfig()).run()
    rng = np.random.default_rng(0)
    n = 40
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    points = rng.normal(size=(n, 3)) + [0.0, 0.0, 5.0]
    xy, scales = rng.uniform(0, 480, (n, 2)), np.ones(n)
    verify_loop_by_reprojection(K, points, np.eye(4), xy, scales, points, np.eye(4), xy, scales,
                                LoopVerificationConfig(max_trials=20))
    optimize_pose(np.eye(4), xy, points, scales ** 2, K)
    refine_absolute_pose(np.eye(4), xy, points, np.ones(n, bool), (500.0, 500.0, 320.0, 240.0))
    _warm_up_local_ba(rng)
    return time.perf_counter() - t


def _warm_up_local_ba(rng: np.random.Generator) -> None:
    """:func:`slamkit.kernels.local_ba.local_bundle_adjustment` on three keyframes seeing 20 points, as
    ``stages.ba`` calls it, once per loss, without weights (COLMAP's) and with them (ORB-SLAM's levels)."""
    from .kernels.local_ba import LOSSES, local_bundle_adjustment

    points = rng.normal(size=(20, 3)) + [0.0, 0.0, 5.0]
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, -0.1, -0.2]
    obs_pose, obs_point = np.repeat(np.arange(3), 20), np.tile(np.arange(20), 3)
    camera = np.array([500.0, 500.0, 320.0, 240.0])
    xc = points[obs_point] + poses[obs_pose, :3, 3]
    xy = camera[:2] * xc[:, :2] / xc[:, 2:] + camera[2:] + rng.normal(scale=0.5, size=(60, 2))
    pose_fixed = np.array([True, False, False])
    for loss in LOSSES:
        for weight in (None, 1.0 / 1.2 ** (2 * rng.integers(0, 8, 60))):
            local_bundle_adjustment(poses, points, obs_pose, obs_point, xy, camera, weight, pose_fixed,
                                    np.zeros(20, bool), (1, 0), loss, 1.0, 3, 1e-6, 0.0, 1e-4,
                                    min_depth=float(np.finfo(np.float64).eps), behind_camera="zero")


def main() -> None:
    print("slamkit: compiling the numba kernels, once per install (about a minute) ...", flush=True)
    print(f"slamkit: kernels compiled and cached in {warm_up():.0f} s")


if __name__ == "__main__":
    main()
