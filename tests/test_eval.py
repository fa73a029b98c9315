"""Evaluation against ground truth (association, alignment, ATE, RPE) and agreement with evo.

evo (GPL) is a test-only reference: it is imported here, never by slamkit.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from slamkit.errors import AssociationError, ConfigError
from slamkit.eval import Alignment, AlignmentError, associate, ate, estimate_alignment, evaluate, rpe
from slamkit.geometry import pose_from_tum
from slamkit.io import read_tum, write_tum
from slamkit.types import Trajectory

STATS = ("rmse", "mean", "median", "std", "min", "max")
EVO_TOL = 1e-6  # metres (and degrees for the rotation part of RPE)


# ------------------------------------------------------------------------------------------ helpers

def rotation_from_rotvec(rv: np.ndarray) -> np.ndarray:
    rv = np.asarray(rv, dtype=np.float64).reshape(-1, 3)
    theta = np.linalg.norm(rv, axis=1, keepdims=True)
    axis = np.divide(rv, theta, out=np.zeros_like(rv), where=theta > 0)
    q = np.concatenate([axis * np.sin(theta / 2), np.cos(theta / 2)], axis=1)
    return pose_from_tum(np.zeros((len(rv), 3)), q)[:, :3, :3]


def make_gt(n: int = 300, rate: float = 30.0, t0: float = 1000.0, planar: bool = False) -> Trajectory:
    """A smooth hand-held-like path: a few metres, turning camera."""
    t = t0 + np.arange(n) / rate
    s = t - t0
    pos = np.c_[1.5 * np.sin(0.5 * s), 1.0 * np.cos(0.3 * s), 0.0 * s if planar else 0.3 * np.sin(s)]
    rv = np.c_[0.3 * np.sin(0.2 * s), 0.2 * np.cos(0.4 * s), 0.05 * s]
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, :3, :3] = rotation_from_rotvec(rv)
    P[:, :3, 3] = pos
    return Trajectory(t, P)


SIM3_R = rotation_from_rotvec([0.3, -0.2, 1.0])[0]
SIM3_T = np.array([2.0, -1.0, 0.5])
SIM3_S = 0.37


def transform(traj: Trajectory, R=SIM3_R, t=SIM3_T, s=SIM3_S) -> Trajectory:
    """The estimate a monocular SLAM would give without error: gt in another frame and scale."""
    return Alignment(R, t, s, "sim3").apply(traj)


def make_estimate(gt: Trajectory, seed: int = 0, pos_noise: float = 0.02, rot_noise: float = 0.01,
                  jitter: float = 0.008, drop: float = 0.15) -> Trajectory:
    """Noisy, scaled, rotated estimate with jittered timestamps and missing frames."""
    rng = np.random.default_rng(seed)
    n = len(gt)
    P = gt.poses.copy()
    P[:, :3, :3] = P[:, :3, :3] @ rotation_from_rotvec(rng.normal(scale=rot_noise, size=(n, 3)))
    P[:, :3, 3] += rng.normal(scale=pos_noise, size=(n, 3))
    keep = rng.random(n) > drop
    t = gt.timestamps + rng.uniform(-jitter, jitter, n)
    return transform(Trajectory(t[keep], P[keep]))


# ------------------------------------------------------------------------------------------ truth

def test_rotation_only_estimate_reports_the_rotation_error_and_no_ate():
    """Issue 42: a pan from one place (the rendered ``pure-rotation`` truth); the estimate holds one centre and
    its orientations are the truth's in another frame, each turned by a known angle about a random axis: the
    rotation error is that angle (the alignment is the rotation nearest to sum R_gt R_est^T), the ATE undefined."""
    from slamkit.eval.metrics import ROTATION_ONLY_ATE, ate_line
    from slamkit.sources import open_source

    src = open_source("synthetic:pure-rotation?frames=90")
    gt = src.ground_truth()
    assert np.ptp(gt.positions, axis=0).max() == 0  # exact: one centre
    rng = np.random.default_rng(3)
    n = len(gt)
    angles = np.radians(rng.uniform(0.05, 0.4, n))  # degrees -> radians, per frame
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, :3, :3] = SIM3_R @ gt.poses[:, :3, :3] @ rotation_from_rotvec(axes * angles[:, None])
    P[:, :3, 3] = [0.3, -0.2, 1.0]  # the estimate's one centre, in its own frame
    est = Trajectory(gt.timestamps.copy(), P)
    a = ate(gt, est)
    assert a.undefined == ROTATION_ONLY_ATE and a.alignment.kind == "rotation"
    assert np.isnan(a.rmse) and a.n_matched == n
    # the alignment leaves the known per-frame angles, to a small part of them (the mean error it absorbs)
    np.testing.assert_allclose(a.rotation_errors_deg, np.degrees(angles), atol=0.05)
    assert a.rotation.rmse == pytest.approx(np.sqrt(np.mean(np.degrees(angles) ** 2)), rel=0.02)
    np.testing.assert_allclose(a.alignment.rotation, SIM3_R.T, atol=2e-3)
    res = evaluate(est, gt)
    assert res["ate"]["undefined"] == ROTATION_ONLY_ATE and res["ate"]["rotation_deg"]["rmse"] == a.rotation.rmse
    assert ate_line(res["ate"]).startswith("ATE undefined: rotation only; rotation error RMSE")
    P[:, :3, :3] = SIM3_R @ gt.poses[:, :3, :3]
    assert ate(gt, Trajectory(gt.timestamps.copy(), P)).rotation.max < 1e-6  # no error added: none found


@pytest.mark.parametrize("planar", [False, True])
def test_exact_sim3_copy_gives_zero_error_and_recovers_the_transform(planar):
    gt = make_gt(planar=planar)
    est = transform(gt)
    a = ate(gt, est)
    assert a.rmse < 1e-9 and a.max < 1e-9
    assert a.alignment.scale == pytest.approx(1 / SIM3_S, rel=1e-9)
    np.testing.assert_allclose(a.alignment.rotation, SIM3_R.T, atol=1e-9)
    np.testing.assert_allclose(a.alignment.matrix() @ np.r_[SIM3_T, 1.0], [0, 0, 0, 1], atol=1e-9)
    aligned = a.alignment.apply(est)
    np.testing.assert_allclose(aligned.poses, gt.poses, atol=1e-9)  # orientations too
    r = rpe(gt, est)
    assert r.translation.max < 1e-9 and r.rotation.max < 1e-8
    assert a.n_matched == len(gt) and a.est_matched_fraction == 1.0 and a.gt_matched_fraction == 1.0


def test_alignment_kinds():
    gt = make_gt()
    rigid = transform(gt, s=1.0)
    assert ate(gt, rigid, align="se3").rmse < 1e-9
    assert ate(gt, rigid, align="se3").alignment.scale == 1.0
    assert ate(gt, transform(gt), align="se3").rmse > 0.1  # scale cannot be fixed without "sim3"
    scaled = Trajectory(gt.timestamps, Alignment(scale=4.0).apply_to_poses(gt.poses))
    a = ate(gt, scaled, align="scale")
    assert a.rmse < 1e-9 and a.alignment.scale == pytest.approx(0.25)
    np.testing.assert_array_equal(a.alignment.rotation, np.eye(3))
    assert ate(gt, gt, align="none").rmse == 0.0
    with pytest.raises(ConfigError, match="align"):
        ate(gt, gt, align="umeyama")


def test_alignment_apply_does_not_touch_its_input():
    gt = make_gt(20)
    before = gt.poses.copy()
    out = Alignment(SIM3_R, SIM3_T, 2.0, "sim3").apply(gt)
    np.testing.assert_array_equal(gt.poses, before)
    R = out.poses[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(out.positions, 2.0 * gt.positions @ SIM3_R.T + SIM3_T)


def test_degenerate_positions_raise_alignment_error():
    line = np.c_[np.arange(10.0), np.zeros(10), np.zeros(10)]
    with pytest.raises(AlignmentError, match="line"):
        estimate_alignment(line, np.random.default_rng(0).normal(size=(10, 3)))
    with pytest.raises(AlignmentError, match="one point"):
        estimate_alignment(np.ones((5, 3)), np.random.default_rng(0).normal(size=(5, 3)))
    with pytest.raises(AlignmentError, match="at least 3"):
        estimate_alignment(line[:2], line[:2])


def test_known_noise_gives_expected_rmse():
    gt = make_gt(2000)
    rng = np.random.default_rng(7)
    # no alignment: every camera centre moved by exactly 5 cm
    d = rng.normal(size=(len(gt), 3))
    d *= 0.05 / np.linalg.norm(d, axis=1, keepdims=True)
    moved = gt.poses.copy()
    moved[:, :3, 3] += d
    a = ate(gt, Trajectory(gt.timestamps, moved), align="none")
    for k in ("rmse", "mean", "median", "min", "max"):
        assert getattr(a, k) == pytest.approx(0.05, abs=1e-12)
    assert a.std == pytest.approx(0.0, abs=1e-12)
    # Sim(3) alignment of a transformed, noisy estimate: isotropic noise sigma per axis -> rmse ~ sigma*sqrt(3)
    sigma = 0.01
    noisy = gt.poses.copy()
    noisy[:, :3, 3] += rng.normal(scale=sigma, size=(len(gt), 3))
    a = ate(gt, transform(Trajectory(gt.timestamps, noisy)))
    assert a.rmse == pytest.approx(sigma * np.sqrt(3), rel=0.05)
    assert a.alignment.scale == pytest.approx(1 / SIM3_S, rel=1e-3)


def test_time_offset_and_missing_frames():
    gt = make_gt(300)
    rng = np.random.default_rng(1)
    keep = np.sort(rng.choice(len(gt), 200, replace=False))
    est = transform(gt.subset(keep))
    # the estimate's clock runs 0.515 s ahead: 15.45 frames, no pose within 10 ms of a ground-truth pose
    shifted = Trajectory(est.timestamps + 0.515, est.poses)
    with pytest.raises(AssociationError):
        ate(gt, shifted, max_dt=0.01)
    a = ate(gt, shifted, max_dt=0.01, offset=-0.515)
    assert a.n_matched == 200 and a.rmse < 1e-9
    np.testing.assert_array_equal(a.idx_gt, keep)
    assert a.est_matched_fraction == 1.0
    assert a.gt_matched_fraction == pytest.approx(200 / 300)
    assert a.gt_time_coverage == pytest.approx((gt.timestamps[keep[-1]] - gt.timestamps[keep[0]])
                                               / (gt.timestamps[-1] - gt.timestamps[0]))


def test_associate_nearest_within_max_dt():
    t_ref = np.array([0.0, 1.0, 2.0, 3.0])
    idx_ref, idx_est = associate(t_ref, [0.005, 1.03, 2.5, 2.99], max_dt=0.02)
    assert idx_ref.tolist() == [0, 3] and idx_est.tolist() == [0, 3]
    idx_ref, idx_est = associate(t_ref, [0.005, 1.03, 2.5, 2.99], max_dt=0.05)
    assert idx_ref.tolist() == [0, 1, 3] and idx_est.tolist() == [0, 1, 3]
    # the estimate is denser: each ground-truth pose takes its nearest estimate pose
    idx_ref, idx_est = associate(t_ref, np.arange(0, 3.2, 0.1) + 0.01, max_dt=0.02)
    assert idx_ref.tolist() == [0, 1, 2, 3] and idx_est.tolist() == [0, 10, 20, 30]
    assert [len(x) for x in associate([], [1.0])] == [0, 0]


def test_associate_one_to_one():
    # a gap in the denser trajectory: two ground-truth poses have the same nearest estimate pose
    t_ref, t_est = [0.0, 0.031], [0.015, 0.1, 0.2]
    assert [x.tolist() for x in associate(t_ref, t_est, 0.02)] == [[0, 1], [0, 0]]  # as evo does
    assert [x.tolist() for x in associate(t_ref, t_est, 0.02, one_to_one=True)] == [[0], [0]]


def test_too_few_matches_say_how_many_and_the_time_ranges():
    gt = make_gt(100)
    est = Trajectory(gt.timestamps[:2] + 0.001, gt.poses[:2])
    with pytest.raises(AssociationError) as e:
        ate(gt, est)
    msg = str(e.value)
    assert "only 2" in msg and "[1000.001000, 1000.034333]" in msg and "[1000.000000, 1003.300000]" in msg
    with pytest.raises(AssociationError, match="only 0"):
        rpe(gt, Trajectory(gt.timestamps + 100, gt.poses))


def test_rpe_options_and_errors():
    gt = make_gt(300)
    est = make_estimate(gt, seed=2)
    r1 = rpe(gt, est)
    assert r1.n_pairs == r1.n_matched - 1 and r1.unit == "frames"
    r5 = rpe(gt, est, delta=5)
    assert r5.n_pairs == (r5.n_matched - 1) // 5
    r5all = rpe(gt, est, delta=5, all_pairs=True)
    assert r5all.n_pairs == r5.n_matched - 5
    rm = rpe(gt, est, delta=0.5, unit="m")
    assert rm.unit == "m" and rm.n_pairs > 3
    with pytest.raises(ConfigError, match="delta"):
        rpe(gt, est, delta=1.5)
    with pytest.raises(ConfigError, match="delta"):
        rpe(gt, est, delta=10_000)
    with pytest.raises(ConfigError, match="unit"):
        rpe(gt, est, unit="deg")


def test_evaluate_is_json_serialisable_and_reads_files(tmp_path):
    gt = make_gt(200)
    est = make_estimate(gt, seed=3)
    gt_path, est_path = write_tum(tmp_path / "gt.txt", gt), write_tum(tmp_path / "est.txt", est)
    summary = evaluate(est_path, gt_path)
    text = json.dumps(summary, allow_nan=False)
    back = json.loads(text)
    a = ate(gt, est)
    assert back["ate"]["rmse"] == pytest.approx(a.rmse, abs=1e-12)
    assert back["matched"] == a.n_matched and back["estimate_poses"] == len(est)
    assert back["rpe"]["translation"]["rmse"] == pytest.approx(rpe(gt, est).translation.rmse, abs=1e-12)
    assert back["estimate"] == str(est_path) and back["alignment"]["kind"] == "sim3"
    in_memory = evaluate(est, gt)["ate"]
    rot, rot_file = in_memory.pop("rotation_deg"), summary["ate"].pop("rotation_deg")
    ori, ori_file = in_memory.pop("rotation_oriented_deg"), summary["ate"].pop("rotation_oriented_deg")
    se, se_file = in_memory.pop("rotation_fit_se_deg"), summary["ate"].pop("rotation_fit_se_deg")
    assert in_memory == summary["ate"]  # the file's quaternions round to 1e-15 degrees of rotation error:
    assert rot["rmse"] == pytest.approx(rot_file["rmse"], abs=1e-9) and rot["count"] == rot_file["count"]
    assert ori["rmse"] == pytest.approx(ori_file["rmse"], abs=1e-9) and se == pytest.approx(se_file, rel=1e-9)


# ------------------------------------------------------------------------------------------ evo

evo_sync = pytest.importorskip("evo.core.sync", reason="evo (test-only reference) is not installed")
from evo.core import metrics as evo_metrics  # noqa: E402
from evo.main_ape import ape as evo_ape  # noqa: E402
from evo.main_rpe import rpe as evo_rpe  # noqa: E402
from evo.tools import file_interface as evo_files  # noqa: E402


def evo_api(gt_path: Path, est_path: Path, max_dt: float, delta: float = 1, unit: str = "frames",
            all_pairs: bool = False) -> dict:
    """evo_ape/evo_rpe -as through evo's Python API: {"ape", "rpe_trans", "rpe_rot"} -> evo Result."""
    ref = evo_files.read_tum_trajectory_file(str(gt_path))
    est = evo_files.read_tum_trajectory_file(str(est_path))
    ref, est = evo_sync.associate_trajectories(ref, est, max_diff=max_dt)
    out = {"ape": evo_ape(copy.deepcopy(ref), copy.deepcopy(est), evo_metrics.PoseRelation.translation_part,
                          align=True, correct_scale=True),
           "ape_rot": evo_ape(copy.deepcopy(ref), copy.deepcopy(est), evo_metrics.PoseRelation.rotation_angle_deg,
                              align=True, correct_scale=True)}
    delta_unit = evo_metrics.Unit.frames if unit == "frames" else evo_metrics.Unit.meters
    for key, relation in (("rpe_trans", evo_metrics.PoseRelation.translation_part),
                          ("rpe_rot", evo_metrics.PoseRelation.rotation_angle_deg)):
        out[key] = evo_rpe(copy.deepcopy(ref), copy.deepcopy(est), relation, delta=delta, delta_unit=delta_unit,
                           all_pairs=all_pairs, align=True, correct_scale=True)
    return out


