"""Evaluation report of a run folder: ATE/RPE (Sim(3)) over all frames and over keyframes, plots, and a
markdown + HTML page in the run folder.

>>> result = evaluate_run("runs/demo")      # doctest: +SKIP
>>> result["all_frames"]["ate"]["rmse"]     # metres                              # doctest: +SKIP

Writes into ``RUN``: ``report.md``, ``report.html``, ``evaluation.json`` and ``plots/`` (trajectory
top and side views coloured by error, error over time, time per stage), plus ``map.html`` (the
static 3D map of :class:`slamkit.viz.meshcat_view.MapView`) when it can be made without a browser;
otherwise the report links ``points.ply``. matplotlib and meshcat are imported only when plotting.
"""

from __future__ import annotations

import html
import json
import os
import re
from pathlib import Path

import numpy as np

from ..errors import OutputError, SessionError, SlamkitError, shown
from ..io import atomic_dir, atomic_write_text
from ..io.run_dir import (PLOT_FILES, REPORT_FILES, REPORT_MARKER, REPORT_MARKS, RUN_MARKER, check_output,
                           is_own_report_file, is_run_folder, out_dir_lock, write_listing)
from ..io.saved import check_json, check_run
from ..io.trajectory import check_input_file, read_tum
from ..types import Trajectory
from .map_alignment import map_alignment_error
from .metrics import ate, matched_warning, rpe
from .pairing import load_pair, read_frame_table

__all__ = ["evaluate_run"]


_MD_MARK, _HTML_MARK, _MAP_MARK = REPORT_MARKS["report.md"], REPORT_MARKS["report.html"], REPORT_MARKS["map.html"]
"""The marks that make a report file slamkit's (:data:`slamkit.io.run_dir.REPORT_OWN_CONTENT`): a run folder's
replacement keeps, and ``eval`` never overwrites, a file without one."""


def _stats(gt: Trajectory, est: Trajectory, max_dt: float) -> tuple[dict, object, object]:
    a = ate(gt, est, max_dt=max_dt)
    try:
        r = rpe(gt, est, max_dt=max_dt)
        rd = r.to_dict()
    except SlamkitError as e:  # too few matched poses for a pair
        r, rd = None, {"error": str(e)}
    return {"ate": a.to_dict(), "rpe": rd}, a, r


