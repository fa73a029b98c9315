"""Hard-motion suite (issue 17): slamkit on every sequence of ../shared/data at its natural rate and faster
(frame skipping), and on synthetic sequences with fast forward motion, fast turns and sudden jerks.

Cases (:data:`CASES`): KITTI odometry 07 at frame skip 1, 2, 3; 7-Scenes redkitchen (600 frames) at skip
1, 3, 5; the driving clip ``video/test_kitti984.mp4`` with ``camera="721"`` (the CLI's ``--camera 721``);
uncalibrated input (issue 39): KITTI 07 as a plain image folder (no calibration: self-calibrated; its ground
truth paired frame by frame from the KITTI layout) and the driving clip with ``camera="auto"``;
the two tiny TUM sequences (the ground-truth-only TUM folders are listed as skipped: no images); and the
synthetic hard motions of :mod:`slamkit.sources.motions`, each at two strengths; and two loops (kind
"loop", not in ``--quick``): twice round the city block (1,000 frames) and the room's loop motion twice
(3,000 frames). Every case runs once per seed
(``--seeds N``: seeds 0 .. N-1 go to ``SlamConfig.seed`` and, for synthetic cases, to the spec's
``seed``: image noise, and the path of random motions). Frame skipping is ``SlamConfig.frame_skip``, as
the CLI's ``--frame-skip``.

Columns, per run (from ``Slam.summary()``, ``Slam.trajectory()`` and :func:`slamkit.ate`):

* frames: frames used (after skipping); posed (%): frames with a pose in any map segment;
* segments: map segments; largest (%): frames posed in the largest segment, in % of all frames (the
  frames the ATE is computed on);
* ATE (m): RMSE after Sim(3) alignment of the largest segment's trajectory to ground truth (= evo
  ``evo_ape -as``); keyframe ATE (m): the same over its keyframes only (what ORB-SLAM2's monocular examples
  save: ``KeyFrameTrajectory.txt``); rotation error (deg): RMS angle of ``R_est,aligned^T R_gt`` after the
  same alignment (= ``evo_ape -as --pose_relation angle_deg``; a run posed by rotation only has its orientations
  aligned and no ATE: "ATE undefined: rotation only"); relocalizations: summed over segments; keyframes; loop closures
  (``summary()["loop_closures"]``);
* fx (px), k1: the run's final camera (with self-calibration, the estimate: compare KITTI 07's 707.09 px);
* fps: frames / wall seconds of the whole run (opening the source to the end of ``run()``, image reading
  and the final bundle adjustment included; not the saving); CPU s/frame: process CPU seconds (all
  threads) / frames -- the steadier measure when other jobs share the machine.

Per case, with several seeds, each number is the mean over the seeds that produced it, ± its standard
error (sd / sqrt(n)). A run that raises, crashes the worker process or exceeds ``--timeout`` is a row with
its error; a case whose data is absent is a row saying so. Runs execute in ``--jobs`` (default 2) worker
processes, one fresh process per run (one BLAS/OpenMP thread each); each run's output (``Slam.save``) goes
to ``benchmarks/results/suite/<case>_seed<S>/``.

Output: a Markdown table on stdout, ``benchmarks/results/bench_suite.csv`` (or ``--csv PATH``: one row
per run, then one per case with means and standard errors) and ``bench_suite.md`` beside it.

Usage::

    PYTHONPATH=$PWD nice -n 5 .venv/bin/python benchmarks/bench_suite.py            # everything, 3 seeds
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_suite.py --quick              # a few minutes, 1 seed
    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_suite.py --cases 'kitti*' --seeds 5
    make bench-suite
"""

from __future__ import annotations

import os

# one BLAS / OpenMP thread per worker, set before numpy starts its thread pool (workers are spawned: they
# import this module first)
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import ast  # noqa: E402
import csv  # noqa: E402
import fnmatch  # noqa: E402
import math  # noqa: E402
import multiprocessing as mp  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from dataclasses import dataclass, field, replace  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_features import code_version  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RESULTS = REPO / "benchmarks" / "results"


