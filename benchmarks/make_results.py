"""Regenerate ``docs/results.md``: run the benchmarks on the data present and write the page with today's numbers.

One command for every figure of the results page (``make results``; ``make results-quick`` for a short check):

========== ==================================================================== ================================
section    what runs                                                            ``--quick`` runs
========== ==================================================================== ================================
suite      ``bench_suite.py --seeds 1``: the hard-motion suite, every case      ``--quick``'s synthetic cases
loop       ``bench_loop.py``: loop closing on and off (two-lap room, KITTI 07,  the two-lap room, 600 frames
           7-Scenes), one seed
speed      ``bench_slam.py --no-colmap``: slamkit's ATE, frames posed and       KITTI 07 only
           frames/s on 7-Scenes (600 frames) and KITTI 07 (160 frames) against
           the published references (COLMAP's own run is cached, not rerun)
table2     ``bench_features.py``: feature pipelines (the seed's Table 2),       ORB and SIFT, 60 + 40 frames
           7-Scenes 300 frames and KITTI 07
table3     ``slamkit ablate``: frame skip, initialization frames and flow       flow threshold on 40 KITTI
           threshold one at a time (the seed's Table 3), 7-Scenes 0-299 and     frames
           KITTI 07 0-159
========== ==================================================================== ================================

Each section runs its script in a subprocess, with a time budget (``--budget-scale`` multiplies it: on
2 cores shared with other jobs, load average 13-16, ``--quick`` took 16 min and two sections ran out of
their budgets);
a section whose data is absent, that fails or runs out of time says so on the page instead of keeping an old
number. The page gets the date, the commit (``+dirty`` when the work tree has changes), the machine and
its load, every command, each section's wall time and its CSV under ``benchmarks/results/``, plus plots in
``docs/results/``. Only the page and its plots change; nothing is appended.

Usage::

    PYTHONPATH=$PWD nice -n 5 .venv/bin/python benchmarks/make_results.py            # ~30 min target
    PYTHONPATH=$PWD .venv/bin/python benchmarks/make_results.py --quick              # < 5 min target
    PYTHONPATH=$PWD .venv/bin/python benchmarks/make_results.py --only loop,speed    # some sections
    PYTHONPATH=$PWD .venv/bin/python benchmarks/make_results.py --quick --out /tmp/results.md
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import os
import platform
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "benchmarks" / "results"
DOCS = ROOT / "docs"
KITTI07 = DATA / "kitti-odometry" / "sequences" / "07"
SCENES7 = DATA / "7scenes-redkitchen"


@dataclass
class Section:
    """One part of the page: the commands that make it (full and ``--quick``), the data it needs."""

    key: str
    title: str
    what: str
    """What the table measures and how to read it (Markdown)."""
    full: list[list[str]]
    quick: list[list[str]]
    csv: str
    """The CSV (under ``benchmarks/results/``) the section's last command writes."""
    needs: list[Path] = field(default_factory=list)
    """Data that must exist for any of it to run (sections with data of their own check it themselves)."""
    budget_s: float = 900.0
    quick_budget_s: float = 150.0
    plot: tuple[str, str, str] | None = None
    """(label column, value column, axis label) of the bar chart drawn from the CSV, or None."""


def _py(script: str, *args: str) -> list[str]:
    return [sys.executable, str(ROOT / "benchmarks" / script), *args]


def _ablate(source: Path, grid: str, out: str, frames: int) -> list[str]:
    return [sys.executable, "-m", "slamkit.cli", "ablate", str(source), "--grid", grid, f"max_frames={frames}",
            "--workers", "1", "-q", "--out", str(RESULTS / "table3" / out)]


