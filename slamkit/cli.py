"""Command line: ``slamkit run | eval | ablate | gt | presets`` — thin callers of the library."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shlex
import signal
import sys
import threading
import traceback
from pathlib import Path

import pycolmap
from tqdm import tqdm

from .ablate import STATUS_LOST, STATUS_OK, check_sweep_args, connect, markdown_table, parse_grid, plan, sweep
from .camera import parse_camera_values
from .config import PRESETS, SlamConfig, is_camera_path
from .errors import SlamkitError, shown
from .eval import evaluate
from .eval.metrics import ate_line
from .eval.map_alignment import map_alignment_error
from .eval.report import check_posed, evaluate_run
from .exporter import add_export_parser
from .eval.pairing import read_frame_table
from .io.run_dir import check_output, is_run_folder, out_dir_lock, save_id
from .io.saved import check_run
from .interrupt import HELD_SIGNALS, Interrupted, StopRequest, exit_code, notify, raise_interrupted, signal_name
from .io import write_tum
from .io.trajectory import check_input_file
from .pipeline import Slam
from .runner import (ABORTED, EXIT_CODES, EXIT_NOTHING_POSED, EXIT_POOR_MATCH, EXIT_USAGE, RunOutcome, run_to_folder,
                     summary_line)
from .sources import open_source
from .stages.mapper import MAPPER_METHODS


def _add_config_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("configuration (see slamkit.SlamConfig)")
    g.add_argument("--preset", help="named preset (slamkit presets lists them; default: default)")
    g.add_argument("--features", help="features: orb (default), sift, xfeat (XFeat + mutual NN), xfeat-lighterglue, "
                                      "aliked-lightglue, superpoint-superglue (learned ones: pip install 'slamkit[learned]')")
    g.add_argument("--matcher", help="pair matcher: nn (default), lighterglue (xfeat), lightglue (aliked), superglue")
    g.add_argument("--weights-dir", help="folder of weight files for learned features (default $SLAMKIT_WEIGHTS; "
                                         "superpoint-superglue needs superpoint_v1.pth and superglue_indoor.pth)")
    g.add_argument("--num-features", type=int)
    g.add_argument("--flow-threshold", type=float, help="keyframe flow threshold (default 0.05)")
    g.add_argument("--min-tracked-matches", type=int, help="keyframe needs this many tracked matches (50)")
    g.add_argument("--init-frames", type=int, help="initialization window N (20)")
    g.add_argument("--init-strategy", choices=["best_pair", "first_inliers"])
    g.add_argument("--mapper", choices=list(MAPPER_METHODS),
                   help="how keyframes make map points: local (ORB-SLAM's local mapping: created, checked, culled "
                        "and fused) or colmap (COLMAP's triangulator); default: "
                        f"{SlamConfig().mapper.method}")
    g.add_argument("--camera", metavar="auto|RUN_DIR|F|FX,FY,CX,CY[,K1,K2,P1,P2[,K3]]",
                   help="intrinsics in pixels instead of the source's: a focal length (principal point at the "
                        "centre) or fx,fy,cx,cy with optional OpenCV distortion; 'auto' estimates the focal "
                        "length from the frames (the default for videos and image folders without camera.txt); "
                        "a run folder or camera.txt reuses the camera another run used or estimated")
    g.add_argument("--frame-skip", type=int, help="use every n-th frame")
    g.add_argument("--max-frames", type=int, help="stop after this many frames")
    g.add_argument("--seed", type=int)
    g.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="any config field, dotted for stages, e.g. --set tracker.min_inliers=25")


def config_from_args(args: argparse.Namespace) -> SlamConfig:
    return SlamConfig.preset(args.preset or "default").with_overrides(**_overrides_from_args(args))


def _overrides_from_args(args: argparse.Namespace) -> dict:
    """The configuration values given explicitly on the command line (options and --set), preset excluded."""
    over = {k: getattr(args, k) for k in ("features", "matcher", "weights_dir", "num_features", "flow_threshold",
                                          "min_tracked_matches",
                                          "init_frames", "init_strategy", "mapper", "camera", "frame_skip", "max_frames",
                                          "seed")
            if getattr(args, k) is not None}
    if args.camera is not None and args.camera != "auto":  # "" given explicitly is a mistake
        if is_camera_path(args.camera):
            if not Path(args.camera).exists():
                raise SlamkitError(f"--camera {args.camera}: no such run folder or camera.txt")
        else:
            parse_camera_values(args.camera, "--camera")
    for item in args.set:
        if "=" not in item:
            raise SlamkitError(f"--set {item!r}: expected KEY=VALUE")
        k, v = item.split("=", 1)
        over[k.strip()] = v.strip()
    return over


def _resume_overrides(args: argparse.Namespace) -> dict:
    """With --resume: the saved config stays, changed only by what is given explicitly (a --preset's values,
    then the options)."""
    if args.preset is not None:
        SlamConfig.preset(args.preset)  # unknown name -> ConfigError
        return {**PRESETS[args.preset], **_overrides_from_args(args)}
    return _overrides_from_args(args)


def cmd_run(args: argparse.Namespace) -> int:
    """Run (or with --resume continue) SLAM into --out (:func:`slamkit.runner.run_to_folder`); print progress
    and the outcome, and map it to the exit code (0 a map was made, 1 a stage failed, 3 no frame posed, 128 +
    signal when interrupted)."""
    pycolmap.logging.minloglevel = 2
    out = Path(args.out)
    bar = None

    def note(line: str) -> None:
        notify(f"slamkit: {line}")

    def on_start(slam: Slam, resumed_after: int | None) -> None:
        nonlocal bar
        if resumed_after is not None:
            note(f"resuming the session in {out} after frame {resumed_after}")
        if slam.calibrator is not None and slam.calibrator.initial is None:
            print(f"slamkit: estimating the camera from the first "
                  f"{min(len(slam), slam.config.self_calibration.window_frames)} frames (no calibration given or "
                  "found; --camera sets one)", file=sys.stderr)
            slam.calibrate()
        print(f"slamkit: {slam.source!r}, {len(slam) - len(slam.records)} frames to process -> {out}; camera "
              f"{slam.describe_camera()}", file=sys.stderr)
        bar = tqdm(total=len(slam), initial=len(slam.records), unit="frame", disable=args.quiet, dynamic_ncols=True)

    def on_result(slam: Slam, r) -> None:
        bar.update(1)
        bar.set_postfix_str(f"{r.status} kf={r.num_keyframes} pts={r.num_points} · {slam.state.describe_speed()}",
                            refresh=False)
        if args.verbose:
            tqdm.write(str(r))

    if args.localize_only and not args.map:
        raise SlamkitError("--localize-only: localizes in a saved map; give it with --map RUN_DIR")
    if args.map and args.resume:
        raise SlamkitError("--map with --resume: a run in a saved map is made in one go; run it again without "
                           "--resume into a new --out")
    outcome, before = None, save_id(out)
    with StopRequest() as stop:  # signals are handled until the last line is printed
        try:
            outcome = run_to_folder(args.source, args.out, config_from_args(args), resume=args.resume,
                                    resume_overrides=_resume_overrides(args) if args.resume else None,
                                    overwrite=args.overwrite, on_start=on_start, on_result=on_result, notify=note,
                                    stop=stop, map=args.map, localize_only=args.localize_only)
            if bar is not None:
                bar.close()
            return _report_run(args, outcome)
        except Interrupted as e:  # the last signal arrived before the first frame, or after the save
            # (then run_to_folder returned no outcome, so the folder's save id says whether this run is in it)
            now = save_id(out)
            saved = outcome.saved if outcome is not None else now is not None and now != before
            held = f"{out} holds this run, saved" if saved else f"{out} was left as it was"
            print(f"slamkit: {e}: stopped at once; {held}", file=sys.stderr)
            return e.exit_code
        finally:
            if bar is not None:
                bar.close()


def _report_run(args: argparse.Namespace, outcome: RunOutcome) -> int:
    out = outcome.out
    if outcome.error is not None and not isinstance(outcome.error, SlamkitError):
        traceback.print_exception(outcome.error)
    if not outcome.saved or outcome.status == ABORTED:
        print(f"slamkit: {outcome.message}", file=sys.stderr)
        return outcome.exit_code
    print(summary_line(outcome.summary), file=sys.stderr)
    if isinstance(outcome.summary.get("map"), dict):
        m = outcome.summary["map"]
        print(f"map of {m['run']}: {m['frames_in_map']} frames posed in it, keyframes {m['keyframes_loaded']} -> "
              f"{m['keyframes']}, points {m['points_loaded']} -> {m['points3D']}"
              + ("" if not m.get("note") else f"; {m['note']}"), file=sys.stderr)
    if outcome.ate is not None:
        print(f"{ate_line(outcome.ate)} ({outcome.ate['matched']} poses)", file=sys.stderr)
    elif outcome.evaluation_error:
        print(f"evaluation skipped: {outcome.evaluation_error}", file=sys.stderr)
    print(f"outputs in {out}/ (trajectory_tum.txt, keyframes_tum.txt, trajectory_kitti.txt, sparse/, points.ply, "
          f"summary.json, session/)")
    if outcome.exit_code == EXIT_NOTHING_POSED:
        print(f"slamkit: no frame was posed, so no map was made (exit code {EXIT_NOTHING_POSED}); {out} holds the "
              "run's frame table and summary", file=sys.stderr)
    if outcome.message and outcome.complete:
        print(f"slamkit: {outcome.message}; saved in {out}", file=sys.stderr)
    elif outcome.message:
        again = f"slamkit run {shlex.quote(args.source)} --out {shlex.quote(str(out))} --resume"
        print(f"slamkit: {outcome.message}; the map, trajectory and session so far are saved in {out} "
              f"(continue with: {again})", file=sys.stderr)
    return outcome.exit_code


def _print_notes(result: dict) -> int:
    """Print the evaluation's notes and warnings (stderr); the exit code: :data:`EXIT_POOR_MATCH` when
    fewer than half of the estimate matched ground truth, else 0."""
    for note in result.get("notes", []):
        print(f"slamkit: note: {note}", file=sys.stderr)
    for warning in result.get("warnings", []):
        print(f"slamkit: warning: {warning} (exit code {EXIT_POOR_MATCH})", file=sys.stderr)
    return EXIT_POOR_MATCH if result.get("warnings") else 0


def cmd_eval(args: argparse.Namespace) -> int:
    run = Path(args.run)
    if args.gt is not None:
        check_input_file(args.gt, "--gt")
    if not run.exists():
        raise SlamkitError(f"{run}: does not exist (give a run folder written by `slamkit run --out`, or a "
                           "trajectory file)")
    if args.out is not None and (not run.is_dir() or args.json_only):
        raise SlamkitError(f"--out {args.out}: a report is written for a run folder only (without --json-only); "
                           "for a trajectory file eval prints the numbers")
    if run.is_dir() and not args.json_only:
        result = evaluate_run(run, gt=args.gt, max_dt=args.max_dt, map_view=not args.no_map_view, out=args.out)
        code = _print_notes(result)
        a, k = result["all_frames"]["ate"], (result.get("keyframes") or {}).get("ate")
        print(f"{ate_line(a)} over {a['count']} frames"
              + (f", {100 * k['rmse']:.2f} cm over {k['count']} keyframes" if k and not k.get("undefined") else "")
              + f" (Sim(3)-aligned); report: {result['report_md']} and {result['report_html']}", file=sys.stderr)
        prior = result.get("map_alignment")
        if isinstance(prior, dict):
            print(f"under the map's alignment ({prior['map_run']}): "
                  + (f"ATE RMSE {100 * prior['ate']['rmse']:.2f} cm over {prior['matched']} frames"
                     if "ate" in prior else prior.get("error", "")) + (f" ({prior['note']})" if prior.get("note") else ""),
                  file=sys.stderr)
        if isinstance(result.get("camera"), dict) and result["camera"].get("description"):
            print(f"camera: {result['camera']['description']}", file=sys.stderr)
        print(json.dumps(result, indent=2))
        return code
    if run.is_dir():
        check_run(run, ("trajectory_tum.txt", "frames.csv", *(("groundtruth_tum.txt",) if args.gt is None else ())))
        check_posed(run)
    est = run / "trajectory_tum.txt" if run.is_dir() else run
    if args.gt:
        gt = check_input_file(args.gt, "--gt")
    else:
        gt = run / "groundtruth_tum.txt" if run.is_dir() else run.parent / "groundtruth_tum.txt"
        if not gt.exists():
            raise SlamkitError(f"{gt}: no ground truth beside the trajectory; pass --gt FILE")
    frames = read_frame_table(run) if run.is_dir() and is_run_folder(run) else None
    result = evaluate(est, gt, max_dt=args.max_dt, frames=frames)
    prior = map_alignment_error(run, args.gt, args.max_dt) if run.is_dir() else None
    if prior is not None:
        result["map_alignment"] = prior
    code = _print_notes(result)
    print(json.dumps(result, indent=2))
    return code


SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx")


def check_scheduler_address(address: str) -> str:
    """``--scheduler``: a dask scheduler address ``[SCHEME://]HOST:PORT`` (scheme tcp, tls, ws, wss or ucx;
    port 1-65535), checked before anything connects; SlamkitError naming the option otherwise."""
    text = address.strip()
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, rest = "tcp", text
    host, colon, port = rest.rpartition(":")
    why = None
    if scheme not in SCHEDULER_SCHEMES:
        why = f"the scheme {scheme!r} is not one of {', '.join(SCHEDULER_SCHEMES)}"
    elif not colon or not host.strip("[]") or "/" in rest or any(c.isspace() for c in rest):
        why = "expected HOST:PORT after the scheme"
    elif not port.isdigit() or not 1 <= int(port) <= 65535:
        why = f"the port {port[:20]!r} is not a number from 1 to 65535"
    if why:
        raise SlamkitError(f"--scheduler {address[:80]!r}: not a dask scheduler address ({why}); give "
                           "tcp://HOST:PORT, as `dask scheduler` prints it")
    return f"{scheme}://{rest}"


def cmd_ablate(args: argparse.Namespace) -> int:
    if args.scheduler is not None:
        args.scheduler = check_scheduler_address(args.scheduler)
    check_sweep_args(args.out, args.workers, flag_out="--out", flag_workers="--workers", sources=args.sources)
    items = list(args.grid)
    if args.features:
        items.append(f"features={args.features}")
    grid = parse_grid(items)
    tasks = plan(args.sources, grid, args.repeats)
    executor, client = ("serial" if args.workers == 0 else "local"), None
    if args.scheduler:
        executor = client = connect(args.scheduler)
    print(f"slamkit ablate: {len(args.sources)} source(s) x {len(grid)} combination(s) x {args.repeats} "
          f"repeat(s) = {len(tasks)} runs on {args.scheduler or (f'{args.workers} local processes' if args.workers else 'all cores' if args.workers is None else 'this process')} -> {args.out}",
          file=sys.stderr)
    bar = tqdm(total=len(tasks), unit="run", disable=args.quiet, dynamic_ncols=True)
    counts = {"kept": 0, "new": 0}

    def progress(row: dict) -> None:
        bar.update(1)
        if row["status"] != STATUS_LOST:  # a lost run (its worker died) is not written: it runs again
            counts["kept"] += 1
            counts["new"] += not row.get("cached", False)
        if row["status"] != STATUS_OK:
            tqdm.write(f"run {row.get('key')} {row['status']}: {row['error']}", file=sys.stderr)

    try:
        df = sweep(args.sources, grid, args.out, executor, repeats=args.repeats, workers=args.workers,
                   retry_failed=args.retry_failed, on_result=progress)
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM / SIGHUP (Interrupted, exit code 143 / 129)
        left = len(tasks) - counts["kept"]
        print(f"slamkit ablate: {e or 'SIGINT'}: stopped; {counts['kept']} of {len(tasks)} runs are kept in "
              f"{args.out}/runs/ ({counts['new']} finished by this command), the other {left} were stopped or "
              "not started — run the same command again to finish the sweep", file=sys.stderr)
        return getattr(e, "exit_code", 130)
    finally:
        bar.close()
        if client is not None:
            client.close()
    ok = int((df["status"] == STATUS_OK).sum())
    print(f"{ok}/{len(df)} runs ok ({int(df['cached'].sum())} reused from an earlier sweep); "
          f"{args.out}/results.csv, results.md, effects.png", file=sys.stderr)
    cols = ["source", *grid.names, "seed", "status", "ate_rmse_m", "fraction_posed", "keyframes", "fps", "error"]
    print(markdown_table(df, cols))
    return 0 if ok == len(df) else 1


def cmd_gt(args: argparse.Namespace) -> int:
    """Write the source's ground truth to OUT, under the rules of every output (check_output: never over an
    existing file without --overwrite, never inside the source or a slamkit output), locked and atomic."""
    check_output(args.out, "file", [args.source], args.overwrite, flag="OUT")  # before the source is read
    if args.camera is not None:
        parse_camera_values(args.camera, "--camera")
    src = open_source(args.source, camera=args.camera)
    out = check_output(args.out, "file", [args.source, src], args.overwrite, flag="OUT")
    gt = src.ground_truth()
    if gt is None or len(gt) == 0:
        raise SlamkitError(f"{args.source}: this source has no ground truth")
    with out_dir_lock(out, flag="OUT", what="file"):
        write_tum(out, gt)
    print(f"{len(gt)} poses written to {out}")
    return 0


def cmd_presets(args: argparse.Namespace) -> int:
    for name, values in PRESETS.items():
        print(f"{name:10s} {values}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``slamkit`` command line: one subcommand per library call."""
    p = argparse.ArgumentParser(prog="slamkit", description="Offline monocular visual SLAM on COLMAP's machinery",
                                epilog=EXIT_CODES)
    sub = p.add_subparsers(dest="command", required=True)
    _add_run_parser(sub)
    _add_eval_parser(sub)
    _add_ablate_parser(sub)
    g = sub.add_parser("gt", help="write a source's ground truth as a TUM file")
    g.add_argument("source")
    g.add_argument("out", help="the TUM file to write (an existing file only with --overwrite; never inside the "
                               "source or a run folder)")
    g.add_argument("--overwrite", action="store_true",
                   help="replace OUT when it exists and is a trajectory slamkit wrote (never another file)")
    g.add_argument("--camera", metavar="F|FX,FY,CX,CY[,K1,K2,P1,P2[,K3]]",
                   help="intrinsics, applied before the source is opened (e.g. a TUM layout without a freiburg name)")
    g.set_defaults(func=cmd_gt)
    add_export_parser(sub)
    pr = sub.add_parser("presets", help="list configuration presets")
    pr.set_defaults(func=cmd_presets)
    return p


