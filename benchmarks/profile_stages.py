"""Where a run's time goes: per stage, milliseconds per frame and share of the whole process's wall time.

Each profile is one fresh process (``python profile_stages.py --child ...``) that runs the whole job the
CLI runs: imports, opening the source, ``Slam`` (default configuration unless ``--set``), every step,
``finish()`` and ``save()`` to a temporary folder. The parent measures that process's wall time from spawn
to exit; the child splits it into rows:

* ``startup and exit``: interpreter start, imports and exit (the parent's wall time minus the intervals the
  child measured after its imports);
* ``open``: opening the source and building ``Slam`` (vocabulary and extractor set-up included);
* ``read + features (wait)``: time the main thread waits in ``FrameLoader.next`` for the frame being read
  and extracted (on the prefetch thread, ``SlamConfig.prefetch``; in line without it);
* one row per main-thread stage of ``StepResult.timings`` (initialize, track, relocalize, keyframe, map,
  ba, cull, loop, local_map, calibrate);
* ``final BA``, ``retrack`` and ``finish, rest`` (the session snapshot) of ``finish()``; ``save``
  (removing the temporary folder it wrote is not timed);
* ``unaccounted``: time of the frame loop no stage measured (records, results, callbacks). The rows are
  back-to-back intervals, so they add up to the wall time; this row is the check that the stages explain
  it: it stays under ``TOLERANCE`` of the wall (``tests/test_profile_stages.py``).

The stages on the prefetch thread (``read``, ``features``) are listed below the table with their own
totals: they overlap the main thread, so they are not part of the sum. The child's CPU time (user + system,
all its threads, from ``getrusage``) is the last row, with the cores it kept busy on average; CPU time
divided by the machine's cores is the shortest wall time any overlap of the same work could reach (the
bound printed below the table, as throughput against the first tree).

``--trees A B ...`` profiles other checkouts of slamkit with the same script, side by side and back to back
(``--repeat`` rounds, interleaved), so a before/after comparison runs on one machine under the same load::

    git worktree add /tmp/before 25846c0
    PYTHONPATH=$PWD .venv/bin/python benchmarks/profile_stages.py --trees /tmp/before . --repeat 3

Sequences (``--sequences``): ``7scenes`` (redkitchen frames 0-599) and ``kitti`` (odometry 07 frames 0-159)
from ../shared/data (skipped, with the reason, when absent), and ``synthetic`` (a rendered sequence,
always available; ``--frames`` sets its length). Output: a Markdown table on stdout and
``benchmarks/results/profile_stages.csv`` (``--csv``), one row per (sequence, tree, round, stage).
"""

from __future__ import annotations

import time

_T0 = time.perf_counter()  # the child's first instant: before its imports

import argparse  # noqa: E402
import ast  # noqa: E402
import csv  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RESULTS = REPO / "benchmarks" / "results"

SEQUENCES = {
    "7scenes": (DATA / "7scenes-redkitchen", 600),
    "kitti": (DATA / "kitti-odometry" / "sequences" / "07", 160),
    "synthetic": ("synthetic:handheld", 60),
}
"""name -> (source path or spec, frames)."""

PREFETCH_STAGES = ("read", "features")
"""Stages of ``StepResult.timings`` measured on the prefetch thread (not part of the main thread's sum)."""

CORES = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
"""Cores of this machine: with every one busy all the time, a run takes at least its CPU time / CORES."""

TOLERANCE = 0.05
"""The ``unaccounted`` row stays below this fraction of the wall time."""


