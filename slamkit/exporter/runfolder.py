"""Reading a saved run folder for export: its COLMAP model, posed frames, camera and source spec.

A run folder (``slam.save(DIR)`` / ``slamkit run --out DIR``, see :mod:`slamkit.io.run`) holds the main
segment's model in ``sparse/`` (keyframe images named ``frame_NNNNNN`` after the source index of the frame,
no image files), every posed frame of that segment in ``trajectory_tum.txt`` (camera-to-world, source
timestamps), one row per frame in ``frames.csv`` and, in ``session/session.json``, the source spec, the
source's intrinsics (distortion included) and the config. The export needs all of them except the session
when the caller hands it the frame source.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..camera import Intrinsics
from ..config import SlamConfig, is_camera_path
from ..errors import FormatError, SlamkitError
from ..io.fingerprint import FINGERPRINT_COLUMNS
from ..io.saved import check_run
from ..io.trajectory import read_tum
from ..sources.calibration import CAMERA_TXT, camera_from_path

MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin")
"""Files of the COLMAP binary model a run folder must hold in ``sparse/``."""

SESSION_JSON = Path("session") / "session.json"

READ_PARTS = ("sparse", "trajectory_tum.txt", "frames.csv", "summary.json")
"""The parts of a run folder the export reads (besides the optional ``session/``)."""


class RunFolderError(SlamkitError):
    """A run folder lacks a file the export needs, or its files do not agree."""


@dataclass(frozen=True)
class PosedFrame:
    """One posed frame of a saved run.

    index: the frame's index in the source (model images are named ``frame_{index:06d}``); frame_id: its number
    in the dataset; fingerprint: what the run recorded of its file (:mod:`slamkit.io.fingerprint`); timestamp:
    seconds; world_from_cam: (4, 4) camera-to-world from ``trajectory_tum.txt``; image_id: its image in the
    run's model when it is a keyframe, else -1.
    """

    index: int
    frame_id: int
    timestamp: float
    world_from_cam: np.ndarray
    image_id: int = -1
    fingerprint: dict = field(default_factory=dict)
    """The file, size and SHA-256 the run recorded for the frame (``frames.csv``; empty for older runs)."""

    @property
    def name(self) -> str:
        """The image name the run's model uses (no extension)."""
        return f"frame_{self.index:06d}"

    @property
    def is_keyframe(self) -> bool:
        return self.image_id >= 0


@dataclass(frozen=True, eq=False)
class SavedRun:
    """What the export reads from a run folder.

    model: the run's COLMAP model (PINHOLE camera of undistorted pixels); frames: every posed frame, in
    trajectory order; camera: the images' intrinsics with their distortion (pinhole part equal to the
    model camera's); spec: how the source was opened (None when the run did not record it); config: the
    run's configuration (default config when the session is missing).
    """

    path: Path
    model: pycolmap.Reconstruction
    frames: list[PosedFrame]
    camera: Intrinsics
    spec: str | None
    config: SlamConfig
    source_frames: int | None = None
    """How many frames the source had when the run was made (from the session; None without one)."""


def _require(path: Path, what: str) -> Path:
    if not path.is_file():
        raise RunFolderError(f"{path} is missing ({what}): not a run folder saved with slam.save() or "
                             "`slamkit run --out`, or saved before any keyframe was mapped")
    return path


def _frame_rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    need = {"index", "frame_id", "timestamp", "segment"}
    if rows and not need <= set(rows[0]):
        raise FormatError(path, 1, f"needs the columns {', '.join(sorted(need))}")
    return rows


def _session(run_dir: Path) -> dict | None:
    path = run_dir / SESSION_JSON
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise RunFolderError(f"{path}: cannot be read ({e})") from None