def _add_run_parser(sub) -> None:
    r = sub.add_parser("run", help="run SLAM on a source and save the map and trajectory", epilog=EXIT_CODES)
    r.add_argument("source", help="'default', 'synthetic:<motion>', a dataset folder, an image folder or a video")
    r.add_argument("--out", required=True,
                   help="run folder: a new or empty folder, or an earlier slamkit run (replaced atomically; keeps a "
                        "session/ to resume); never inside the source")
    r.add_argument("--overwrite", action="store_true",
                   help="accepted for older scripts: an earlier slamkit run in --out is replaced without it, and a "
                        "folder holding anything else never is (nor the home or current folder)")
    r.add_argument("--resume", action="store_true",
                   help="continue the run saved in --out (its session/) if there is one: same source, the saved "
                        "config changed only by the options given; else start a new run")
    r.add_argument("--map", metavar="RUN_DIR",
                   help="pose the frames in the map of an earlier run (its frame and scale) and extend that map; "
                        "the earlier run folder is only read (the same camera and image size)")
    r.add_argument("--localize-only", action="store_true",
                   help="with --map: localize only, adding no keyframe and no point (ORB-SLAM's localization mode)")
    r.add_argument("-v", "--verbose", action="store_true", help="print every frame's result")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    _add_config_args(r)
    r.set_defaults(func=cmd_run)


