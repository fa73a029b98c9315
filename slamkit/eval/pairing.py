"""Which estimate pose goes with which ground-truth pose: by time, or by frame index when a file has no time.

A TUM file has a timestamp on every line, so an estimate and a ground truth in TUM form are associated by
time (:mod:`slamkit.eval.associate`). A KITTI pose file (12 values a line: the row-major 3x4 camera-to-world
matrix) has none: its line ``k`` is the pose of frame ``k`` of the sequence. Reading its lines as times
0, 1, 2 s would pair the wrong poses and report a wrong ATE, so a KITTI file is paired by **frame index**:

- a KITTI ground truth with a run folder's estimate: each frame the run processed is looked up in the
  run's ``frames.csv`` (its ``frame_id`` is the source's own frame number, which with ``--frame-skip`` is
  the index in the whole sequence, not the position in the run), and ground-truth line ``frame_id`` is given
  that frame's timestamp; the time association then pairs them exactly;
- a KITTI ground truth with a KITTI estimate of as many lines: line ``k`` with line ``k`` (as ``evo_ape kitti``
  does); of another number of lines (a run's ``trajectory_kitti.txt`` holds the posed frames only): refused;
- a KITTI file with a TUM file outside a run folder (no frame list): refused, with the reason.

Every pairing that is not by time adds a note saying how it was made (printed by ``slamkit eval``).
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..io.run_dir import RUN_MARKER
from ..io.trajectory import read_pose_file
from ..types import Trajectory

__all__ = ["FrameTable", "Pairing", "load_pair", "read_frame_table"]

FRAMES_CSV = "frames.csv"


@dataclass(frozen=True, eq=False)
class FrameTable:
    """The frames a run processed (its ``frames.csv``): ``timestamps`` (N,) seconds and ``frame_ids`` (N,)
    int64, the source's frame number of each (its index in the whole sequence)."""

    path: Path
    timestamps: np.ndarray
    frame_ids: np.ndarray


@dataclass(frozen=True, eq=False)
class Pairing:
    """An estimate and a ground truth ready for time association. ``method``: "time", "frame index" or
    "line"; ``notes``: how a pairing other than by time was made (one line each)."""

    est: Trajectory
    gt: Trajectory
    method: str
    notes: list[str] = field(default_factory=list)


def read_frame_table(run: str | os.PathLike) -> FrameTable | None:
    """The frame table of run folder ``run`` (None when it has no ``frames.csv``); FormatError naming the
    file and line of a row that cannot be read."""
    path = Path(run) / FRAMES_CSV
    if not path.is_file():
        return None
    ts, ids = [], []
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            if not {"frame_id", "timestamp"} <= set(reader.fieldnames or ()):
                raise FormatError(path, 1, "needs the columns frame_id and timestamp")
            for line, row in enumerate(reader, start=2):
                try:
                    ids.append(int(row["frame_id"]))
                    ts.append(float(row["timestamp"]))
                except (TypeError, ValueError):
                    raise FormatError(path, line, "frame_id or timestamp is not a number") from None
    except (OSError, UnicodeDecodeError) as e:
        raise FormatError(path, None, f"cannot be read ({e})") from None
    return FrameTable(path, np.asarray(ts, dtype=np.float64), np.asarray(ids, dtype=np.int64))


def _run_of(path: Path) -> Path | None:
    """The slamkit run folder holding trajectory file ``path`` directly (None when it is not in one)."""
    folder = path.parent
    return folder if (folder / RUN_MARKER).is_file() and (folder / FRAMES_CSV).is_file() else None


def _by_frame_index(gt: Trajectory, gt_path: Path, frames: FrameTable) -> tuple[Trajectory, str]:
    """Ground-truth line ``frame_id`` at the timestamp of each frame of the run that has one."""
    ok = (frames.frame_ids >= 0) & (frames.frame_ids < len(gt)) & np.isfinite(frames.timestamps)
    t, poses = frames.timestamps[ok], gt.poses[frames.frame_ids[ok]]
    order = np.argsort(t, kind="stable")
    t, poses = t[order], poses[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) if len(t) else np.zeros(0, bool)
    note = (f"{gt_path}: a KITTI pose file ({len(gt)} poses, 12 values a line, no timestamps): paired by frame "
            f"index, line k with source frame k of the run ({frames.path}); {int(keep.sum())} of the run's "
            f"{len(frames.frame_ids)} frames have a line")
    missing = len(frames.frame_ids) - int(ok.sum())
    if missing:
        beyond = frames.frame_ids[~ok]
        note += (f", {missing} have none (frame ids up to {int(beyond.max())}, the file ends at {len(gt) - 1}): "
                 "is it the ground truth of this sequence?")
    return Trajectory(t[keep], poses[keep]), note


def load_pair(est: Trajectory | str | os.PathLike, gt: Trajectory | str | os.PathLike, *,
              frames: FrameTable | None = None) -> Pairing:
    """Read ``est`` and ``gt`` (Trajectories, or TUM / KITTI files) and make them pairable by time (see the
    module docstring). ``frames``: the run's frame table, needed for a KITTI ground truth; by default the one
    of the run folder that holds the estimate file, if any. FormatError naming the file when a KITTI file
    cannot be paired."""
    est_kind, gt_kind = "tum", "tum"
    est_path = gt_path = None
    if not isinstance(est, Trajectory):
        est_path = Path(est)
        est_kind, est = read_pose_file(est_path)
    if not isinstance(gt, Trajectory):
        gt_path = Path(gt)
        gt_kind, gt = read_pose_file(gt_path)
    if est_kind == "tum" and gt_kind == "tum":
        return Pairing(est, gt, "time")
    if est_kind == "kitti" and gt_kind == "kitti":
        if len(est) != len(gt):
            raise FormatError(est_path, None, f"a KITTI pose file of {len(est)} lines against the KITTI ground truth "
                                              f"{gt_path} of {len(gt)}: neither has timestamps or frame numbers, so "
                                              "lines pair only when both hold every frame; evaluate the run folder "
                                              "(slamkit eval RUN --gt FILE), which pairs by frame index")
        note = (f"{est_path} and {gt_path} are both KITTI pose files (no timestamps): paired line by line "
                f"({min(len(est), len(gt))} lines)")
        return Pairing(est, gt, "line", [note])
    if est_kind == "kitti":
        beside = est_path.with_name("trajectory_tum.txt")
        hint = (f"evaluate {beside} (the same poses with their timestamps) or the run folder"
                if beside.is_file() else "give the estimate in TUM form (with timestamps)")
        raise FormatError(est_path, None, f"a KITTI pose file (12 values a line) has no timestamps, so it cannot be "
                                          f"paired with the TUM ground truth {gt_path or 'given'}: {hint}")
    if frames is None and est_path is not None:
        run = _run_of(est_path)
        frames = read_frame_table(run) if run is not None else None
    if frames is None:
        raise FormatError(gt_path or Path("gt"), None,
                          "a KITTI pose file (12 values a line, no timestamps): its line k is frame k of the "
                          f"sequence, but the estimate {est_path or ''} is a TUM trajectory without the run's frame "
                          "list, so its frames cannot be paired by index (reading the lines as 0, 1, 2 s would pair "
                          "the wrong poses): evaluate the run folder (slamkit eval RUN --gt FILE), or give the "
                          "estimate as a KITTI file of the same frames")
    paired, note = _by_frame_index(gt, gt_path or Path("gt"), frames)
    return Pairing(est, paired, "frame index", [note])
