"""benchmarks/diagnose_map_quality.py (issue 52): its numbers against what they claim to be, on exact geometry
and on a short rendered run (the map's own counts, slamkit's ATE, the truth), so the tool cannot rot silently."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

import slamkit  # noqa: F401  (before pycolmap)
import pycolmap  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import diagnose_map_quality as dmq  # noqa: E402
from ba_from_truth import keyframe_ate  # noqa: E402

from slamkit import Trajectory, ate  # noqa: E402
from slamkit.io.trajectory import read_tum  # noqa: E402

SPEC = "synthetic:default?frames=30&noise=1"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("diagnose") / "run"
    import slamkit.stages.ba as ba_mod
    from slamkit.map import SlamMap

    original = (ba_mod.remove_outlier_observations, SlamMap.add_observations, SlamMap.add_point)
    dmq.record_run(SPEC, out, "local", seed=0, log=lambda *a, **k: None)
    # the hooks are gone after the run
    assert (ba_mod.remove_outlier_observations, SlamMap.add_observations, SlamMap.add_point) == original
    return out


@pytest.fixture(scope="module")
def tables(run):
    return dmq.analyze([run], log=lambda *a, **k: None)


def test_map_counts_are_the_maps_own(run, tables):
    row = tables["summary"][0]
    rec = pycolmap.Reconstruction(str(run / "sparse"))
    tl = np.array([p.track.length() for p in rec.points3D.values()])
    summary = json.loads((run / "summary.json").read_text())
    assert row["points"] == rec.num_points3D() == len(tl) == summary["points3D"]
    assert row["obs"] == rec.compute_num_observations() == int(tl.sum())
    assert row["keyframes"] == rec.num_reg_images() == summary["keyframes"]
    assert row["track_mean"] == pytest.approx(tl.mean(), rel=1e-12)
    assert row["track_median"] == np.median(tl)
    assert row["track_p90"] == pytest.approx(np.percentile(tl, 90))
    assert row["track2_pct"] == pytest.approx(100 * (tl == 2).mean())
    per_image = [rec.image(i).num_points3D for i in rec.reg_image_ids()]
    assert row["pts_per_kf"] == pytest.approx(np.mean(per_image))
    assert row["culled"] == summary["keyframes_culled"]
    for table in ("octave", "depth", "track"):  # every observation in exactly one bin
        assert sum(r["obs"] for r in tables[table]) == row["obs"], table
    assert sum(r["points"] for r in tables["track"]) == row["points"]  # a point's track length is one bin
    origins = {r["origin"]: r for r in tables["origin"]}
    assert sum(r["obs"] for r in origins.values()) == row["obs"]
    assert {"tracked", "created"} <= set(origins)  # local mapping: tracking inliers and new points
    assert origins["created"]["gt_reproj_median"] < 1.0  # rendered frames: exact tracks, keypoint noise only
    frames = sorted(int(r["index"]) for r in dmq.load_run(run).frames if int(r["keyframe_image_id"]) >= 0)
    assert row["kf_gap_max"] == max(np.diff(frames))


def test_octaves_are_orb_levels_and_errors_the_maps(run):
    d = dmq.load_run(run)
    obs = dmq.observations(d, dmq.gt_cam_from_world(d))
    assert np.isfinite(obs.scale).all()  # every keyframe's keypoint sizes found in the session
    lv = np.log(obs.scale) / math.log(dmq.LEVEL)
    assert np.abs(lv - np.rint(lv)).max() < 1e-3 and lv.min() > -1e-9 and lv.max() < 8 + 1e-9  # ORB: 1.2^octave
    # one observation recomputed by hand from the model
    rec = d.rec
    k = len(obs.err) // 2
    img, cam = rec.image(int(obs.image_id[k])), rec.camera(next(iter(rec.cameras)))
    p2 = next(p for p in img.points2D if p.has_point3D() and p.point3D_id == obs.point_id[k])
    X = img.cam_from_world() * rec.point3D(int(obs.point_id[k])).xyz
    assert obs.err[k] == pytest.approx(np.linalg.norm(cam.img_from_cam(X)[:2] - p2.xy), abs=1e-9)
    assert obs.depth[k] == pytest.approx(X[2])
    # rendered frames, true poses: the tracks agree with the true geometry to about the keypoints' noise
    assert np.nanmedian(obs.gt_err) < 1.0


def test_keyframe_ate_is_small_and_the_same_as_slamkits(run, tables):
    row = tables["summary"][0]
    gt, traj = read_tum(run / "groundtruth_tum.txt"), read_tum(run / "trajectory_tum.txt")
    assert row["ate_all"] == pytest.approx(ate(gt, traj, align="sim3").rmse, rel=1e-6)
    kf = read_tum(run / "keyframes_tum.txt")
    assert row["ate_kf"] == pytest.approx(ate(gt, kf, align="sim3").rmse, rel=1e-6)
    d = dmq.load_run(run)
    assert row["ba_kf_ate"] == pytest.approx(keyframe_ate(d.rec, dmq.gt_cam_from_world(d)), rel=1e-9)
    assert row["ate_kf"] < 0.02 and row["ba_opt_ate"] < 0.02  # metres, a rendered room
    assert row["ate_all_on_kf"] <= row["ate_all"] * 2 and row["posed"] == 30


def test_the_chi2_log_holds_what_the_test_removed(run, tables):
    row = tables["summary"][0]
    assert row["chi2_tested"] > row["obs"]  # every local BA tests its window's observations
    rows = list(__import__("csv").DictReader(open(run / "chi2_removed.csv")))
    assert len(rows) == row["chi2_removed"]
    for r in rows:
        assert r["context"] in dmq.CHI2_CONTEXTS
        e, b = float(r["error_px"]), float(r["bound_px"])
        assert e > b or math.isnan(e), r  # removed for its error (or behind the camera)
    by_octave = [c for c in tables["chi2"] if c["by"] == "octave"]
    assert sum(c["removed"] for c in by_octave) == row["chi2_removed"]
    assert sum(c["tested"] for c in by_octave) == row["chi2_tested"]


def test_gt_reprojection_is_zero_on_exact_tracks_and_finds_a_wrong_match():
    rng = np.random.default_rng(0)
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500.0, 500.0, 320.0, 240.0])
    K = np.asarray(cam.calibration_matrix())
    poses = {}
    for i in range(1, 5):
        T = np.eye(4)
        T[:3, 3] = [-0.1 * i, 0.02 * i, 0.0]
        poses[i] = T
    pts = rng.uniform([-1, -1, 3], [1, 1, 6], (50, 3))
    image_ids, point_ids, xy = [], [], []
    for pid, X in enumerate(pts):
        for i in range(1, 2 + pid % 4):  # tracks of 1 to 4 observations
            x = K @ (poses[i][:3, :3] @ X + poses[i][:3, 3])
            image_ids.append(i)
            point_ids.append(pid)
            xy.append(x[:2] / x[2])
    image_ids, point_ids, xy = np.array(image_ids), np.array(point_ids), np.array(xy)
    uniq, counts = np.unique(point_ids, return_counts=True)
    err = dmq._gt_reprojection(image_ids, point_ids, xy, uniq, counts, poses, cam)
    assert np.isnan(err[counts[point_ids] < 2]).all()
    assert np.nanmax(err) < 1e-6
    bad = np.flatnonzero(counts[point_ids] == 4)[0]
    xy[bad] += [12.0, 0.0]  # one wrong observation in a 4-view track
    err = dmq._gt_reprojection(image_ids, point_ids, xy, uniq, counts, poses, cam)
    assert err[bad] > 3.0  # a DLT of 4 views shares the 12 px among them; the wrong one keeps the most
    others = point_ids != point_ids[bad]
    assert np.nanmax(err[others]) < 1e-6


def test_seeds_are_grouped_with_their_standard_error():
    rows = [{"run": f"a_s{k}", "ate_all": v} for k, v in enumerate((1.0, 2.0, 3.0))] + [{"run": "b_s0", "ate_all": 5.0}]
    g = {r["run"]: r for r in dmq.group_seeds(rows)}
    assert g["a (n=3)"]["ate_all"] == "2 ± 0.58" and g["b (n=1)"]["ate_all"] == "5"


def test_trajectory_errors_on_exact_trajectories():
    n = 40
    t = np.arange(n) / 10.0
    gt = np.repeat(np.eye(4)[None], n, axis=0)
    gt[:, 0, 3], gt[:, 2, 3] = np.linspace(0, 4, n), np.sin(t)
    a = 0.3
    R = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    est = gt.copy()
    est[:, :3, 3] = 0.5 * gt[:, :3, 3] @ R.T + [1, 2, 3]  # a Sim(3) of the truth
    kf = np.arange(0, n, 4)
    d = dmq.RunData(Path("x"), None, [], {}, t, est, t[kf], t, gt, {}, {}, {})
    s = dmq.trajectory_stats(d)
    for k in ("ate_all", "ate_kf", "ate_all_on_kf", "ate_all_on_nonkf", "rel_nonkf", "rel_kf"):
        assert s[k] < 1e-9, k
    # every frame between keyframes 1 cm (true scale) off in a random direction: their error, not the keyframes'
    est2 = est.copy()
    off = np.setdiff1d(np.arange(n), kf)
    u = np.random.default_rng(1).normal(size=(len(off), 3))
    est2[off, :3, 3] += 0.5 * 0.01 * (u / np.linalg.norm(u, axis=1, keepdims=True)) @ R.T
    s = dmq.trajectory_stats(dmq.RunData(Path("x"), None, [], {}, t, est2, t[kf], t, gt, {}, {}, {}))
    assert s["rel_nonkf"] == pytest.approx(0.01, rel=0.1) and s["rel_kf"] < 0.003
    assert s["ate_all_on_nonkf"] > 2 * s["ate_all_on_kf"] and s["ate_kf"] < 1e-9
