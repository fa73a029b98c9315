"""Map reuse (issue 49): a second walk through the rendered room localized in the first walk's saved map.

Exact geometry: both walks are rendered in one room with exact poses, so the Sim(3) that aligns the first run's
trajectory to its ground truth must also align the second run's trajectory to the second walk's ground truth
when (and only when) the second run is posed in the first run's map. A segment of its own has an arbitrary
frame and scale (a monocular gauge): under the first run's alignment it would be off by metres.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from slamkit.cli import main
from slamkit.config import SlamConfig
from slamkit.errors import MapError
from slamkit.eval import ate
from slamkit.eval.map_alignment import error_under, map_alignment_error
from slamkit.pipeline import Slam
from slamkit.sources import open_source
from slamkit.sources.base import FrameRange

pycolmap.logging.minloglevel = 2

FIRST = "synthetic:loop?frames=120"
SECOND = "synthetic:loop?frames=80&jitter=1&seed=1"
"""Two walks round the same ellipse in the room, the second on another path (hand-held shake of about 3 cm and
0.1 m of gaze, 1.5 degrees of roll) and faster."""
RATIO = 1.2
"""The second walk's RMSE under the first run's alignment is within this factor of the first run's own ATE (the
issue's target). Measured: first run 1.86 mm, second walk 1.70 mm (localize-only) and 1.84 mm (mapping) under
its alignment. A frame of its own (a segment that never met the map) has an arbitrary monocular gauge: under
the first run's alignment it would be off by about the room's size."""


def _hashes(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def first_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("map") / "first"
    slam = Slam(FIRST, SlamConfig())
    slam.run()
    assert ate(slam.source.ground_truth(), slam.trajectory()).rmse < 0.005
    slam.save(out)
    return out


def _bound(first: Path) -> float:
    return RATIO * ate(_tum(first / "groundtruth_tum.txt"), _tum(first / "trajectory_tum.txt")).rmse


def _under_first(first: Path, slam: Slam) -> float:
    a1 = ate(_tum(first / "groundtruth_tum.txt"), _tum(first / "trajectory_tum.txt")).alignment
    return error_under(a1, slam.trajectory(), slam.source.ground_truth())["ate"]["rmse"]


def _tum(path: Path):
    from slamkit.io import read_tum
    return read_tum(path)


def test_localize_only_poses_the_second_walk_in_the_first_map_and_adds_nothing(first_run, tmp_path):
    before = _hashes(first_run)
    slam = Slam(SECOND, SlamConfig(), map=first_run, localize_only=True)
    loaded = slam.state.segments[0].slam_map
    kf_before, points_before = set(loaded.keyframes), dict(zip(*_points(loaded)))
    slam.run()
    s = slam.summary()
    assert s["frames_posed"] >= 0.95 * s["frames"]
    assert [seg.id for seg in slam.state.live_segments] == [0]  # no segment of its own
    after = slam.state.segments[0].slam_map
    assert set(after.keyframes) == kf_before and after.num_points == len(points_before)
    ids, xyz = _points(after)
    assert all(np.array_equal(points_before[i], x) for i, x in zip(ids, xyz))  # no point moved either
    assert s["map"]["keyframes"] == s["map"]["keyframes_loaded"] and s["map"]["points3D"] == s["map"]["points_loaded"]
    assert _under_first(first_run, slam) < _bound(first_run)
    out = tmp_path / "second"
    slam.save(out)
    prior = map_alignment_error(out)  # what `slamkit eval` reports
    assert prior["main_in_map"] and prior["matched"] == s["frames_posed"]
    assert prior["ate"]["rmse"] < _bound(first_run)
    assert _hashes(first_run) == before  # the saved run folder is byte-identical


def _points(slam_map):
    rec = slam_map.reconstruction
    ids = sorted(rec.point3D_ids())
    return ids, [np.asarray(rec.point3D(i).xyz).copy() for i in ids]


def test_mapping_extends_the_map_in_its_frame(first_run, tmp_path):
    before = _hashes(first_run)
    slam = Slam(SECOND, SlamConfig(), map=first_run)
    n_kf = slam.state.segments[0].slam_map.num_keyframes
    slam.run()
    s = slam.summary()
    assert s["frames_posed"] >= 0.95 * s["frames"] and s["map"]["main_in_map"]
    assert s["keyframes"] > n_kf and s["map"]["keyframes"] == s["keyframes"]  # the extended map is the main one
    assert _under_first(first_run, slam) < _bound(first_run)
    slam.save(tmp_path / "second")
    assert _hashes(first_run) == before


def test_a_walk_that_never_meets_the_map_is_a_segment_of_its_own_and_says_so(first_run):
    street = "synthetic:street-drive?frames=40"
    slam = Slam(street, SlamConfig(), map=first_run)
    slam.run()
    s = slam.summary()
    assert s["map"]["frames_in_map"] == 0 and "never met the map" in s["map"]["note"]
    assert s["frames_posed"] >= 0.9 * s["frames"] and s["main_segment"] != 0  # nothing lost: its own segment
    assert s["map"]["keyframes"] == s["map"]["keyframes_loaded"]  # the map was not touched
    only = Slam(street, SlamConfig(), map=first_run, localize_only=True)
    only.run()
    s = only.summary()
    assert s["frames_posed"] == 0 and len(only.state.segments) == 1 and "never met the map" in s["map"]["note"]


def test_refusals_name_the_reason_in_one_line(first_run, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    cases = {str(empty): "not a slamkit run folder", str(tmp_path / "none"): "no such folder"}
    for where, words in cases.items():
        with pytest.raises(MapError, match=words):
            Slam(SECOND, SlamConfig(), map=where)
    with pytest.raises(MapError, match="640x480 images, this source's are 320x240"):
        Slam(SECOND + "&scale=0.5", SlamConfig(), map=first_run)
    with pytest.raises(MapError, match="another camera .*fx=500.*fx=450"):
        Slam(SECOND + "&focal=450", SlamConfig(), map=first_run)
    old = tmp_path / "old"
    shutil.copytree(first_run, old)
    meta = json.loads((old / "session" / "session.json").read_text())
    (old / "session" / "session.json").write_text(json.dumps({**meta, "version": 0}))
    with pytest.raises(MapError, match="incompatible slamkit") as e:
        Slam(SECOND, SlamConfig(), map=old)
    assert "\n" not in str(e.value)


def test_cli_refusal_writes_nothing(first_run, tmp_path, capsys):
    out = tmp_path / "out"
    before = _hashes(first_run)
    assert main(["run", SECOND + "&focal=450", "--map", str(first_run), "--out", str(out), "-q"]) == 2
    (tmp_path / "not-a-run").mkdir()
    assert main(["run", SECOND, "--map", str(tmp_path / "not-a-run"), "--out", str(out), "-q"]) == 2
    assert main(["run", SECOND, "--localize-only", "--out", str(out), "-q"]) == 2
    assert main(["run", SECOND, "--map", str(first_run), "--out", str(first_run / "inside"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 4 and all(line.startswith("slamkit: error: ") for line in err)
    assert "another camera" in err[0] and "not a slamkit run folder" in err[1] and "inside" in err[3]
    assert not out.exists() and _hashes(first_run) == before


def test_cli_run_in_a_map_and_eval_under_its_alignment(first_run, tmp_path, capsys):
    before = _hashes(first_run)
    out = tmp_path / "second"
    assert main(["run", SECOND, "--map", str(first_run), "--localize-only", "--max-frames", "30", "--out", str(out),
                 "-q"]) == 0
    assert f"map of {first_run.resolve()}: 30 frames posed in it" in capsys.readouterr().err
    assert main(["eval", str(out), "--json-only"]) == 0
    result = json.loads(capsys.readouterr().out)
    prior = result["map_alignment"]
    assert prior["map_run"] == str(first_run.resolve()) and prior["matched"] == 30
    assert prior["ate"]["rmse"] < _bound(first_run)
    assert _hashes(first_run) == before


LEAVING = "synthetic:loop?frames=120"
"""The room's ellipse walked once: the map is made of its first half (frames 0-59), the second run walks frames
40-119, in the map for 20 frames, then round the half the map never saw, back to where the map began."""


@pytest.fixture(scope="module")
def half_map(tmp_path_factory):
    whole = open_source(LEAVING)
    slam = Slam(FrameRange(whole, 0, 60), SlamConfig())
    slam.run()
    out = tmp_path_factory.mktemp("half") / "first"
    slam.save(out)
    return out, whole, ate(slam.source.ground_truth(), slam.trajectory())


def test_localize_only_leaving_the_map_is_posed_by_odometry_and_comes_back(half_map):
    """ORB-SLAM's localization mode: outside the map tracking goes on (temporary keyframes and points of its own,
    dropped at the end); back in the map, tracked in it. Measured: 80/80 frames posed, 16.5 mm under the first
    run's alignment (first run 1.6 mm; without odometry, map_reuse.odometry_below=0: 6.9 mm, the room's far
    walls stay in sight); a frame of its own would be off by metres."""
    first, whole, first_ate = half_map
    slam = Slam(FrameRange(whole, 40, 120), SlamConfig(), map=first, localize_only=True)
    loaded = slam.state.segments[0].slam_map
    kf_before, points_before = set(loaded.keyframes), dict(zip(*_points(loaded)))
    slam.run()
    s = slam.summary()
    assert s["frames_posed"] >= 0.98 * s["frames"] and [seg.id for seg in slam.state.live_segments] == [0]
    assert s["map"]["temporary_keyframes"] > 0 and s["map"]["temporary_dropped"] > 0
    after = slam.state.segments[0].slam_map  # the map as loaded again: no keyframe, no point added or moved
    assert set(after.keyframes) == kf_before and after.num_points == len(points_before)
    assert all(np.array_equal(points_before[i], x) for i, x in zip(*_points(after)))
    assert error_under(first_ate.alignment, slam.trajectory(), slam.source.ground_truth())["ate"]["rmse"] < 0.03


def test_mapping_leaving_the_map_extends_it_in_its_frame(half_map):
    """Measured: 80/80 posed, 3.1 mm under the first run's alignment (first run 1.6 mm)."""
    first, whole, first_ate = half_map
    slam = Slam(FrameRange(whole, 40, 120), SlamConfig(), map=first)
    slam.run()
    s = slam.summary()
    assert s["frames_posed"] >= 0.98 * s["frames"] and s["map"]["main_in_map"]
    assert error_under(first_ate.alignment, slam.trajectory(), slam.source.ground_truth())["ate"]["rmse"] \
        < 2.5 * first_ate.rmse
