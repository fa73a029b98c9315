"""Export a saved run as a dataset for Gaussian splatting or NeRF: the library function (see the package
docstring of :mod:`slamkit.exporter`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import SlamConfig
from ..errors import ConfigError, OutputError, SlamkitError, shown
from ..features import create_extractor
from ..io.atomic import atomic_dir
from ..io.run_dir import EXPORT_MARKER, check_output, out_dir_lock, write_listing
from ..sources.base import FrameSource
from .camera import ExportCamera
from .images import ProgressCallback, check_unchanged, file_name, read_gray, reopen_source, write_image
from .model import PointDescriptors, build_model, keyframe_descriptors, match_frame, select_frames
from .nerfstudio import PLY_NAME, write_ply, write_transforms
from .runfolder import PosedFrame, SavedRun, load_run

FORMATS = ("colmap", "nerfstudio")
MARKER = EXPORT_MARKER
"""File marking a folder written by :func:`export` (an existing folder without it is never replaced)."""


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export` wrote: folder, format, registered images, 3D points, observations recovered
    for non-keyframes, the exported camera model and its mean reprojection error (pixels)."""

    path: Path
    format: str
    num_images: int
    num_points: int
    num_matched_observations: int
    camera_model: str
    mean_reprojection_error: float


def _check_out(out: Path, run_dir: Path, source) -> None:
    """The export folder may be written (:func:`slamkit.io.run_dir.check_output`): never the run folder or
    one holding it, nothing inside a run or the source, an existing folder only when it is an export."""
    out_r, run_r = out.resolve(), run_dir.resolve()
    if out_r == run_r or out_r in run_r.parents:
        raise OutputError(f"{out}: the export folder would replace the run folder {run_dir}")
    check_output(out, "export", [source], flag="out")


def _extractor(config: SlamConfig):
    """The run's feature extractor, or None when it cannot be created here (then no observations)."""
    try:
        return create_extractor(config.features, **config.extractor_options())
    except (SlamkitError, ImportError):
        return None


def _write_images(run: SavedRun, source: FrameSource, frames: list[PosedFrame], camera: ExportCamera,
                  folder: Path, names: dict[int, str], progress: ProgressCallback | None):
    """Write every frame's image; returns the non-keyframe observations ``{index: (pixels, point ids)}``."""
    folder.mkdir(parents=True, exist_ok=True)
    keyframes = [f for f in frames if f.is_keyframe]
    others = [f for f in frames if not f.is_keyframe]
    extractor = _extractor(run.config) if others else None
    points = PointDescriptors(run.model)
    extra: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    K, size = run.camera.K, (run.camera.width, run.camera.height)
    for done, f in enumerate(keyframes + others, start=1):
        decoded = write_image(run, source, f, camera, folder / names[f.index])
        if extractor is not None:
            gray = decoded.gray if decoded is not None else read_gray(run, source, f)
            feats = extractor.extract(gray)
            kp = run.camera.undistort_points(feats.keypoints)
            if f.is_keyframe:
                found = keyframe_descriptors(run.model, f.image_id, feats, kp)
                if found is not None:
                    points.add(f.index, f.image_id, *found, feats.binary)
            else:
                extra[f.index] = match_frame(points, f, feats, kp, K, size, run.config)
        if progress is not None:
            progress(done, len(frames))
    return extra


def export(run_dir: str | Path, out: str | Path, format: str = "colmap", frames: str = "keyframes",
           undistort: bool | None = None, progress: ProgressCallback | None = None,
           source: FrameSource | str | None = None) -> ExportResult:
    """Export the run saved in ``run_dir`` to ``out`` (see the module docstring).

    Args:
        format: ``"colmap"`` (``images/`` + ``sparse/0/``) or ``"nerfstudio"`` (``images/`` +
            ``transforms.json`` + ``sparse_pc.ply``).
        frames: ``"keyframes"``, ``"all"`` or ``"every=N"`` (every N-th posed frame plus the keyframes).
        undistort: resample distorted images onto a PINHOLE camera (COLMAP's undistorter); None or False
            keeps the source's distortion in the exported camera (OPENCV). No effect without distortion.
        progress: ``progress(done, total)`` after each image.
        source: the run's frame source (or spec) when the session does not record it or it moved.

    Raises RunFolderError naming the missing file of an incomplete run folder, ConfigError for a bad
    ``format``/``frames``, OutputError when ``out`` cannot be written or is a folder that is not an export.
    """
    if format not in FORMATS:
        raise ConfigError(f"format must be one of {', '.join(FORMATS)} (got {format!r})")
    out, run_dir = Path(out), Path(run_dir)
    _check_out(out, run_dir, None)  # before anything is read; again below with the source's paths
    with out_dir_lock(out, flag="out", what="export folder"):  # one writer at a time, from the first check on
        return _export(run_dir, out, format, frames, undistort, progress, source)


def _export(run_dir: Path, out: Path, format: str, frames: str, undistort: bool | None,
            progress: ProgressCallback | None, source: FrameSource | str | None) -> ExportResult:
    run = load_run(run_dir, source.camera if isinstance(source, FrameSource) else None)
    selected = select_frames(run.frames, frames)
    src = reopen_source(run, source)
    _check_out(out, run_dir, src)
    check_unchanged(run, src, selected)  # the images the run posed, or nothing is written
    camera = ExportCamera.create(run.camera, bool(undistort))
    names = {f.index: file_name(run, src, f, camera) for f in selected}
    with atomic_dir(out, kind="export") as tmp:  # _check_out allowed it; atomic_dir checks again
        extra = _write_images(run, src, selected, camera, tmp / "images", names, progress)
        rec = build_model(run.model, selected, camera, names, extra)
        if format == "colmap":
            (tmp / "sparse" / "0").mkdir(parents=True)
            rec.write_binary(str(tmp / "sparse" / "0"))
        else:
            write_transforms(tmp / "transforms.json", camera, rec)
            write_ply(tmp / PLY_NAME, rec)
        write_listing(tmp, MARKER, f"slamkit export of {shown(run_dir.resolve())}")  # what a later export replaces
    return ExportResult(out, format, rec.num_reg_images(), rec.num_points3D(),
                        int(sum(len(p) for _, p in extra.values())), camera.model_name,
                        float(rec.compute_mean_reprojection_error()))

