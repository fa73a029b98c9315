"""How long does the Sim(3) pose-graph correction take, per backend, as the number of keyframes grows?

A circle of keyframes (radius 10 m) with drifting odometry (0.02 degree, 0.05 % scale and 1 mm per keyframe),
spanning-tree and covisibility edges to the 5 previous keyframes, one loop edge (last -> first) with the true
Sim(3). Reported per size and backend: process CPU seconds, iterations/evaluations, largest camera-centre and
rotation error before and after.

Usage::

    nice -n 5 .venv/bin/python benchmarks/bench_pose_graph.py --sizes 100 300 1000 --backends scipy gtsam
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation

from slamkit.pose_graph import PoseGraphConfig, loop_edge, optimize_pose_graph, relative_edges, sim3_matrix


def _loop(n: int) -> tuple[dict, dict, np.ndarray]:
    """(ground-truth cam_from_world, drifted cam_from_world, true Sim(3) of the loop: last map -> first)."""
    gt, est = {}, {}
    err = Rotation.from_euler("xyz", [0.02, -0.01, 0.014], degrees=True).as_matrix()
    scale = 1.0
    for i in range(n):
        a = 2 * np.pi * i / n
        c = np.array([10 * np.cos(a), 10 * np.sin(a), 1.5])
        z = np.array([np.cos(a), np.sin(a), 0.0])
        x = np.cross(z, [0, 0, 1.0])
        r_wc = np.stack([x, np.cross(z, x), z], axis=1)
        gt[i] = np.eye(4)
        gt[i][:3, :3], gt[i][:3, 3] = r_wc.T, -r_wc.T @ c
        if i == 0:
            est[0] = gt[0].copy()
            continue
        rel = gt[i] @ np.linalg.inv(gt[i - 1])
        scale *= 1.0005
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = err @ rel[:3, :3], scale * rel[:3, 3] + 0.001
        est[i] = step @ est[i - 1]
    q = n - 1
    return gt, est, np.linalg.inv(gt[q]) @ sim3_matrix(1.0 / scale, np.eye(3), np.zeros(3)) @ est[q]


def _max_errors(poses: dict, gt: dict) -> tuple[float, float]:
    centre = lambda t: -t[:3, :3].T @ t[:3, 3]  # noqa: E731
    pos = max(np.linalg.norm(centre(poses[k]) - centre(gt[k])) for k in gt)
    rot = max(np.degrees(Rotation.from_matrix(poses[k][:3, :3] @ gt[k][:3, :3].T).magnitude()) for k in gt)
    return pos, rot


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100, 300, 1000])
    ap.add_argument("--backends", nargs="+", default=["scipy", "gtsam"])
    args = ap.parse_args()
    print(f"{'keyframes':>9} {'edges':>6} {'backend':>7} {'cpu s':>7} {'iter':>5} {'pos err m':>15} {'rot err deg':>15}")
    for n in args.sizes:
        gt, est, sim = _loop(n)
        pairs = [(i, i - d) for d in range(1, 6) for i in range(d, n)]
        edges = relative_edges(est, pairs) + [loop_edge(n - 1, 0, est[n - 1], est[0], sim)]
        before = _max_errors(est, gt)
        for backend in args.backends:
            t = time.process_time()
            result = optimize_pose_graph(est, edges, fixed=0, config=PoseGraphConfig(backend=backend))
            cpu = time.process_time() - t
            after = _max_errors(result.cam_from_world, gt)
            print(f"{n:>9} {len(edges):>6} {backend:>7} {cpu:>7.2f} {result.evaluations:>5} "
                  f"{before[0]:>6.3f} -> {after[0]:<6.3f} {before[1]:>6.2f} -> {after[1]:<6.2f}")


if __name__ == "__main__":
    main()