@dataclass(frozen=True)
class Case:
    """One sequence at one speed. ``spec`` is a path relative to ``../shared/data`` or a synthetic spec
    (``{seed}`` is replaced by the run's seed); ``kw`` goes to ``open_source``, ``config`` to
    ``SlamConfig.with_overrides`` (besides ``seed`` and ``frame_skip``)."""

    name: str
    kind: str
    """real | tiny | fast-forward | fast-yaw | jerky | rotation | loop"""
    spec: str
    skip: int = 1
    kw: dict = field(default_factory=dict)
    config: dict = field(default_factory=dict)
    quick: bool = False
    """part of ``--quick``"""
    what: str = ""
    ground_truth: tuple = ()
    """(spec relative to ``../shared/data``, ``open_source`` kw) of a source of the same frames that carries the
    ground truth, paired frame by frame with the case's (a plain image folder has none of its own); empty: the
    case's source's own."""

    @property
    def synthetic(self) -> bool:
        return self.spec.startswith("synthetic:")

    def source_spec(self, seed: int) -> str:
        return self.spec.format(seed=seed) if self.synthetic else str(DATA / self.spec)


_SYN = "&noise=1&seed={seed}"
CASES = [
    *(Case(f"kitti-07/skip{k}", "real", "kitti-odometry", k, {"sequence": "07"}, quick=k == 2,
           what=f"KITTI odometry 07 frames 0-159, frame skip {k} (~{0.55 * k:.1f} m per frame)") for k in (1, 2, 3)),
    *(Case(f"7scenes/skip{k}", "real", "7scenes-redkitchen", k, {"max_frames": 600}, quick=k == 3,
           what=f"7-Scenes redkitchen frames 0-599, frame skip {k}") for k in (1, 3, 5)),
    Case("video-kitti984", "real", "video/test_kitti984.mp4", 1, config={"camera": "721"}, quick=True,
         what="the source paper's driving clip, 268 frames 1242x375, --camera 721"),
    Case("kitti-07/folder", "real", "kitti-odometry/sequences/07/image_0", 1,
         ground_truth=("kitti-odometry", {"sequence": "07"}),
         what="KITTI odometry 07 frames 0-159 as a plain image folder: no calibration, the camera self-calibrated "
              "(true fx 707.09)"),
    Case("video-kitti984/auto", "real", "video/test_kitti984.mp4", 1, config={"camera": "auto"},
         what="the driving clip, 268 frames 1242x375, --camera auto (self-calibrated; ~721 px)"),
    Case("tum-fr1-desk-9", "tiny", "tum/rgbd_dataset_freiburg1_desk_9frames", what="TUM fr1/desk, 9 frames"),
    Case("tum-fr3-office-4", "tiny", "tum/rgbd_dataset_freiburg3_long_office_household_4frames",
         what="TUM fr3/long_office_household, 4 frames 3.3 s apart"),
    *(Case(f"tum-gt-only/{s}", "tiny", f"tum/groundtruth-only/{s}", what="ground truth only")
      for s in ("fr1_xyz", "fr2_xyz", "fr1_desk")),
    Case("syn-forward-0.25", "fast-forward", "synthetic:fast-forward?frames=80&speed=0.25" + _SYN,
         what="along the optical axis, forward and back, 0.25 m/frame (median flow ~25 px)"),
    Case("syn-forward-0.5", "fast-forward", "synthetic:fast-forward?frames=80&speed=0.5" + _SYN, quick=True,
         what="along the optical axis, forward and back, 0.5 m/frame (median flow ~48 px)"),
    Case("syn-street-1.0", "fast-forward", "synthetic:street-drive?frames=150&speed=1.0" + _SYN,
         what="driving 150 m down the synthetic street at 1.0 m/frame (KITTI at skip 2), 640x480"),
    Case("syn-fast-yaw-10", "fast-yaw", "synthetic:fast-yaw?frames=100&yaw_rate=10&turn=150&hold=0" + _SYN,
         quick=True, what="swings of +-75 deg at 10 deg/frame (~87 px), walking 1 cm/frame"),
    Case("syn-fast-yaw-20", "fast-yaw",
         "synthetic:fast-yaw?frames=100&yaw_rate=20&turn=150&hold=3&speed=0.005" + _SYN,
         what="swings of +-75 deg at 20 deg/frame (~175 px), 3 frames still between, walking 5 mm/frame"),
    Case("syn-turn-then-walk", "rotation", "synthetic:turn-then-walk?frames=150&amplitude=45" + _SYN,
         what="2 s turning in place (+-45 deg, ~4.7 deg/frame), then walking 1.5 cm/frame (issue 42)"),
    Case("syn-pure-rotation", "rotation", "synthetic:pure-rotation?frames=150" + _SYN,
         what="a pan from one place, +-60 deg with tilt: no 3-D structure (issue 42; ATE undefined)"),
    Case("syn-jerky-10", "jerky", "synthetic:jerky?frames=150&jump=10" + _SYN,
         what="hand-held 1.5 cm/frame, 3 jerks of 10 frames of motion in one (~15 cm)"),
    Case("syn-jerky-30", "jerky", "synthetic:jerky?frames=150&jump=30" + _SYN, quick=True,
         what="hand-held 1.5 cm/frame, 3 jerks of 30 frames of motion in one (~45 cm)"),
    Case("syn-block-loop", "loop", "synthetic:block-loop?frames=1000&laps=2" + _SYN,
         what="twice round the 250 m city block, 1,000 frames (0.5 m/frame): drift a loop closure must undo"),
    Case("syn-room-two-lap", "loop", "synthetic:loop?frames=3000&laps=2&jitter=1" + _SYN,
         what="the room's loop motion twice, 3,000 frames: the second lap revisits the first"),
]

