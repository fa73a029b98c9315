"""Robustness of slamkit (issue 7): every sequence of ../shared/data it can open, and synthetic sequences
made to break monocular SLAM (pure rotation, a loop, sudden fast motion, black frames, a corrupt frame).

For each case this runs slamkit with the default configuration and records, from ``Slam.summary()``:
whether the run finished without an exception, the fraction of frames posed (in any segment, and in the
largest one), the number of map segments, relocalizations, the ATE RMSE (Sim(3)) of the largest segment
against ground truth, the RMSE of the frame-to-frame rotation error (``rpe(..., delta=1, align="none")``,
defined even where a Sim(3) alignment is not: a path on a line), degenerate-motion frames (keyframe refused
for too little parallax), skipped and lost frames. A case whose data are missing or have no images is listed
as skipped with the reason.

Writes ``benchmarks/results/robustness.csv`` and ``robustness.json`` (every summary) and prints a Markdown
table.

Usage::

    nice -n 10 .venv/bin/python benchmarks/bench_robustness.py                    # every case
    nice -n 10 .venv/bin/python benchmarks/bench_robustness.py --max-frames 200   # cap long sequences
    nice -n 10 .venv/bin/python benchmarks/bench_robustness.py --cases kitti-07,black-frames
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pycolmap

pycolmap.logging.minloglevel = 2

from slamkit.config import SlamConfig  # noqa: E402
from slamkit.errors import SlamkitError  # noqa: E402
from slamkit.eval import ate, rpe  # noqa: E402
from slamkit.pipeline import Slam  # noqa: E402
from slamkit.sources import open_source  # noqa: E402
from slamkit.sources.base import FrameSource  # noqa: E402
from slamkit.sources.scene import default_room  # noqa: E402
from slamkit.sources.synthetic import DEFAULT_CAMERA, MOTIONS, SyntheticSource  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RESULTS = REPO / "benchmarks" / "results"


class Skip(Exception):
    """A case that cannot run here (missing data, no images); the message says why."""


# ----------------------------------------------------------------------------------------------- sources
class WithBadFrames(FrameSource):
    """``inner`` with the frames in ``bad`` replaced: "black" (covered lens) or "corrupt" (the file cannot
    be decoded: the read raises ImageReadError, as a truncated PNG does)."""

    def __init__(self, inner: FrameSource, bad: range, kind: str):
        self.inner, self.bad, self.kind = inner, bad, kind
        self.name, self.camera = f"{inner.name}+{kind}", inner.camera
        self.timestamps, self.frame_ids, self.gt_poses = inner.timestamps, inner.frame_ids, inner.gt_poses

    def _read(self, i: int):
        if i in self.bad and self.kind == "corrupt":
            from slamkit.errors import ImageReadError

            raise ImageReadError(f"{self.name}/frame{i}.png", "could not be decoded (corrupt or not an image)")
        image, path = self.inner._read(i)
        return (np.zeros_like(image) if i in self.bad else image), path


def synthetic(poses: np.ndarray, name: str) -> SyntheticSource:
    return SyntheticSource(default_room(), poses, DEFAULT_CAMERA, noise=1.0, name=name)


def whip_pan(n: int = 220, at: int = 100, degrees: float = 60.0, out: int = 4, hold: int = 4) -> np.ndarray:
    """Hand-held motion with a whip pan at frame ``at``: the gaze swings ``degrees`` about the vertical in
    ``out`` frames (15 degrees per frame for the defaults), stays there ``hold`` frames, swings back as
    fast, then the hand-held motion goes on."""
    base = MOTIONS["handheld"](n)
    steps = np.r_[np.linspace(0, 1, out + 1)[1:], np.ones(hold), np.linspace(1, 0, out + 1)[1:]]
    poses = [*base[:at]]
    for s in steps:
        a = np.radians(degrees * s)
        Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        T = base[at].copy()
        T[:3, :3] = Rz @ T[:3, :3]
        poses.append(T)
    return np.array(poses + [*base[at:]])


@dataclass(frozen=True)
class Case:
    name: str
    what: str
    open: Callable[[int | None], FrameSource]
    """max_frames -> source; raises Skip when the data are not there."""


def _shared(folder: str, **kw) -> Callable[[int | None], FrameSource]:
    def opener(max_frames):
        path = DATA / folder
        if not path.exists():
            raise Skip(f"{path} not found")
        return open_source(str(path), max_frames=max_frames, **kw)
    return opener


def _no_images(folder: str) -> Callable[[int | None], FrameSource]:
    def opener(max_frames):
        path = DATA / folder
        images = [p for p in path.rglob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg")] if path.exists() else []
        if not images:
            raise Skip(f"{path.relative_to(DATA.parent)}: ground truth and rgb.txt only, no images")
        return open_source(str(path), max_frames=max_frames)
    return opener


def _synthetic(make: Callable[[], FrameSource]) -> Callable[[int | None], FrameSource]:
    def opener(max_frames):
        src = make()
        if max_frames is not None and max_frames < len(src):
            inner = src.inner if isinstance(src, WithBadFrames) else src
            inner = SyntheticSource(default_room(), inner.gt_poses[:max_frames], inner.camera, noise=inner.noise,
                                    name=inner.name)
            src = WithBadFrames(inner, src.bad, src.kind) if isinstance(src, WithBadFrames) else inner
        return src
    return opener


CASES = [
    Case("7scenes-redkitchen", "Kinect 640x480, 600 frames, hand-held", _shared("7scenes-redkitchen")),
    Case("kitti-07", "KITTI odometry 07, 1226x370, 160 frames, car", _shared("kitti-odometry", sequence="07")),
    Case("tum-fr1-desk-9", "TUM fr1/desk, 9 frames", _shared("tum/rgbd_dataset_freiburg1_desk_9frames")),
    Case("tum-fr3-office-4", "TUM fr3/long_office, 4 frames 3.3 s apart",
         _shared("tum/rgbd_dataset_freiburg3_long_office_household_4frames")),
    *[Case(f"tum-{s}", f"TUM {s}", _no_images(f"tum/groundtruth-only/{s}")) for s in ("fr1_xyz", "fr2_xyz", "fr1_desk")],
    Case("video-kitti984", "test_kitti984.mp4, 1242x375, 268 frames, focal 984 px, no ground truth",
         _shared("video/test_kitti984.mp4", camera=984.0)),
    Case("default", "embedded default sequence, 360 frames (reference)", lambda m: open_source("default", max_frames=m)),
    Case("pure-rotation", "synthetic:rotation, 150 frames, zero baseline from the start",
         _synthetic(lambda: synthetic(MOTIONS["rotation"](150), "rotation"))),
    Case("translate-then-rotate", "40 frames sideways, then 110 frames of +-25 deg pan in place",
         _synthetic(lambda: synthetic(MOTIONS["translate-then-rotate"](150), "translate-then-rotate"))),
    Case("loop", "synthetic:loop, 240 frames, returns to its start",
         _synthetic(lambda: synthetic(MOTIONS["loop"](240), "loop"))),
    Case("sudden-jump", "hand-held, frames 100-129 of 260 dropped (0.45 m and the gaze change in one frame)",
         _synthetic(lambda: synthetic(np.delete(MOTIONS["handheld"](260), np.s_[100:130], axis=0), "jump"))),
    Case("whip-pan", "hand-held 220 frames, 60 deg whip pan at frame 100 (15 deg/frame, out and back)",
         _synthetic(lambda: synthetic(whip_pan(), "whip-pan"))),
    Case("black-frames", "hand-held 220 frames, frames 100-111 black",
         _synthetic(lambda: WithBadFrames(synthetic(MOTIONS["handheld"](220), "handheld"), range(100, 112),
                                          "black"))),
    Case("corrupt-frames", "hand-held 220 frames, frames 100 and 150 cannot be decoded",
         _synthetic(lambda: WithBadFrames(synthetic(MOTIONS["handheld"](220), "handheld"), range(100, 151, 50),
                                          "corrupt"))),
]


# ----------------------------------------------------------------------------------------------- running
def run_case(case: Case, max_frames: int | None, config: SlamConfig) -> dict:
    row: dict = {"case": case.name, "what": case.what}
    try:
        src = case.open(max_frames)
    except Skip as e:
        return {**row, "status": "skipped", "note": str(e)}
    t0 = time.perf_counter()
    slam = Slam(src, config)
    try:
        slam.run()
        status, note = "ok", ""
    except Exception as e:  # a crash is what this benchmark looks for: record it, go on
        status, note = "CRASH", f"{type(e).__name__}: {e}"
        traceback.print_exc()
    s = slam.summary()
    main = slam.main_segment
    gt = src.ground_truth()
    ate_m, rpe_deg, ate_note = None, None, ""
    if gt is None:
        ate_note = "no ground truth"
    elif main is None:
        ate_note = "no map"
    else:
        try:  # frame-to-frame rotation error: needs no alignment (defined when the ATE is not)
            rpe_deg = rpe(gt, slam.trajectory(), delta=1, align="none").rotation.rmse
        except SlamkitError:
            pass
        try:
            ate_m = ate(gt, slam.trajectory()).rmse
        except SlamkitError as e:
            ate_note = f"ATE undefined: {e}"
    n = s["frames"]
    return {
        **row, "status": status, "frames": n,
        "posed": s["fraction_posed"],
        "posed_main": len(main.frames) / n if main is not None and n else 0.0,
        "segments": len(s["segments"]), "relocalizations": s["relocalizations"], "ate_m": ate_m,
        "rpe_rot_deg": rpe_deg,
        "degenerate": s.get("frames_degenerate", 0), "skipped": s["frames_skipped"], "lost": s["frames_lost"],
        "keyframes": s["keyframes"], "wall_s": time.perf_counter() - t0,
        "note": "; ".join(x for x in (note, ate_note, s.get("not_initialized_reason") or "") if x),
        "summary": s,
    }


COLUMNS = ["case", "status", "frames", "posed", "posed_main", "segments", "relocalizations", "ate_m",
           "rpe_rot_deg", "degenerate", "skipped", "lost", "keyframes", "wall_s", "what", "note"]


def markdown(rows: list[dict]) -> str:
    head = ("| case | finished | frames | posed | posed (largest segment) | segments | relocalizations | "
            "ATE largest segment | rotation error per frame | degenerate-motion frames | skipped | lost | keyframes | wall (s) | notes |")
    lines = [head, "|" + "---|" * 15]
    for r in rows:
        if r["status"] == "skipped":
            lines.append(f"| {r['case']} | skipped |" + " |" * 12 + f" {r['note']} |")
            continue
        ate_s = "n/a" if r["ate_m"] is None else (f"{r['ate_m'] * 100:.2f} cm" if r["ate_m"] < 1 else f"{r['ate_m']:.2f} m")
        rot_s = "n/a" if r["rpe_rot_deg"] is None else f"{r['rpe_rot_deg']:.3f}°"
        note = r["note"][:160] + ("..." if len(r["note"]) > 160 else "")
        lines.append(
            f"| {r['case']} | {'yes' if r['status'] == 'ok' else '**CRASH**'} | {r['frames']} | {r['posed']:.1%} | "
            f"{r['posed_main']:.1%} | {r['segments']} | {r['relocalizations']} | {ate_s} | {rot_s} | {r['degenerate']} | "
            f"{r['skipped']} | {r['lost']} | {r['keyframes']} | {r['wall_s']:.0f} | {note.replace('|', '/')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", help=f"comma-separated subset of: {', '.join(c.name for c in CASES)}")
    ap.add_argument("--max-frames", type=int, default=None, help="use at most this many frames of each case")
    ap.add_argument("--config", default="default", help="slamkit preset (default: default)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="results folder (default: benchmarks/results)")
    args = ap.parse_args(argv)
    cases = CASES
    if args.cases:
        wanted = args.cases.split(",")
        unknown = set(wanted) - {c.name for c in CASES}
        if unknown:
            ap.error(f"unknown cases: {', '.join(sorted(unknown))}")
        cases = [c for c in CASES if c.name in wanted]
    config = SlamConfig.preset(args.config)
    rows = []
    for case in cases:
        print(f"[{time.strftime('%H:%M:%S')}] {case.name} ...", file=sys.stderr, flush=True)
        rows.append(run_case(case, args.max_frames, config))
        r = rows[-1]
        print(f"    {r['status']}" + (f": posed {r['posed']:.1%}, {r['segments']} segment(s), ATE {r['ate_m']}"
                                      if r["status"] != "skipped" else f": {r['note']}"), file=sys.stderr, flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "robustness.csv", "w", newline="") as f:
        w = csv.DictWriter(f, COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    (args.out / "robustness.json").write_text(json.dumps(
        {"argv": sys.argv[1:], "max_frames": args.max_frames, "config": args.config, "rows": rows},
        indent=1, default=float) + "\n")
    print(markdown(rows))
    print(f"\nwritten: {args.out / 'robustness.csv'}, {args.out / 'robustness.json'}", file=sys.stderr)
    return 1 if any(r["status"] == "CRASH" for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
