"""Saving a SLAM run: trajectories, COLMAP model, PLY and summary, written atomically as one folder.

Layout of ``DIR`` (the main segment's map at the top; every segment under ``segments/`` when there are
several):

- ``trajectory_tum.txt`` every posed frame (TUM: timestamp tx ty tz qx qy qz qw, camera-to-world)
- ``keyframes_tum.txt`` keyframes only; ``trajectory_kitti.txt`` KITTI format (12 values per line)
- ``sparse/`` COLMAP binary model (``pycolmap.Reconstruction(DIR / "sparse")``); ``points.ply``
- ``summary.json`` timings, counts, Table-2 columns and the config; ``frames.csv`` one row per frame, with
  the file it was read from, its size in bytes and pixels and SHA-256, measured when the frame was read
  (:mod:`slamkit.io.fingerprint`; checked by ``export`` and ``--resume``)
- ``camera.txt`` the intrinsics used (given, found or estimated; how, in its comment): ``--camera DIR`` reuses them
- ``groundtruth_tum.txt`` the source's ground truth of the used frames, when it has one
- ``session/`` everything ``Slam.resume(DIR)`` needs to continue the run (:mod:`slamkit.session`: COLMAP
  models of every segment, JSON state and ``.npz`` arrays, no pickle)
- ``.slamkit-run`` the marker: size and SHA-256 of every file above (``session/.slamkit-session.json`` likewise),
  checked before a run is read again (:mod:`slamkit.io.saved`)

Frames a stage failed on have status ``error`` in ``frames.csv`` (message in its ``error`` column and in
``summary.json["errors"]``).
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..session import SESSION_DIR, write_session
from ..sources.calibration import CAMERA_TXT, write_camera_txt
from ..types import Trajectory
from .atomic import atomic_dir
from .fingerprint import FINGERPRINT_COLUMNS, csv_fields
from .run_dir import RUN_MARKER, SESSION_MARKER, check_out_dir, out_dir_lock, write_manifest
from .trajectory import write_kitti, write_tum

if TYPE_CHECKING:  # pragma: no cover
    from ..pipeline import Slam


def save_run(slam: "Slam", out_dir: str | Path, session: bool = True, overwrite: bool = False,
             lock: bool = True) -> Path:
    """Write ``slam``'s state to ``out_dir`` (replaced atomically: a crash never leaves half a folder), with a
    resumable session in ``out_dir/session/`` unless ``session=False``, and the marker ``.slamkit-run``
    listing the size and SHA-256 of every file written (readers check them first).

    ``out_dir`` must pass :func:`slamkit.io.run_dir.check_out_dir`: a new or empty folder, or a slamkit run
    holding nothing else (replaced); anything else is refused (OutputError), ``overwrite`` or not: a folder
    holding other files, the home or current folder, a folder equal to, inside or holding the source.
    ``overwrite`` is accepted for older callers and widens nothing. ``lock``: hold ``out_dir``'s lock while
    writing (False when the caller already holds it, as ``slamkit run`` does for the whole run).
    """
    out_dir = Path(out_dir)
    check_out_dir(out_dir, [getattr(slam, "source_spec", None), slam.source], overwrite, flag="out_dir")
    with out_dir_lock(out_dir, flag="out_dir") if lock else contextlib.nullcontext():
        with atomic_dir(out_dir, kind="run") as tmp:
            _write_run(slam, tmp, session)
    return out_dir


def _write_run(slam: "Slam", tmp: Path, session: bool) -> None:
    _write_segment(slam, None, tmp)
    if len(slam.state.live_segments) > 1:
        for seg in slam.state.live_segments:  # a merged segment is part of the one it was merged into
            _write_segment(slam, seg.id, tmp / "segments" / f"segment_{seg.id:02d}")
    summary = slam.summary()
    errors = getattr(slam, "errors", {})
    if errors:
        summary["errors"] = {str(k): v for k, v in sorted(errors.items())}
    (tmp / "summary.json").write_text(json.dumps(_jsonable(summary), indent=2))
    (tmp / "frames.csv").write_text(_frames_csv(slam), errors="backslashreplace")  # any bytes in a message
    if getattr(slam, "camera", None) is not None:
        write_camera_txt(tmp / CAMERA_TXT, slam.camera, f"the camera of this run: {_describe_camera(slam)}\n"
                         "reuse it on another video from the same camera: slamkit run VIDEO --camera RUN_DIR")
    gt = _ground_truth(slam)
    if gt is not None and len(gt):
        write_tum(tmp / "groundtruth_tum.txt", gt)
    if session:
        write_session(slam, tmp / SESSION_DIR)
        write_manifest(tmp / SESSION_DIR, SESSION_MARKER)
    write_manifest(tmp, RUN_MARKER)


def _write_segment(slam: "Slam", segment: int | None, folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    seg = slam.main_segment if segment is None else slam.segments[segment]
    write_tum(folder / "trajectory_tum.txt", slam.trajectory(segment=segment))
    write_tum(folder / "keyframes_tum.txt", slam.trajectory(keyframes_only=True, segment=segment))
    write_kitti(folder / "trajectory_kitti.txt", slam.trajectory(segment=segment))
    if seg is None:
        return
    rec = seg.slam_map.reconstruction
    (folder / "sparse").mkdir(exist_ok=True)
    rec.write_binary(str(folder / "sparse"))
    rec.export_PLY(str(folder / "points.ply"))


def _describe_camera(slam) -> str:
    describe = getattr(slam, "describe_camera", None)
    return describe() if describe is not None else "the source's calibration"


def _frames_csv(slam: "Slam") -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    errors = getattr(slam, "errors", {})
    w.writerow(["index", "frame_id", "timestamp", "status", "segment", "keyframe_image_id", *FINGERPRINT_COLUMNS,
                "error"])
    indices = getattr(slam, "indices", None)
    for r in slam.records:  # fingerprints as measured when each frame was read: no file is hashed now
        i = int(indices[r.index]) if indices is not None and 0 <= r.index < len(indices) else None
        print_ = csv_fields(r, slam.source, i)
        w.writerow([r.index, r.frame_id, f"{r.timestamp:.6f}", r.status, r.segment, r.keyframe_image_id,
                    *(print_[c] for c in FINGERPRINT_COLUMNS), errors.get(r.index, "")])
    return buf.getvalue()


def _ground_truth(slam: "Slam"):
    src = slam.source
    gt = getattr(src, "gt_poses", None)
    if gt is None:
        return None
    idx = slam.indices[: len(slam.records)] if slam.records else slam.indices
    poses = gt[idx]
    ok = np.isfinite(poses).all(axis=(1, 2))
    return Trajectory(np.asarray(src.timestamps)[idx][ok], poses[ok])


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    if isinstance(x, np.ndarray):
        return x.tolist()
    return x