RUN_COLUMNS = ["row", "case", "skip", "seed", "status", "frames", "posed_pct", "segments", "largest_pct",
               "ate_m", "ate_kf_m", "rot_deg", "relocalizations", "fps", "cpu_s_per_frame", "wall_s", "keyframes",
               "loop_closures", "focal_px", "k1", "error"]
MEAN_KEYS = ["posed_pct", "segments", "largest_pct", "ate_m", "ate_kf_m", "rot_deg", "relocalizations", "fps",
             "cpu_s_per_frame",
             "wall_s", "keyframes", "loop_closures", "focal_px", "k1"]


def select_cases(cases: list[Case], pattern: str | None, quick: bool) -> list[Case]:
    """The cases whose name matches any of the comma-separated glob ``pattern`` (all when None), of
    ``--quick`` only when ``quick``."""
    pats = [p.strip() for p in pattern.split(",")] if pattern else ["*"]
    return [c for c in cases if (c.quick or not quick) and any(fnmatch.fnmatch(c.name, p) for p in pats)]


# ------------------------------------------------------------------------------------------------ one run
def _absent(case: Case) -> str | None:
    """Why the case cannot run here (its data absent, or no images), else None."""
    if case.synthetic:
        return None
    path = DATA / case.spec
    if not path.exists():
        return f"{path} not found"
    if path.is_dir() and not any(p.suffix.lower() in (".png", ".jpg", ".jpeg") for p in path.rglob("*")):
        return f"{path.relative_to(DATA.parent)}: no images (ground truth and rgb.txt only)"
    return None


def _ground_truth(case: Case, source):
    """The ground truth of ``source`` (the case's), or with ``case.ground_truth`` that of another source of
    the same frames, paired by position and given the timestamps of ``source``."""
    if not case.ground_truth:
        return source.ground_truth()
    import numpy as np

    from slamkit import SlamkitError, Trajectory, open_source

    spec, kw = case.ground_truth
    ref = open_source(str(DATA / spec), **kw)
    if ref.gt_poses is None or len(ref) != len(source):
        raise SlamkitError(f"{spec}: {len(ref)} frames, {'no' if ref.gt_poses is None else 'a'} ground truth; "
                           f"the case's source has {len(source)} frames")
    ok = np.isfinite(ref.gt_poses).all(axis=(1, 2))
    return Trajectory(np.asarray(source.timestamps)[ok], ref.gt_poses[ok])