def _add_eval_parser(sub) -> None:
    e = sub.add_parser("eval", help="ATE/RPE of a run (or a TUM file) against ground truth", epilog=EXIT_CODES)
    e.add_argument("run", help="run folder or trajectory file")
    e.add_argument("--gt", help="ground truth: TUM (paired by time) or KITTI's poses/NN.txt (12 values a line, no "
                                "time: paired by the run's source frame index, with a note); default "
                                "RUN/groundtruth_tum.txt")
    e.add_argument("--max-dt", type=float, default=0.02)
    e.add_argument("--no-map-view", action="store_true", help="link points.ply instead of a static 3D map page")
    e.add_argument("--json-only", action="store_true", help="print the numbers only (no plots, no report)")
    e.add_argument("--out", metavar="DIR",
                   help="write the report into DIR (a new or empty folder, or an earlier report); needed when RUN is "
                        "not a slamkit run folder (eval never writes into another tool's folder)")
    e.set_defaults(func=cmd_eval)


def _add_ablate_parser(sub) -> None:
    a = sub.add_parser("ablate", help="run a parameter grid on sources (local processes or a dask cluster)")
    a.add_argument("sources", nargs="+", metavar="SOURCE", help="sources as for `slamkit run`")
    a.add_argument("--grid", nargs="+", default=[], metavar="NAME=V1,V2",
                   help="parameter values to combine, e.g. flow_threshold=0.02,0.05 init_frames=10,20 "
                        "(short names or dotted config paths; a single value fixes a parameter)")
    a.add_argument("--features", help="extractors to compare, e.g. orb,sift")
    a.add_argument("--repeats", type=int, default=1, help="runs per combination; repeat r uses seed r")
    a.add_argument("--out", required=True, help="sweep folder (runs/*.json, results.csv/.parquet/.md, effects.png)")
    a.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="run on this dask distributed cluster")
    a.add_argument("--workers", type=int, help="local processes (default: all cores; 0 = in this process)")
    a.add_argument("--retry-failed", action="store_true", help="run again the runs recorded as failed")
    a.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    a.set_defaults(func=cmd_ablate)


