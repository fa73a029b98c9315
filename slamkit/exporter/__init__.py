"""Export a saved run as a dataset for Gaussian splatting or NeRF training.

``export(RUN_DIR, OUT, format="colmap")`` writes ``OUT/images/`` (the frames, read again from the run's
source, under the names the model uses, with extension) and ``OUT/sparse/0/{cameras,images,points3D}.bin``:
the layout the COLMAP loaders of gsplat and of the original 3D Gaussian Splatting code read.
``format="nerfstudio"`` writes ``OUT/images/``, ``OUT/transforms.json`` and ``OUT/sparse_pc.ply``
(:mod:`slamkit.exporter.nerfstudio`). ``frames`` chooses the registered views: the keyframes (the run's model
as it is), ``"all"`` posed frames or ``"every=N"``; non-keyframes get their pose from
``trajectory_tum.txt`` and 2D-3D observations recovered by guided matching (:mod:`slamkit.exporter.model`).
A source with lens distortion keeps it (OPENCV camera) unless ``undistort=True``, which resamples the
images with COLMAP's undistorter onto a PINHOLE camera (:mod:`slamkit.exporter.camera`).

The output folder is written atomically (:func:`slamkit.io.atomic.atomic_dir`) and carries a marker file:
an existing folder is replaced only when it is empty or a previous export.
"""

from .cli import add_export_parser
from .api import FORMATS, MARKER, ExportResult, export
from .runfolder import RunFolderError

__all__ = ["export", "ExportResult", "FORMATS", "MARKER", "RunFolderError", "add_export_parser"]
