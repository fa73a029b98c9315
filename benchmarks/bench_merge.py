"""Map merging benchmark (issue 18): a sequence that loses tracking and then comes back to where it was.

Each case plays frames of a sequence in the order first visit -> ``gap`` unrelated frames -> second visit
starting inside the first visit's stretch. The gap frames are blurred noise (a covered lens, a view of
nothing the map knows): tracking is lost for ``gap`` >= ``max_lost_frames`` frames (30 by default), so the
pipeline ends the map segment and initializes a new one, and the second visit then passes places of the
first. Without loop closing the run ends in two segments; with it (the default) the second segment should
recognise the first visit's place and be merged into it.

Cases (:data:`CASES`):

* ``7scenes-revisit``: 7-Scenes redkitchen frames 0-299, 35 gap frames, frames 150-449 (real images and
  ground truth; ``../shared/data/7scenes-redkitchen``; skipped with a reason when absent);
* ``synthetic-revisit``: the synthetic room's hand-held motion (``synthetic:handheld?frames=300&seed=S``)
  frames 0-149, 35 gap frames, frames 75-299 (exact ground truth).

Every frame gets a new timestamp (its position / 30 s), so a place visited twice is two frames of the
trajectory; ground truth follows the same order. Columns, per case and loop-closing setting (mean ± standard
error over the seeds, ``SlamConfig.seed``; for the synthetic case also the motion's seed): frames; posed (%):
frames with a pose in any segment; segments at the end; largest (%): frames of the largest segment; ATE (m)
of the largest segment (Sim(3), as evo ``evo_ape -as``); merges (``summary()["merges"]``).

Usage::

    PYTHONPATH=$PWD nice -n 5 .venv/bin/python benchmarks/bench_merge.py              # both cases, 3 seeds
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_merge.py --cases synthetic-revisit --seeds 1

Output: a Markdown table on stdout and ``benchmarks/results/bench_merge.csv`` (one row per run).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import csv  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from slamkit.config import SlamConfig  # noqa: E402
from slamkit.eval.metrics import ate  # noqa: E402
from slamkit.pipeline import Slam  # noqa: E402
from slamkit.sources import open_source  # noqa: E402
from slamkit.sources.base import FrameSource  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RESULTS = REPO / "benchmarks" / "results"
GAP = 35
"""Unrelated frames between the two visits (> the default ``max_lost_frames`` of 30)."""
CASES = {
    "7scenes-revisit": {"spec": str(DATA / "7scenes-redkitchen"), "kw": {"max_frames": 450},
                        "order": [*range(0, 300), *([-1] * GAP), *range(150, 450)]},
    "synthetic-revisit": {"spec": "synthetic:handheld?frames=300&seed={seed}", "kw": {},
                          "order": [*range(0, 150), *([-1] * GAP), *range(75, 300)]},
}


class Revisit(FrameSource):
    """Frames of ``base`` in the order ``order`` (-1: a gap frame of blurred noise), timestamps i / 30 s."""

    def __init__(self, base: FrameSource, order: list[int]):
        self.base, self.order = base, np.asarray(order, np.int64)
        self.name, self.camera = f"{base.name} (revisit)", base.camera
        self.timestamps = np.arange(len(order)) / 30.0
        self.frame_ids = np.arange(len(order), dtype=np.int64)
        gt = np.full((len(order), 4, 4), np.nan)
        if base.gt_poses is not None:
            gt[self.order >= 0] = base.gt_poses[self.order[self.order >= 0]]
        self.gt_poses = gt

    def _read(self, i: int):
        if self.order[i] >= 0:
            return self.base._read(int(self.order[i]))
        noise = np.random.default_rng(i).integers(0, 256, (self.camera.height, self.camera.width), dtype=np.uint8)
        return cv2.GaussianBlur(noise, (5, 5), 1.5), None


def run_one(case: str, seed: int, loop_closing: bool) -> dict:
    c = CASES[case]
    base = open_source(c["spec"].format(seed=seed), **c["kw"])
    source = Revisit(base, c["order"])
    config = SlamConfig(seed=seed).with_overrides(**{"loop_closing.enabled": loop_closing})
    t = time.perf_counter()
    slam = Slam(source, config)
    slam.run()
    s = slam.summary()
    traj = slam.trajectory()
    n = len(source)
    return {"case": case, "seed": seed, "loop_closing": loop_closing, "frames": n,
            "posed_pct": 100.0 * s["frames_posed"] / n, "segments": len(s["segments"]),
            "largest_pct": 100.0 * len(traj) / n, "ate_m": ate(source.ground_truth(), traj).rmse,
            "merges": s["merges"], "wall_s": time.perf_counter() - t}


def _mean(values: list[float]) -> str:
    v = [x for x in values if x is not None and math.isfinite(x)]
    if not v:
        return "-"
    m = sum(v) / len(v)
    if len(v) == 1:
        return f"{m:.4g}"
    se = (sum((x - m) ** 2 for x in v) / (len(v) - 1)) ** 0.5 / len(v) ** 0.5
    return f"{m:.4g} ± {se:.2g}"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--csv", default=str(RESULTS / "bench_merge.csv"))
    a = p.parse_args(argv)
    rows = []
    for case in a.cases:
        if not CASES[case]["spec"].startswith("synthetic:") and not Path(CASES[case]["spec"]).exists():
            print(f"{case}: skipped ({CASES[case]['spec']} is absent)")
            continue
        for seed in range(a.seeds):
            for on in (False, True):
                r = run_one(case, seed, on)
                rows.append(r)
                print(f"{case} seed {seed} loop closing {'on' if on else 'off'}: posed {r['posed_pct']:.1f} %, "
                      f"{r['segments']} segment(s), largest {r['largest_pct']:.1f} %, ATE {r['ate_m']:.4g} m, "
                      f"{r['merges']} merge(s), {r['wall_s']:.0f} s", flush=True)
    print("\n| case | loop closing | seeds | frames | posed (%) | segments | largest (%) | ATE (m) | merges |")
    print("|---|---|---|---|---|---|---|---|---|")
    for case in a.cases:
        for on in (False, True):
            g = [r for r in rows if r["case"] == case and r["loop_closing"] == on]
            if g:
                print(f"| {case} | {'on' if on else 'off'} | {len(g)} | {g[0]['frames']} | "
                      + " | ".join(_mean([r[k] for r in g]) for k in ("posed_pct", "segments", "largest_pct",
                                                                         "ate_m", "merges")) + " |")
    Path(a.csv).parent.mkdir(parents=True, exist_ok=True)
    with open(a.csv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]) if rows else ["case"])
        w.writeheader()
        w.writerows(rows)
    print(f"\nwritten: {a.csv}")


if __name__ == "__main__":
    main()