def max_stat_diff(evo_stats: dict, ours) -> float:
    return max(abs(float(evo_stats[k]) - getattr(ours, k)) for k in STATS)


def check_against_evo_api(gt_path: Path, est_path: Path, max_dt: float, **rpe_kw) -> float:
    gt, est = read_tum(gt_path), read_tum(est_path)
    a = ate(gt, est, max_dt=max_dt)
    r = rpe(gt, est, max_dt=max_dt, **rpe_kw)
    ref = evo_api(gt_path, est_path, max_dt, **rpe_kw)
    np.testing.assert_allclose(a.errors, ref["ape"].np_arrays["error_array"], rtol=0, atol=EVO_TOL)
    np.testing.assert_allclose(a.timestamps, ref["ape"].np_arrays["timestamps"], rtol=0, atol=0)
    np.testing.assert_allclose(a.alignment.matrix(), ref["ape"].np_arrays["alignment_transformation_sim3"],
                               atol=1e-9)
    np.testing.assert_allclose(a.rotation_errors_deg, ref["ape_rot"].np_arrays["error_array"], atol=EVO_TOL)
    assert a.rotation.rmse > 0.1 and not a.undefined  # degrees: the estimate's rotation noise is seen
    np.testing.assert_allclose(r.translation_errors, ref["rpe_trans"].np_arrays["error_array"], atol=EVO_TOL)
    np.testing.assert_allclose(r.rotation_errors_deg, ref["rpe_rot"].np_arrays["error_array"], atol=EVO_TOL)
    diffs = [max_stat_diff(ref["ape"].stats, a.stats), max_stat_diff(ref["rpe_trans"].stats, r.translation),
             max_stat_diff(ref["rpe_rot"].stats, r.rotation)]
    assert max(diffs) < EVO_TOL, diffs
    return max(diffs)


