"""What a finished run's map is made of, against ground truth (issue 52, item 1): where local mapping loses
against COLMAP's triangulator.

Two verbs:

``run SOURCE --out DIR [--mapper local|colmap] [--seed S] [--max-frames N] [--set KEY=VALUE ...]``
    One ordinary slamkit run (``Slam(source, SlamConfig().with_overrides(...)).run()``, then ``Slam.save``),
    with measurements that only watch: every step's result goes to ``DIR/steps.csv``, the step that made
    each observation to ``DIR/provenance.csv`` (:func:`install_provenance_hook`), and every call of
    ORB-SLAM's outlier test (:func:`slamkit.stages.ba.remove_outlier_observations`, wrapped in this process
    only; its result is unchanged) is counted into ``DIR/chi2_tested.csv`` (observations tested, by context,
    octave and depth bin) and ``DIR/chi2_removed.csv`` (one row per observation removed). The library is not
    changed: a run folder made by ``slamkit run`` can be analysed too, without the chi2 and steps columns.

``analyze --runs DIR [DIR ...] [--gt FILE] [--csv PREFIX] [--no-ba] [--group]``
    Reads each finished run folder (``sparse/``, ``frames.csv``, ``summary.json``, ``trajectory_tum.txt``,
    ``keyframes_tum.txt``, ``groundtruth_tum.txt`` or ``--gt``, ``session/`` for keypoint sizes) and prints
    the tables below; writes ``PREFIX_summary.csv`` (one row per run), ``PREFIX_octave.csv``,
    ``PREFIX_depth.csv``, ``PREFIX_track.csv``, ``PREFIX_origin.csv`` and ``PREFIX_chi2.csv`` (one row per
    run and bin).

Summary columns (one row per run; lengths in metres after the Sim(3) alignment, errors in pixels):

* run: the folder's name; frames: frames of the run; posed: frames in the main segment's trajectory;
* ate_all: ATE RMSE (Sim(3) fitted to all posed frames); ate_kf: ATE RMSE over keyframes only (Sim(3)
  fitted to keyframes: ORB-SLAM2's KeyFrameTrajectory.txt); ate_all_on_kf / ate_all_on_nonkf: the RMSE of
  the all-frames alignment's errors restricted to keyframes / to the frames between them (is the loss in
  the frames posed between keyframes?); ate_all_on_inner_nonkf: the same over the non-keyframes between the
  first and the last keyframe; outer_frames: frames before the first or after the last keyframe;
* rel_nonkf: RMS of the error of each non-keyframe's displacement from the keyframe before it (estimate
  scaled and rotated by the all-frames alignment minus the truth): error made *since* the last keyframe;
  rel_kf: the same for each keyframe from the keyframe before it;
* keyframes, culled (``summary.json``'s keyframes_culled), kf_gap_mean / kf_gap_median / kf_gap_max: frame
  index spacing of the final keyframes;
* points, obs: 3-D points and observations of the map; track_mean / track_median / track_p10 / track_p25 /
  track_p75 / track_p90: keyframe observations per point; track2_pct: % points seen by exactly 2 keyframes;
  track5_pct: % seen by >= 5; pts_per_kf / obs_per_kf: mean points seen per keyframe (= its observations);
* reproj_rms / reproj_median: reprojection error of every observation in the final map;
* gt_reproj_median / gt_reproj_p90 / gt_bad_pct: each point triangulated (DLT) from the *true* poses of its
  keyframes, reprojection error there: how consistent the tracks are with the true geometry (a wrong match
  or a merged duplicate shows up here whatever the estimate); gt_bad_pct: % of observations above
  sqrt(5.991) x the keypoint's scale (ORB-SLAM's chi2 bound) at the truth;
* ba_kf_ate: keyframe ATE of the run's own map (keyframe poses only, as in ``ba_from_truth.py``); ba_opt_ate:
  keyframe ATE of the optimum of the map's observations started from the truth (``ba_from_truth.py``: what
  the observations themselves allow); ba_gap: ba_kf_ate - ba_opt_ate (lost by the estimation);
* inliers_mean / inliers_median: 2D-3D pose inliers per tracked frame (``run`` only: how many map points each
  frame is posed from); created / culled_pts / fused / fused_obs: local mapping's counts summed over keyframes;
* chi2_tested / chi2_removed / chi2_removed_pct: observations the outlier test looked at / removed (``run``
  only; every pass counted).

Octave table (per run and ORB octave, octave = round(log(size / smallest size) / log 1.2)): obs, obs_pct,
points (points with an observation at this octave), reproj_rms, reproj_median, norm_median (error /
1.2^octave), gt_reproj_median, gt_bad_pct, track_mean (track length of the observation's point, averaged over
the observations at this octave).

Depth table (per run and metric depth bin of the observation, depth = camera z x the keyframe alignment's
scale; bin edges: quantiles 0/20/40/60/80/100 % of the first run's depths, the same for every run, or
``--depth-edges``): obs, obs_pct, reproj_rms, reproj_median, gt_reproj_median, gt_bad_pct, track_mean (as in
the octave table).

Seeds table (with ``--group``): runs named ``NAME_sSEED`` grouped by NAME, each summary column as mean ± standard
error (sd / sqrt(n)) over the seeds, n the number of runs.

Track table (per run and track-length bin of the observation's point): obs, obs_pct, points, reproj_median,
norm_median, gt_reproj_median, gt_bad_pct. Compare maps within a bin: a point adjusted from L observations keeps
2L - 3 of their 2L residual dimensions, so shorter tracks show smaller residuals for the same keypoint noise.

Origin table (``run`` only; per run and the step that last gave the observation its point: tracked = the new
keyframe's tracking inliers, created = local mapping's new points, fused = local mapping's fusion,
triangulator = COLMAP's triangulation, track completion and merging): obs, obs_pct, reproj_median,
gt_reproj_median, gt_bad_pct, track_mean, reproj_median_4_8 and gt_bad_pct_4_8 (over points of 4-8
observations only).

Chi2 table (``run`` only; per run, context and octave or relative-depth bin): context is ``local_pass``
(between the two local BA passes), ``local_maintain`` (after the last local pass) or ``global`` (after a
global BA, the final one included); tested, removed, removed_pct, point_deleted (points that lost their
last-but-one observation with it). Relative depth = z / median z of the keyframe's tested observations.

Usage::

    PYTHONPATH=$PWD nice -n 10 .venv/bin/python benchmarks/diagnose_map_quality.py run \\
        ../shared/data/7scenes-redkitchen --max-frames 600 --out /tmp/r/s600_local --mapper local --seed 0
    PYTHONPATH=$PWD .venv/bin/python benchmarks/diagnose_map_quality.py analyze \\
        --runs /tmp/r/s600_local /tmp/r/s600_colmap --csv /tmp/r/s600
"""