def evaluate_run(run_dir: str | os.PathLike, gt: str | os.PathLike | None = None, *, max_dt: float = 0.02,
                 plots: bool = True, map_view: bool = True, out: str | os.PathLike | None = None) -> dict:
    """ATE and RPE (Sim(3) alignment, evo's conventions; metres / degrees) of ``RUN/trajectory_tum.txt``
    over all frames and of ``RUN/keyframes_tum.txt`` over keyframes, against ``gt`` (TUM or KITTI file, a
    KITTI file paired by frame index: :mod:`slamkit.eval.pairing`; default ``RUN/groundtruth_tum.txt``);
    writes the report (see the module docstring) and returns the numbers with the paths written.

    The report goes into ``run_dir`` only when it is a slamkit run folder, and replaces a report file there
    only when slamkit wrote it (its marker); elsewhere (another tool's results) ``out`` must say where: a new
    or empty folder, or an earlier report folder (``.slamkit-report``), replaced atomically. OutputError
    before any work otherwise. SlamkitError naming the file when the run folder, its trajectory or the
    ground truth is missing or too short to align."""
    run = Path(run_dir)
    traj_path, gt_path = _run_inputs(run, gt)
    dest = _report_destination(run, out)
    # what is read is checked first against the run's manifest and formats (a damaged sparse/ model would
    # otherwise hang pycolmap's reader in the map view)
    check_run(run, ("trajectory_tum.txt", "keyframes_tum.txt", "summary.json", "frames.csv",
                    *(("groundtruth_tum.txt",) if gt is None else ()), *(("sparse",) if map_view else ())))
    pair = load_pair(traj_path, gt_path, frames=read_frame_table(run))
    est, gt_traj = pair.est, pair.gt
    summary = _summary(run)
    all_frames, a, r = _stats(gt_traj, est, max_dt)
    kf_path = run / "keyframes_tum.txt"
    keyframes, kf_traj = None, None
    if kf_path.exists():
        kf_traj = read_tum(kf_path)
        try:
            keyframes = _stats(gt_traj, kf_traj, max_dt)[0]
        except SlamkitError as e:
            keyframes = {"error": str(e)}
    warning = matched_warning(all_frames["ate"], str(traj_path))
    result = {
        "generator": "slamkit eval",
        "run": str(run), "estimate": str(traj_path), "ground_truth": str(gt_path), "alignment": "sim3",
        "max_dt": max_dt, "pairing": pair.method, "notes": pair.notes, "warnings": [warning] if warning else [],
        "all_frames": all_frames, "keyframes": keyframes,
        "frames": summary.get("frames"), "frames_posed": summary.get("frames_posed"),
        "fraction_posed": summary.get("fraction_posed"), "num_keyframes": summary.get("keyframes"),
        "points3D": summary.get("points3D"), "points_per_image": summary.get("points_per_image"),
        "mean_reprojection_error_px": summary.get("mean_reprojection_error_px"),
        "fps": summary.get("fps"), "wall_time_s": summary.get("wall_time_s"),
        "timings_s": summary.get("timings_s", {}),
        "camera": summary.get("camera"),
    }
    prior = map_alignment_error(run, gt, max_dt)  # a run made in a saved map (--map): under the map's alignment
    if prior is not None:
        result["map_alignment"] = prior
    if dest == run:
        _write_report(run, run, result, summary, est, gt_traj, kf_traj, a, r, plots, map_view)
    else:
        with out_dir_lock(dest, flag="out", what="report folder"):
            with atomic_dir(dest, kind="report") as tmp:
                _write_report(run, tmp, result, summary, est, gt_traj, kf_traj, a, r, plots, map_view)
                write_listing(tmp, REPORT_MARKER, f"slamkit eval report of {shown(run.resolve())}")
        for key in ("report_md", "report_html"):
            result[key] = str(dest / Path(result[key]).name)
    return result


def _write_report(run: Path, dest: Path, result: dict, summary: dict, est: Trajectory, gt_traj: Trajectory,
                  kf_traj: Trajectory | None, a, r, plots: bool, map_view: bool) -> None:
    files = _plots(dest, summary, est, gt_traj, kf_traj, a, r, result["timings_s"]) if plots else {}
    if map_view:
        files["map"] = _map_view(run, dest)
    result["files"] = {k: str(Path(v).relative_to(dest)) for k, v in files.items() if v is not None}
    atomic_write_text(dest / "evaluation.json", json.dumps(result, indent=2, default=_json_default))
    md, page = _report(result, run, dest)
    result["report_md"] = str(atomic_write_text(dest / "report.md", md))
    result["report_html"] = str(atomic_write_text(dest / "report.html", page))


def _report_destination(run: Path, out: str | os.PathLike | None) -> Path:
    """Where the report may be written (see :func:`evaluate_run`); OutputError naming the path otherwise."""
    own = is_run_folder(run)
    if out is not None and own and os.path.realpath(out) == os.path.realpath(run):
        out = None
    if out is None:
        if not own:
            raise OutputError(f"{run}: not a slamkit run folder (no {RUN_MARKER}), so slamkit eval writes nothing "
                              "into it (its report.md and plots/ may be another tool's): pass --out DIR (out=) for "
                              "the report, or --json-only for the numbers alone")
        _check_own_report_files(run)
        return run
    dest = check_output(out, "report", [], flag="--out")
    if os.path.realpath(dest) in (os.path.realpath(p) for p in (run, *run.resolve().parents)):
        raise OutputError(f"--out {dest}: would replace the folder of the run {run}; give a new folder")
    return dest


