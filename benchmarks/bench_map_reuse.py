"""Coming back to a map (issue 49): a second video localized in a first run's saved map, and the map extended.

For each case a first run maps the first part and is saved (a throwaway folder under ``--work``); the second
part is then run in that map (``Slam(source, config, map=RUN_DIR)``), once mapping and once
``localize_only=True``, and a single run over both parts is made for reference. Columns:

- ``posed_%``: frames of the second part posed (mapping / localize-only);
- ``under_map_cm``: ATE RMSE of the second part under the *first run's* Sim(3) alignment to its ground truth
  (what says the two share one frame), mapping / localize-only;
- ``own_cm``: the second part's ATE after its own Sim(3) (mapping);
- ``one_run_cm``: ATE of one run over both parts (7-Scenes, the city block) or of the first run (the room:
  its two walks are not one video);
- ``one_run_split_cm``: the same measure as ``under_map_cm`` made on that one run: its Sim(3) to the ground
  truth fitted on the first part's frames only, its error on the second part's (7-Scenes, the city block). A
  run's drift grows away from where it was aligned, so this, not ``one_run_cm``, is what a second run in the
  map can match: ``ratio_to_split`` is ``under_map_cm`` over it;
- ``fps``: frames per second of the second part, mapping / localize-only, and their ratio (``lo_speedup``, wall
  clock); ``lo_cpu_speedup``: the same ratio in process CPU seconds (all threads), which other jobs on the
  machine do not change.

Cases: ``7scenes`` (redkitchen frames 0-299 mapped, 300-599 in the map), ``room`` (the rendered room walked
round the ellipse twice, the second time on another, shaken path: ``loop?frames=120`` then
``loop?frames=80&jitter=1&seed=1``), ``block`` (the rendered city block driven once round in 500 frames, in two
halves of 250), ``never`` (the room's map, a street drive that never meets it).

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_map_reuse.py --cases 7scenes,room,block,never \\
        --work /tmp/map_reuse --csv /tmp/map_reuse.csv
"""

from __future__ import annotations

import argparse
import csv
import shutil
import sys
import time
from pathlib import Path

import numpy as np  # noqa: F401  (before pycolmap: see slamkit/__init__.py)
import pycolmap

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slamkit.config import SlamConfig  # noqa: E402
from slamkit.eval import ate  # noqa: E402
from slamkit.eval.map_alignment import error_under  # noqa: E402
from slamkit.pipeline import Slam  # noqa: E402
from slamkit.sources import open_source  # noqa: E402
from slamkit.sources.base import FrameRange  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
COLUMNS = ["case", "frames", "posed_%", "posed_lo_%", "under_map_cm", "under_map_lo_cm", "own_cm", "one_run_cm",
           "ratio_to_one_run", "one_run_split_cm", "ratio_to_split", "fps", "fps_lo", "lo_speedup", "lo_cpu_speedup",
           "keyframes_added", "segments", "note"]


def _run(source, folder: Path | None = None, **kw) -> tuple[Slam, float, float]:
    """(the finished run, its wall seconds, its process CPU seconds), saved to ``folder`` when given."""
    slam = Slam(source, SlamConfig(), **kw)
    t, cpu = time.perf_counter(), time.process_time()
    slam.run()
    wall = time.perf_counter() - t
    cpu = time.process_time() - cpu
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)
        slam.save(folder)
    return slam, wall, cpu


def _ate(slam: Slam) -> float:
    return ate(slam.source.ground_truth(), slam.trajectory()).rmse


def _parts(case: str):
    """(first source, second source, source of one run over both or None)."""
    if case == "7scenes":
        whole = open_source(f"7scenes:{DATA / '7scenes-redkitchen'}")
        return FrameRange(whole, 0, 300), FrameRange(whole, 300, 600), FrameRange(whole, 0, 600)
    if case == "room":
        return "synthetic:loop?frames=120", "synthetic:loop?frames=80&jitter=1&seed=1", None
    if case == "block":
        whole = open_source("synthetic:block-loop?frames=500&laps=1")
        return FrameRange(whole, 0, 250), FrameRange(whole, 250, 500), whole
    if case == "never":
        return "synthetic:loop?frames=120", "synthetic:street-drive?frames=60", None
    raise SystemExit(f"unknown case {case!r}")


def bench(case: str, work: Path) -> dict:
    first_src, second_src, whole_src = _parts(case)
    first_dir = work / f"{case}-first"
    first = _run(first_src, first_dir)[0]
    align = ate(first.source.ground_truth(), first.trajectory()).alignment
    mapped, wall, cpu = _run(second_src, map=first_dir)
    only, wall_lo, cpu_lo = _run(second_src, map=first_dir, localize_only=True)
    n = len(mapped.records)
    row = {"case": case, "frames": n}
    for tag, slam, w in (("", mapped, wall), ("_lo", only, wall_lo)):
        s = slam.summary()
        row[f"posed{tag}_%"] = round(100 * s["frames_posed"] / max(n, 1), 1)
        row[f"fps{tag}"] = round(n / w, 2)
        try:
            row[f"under_map{tag}_cm"] = round(100 * error_under(align, slam.trajectory(),
                                                                slam.source.ground_truth())["ate"]["rmse"], 3)
        except Exception as e:  # noqa: BLE001 - a row says why
            row[f"under_map{tag}_cm"] = f"n/a ({type(e).__name__})"
        if tag == "":
            row["keyframes_added"] = s["map"]["keyframes"] - s["map"]["keyframes_loaded"]
            row["segments"] = len(mapped.state.live_segments)
            row["note"] = s["map"].get("note", "")
    row["lo_speedup"] = round(row["fps_lo"] / row["fps"], 2)
    row["lo_cpu_speedup"] = round(cpu / cpu_lo, 2)
    try:
        row["own_cm"] = round(100 * _ate(mapped), 3)
    except Exception as e:  # noqa: BLE001
        row["own_cm"] = f"n/a ({type(e).__name__})"
    one = _run(whole_src)[0] if whole_src is not None else first
    row["one_run_cm"] = round(100 * _ate(one), 3)
    if isinstance(row["under_map_cm"], float):
        row["ratio_to_one_run"] = round(row["under_map_cm"] / row["one_run_cm"], 2)
    if whole_src is not None:  # the same measure on the one run: aligned on its first part, error on its second
        traj, gt = one.trajectory(), one.source.ground_truth()
        split = float(second_src.timestamps[0]) - 1e-6  # a FrameRange of the same video
        part_align = ate(gt, traj.subset(traj.timestamps < split)).alignment
        row["one_run_split_cm"] = round(100 * error_under(part_align, traj.subset(traj.timestamps >= split),
                                                          gt)["ate"]["rmse"], 3)
        if isinstance(row["under_map_cm"], float):
            row["ratio_to_split"] = round(row["under_map_cm"] / row["one_run_split_cm"], 2)
    return row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default="7scenes,room,block,never")
    p.add_argument("--work", required=True, help="a throwaway folder for the first runs (e.g. under /tmp)")
    p.add_argument("--csv", help="write the rows here")
    args = p.parse_args()
    pycolmap.logging.minloglevel = 2
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in args.cases.split(","):
        rows.append(bench(case, work))
        print(" | ".join(f"{k}={rows[-1].get(k, '')}" for k in COLUMNS), flush=True)
    print("| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS))
    for r in rows:
        print("| " + " | ".join(str(r.get(k, "")) for k in COLUMNS) + " |")
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            w = csv.DictWriter(f, COLUMNS)
            w.writeheader()
            w.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
