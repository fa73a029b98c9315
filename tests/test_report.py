"""`slamkit eval` / evaluate_run: numbers against a known Sim(3)-distorted estimate, the plots and reports
written into the run folder, the 3D map page from a real run, clear errors, and no matplotlib in the core."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slamkit import SlamkitError, Trajectory, write_tum
from slamkit.cli import main
from slamkit.eval.report import evaluate_run
from slamkit.io.run_dir import write_manifest


def _helix(n: int = 120) -> Trajectory:
    t = np.arange(n) / 30.0
    poses = np.tile(np.eye(4), (n, 1, 1))
    a = np.linspace(0, 3 * np.pi, n)
    poses[:, :3, 3] = np.stack([np.cos(a), 0.2 * np.sin(3 * a), np.sin(a) + 0.3 * a], axis=1)
    for i, ang in enumerate(a):  # yaw with the path
        c, s = np.cos(ang), np.sin(ang)
        poses[i, :3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    return Trajectory(t, poses)


def _fake_run(folder: Path, noise_m: float, seed: int = 0) -> tuple[Path, np.ndarray]:
    """A run folder whose estimate is the ground truth in another Sim(3) frame plus position noise."""
    gt = _helix()
    rng = np.random.default_rng(seed)
    noise = rng.normal(0, noise_m, (len(gt), 3))
    est = gt.poses.copy()
    est[:, :3, 3] += noise
    s, ang = 0.25, 0.7
    S = np.eye(4)
    S[:3, :3] = s * np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    S[:3, 3] = [3.0, -1.0, 2.0]
    est = S @ est
    est[:, :3, :3] /= s  # keep rotations orthonormal
    folder.mkdir(parents=True)
    write_tum(folder / "groundtruth_tum.txt", gt)
    write_tum(folder / "trajectory_tum.txt", Trajectory(gt.timestamps, est))
    write_tum(folder / "keyframes_tum.txt", Trajectory(gt.timestamps[::10], est[::10]))
    summary = {"source": "helix", "frames": len(gt), "frames_posed": len(gt), "fraction_posed": 1.0, "keyframes": 12,
               "points3D": 1000, "points_per_image": 300.0, "mean_reprojection_error_px": 0.5, "fps": 10.0,
               "wall_time_s": 12.0, "timings_s": {"features": 4.0, "track": 5.0, "ba": 2.0, "map": 1.0}}
    (folder / "summary.json").write_text(json.dumps(summary))
    write_manifest(folder)  # a slamkit run folder: eval writes its report only into one (or where --out says)
    return folder, noise


def test_evaluate_run_numbers_plots_reports(tmp_path):
    run, noise = _fake_run(tmp_path / "run", noise_m=0.01)
    res = evaluate_run(run, map_view=False)
    ate = res["all_frames"]["ate"]
    # the Sim(3) is undone: what is left is the added noise (a 7-parameter fit absorbs a little of it)
    expected = float(np.sqrt(np.mean(np.sum(noise**2, axis=1))))
    assert ate["rmse"] == pytest.approx(expected, rel=0.1)
    assert ate["count"] == 120 and ate["alignment"]["scale"] == pytest.approx(4.0, rel=0.01)
    assert res["keyframes"]["ate"]["count"] == 12 and res["keyframes"]["ate"]["rmse"] < 3 * expected
    assert res["all_frames"]["rpe"]["translation"]["rmse"] == pytest.approx(np.sqrt(2) * expected, rel=0.2)
    for key in ("trajectory", "error_over_time", "timings"):
        png = run / res["files"][key]
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000, key
    md = (run / "report.md").read_text()
    assert f"| all frames | 120 | {100 * ate['rmse']:.2f} |" in md
    assert "![trajectory](plots/trajectory.png)" in md and "map.html" not in md
    page = (run / "report.html").read_text()
    assert '<img alt="trajectory" src="plots/trajectory.png">' in page and "<table>" in page
    assert json.loads((run / "evaluation.json").read_text())["all_frames"]["ate"]["rmse"] == ate["rmse"]


def test_exact_estimate_has_zero_error(tmp_path):
    run, _ = _fake_run(tmp_path / "run", noise_m=0.0)
    res = evaluate_run(run, plots=False, map_view=False)
    assert res["all_frames"]["ate"]["rmse"] < 1e-9 and res["keyframes"]["ate"]["rmse"] < 1e-9


def test_gt_argument_and_errors(tmp_path, capsys):
    run, _ = _fake_run(tmp_path / "run", noise_m=0.005)
    gt = tmp_path / "elsewhere.txt"
    (run / "groundtruth_tum.txt").rename(gt)
    with pytest.raises(SlamkitError, match="groundtruth_tum.txt: no ground truth"):
        evaluate_run(run)
    assert main(["eval", str(run), "--no-map-view"]) == 2
    assert "--gt" in capsys.readouterr().err
    assert main(["eval", str(run), "--gt", str(gt), "--no-map-view"]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["all_frames"]["ate"]["count"] == 120 and "ATE RMSE" in out.err
    with pytest.raises(SlamkitError, match="not a run folder"):
        evaluate_run(tmp_path / "missing")
    # too few poses to align: the message says so
    write_tum(run / "trajectory_tum.txt", Trajectory(np.array([0.0, 1 / 30]), np.tile(np.eye(4), (2, 1, 1))))
    write_manifest(run)  # as saved so (an edited file is refused before it is read)
    with pytest.raises(SlamkitError, match="need at least 3"):
        evaluate_run(run, gt=gt)


def test_real_run_report_with_map_view(tmp_path):
    import pycolmap

    from slamkit import Slam, SlamConfig, open_source

    pycolmap.logging.minloglevel = 2
    slam = Slam(open_source("synthetic:handheld?frames=24"), SlamConfig().with_overrides(init_frames=8))
    slam.run()
    run = slam.save(tmp_path / "run")
    assert main(["eval", str(run)]) == 0
    res = json.loads((run / "evaluation.json").read_text())
    assert res["all_frames"]["ate"]["count"] == slam.summary()["frames_posed"] >= 20
    assert res["all_frames"]["ate"]["rmse"] < 0.05  # exact synthetic ground truth: centimetres at most
    assert res["files"].get("map") == "map.html" and (run / "map.html").stat().st_size > 10_000
    assert "three" in (run / "map.html").read_text()[:2_000_000].lower()
    md = (run / "report.md").read_text()
    assert "[Open the static 3D map view](map.html)" in md and "points.ply" in md
    assert "<iframe" in (run / "report.html").read_text()


def test_core_does_not_import_matplotlib():
    code = ("import sys, slamkit, slamkit.ablate, slamkit.eval, slamkit.eval.report, slamkit.cli; "
            "print('matplotlib' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