def _check_own_report_files(run: Path) -> None:
    """OutputError naming the first report file (or ``plots/`` entry) in run folder ``run`` that slamkit did
    not write: it is never replaced."""
    for name in REPORT_FILES:
        path = run / name
        if not (path.exists() or path.is_symlink()):
            continue
        if not is_own_report_file(path):
            raise OutputError(f"{path}: not a report slamkit wrote (no slamkit marker), so it is kept and nothing "
                              "was written: move it away, or pass --out DIR for the report")
    plots = run / "plots"
    if plots.is_symlink() or (plots.exists() and not plots.is_dir()):
        raise OutputError(f"{plots}: not a folder slamkit wrote; it is kept: move it away, or pass --out DIR")
    if plots.is_dir():
        other = sorted(n for n in os.listdir(plots) if n not in PLOT_FILES or not (plots / n).is_file()
                       or (plots / n).is_symlink())
        if other:
            raise OutputError(f"{plots}: holds {', '.join(other[:3])}, which slamkit eval did not write, so nothing "
                              "was written: move them away, or pass --out DIR for the report")


def _run_inputs(run: Path, gt: str | os.PathLike | None) -> tuple[Path, Path]:
    """(estimate, ground truth) paths of run folder ``run``; SlamkitError naming what is missing."""
    if not run.exists():
        raise SlamkitError(f"{run}: does not exist, so it is not a run folder (expected the output folder of "
                           "`slamkit run`)")
    if not run.is_dir():
        raise SlamkitError(f"{run}: not a run folder (expected the output folder of `slamkit run`)")
    traj_path = run / "trajectory_tum.txt"
    if not traj_path.exists():
        raise SlamkitError(f"{traj_path}: missing; is {run} a slamkit run folder?")
    check_posed(run)
    if gt is not None:
        return traj_path, check_input_file(gt, "gt (--gt)")
    gt_path = run / "groundtruth_tum.txt"
    if not gt_path.exists():
        raise SlamkitError(f"{gt_path}: no ground truth in the run (its source has none); pass gt=FILE (--gt FILE)")
    return traj_path, gt_path


def check_posed(run: Path) -> None:
    """SlamkitError when run folder ``run`` posed no frame (nothing to evaluate), with the run's reason."""
    try:
        summary = _summary(run)
    except SlamkitError:
        return  # the trajectory's own check names the problem
    if summary.get("frames_posed") == 0:
        why = summary.get("not_initialized_reason") or "see its summary.json"
        raise SlamkitError(f"{run}: the run posed no frame, so there is nothing to evaluate (no map: {why})")


def _summary(run: Path) -> dict:
    """The run's ``summary.json`` ({} when it has none); SessionError naming it when it is not a summary."""
    if not (run / "summary.json").exists():
        return {}
    summary = check_json(run / "summary.json")
    if not isinstance(summary, dict):
        raise SessionError(f"{run / 'summary.json'}: not a slamkit summary (a JSON {type(summary).__name__})")
    return summary


def _plots(dest: Path, summary: dict, est: Trajectory, gt_traj: Trajectory, kf_traj: Trajectory | None, a, r,
           timings: dict) -> dict[str, str | None]:
    """The report's figures under ``run/plots``: trajectory views, error over time, timings."""
    from . import plots as P  # matplotlib only when plotting: the core imports no UI

    files: dict[str, str | None] = {}
    pdir = dest / "plots"
    aligned = a.alignment.apply(est.subset(a.idx_est))
    gt_m = gt_traj.subset(a.idx_gt)
    title = str(summary.get("source", dest.name))
    if a.undefined:  # rotation only: every centre at one point, no position error to draw
        return {"timings": P.plot_timings(timings, int(summary.get("frames") or 0), pdir / "timings.png")
                if timings else None}
    files["trajectory"] = P.plot_trajectory_views(gt_m.positions, aligned.positions, a.errors,
                                                  pdir / "trajectory.png", title=title,
                                                  gt_full_xyz=gt_traj.positions)
    files["error_over_time"] = P.plot_error_over_time(
        a.timestamps, a.errors, pdir / "error_over_time.png",
        keyframe_t=kf_traj.timestamps if kf_traj is not None else None,
        rpe_t=r.timestamps if r is not None else None,
        rpe_errors=r.translation_errors if r is not None else None, title=title)
    if timings:
        files["timings"] = P.plot_timings(timings, int(summary.get("frames") or 0), pdir / "timings.png")
    return files