def sections() -> list[Section]:
    table3_full = [_ablate(src, f"{name}={values}", f"{tag}-{name}", frames)
                   for tag, src, frames in (("7scenes", SCENES7, 300), ("kitti07", KITTI07, 160))
                   for name, values in (("frame_skip", "1,2,5"), ("init_frames", "10,20,40"),
                                        ("flow_threshold", "0.02,0.05,0.1"))]
    return [
        Section("suite", "Hard-motion suite",
                "Every sequence of `../shared/data` at its natural rate and faster, the driving clip and the "
                "synthetic fast-motion sequences (`benchmarks/bench_suite.py`). ATE in metres after Sim(3) "
                "alignment of the largest map segment; *posed* counts every segment.",
                [_py("bench_suite.py", "--seeds", "1", "--no-save", "--csv", str(RESULTS / "bench_suite.csv"))],
                [_py("bench_suite.py", "--quick", "--seeds", "1", "--cases", "syn-*", "--no-save",
                     "--csv", str(RESULTS / "bench_suite.csv"))],
                "bench_suite.csv", budget_s=1200, quick_budget_s=400, plot=("case", "ate_m", "ATE [m]")),
        Section("loop", "Loop closure",
                "slamkit with loop closing on (the default) and off (`benchmarks/bench_loop.py`): the synthetic "
                "room driven round twice, and two real sequences that must not get worse. ATE in metres.",
                [_py("bench_loop.py", "--cases", "two-lap", "kitti-07", "7scenes", "--seeds", "1", "--frames",
                     "1000", "--csv", str(RESULTS / "bench_loop.csv"))],
                [_py("bench_loop.py", "--cases", "two-lap", "--seeds", "1", "--frames", "600",
                     "--csv", str(RESULTS / "bench_loop.csv"))],
                "bench_loop.csv", budget_s=900, quick_budget_s=400),
        Section("speed", "Accuracy and speed on the real sequences",
                "slamkit (default configuration) on 7-Scenes redkitchen frames 0-599 and KITTI 07 frames 0-159 "
                "(`benchmarks/bench_slam.py --no-colmap`), beside the published ORB-SLAM2 and COLMAP numbers "
                "(not run here). ATE in metres; frames/s end to end on this machine under the load below.",
                [_py("bench_slam.py", "--no-colmap", "--out", str(RESULTS / "slam_vs_colmap.csv"))],
                [_py("bench_slam.py", "--no-colmap", "--sequences", "kitti-07",
                     "--out", str(RESULTS / "slam_vs_colmap.csv"))],
                "slam_vs_colmap.csv", budget_s=900, quick_budget_s=400),
        Section("table2", "Feature pipelines (the seed's Table 2)",
                "Every feature pipeline that can run here (learned ones need torch and their weights) "
                "(`benchmarks/bench_features.py`). ATE in metres.",
                [_py("bench_features.py", "--frames", "300", "--cores", "0",
                     "--out", str(RESULTS / "bench_features.csv"))],
                [_py("bench_features.py", "--frames", "60", "--kitti-frames", "40", "--pipelines", "orb", "sift",
                     "--cores", "0", "--out", str(RESULTS / "bench_features.csv"))],
                "bench_features.csv", budget_s=900, quick_budget_s=400,
                plot=("pipeline", "ate_rmse_m", "ATE [m]")),
        Section("table3", "Parameter sweeps (the seed's Table 3)",
                "One parameter at a time, every other at its default (`slamkit ablate`, one run per value). "
                "Each sweep's folder under `benchmarks/results/table3/` has `results.csv`, `results.md` and "
                "`effects.png`.",
                table3_full,
                [_ablate(KITTI07, "flow_threshold=0.02,0.05,0.1", "kitti07-flow_threshold", 40)],
                "table3", needs=[KITTI07], budget_s=1800, quick_budget_s=400),
    ]


# ------------------------------------------------------------------------------------------------ running


@dataclass
class Outcome:
    section: Section
    commands: list[list[str]]
    seconds: float = 0.0
    tables: list[str] = field(default_factory=list)
    problem: str = ""
    plots: list[Path] = field(default_factory=list)
    started: str = ""
    """When the section started (UTC), the commit and the machine's load then."""


def last_table(text: str) -> str:
    """The last Markdown table (consecutive lines starting with '|') printed in ``text``."""
    blocks, cur = [], []
    for line in text.splitlines():
        if line.startswith("|"):
            cur.append(line.rstrip())
        elif cur:
            blocks.append(cur)
            cur = []
    if cur:
        blocks.append(cur)
    return "\n".join(blocks[-1]) if blocks else ""


def run_section(sec: Section, quick: bool, log_dir: Path, budget_scale: float = 1.0) -> Outcome:
    cmds = sec.quick if quick else sec.full
    out = Outcome(sec, cmds, started=f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M} UTC, commit {commit()}, "
                                     f"load average {os.getloadavg()[0]:.1f}")
    missing = [p for p in sec.needs if not p.exists()]
    if missing:
        out.problem = "not run: " + ", ".join(str(p) for p in missing) + " not found"
        return out
    budget = (sec.quick_budget_s if quick else sec.budget_s) * budget_scale
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    t0 = time.monotonic()
    for i, cmd in enumerate(cmds):
        if sec.key == "table3":  # a sweep folder resumes finished runs: start from nothing
            shutil.rmtree(cmd[cmd.index("--out") + 1], ignore_errors=True)
        left = budget - (time.monotonic() - t0)
        log = log_dir / f"{sec.key}-{i}.log"
        print(f"[results] {sec.key}: {' '.join(_shown(c) for c in cmd)}  (budget {left:.0f} s, log {log})", flush=True)
        with open(log, "w") as f:  # its own process group: a run out of time ends with its worker processes
            proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=f, text=True,
                                    start_new_session=True)
            try:
                stdout, _ = proc.communicate(timeout=max(left, 1.0))
            except subprocess.TimeoutExpired:
                _stop_group(proc)
                out.problem = f"stopped after its time budget of {budget:.0f} s (command {i + 1} of {len(cmds)})"
                break
        (log.with_suffix(".out")).write_text(stdout)
        if sec.key == "table3":
            sweep = Path(cmd[cmd.index("--out") + 1])
            out.tables.append(f"**{sweep.name}**\n\n" + (_table3_rows(sweep) or "(no runs)"))
            if (sweep / "effects.png").is_file():
                out.plots.append(sweep / "effects.png")
        elif proc.returncode == 0:
            out.tables.append(last_table(stdout))
        if proc.returncode != 0:
            out.problem = f"command {i + 1} exited with status {proc.returncode} (see {log})"
            break
    out.seconds = time.monotonic() - t0
    return out