@pytest.fixture(scope="module")
def synthetic_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("evo")
    gt = make_gt(600)
    est = make_estimate(gt, seed=11)
    return write_tum(d / "gt.txt", gt), write_tum(d / "est.txt", est)


@pytest.mark.parametrize("max_dt", [0.01, 0.02])
def test_agrees_with_evo_api(synthetic_files, max_dt):
    check_against_evo_api(*synthetic_files, max_dt=max_dt)


@pytest.mark.parametrize("rpe_kw", [dict(delta=5), dict(delta=5, all_pairs=True), dict(delta=0.3, unit="m"),
                                    dict(delta=0.3, unit="m", all_pairs=True)])
def test_rpe_variants_agree_with_evo_api(synthetic_files, rpe_kw):
    check_against_evo_api(*synthetic_files, max_dt=0.02, **rpe_kw)


def test_planar_and_equal_length_trajectories_agree_with_evo_api(tmp_path):
    # a path at z = 0 (COLMAP refuses it, the numpy fallback takes over); the estimate has as many
    # poses as the ground truth (evo then queries with the estimate)
    gt = make_gt(200, planar=True)
    est = make_estimate(gt, seed=5, drop=0.0)
    check_against_evo_api(write_tum(tmp_path / "gt.txt", gt), write_tum(tmp_path / "est.txt", est), 0.02)