def _json_default(x):
    if isinstance(x, (np.integer, np.floating)):
        return x.item()
    raise TypeError(type(x).__name__)


def _map_view(run: Path, dest: Path) -> Path | None:
    """``DEST/map.html`` from MapView of run ``run`` (a local meshcat server, no browser), or None when that
    fails."""
    if not (run / "sparse").exists():
        return None
    view = None
    try:
        from ..viz.meshcat_view import MapView  # the viewer (meshcat) only when a map page is made

        view = MapView()
        view.load_run(run)
        return atomic_write_text(dest / "map.html", view.static_html() + f"\n{_MAP_MARK}\n")
    except Exception:  # noqa: BLE001 - the viewer is optional: the report links points.ply instead
        return None
    finally:
        if view is not None:
            view.close()


def _cm(x) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{100 * x:.2f}"


def _row(name: str, part: dict | None) -> str:
    if not part or "ate" not in part:
        why = (part or {}).get("error", "no keyframes file")
        return f"| {name} | – | – | – | – | – | – | {html.escape(why)} |"
    a, rp = part["ate"], part["rpe"]
    t = rp.get("translation", {}).get("rmse")
    d = rp.get("rotation_deg", {}).get("rmse")
    rot = (a.get("rotation_deg") or {}).get("rmse")
    oriented = (a.get("rotation_oriented_deg") or {}).get("rmse")
    if a.get("rotation_free") and oriented is not None and rot is not None:
        rot_text = (f"; rotation error RMSE {oriented:.3f}° after aligning orientations: {a['rotation_free']} "
                    f"(evo_ape angle after the position fit: {rot:.3f}°)")
    else:
        rot_text = f"; rotation error RMSE {rot:.3f}°" if rot is not None else ""
    note = (f"{a['undefined']}; rotation error RMSE {rot:.3f}°" if a.get("undefined") else
            f"scale {a['alignment'].get('scale', float('nan')):.4g}" + rot_text)
    rpe_cell = f"{_cm(t)} cm, {d:.3f}°" if d is not None else "–"
    return (f"| {name} | {a['count']} | {_cm(a['rmse'])} | {_cm(a['mean'])} | {_cm(a['median'])} | {_cm(a['max'])} "
            f"| {rpe_cell} | {html.escape(note)} |")


