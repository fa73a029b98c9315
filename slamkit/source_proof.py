"""A resume proves its source (issue 50): before one frame is processed, the source a session is resumed on
must be the one the run read.

:func:`source_identity` is what a session records of its source (kind, name, frame count, a digest of the
frame ids and times, camera); :func:`check_source` compares it. :func:`check_frames_read` then reads every
frame the session processed again and compares it with the fingerprint taken when the run read it
(:class:`~slamkit.types.Fingerprint`, :func:`slamkit.io.fingerprint.changed`). A mismatch is one
:class:`~slamkit.errors.SessionError` line naming the frames and files that differ; nothing is written.
"""

from __future__ import annotations

import csv
import hashlib
import os
from pathlib import Path

import numpy as np

from .errors import SessionError
from .io.fingerprint import FINGERPRINT_COLUMNS, MAX_NAMED, also_changed, changed, frame_file
from .types import Fingerprint

SESSION_DIR = "session"
"""The session folder's name inside a run folder (:data:`slamkit.session.SESSION_DIR`)."""


def source_identity(source, frames: int | None = None) -> dict:
    """Name, frame count, a digest of frame ids and timestamps, and the intrinsics of a frame source (the
    digest of its first ``frames`` frames when given)."""
    h = hashlib.sha256()
    for name, dtype in (("frame_ids", np.int64), ("timestamps", np.float64)):
        values = getattr(source, name, None)
        if values is not None:
            h.update(np.ascontiguousarray(np.asarray(values, dtype)[:frames]).tobytes())
    cam = getattr(source, "camera", None)
    return {"kind": source_kind(source), "name": str(getattr(source, "name", type(source).__name__)),
            "frames": int(len(source)), "digest": h.hexdigest()[:16],
            "camera": cam.to_dict() if cam is not None else None}


_LAYOUTS = ("tum", "kitti", "7scenes", "euroc", "folder")


def source_kind(source) -> str:
    """What kind of source it is: its layout (``tum``, ``kitti``, ``7scenes``, ``euroc``, ``folder``), ``video``,
    ``synthetic`` (rendered), or "" for a source of the caller's own (a wrapper of one of these, say: its
    kind is not known, and not compared)."""
    cls = type(source).__name__
    if cls in ("VideoSource", "SyntheticSource"):
        return "video" if cls == "VideoSource" else "synthetic"
    prefix = str(getattr(source, "name", "")).split("/", 1)[0]
    return prefix if prefix in _LAYOUTS and cls == "ImageListSource" else ""


def check_source(saved: dict, source, folder: Path) -> None:
    """SessionError naming what differs when ``source`` is not the source whose :func:`source_identity` a
    session saved (``saved``): its kind first, then name, frame count, frame ids and times, camera."""
    now = source_identity(source)
    if saved.get("kind") and now["kind"] and saved["kind"] != now["kind"]:  # none in sessions before issue 50
        raise SessionError(f"{folder}: the session was recorded on a {saved['kind']} source ({saved['name']!r}), "
                           f"this is a {now['kind']} source ({now['name']!r}): give the source the run was made on")
    problems = []
    if now["name"] != saved["name"]:
        problems.append(f"name {saved['name']!r} vs {now['name']!r}")
    if saved.get("spec") and saved["spec"] == getattr(source, "spec", None) and saved["frames"] < now["frames"]:
        # the same spec, opened with max_frames in Python (open_source(spec, max_frames=N)), resumed on the whole
        # source: its first frames must be the saved ones
        if source_identity(source, saved["frames"])["digest"] != saved["digest"]:
            problems.append(f"different frame ids or timestamps in the first {saved['frames']} frames")
    elif now["frames"] != saved["frames"]:
        problems.append(f"{saved['frames']} frames vs {now['frames']}")
    elif now["digest"] != saved["digest"]:
        problems.append("different frame ids or timestamps")
    if now["camera"] != saved["camera"]:
        problems.append(f"intrinsics {saved['camera']} vs {now['camera']}")
    if problems:
        raise SessionError(f"{folder}: the session was recorded on another source ({'; '.join(problems)}): "
                           f"session {saved['name']!r} ({saved['frames']} frames), given {now['name']!r} "
                           f"({now['frames']} frames)")