from __future__ import annotations

import argparse
import ast
import csv
import json
import math
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np  # before pycolmap (see common notes: the other order aborts at the first numba compile)

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import slamkit  # noqa: E402,F401  (before pycolmap)
import pycolmap  # noqa: E402

from slamkit.eval.align import estimate_alignment  # noqa: E402
from slamkit.io.trajectory import read_tum  # noqa: E402

CHI2 = 5.991
"""ORB-SLAM's bound (2 degrees of freedom, 95 %), times the keypoint's scale squared."""
LEVEL = 1.2
"""ORB's scale factor between octaves."""
REL_DEPTH_EDGES = (0.0, 0.5, 0.8, 1.25, 2.0, 4.0, math.inf)
"""Bins of z / median z for the chi2 log."""
CHI2_CONTEXTS = ("local_pass", "local_maintain", "global")


# ============================================================================================== recording
@dataclass
class Chi2Log:
    """Counts of :func:`remove_outlier_observations` calls, filled by :func:`install_chi2_hook`."""

    tested: dict = field(default_factory=lambda: defaultdict(int))
    """(context, octave, relative-depth bin) -> observations tested"""
    removed: list = field(default_factory=list)
    """(context, image id, point2D idx, point3D id, octave, z / median z, error px, bound px, point deleted)"""

    def write(self, out: Path) -> None:
        with open(out / "chi2_tested.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["context", "octave", "rel_depth_bin", "tested"])
            for (ctx, octv, b), n in sorted(self.tested.items()):
                w.writerow([ctx, octv, b, n])
        with open(out / "chi2_removed.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["context", "image_id", "point2D_idx", "point3D_id", "octave", "rel_depth", "error_px",
                        "bound_px", "point_deleted"])
            for r in self.removed:
                w.writerow([r[0], r[1], r[2], r[3], r[4], f"{r[5]:.4g}", f"{r[6]:.4g}", f"{r[7]:.4g}", int(r[8])])


def _octaves(scales: np.ndarray) -> np.ndarray:
    return np.rint(np.log(np.maximum(scales, 1e-9)) / math.log(LEVEL)).astype(np.int64)


def _rel_bin(r: np.ndarray) -> np.ndarray:
    return np.clip(np.searchsorted(REL_DEPTH_EDGES, r, side="right") - 1, 0, len(REL_DEPTH_EDGES) - 2)


def _context() -> str:
    """Which BA called the outlier test: the caller chain's function names."""
    names = []
    f = sys._getframe(2)
    while f is not None and len(names) < 4:
        names.append(f.f_code.co_name)
        f = f.f_back
    if names and names[0] == "adjust_local":
        return "local_pass"
    if "adjust_local" in names:
        return "local_maintain"
    return "global"


def install_chi2_hook(log: Chi2Log):
    """Wrap ``slamkit.stages.ba.remove_outlier_observations`` (module global, looked up at each call) so that
    each call also counts what it tests and removes into ``log``; the wrapped function's effect and return
    value are unchanged. Returns a function that undoes the wrap."""
    import slamkit.stages.ba as ba_mod
    from slamkit.map import keypoint_scales

    original = ba_mod.remove_outlier_observations

    def wrapped(slam_map, image_ids, chi2, scaled=True, removed=None):
        ctx = _context()
        ids_sorted = [i for i in sorted(int(i) for i in image_ids) if i in slam_map.keyframes]
        K = slam_map.pycolmap_camera.calibration_matrix()
        info = {}
        for image_id in ids_sorted:  # the same test as the wrapped function, on the state before it
            ids = slam_map.point3D_ids(image_id)
            idx = np.flatnonzero(ids >= 0)
            if not len(idx):
                continue
            kf = slam_map.keyframes[image_id]
            T = slam_map.cam_from_world(image_id).matrix()
            X = slam_map.points_xyz(ids[idx]) @ T[:, :3].T + T[:, 3]
            z = X[:, 2]
            uv = (X @ K.T)[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None]
            err = np.sqrt(((uv - kf.keypoints[idx]) ** 2).sum(axis=1))
            sc = keypoint_scales(kf.features)[idx]
            octv = _octaves(sc)
            zpos = z[z > 0]
            rel = z / (float(np.median(zpos)) if len(zpos) else 1.0)
            rb = _rel_bin(rel)
            for o, b in zip(octv.tolist(), rb.tolist()):
                log.tested[(ctx, o, b)] += 1
            bound = np.sqrt(chi2 * (sc ** 2 if scaled else np.ones_like(sc)))
            info[image_id] = {int(p): (int(o), float(r), float(e), float(bd))
                              for p, o, r, e, bd in zip(idx, octv, rel, err, bound)}
        mine = [] if removed is None else removed
        start = len(mine)
        n = original(slam_map, image_ids, chi2, scaled=scaled, removed=mine)
        rec = slam_map.reconstruction
        for image_id, p2, pid in mine[start:]:
            o, r, e, bd = info.get(int(image_id), {}).get(int(p2), (-1, float("nan"), float("nan"), float("nan")))
            log.removed.append((ctx, int(image_id), int(p2), int(pid), o, r, e, bd, not rec.exists_point3D(pid)))
        return n

    ba_mod.remove_outlier_observations = wrapped

    def undo():
        ba_mod.remove_outlier_observations = original

    return undo