def _report(res: dict, run: Path, dest: Path) -> tuple[str, str]:
    f = res["files"]
    paired = ("timestamps matched within {} s".format(res["max_dt"]) if res.get("pairing", "time") == "time"
              else f"paired by {res['pairing']}")
    lines = [f"# Evaluation of `{run.name}`", "",
             f"Estimate `{Path(res['estimate']).name}` against `{res['ground_truth']}`; Sim(3) alignment "
             f"(Umeyama on the matched camera centres), {paired}; rotation error: the angle of "
             "R_est,aligned^T R_gt (evo_ape --pose_relation angle_deg), or, when the positions leave the fit's "
             "rotation free (a nearly straight path: its standard error about the path, from the centres' spread "
             "across it, above 0.1° and a quarter of the orientation error), the angle after aligning orientations "
             "alone (the rotation nearest to sum R_gt R_est^T), with evo's beside it.", ""]
    if res["all_frames"]["ate"].get("undefined"):
        lines += [f"**{res['all_frames']['ate']['undefined']}**: every estimated camera centre is one point, so "
                  "the orientations are aligned by the rotation nearest to sum R_gt R_est^T and only the rotation "
                  "error is reported.", ""]
    for text in [f"Note: {n}" for n in res.get("notes", [])] + [f"**Warning**: {w}" for w in res.get("warnings", [])]:
        lines += [text, ""]
    lines += ["| poses | matched | ATE RMSE [cm] | mean | median | max | RPE (1 frame) RMSE | note |",
              "|---|---|---|---|---|---|---|---|",
              _row("all frames", res["all_frames"]), _row("keyframes", res["keyframes"]), ""]
    if res.get("frames") is not None:
        lines += ["| frames | posed | keyframes | 3D points | points / image | reprojection error [px] | frames/s |",
                  "|---|---|---|---|---|---|---|",
                  f"| {res['frames']} | {res['frames_posed']} ({100 * (res['fraction_posed'] or 0):.1f} %) | "
                  f"{res['num_keyframes']} | {res['points3D']} | {res['points_per_image']:.0f} | "
                  f"{res['mean_reprojection_error_px']:.3f} | {res['fps']:.2f} |", ""]
    cam = res.get("camera")
    if isinstance(cam, dict) and cam.get("description"):
        lines += [f"Camera: {cam['description']}.", ""]
    for key, caption in (("trajectory", "Trajectory against ground truth, coloured by position error"),
                         ("error_over_time", "Position error over time (grey lines: keyframes)"),
                         ("timings", "Time per pipeline stage")):
        if key in f:
            lines += [f"## {caption}", "", f"![{key}]({f[key]})", ""]
    lines += ["## 3D map", ""]
    if "map" in f:
        lines += [f"[Open the static 3D map view]({f['map']}) (self-contained HTML, works offline).", ""]
    if (run / "points.ply").exists():
        ply = ("points.ply" if dest == run else
               Path(os.path.relpath(run.resolve() / "points.ply", dest.resolve())).as_posix())
        lines += [f"Point cloud: [points.ply]({ply}) (MeshLab, CloudCompare); COLMAP model in `sparse/`.", ""]
    lines += [_MD_MARK, ""]
    md = "\n".join(lines)
    return md, _html(md, f)


def _html(md: str, files: dict) -> str:
    """The markdown as a small self-contained HTML page (tables, headings, images, links)."""
    body, table = [], []

    def flush():
        if table:
            rows = [r for r in table if not re.match(r"^\|[-|]+\|$", r)]
            cells = [[html.escape(c.strip()) for c in r.strip("|").split("|")] for r in rows]
            out = ["<table>", "<tr>" + "".join(f"<th>{c}</th>" for c in cells[0]) + "</tr>"]
            out += ["<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in cells[1:]]
            body.append("\n".join(out + ["</table>"]))
            table.clear()

    for line in md.splitlines():
        if line == _MD_MARK:
            continue
        if line.startswith("|"):
            table.append(line)
            continue
        flush()
        if line.startswith("## "):
            body.append(f"<h2>{html.escape(line[3:])}</h2>")
        elif line.startswith("# "):
            body.append(f"<h1>{html.escape(line[2:])}</h1>")
        elif m := re.match(r"^!\[(.*)\]\((.*)\)$", line):
            body.append(f'<img alt="{html.escape(m[1])}" src="{html.escape(m[2])}">')
        elif line.strip():
            text = html.escape(line)
            text = re.sub(r"\[([^\]]+)\]\(([^)]+)\)", r'<a href="\2">\1</a>', text)
            text = re.sub(r"`([^`]+)`", r"<code>\1</code>", text)
            body.append(f"<p>{text}</p>")
    flush()
    if "map" in files:
        body.append(f'<iframe src="{html.escape(files["map"])}" style="width:100%;height:520px;border:1px solid #ccc">'
                    "</iframe>")
    style = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
             "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:4px 8px;text-align:right}"
             "img{max-width:100%}code{background:#f4f4f4;padding:0 3px}")
    return ("<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>slamkit evaluation</title>"
            f"{_HTML_MARK}"
            f"<style>{style}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")