def run_one(case: Case, seed: int, out_dir: Path | None = None) -> dict:
    """Run slamkit once on ``case`` with ``seed``; the run's row (see the module docstring). A raised
    exception becomes ``status="error"`` with the message; ``out_dir`` receives ``Slam.save``."""
    import pycolmap

    pycolmap.logging.minloglevel = 2
    from slamkit import Slam, SlamConfig, SlamkitError, ate, open_source

    row = {"row": "run", "case": case.name, "skip": case.skip, "seed": seed, "error": ""}
    why = _absent(case)
    if why:
        return row | {"status": "skipped", "error": why}
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        config = SlamConfig().with_overrides(seed=seed, frame_skip=case.skip, **case.config)
        source = open_source(case.source_spec(seed), **case.kw)
        slam = Slam(source, config)
        slam.run()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        s, traj, gt = slam.summary(), slam.trajectory(), _ground_truth(case, source)
        n = s["frames"]
        row |= {"status": "ok", "frames": n, "posed_pct": 100.0 * s["frames_posed"] / n,
                "segments": len(s["segments"]), "largest_pct": 100.0 * len(traj) / n,
                "relocalizations": s["relocalizations"], "fps": n / wall, "cpu_s_per_frame": cpu / n,
                "wall_s": wall, "keyframes": s["keyframes"], "loop_closures": s["loop_closures"],
                "ate_m": None, "ate_kf_m": None, "rot_deg": None, "focal_px": slam.camera.fx, "k1": slam.camera.dist[0]}
        if gt is None:
            row["error"] = "no ground truth"
        elif len(traj) < 3:
            row["error"] = f"ATE undefined: {len(traj)} frames posed in the largest segment"
            if s["not_initialized_reason"]:
                row["error"] += f" ({s['not_initialized_reason']})"
        else:
            try:  # a path ATE cannot align to (all on a line) leaves the other numbers standing
                a = ate(gt, traj, align="sim3")
                row["rot_deg"] = float(a.rotation.rmse)  # after the same alignment (orientations alone: rotation only)
                if a.undefined:
                    row["error"] = a.undefined
                else:
                    row["ate_m"] = float(a.rmse)
                    # keyframes only, as ORB-SLAM2's monocular examples save their trajectory (KeyFrameTrajectory.txt)
                    row["ate_kf_m"] = float(ate(gt, slam.trajectory(keyframes_only=True), align="sim3").rmse)
            except SlamkitError as e:
                row["error"] = f"ATE undefined: {e}"
    except Exception as e:  # a failing run is a row of the table, never the end of the suite
        traceback.print_exc()
        return row | {"status": "error", "error": f"{type(e).__name__}: {e}"}
    if out_dir is not None:
        try:  # the run's numbers stand even when its output cannot be written
            slam.save(out_dir)
        except Exception as e:
            row["error"] = "; ".join(x for x in (row["error"], f"not saved: {type(e).__name__}: {e}") if x)
    return row


def _worker(case: Case, seed: int, out_dir: Path | None, conn) -> None:
    conn.send(run_one(case, seed, out_dir))
    conn.close()


# ----------------------------------------------------------------------------------------- the scheduler
def run_all(jobs: list[tuple[Case, int]], workers: int = 2, timeout_s: float = 600.0,
            out_root: Path | None = None, log=print) -> list[dict]:
    """Run every (case, seed) in its own spawned process, ``workers`` at a time, longest first; a run still
    going after ``timeout_s`` is terminated and reported. Rows come back in the order of ``jobs``."""
    ctx = mp.get_context("spawn")
    order = sorted(range(len(jobs)), key=lambda i: -_cost(jobs[i][0]))
    pending, running, rows = list(order), {}, {}
    while pending or running:
        while pending and len(running) < workers:
            i = pending.pop(0)
            case, seed = jobs[i]
            if (why := _absent(case)) is not None:  # no process for a case that cannot run
                rows[i] = {"row": "run", "case": case.name, "skip": case.skip, "seed": seed, "status": "skipped",
                           "error": why}
                continue
            recv, send = ctx.Pipe(duplex=False)
            out = None if out_root is None else out_root / f"{case.name.replace('/', '_')}_seed{seed}"
            p = ctx.Process(target=_worker, args=(case, seed, out, send), daemon=True)
            p.start()
            send.close()
            running[i] = (p, recv, time.perf_counter())
        time.sleep(0.2)
        for i, (p, recv, t0) in list(running.items()):
            case, seed = jobs[i]
            base = {"row": "run", "case": case.name, "skip": case.skip, "seed": seed}
            if recv.poll():
                try:
                    rows[i] = recv.recv()
                except EOFError:  # the process died before sending: a crash (SIGABRT, out of memory)
                    p.join(5)
                    rows[i] = base | {"status": "crash", "error": f"worker died, exit code {p.exitcode}"}
            elif not p.is_alive():
                rows[i] = base | {"status": "crash", "error": f"worker died, exit code {p.exitcode}"}
            elif time.perf_counter() - t0 > timeout_s:
                p.terminate()
                rows[i] = base | {"status": "timeout", "error": f"no result after {timeout_s:.0f} s (terminated)"}
            else:
                continue
            p.join(10)
            recv.close()
            del running[i]
            log(_progress(rows[i]))
    return [rows[i] for i in range(len(jobs))]


