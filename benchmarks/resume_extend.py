"""Extending a finished run with ``--resume`` (issue 28): ATE of (M frames, then resumed to N) against fresh
N-frame runs, over seeds, through :func:`slamkit.runner.run_to_folder` (the library behind ``slamkit run``).

    PYTHONPATH=. python benchmarks/resume_extend.py default ../shared/data/7scenes-redkitchen \\
        --seeds 0 1 2 3 4 --first 40 --frames 50 --work /tmp/resume_extend

Prints one line per (source, seed) and, per source, the mean ATE and its standard error for both, and how many
resumed trajectories equal the fresh one bit for bit.
"""

from __future__ import annotations

import argparse
import math
import shutil
from pathlib import Path

import numpy as np
import pycolmap

from slamkit.config import SlamConfig
from slamkit.io import read_tum
from slamkit.runner import run_to_folder


def _ate(out: Path) -> float:
    from slamkit.eval import evaluate

    return float(evaluate(out / "trajectory_tum.txt", out / "groundtruth_tum.txt")["ate"]["rmse"])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sources", nargs="+")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    p.add_argument("--first", type=int, default=40)
    p.add_argument("--frames", type=int, default=50)
    p.add_argument("--preset", default="default")
    p.add_argument("--work", default="/tmp/resume_extend")
    a = p.parse_args()
    pycolmap.logging.minloglevel = 2
    work = Path(a.work)
    for source in a.sources:
        fresh, resumed, same = [], [], 0
        for seed in a.seeds:
            cfg = SlamConfig.preset(a.preset).with_overrides(seed=seed)
            f_dir, r_dir = work / f"{Path(source).name}-{seed}-fresh", work / f"{Path(source).name}-{seed}-resumed"
            for d in (f_dir, r_dir):
                shutil.rmtree(d, ignore_errors=True)
            run_to_folder(source, f_dir, cfg.with_overrides(max_frames=a.frames))
            run_to_folder(source, r_dir, cfg.with_overrides(max_frames=a.first))
            run_to_folder(source, r_dir, resume=True, resume_overrides={"max_frames": a.frames})
            fa, ra = _ate(f_dir), _ate(r_dir)
            eq = np.array_equal(read_tum(f_dir / "trajectory_tum.txt").poses, read_tum(r_dir / "trajectory_tum.txt").poses)
            same += eq
            fresh.append(fa)
            resumed.append(ra)
            print(f"{source} seed {seed}: fresh {a.frames} frames ATE {100 * fa:.3f} cm; {a.first} then resumed to "
                  f"{a.frames}: {100 * ra:.3f} cm; bit-identical: {eq}", flush=True)
        se = lambda x: float(np.std(x, ddof=1) / math.sqrt(len(x))) if len(x) > 1 else float("nan")  # noqa: E731
        print(f"{source}: fresh {100 * np.mean(fresh):.3f} ± {100 * se(fresh):.3f} cm (standard error), resumed "
              f"{100 * np.mean(resumed):.3f} ± {100 * se(resumed):.3f} cm, {same}/{len(a.seeds)} bit-identical",
              flush=True)


if __name__ == "__main__":
    main()
