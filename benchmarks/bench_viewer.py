"""How long does one 3D-view update take as the map grows? Target: <= 50 ms per keyframe at 100,000 points.

Builds synthetic maps (pycolmap Reconstructions with ``--keyframes`` posed keyframes and 25k-200k points,
each point observed by three consecutive keyframes, as a SLAM map is) and times :meth:`MapView.show`, which
is what ``MapView.update(slam)`` does after reading the state, against a live loopback meshcat server (no
browser connected: the server stores and would forward each message; a browser renders asynchronously):

* ``load``         the first update: every point read and sent (a loaded run, a new segment, a reset)
* ``keyframe``     one keyframe later, as after a local bundle adjustment: a new keyframe with its new
                   points; the 7 newest keyframes' poses and every point they observe moved by 1e-3 of the
                   map extent (above the 1e-4 send tolerance, so all their groups are re-sent: the worst
                   case of a local BA); 20 of those points filtered (deleted). Repeated ``--updates`` times.
* ``keyframe_small_moves``  the same with moves of 1e-5 of the extent (below the tolerance) and no point
                   deleted: a converged local BA (read and diff; only the new keyframe's points are sent)
* ``global``       every keyframe and point moved (global BA / normalization): everything read and re-sent
* ``idle``         nothing changed (a non-keyframe step's map update; normally only the current frame moves)

Columns: median and 90th percentile of the total time (ms), the median read / diff / send split, points
read and sent, objects (meshcat ``set_object`` messages) and MB sent per update. A real SLAM run's
per-keyframe updates are timed too with ``--real`` (the default sequence).

Writes ``benchmarks/results/bench_viewer.csv``. Usage::

    .venv/bin/python benchmarks/bench_viewer.py                       # 25k, 50k, 100k, 200k points
    .venv/bin/python benchmarks/bench_viewer.py --points 100000 --updates 20 --real
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap

pycolmap.logging.minloglevel = 2

from slamkit.viz.meshcat_view import MapState, MapView  # noqa: E402
from slamkit.viz.server import MeshcatServer  # noqa: E402

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"
TARGET_MS = 50.0
WINDOW = 7
"""Keyframes moved by a simulated local bundle adjustment (slamkit's default local window is 6 + the new one)."""


class SyntheticMap:
    """A growing map: keyframes along a path, points introduced by each keyframe and observed by it and its
    two neighbours."""

    def __init__(self, keyframes: int, points: int, seed: int = 0):
        self.rng = np.random.default_rng(seed)
        self.per_kf = max(1, points // keyframes)
        self.rec = pycolmap.Reconstruction()
        cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500, 500, 320, 240], camera_id=1)
        self.rec.add_camera_with_trivial_rig(cam)
        self.slots: dict[int, int] = {}
        self.n_kf = 0
        for _ in range(keyframes):
            self.add_keyframe()
        self.key = object()

    def _pose(self, i: int) -> pycolmap.Rigid3d:
        a = 0.02 * i
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        c = np.array([5 * np.sin(0.01 * i), 0.0, 0.05 * i])
        return pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ c)

    def add_keyframe(self) -> list[int]:
        """A new keyframe with ``per_kf`` new points seen by it and the previous two keyframes."""
        self.n_kf += 1
        i = self.n_kf
        im = pycolmap.Image(name=f"kf{i}", keypoints=np.zeros((4 * self.per_kf + 16, 2)), camera_id=1, image_id=i)
        self.rec.add_image_with_trivial_frame(im)
        self.rec.frame(i).rig_from_world = self._pose(i)
        self.rec.register_frame(i)
        self.slots[i] = 0
        new = []
        observers = [j for j in (i - 2, i - 1, i) if j >= 1]
        centre = np.array([5 * np.sin(0.01 * i), 0.0, 0.05 * i])
        xyz = centre + self.rng.normal(0, 2.0, (self.per_kf, 3)) + [0, 0, 4]
        rgb = self.rng.integers(0, 255, (self.per_kf, 3)).astype(np.uint8)
        for p in range(self.per_kf):
            track = pycolmap.Track()
            for j in observers:
                track.add_element(j, self.slots[j])
                self.slots[j] += 1
            new.append(self.rec.add_point3D(xyz[p], track, rgb[p]))
        return new

    def local_ba(self, move: float, deleted: int = 20) -> None:
        """Move the newest WINDOW keyframes and every point they observe by ``move`` (map units); delete some."""
        ids = sorted(self.rec.reg_image_ids())[-WINDOW:]
        pts: set[int] = set()
        for i in ids:
            pose = self.rec.frame(i).rig_from_world
            self.rec.frame(i).rig_from_world = pycolmap.Rigid3d(pose.rotation, pose.translation + move)
            pts.update(p.point3D_id for p in self.rec.image(i).get_observation_points2D())
        pts_l = sorted(pts)
        for p in pts_l:
            self.rec.point3D(p).xyz = self.rec.point3D(p).xyz + self.rng.normal(0, move, 3)
        for p in self.rng.choice(pts_l, size=min(deleted, len(pts_l)), replace=False).tolist():
            self.rec.delete_point3D(int(p))

    def global_ba(self, move: float) -> None:
        for i in self.rec.reg_image_ids():
            pose = self.rec.frame(i).rig_from_world
            self.rec.frame(i).rig_from_world = pycolmap.Rigid3d(pose.rotation, pose.translation + move)
        for p in list(self.rec.point3D_ids()):
            self.rec.point3D(p).xyz = self.rec.point3D(p).xyz + move

    def state(self) -> MapState:
        ids = np.array(sorted(self.rec.reg_image_ids()))
        centres = np.array([self.rec.image(int(i)).projection_center() for i in ids])
        t = ids / 10.0
        return MapState(self.rec, ids, t, t, centres, None, key=self.key)

    @property
    def extent(self) -> float:
        c = np.array([self.rec.image(int(i)).projection_center() for i in self.rec.reg_image_ids()])
        return float(np.ptp(c, axis=0).max()) + 8.0