def _stop_group(proc: subprocess.Popen) -> None:
    """End a command and every process it started (SIGTERM to its group, SIGKILL after 10 s)."""
    for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 5)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue


def _shown(arg: str) -> str:
    """A command argument as the page shows it: paths relative to the repository, python as `python`."""
    if arg == sys.executable:
        return "python"
    for base, name in ((ROOT, ""), (DATA, "../shared/data/")):
        if arg.startswith(str(base) + os.sep):
            return name + os.path.relpath(arg, base)
    return arg


def _table3_rows(sweep: Path) -> str:
    """The sweep's own results table: one row per value with ATE, frames posed, keyframes and time."""
    path = sweep / "results.csv"
    if not path.is_file():
        return ""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return ""
    param = sweep.name.split("-", 1)[-1]  # the folder is named <data>-<parameter>
    preferred = [param, "status", "ate_rmse_m", "ate_keyframes_rmse_m", "frames_posed", "frames", "keyframes",
                 "fps", "wall_s"]
    wanted = [c for c in preferred if c in rows[0]]
    if len(wanted) < 3:  # another layout: the first columns as they come
        wanted = [c for c in rows[0] if c not in ("run_id", "source", "config", "error", "out_dir", "seed")
                  and not c.startswith("_")][:10]
    lines = ["| " + " | ".join(wanted) + " |", "|" + "---|" * len(wanted)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(c, "")) for c in wanted) + " |")
    return "\n".join(lines)


def _fmt(v: str) -> str:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return str(v).replace("|", "/")
    if x != x:
        return "–"
    return f"{x:.4g}"


# ------------------------------------------------------------------------------------------------ the page


def bar_plot(csv_path: Path, label: str, value: str, ylabel: str, title: str, out: Path) -> Path | None:
    """A bar chart of ``value`` per ``label`` (mean over rows with a number), or None when the CSV lacks them."""
    if not csv_path.is_file():
        return None
    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    groups: dict[str, list[float]] = {}
    for r in rows:
        try:
            v = float(r.get(value, ""))
        except ValueError:
            continue
        if v == v and r.get(label):
            name = r[label] + (f" ({r['sequence']})" if r.get("sequence") and label != "sequence" else "")
            groups.setdefault(name, []).append(v)
    if not groups:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    names = list(groups)
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(names) + 1.2))
    ax.barh(names, [sum(v) / len(v) for v in groups.values()], color="tab:blue")
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel(ylabel + " (log scale; mean over the rows of the CSV)")
    ax.set_title(title)
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def earlier_sections(path: Path) -> dict[str, str]:
    """Section title -> its text (below the heading) on an existing page written by this script."""
    if not path.is_file():
        return {}
    text = path.read_text()
    out = {}
    for block in text.split("\n## ")[1:]:
        title, _, body = block.partition("\n")
        out[title.strip()] = body
    return out


def machine() -> str:
    import cv2
    import numpy as np
    import pycolmap
    load = os.getloadavg()
    return (f"{platform.node()}: {os.cpu_count()} cores, load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} "
            f"(1 / 5 / 15 min) at the start; Python {platform.python_version()}, pycolmap {pycolmap.__version__}, "
            f"OpenCV {cv2.__version__}, numpy {np.__version__}")


def commit() -> str:
    def git(*a):
        return subprocess.run(["git", "-C", str(ROOT), *a], capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "--short", "HEAD") or "unknown"
    changed = [ln.split()[-1] for ln in git("status", "--porcelain", "--untracked-files=no").splitlines()]
    dirty = any(not p.startswith("docs/results") for p in changed)  # the page being rewritten does not count
    return head + ("+dirty" if dirty else "")


