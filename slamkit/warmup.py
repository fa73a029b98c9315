"""Compile slamkit's numba kernels once per install: ``python -m slamkit.warmup`` (``make install`` runs it).

Every kernel (descriptor matching, the epipolar search, pose optimization, loop verification) is
``@njit(cache=True)``: numba compiles it at its first call and writes the machine code beside its source
(``__pycache__/*.nbi``, ``*.nbc``), where every later process finds it. Without this step the first run after an
install spends about a minute compiling, and says nothing. The warm-up runs the pipeline on a short rendered
sequence (which calls every kernel of tracking and mapping with the types a real run uses) and loop
verification on random geometry (a short sequence closes no loop); its own timing is printed.
"""

from __future__ import annotations

import time

import numpy as np


def warm_up(frames: int = 30) -> float:
    """Call every numba kernel once (compiling and caching it when no cache is there); seconds taken."""
    from .config import SlamConfig
    from .loop_verification import LoopVerificationConfig, verify_loop_by_reprojection
    from .pipeline import Slam
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
    return time.perf_counter() - t


def main() -> None:
    print("slamkit: compiling the numba kernels, once per install (about a minute) ...", flush=True)
    print(f"slamkit: kernels compiled and cached in {warm_up():.0f} s")


if __name__ == "__main__":
    main()
