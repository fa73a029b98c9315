"""The exported image files: the run's frames read again from its source, under the model's names.

A run folder holds no image. Its session records how the source was opened (``source.spec``) and
``frames.csv`` which frames were used (``index`` counts the frames the run saw, source index = ``index x
frame_skip``); the export reopens the source (with the run's ``--camera`` so a TUM-layout folder without a
freiburg name opens too) and checks that the dataset frame ids agree. Each frame becomes
``images/frame_NNNNNN.png`` (lossless); a JPEG file is copied byte for byte instead when nothing is
resampled.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..errors import OutputError, SlamkitError
from ..io.fingerprint import also_changed, changed, frame_file
from ..io.run_dir import source_paths
from ..sources import open_source
from ..sources.base import FrameSource, ImageListSource
from ..types import Frame
from .camera import ExportCamera
from .runfolder import PosedFrame, SavedRun

JPEG_SUFFIXES = (".jpg", ".jpeg")


def reopen_source(run: SavedRun, source: FrameSource | str | None = None) -> FrameSource:
    """The run's frame source: ``source`` when given (a FrameSource or spec), else the spec the session
    recorded, opened with the run's camera; SlamkitError when there is neither."""
    if isinstance(source, FrameSource):
        return source
    spec = source if source is not None else run.spec
    if spec is None:
        raise SlamkitError(f"{run.path}: the run does not record how its source was opened (no source.spec in "
                           "session/session.json); pass source= (the FrameSource or path the run used)")
    camera = run.config.camera or None
    if str(spec) == "default" or str(spec).startswith("synthetic:"):
        camera = None  # a synthetic source's camera is part of its spec
    return open_source(str(spec), camera=camera)


def source_position(run: SavedRun, source: FrameSource, frame: PosedFrame) -> int:
    """The index in ``source`` of a posed frame; SlamkitError when its dataset frame id disagrees."""
    i = frame.index * int(run.config.frame_skip)
    if not 0 <= i < len(source) or int(source.frame_ids[i]) != frame.frame_id:
        if run.source_frames is not None and run.source_frames != len(source):
            raise _count_changed(run, source, f"dataset frame {frame.frame_id} is not where it was")
        raise SlamkitError(f"{run.path}: frame {frame.index} (dataset frame {frame.frame_id}) is not frame {i} of "
                           f"the source {getattr(source, 'name', '?')!r}: is it the source the run was made on?")
    return i


def _count_changed(run: SavedRun, source: FrameSource, detail: str) -> SlamkitError:
    where = next(iter(source_paths(source)), None)
    return SlamkitError(f"{run.path}: its source {getattr(source, 'name', '?')!r}{f' ({where})' if where else ''} has "
                        f"{len(source)} frames now but had {run.source_frames} when the run was made: images were "
                        f"deleted, added or moved since ({detail}); restore them, or pass the source the run used "
                        "(source=)")


def check_unchanged(run: SavedRun, source: FrameSource, frames: list[PosedFrame]) -> None:
    """SlamkitError, one line naming the frames of ``frames`` whose file is not the one the run read (missing,
    another size, other bytes: :func:`slamkit.io.fingerprint.changed`, against what the run measured when it
    read each frame): the source changed during or after the run, and its poses would go with other images.
    Every frame is checked, so two swapped files are both named. Frames of a run saved before fingerprints were
    recorded pass."""
    checked: set = set()
    found: list[tuple[PosedFrame, str]] = []
    for f in frames:
        i = source_position(run, source, f)
        key = (str(frame_file(source, i)), f.fingerprint.get("sha256"), i if f.fingerprint.get("bytes") else None)
        if key in checked:  # a video of an older run: one file hash for every frame
            continue
        checked.add(key)
        why = changed(f.fingerprint, source, i)
        if why and run.source_frames is not None and run.source_frames != len(source):
            raise _count_changed(run, source, f"frame {f.index}: {why}")
        if why:
            found.append((f, why))
    if found:
        (f, why), rest = found[0], found[1:]
        also = also_changed([(g.index, g.fingerprint.get("file")) for g, _ in rest])
        raise SlamkitError(f"{run.path}: frame {f.index} (dataset frame {f.frame_id}) is not the image the run "
                           f"posed: {why}{also}; the source changed after the run read it, so nothing was exported "
                           "— restore its images, or run again on the source as it is now")


def file_name(run: SavedRun, source: FrameSource, frame: PosedFrame, camera: ExportCamera) -> str:
    """``frame_NNNNNN.png``, or ``.jpg`` for a JPEG file copied as it is."""
    path = _source_path(run, source, frame)
    if path is not None and not camera.undistort:
        return frame.name + path.suffix.lower()
    return frame.name + ".png"


def _source_path(run: SavedRun, source: FrameSource, frame: PosedFrame) -> Path | None:
    if not isinstance(source, ImageListSource):
        return None
    path = source.paths[source_position(run, source, frame)]
    return path if path.suffix.lower() in JPEG_SUFFIXES else None


def write_image(run: SavedRun, source: FrameSource, frame: PosedFrame, camera: ExportCamera,
                out: Path) -> Frame | None:
    """Write one frame to ``out`` (copy or PNG); returns the decoded frame (None for a copied JPEG)."""
    copy_from = _source_path(run, source, frame) if not camera.undistort else None
    if copy_from is not None and out.suffix.lower() == copy_from.suffix.lower():
        shutil.copyfile(copy_from, out)
        return None
    decoded = source[source_position(run, source, frame)]
    rgb = camera.undistort_image(decoded.color)
    # encoded by OpenCV, written by Python: OpenCV's writer crashes on a name that is not UTF-8
    ok, png = cv2.imencode(out.suffix or ".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    try:
        if not ok:
            raise OSError("the image cannot be encoded")
        out.write_bytes(png.tobytes())
    except OSError as e:
        raise OutputError(f"{out}: image cannot be written ({e.strerror or e})") from None
    return decoded


def read_gray(run: SavedRun, source: FrameSource, frame: PosedFrame) -> np.ndarray:
    """(H, W) uint8 grey image of a frame as the run saw it (for feature extraction)."""
    return source[source_position(run, source, frame)].gray


ProgressCallback = Callable[[int, int], None]
"""``progress(done, total)``: called after each image is written."""