def test_association_matches_evo_on_random_clocks():
    from evo.core.trajectory import PoseTrajectory3D

    rng = np.random.default_rng(0)
    for trial in range(40):
        n_ref, n_est = rng.integers(5, 60, size=2)
        if trial % 5 == 0:
            n_est = n_ref
        t_ref = np.cumsum(rng.uniform(0.005, 0.05, n_ref))
        t_est = np.cumsum(rng.uniform(0.005, 0.05, n_est))
        if trial % 7 == 0:
            rng.shuffle(t_est)  # evo's linear-search branch
        max_dt, offset = rng.uniform(0.002, 0.03), rng.choice([0.0, 0.01, -0.02])

        def traj(t):  # x = index, so evo's synced copies tell which poses it kept
            n = len(t)
            return PoseTrajectory3D(np.c_[np.arange(n), np.zeros((n, 2))], np.tile([1.0, 0, 0, 0], (n, 1)), t)

        idx_ref, idx_est = associate(t_ref, t_est, max_dt, offset)
        try:
            r, e = evo_sync.associate_trajectories(traj(t_ref), traj(t_est), max_diff=max_dt, offset_2=offset)
        except evo_sync.SyncException:
            assert len(idx_ref) == 0
            continue
        assert idx_ref.tolist() == r.positions_xyz[:, 0].astype(int).tolist()
        assert idx_est.tolist() == e.positions_xyz[:, 0].astype(int).tolist()