def _cost(case: Case) -> float:
    """Rough relative cost of a run, to start the long ones first."""
    return {"kitti-07": 160 * 4, "7scenes": 600, "video-kitti984": 268 * 4, "syn-block-loop": 1000 * 4,
            "syn-room-two-lap": 3000 * 2}.get(
        case.name.split("/")[0], 150) / case.skip


def _progress(r: dict) -> str:
    head = f"[{time.strftime('%H:%M:%S')}] {r['case']} seed {r['seed']}: {r['status']}"
    if r["status"] != "ok":
        return f"{head} ({r['error']})"
    ate_s = "-" if r["ate_m"] is None else f"{r['ate_m']:.4g} m"
    ate_s += "" if r.get("rot_deg") is None else f" (rotation {r['rot_deg']:.3g} deg)"
    return (f"{head}, posed {r['posed_pct']:.1f} %, {r['segments']} segment(s), largest {r['largest_pct']:.1f} %, "
            f"ATE {ate_s}, {r['relocalizations']} reloc, {r['fps']:.1f} fps, {r['cpu_s_per_frame']:.3f} CPU s/frame, "
            f"fx {r['focal_px']:.1f} px, k1 {r['k1']:.3f}")


# ----------------------------------------------------------------------------------------- aggregation
def mean_se(values: list[float]) -> tuple[float | None, float | None]:
    """Mean and standard error (sd / sqrt(n), sd with n - 1) of ``values``; (None, None) when empty, SE None
    for one value."""
    if not values:
        return None, None
    m = sum(values) / len(values)
    if len(values) < 2:
        return m, None
    sd = math.sqrt(sum((v - m) ** 2 for v in values) / (len(values) - 1))
    return m, sd / math.sqrt(len(values))


def case_rows(cases: list[Case], runs: list[dict]) -> list[dict]:
    """One row per case: every number of :data:`MEAN_KEYS` as its mean over the case's ok runs, ``<key>_se``
    its standard error; ``status`` says how many runs finished; ``error`` gathers the failures."""
    rows = []
    for case in cases:
        mine = [r for r in runs if r["case"] == case.name]
        ok = [r for r in mine if r["status"] == "ok"]
        row = {"row": "case", "case": case.name, "skip": case.skip, "seed": " ".join(str(r["seed"]) for r in mine),
               "frames": ok[0]["frames"] if ok else None, "what": case.what}
        if mine and all(r["status"] == "skipped" for r in mine):
            row |= {"status": "skipped", "error": mine[0]["error"]}
        else:
            row["status"] = f"{len(ok)}/{len(mine)} ok"
            row["error"] = "; ".join(sorted({f"seed {r['seed']}: {r['error']}" if r["status"] != "ok" else r["error"]
                                             for r in mine if r["error"]}))
        for k in MEAN_KEYS:
            vals = [r[k] for r in ok if r.get(k) is not None]
            row[k], row[f"{k}_se"] = mean_se(vals)
            if k == "ate_m" and 0 < len(vals) < len(ok):
                row["error"] = "; ".join(x for x in (row["error"], f"ATE over {len(vals)}/{len(ok)} seeds") if x)
        rows.append(row)
    return rows


def _cell(row: dict, key: str, fmt: str, scale: float = 1.0) -> str:
    v, se = row.get(key), row.get(f"{key}_se")
    if v is None:
        return "-"
    text = format(v * scale, fmt)
    return text if se is None else f"{text} ± {format(se * scale, fmt)}"