def page(outcomes: list[Outcome], quick: bool, started: dt.datetime, header: dict, plot_dir: Path, out: Path,
         kept: dict[str, str] | None = None) -> str:
    """The page: a header, then one section per outcome (or, with ``kept``, the section text of an earlier
    run for the sections not run now, in the order of :func:`sections`)."""
    total = sum(o.seconds for o in outcomes)
    lines = [
        "# Results",
        "",
        "Generated by `benchmarks/make_results.py" + (" --quick" if quick else "") + "` (`make results"
        + ("-quick" if quick else "") + "`); do not edit by hand — run it again. Each section says when it ran, "
        "on which commit and under what load; every figure in it comes from that run.",
        "",
        f"- **Date**: {started:%Y-%m-%d %H:%M} UTC, {total / 60:.1f} min in all"
        + (" (some sections kept from an earlier run: see each)" if kept else ""),
        f"- **Commit**: {header['commit']}",
        f"- **Machine**: {header['machine']}",
        f"- **Mode**: {'quick (short subsets: a check that everything runs, not the reference numbers)' if quick else 'full'}",
        "- **How the numbers are made**: `benchmarks/README.md`; older numbers and how they moved: "
        "`benchmarks/HISTORY.md`.",
        "",
    ]
    done = {o.section.key: o for o in outcomes}
    for sec in sections():
        if sec.key not in done:
            if kept and sec.title in kept:
                lines += [f"## {sec.title}", "", kept[sec.title].strip(), ""]
            continue
        o = done[sec.key]
        lines += [f"## {sec.title}", "", sec.what, ""]
        lines += ["```", *(" ".join(_shown(a) for a in c) for c in o.commands), "```", ""]
        lines.append(f"Ran {o.started}: {o.seconds:.0f} s"
                     + (f"; CSV: `benchmarks/results/{sec.csv}`" if sec.csv else "") + ".")
        lines.append("")
        if o.problem:
            lines += [f"**Not complete**: {o.problem}.", ""]
        for t in o.tables:
            if t:
                lines += [t, ""]
        plots = list(o.plots)
        if sec.plot and not o.problem:
            p = bar_plot(RESULTS / sec.csv, *sec.plot, sec.title, plot_dir / f"{sec.key}.png")
            if p:
                plots.append(p)
        for i, p in enumerate(plots):
            dest = plot_dir / (p.name if p.parent == plot_dir else f"{sec.key}-{p.parent.name}-{p.name}")
            if p != dest:
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(p, dest)
            lines += [f"![{sec.title}]({os.path.relpath(dest, out.parent)})", ""]
    return "\n".join(lines).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="short subsets of every section (< 5 min target)")
    ap.add_argument("--only", default=None, help="comma-separated sections: " + ",".join(s.key for s in sections()))
    ap.add_argument("--out", type=Path, default=DOCS / "results.md", help="the page to write (docs/results.md)")
    ap.add_argument("--list", action="store_true", help="print the commands and exit")
    ap.add_argument("--budget-scale", type=float, default=1.0,
                    help="multiply every section's time budget (e.g. 3 on a machine shared with other jobs)")
    args = ap.parse_args(argv)
    chosen = sections()
    if args.only:
        keys = {k.strip() for k in args.only.split(",")}
        unknown = keys - {s.key for s in chosen}
        if unknown:
            ap.error(f"--only: unknown section(s) {', '.join(sorted(unknown))}")
        chosen = [s for s in chosen if s.key in keys]
    if args.list:
        for s in chosen:
            for c in (s.quick if args.quick else s.full):
                print(f"{s.key}: {' '.join(_shown(a) for a in c)}")
        return 0
    started = dt.datetime.now(dt.timezone.utc)
    header = {"commit": commit(), "machine": machine()}
    log_dir = RESULTS / "make_results"
    log_dir.mkdir(parents=True, exist_ok=True)
    outcomes = []
    for s in chosen:
        o = run_section(s, args.quick, log_dir, args.budget_scale)
        print(f"[results] {s.key}: {o.seconds:.0f} s" + (f" — {o.problem}" if o.problem else ""), flush=True)
        outcomes.append(o)
    plot_dir = args.out.parent / args.out.stem
    kept = earlier_sections(args.out) if args.only else None  # --only: the other sections stay as they were
    text = page(outcomes, args.quick, started, header, plot_dir, args.out, kept)
    tmp = args.out.with_suffix(".md.tmp")
    tmp.write_text(text)
    os.replace(tmp, args.out)
    print(f"[results] wrote {args.out} ({sum(o.seconds for o in outcomes) / 60:.1f} min)")
    return 0 if not any(o.problem and not o.problem.startswith("not run") for o in outcomes) else 1


if __name__ == "__main__":
    raise SystemExit(main())