def evo_executable(name: str) -> Path | None:
    candidate = Path(sys.executable).parent / name
    if candidate.exists():
        return candidate
    found = shutil.which(name)
    return Path(found) if found else None


def run_evo_cli(tool: str, gt_path: Path, est_path: Path, out_zip: Path, *extra: str) -> dict:
    exe = evo_executable(tool)
    if exe is None:
        pytest.skip(f"the {tool} executable is not installed (pip install evo); the API comparison still runs")
    home = out_zip.parent / "home"
    home.mkdir(exist_ok=True)
    env = {**os.environ, "HOME": str(home), "MPLBACKEND": "Agg"}  # evo writes ~/.evo/settings.json once
    cmd = [str(exe), "tum", str(gt_path), str(est_path), "-as", "--t_max_diff", "0.02",
           "--save_results", str(out_zip), "--no_warnings", *extra]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with zipfile.ZipFile(out_zip) as z:
        return json.loads(z.read("stats.json"))


def test_agrees_with_evo_command_line(synthetic_files, tmp_path):
    gt_path, est_path = synthetic_files
    gt, est = read_tum(gt_path), read_tum(est_path)
    a, r = ate(gt, est, max_dt=0.02), rpe(gt, est, max_dt=0.02)
    ape_stats = run_evo_cli("evo_ape", gt_path, est_path, tmp_path / "ape.zip")
    rpe_trans = run_evo_cli("evo_rpe", gt_path, est_path, tmp_path / "rpe_t.zip", "--delta", "1",
                            "--delta_unit", "f")
    rpe_rot = run_evo_cli("evo_rpe", gt_path, est_path, tmp_path / "rpe_r.zip", "--pose_relation", "angle_deg")
    assert max_stat_diff(ape_stats, a.stats) < EVO_TOL
    assert max_stat_diff(rpe_trans, r.translation) < EVO_TOL
    assert max_stat_diff(rpe_rot, r.rotation) < EVO_TOL
    summary = evaluate(est_path, gt_path)
    assert max(abs(summary["ate"][k] - ape_stats[k]) for k in STATS) < EVO_TOL
    assert max(abs(summary["rpe"]["translation"][k] - rpe_trans[k]) for k in STATS) < EVO_TOL


@pytest.mark.shared_data
def test_agrees_with_evo_on_real_ground_truth(shared, tmp_path):
    gt_path = shared("tum/groundtruth-only/fr1_xyz/groundtruth.txt")
    gt = read_tum(gt_path)
    # a 30 Hz-like estimate: every third ground-truth pose, perturbed, in another frame and scale
    est = make_estimate(gt.subset(slice(0, None, 3)), seed=21, pos_noise=0.01, rot_noise=0.005, jitter=0.004,
                        drop=0.1)
    est_path = write_tum(tmp_path / "est.txt", est)
    check_against_evo_api(gt_path, est_path, max_dt=0.02)
    ape_stats = run_evo_cli("evo_ape", gt_path, est_path, tmp_path / "ape.zip")
    assert max_stat_diff(ape_stats, ate(gt, est, max_dt=0.02).stats) < EVO_TOL
