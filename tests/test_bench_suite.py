"""benchmarks/bench_suite.py's machinery on a tiny synthetic case: the row's numbers against the run's own
summary and saved trajectory, the aggregation over seeds, and the scheduler's handling of a crashed, a
hanging and an absent case (real worker processes)."""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from slamkit import ate, read_tum
from slamkit.sources import open_source

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_suite  # noqa: E402
from bench_suite import Case  # noqa: E402

TINY = Case("tiny-jerky", "jerky", "synthetic:jerky?frames=60&jumps=1&jump=4&noise=1&seed={seed}", what="test")


def test_run_row_matches_the_runs_summary_and_saved_trajectory(tmp_path):
    row = bench_suite.run_one(TINY, seed=1, out_dir=tmp_path / "run")
    assert row["status"] == "ok", row["error"]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    n = summary["frames"]
    assert row["frames"] == n == 60
    assert row["posed_pct"] == pytest.approx(100 * summary["frames_posed"] / n)
    assert row["posed_pct"] > 50  # a slow tiny case is tracked
    assert row["segments"] == len(summary["segments"])
    assert row["relocalizations"] == summary["relocalizations"]
    assert row["keyframes"] == summary["keyframes"]
    est = read_tum(tmp_path / "run" / "trajectory_tum.txt")
    assert row["largest_pct"] == pytest.approx(100 * len(est) / n)
    largest = max(s["frames"] for s in summary["segments"])
    assert len(est) == largest
    # ATE: Sim(3) of the saved trajectory against the exact ground truth of the same spec
    gt = open_source("synthetic:jerky?frames=60&jumps=1&jump=4&noise=1&seed=1").ground_truth()
    assert row["ate_m"] == pytest.approx(ate(gt, est).rmse, rel=1e-6)
    assert 0 < row["ate_m"] < 0.05
    assert row["rot_deg"] == pytest.approx(ate(gt, est).rotation.rmse, rel=1e-6) and 0 < row["rot_deg"] < 1
    # keyframe ATE: the saved keyframe trajectory (ORB-SLAM2's KeyFrameTrajectory.txt)
    kf = read_tum(tmp_path / "run" / "keyframes_tum.txt")
    assert 3 <= len(kf) < len(est)
    assert row["ate_kf_m"] == pytest.approx(ate(gt, kf).rmse, rel=1e-6)
    assert row["fps"] == pytest.approx(n / row["wall_s"])
    assert 0 < row["cpu_s_per_frame"] < 5


def test_mean_and_standard_error():
    m, se = bench_suite.mean_se([1.0, 2.0, 3.0, 6.0])
    assert m == 3.0
    assert se == pytest.approx(np.std([1, 2, 3, 6], ddof=1) / 2)
    assert bench_suite.mean_se([4.0]) == (4.0, None)
    assert bench_suite.mean_se([]) == (None, None)


def test_case_rows_aggregate_over_the_ok_seeds():
    runs = [{"row": "run", "case": "c", "skip": 2, "seed": s, "status": "ok", "frames": 10, "posed_pct": p,
             "segments": 1, "largest_pct": p, "ate_m": a, "relocalizations": 0, "fps": 5.0,
             "cpu_s_per_frame": 0.1, "wall_s": 2.0, "keyframes": 3, "error": ""}
            for s, p, a in ((0, 50.0, 0.1), (1, 70.0, None))]
    runs.append({"row": "run", "case": "c", "skip": 2, "seed": 2, "status": "timeout", "error": "no result"})
    (row,) = bench_suite.case_rows([Case("c", "real", "x", 2)], runs)
    assert row["status"] == "2/3 ok" and row["seed"] == "0 1 2"
    assert row["posed_pct"] == 60.0 and row["posed_pct_se"] == pytest.approx(10.0)
    assert row["ate_m"] == 0.1 and row["ate_m_se"] is None
    assert "seed 2: no result" in row["error"] and "ATE over 1/2 seeds" in row["error"]
    table = bench_suite.markdown([row])
    assert "| c | 2 | 10 | 2/3 ok | 60.0 ± 10.0 |" in table


def test_select_cases():
    names = [c.name for c in bench_suite.select_cases(bench_suite.CASES, None, quick=True)]
    assert names == ["kitti-07/skip2", "7scenes/skip3", "video-kitti984", "syn-forward-0.5", "syn-fast-yaw-10",
                     "syn-jerky-30"]
    assert [c.name for c in bench_suite.select_cases(bench_suite.CASES, "kitti*,syn-jerky-10", False)] == [
        "kitti-07/skip1", "kitti-07/skip2", "kitti-07/skip3", "kitti-07/folder", "syn-jerky-10"]


def test_scheduler_reports_errors_timeouts_and_absent_data_as_rows(tmp_path):
    bad = Case("bad-spec", "jerky", "synthetic:jerky?frames=1&seed={seed}")  # raises ConfigError in the worker
    slow = Case("slow", "jerky", "synthetic:jerky?frames=400&noise=1&seed={seed}")
    absent = Case("absent", "real", "no-such-folder-here")
    rows = bench_suite.run_all([(bad, 0), (absent, 3)], workers=2, timeout_s=120.0, log=lambda s: None)
    rows.insert(1, bench_suite.run_all([(slow, 0)], workers=1, timeout_s=3.0, log=lambda s: None)[0])
    assert [r["case"] for r in rows] == ["bad-spec", "slow", "absent"]
    assert rows[0]["status"] == "error" and "frames" in rows[0]["error"]
    assert rows[1]["status"] == "timeout"
    assert rows[2]["status"] == "skipped" and "no-such-folder-here" in rows[2]["error"] and rows[2]["seed"] == 3
    path = tmp_path / "s.csv"
    bench_suite.write_csv(path, rows, bench_suite.case_rows([bad, slow, absent], rows))
    with open(path) as f:
        got = list(csv.DictReader(f))
    assert [(r["row"], r["case"], r["status"]) for r in got] == [
        ("run", "bad-spec", "error"), ("run", "slow", "timeout"), ("run", "absent", "skipped"),
        ("case", "bad-spec", "0/1 ok"), ("case", "slow", "0/1 ok"), ("case", "absent", "skipped")]
    assert all(math.isnan(float(r["ate_m"] or "nan")) for r in got)
