"""Is a given camera's leftover radial distortion real? k1 of the whole map against k1 of its halves (issue 39).

``ba.radial_keyframes`` estimates one radial coefficient k1 for a given camera when the map reaches N keyframes
(:func:`slamkit.run_camera.calibrate_radial`). It gains KITTI and costs 7-Scenes and the rendered (exact pinhole)
street. To turn it on by default, a test must tell leftover lens distortion (constant over the sequence) from a
k1 that fits something else. This script runs each case until the estimate is due, then estimates k1 again on
four halves of the same map, each alone (the other half's observations deleted from a copy; a global BA with
only k1 refined among the intrinsics, two poses fixed): the first and the second half in time, the even and the
odd keyframes. The run stops there. One row per (case, seed); CSV with ``--csv``.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/radial_halves.py --cases 'kitti-07/*,7scenes/*,syn-street-1.0' \\
        --seeds 3 --csv /tmp/radial_halves.csv

The estimate is intercepted by replacing ``slamkit.pipeline.calibrate_radial`` with a wrapper in this process
(instrumentation of a real run; the pipeline's own estimate is the ``pipeline`` column).
"""

from __future__ import annotations

import argparse
import copy
import csv
import sys
from pathlib import Path

import numpy  # noqa: F401  (before pycolmap: see slamkit/__init__.py)
import pycolmap

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import bench_suite as bs  # noqa: E402

from slamkit import pipeline  # noqa: E402
from slamkit.config import SlamConfig  # noqa: E402
from slamkit.map import CAMERA_ID, bundle_adjustment_options  # noqa: E402
from slamkit.sources import open_source  # noqa: E402

COLUMNS = ["case", "seed", "keyframes", "pipeline", "all", "first", "second", "even", "odd"]


class _Due(Exception):
    """Raised by the wrapper once the estimate was made: the run ends there."""


def k1_of(rec0: pycolmap.Reconstruction, keep: set[int], iterations: int = 100) -> float:
    """k1 of a global BA of a copy of ``rec0`` with only the keyframes ``keep`` observing its points (every
    other keyframe's observations deleted) and a SIMPLE_RADIAL camera whose focal length and principal point
    are held."""
    rec = copy.deepcopy(rec0)
    for image_id in list(rec.images):
        if image_id in keep:
            continue
        for idx, p in enumerate(rec.image(image_id).points2D):
            if p.has_point3D():
                rec.delete_observation(image_id, idx)
    cam = rec.camera(CAMERA_ID)
    fx, _, cx, cy = (float(v) for v in cam.params)
    rec.cameras[CAMERA_ID] = pycolmap.Camera(model="SIMPLE_RADIAL", width=cam.width, height=cam.height,
                                             params=[fx, cx, cy, 0.0], camera_id=CAMERA_ID)
    cfg = pycolmap.BundleAdjustmentConfig()
    for image_id in keep:
        cfg.add_image(image_id)
    cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    opts = bundle_adjustment_options(iterations, "soft_l1", False, 1e-6, 1, refine_principal_point=False,
                                     refine_extra_params=True)
    opts.refine_focal_length = False
    pycolmap.create_default_bundle_adjuster(opts, cfg, rec).solve()
    return float(rec.camera(CAMERA_ID).params[3])


def measure(case: bs.Case, seed: int, keyframes: int) -> dict:
    """Run ``case`` until the k1 estimate is due; the row of k1 values (None when it never became due)."""
    row = {"case": case.name, "seed": seed, "keyframes": keyframes}
    original = pipeline.calibrate_radial

    def wrapper(state, seg, adjuster, camera, config):
        rec, ids = seg.slam_map.reconstruction, sorted(seg.slam_map.keyframes)
        n = len(ids)
        for name, keep in (("all", ids), ("first", ids[:n // 2]), ("second", ids[n // 2:]),
                           ("even", ids[0::2]), ("odd", ids[1::2])):
            row[name] = k1_of(rec, set(keep))
        row["pipeline"] = original(state, seg, adjuster, camera, config).dist[0] - camera.dist[0]
        raise _Due

    pipeline.calibrate_radial = wrapper
    try:
        config = SlamConfig().with_overrides(seed=seed, frame_skip=case.skip, **case.config)
        config = config.with_overrides(**{"ba.radial_keyframes": keyframes})
        pipeline.Slam(open_source(case.source_spec(seed), **case.kw), config).run()
    except _Due:
        pass
    finally:
        pipeline.calibrate_radial = original
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="kitti-07/*,7scenes/*,video-kitti984,syn-*", help="glob patterns, comma-separated")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--keyframes", type=int, default=20, help="ba.radial_keyframes")
    ap.add_argument("--csv", default=None)
    args = ap.parse_args(argv)
    pycolmap.logging.minloglevel = 2
    cases = [c for c in bs.select_cases(bs.CASES, args.cases, False) if not bs._absent(c)
             and c.config.get("camera") != "auto" and c.ground_truth == ()]
    rows = []
    print(" | ".join(COLUMNS))
    for case in cases:
        for seed in range(args.seeds):
            row = measure(case, seed, args.keyframes)
            rows.append(row)
            print(" | ".join(f"{row[k]:+.4f}" if isinstance(row.get(k), float) else str(row.get(k, "-"))
                             for k in COLUMNS), flush=True)
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            w = csv.DictWriter(f, COLUMNS)
            w.writeheader()
            w.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
