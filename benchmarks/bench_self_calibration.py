"""Self-calibration (issue 30): every sequence run twice, with its calibration and with ``camera="auto"``
(the focal length estimated from the frames and the map, principal point at the image centre; the final
BA adds one radial coefficient k1).

Cases (:data:`CASES`): KITTI odometry 07 (160 frames, true focal 707.09 px, principal point 11 px left of
the centre), 7-Scenes redkitchen (600 frames; the dataset's nominal 585 px), the driving clip (268 frames;
``--camera 721`` as its known calibration, no ground truth), and rendered sequences with exact intrinsics:
the hand-held room (150 frames) at focal lengths 0.5x, 1x and 2x the image width (320, 640, 1280 px) and
with barrel distortion (500 px, k1 = -0.1), with pincushion distortion as strong as TUM freiburg1's
(k1 = 0.25) and with freiburg1's own lens (k1 0.262, k2 -0.953, k3 1.163; its ``k1`` column is the truth's k1
only), a drive round a city block (forward motion with four turns,
700 px), pure forward motion and an orbit round the room's cube, looking at it (degenerate cases: the
estimate must say it is weak), and a hand-held pan (issue 52: looking round from where one stands, a few
centimetres of baseline; ``syn-pan*``) without distortion, with k1 = 0.25 and with freiburg1's lens. Seeds 0 .. N-1 go
to ``SlamConfig.seed`` and to the synthetic spec's seed.

Columns per run: posed (%) of all frames; ATE (m, Sim(3), largest segment; undefined, "-", for a run posed by
rotation only, every camera centre one point); rot (degrees: the rotation error's RMSE after aligning the
orientations alone, defined for those too); focal (px, the final camera of
the run) and its error against the truth (%); k1 (the run's radial coefficient); first (px) the estimate
from the first frames, the ± it shows (%, none when weak) and whether it was weak; whether the run's estimate is
reported weak at the end; wall seconds. Per case and
mode: mean ± standard error over seeds.

Output: a Markdown table on stdout and ``benchmarks/results/bench_self_calibration.csv`` (``--csv``).
``--first-frames`` runs only the estimate from the first frames (seconds per seed) and counts how often the
``± %`` it shows covers the true focal length (``bench_self_calibration_first.csv``).

Usage::

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_self_calibration.py --seeds 3 --jobs 2
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_self_calibration.py --cases 'syn-*' --modes auto
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_self_calibration.py --cases 'syn-*' --first-frames --seeds 10
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import csv  # noqa: E402
import fnmatch  # noqa: E402
import math  # noqa: E402
import multiprocessing as mp  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_suite import DATA, RESULTS, mean_se  # noqa: E402


@dataclass(frozen=True)
class Case:
    name: str
    spec: str
    """A path relative to ``../shared/data`` or a synthetic spec (``{seed}``: the run's seed)."""
    focal: float
    """The true focal length, px."""
    known: str = ""
    """``SlamConfig.camera`` of the calibrated run ("" = the source's own)."""
    k1: float = 0.0
    """The true radial distortion coefficient (OpenCV's k1)."""
    kw: dict = field(default_factory=dict)

    def source_spec(self, seed: int) -> str:
        return self.spec.format(seed=seed) if self.spec.startswith("synthetic:") else str(DATA / self.spec)


_SYN = "&noise=1&seed={seed}"
CASES = [
    Case("kitti-07", "kitti-odometry", 707.0912, kw={"sequence": "07"}),
    Case("7scenes", "7scenes-redkitchen", 585.0, kw={"max_frames": 600}),
    Case("video-kitti984", "video/test_kitti984.mp4", 721.0, known="721"),
    *(Case(f"syn-room-f{f}", f"synthetic:handheld?frames=150&focal={f}" + _SYN, float(f)) for f in (320, 640, 1280)),
    Case("syn-block-f700", "synthetic:block-loop?frames=300&focal=700" + _SYN, 700.0),
    Case("syn-forward", "synthetic:forward?frames=100" + _SYN, 500.0),
    Case("syn-room-k1", "synthetic:handheld?frames=150&k1=-0.1" + _SYN, 500.0, k1=-0.1),
    Case("syn-room-k1+0.25", "synthetic:handheld?frames=150&k1=0.25" + _SYN, 500.0, k1=0.25),
    Case("syn-room-fr1lens", "synthetic:handheld?frames=150&k1=0.262&k2=-0.953&k3=1.163" + _SYN, 500.0, k1=0.262),
    Case("syn-orbit", "synthetic:orbit?frames=150" + _SYN, 500.0),
    Case("syn-pan", "synthetic:handheld-pan?frames=150" + _SYN, 500.0),
    Case("syn-pan-k1+0.25", "synthetic:handheld-pan?frames=150&k1=0.25" + _SYN, 500.0, k1=0.25),
    Case("syn-pan-fr1lens", "synthetic:handheld-pan?frames=150&k1=0.262&k2=-0.953&k3=1.163" + _SYN, 500.0,
         k1=0.262),
]
MODES = ("known", "auto", "auto-nofinal")
"""known: the case's calibration; auto: ``camera="auto"``; auto-nofinal: the same without the final global
BA's refinement of the focal length (``self_calibration.refine_final=false``)."""
COLUMNS = ["row", "case", "mode", "seed", "status", "frames", "posed_pct", "ate_m", "rot_deg", "focal", "focal_err_pct",
           "k1", "first_focal", "first_uncertainty_pct", "first_weak", "weak_at_end", "wall_s", "error"]
MEAN_KEYS = ["posed_pct", "ate_m", "rot_deg", "focal", "focal_err_pct", "k1", "first_focal", "first_uncertainty_pct",
             "wall_s"]


def _absent(case: Case) -> str | None:
    if case.spec.startswith("synthetic:"):
        return None
    path = DATA / case.spec
    return None if path.exists() else f"{path} not found"


def run_one(job: tuple[Case, str, int, dict]) -> dict:
    case, mode, seed, overrides = job
    from slamkit import Slam, SlamConfig, SlamkitError, ate, open_source  # before pycolmap: see slamkit/__init__.py
    import pycolmap

    pycolmap.logging.minloglevel = 2

    row = {"row": "run", "case": case.name, "mode": mode, "seed": seed, "error": ""}
    if (why := _absent(case)) is not None:
        return row | {"status": "skipped", "error": why}
    try:
        t0 = time.perf_counter()
        camera = "auto" if mode.startswith("auto") else case.known
        extra = {"self_calibration.refine_final": False} if mode == "auto-nofinal" else {}
        config = SlamConfig().with_overrides(seed=seed, camera=camera, **extra, **overrides)
        source = open_source(case.source_spec(seed), **case.kw)
        slam = Slam(source, config)
        slam.run()
        s, traj, gt = slam.summary(), slam.trajectory(), source.ground_truth()
        focal = float(slam.camera.fx)
        row |= {"status": "ok", "frames": s["frames"], "posed_pct": 100.0 * s["frames_posed"] / s["frames"],
                "focal": focal, "focal_err_pct": 100.0 * (focal / case.focal - 1), "k1": float(slam.camera.dist[0]),
                "wall_s": time.perf_counter() - t0}
        first = slam.calibrator.initial if slam.calibrator is not None else None
        if first is not None:
            row |= {"weak_at_end": bool(slam.calibrator.weak),
                    "first_focal": first.focal if math.isfinite(first.focal) else None,
                    "first_uncertainty_pct": None if first.weak else 100 * first.interval,
                    "first_weak": bool(first.weak)}
        if gt is not None and len(traj) >= 3:
            try:
                result = ate(gt, traj, align="sim3")
                row["rot_deg"] = float(result.oriented_rotation.rmse)
                if math.isfinite(result.rmse):
                    row["ate_m"] = float(result.rmse)
            except SlamkitError as e:
                row["error"] = f"ATE undefined: {e}"
    except Exception as e:  # a failing run is a row of the table
        traceback.print_exc()
        return row | {"status": "error", "error": f"{type(e).__name__}: {e}"}
    return row


FIRST_COLUMNS = ["case", "seed", "focal_true", "first_focal", "err_pct", "interval_pct", "pairs", "weak", "covered",
                 "k1", "model", "reason"]


def first_frames_one(job: tuple[Case, int, dict]) -> dict:
    """Self-calibration's first phase only (:func:`estimate_focal` on the first ``window_frames`` frames, as a
    run with ``camera="auto"`` makes it, with the run's seed): the estimate, its error against the truth, the
    interval it shows (``± %``) and whether that covers the truth (None for a weak estimate, which shows none)."""
    case, seed, overrides = job
    from slamkit import SlamConfig, open_source
    from slamkit.stages.self_calibration import estimate_focal

    row = {"case": case.name, "seed": seed, "focal_true": case.focal}
    if (why := _absent(case)) is not None:
        return row | {"reason": f"skipped: {why}"}
    config = SlamConfig().with_overrides(**overrides).self_calibration
    source = open_source(case.source_spec(seed), **case.kw)
    grays = [source[i].gray for i in range(min(len(source), config.window_frames))]
    est = estimate_focal(grays, config, seed)
    err = math.log(est.focal / case.focal) if math.isfinite(est.focal) else math.nan
    return row | {"first_focal": est.focal, "err_pct": 100 * math.expm1(err),
                  "interval_pct": None if est.weak else 100 * est.interval, "pairs": est.num_pairs,
                  "weak": est.weak, "covered": None if est.weak else bool(abs(err) <= est.interval),
                  "k1": est.k1, "model": est.model, "reason": est.reason}


def first_frames(cases: list[Case], seeds: int, jobs: int, csv_path: Path, overrides: dict | None = None) -> int:
    """``--first-frames``: per case, how often the interval of the first frames' estimate covers the true
    focal length (weak estimates show none and are counted apart)."""
    runs = []
    pool = mp.get_context("spawn").Pool(jobs, maxtasksperchild=4)
    try:
        for r in pool.imap_unordered(first_frames_one, [(c, s, overrides or {}) for c in cases for s in range(seeds)]):
            runs.append(r)
            print(" ".join(f"{k}={r[k]:.4g}" if isinstance(r.get(k), float) else f"{k}={r.get(k)}"
                           for k in FIRST_COLUMNS if k in r), flush=True)
    finally:
        pool.close()  # workers exit on their own (terminating them mid-teardown makes pycolmap print a trace)
        pool.join()
    print("| case | seeds | weak | covered / not weak | error % (median abs) | ± % shown (median) |")
    print("|---|---|---|---|---|---|")
    for c in cases:
        rs = [r for r in runs if r["case"] == c.name and "first_focal" in r]
        strong = [r for r in rs if not r["weak"]]
        errs = sorted(abs(r["err_pct"]) for r in strong)
        shown = sorted(r["interval_pct"] for r in strong)
        print(f"| {c.name} | {len(rs)} | {len(rs) - len(strong)} | {sum(r['covered'] for r in strong)} / "
              f"{len(strong)} | {errs[len(errs) // 2] if errs else math.nan:.2f} | "
              f"{shown[len(shown) // 2] if shown else math.nan:.2f} |")
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    with open(csv_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIRST_COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(sorted(runs, key=lambda r: (r["case"], r["seed"])))
    print(f"wrote {csv_path}")
    return 0


def case_rows(runs: list[dict]) -> list[dict]:
    out = []
    for key in dict.fromkeys((r["case"], r["mode"]) for r in runs):
        rs = [r for r in runs if (r["case"], r["mode"]) == key and r["status"] == "ok"]
        row = {"row": "case", "case": key[0], "mode": key[1], "seed": len(rs),
               "status": "ok" if rs else next(r["status"] for r in runs if (r["case"], r["mode"]) == key)}
        for k in MEAN_KEYS:
            m, se = mean_se([r[k] for r in rs if r.get(k) is not None])
            row[k], row[k + "_se"] = m, se
        row["first_weak"] = sum(bool(r.get("first_weak")) for r in rs) if key[1] == "auto" else None
        row["weak_at_end"] = sum(bool(r.get("weak_at_end")) for r in rs) if key[1] == "auto" else None
        out.append(row)
    return out


def _cell(row: dict, key: str, fmt: str) -> str:
    m, se = row.get(key), row.get(key + "_se")
    if m is None:
        return "-"
    return f"{m:{fmt}}" + (f" ± {se:{fmt}}" if se else "")


def markdown(rows: list[dict]) -> str:
    lines = ["| case | mode | seeds | posed % | ATE (m) | rot (deg) | focal (px) | focal error % | k1 | "
             "first frames (px) | ± % | weak | weak at the end |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['mode']} | {r['seed']} | {_cell(r, 'posed_pct', '.1f')} | "
                     f"{_cell(r, 'ate_m', '.4f')} | {_cell(r, 'rot_deg', '.3f')} | {_cell(r, 'focal', '.1f')} | "
                     f"{_cell(r, 'focal_err_pct', '.2f')} | "
                     f"{_cell(r, 'k1', '.4f')} | "
                     f"{_cell(r, 'first_focal', '.1f')} | {_cell(r, 'first_uncertainty_pct', '.1f')} | "
                     f"{'-' if r['first_weak'] is None else r['first_weak']} | "
                     f"{'-' if r['weak_at_end'] is None else r['weak_at_end']} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", help="comma-separated globs of case names (default: all)")
    ap.add_argument("--modes", default=",".join(MODES), help=f"comma-separated of {', '.join(MODES)} (default all)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--csv", type=Path, default=RESULTS / "bench_self_calibration.csv")
    ap.add_argument("--first-frames", action="store_true",
                    help="only the estimate from the first frames: how often its ± covers the true focal length")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override for every run, e.g. --set initializer.window_overlap=0.3")
    args = ap.parse_args(argv)
    pats = args.cases.split(",") if args.cases else ["*"]
    cases = [c for c in CASES if any(fnmatch.fnmatch(c.name, p.strip()) for p in pats)]
    overrides = dict(item.split("=", 1) for item in args.set)
    if args.first_frames:
        return first_frames(cases, args.seeds, args.jobs, args.csv.with_name("bench_self_calibration_first.csv"),
                            overrides)
    modes = [m.strip() for m in args.modes.split(",")]
    jobs = [(c, m, s, overrides) for c in cases for m in modes for s in range(args.seeds)]
    runs = []
    pool = mp.get_context("spawn").Pool(args.jobs, maxtasksperchild=1)
    try:
        for r in pool.imap_unordered(run_one, jobs):
            runs.append(r)
            print(f"[{time.strftime('%H:%M:%S')}] {r['case']} {r['mode']} seed {r['seed']}: {r['status']} "
                  + " ".join(f"{k}={r[k]:.4g}" if isinstance(r.get(k), float) else f"{k}={r.get(k)}"
                             for k in ("posed_pct", "ate_m", "rot_deg", "focal", "focal_err_pct", "k1", "first_focal",
                                       "first_weak", "weak_at_end")
                             if k in r) + (f" {r['error']}" if r["error"] else ""), flush=True)
    finally:
        pool.close()  # workers exit on their own (terminating them mid-teardown makes pycolmap print a trace)
        pool.join()
    order = {(c.name, m, s): i for i, (c, m, s, _) in enumerate(jobs)}
    runs.sort(key=lambda r: order[(r["case"], r["mode"], r["seed"])])
    rows = case_rows(runs)
    print(markdown(rows))
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    with open(args.csv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS + [k + "_se" for k in MEAN_KEYS], extrasaction="ignore")
        w.writeheader()
        w.writerows(runs + rows)
    print(f"wrote {args.csv}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