# ----------------------------------------------------------------------------- the child: one profiled run
def profile_run(source_spec: str, frames: int, overrides: dict) -> dict:
    """Run the whole job once in this process and time it: {"rows": {stage: seconds}, "prefetch": {stage:
    seconds}, "frames", "posed", "measured_s"} (measured_s: everything timed here, from ``_T0``)."""
    import cv2  # noqa: F401  (before pycolmap)
    import pycolmap

    pycolmap.logging.minloglevel = 2
    from slamkit.config import SlamConfig
    from slamkit.pipeline import Slam
    from slamkit.sources import open_source

    rows: dict[str, float] = {}
    t = time.perf_counter()  # the rows below are back-to-back intervals from _T0: they add up to measured_s
    rows["imports"] = t - _T0
    config = SlamConfig().with_overrides(**overrides) if overrides else SlamConfig()
    source = open_source(source_spec, max_frames=frames)
    slam = Slam(source, config)
    loader, wait = slam.loader, [0.0]
    next_frame = loader.next

    def timed_next(cursor):  # the main thread's wait for a frame (instrumentation, same call)
        t = time.perf_counter()
        try:
            return next_frame(cursor)
        finally:
            wait[0] += time.perf_counter() - t

    loader.next = timed_next
    stages: dict[str, float] = {}
    prefetch: dict[str, float] = {}
    t_steps = time.perf_counter()
    rows["open"] = t_steps - t
    while not slam.done:
        for k, v in slam.step().timings.items():
            into = prefetch if k in PREFETCH_STAGES else stages
            into[k] = into.get(k, 0.0) + v
    before = dict(slam.timings)
    t_finish = time.perf_counter()
    rows["read + features (wait)"] = wait[0]
    rows.update(stages)
    rows["unaccounted"] = t_finish - t_steps - wait[0] - sum(stages.values())
    slam.finish()
    t_save = time.perf_counter()
    rows["final BA"] = slam.timings.get("ba", 0.0) - before.get("ba", 0.0)
    rows["retrack"] = slam.timings.get("track", 0.0) - before.get("track", 0.0)
    rows["finish, rest"] = t_save - t_finish - rows["final BA"] - rows["retrack"]
    with tempfile.TemporaryDirectory() as tmp:
        slam.save(Path(tmp) / "run")
        t_end = time.perf_counter()
    rows["save"] = t_end - t_save
    s = slam.summary()
    return {"rows": rows, "prefetch": prefetch, "frames": len(slam), "posed": s["frames_posed"],
            "keyframes": s["keyframes"], "slam_wall_s": s["wall_time_s"], "measured_s": t_end - _T0}


def _child_main(args) -> int:
    out = profile_run(args.source, args.frames, json.loads(args.overrides))
    print("PROFILE " + json.dumps(out), flush=True)
    return 0