def _camera(meta: dict | None, model: pycolmap.Reconstruction, source_camera: Intrinsics | None,
            run_dir: Path | None = None, estimated: bool = False) -> Intrinsics:
    """The images' intrinsics: the run's ``--camera``, else the source's, with the model camera's pinhole part;
    ``estimated`` (self-calibration): the run's own ``camera.txt``, which holds the radial coefficient."""
    cam = model.camera(next(iter(model.cameras)))
    text = ((meta or {}).get("config") or {}).get("camera") or ""
    if estimated or text == "auto":  # the model holds the pinhole part, camera.txt the radial coefficient
        base = Intrinsics(cam.width, cam.height, *cam.params[:4])
        if run_dir is not None and (run_dir / CAMERA_TXT).is_file():
            try:
                base = camera_from_path(str(run_dir), cam.width, cam.height)
            except SlamkitError:
                pass
    elif is_camera_path(text):  # another run's camera.txt: its distortion, if it is still there
        try:
            base = camera_from_path(text, cam.width, cam.height)
        except SlamkitError:
            base = Intrinsics(cam.width, cam.height, *cam.params[:4])
    elif text:
        base = Intrinsics.parse(text, cam.width, cam.height)
    elif source_camera is not None:
        base = source_camera
    elif meta is not None and (meta.get("source") or {}).get("camera"):
        base = Intrinsics.from_dict(meta["source"]["camera"])
    else:
        base = Intrinsics(cam.width, cam.height, *cam.params[:4])
    fx, fy, cx, cy = (float(v) for v in cam.params[:4])
    return Intrinsics(int(cam.width), int(cam.height), fx, fy, cx, cy, base.dist)


def _posed_frames(run_dir: Path, model: pycolmap.Reconstruction, main_segment) -> list[PosedFrame]:
    traj = read_tum(_require(run_dir / "trajectory_tum.txt", "trajectory of the posed frames"))
    csv_path = _require(run_dir / "frames.csv", "frame table")
    rows = [r for r in _frame_rows(csv_path) if main_segment is None or r["segment"] == str(main_segment)]
    t_rows = np.array([float(r["timestamp"]) for r in rows]).reshape(-1)
    by_name = {model.image(i).name: int(i) for i in model.reg_image_ids()}
    frames = []
    for t, pose in zip(traj.timestamps, traj.poses):
        k = int(np.argmin(np.abs(t_rows - t))) if len(t_rows) else -1
        if k < 0 or abs(t_rows[k] - t) > 1e-6 + 1e-9 * abs(t):  # frames.csv prints 6 decimals
            raise RunFolderError(f"{run_dir / 'trajectory_tum.txt'}: the pose at t={t!r} s has no frame in "
                                 f"{csv_path}")
        r = rows[k]
        index = int(r["index"])
        frames.append(PosedFrame(index, int(r["frame_id"]), float(t), pose,
                                 by_name.get(f"frame_{index:06d}", -1),
                                 {c: r.get(c) or "" for c in FINGERPRINT_COLUMNS}))
    ours = {i for name, i in by_name.items() if not name.startswith("map_")}  # map_*: a loaded map's (map_reuse)
    missing = ours - {f.image_id for f in frames}
    if missing:
        raise RunFolderError(f"{run_dir / 'sparse'}: {len(missing)} keyframes have no pose in trajectory_tum.txt")
    return frames


def load_run(run_dir: str | Path, source_camera: Intrinsics | None = None) -> SavedRun:
    """Read a run folder; :class:`RunFolderError` naming the first missing file (model, trajectory, frame
    table). ``source_camera``: the intrinsics of a source given by the caller (else the session's)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunFolderError(f"{run_dir}: run folder does not exist")
    for name in MODEL_FILES:
        _require(run_dir / "sparse" / name, "the run's COLMAP model")
    # what the export reads is checked against the run's manifest: a damaged file is named here, never a
    # hang inside pycolmap's reader (the session is optional: the caller may hand over the source)
    check_run(run_dir, READ_PARTS + (("session",) if (run_dir / "session").is_dir() else ()))
    model = pycolmap.Reconstruction(str(run_dir / "sparse"))
    if model.num_reg_images() == 0:
        raise RunFolderError(f"{run_dir / 'sparse'}: the model has no registered keyframe")
    meta = _session(run_dir)
    main, estimated = None, False
    summary = run_dir / "summary.json"
    if summary.is_file():
        saved = json.loads(summary.read_text())
        main = saved.get("main_segment")
        estimated = (saved.get("camera") or {}).get("origin") == "estimated"
    frames = _posed_frames(run_dir, model, main)
    config = SlamConfig.from_dict(meta["config"]) if meta is not None and "config" in meta else SlamConfig()
    spec = meta.get("source", {}).get("spec") if meta is not None else None
    recorded = meta.get("source", {}).get("frames") if meta is not None else None
    return SavedRun(run_dir, model, frames, _camera(meta, model, source_camera, run_dir, estimated), spec, config,
                    int(recorded) if isinstance(recorded, int) else None)
