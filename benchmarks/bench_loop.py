"""Loop closure benchmark (issue 18): slamkit with and without loop closing on sequences that loop and on
sequences that never revisit a place.

Cases (:data:`CASES`):

* ``two-lap``: the synthetic room's ``loop`` motion driven round twice (``synthetic:loop?frames=N&laps=2&
  jitter=1&noise=1&seed=S``, default 2,000 frames), exact ground truth; one run per seed with and without
  loop closing;
* ``block``: driving twice round a city block (``synthetic:block-loop?frames=N&laps=2&noise=1&seed=S``,
  :mod:`slamkit.sources.block`, 250 m a lap, default 2,000 frames: 0.25 m per frame), a loop large enough
  that the local map has lost the start when the car returns, so drift builds up as on KITTI 00/05;
* ``kitti-07``: KITTI odometry 07 frames 0-159 (``../shared/data/kitti-odometry``, ``max_frames=160``): a
  drive that never comes back -- any loop closure there is a false one;
* ``7scenes``: 7-Scenes redkitchen frames 0-599 (``../shared/data/7scenes-redkitchen``), a hand-held room
  sequence: ATE with loop closing must not be worse (mean over the seeds).

Columns, per case and loop-closing setting (means over the seeds, ± standard error where there are several):
frames; posed (%): frames with a pose; segments; ATE (m): RMSE after Sim(3) alignment of the largest
segment (evo ``evo_ape -as``); loops: loop closures (``summary()["loop_closures"]``); t(1/3) and t(all):
wall seconds of the steps up to a third of the frames and of all steps (``finish`` excluded); flat:
t(all) / (3 x t(1/3)), the per-frame cost growth (target <= 1.25).

Every run is a fresh worker process (one BLAS thread; ``--jobs`` of them at a time). Output: a Markdown table
on stdout and ``benchmarks/results/bench_loop.csv`` (one row per run; ``--csv PATH`` elsewhere).

Usage::

    PYTHONPATH=$PWD nice -n 5 .venv/bin/python benchmarks/bench_loop.py                       # all, 3 + 5 seeds
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_loop.py --cases two-lap --seeds 1 --frames 600
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_loop.py --cases block --seeds 3 --set mapper=colmap

``loop closing on`` is the default (``loop_closing.enabled`` and ``loop_closing.correct``); "off" sets both false.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import csv  # noqa: E402
import math  # noqa: E402
import multiprocessing as mp  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402

from bench_suite import _override  # noqa: E402  (--set as the suite parses it)

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RESULTS = REPO / "benchmarks" / "results"

CASES = {
    "two-lap": {"spec": "synthetic:loop?frames={frames}&laps=2&jitter=1&noise=1&seed={seed}", "kw": {}},
    "block": {"spec": "synthetic:block-loop?frames={frames}&laps=2&noise=1&seed={seed}", "kw": {}},
    "kitti-07": {"spec": "kitti-odometry", "kw": {"sequence": "07", "max_frames": 160}},
    "7scenes": {"spec": "7scenes-redkitchen", "kw": {"max_frames": 600}},
}
SEEDS = {"two-lap": 3, "block": 2, "kitti-07": 1, "7scenes": 5}
"""Default number of seeds per case (``SlamConfig.seed``; for the synthetic case also the image noise and
the hand-held jitter or weave of the path)."""


def run_one(task: tuple[str, int, bool, int, dict]) -> dict:
    """One run: (case, seed, loop closing on, frames of the synthetic case, config overrides) -> a row."""
    from slamkit import Slam, SlamConfig, ate, open_source  # before pycolmap: see slamkit/__init__.py
    import pycolmap

    pycolmap.logging.minloglevel = 2

    case, seed, enabled, frames, overrides = task
    row = {"case": case, "seed": seed, "loop_closing": enabled, "error": ""}
    spec = CASES[case]["spec"]
    if spec.startswith("synthetic:"):
        spec = spec.format(frames=frames, seed=seed)
    elif not (DATA / spec).exists():
        return row | {"error": f"absent: {DATA / spec}"}
    else:
        spec = str(DATA / spec)
    try:
        source = open_source(spec, **CASES[case]["kw"])
        slam = Slam(source, SlamConfig().with_overrides(seed=seed, **overrides, **{
            "loop_closing.enabled": enabled, "loop_closing.correct": enabled}))
        t0, times = time.perf_counter(), []
        for _ in slam:
            times.append(time.perf_counter() - t0)
        slam.finish()
        s, traj, gt = slam.summary(), slam.trajectory(), source.ground_truth()
        n = s["frames"]
        third = times[max(0, n // 3 - 1)]
        row |= {"frames": n, "posed_pct": 100.0 * s["frames_posed"] / n, "segments": len(s["segments"]),
                "loops": s["loop_closures"], "loop_pairs": ";".join(f"{p['query_frame']}~{p['candidate_frame']}"
                                                                    for p in s["loop_closure_pairs"]),
                "t_third_s": third, "t_all_s": times[-1], "flat": times[-1] / (3 * third),
                "ate_m": float(ate(gt, traj, align="sim3").rmse) if gt is not None and len(traj) >= 3 else None}
    except Exception as e:  # a failing run is a row, never the end of the benchmark
        traceback.print_exc()
        row["error"] = f"{type(e).__name__}: {e}"
    return row


def _mean(values: list[float]) -> str:
    v = [x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))]
    if not v:
        return "-"
    m = sum(v) / len(v)
    if len(v) == 1:
        return f"{m:.4g}"
    sd = math.sqrt(sum((x - m) ** 2 for x in v) / (len(v) - 1))
    return f"{m:.4g} ± {sd / math.sqrt(len(v)):.2g}"


def table(rows: list[dict]) -> str:
    """Markdown: one line per case and setting, means over seeds."""
    head = ("| case | loop closing | seeds | frames | posed (%) | segments | ATE (m) | loops | t(1/3) s | t(all) s "
            "| flat |\n|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for case in CASES:
        for enabled in (False, True):
            rs = [r for r in rows if r["case"] == case and r["loop_closing"] == enabled and not r["error"]]
            if not rs:
                errs = {r["error"] for r in rows if r["case"] == case and r["loop_closing"] == enabled}
                if errs:
                    lines.append(f"| {case} | {'on' if enabled else 'off'} | - | {'; '.join(sorted(errs))} |")
                continue
            lines.append("| " + " | ".join([case, "on" if enabled else "off", str(len(rs))] + [
                _mean([r[k] for r in rs]) for k in ("frames", "posed_pct", "segments", "ate_m", "loops",
                                                    "t_third_s", "t_all_s", "flat")]) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    p.add_argument("--seeds", type=int, help="seeds per case (default: 3 two-lap, 2 block, 1 KITTI, 5 7-Scenes)")
    p.add_argument("--frames", type=int, default=2000, help="frames of the synthetic two-lap loops (2000)")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--csv", type=Path, default=RESULTS / "bench_loop.csv")
    p.add_argument("--loop-closing", choices=["both", "on", "off"], default="both",
                   help="run with loop closing on, off or both (default)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a config override for every run (SlamConfig.with_overrides key, e.g. mapper=colmap); "
                        "repeatable")
    args = p.parse_args(argv)
    overrides = dict(_override(kv) for kv in args.set)
    tasks = [(case, seed, enabled, args.frames, overrides) for case in args.cases
             for seed in range(args.seeds or SEEDS[case])
             for enabled in {"both": (False, True), "on": (True,), "off": (False,)}[args.loop_closing]]
    with mp.get_context("spawn").Pool(args.jobs, maxtasksperchild=1) as pool:
        rows = []
        for row in pool.imap(run_one, tasks):
            rows.append(row)
            print({k: (round(v, 5) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
        pool.close()  # let the workers exit: the pool's exit would SIGTERM them (pycolmap prints a crash report)
        pool.join()
    print(table(rows))
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    keys = sorted({k for r in rows for k in r}, key=lambda k: list(rows[0]).index(k) if k in rows[0] else 99)
    with args.csv.open("w", newline="") as f:
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {args.csv}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