def _recorded_frames(meta: dict, folder: Path) -> tuple[list[dict], str]:
    """What the session says of each frame it processed: index, status, unreadable and the fingerprint
    columns (``frames.csv``'s names), and where that came from. A session of slamkit before issue 50 holds no
    fingerprint: those of the run folder's ``frames.csv`` (measured when it was saved) stand in for them."""
    cols, n = meta["records"]["columns"], int(meta["records"]["count"])
    rows = [{"index": int(cols["index"][k]), "status": str(cols["status"][k]),
             "unreadable": str((cols.get("unreadable") or [""] * n)[k] or "")} for k in range(n)]
    if "sha256" in cols:
        for k, r in enumerate(rows):
            r.update(file=cols["file"][k], bytes=str(cols["file_bytes"][k]), width=str(cols["width"][k]),
                     height=str(cols["height"][k]), sha256=cols["sha256"][k])
        return rows, "session"
    table = folder.parent / "frames.csv" if folder.name == SESSION_DIR else None
    if table is None or not table.is_file():
        return rows, ""
    with open(table, newline="", errors="surrogateescape") as f:
        by_index = {int(r["index"]): r for r in csv.DictReader(f) if (r.get("index") or "").strip().isdigit()}
    for r in rows:
        saved = by_index.get(r["index"], {})
        r.update({c: saved.get(c) or "" for c in FINGERPRINT_COLUMNS})
    return rows, str(table)


def check_frames_read(meta: dict, source, indices: np.ndarray, folder: Path) -> dict[int, Fingerprint]:
    """A resume proves its source (issue 50): every frame the session processed is read again from ``source``
    (``indices``: the run's source index of each frame) and measured as the run measured it when it read it
    (:func:`slamkit.io.fingerprint.changed`: name, size, pixels, SHA-256); SessionError, one line naming the
    frames and files that differ, before anything is processed or written. Every frame is checked (a 1,000-frame
    image folder costs about a second: the files are read, not decoded; a video is decoded again up to the
    resume point). A session of slamkit before issue 50 is checked against its run folder's ``frames.csv``; one
    without either (a session folder alone) is refused when its source has files: nothing proves them.
    Returns the fingerprints proven that the session itself did not hold (index -> Fingerprint)."""
    rows, origin = _recorded_frames(meta, folder)
    read = [r for r in rows if (r.get("sha256") or "").strip()  # a frame a stage failed on too: it was read
            or (r["status"] != "error" and not r["unreadable"])]
    unrecorded = [r for r in read if not (r.get("sha256") or "").strip()
                  and frame_file(source, int(indices[r["index"]])) is not None]
    if unrecorded and not origin:
        raise SessionError(f"{folder}: saved by an older slamkit without the fingerprints of the {len(read)} frames "
                           "it read, and no frames.csv beside it: nothing proves that this source holds the images the "
                           "run used; start a new run (slamkit run SOURCE --out NEW_FOLDER)")
    differ: list[tuple[dict, str]] = []
    proven: dict[int, Fingerprint] = {}
    for r in read:
        if not (r.get("sha256") or "").strip():
            continue
        i = int(indices[r["index"]])
        why = changed(r, source, i)
        if why:
            differ.append((r, why))
        elif origin != "session" and getattr(source, "paths", None) is not None and str(r.get("width")).isdigit():
            size = str(r["bytes"]) if str(r["bytes"]).isdigit() else os.stat(frame_file(source, i)).st_size
            proven[r["index"]] = Fingerprint(r["file"], int(size), int(r["width"]), int(r["height"]), r["sha256"])
    if differ:
        (r, why), rest = differ[0], differ[1:]
        name = r.get("file") or "?"
        also = also_changed([(x["index"], x.get("file")) for x, _ in rest])
        raise SessionError(f"{folder}: frame {r['index']} ({name}) is not the image the run read: {why}{also}; "
                           f"{len(differ)} of the {len(read)} frames processed differ, so nothing was resumed or "
                           "written — give the source the run was made on")
    return proven


__all__ = ["MAX_NAMED", "check_frames_read", "check_source", "source_identity", "source_kind"]
