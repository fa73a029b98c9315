"""Where the least-squares optimum of a run's observations lies (issue 39, session 21).

Runs slamkit once on a sequence with ground truth, keeps its main map's observations (keyframes, points,
tracks), sets every keyframe to its ground-truth pose, re-triangulates every point from those poses (DLT
with the source's camera), and solves a global BA from there with a camera of your choice. The keyframe ATE
(Sim(3)) of that optimum is what any estimator minimising reprojection error on these observations would
reach; when the run's own keyframe ATE matches it, initialization, tracking and mapping cost nothing and the
error is in the observations or the camera model.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/ba_from_truth.py kitti-odometry/sequences/07 --max-frames 160 \\
        --camera "707.0912,707.0912,601.8873,183.1104" --camera "707.0912,707.0912,613.0,183.1104" \\
        --camera "SIMPLE_RADIAL:707.0912,601.8873,183.1104,0"
    PYTHONPATH=$PWD .venv/bin/python benchmarks/ba_from_truth.py \\
        "synthetic:street-drive?frames=100&speed=0.5&noise=1&wide=1&seed=1" --camera "707.0912,707.0912,613.1,183.1104"

``--camera MODEL:PARAMS`` is a pycolmap camera (PINHOLE when no model is named); the extra parameters of a
model with distortion (k1, k2) are refined, focal length and principal point are held.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pycolmap

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slamkit import Slam, SlamConfig  # noqa: E402
from slamkit.eval.align import estimate_alignment  # noqa: E402
from slamkit.map import CAMERA_ID, bundle_adjustment_options  # noqa: E402
from slamkit.sources import open_source  # noqa: E402


def keyframe_ate(rec: pycolmap.Reconstruction, cam_from_world_gt: dict[int, np.ndarray]) -> float:
    """RMS distance (metres) of the keyframe centres of ``rec`` to the ground truth's after a Sim(3) fit."""
    ids = sorted(cam_from_world_gt)
    est = np.array([rec.frame(i).rig_from_world.inverse().translation for i in ids])
    gt = np.array([np.linalg.inv(cam_from_world_gt[i])[:3, 3] for i in ids])
    a = estimate_alignment(est, gt, "sim3")
    return float(np.sqrt((((a.scale * est @ a.rotation.T + a.translation) - gt) ** 2).sum(1).mean()))


def ba_from_truth(rec0: pycolmap.Reconstruction, cam_from_world_gt: dict[int, np.ndarray], K: np.ndarray,
                  model: str, params: list[float]) -> tuple[float, np.ndarray]:
    """(keyframe ATE in metres, camera parameters) of a global BA of ``rec0``'s observations started from
    the ground truth, with a ``model`` camera of ``params`` (its distortion refined, the rest held)."""
    rec = pycolmap.Reconstruction(rec0)  # a copy: the run's map is left as it was
    cam = rec.camera(CAMERA_ID)
    cam.model = getattr(pycolmap.CameraModelId, model)
    cam.params = np.asarray(params, np.float64)
    for iid, T in cam_from_world_gt.items():
        rec.frame(iid).rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3])
    for pid in list(rec.points3D):
        point, rows = rec.points3D[pid], []
        for el in point.track.elements:
            xy, P = rec.image(el.image_id).points2D[el.point2D_idx].xy, K @ cam_from_world_gt[el.image_id][:3]
            rows += [xy[0] * P[2] - P[0], xy[1] * P[2] - P[1]]
        if len(rows) >= 4:
            X = np.linalg.svd(np.asarray(rows))[2][-1]
            point.xyz = X[:3] / X[3]
    config = pycolmap.BundleAdjustmentConfig()
    for iid in cam_from_world_gt:
        config.add_image(iid)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    options = bundle_adjustment_options(200, "soft_l1", refine_extra_params=model != "PINHOLE")
    pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
    return keyframe_ate(rec, cam_from_world_gt), np.asarray(rec.camera(CAMERA_ID).params)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", help="a path or synthetic spec with ground truth")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--camera", action="append", default=[],
                    help="[MODEL:]PARAMS of a camera for the BA (repeatable; default: the source's)")
    args = ap.parse_args(argv)
    pycolmap.logging.minloglevel = 2
    source = open_source(args.source, max_frames=args.max_frames)
    slam = Slam(source, SlamConfig().with_overrides(seed=args.seed))
    slam.run()
    slam_map = slam.segments[0].slam_map
    gt = {iid: np.linalg.inv(source.gt_poses[kf.frame_index]) for iid, kf in slam_map.keyframes.items()}
    c = source.camera
    print(f"{args.source}, seed {args.seed}: {len(gt)} keyframes, {slam_map.num_points} points; the run's "
          f"keyframe ATE {keyframe_ate(slam_map.reconstruction, gt):.4f} m "
          f"(camera {c.fx:g}, {c.fy:g}, {c.cx:g}, {c.cy:g})")
    for text in args.camera or [f"{c.fx},{c.fy},{c.cx},{c.cy}"]:
        model, _, numbers = text.rpartition(":")
        params = [float(v) for v in numbers.split(",")]
        err, found = ba_from_truth(slam_map.reconstruction, gt, c.K, model or "PINHOLE", params)
        print(f"  {model or 'PINHOLE'} {numbers}: BA from the truth -> keyframe ATE {err:.4f} m, "
              f"camera {np.array2string(found, precision=4)}", flush=True)


if __name__ == "__main__":
    main()