def main(argv: list[str] | None = None) -> int:
    for stream in (sys.stdout, sys.stderr):  # a non-UTF-8 locale (LC_ALL=C): a name is shown escaped, never a crash
        if stream is not None and (getattr(stream, "encoding", None) or "utf-8").lower().replace("-", "") != "utf8":
            with contextlib.suppress(AttributeError, ValueError, OSError):
                stream.reconfigure(errors="backslashreplace")
    args = build_parser().parse_args(argv)
    handler = _SignalsInterrupt()
    previous = handler.install()
    hook = sys.unraisablehook
    sys.unraisablehook = handler.unraisable
    try:
        code = args.func(args)
        # a signal that landed in a __del__ (e.g. a progress bar's) could not propagate: it still ends the command
        return handler.swallowed[0].exit_code if handler.swallowed else code
    except SlamkitError as e:
        handler.active = False
        print(f"slamkit: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:  # `slamkit eval ... | head`: the reader left; not an error of ours
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as e:  # the OS refused a path given on the command line (name too long, no permission, ...)
        handler.active = False
        where = f"{e.filename}: " if e.filename else ""
        print(f"slamkit: error: {where}{e.strerror or e} (the operating system refused it; check the path)",
              file=sys.stderr)
        return EXIT_USAGE
    except UnicodeError as e:  # a name this locale cannot encode, passed to a library that needs text
        handler.active = False
        print(f"slamkit: error: {shown(str(e))}: a file name that the locale's encoding "
              f"({sys.getfilesystemencoding()}) cannot write; nothing was kept — use a UTF-8 locale "
              "(e.g. LC_ALL=C.UTF-8) or a plain ASCII name", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt as e:  # Ctrl-C (or SIGTERM / SIGHUP: Interrupted) outside a run's own handling
        handler.active = False
        signum = getattr(e, "signum", signal.SIGINT)
        print(f"slamkit: {signal_name(signum)}: stopped; every output is either complete or as it was before "
              "(files and folders are replaced atomically, a temporary one is removed)", file=sys.stderr)
        return exit_code(signum)
    finally:
        handler.active = False
        sys.unraisablehook = hook
        if argv is not None:  # called from Python: give the handlers back
            for s, h in previous.items():
                signal.signal(s, h if h is not None else signal.SIG_DFL)
        else:  # as a program: the outcome is decided; a late signal must not kill the exiting process
            for s in previous:
                signal.signal(s, signal.SIG_IGN)


class _SignalsInterrupt:
    """SIGTERM and SIGHUP raise :class:`Interrupted` like Ctrl-C does while a command runs (not when ignored,
    as under nohup); inert once ``active`` is False. ``slamkit run`` replaces it by its StopRequest."""

    def __init__(self):
        self.active = True
        self.swallowed: list[Interrupted] = []
        """Interruptions raised where Python cannot propagate them (a ``__del__``), kept instead of printed."""

    def __call__(self, signum: int, frame) -> None:
        if self.active:
            raise_interrupted(signum, frame)

    def unraisable(self, unraisable) -> None:
        """``sys.unraisablehook`` while a command runs: an :class:`Interrupted` is kept (no traceback)."""
        if isinstance(unraisable.exc_value, Interrupted):
            self.swallowed.append(unraisable.exc_value)
        else:
            sys.__unraisablehook__(unraisable)

    def install(self) -> dict:
        previous = {}
        if threading.current_thread() is threading.main_thread():
            for s in HELD_SIGNALS:
                if s != signal.SIGINT and signal.getsignal(s) is not signal.SIG_IGN:
                    previous[s] = signal.signal(s, self)
        return previous


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