def _row(scenario: str, points: int, keyframes: int, stats: list) -> dict:
    tot = np.array([s.total_s for s in stats]) * 1e3
    return {
        "scenario": scenario, "points": points, "keyframes": keyframes, "updates": len(stats),
        "median_ms": float(np.median(tot)), "p90_ms": float(np.percentile(tot, 90)),
        "read_ms": float(np.median([s.read_s for s in stats]) * 1e3),
        "diff_ms": float(np.median([s.diff_s for s in stats]) * 1e3),
        "send_ms": float(np.median([s.send_s for s in stats]) * 1e3),
        "mode": stats[-1].mode,
        "points_read": int(np.median([s.points_read for s in stats])),
        "points_sent": int(np.median([s.points_sent for s in stats])),
        "objects": int(np.median([s.objects_sent for s in stats])),
        "mb_sent": float(np.median([s.bytes_sent for s in stats]) / 1e6),
    }


def bench_synthetic(server: MeshcatServer, points: int, keyframes: int, updates: int) -> list[dict]:
    t = time.perf_counter()
    m = SyntheticMap(keyframes, points)
    build = time.perf_counter() - t
    view = MapView(server=server, name=f"bench{points}")
    rows = []
    try:
        rows.append(_row("load", points, m.n_kf, [view.show(m.state())]))
        extent = m.extent
        for name, move, deleted in (("keyframe", 1e-3 * extent, 20), ("keyframe_small_moves", 1e-5 * extent, 0)):
            stats = []
            for _ in range(updates):
                m.add_keyframe()
                m.local_ba(move, deleted)
                stats.append(view.show(m.state()))
                assert view.scene_counts()["points"] == m.rec.num_points3D()
            rows.append(_row(name, m.rec.num_points3D(), m.n_kf, stats))
        rows.append(_row("idle", m.rec.num_points3D(), m.n_kf, [view.show(m.state()) for _ in range(updates)]))
        m.global_ba(1e-3 * extent)
        rows.append(_row("global", m.rec.num_points3D(), m.n_kf, [view.show(m.state())]))
        assert view.scene_counts()["points"] == m.rec.num_points3D()
    finally:
        view.show(None)
    print(f"  ({points} points: map built in {build:.1f} s)", file=sys.stderr)
    return rows


def bench_real(server: MeshcatServer, max_frames: int) -> list[dict]:
    """Per-keyframe updates of a real run (the default sequence)."""
    from slamkit.config import SlamConfig
    from slamkit.pipeline import Slam
    from slamkit.sources import open_source

    slam = Slam(open_source("default"), SlamConfig().with_overrides(frame_skip=2, max_frames=max_frames))
    view = MapView(server=server, name="real")
    stats = []
    try:
        for r in slam:
            if r.is_keyframe or r.status == "initialized":
                stats.append(view.update(slam))
    finally:
        view.show(None)
    m = slam.slam_map
    return [_row(f"real_default_{max_frames}f", m.num_points, m.num_keyframes, stats)]


COLUMNS = ["scenario", "points", "keyframes", "updates", "median_ms", "p90_ms", "read_ms", "diff_ms", "send_ms",
           "mode", "points_read", "points_sent", "objects", "mb_sent"]


def print_table(rows: list[dict]) -> None:
    head = (f"{'scenario':<22} {'points':>7} {'kf':>4} {'n':>3} {'median ms':>9} {'p90 ms':>7} {'read':>6} "
            f"{'diff':>6} {'send':>6} {'mode':<11} {'pts read':>8} {'pts sent':>8} {'objs':>5} {'MB':>5}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['scenario']:<22} {r['points']:>7} {r['keyframes']:>4} {r['updates']:>3} {r['median_ms']:>9.1f} "
              f"{r['p90_ms']:>7.1f} {r['read_ms']:>6.1f} {r['diff_ms']:>6.1f} {r['send_ms']:>6.1f} {r['mode']:<11} "
              f"{r['points_read']:>8} {r['points_sent']:>8} {r['objects']:>5} {r['mb_sent']:>5.2f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, nargs="+", default=[25_000, 50_000, 100_000, 200_000])
    ap.add_argument("--keyframes", type=int, default=300, help="keyframes of the synthetic maps")
    ap.add_argument("--updates", type=int, default=10, help="keyframe updates timed per map")
    ap.add_argument("--real", action="store_true", help="also time a real run of the default sequence")
    ap.add_argument("--real-frames", type=int, default=120)
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_viewer.csv")
    args = ap.parse_args(argv)

    rows = []
    with MeshcatServer() as server:
        for n in args.points:
            rows += bench_synthetic(server, n, args.keyframes, args.updates)
        if args.real:
            rows += bench_real(server, args.real_frames)
    print(f"MapView.show() per update, loopback meshcat server, no browser; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print_table(rows)
    at_100k = [r for r in rows if r["scenario"] == "keyframe" and r["points"] >= 95_000 and r["points"] <= 110_000]
    if at_100k:
        ms = at_100k[0]["median_ms"]
        print(f"\nkeyframe update at ~100k points: median {ms:.1f} ms (target <= {TARGET_MS:.0f} ms): "
              f"{'met' if ms <= TARGET_MS else 'NOT met'}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.3f}" if isinstance(v, float) else v) for k, v in r.items()})
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