# ----------------------------------------------------------------------------- the parent
def profile_tree(tree: Path, source: str, frames: int, overrides: dict) -> dict:
    """One child process with ``tree`` first on PYTHONPATH; adds its wall time and the ``startup`` row."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")]).rstrip(
        os.pathsep)}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--source", source, "--frames", str(frames),
           "--overrides", json.dumps(overrides)]
    t, used = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tree)
    wall = time.perf_counter() - t
    now = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (now.ru_utime - used.ru_utime) + (now.ru_stime - used.ru_stime)
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("PROFILE ")), None)
    if proc.returncode != 0 or line is None:
        raise RuntimeError(f"profiling {source} with {tree} failed (exit {proc.returncode}):\n{proc.stderr[-2000:]}")
    out = json.loads(line[len("PROFILE "):])
    rows = out["rows"]
    startup = wall - out["measured_s"] + rows.pop("imports")
    out["rows"] = {"startup and exit": startup, **rows}
    out["wall_s"] = wall
    out["cpu_s"] = cpu
    return out


def _table(name: str, labels: list[str], runs: dict[str, list[dict]]) -> str:
    """Markdown: one row per stage, per tree ms/frame (mean over rounds) and share of the wall time."""
    stages: list[str] = []
    for label in labels:
        for r in runs[label]:
            stages += [s for s in r["rows"] if s not in stages]
    frames = runs[labels[0]][0]["frames"]
    head = "| stage | " + " | ".join(f"{lb} ms/frame | {lb} share" for lb in labels) + " |"
    lines = [f"\n{name}: {frames} frames, mean of {len(runs[labels[0]])} round(s)\n", head,
             "|---" * (1 + 2 * len(labels)) + "|"]
    walls = {lb: sum(r["wall_s"] for r in runs[lb]) / len(runs[lb]) for lb in labels}
    for s in stages:
        cells = []
        for lb in labels:
            v = sum(r["rows"].get(s, 0.0) for r in runs[lb]) / len(runs[lb])
            cells.append(f"{1e3 * v / frames:.1f} | {100 * v / walls[lb]:.1f} %")
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    lines.append("| **whole process** | " + " | ".join(
        f"**{1e3 * walls[lb] / frames:.1f}** ({walls[lb]:.1f} s, {frames / walls[lb]:.1f} fps) | 100 %" for lb in labels)
        + " |")
    cpus = {lb: sum(r["cpu_s"] for r in runs[lb]) / len(runs[lb]) for lb in labels}
    lines.append("| CPU time, all threads | " + " | ".join(
        f"{1e3 * cpus[lb] / frames:.1f} ({cpus[lb]:.1f} s) | {cpus[lb] / walls[lb]:.2f} cores" for lb in labels) + " |")
    for lb in labels:
        pre = {k: sum(r["prefetch"].get(k, 0.0) for r in runs[lb]) / len(runs[lb]) for k in PREFETCH_STAGES}
        rounds = ", ".join(f"{r['wall_s']:.1f}" for r in runs[lb])
        lines.append(f"\n{lb}: wall per round {rounds} s; on the prefetch thread (overlapping): "
                     + ", ".join(f"{k} {1e3 * v / frames:.1f} ms/frame" for k, v in pre.items())
                     + f"; posed {runs[lb][0]['posed']}/{frames}, keyframes {runs[lb][0]['keyframes']}")
    if len(labels) > 1:
        base = walls[labels[0]]
        lines.append("\nthroughput vs " + labels[0] + ": " + ", ".join(f"{lb} {base / walls[lb]:.2f}x" for lb in labels[1:]))
    lines.append(f"\nbound with all {CORES} cores busy all the time (CPU time / {CORES})"
                 + (f", as throughput vs {labels[0]}" if len(labels) > 1 else "") + ": " + ", ".join(
                     f"{lb} {cpus[lb] / CORES:.1f} s" + (f" = {walls[labels[0]] / (cpus[lb] / CORES):.2f}x"
                                                         if len(labels) > 1 else "") for lb in labels))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequences", nargs="+", default=["7scenes", "kitti"], choices=sorted(SEQUENCES))
    ap.add_argument("--frames", type=int, help="frames per sequence (default: 600 / 160 / 60)")
    ap.add_argument("--trees", nargs="+", type=Path, default=[REPO],
                    help="slamkit checkouts to profile side by side (default: this one)")
    ap.add_argument("--repeat", type=int, default=1, help="rounds per tree, interleaved")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="SlamConfig override")
    ap.add_argument("--csv", type=Path, default=RESULTS / "profile_stages.csv")
    # the child process (internal)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--source", help=argparse.SUPPRESS)
    ap.add_argument("--overrides", default="{}", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return _child_main(args)
    overrides = {}
    for kv in args.set:
        k, sep, v = kv.partition("=")
        if not sep or not k:
            raise SystemExit(f"--set {kv!r}: expected KEY=VALUE")
        try:  # a Python literal when it is one (numbers, booleans), else a string (as bench_suite's --set)
            overrides[k] = ast.literal_eval(v)
        except (ValueError, SyntaxError):
            overrides[k] = v
    labels = {tree: (tree.resolve().name if tree.resolve() != REPO else "this tree") for tree in args.trees}
    if len(set(labels.values())) < len(labels):
        labels = {tree: str(tree) for tree in args.trees}
    out_rows = []
    for name in args.sequences:
        source, frames = SEQUENCES[name]
        frames = args.frames or frames
        if not str(source).startswith("synthetic:") and not Path(source).exists():
            print(f"[profile] skipping {name}: {source} not found (the shared data sets live in ../shared/data)")
            continue
        runs: dict[str, list[dict]] = {lb: [] for lb in labels.values()}
        for k in range(args.repeat):
            for tree, lb in labels.items():
                print(f"[profile] {name}, {lb}, round {k + 1}/{args.repeat} ...", file=sys.stderr, flush=True)
                r = profile_tree(tree, str(source), frames, overrides)
                runs[lb].append(r)
                for stage, v in r["rows"].items():
                    out_rows.append({"sequence": name, "tree": lb, "round": k, "stage": stage, "seconds": v,
                                     "ms_per_frame": 1e3 * v / r["frames"], "share": v / r["wall_s"],
                                     "wall_s": r["wall_s"], "cpu_s": r["cpu_s"], "frames": r["frames"]})
        print(_table(name, list(labels.values()), runs), flush=True)
    if out_rows:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        with open(args.csv, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(out_rows[0]))
            w.writeheader()
            w.writerows(out_rows)
        print(f"\nwrote {args.csv}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