def install_provenance_hook(origin: dict):
    """Wrap ``SlamMap.add_observations`` and ``SlamMap.add_point`` (on the class, this process only) so that
    ``origin[(image id, point2D idx)]`` names the step that last gave the observation a 3-D point: "tracked"
    (the new keyframe's 2D-3D inliers from tracking, added by either mapper's ``step``), "fused" (local
    mapping's fusion), "created" (local mapping's new points, both observations), or the caller's name.
    Observations never named here came from COLMAP's triangulator (its new points, track completion and
    merging; both mappers complete and merge after each BA). Returns a function that undoes the wrap."""
    from slamkit.map import SlamMap

    add_obs, add_pt = SlamMap.add_observations, SlamMap.add_point

    def _caller() -> str:
        name = sys._getframe(2).f_code.co_name
        return {"step": "tracked", "_fuse_into": "fused"}.get(name, name)

    def add_observations(self, image_id, point2D_idxs, point3D_ids):
        tag = _caller()
        before = self.point3D_ids(image_id).copy() if len(point2D_idxs) else None
        n = add_obs(self, image_id, point2D_idxs, point3D_ids)
        if n:
            after = self.point3D_ids(image_id)
            for j in np.flatnonzero((before < 0) & (after >= 0)).tolist():
                origin[(int(image_id), int(j))] = tag
        return n

    def add_point(self, xyz, observations, color):
        name = sys._getframe(1).f_code.co_name
        tag = "created" if name in ("<listcomp>", "step") else name
        pid = add_pt(self, xyz, observations, color)
        for image_id, j in observations:
            origin[(int(image_id), int(j))] = tag
        return pid

    SlamMap.add_observations, SlamMap.add_point = add_observations, add_point

    def undo():
        SlamMap.add_observations, SlamMap.add_point = add_obs, add_pt

    return undo


STEP_COLUMNS = ["frame_index", "timestamp", "status", "segment", "is_keyframe", "matches", "inliers",
                "reference_keyframe", "num_keyframes", "num_points", "ba", "new_points", "created", "culled",
                "fused", "observations_added"]


def _literal(text: str):
    key, sep, value = text.partition("=")
    if not sep:
        raise SystemExit(f"--set {text!r}: expected KEY=VALUE")
    try:
        return key.strip(), ast.literal_eval(value)
    except (ValueError, SyntaxError):
        return key.strip(), value


