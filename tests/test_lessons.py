"""The lesson computations of notebooks 02, 04 and 05 against exact truth (cheap: no SLAM run)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from slamkit.types import Trajectory
from slamkit.viz import lessons


def _poses(xyz: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(xyz), 1, 1))
    T[:, :3, 3] = xyz
    return T


def test_loop_correction_measures_the_gap_the_loop_closes():
    """A square loop of 40 m a side driven once and a bit: the map before the closure drifted (its heading
    turns 0.3 deg a frame too much, so the end is far from the start), after the closure it is the truth.
    The gap between the newest frame and the start must be large before, the truth's after."""
    n = 170
    s = np.arange(n) * 1.0  # metres along the path
    side = 40.0
    def square(s):
        s = s % (4 * side)
        k, r = np.divmod(s, side)
        corners = np.array([[0, 0], [side, 0], [side, side], [0, side]])
        dirs = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])
        return corners[k.astype(int)] + dirs[k.astype(int)] * r[:, None]
    xy = square(s)
    gt_xyz = np.c_[xy, np.zeros(n)]
    t = np.arange(n) * 0.1
    step = np.diff(xy, axis=0)
    yaw = np.radians(0.3) * np.arange(1, n)  # drift: the heading turns 0.3 deg a frame too much
    step = np.c_[np.cos(yaw) * step[:, 0] - np.sin(yaw) * step[:, 1], np.sin(yaw) * step[:, 0] + np.cos(yaw) * step[:, 1]]
    drift = np.c_[np.vstack([[0.0, 0.0], np.cumsum(step, axis=0)]), np.zeros(n)]
    gt = Trajectory(t, _poses(gt_xyz))
    before = Trajectory(t[:-1], _poses(drift[:-1]))  # the closing step's frame is not posed yet
    after = Trajectory(t, _poses(gt_xyz))
    closure = SimpleNamespace(candidate_frame=2, query_frame=n - 1)
    lc = lessons.loop_correction(gt, before, after, closure, t)
    q, c = n - 2, 2
    assert (lc.query, lc.candidate, lc.query_frame, lc.candidate_frame) == (q, c, q, c)
    truth = float(np.linalg.norm(gt_xyz[q] - gt_xyz[c]))
    assert lc.gap_gt == pytest.approx(truth) and lc.gap_after == pytest.approx(truth, abs=1e-6)
    assert lc.gap_before > 3 * truth  # the drifted map (aligned as well as it can be) puts the return far away
    assert lc.ate_after == pytest.approx(0.0, abs=1e-6) and lc.ate_before > 1.0
    assert len(lc.before_xyz) == len(lc.after_xyz) == len(lc.gt_xyz) == n - 1


def test_flow_scores_follow_the_keyframe_rule():
    """After the rule fires, the next frames are measured against the new keyframe (as the pipeline does):
    every reference is the source index of a frame the rule made a keyframe, or the first keyframe."""
    from slamkit.sources import open_source

    src = open_source("default")
    fs = lessons.flow_scores(src, 0, range(1, 9))
    assert fs.keyframes and fs.first_keyframe == fs.keyframes[0]
    assert set(fs.references.tolist()) <= {0, *fs.keyframes}
    for k in fs.keyframes[:-1]:  # the frame after a keyframe is measured against it, with a small score
        i = list(fs.frame_indices).index(k) + 1
        if i < len(fs.frame_indices):
            assert fs.references[i] == k and fs.scores[i] < fs.threshold
    assert np.all(fs.scores[fs.due] > fs.threshold)


def test_describe_focal_prints_the_runs_interval_and_whether_it_covers_the_truth():
    """The ± of a focal estimate is the same two standard deviations as the run's camera line (the notebook showed
    "within 1.0 %" of one sd beside the run's "± 2.0 %"), the bootstrap spread inside it is named, and whether the
    ± covers the true focal length is said, never assumed; a weak estimate gets no ±, a missing one says so."""
    import math

    from slamkit.stages.self_calibration import COVERAGE, MODEL_ERROR, FocalEstimate

    spread = 0.004
    est = FocalEstimate(322.24, math.hypot(spread, MODEL_ERROR), 120, 60, False)
    text = lessons.describe_focal(est, 320.0)
    assert f"± {100 * COVERAGE * est.uncertainty:.1f} %" in text and est.interval == COVERAGE * est.uncertainty
    assert f"bootstrap spread {100 * spread:.1f} %, model error 1 %" in text
    assert "the error is +0.7 % (true f = 320 px), inside the ±" in text  # 0.7 % < 2 sd = 2.2 %
    far = FocalEstimate(340.0, math.hypot(spread, MODEL_ERROR), 120, 60, False)
    assert "the error is +6.2 %" in lessons.describe_focal(far, 320.0) and "outside the ±" in lessons.describe_focal(far, 320.0)
    weak = FocalEstimate(300.0, 0.3, 4, 20, True, "the frame pairs disagree")
    assert "±" not in lessons.describe_focal(weak, 320.0) and "weak" in lessons.describe_focal(weak, 320.0)
    none = FocalEstimate(float("nan"), math.inf, 0, 40, True, "the optical axes meet in all 12 frame pairs")
    assert lessons.describe_focal(none, 320.0).startswith("no estimate (the optical axes meet")


def test_rank_settings_names_ties_by_the_spread_over_repeats():
    """Notebook 03's "best": the lowest mean ATE, and the settings that cannot be told apart from it — within two
    combined standard errors over repeats, or, with one run per setting, equal at the precision shown."""
    import pandas as pd

    def frame(rows):
        return pd.DataFrame([{"flow_threshold": f, "init_frames": i, "seed": s, "status": "ok", "ate_rmse_m": a}
                             for f, i, s, a in rows])

    one = frame([(0.05, 10, 0, 0.00620), (0.05, 20, 0, 0.00626), (0.1, 10, 0, 0.00800), (0.1, 20, 0, 0.00619)])
    r = lessons.rank_settings(one, ["flow_threshold", "init_frames"])
    assert r.best == {"flow_threshold": 0.1, "init_frames": 20} and r.seed == 0
    assert r.tied == [{"flow_threshold": 0.05, "init_frames": 10}]  # shown as 0.62 cm like the best; 0.63 and 0.80 cm are not
    assert [round(a, 5) for _, a, _, _ in r.ate_m] == [0.00619, 0.0062, 0.00626, 0.008]
    assert "a tie, not a ranking" in r.describe() and "no spread" in r.rule
    rows = [(0.05, 10, s, a) for s, a in enumerate((0.010, 0.011, 0.012))]
    rows += [(0.1, 10, s, a) for s, a in enumerate((0.0115, 0.0125, 0.0105))]  # mean 0.0115: 1.4 se apart
    rows += [(0.2, 10, s, a) for s, a in enumerate((0.030, 0.031, 0.029))]
    r = lessons.rank_settings(frame(rows), ["flow_threshold"])
    assert r.best == {"flow_threshold": 0.05} and r.tied == [{"flow_threshold": 0.1}]
    assert r.ate_m[0][2] == pytest.approx(0.001) and r.ate_m[0][3] == 3
    r = lessons.rank_settings(frame(rows[:3] + rows[6:]), ["flow_threshold"])
    assert r.tied == [] and "no other setting is tied" in r.describe()
    failed = frame([(0.05, 10, 0, float("nan"))]).assign(status="failed")
    with pytest.raises(ValueError):
        lessons.rank_settings(failed, ["flow_threshold"])
