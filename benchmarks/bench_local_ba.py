"""Local bundle adjustment: Ceres (today's path) against the compiled kernel (``ba.engine = "compiled"``, issue 48).

Two measurements.

``problems`` (default): one run of a sequence with the default config; every local BA solve it makes (each
pass of each keyframe's local BA) is solved twice from the same map state, by Ceres as the stage does it
(``BundleAdjustmentConfig`` built from the map, pycolmap's bundle adjuster: "ceres build" and "ceres solve",
which includes pycolmap's own reading and writing of the map) and by the compiled engine ("extract": the
problem read from the map as arrays, "solve": the kernel, "write": the solution written back). The order
alternates from problem to problem, so machine load (the machine is shared) falls on both alike; the run then
goes on from Ceres' solution, as the default does. Each solution's cost is evaluated by the same function (the
config's loss, COLMAP's flat weights) on the same observations. Columns per sequence: problems, mean
keyframes / points / observations per problem, ms per solve of each part (mean), the final costs' ratio
(compiled / Ceres: median and worst), the iterations of each.

``rows``: whole runs with ``ba.engine`` "ceres" and "compiled" interleaved (one process, one after the other
per case and seed): ATE (m, Sim(3)-aligned, as ``bench_suite.py``), posed %, keyframes, and ``ba`` / total ms
per frame from the run's ``stage_ms_per_frame``.

Usage::

    PYTHONPATH=$PWD nice -n 10 .venv/bin/python benchmarks/bench_local_ba.py problems --cases 7scenes/skip5
    PYTHONPATH=$PWD nice -n 10 .venv/bin/python benchmarks/bench_local_ba.py rows --cases default,7scenes/skip5

Output: a Markdown table on stdout and ``benchmarks/results/bench_local_ba_<mode>.csv`` (``--csv PATH``).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import csv  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import slamkit  # noqa: E402,F401  (numpy and slamkit before pycolmap)

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_suite  # noqa: E402

import pycolmap  # noqa: E402

from slamkit import Slam, SlamConfig, ate, open_source  # noqa: E402
from slamkit.kernels.local_ba import LOSSES, _cost, local_bundle_adjustment  # noqa: E402
from slamkit.local_ba_problem import local_problem, write_back  # noqa: E402
from slamkit.stages import ba as ba_stage  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_CASE = bench_suite.Case("default", "rendered", "synthetic:default", what="the default rendered sequence")


def _cases(pattern: str) -> list:
    out = []
    for name in pattern.split(","):
        if name == "default":
            out.append(DEFAULT_CASE)
        else:
            out.extend(bench_suite.select_cases(bench_suite.CASES, name, False))
    return out


def _problem_cost(problem, T, X, loss: str, active) -> float:
    n = len(problem.obs_pose)
    return float(_cost(np.ascontiguousarray(T[:, :3, :3]), np.ascontiguousarray(T[:, :3, 3]), np.ascontiguousarray(X),
                       problem.obs_pose, problem.obs_point, problem.obs_xy, np.ones(n), active, problem.camera,
                       LOSSES[loss], 1.0, ba_stage._EPS, True))


def measure_problems(case, seed: int = 0) -> list[dict]:
    """Every local BA solve of one default run of ``case``, by Ceres and by the kernel (module docstring)."""
    rows: list[dict] = []
    original = ba_stage.BundleAdjuster._solve_local

    def both(self, slam_map, window):
        c = self.config
        t0 = time.perf_counter()
        start = local_problem(slam_map, window, c.local_max_track_length)
        extract_ms = 1e3 * (time.perf_counter() - t0)
        Xc = np.einsum("nij,nj->ni", start.cam_from_world[start.obs_pose, :, :3], start.points[start.obs_point])
        active = np.ones(len(Xc), bool)  # COLMAP's cost: an observation behind its camera adds 0
        row = {"case": case.name, "problem": len(rows), "keyframes": int((~start.pose_fixed).sum()),
               "held_keyframes": int(start.pose_fixed.sum()), "points": len(start.point3D_ids),
               "held_points": int(start.point_fixed.sum()), "observations": len(start.obs_pose),
               "extract_ms": extract_ms}

        def ceres():
            t0 = time.perf_counter()
            cfg, _ = self._local_config(slam_map, window)
            t1 = time.perf_counter()
            summary = slam_map.bundle_adjust(self._options(c.local_iterations), cfg)  # forgets moved positions
            t2 = time.perf_counter()
            after = local_problem(slam_map, window, c.local_max_track_length)
            row.update(ceres_build_ms=1e3 * (t1 - t0), ceres_solve_ms=1e3 * (t2 - t1),
                       ceres_iterations=int(summary.ceres_summary.num_successful_steps
                                             + summary.ceres_summary.num_unsuccessful_steps),
                       ceres_termination=str(summary.termination_type).split(".")[-1],
                       ceres_cost=_problem_cost(start, after.cam_from_world, after.points, c.loss, active))
            return after

        def compiled():
            t0 = time.perf_counter()
            problem = local_problem(slam_map, window, c.local_max_track_length)
            t1 = time.perf_counter()
            res = local_bundle_adjustment(problem.cam_from_world, problem.points, problem.obs_pose,
                                          problem.obs_point, problem.obs_xy, problem.camera, None,
                                          problem.pose_fixed, problem.point_fixed, problem.gauge, c.loss, 1.0,
                                          c.local_iterations, c.function_tolerance,
                                          ba_stage._COLMAP_SOLVER["parameter_tolerance"],
                                          ba_stage._COLMAP_SOLVER["gradient_tolerance"], min_depth=ba_stage._EPS,
                                          behind_camera="zero")
            t2 = time.perf_counter()
            if res.success:
                write_back(slam_map, problem, res.cam_from_world, res.points)
            t3 = time.perf_counter()
            row.update(compiled_extract_ms=1e3 * (t1 - t0), compiled_solve_ms=1e3 * (t2 - t1),
                       compiled_write_ms=1e3 * (t3 - t2), compiled_iterations=res.iterations,
                       compiled_termination=res.termination,
                       compiled_cost=_problem_cost(start, res.cam_from_world, res.points, c.loss, active))
            return res

        if len(rows) % 2 == 0:
            after = ceres()
            write_back(slam_map, start, start.cam_from_world, start.points)
            res = compiled()
            write_back(slam_map, after, after.cam_from_world, after.points)  # go on from Ceres' solution
        else:
            res = compiled()
            write_back(slam_map, start, start.cam_from_world, start.points)
            after = ceres()
        # how far apart the two solutions are: camera centres (world units) and points, largest
        k = len(window)
        centre = lambda T: -np.einsum("kji,kj->ki", T[:, :3, :3], T[:, :3, 3])  # noqa: E731
        row["centre_gap"] = float(np.linalg.norm(centre(res.cam_from_world[:k]) - centre(after.cam_from_world[:k]),
                                                 axis=1).max())
        row["point_gap_median"] = float(np.median(np.linalg.norm(res.points - after.points, axis=1))) \
            if len(res.points) == len(after.points) else float("nan")
        row["initial_cost"] = _problem_cost(start, start.cam_from_world, start.points, c.loss, active)
        rows.append(row)
        return row["ceres_termination"], len(start.point3D_ids)

    ba_stage.BundleAdjuster._solve_local = both
    try:
        config = SlamConfig().with_overrides(seed=seed, frame_skip=case.skip, **case.config)
        Slam(open_source(case.source_spec(seed), **case.kw), config).run()
    finally:
        ba_stage.BundleAdjuster._solve_local = original
    return rows


def problems_table(rows: list[dict]) -> str:
    lines = ["| case | problems | keyframes (+held) | points (held) | observations | extract ms | compiled solve ms "
             "| write ms | compiled total ms | Ceres build ms | Ceres solve ms | Ceres total ms | cost compiled/Ceres "
             "median (worst) | iterations compiled / Ceres | centre gap median (max) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for case in dict.fromkeys(r["case"] for r in rows):
        rs = [r for r in rows if r["case"] == case]
        m = lambda k: float(np.mean([r[k] for r in rs]))  # noqa: E731
        ratio = np.array([r["compiled_cost"] / r["ceres_cost"] for r in rs if 0 < r["ceres_cost"] < np.inf])
        comp = m("compiled_extract_ms") + m("compiled_solve_ms") + m("compiled_write_ms")
        ceres = m("ceres_build_ms") + m("ceres_solve_ms")
        lines.append(
            f"| {case} | {len(rs)} | {m('keyframes'):.1f} (+{m('held_keyframes'):.1f}) | {m('points'):.0f} "
            f"({m('held_points'):.0f}) | {m('observations'):.0f} | {m('compiled_extract_ms'):.2f} | "
            f"{m('compiled_solve_ms'):.2f} | {m('compiled_write_ms'):.2f} | {comp:.2f} | {m('ceres_build_ms'):.2f} | "
            f"{m('ceres_solve_ms'):.2f} | {ceres:.2f} | {np.median(ratio):.5f} ({ratio.max():.4f}) | "
            f"{m('compiled_iterations'):.1f} / {m('ceres_iterations'):.1f} | "
            f"{np.median([r['centre_gap'] for r in rs]):.2e} ({max(r['centre_gap'] for r in rs):.2e}) |")
    return "\n".join(lines)


def run_row(case, seed: int, engine: str, overrides: dict | None = None) -> dict:
    """One whole run of ``case`` with ``ba.engine = engine`` (and ``overrides``): ATE, posed %, keyframes, ba and
    total ms/frame."""
    settings = "".join(f" {k}={v}" for k, v in (overrides or {}).items())
    row = {"case": case.name, "seed": seed, "engine": engine + settings}
    t0 = time.perf_counter()
    config = SlamConfig().with_overrides(seed=seed, frame_skip=case.skip,
                                         **{**case.config, **(overrides or {}), "ba.engine": engine})
    source = open_source(case.source_spec(seed), **case.kw)
    slam = Slam(source, config)
    slam.run()
    wall = time.perf_counter() - t0
    s, traj, gt = slam.summary(), slam.trajectory(), bench_suite._ground_truth(case, source)
    ms = s["stage_ms_per_frame"]
    row |= {"frames": s["frames"], "posed_pct": 100.0 * s["frames_posed"] / s["frames"],
            "largest_pct": 100.0 * len(traj) / s["frames"], "keyframes": s["keyframes"],
            "ba_ms": ms.get("ba", 0.0), "total_ms": 1e3 * wall / s["frames"],
            "ate_m": float(ate(gt, traj, align="sim3").rmse) if gt is not None and len(traj) >= 3 else None}
    return row


def rows_table(rows: list[dict]) -> str:
    lines = ["| case | seed | engine | ATE (m) | posed % | largest % | keyframes | ba ms/frame | total ms/frame |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        a = "-" if r["ate_m"] is None else f"{r['ate_m']:.4f}"
        lines.append(f"| {r['case']} | {r['seed']} | {r['engine']} | {a} | {r['posed_pct']:.1f} | "
                     f"{r['largest_pct']:.1f} | {r['keyframes']} | {r['ba_ms']:.1f} | {r['total_ms']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", nargs="?", default="problems", choices=("problems", "rows"))
    ap.add_argument("--cases", default="7scenes/skip5", help="comma-separated case names (bench_suite's, or default)")
    ap.add_argument("--seeds", type=int, default=1, help="seeds per case (default 1)")
    ap.add_argument("--first-seed", type=int, default=0, help="the first seed (default 0)")
    ap.add_argument("--csv", type=Path, default=None)
    ap.add_argument("--engines", default="ceres,compiled", help="rows: the engines to run (default ceres,compiled)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="rows: a config override for every run (a control: e.g. ba.function_tolerance=1.1e-6)")
    args = ap.parse_args(argv)
    pycolmap.logging.minloglevel = 2
    cases = _cases(args.cases)
    print(f"[bench_local_ba] {args.mode}: {[c.name for c in cases]}, load average {os.getloadavg()[0]:.1f} "
          "(the machine is shared: the two engines are interleaved)", file=sys.stderr, flush=True)
    rows: list[dict] = []
    for case in cases:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            if args.mode == "problems":
                rows += measure_problems(case, seed)
            else:
                engines = args.engines.split(",")
                overrides = dict(bench_suite._override(kv) for kv in args.set)
                for engine in (engines if seed % 2 == 0 else engines[::-1]):
                    rows.append(run_row(case, seed, engine, overrides))
                    print(rows_table(rows[-1:]).splitlines()[-1], file=sys.stderr, flush=True)
    table = problems_table(rows) if args.mode == "problems" else rows_table(rows)
    path = args.csv or RESULTS / f"bench_local_ba_{args.mode}.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        keys = list(dict.fromkeys(k for r in rows for k in r))
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)
    print(table + f"\n\nload average at the end {os.getloadavg()[0]:.1f}, {time.strftime('%Y-%m-%d %H:%M %Z')}")
    print(f"written: {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