def record_run(source_spec: str, out: Path, mapper: str = "local", seed: int = 0, max_frames: int | None = None,
               overrides: dict | None = None, log=print) -> Path:
    """Run slamkit on ``source_spec`` with the outlier test counted and every step's result kept; save the run
    to ``out`` (``Slam.save``) with ``steps.csv``, ``chi2_tested.csv`` and
    ``chi2_removed.csv`` beside it. Returns ``out``."""
    from slamkit import Slam, SlamConfig, open_source

    pycolmap.logging.minloglevel = 2
    config = SlamConfig().with_overrides(seed=seed, **{"mapper.method": mapper}, **(overrides or {}))
    source = open_source(source_spec, max_frames=max_frames)
    chi2, origin = Chi2Log(), {}
    undo_chi2, undo_origin = install_chi2_hook(chi2), install_provenance_hook(origin)
    rows = []
    try:
        slam = Slam(source, config)
        while not slam.done:
            r = slam.step()
            m = r.mapping
            rows.append([r.frame_index, f"{r.timestamp:.6f}", str(r.status), r.segment, int(r.is_keyframe), r.matches,
                         r.inliers, r.reference_keyframe, r.num_keyframes, r.num_points, r.ba,
                         getattr(m, "new_points", ""), getattr(m, "created", ""), getattr(m, "culled", ""),
                         getattr(m, "fused", ""), getattr(m, "observations_added", "")])
            if len(rows) % 100 == 0:
                log(f"  {source_spec} [{mapper}]: frame {r.frame_index}, {r.num_keyframes} keyframes", flush=True)
        slam.finish()
    finally:
        undo_chi2()
        undo_origin()
    slam.save(out)
    with open(out / "steps.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(STEP_COLUMNS)
        w.writerows(rows)
    chi2.write(out)
    with open(out / "provenance.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["image_id", "point2D_idx", "origin"])
        w.writerows([i, j, o] for (i, j), o in sorted(origin.items()))
    (out / "diagnose_run.json").write_text(json.dumps({"source": source_spec, "mapper": mapper, "seed": seed,
                                                        "max_frames": max_frames, "set": overrides or {}}))
    return out


# ============================================================================================== analysis
@dataclass
class RunData:
    """A finished run read back: trajectories, ground truth, the main map and keypoint scales."""

    path: Path
    rec: pycolmap.Reconstruction
    frames: list[dict]
    summary: dict
    traj_t: np.ndarray
    traj_T: np.ndarray
    """(N, 4, 4) camera-to-world of the main segment's posed frames"""
    kf_t: np.ndarray
    gt_t: np.ndarray
    gt_T: np.ndarray
    image_frame: dict
    """image id -> frame index"""
    image_time: dict
    """image id -> timestamp"""
    scales: dict
    """image id -> (num points2D,) keypoint scale (1.2^octave), or missing"""
    steps: list[dict] | None = None


def _nearest(t_query: np.ndarray, t_ref: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """Index into sorted ``t_ref`` of each query time within ``tol`` seconds, -1 elsewhere."""
    order = np.argsort(t_ref)
    tr = t_ref[order]
    j = np.clip(np.searchsorted(tr, t_query), 1, max(len(tr) - 1, 1))
    left, right = tr[j - 1], tr[np.minimum(j, len(tr) - 1)]
    pick = np.where(np.abs(t_query - left) <= np.abs(t_query - right), j - 1, j)
    pick = np.minimum(pick, len(tr) - 1)
    ok = np.abs(tr[pick] - t_query) <= tol
    return np.where(ok, order[pick], -1)


def _keypoint_scales(path: Path, segment: int) -> dict:
    """image id -> keypoint scales from the run's session (``session/segment_XX/arrays.npz``)."""
    sess = path / "session"
    try:
        meta = json.loads((sess / "session.json").read_text())
    except (OSError, ValueError):
        return {}
    segs = [s for s in meta.get("segments", []) if int(s["id"]) == int(segment)]
    if not segs:
        return {}
    arrays = np.load(sess / f"segment_{int(segment):02d}" / "arrays.npz", allow_pickle=False)
    if "kf_sizes__shape" not in arrays.files:
        return {}
    shapes, data = arrays["kf_sizes__shape"], arrays["kf_sizes__data"]
    out, at = {}, 0
    for kmeta, shape in zip(segs[0]["keyframes"], shapes):
        if shape[0] < 0:
            continue
        n = int(np.prod(shape))
        s = np.asarray(data[at:at + n], np.float64)
        at += n
        pos = s[s > 0]
        out[int(kmeta["image_id"])] = s / max(float(pos.min()) if len(pos) else 1.0, 1e-9) if len(s) else s
    return out


def load_run(path: str | Path, gt_file: str | Path | None = None) -> RunData:
    """Read a finished run folder (``Slam.save``'s layout)."""
    path = Path(path)
    if not (path / "sparse").is_dir():
        raise SystemExit(f"{path}: no sparse/ (not a finished slamkit run folder)")
    summary = json.loads((path / "summary.json").read_text())
    with open(path / "frames.csv", newline="") as f:
        frames = list(csv.DictReader(f))
    traj = read_tum(path / "trajectory_tum.txt")
    kf = read_tum(path / "keyframes_tum.txt")
    gt_path = Path(gt_file) if gt_file else path / "groundtruth_tum.txt"
    if not gt_path.is_file():
        raise SystemExit(f"{path}: no ground truth (groundtruth_tum.txt missing; give --gt FILE)")
    gt = read_tum(gt_path)
    ok = np.isfinite(gt.poses).all(axis=(1, 2))
    main = int(summary.get("main_segment", 0))
    image_frame, image_time = {}, {}
    for r in frames:
        iid = int(r["keyframe_image_id"])
        if iid >= 0 and int(r["segment"]) == main:
            image_frame[iid] = int(r["index"])
            image_time[iid] = float(r["timestamp"])
    rec = pycolmap.Reconstruction(str(path / "sparse"))
    steps = None
    if (path / "steps.csv").is_file():
        with open(path / "steps.csv", newline="") as f:
            steps = list(csv.DictReader(f))
    return RunData(path, rec, frames, summary, traj.timestamps, traj.poses, kf.timestamps, gt.timestamps[ok],
                   gt.poses[ok], image_frame, image_time, _keypoint_scales(path, main), steps)


def _align(est: np.ndarray, gt: np.ndarray):
    a = estimate_alignment(est, gt, "sim3")
    return a, (a.scale * est @ np.asarray(a.rotation).T + a.translation) - gt


def _rms(x: np.ndarray) -> float:
    x = np.asarray(x, np.float64)
    return float(np.sqrt((x ** 2).mean())) if len(x) else float("nan")


def trajectory_stats(d: RunData) -> dict:
    """ATE over all frames / keyframes, errors of keyframes and the frames between them (see module doc)."""
    j = _nearest(d.traj_t, d.gt_t)
    m = j >= 0
    t, est, gt = d.traj_t[m], d.traj_T[m][:, :3, 3], d.gt_T[j[m]][:, :3, 3]
    a, err = _align(est, gt)
    e = np.linalg.norm(err, axis=1)
    is_kf = _nearest(t, d.kf_t) >= 0
    inner = (t >= t[is_kf].min()) & (t <= t[is_kf].max()) if is_kf.any() else np.zeros(len(t), bool)
    out = {"posed": int(len(d.traj_t)), "ate_all": _rms(e), "ate_all_on_kf": _rms(e[is_kf]),
           "ate_all_on_nonkf": _rms(e[~is_kf]), "ate_all_on_inner_nonkf": _rms(e[~is_kf & inner]),
           "outer_frames": int((~inner).sum())}
    jk = _nearest(d.kf_t, d.gt_t)
    kest = d.traj_T[_nearest(d.kf_t, d.traj_t)]
    mk = (jk >= 0)
    out["ate_kf"] = _rms(np.linalg.norm(_align(kest[mk][:, :3, 3], d.gt_T[jk[mk]][:, :3, 3])[1], axis=1))
    # displacement since the keyframe before (in the all-frames alignment)
    R, s = np.asarray(a.rotation), float(a.scale)
    rel_nonkf, rel_kf, last = [], [], None
    for k in range(len(t)):
        if last is not None:
            d_est = s * R @ (est[k] - est[last])
            d_gt = gt[k] - gt[last]
            (rel_kf if is_kf[k] else rel_nonkf).append(np.linalg.norm(d_est - d_gt))
        if is_kf[k]:
            last = k
    out["rel_nonkf"], out["rel_kf"] = _rms(np.asarray(rel_nonkf)), _rms(np.asarray(rel_kf))
    return out


@dataclass
class Observations:
    """Every observation of the map as flat arrays."""

    image_id: np.ndarray
    point_id: np.ndarray
    err: np.ndarray
    """reprojection error (px) in the final map"""
    depth: np.ndarray
    """camera z (map units)"""
    scale: np.ndarray
    """keypoint scale (1.2^octave; NaN when unknown)"""
    gt_err: np.ndarray
    """reprojection error (px) at the true poses, the point triangulated (DLT) from them; NaN without truth"""
    track_len: np.ndarray
    """track length of the observation's point"""
    point2D_idx: np.ndarray
    """keypoint index of the observation in its keyframe"""


def gt_cam_from_world(d: RunData) -> dict:
    """image id -> (4, 4) true cam_from_world of the map's keyframes that have ground truth."""
    out = {}
    ids = [i for i in d.rec.reg_image_ids() if i in d.image_time]
    if not ids:
        return out
    j = _nearest(np.array([d.image_time[i] for i in ids]), d.gt_t)
    for i, k in zip(ids, j):
        if k >= 0:
            out[int(i)] = np.linalg.inv(d.gt_T[k])
    return out


def observations(d: RunData, gt_cfw: dict) -> Observations:
    rec = d.rec
    cam = rec.camera(next(iter(rec.cameras)))
    image_ids, point_ids, xy, pidx = [], [], [], []
    for iid in rec.reg_image_ids():
        img = rec.image(iid)
        for k, p in enumerate(img.points2D):
            if p.has_point3D():
                image_ids.append(iid)
                point_ids.append(p.point3D_id)
                xy.append(p.xy)
                pidx.append(k)
    image_ids, point_ids = np.asarray(image_ids, np.int64), np.asarray(point_ids, np.int64)
    xy, pidx = np.asarray(xy, np.float64).reshape(-1, 2), np.asarray(pidx, np.int64)
    n = len(image_ids)
    err, depth, scale = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    uniq_pids = np.unique(point_ids)
    xyz = np.array([rec.point3D(int(p)).xyz for p in uniq_pids]).reshape(-1, 3)
    P = xyz[np.searchsorted(uniq_pids, point_ids)]
    for iid in np.unique(image_ids):
        sel = image_ids == iid
        T = rec.image(int(iid)).cam_from_world().matrix()
        X = P[sel] @ T[:, :3].T + T[:, 3]
        depth[sel] = X[:, 2]
        uv = np.asarray(cam.img_from_cam(X))
        err[sel] = np.linalg.norm(uv[:, :2] - xy[sel], axis=1)
        sc = d.scales.get(int(iid))
        if sc is not None and len(sc) > pidx[sel].max():
            scale[sel] = sc[pidx[sel]]
    counts = np.bincount(np.searchsorted(uniq_pids, point_ids), minlength=len(uniq_pids))
    track_len = counts[np.searchsorted(uniq_pids, point_ids)]
    gt_err = _gt_reprojection(image_ids, point_ids, xy, uniq_pids, counts, gt_cfw, cam)
    return Observations(image_ids, point_ids, err, depth, scale, gt_err, track_len, pidx)


def _gt_reprojection(image_ids, point_ids, xy, uniq_pids, counts, gt_cfw: dict, cam) -> np.ndarray:
    """Reprojection error of each observation at the true poses, its point triangulated by DLT from every
    observation of it in a keyframe with truth (points with fewer than two such observations: NaN). The
    keypoints are taken as undistorted pixels of the map camera (PINHOLE; a SIMPLE_RADIAL map camera's
    distortion is applied by ``cam.img_from_cam``)."""
    n = len(image_ids)
    out = np.full(n, np.nan)
    if not gt_cfw:
        return out
    K = np.asarray(cam.calibration_matrix())
    has = np.array([int(i) in gt_cfw for i in image_ids], bool)
    Pm = {i: K @ T[:3] for i, T in gt_cfw.items()}
    order = np.lexsort((image_ids, point_ids))
    pid_sorted = point_ids[order]
    starts = np.r_[0, np.flatnonzero(np.diff(pid_sorted)) + 1]
    ends = np.r_[starts[1:], len(order)]
    # group points by the number of usable observations to solve many DLTs at once
    groups = defaultdict(list)
    for s, e in zip(starts, ends):
        rows = order[s:e]
        rows = rows[has[rows]]
        if len(rows) >= 2:
            groups[len(rows)].append(rows)
    for L, members in groups.items():
        rows = np.asarray(members)  # (m, L)
        Ps = np.array([[Pm[int(image_ids[r])] for r in rr] for rr in rows])  # (m, L, 3, 4)
        x = xy[rows]  # (m, L, 2)
        A = np.concatenate([x[..., 0:1] * Ps[..., 2, :] - Ps[..., 0, :],
                            x[..., 1:2] * Ps[..., 2, :] - Ps[..., 1, :]], axis=1)  # (m, 2L, 4)
        X = np.linalg.svd(A)[2][:, -1, :]  # (m, 4)
        X = X[:, :3] / np.where(np.abs(X[:, 3:]) > 1e-12, X[:, 3:], 1e-12)
        for col in range(L):
            r = rows[:, col]
            T = np.array([gt_cfw[int(image_ids[k])] for k in r])
            Xc = np.einsum("mij,mj->mi", T[:, :3, :3], X) + T[:, :3, 3]
            uv = np.asarray(cam.img_from_cam(Xc))[:, :2]
            e = np.linalg.norm(uv - xy[r], axis=1)
            out[r] = np.where(Xc[:, 2] > 0, e, np.nan)
    return out


def _pct(x: np.ndarray, q: float) -> float:
    return float(np.percentile(x, q)) if len(x) else float("nan")


def map_stats(d: RunData, obs: Observations) -> dict:
    rec = d.rec
    kfs = sorted(rec.reg_image_ids())
    frames = sorted(d.image_frame[i] for i in kfs if i in d.image_frame)
    gaps = np.diff(frames) if len(frames) > 1 else np.array([np.nan])
    _, tl = np.unique(obs.point_id, return_counts=True)
    per_kf = np.bincount(np.searchsorted(np.asarray(kfs), obs.image_id), minlength=len(kfs))
    bound = np.sqrt(CHI2) * np.where(np.isfinite(obs.scale), obs.scale, 1.0)
    g = np.isfinite(obs.gt_err)
    return {"frames": int(d.summary.get("frames", len(d.frames))), "keyframes": len(kfs),
            "culled": d.summary.get("keyframes_culled", ""),
            "kf_gap_mean": float(np.mean(gaps)), "kf_gap_median": float(np.median(gaps)),
            "kf_gap_max": float(np.max(gaps)),
            "points": int(len(tl)), "obs": int(len(obs.point_id)),
            "track_mean": float(tl.mean()), "track_median": float(np.median(tl)), "track_p10": _pct(tl, 10),
            "track_p25": _pct(tl, 25), "track_p75": _pct(tl, 75), "track_p90": _pct(tl, 90),
            "track2_pct": 100.0 * float((tl == 2).mean()), "track5_pct": 100.0 * float((tl >= 5).mean()),
            "pts_per_kf": float(per_kf.mean()), "obs_per_kf": float(per_kf.mean()),
            "reproj_rms": _rms(obs.err), "reproj_median": float(np.median(obs.err)),
            "gt_reproj_median": float(np.median(obs.gt_err[g])) if g.any() else float("nan"),
            "gt_reproj_p90": _pct(obs.gt_err[g], 90),
            "gt_bad_pct": 100.0 * float((obs.gt_err[g] > bound[g]).mean()) if g.any() else float("nan")}


def ba_stats(d: RunData, gt_cfw: dict) -> dict:
    """The run's keyframe ATE and that of the optimum of its observations started from the truth."""
    from ba_from_truth import ba_from_truth, keyframe_ate

    rec = d.rec
    gt = {i: T for i, T in gt_cfw.items() if rec.exists_image(i)}
    if len(gt) < 3:
        return {}
    cam = rec.camera(next(iter(rec.cameras)))
    K = np.asarray(cam.calibration_matrix())
    model = str(cam.model).split(".")[-1]
    own = keyframe_ate(rec, gt)
    opt, _ = ba_from_truth(rec, gt, K, model, list(np.asarray(cam.params)))
    return {"ba_kf_ate": own, "ba_opt_ate": opt, "ba_gap": own - opt}


def step_stats(d: RunData) -> dict:
    if not d.steps:
        return {}
    inl = np.array([int(r["inliers"]) for r in d.steps if "TRACKED" in r["status"].upper() and int(r["inliers"]) > 0])
    out = {"inliers_mean": float(inl.mean()) if len(inl) else float("nan"),
           "inliers_median": float(np.median(inl)) if len(inl) else float("nan")}
    for col, key in (("created", "created"), ("culled", "culled_pts"), ("fused", "fused"),
                     ("observations_added", "fused_obs")):
        v = [int(r[col]) for r in d.steps if r[col] not in ("", None)]
        out[key] = int(sum(v)) if v else ""
    return out


def chi2_table(d: RunData) -> tuple[dict, list[dict]]:
    """Summary counts and per (context, octave) / (context, relative-depth bin) rows of the chi2 log."""
    tp, rp = d.path / "chi2_tested.csv", d.path / "chi2_removed.csv"
    if not tp.is_file():
        return {}, []
    with open(tp, newline="") as f:
        tested = [(r["context"], int(r["octave"]), int(r["rel_depth_bin"]), int(r["tested"]))
                  for r in csv.DictReader(f)]
    with open(rp, newline="") as f:
        removed = list(csv.DictReader(f))
    rows = []
    for by in ("octave", "rel_depth_bin"):
        keys = sorted({(c, o if by == "octave" else b) for c, o, b, _ in tested})
        for ctx, k in keys:
            n = sum(t for c, o, b, t in tested if c == ctx and (o if by == "octave" else b) == k)
            if by == "octave":
                rem = [r for r in removed if r["context"] == ctx and int(r["octave"]) == k]
                label = str(k)
            else:
                rel = np.array([float(r["rel_depth"]) for r in removed if r["context"] == ctx], np.float64)
                mask = _rel_bin(np.nan_to_num(rel, nan=1.0)) == k
                rem = [r for r, m in zip([r for r in removed if r["context"] == ctx], mask) if m]
                lo, hi = REL_DEPTH_EDGES[k], REL_DEPTH_EDGES[k + 1]
                label = f"{lo:g}-{hi:g}"
            rows.append({"run": d.path.name, "by": by, "context": ctx, "bin": label, "tested": n, "removed": len(rem),
                         "removed_pct": 100.0 * len(rem) / n if n else float("nan"),
                         "point_deleted": sum(int(r["point_deleted"]) for r in rem)})
    n_t, n_r = sum(t for *_, t in tested), len(removed)
    pct = 100.0 * n_r / n_t if n_t else float("nan")
    return {"chi2_tested": n_t, "chi2_removed": n_r, "chi2_removed_pct": pct}, rows


def octave_rows(name: str, obs: Observations) -> list[dict]:
    rows = []
    known = np.isfinite(obs.scale)
    if not known.any():
        return rows
    octv = _octaves(np.where(known, obs.scale, 1.0))
    bound = np.sqrt(CHI2) * np.where(known, obs.scale, 1.0)
    for o in np.unique(octv[known]):
        m = known & (octv == o)
        g = m & np.isfinite(obs.gt_err)
        pts = np.unique(obs.point_id[m])
        rows.append({"run": name, "octave": int(o), "obs": int(m.sum()), "obs_pct": 100.0 * m.sum() / len(octv),
                     "points": int(len(pts)), "reproj_rms": _rms(obs.err[m]),
                     "reproj_median": float(np.median(obs.err[m])),
                     "norm_median": float(np.median(obs.err[m] / obs.scale[m])),
                     "gt_reproj_median": float(np.median(obs.gt_err[g])) if g.any() else float("nan"),
                     "gt_bad_pct": 100.0 * float((obs.gt_err[g] > bound[g]).mean()) if g.any() else float("nan"),
                     "track_mean": float(obs.track_len[m].mean())})
    return rows


def depth_rows(name: str, obs: Observations, metric_scale: float, edges: np.ndarray) -> list[dict]:
    rows = []
    z = obs.depth * metric_scale
    bound = np.sqrt(CHI2) * np.where(np.isfinite(obs.scale), obs.scale, 1.0)
    b = np.clip(np.searchsorted(edges, z, side="right") - 1, 0, len(edges) - 2)
    for k in range(len(edges) - 1):
        m = b == k
        if not m.any():
            continue
        g = m & np.isfinite(obs.gt_err)
        rows.append({"run": name, "depth_m": f"{edges[k]:.3g}-{edges[k + 1]:.3g}", "obs": int(m.sum()),
                     "obs_pct": 100.0 * m.sum() / len(z), "reproj_rms": _rms(obs.err[m]),
                     "reproj_median": float(np.median(obs.err[m])),
                     "gt_reproj_median": float(np.median(obs.gt_err[g])) if g.any() else float("nan"),
                     "gt_bad_pct": 100.0 * float((obs.gt_err[g] > bound[g]).mean()) if g.any() else float("nan"),
                     "track_mean": float(obs.track_len[m].mean())})
    return rows


TRACK_BINS = ((2, 2), (3, 3), (4, 5), (6, 8), (9, 12), (13, 10 ** 9))
"""Track-length bins (inclusive) of the track table."""


def track_rows(name: str, obs: Observations) -> list[dict]:
    """Residuals by the track length of the observation's point: a point adjusted from L observations keeps
    2L - 3 of their 2L residual dimensions, so a map of shorter tracks shows smaller residuals for the same
    keypoint noise; compare maps within a bin."""
    rows = []
    bound = np.sqrt(CHI2) * np.where(np.isfinite(obs.scale), obs.scale, 1.0)
    norm = obs.err / np.where(np.isfinite(obs.scale), obs.scale, 1.0)
    for lo, hi in TRACK_BINS:
        m = (obs.track_len >= lo) & (obs.track_len <= hi)
        if not m.any():
            continue
        g = m & np.isfinite(obs.gt_err)
        rows.append({"run": name, "track": f"{lo}" if lo == hi else (f"{lo}-{hi}" if hi < 10 ** 9 else f">={lo}"),
                     "obs": int(m.sum()), "obs_pct": 100.0 * m.sum() / len(m),
                     "points": int(len(np.unique(obs.point_id[m]))), "reproj_median": float(np.median(obs.err[m])),
                     "norm_median": float(np.median(norm[m])),
                     "gt_reproj_median": float(np.median(obs.gt_err[g])) if g.any() else float("nan"),
                     "gt_bad_pct": 100.0 * float((obs.gt_err[g] > bound[g]).mean()) if g.any() else float("nan")})
    return rows


def origin_rows(d: RunData, obs: Observations) -> list[dict]:
    """Residuals by the step that made each observation (``provenance.csv`` of ``run``; see
    :func:`install_provenance_hook`); "triangulator": never named by the hook (COLMAP's triangulation, track
    completion and merging). reproj_median_4_8 / gt_bad_pct_4_8: the same over points of 4-8 observations
    only (the track-length mix differs between origins)."""
    path = d.path / "provenance.csv"
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        origin = {(int(r["image_id"]), int(r["point2D_idx"])): r["origin"] for r in csv.DictReader(f)}
    tags = np.array([origin.get((int(i), int(j)), "triangulator") for i, j in zip(obs.image_id, obs.point2D_idx)])
    bound = np.sqrt(CHI2) * np.where(np.isfinite(obs.scale), obs.scale, 1.0)
    mid = (obs.track_len >= 4) & (obs.track_len <= 8)
    rows = []
    for tag in sorted(set(tags.tolist())):
        m = tags == tag
        g, gm = m & np.isfinite(obs.gt_err), m & mid & np.isfinite(obs.gt_err)
        rows.append({"run": d.path.name, "origin": tag, "obs": int(m.sum()), "obs_pct": 100.0 * m.sum() / len(m),
                     "reproj_median": float(np.median(obs.err[m])),
                     "gt_reproj_median": float(np.median(obs.gt_err[g])) if g.any() else float("nan"),
                     "gt_bad_pct": 100.0 * float((obs.gt_err[g] > bound[g]).mean()) if g.any() else float("nan"),
                     "track_mean": float(obs.track_len[m].mean()),
                     "reproj_median_4_8": float(np.median(obs.err[m & mid])) if (m & mid).any() else float("nan"),
                     "gt_bad_pct_4_8": (100.0 * float((obs.gt_err[gm] > bound[gm]).mean()) if gm.any()
                                        else float("nan"))})
    return rows


def keyframe_scale(d: RunData) -> float:
    """The scale of the Sim(3) fitted to the map's keyframe centres (map units -> metres)."""
    gt = gt_cam_from_world(d)
    ids = sorted(i for i in gt if d.rec.exists_image(i))
    est = np.array([d.rec.image(i).cam_from_world().inverse().translation for i in ids])
    ref = np.array([np.linalg.inv(gt[i])[:3, 3] for i in ids])
    return float(estimate_alignment(est, ref, "sim3").scale)


def analyze(paths: list, gt_file=None, with_ba: bool = True, depth_edges=None, log=print) -> dict:
    """Every table for the run folders ``paths``: {"summary": [...], "octave": [...], "depth": [...],
    "chi2": [...]} (lists of row dicts)."""
    out = {"summary": [], "octave": [], "depth": [], "track": [], "origin": [], "chi2": []}
    edges = None if depth_edges is None else np.asarray(depth_edges, np.float64)
    for p in paths:
        d = load_run(p, gt_file)
        name = d.path.name
        gt_cfw = gt_cam_from_world(d)
        obs = observations(d, gt_cfw)
        s = keyframe_scale(d)
        if edges is None:
            z = obs.depth * s
            edges = np.percentile(z[np.isfinite(z) & (z > 0)], [0, 20, 40, 60, 80, 100])
            edges[0], edges[-1] = 0.0, math.inf
        row = {"run": name}
        row |= trajectory_stats(d)
        row |= map_stats(d, obs)
        if with_ba:
            row |= ba_stats(d, gt_cfw)
        row |= step_stats(d)
        c, crows = chi2_table(d)
        row |= c
        out["summary"].append(row)
        out["octave"] += octave_rows(name, obs)
        out["depth"] += depth_rows(name, obs, s, edges)
        out["track"] += track_rows(name, obs)
        out["origin"] += origin_rows(d, obs)
        out["chi2"] += crows
        log(f"  analysed {p}", flush=True)
    return out


SUMMARY_COLUMNS = ["run", "frames", "posed", "ate_all", "ate_kf", "ate_all_on_kf", "ate_all_on_nonkf",
                   "ate_all_on_inner_nonkf", "outer_frames", "rel_nonkf", "rel_kf", "keyframes", "culled",
                   "kf_gap_mean", "kf_gap_median", "kf_gap_max",
                   "points", "obs", "track_mean", "track_median", "track_p10", "track_p25", "track_p75",
                   "track_p90", "track2_pct", "track5_pct", "pts_per_kf", "obs_per_kf", "reproj_rms",
                   "reproj_median", "gt_reproj_median", "gt_reproj_p90", "gt_bad_pct", "ba_kf_ate", "ba_opt_ate",
                   "ba_gap", "inliers_mean", "inliers_median", "created", "culled_pts", "fused", "fused_obs",
                   "chi2_tested", "chi2_removed", "chi2_removed_pct"]


GROUP_COLUMNS = ["ate_all", "ate_kf", "ate_all_on_kf", "ate_all_on_nonkf", "ate_all_on_inner_nonkf", "rel_nonkf",
                 "rel_kf", "keyframes", "culled", "kf_gap_mean", "points", "obs", "track_mean", "track_median",
                 "track2_pct", "track5_pct", "pts_per_kf", "reproj_median", "gt_reproj_median", "gt_bad_pct",
                 "ba_kf_ate", "ba_opt_ate", "ba_gap", "inliers_mean", "fused_obs", "chi2_removed_pct"]


def group_seeds(rows: list[dict]) -> list[dict]:
    """Summary rows of runs named ``NAME_sSEED`` grouped by NAME: mean ± SE of :data:`GROUP_COLUMNS`."""
    import re

    groups: dict[str, list[dict]] = {}
    for r in rows:
        m = re.match(r"^(.*)_s(\d+)$", str(r["run"]))
        groups.setdefault(m.group(1) if m else str(r["run"]), []).append(r)
    out = []
    for name, rs in groups.items():
        g = {"run": f"{name} (n={len(rs)})"}
        for c in GROUP_COLUMNS:
            v = np.array([float(r[c]) for r in rs if isinstance(r.get(c), (int, float))], np.float64)
            v = v[np.isfinite(v)]
            if not len(v):
                continue
            se = float(v.std(ddof=1) / math.sqrt(len(v))) if len(v) > 1 else float("nan")
            g[c] = f"{v.mean():.4g}" + ("" if math.isnan(se) else f" ± {se:.2g}")
        out.append(g)
    return out


def _fmt(v) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "-"
        return f"{v:.4g}"
    return str(v)


def markdown(rows: list[dict], columns: list[str] | None = None, transpose: bool = False) -> str:
    if not rows:
        return "(none)\n"
    cols = columns or list(rows[0])
    cols = [c for c in cols if any(c in r for r in rows)]
    if transpose:  # one column per run: the summary has many columns and few runs
        lines = ["| | " + " | ".join(str(r["run"]) for r in rows) + " |", "|---" * (len(rows) + 1) + "|"]
        for c in cols[1:]:
            lines.append(f"| {c} | " + " | ".join(_fmt(r.get(c, "")) for r in rows) + " |")
        return "\n".join(lines) + "\n"
    lines = ["| " + " | ".join(cols) + " |", "|---" * len(cols) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(c, "")) for c in cols) + " |")
    return "\n".join(lines) + "\n"


def write_csv(path: Path, rows: list[dict], columns: list[str] | None = None) -> None:
    cols = columns or (list(rows[0]) if rows else [])
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({c: r.get(c, "") for c in cols})


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="verb", required=True)
    r = sub.add_parser("run", help="one slamkit run with the outlier test counted and every step kept")
    r.add_argument("source", help="a path or synthetic spec (with ground truth, to be analysed)")
    r.add_argument("--out", required=True, help="run folder to write (new or empty)")
    r.add_argument("--mapper", choices=["local", "colmap"], default="local")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--max-frames", type=int, default=None)
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a SlamConfig field")
    a = sub.add_parser("analyze", help="tables of finished run folders against ground truth",
                       epilog=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("--runs", nargs="+", required=True, help="run folders (Slam.save / slamkit run --out)")
    a.add_argument("--gt", default=None, help="ground truth (TUM format) when a run has no groundtruth_tum.txt")
    a.add_argument("--csv", default=None,
                   help="prefix of the CSV files (PREFIX_summary.csv, _octave, _depth, _track, _origin, _chi2, _seeds)")
    a.add_argument("--no-ba", action="store_true", help="skip the BA from the truth (the slow part)")
    a.add_argument("--group", action="store_true", help="also a table of mean ± SE over runs named NAME_sSEED")
    a.add_argument("--depth-edges", default=None,
                   help="comma-separated metric depth bin edges (default: quintiles of the first run)")
    args = ap.parse_args(argv)
    if args.verb == "run":
        out = record_run(args.source, Path(args.out), args.mapper, args.seed, args.max_frames,
                         dict(_literal(s) for s in args.set))
        print(f"saved {out}")
        return
    edges = None if args.depth_edges is None else [float(v) for v in args.depth_edges.split(",")]
    t = analyze(args.runs, args.gt, not args.no_ba, edges)
    print("\n## Summary (one column per run)\n")
    print(markdown(t["summary"], SUMMARY_COLUMNS, transpose=True))
    if args.group:
        print("## Over seeds (mean ± SE)\n")
        print(markdown(group_seeds(t["summary"]), ["run"] + GROUP_COLUMNS, transpose=True))
    print("## Reprojection error by octave\n")
    print(markdown(t["octave"]))
    print("## Reprojection error by metric depth\n")
    print(markdown(t["depth"]))
    print("## Residuals by track length\n")
    print(markdown(t["track"]))
    if t["origin"]:
        print("## Residuals by the step that made the observation\n")
        print(markdown(t["origin"]))
    if t["chi2"]:
        print("## What the chi2 test removes\n")
        print(markdown(t["chi2"]))
    if args.csv:
        prefix = Path(args.csv)
        prefix.parent.mkdir(parents=True, exist_ok=True)
        write_csv(Path(f"{prefix}_summary.csv"), t["summary"], SUMMARY_COLUMNS)
        for k in ("octave", "depth", "track", "origin", "chi2"):
            write_csv(Path(f"{prefix}_{k}.csv"), t[k])
        if args.group:
            write_csv(Path(f"{prefix}_seeds.csv"), group_seeds(t["summary"]), ["run"] + GROUP_COLUMNS)
        print(f"CSV: {prefix}_summary.csv, _octave.csv, _depth.csv, _track.csv, _chi2.csv")


if __name__ == "__main__":
    main()
