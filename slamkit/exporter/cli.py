"""``slamkit export RUN_DIR --format colmap|nerfstudio --out DIR [--frames ...] [--undistort]``.

:func:`add_export_parser` registers the subcommand on the ``slamkit`` parser's subparsers; its handler
(``args.func``) calls :func:`slamkit.exporter.export` with a tqdm progress bar and prints what was written.
"""

from __future__ import annotations

import argparse

from tqdm import tqdm

from .api import FORMATS, export


def run_export(args: argparse.Namespace) -> int:
    """Handler of ``slamkit export``; returns the exit code (errors propagate as SlamkitError)."""
    bar = tqdm(total=0, unit="img", desc="export", disable=args.quiet, leave=False)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    try:
        result = export(args.run_dir, args.out, format=args.format, frames=args.frames, undistort=args.undistort,
                        progress=progress)
    finally:
        bar.close()
    print(f"{result.format} export: {result.num_images} images, {result.num_points} points "
          f"({result.camera_model} camera, mean reprojection error {result.mean_reprojection_error:.3f} px) "
          f"-> {result.path}")
    return 0


def add_export_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``export`` subcommand to ``subparsers`` (from ``ArgumentParser.add_subparsers()``); sets
    ``func=run_export`` as its default. Returns the subparser."""
    p = subparsers.add_parser(
        "export", help="export a run as a Gaussian-splatting / NeRF dataset (COLMAP layout or nerfstudio)",
        description="Write the run's frames and model as DIR/images + DIR/sparse/0 (gsplat, 3DGS) or "
                    "DIR/images + DIR/transforms.json + DIR/sparse_pc.ply (nerfstudio).")
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run folder (slamkit run --out / slam.save)")
    p.add_argument("--format", choices=FORMATS, required=True, help="output layout")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (replaced atomically)")
    p.add_argument("--frames", default="keyframes", metavar="keyframes|all|every=N",
                   help="registered views: the keyframes (default), every posed frame, or every N-th plus "
                        "the keyframes")
    p.add_argument("--undistort", action="store_true",
                   help="resample distorted images onto a pinhole camera (COLMAP's undistorter)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_export)
    return p