def markdown(rows: list[dict]) -> str:
    """The per-case table (means ± standard errors over seeds)."""
    head = ["case", "skip", "frames", "runs", "posed (%)", "segments", "largest (%)", "ATE (m)", "keyframe ATE (m)",
            "rotation error (deg)", "relocalizations", "keyframes", "loop closures", "fps", "CPU s/frame", "fx (px)", "k1", "seeds", "notes"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        if r["status"] == "skipped":
            cells = [r["case"], str(r["skip"]), "-", "skipped"] + ["-"] * 14 + [r["error"]]
        else:
            cells = [r["case"], str(r["skip"]), str(r["frames"] or "-"), r["status"],
                     _cell(r, "posed_pct", ".1f"), _cell(r, "segments", ".2g"), _cell(r, "largest_pct", ".1f"),
                     _cell(r, "ate_m", ".3g"), _cell(r, "ate_kf_m", ".3g"), _cell(r, "rot_deg", ".3g"),
                     _cell(r, "relocalizations", ".2g"),
                     _cell(r, "keyframes", ".4g"), _cell(r, "loop_closures", ".2g"), _cell(r, "fps", ".1f"),
                     _cell(r, "cpu_s_per_frame", ".3f"), _cell(r, "focal_px", ".1f"), _cell(r, "k1", ".3f"),
                     r["seed"], r["error"][:200]]
        lines.append("| " + " | ".join(c.replace("|", "/") for c in cells) + " |")
    return "\n".join(lines)


def write_csv(path: Path, runs: list[dict], cases: list[dict]) -> None:
    cols = RUN_COLUMNS + [f"{k}_se" for k in MEAN_KEYS] + ["what"]
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(runs + cases)


def _override(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` of ``--set``: the value as a Python literal when it is one (numbers, booleans), else a string."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise SystemExit(f"--set {text!r}: expected KEY=VALUE")
    try:
        return key, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        return key, value


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a subset for day-to-day use (one seed unless --seeds)")
    ap.add_argument("--seeds", type=int, default=None, help="seeds 0..N-1 per case (default 3; --quick: 1)")
    ap.add_argument("--cases", default=None, help="comma-separated glob patterns of case names, e.g. 'kitti*,syn-*'")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds before a run is terminated (default 600)")
    ap.add_argument("--csv", type=Path, default=RESULTS / "bench_suite.csv", help="CSV to write")
    ap.add_argument("--no-save", action="store_true", help="do not write each run's output folder")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override for every case (SlamConfig.with_overrides key, e.g. mapper.method=local); "
                         "repeatable")
    args = ap.parse_args(argv)
    cases = select_cases(CASES, args.cases, args.quick)
    if args.list or not cases:
        for c in cases or CASES:
            print(f"{c.name:22s} {'quick' if c.quick else '     '} {c.what}")
        return 0 if cases else 2
    seeds = list(range(args.seeds if args.seeds is not None else (1 if args.quick else 3)))
    overrides = dict(_override(kv) for kv in args.set)
    jobs = [(replace(c, config={**c.config, **overrides}), s) for c in cases for s in seeds]
    version = code_version()
    print(f"[suite] {len(cases)} cases x {len(seeds)} seed(s) = {len(jobs)} runs in {args.jobs} workers, "
          f"slamkit {version}, load average {os.getloadavg()[0]:.1f}", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    runs = run_all(jobs, args.jobs, args.timeout, None if args.no_save else RESULTS / "suite",
                   log=lambda s: print(s, file=sys.stderr, flush=True))
    wall = time.perf_counter() - t0
    table = case_rows(cases, runs)
    write_csv(args.csv, runs, table)
    text = markdown(table)
    footer = (f"\n\n{len(jobs)} runs in {wall / 60:.1f} min wall ({args.jobs} workers), slamkit {version}, "
              f"{time.strftime('%Y-%m-%d %H:%M %Z')}, load average at the end {os.getloadavg()[0]:.1f}")
    args.csv.with_suffix(".md").write_text(text + footer + "\n")
    print(text + footer)
    print(f"written: {args.csv}, {args.csv.with_suffix('.md')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
