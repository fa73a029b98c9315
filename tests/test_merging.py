"""Map merging (issue 18): two segments of one synthetic scene merged into one map, exact geometry.

The sequence: 80 frames of a hand-held motion, 8 unrelated frames (noise: tracking is lost, the pipeline ends
the segment and initializes a new one), then frames 40-149 of the same motion again. The two segments thus see
the same place (frames 40-79) in two unrelated gauges and scales; they are aligned through their map points
matched by descriptor (``segment_alignment``) and merged. The run stops at frame 178, is saved once, and every
test resumes that session (so each gets a fresh state; the last 20 frames are for continuing after a merge).
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from dataclasses import replace

import cv2
import numpy as np
import pytest

from slamkit.config import SlamConfig
from slamkit.errors import ConfigError
from slamkit.eval.align import estimate_alignment
from slamkit.eval.metrics import ate
from slamkit.io.run_dir import SESSION_MARKER, write_manifest
from slamkit.local_map import LocalMap
from slamkit.map import graph_pairs, matrix_from_rigid
from slamkit.merging import MergeResult, merge_segments, segment_alignment, transform_cam_from_world
from slamkit.pipeline import Slam
from slamkit.session import SESSION_FILE
from slamkit.pose_graph import sim3_decompose, sim3_matrix
from slamkit.sources import open_source
from slamkit.sources.scene import default_room
from slamkit.sources.synthetic import SyntheticSource
from slamkit.stages.ba import BundleAdjuster

ORDER = list(range(0, 80)) + [-1] * 8 + list(range(40, 150))
"""Frames of the hand-held motion played, -1 = an unrelated (noise) frame."""
STOP = 178
"""Frames processed before the session is saved (the rest continue after a merge)."""
SCALE_TOL, ANGLE_TOL_DEG = 0.01, 1.0
"""Agreement of the Sim(3) from matched points with the one from the frames both segments posed."""


class TwoVisits:
    """Synthetic hand-held frames in the order :data:`ORDER` (rendered, exact ground truth), noise at -1."""

    def __init__(self):
        base = open_source("synthetic:handheld?frames=150&seed=0")
        poses = base.gt_poses[[max(o, 0) for o in ORDER]]
        self.src = SyntheticSource(default_room(), poses, base.camera, name="synthetic/two-visits")
        self.name, self.camera = self.src.name, self.src.camera
        self.timestamps, self.frame_ids, self.gt_poses = self.src.timestamps, self.src.frame_ids, self.src.gt_poses

    def __len__(self):
        return len(self.src)

    def __getitem__(self, i):
        frame = self.src[i]
        if ORDER[i] >= 0:
            return frame
        gray = cv2.GaussianBlur(np.random.default_rng(i).integers(0, 256, frame.gray.shape, dtype=np.uint8),
                                (5, 5), 1.5)
        return replace(frame, gray=gray, color=np.dstack([gray] * 3))

    def ground_truth(self):
        return self.src.ground_truth()


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    src = TwoVisits()
    config = SlamConfig(max_lost_frames=5).with_overrides(init_frames=10, **{"loop_closing.enabled": False})
    slam = Slam(src, config)  # no loop closing: the pipeline would merge the segments itself (test below)
    slam.run(max_steps=STOP)
    assert len(slam.segments) == 2 and slam.state.segment is slam.segments[1]  # the break happened
    folder = tmp_path_factory.mktemp("merging") / "session"
    slam.save_session(folder)
    return src, folder


def _resume(session) -> tuple[TwoVisits, Slam]:
    src, folder = session
    return src, Slam.resume(folder, source=src)


def _posed(slam: Slam, seg_id: int) -> dict[int, np.ndarray]:
    return {r.index: slam.state.pose_of(r) for r in slam.records if r.segment == seg_id and r.rel_pose is not None}


def _common_frames_similarity(slam: Slam) -> tuple[float, np.ndarray]:
    """(scale, rotation (3, 3)) of target_from_source from the frames of the first visit (segment 0) posed
    again on the second visit (segment 1): the scale of the Umeyama fit of their camera centres, the rotation
    the chordal mean of ``R_cw(target)^T R_cw(source)`` (the centres of a short path hardly fix the rotation
    about it)."""
    first, second = _posed(slam, 0), _posed(slam, 1)
    again = {ORDER[i]: i for i in second}
    common = [(i, again[ORDER[i]]) for i in first if ORDER[i] in again]
    assert len(common) >= 20
    c0 = np.array([np.linalg.inv(first[i])[:3, 3] for i, _ in common])
    c1 = np.array([np.linalg.inv(second[j])[:3, 3] for _, j in common])
    u, _, vt = np.linalg.svd(sum(first[i][:3, :3].T @ second[j][:3, :3] for i, j in common))
    return estimate_alignment(c1, c0).scale, u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))))


def _check_valid(rec) -> None:
    """Every track's images are registered and their keypoints point back at the track."""
    reg = set(rec.reg_image_ids())
    for pid, point in rec.points3D.items():
        assert point.track.length() >= 2
        for el in point.track.elements:
            assert el.image_id in reg
            assert rec.image(el.image_id).point2D(el.point2D_idx).point3D_id == pid


def test_two_segments_merge_into_one_map_matching_ground_truth(session, tmp_path):
    src, slam = _resume(session)
    target, source = slam.segments
    gt = src.ground_truth()
    n_frames = {s.id: len(_posed(slam, s.id)) for s in slam.segments}
    n_points = (target.slam_map.num_points, source.slam_map.num_points)
    n_kf = (target.slam_map.num_keyframes, source.slam_map.num_keyframes)
    n_pairs = (len(graph_pairs(target.slam_map)[0]), len(graph_pairs(source.slam_map)[0]))
    # the Sim(3) from map points matched by descriptor agrees with the one the frames both segments posed give
    al = segment_alignment(target.slam_map, source.slam_map)
    assert al.accepted, al.verification.reason
    assert len(al.point_pairs) >= 50
    s_ref, r_ref = _common_frames_similarity(slam)
    s_est, r_est, _ = sim3_decompose(al.target_from_source)
    assert abs(s_est / s_ref - 1) < SCALE_TOL and _angle_deg(r_est, r_ref) < ANGLE_TOL_DEG

    res = merge_segments(slam.state, target, source, al.target_from_source, al.point_pairs)
    assert isinstance(res, MergeResult) and res.global_ba_advised
    assert res.points_fused == len(al.point_pairs) and res.keyframes_moved == n_kf[1]
    assert target.slam_map.num_points == sum(n_points) - res.points_fused
    assert target.slam_map.num_keyframes == sum(n_kf) and source.slam_map.num_keyframes == 0
    assert res.seam_image_pairs > 0  # keyframes that see a fused point are matched across the seam
    assert len(graph_pairs(target.slam_map)[0]) == sum(n_pairs) + res.seam_image_pairs  # source matches carried
    assert source.merged_into == 0 and source.frames == [] and res.frames_moved >= n_frames[1]
    _check_valid(target.slam_map.reconstruction)
    # one map, one trajectory: every posed frame of both segments, accurate after ONE Sim(3)
    traj = slam.trajectory()
    assert len(traj) == sum(n_frames.values())
    assert ate(gt, traj).rmse < 0.015
    s = slam.summary()
    assert len(s["segments"]) == 1 and s["merges"] == 1 and s["main_segment"] == 0
    assert s["keyframes"] == sum(n_kf) and s["frames_posed"] == sum(n_frames.values())
    assert len(slam.trajectory(segment=1)) == len(traj)  # a merged segment's trajectory is its target's

    # a global BA of the merged map runs and does not raise the reprojection error (beyond what completing and
    # merging tracks after it adds: observations within the chi-square bound; measured +0.02 %)
    error_before = target.slam_map.mean_reprojection_error()
    bres = BundleAdjuster(slam.config.ba).adjust_global(target.slam_map)
    if bres.normalization is not None:
        slam.state.apply_normalization(target, float(bres.normalization.scale))
    assert bres.termination in ("CONVERGENCE", "NO_CONVERGENCE")
    assert target.slam_map.mean_reprojection_error() <= error_before * 1.005
    assert bres.merged > 0  # tracks joined across the seam through the fused points' matches
    assert ate(gt, slam.trajectory()).rmse < 0.008  # BA reconciles the two parts (measured 3.8 mm, 8.8 before)
    _check_valid(target.slam_map.reconstruction)

    # save and resume the merged state
    slam.save_session(tmp_path / "merged")
    again = Slam.resume(tmp_path / "merged", source=src)
    assert [g.merged_into for g in again.segments] == [-1, 0]
    assert again.summary()["segments"] == slam.summary()["segments"] and again.summary()["merges"] == 1
    np.testing.assert_allclose(again.trajectory().poses, slam.trajectory().poses, atol=1e-12)


def test_frame_poses_after_merging_are_the_sim3_transformed_ones(session):
    """With any similarity (here an arbitrary one, no fused points) every frame, keyframe and point of the
    source is exactly the transformed old one; the target's are untouched."""
    _, slam = _resume(session)
    target, source = slam.segments
    angle = np.radians(37.0)
    rot = cv2.Rodrigues(np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]) * angle)[0]
    sim = sim3_matrix(2.7, rot, [0.4, -1.3, 2.1])
    old_source, old_target = _posed(slam, 1), _posed(slam, 0)
    old_kf = {i: matrix_from_rigid(source.slam_map.cam_from_world(i)) for i in source.slam_map.keyframes}
    old_xyz = {int(p): np.array(pt.xyz) for p, pt in source.slam_map.reconstruction.points3D.items()}
    res = merge_segments(slam.state, target, source, sim)
    assert res.points_fused == 0 and not res.global_ba_advised
    assert res.scale == pytest.approx(2.7) and np.allclose(res.rotation, rot)
    for i, pose in old_source.items():
        assert slam.records[i].segment == 0
        np.testing.assert_allclose(slam.state.pose_of(i), transform_cam_from_world(pose, sim), atol=1e-9)
        world = np.linalg.inv(slam.state.pose_of(i))  # camera centres move with the points
        np.testing.assert_allclose(world[:3, 3], 2.7 * rot @ np.linalg.inv(pose)[:3, 3] + sim[:3, 3], atol=1e-9)
    for i, pose in old_target.items():
        np.testing.assert_allclose(slam.state.pose_of(i), pose, atol=0)
    for old, new in res.image_ids.items():
        np.testing.assert_allclose(matrix_from_rigid(target.slam_map.cam_from_world(new)),
                                   transform_cam_from_world(old_kf[old], sim), atol=1e-9)
        assert slam.records[target.slam_map.keyframes[new].frame_index].keyframe_image_id == new
    assert len(res.point3D_ids) == len(old_xyz) == res.points_moved
    xyz = target.slam_map.points_xyz([res.point3D_ids[p] for p in old_xyz])
    np.testing.assert_allclose(xyz, 2.7 * np.array(list(old_xyz.values())) @ rot.T + sim[:3, 3], atol=1e-9)


def test_tracking_continues_in_the_merged_map(session):
    """The source was the segment being tracked: after the merge the state tracks in the target, the caller
    rebuilds the local map around the returned keyframe, and the remaining frames are tracked and mapped
    (new keyframes matched against moved ones) in the one map."""
    src, slam = _resume(session)
    target, source = slam.segments
    al = segment_alignment(target.slam_map, source.slam_map)
    res = merge_segments(slam.state, target, source, al.target_from_source, al.point_pairs)
    assert slam.state.segment is target and res.local_map_stale and slam.state.local_map is None
    assert slam.state.last_keyframe == res.last_keyframe and res.last_keyframe in target.slam_map.keyframes
    assert all(target.slam_map.reconstruction.exists_point3D(int(p)) for p in slam.state.last_ids)
    c = slam.config.tracker
    slam.state.local_map = LocalMap.build(target.slam_map, res.last_keyframe, c.local_keyframes, c.point_descriptor)
    keyframes = target.slam_map.num_keyframes
    results = slam.run()
    assert len(results) == len(ORDER) - STOP
    assert all(r.status == "tracked" and r.segment == 0 for r in results)
    assert target.slam_map.num_keyframes > keyframes  # mapping went on
    assert len(slam.summary()["segments"]) == 1
    _check_valid(target.slam_map.reconstruction)
    assert ate(src.ground_truth(), slam.trajectory()).rmse < 0.015


def test_misuse_is_a_clear_error(session):
    _, slam = _resume(session)
    target, source = slam.segments
    sim = np.eye(4)
    with pytest.raises(ConfigError, match="into itself"):
        merge_segments(slam.state, target, target, sim)
    with pytest.raises(ConfigError, match="target_from_source: not a similarity"):
        merge_segments(slam.state, target, source, np.diag([1.0, 1.0, -1.0, 1.0]))  # a reflection
    with pytest.raises(ConfigError, match="target_from_source: not a similarity"):
        merge_segments(slam.state, target, source, np.diag([1.0, 2.0, 1.0, 1.0]))  # anisotropic
    with pytest.raises(ConfigError, match="target_from_source: expected a finite"):
        merge_segments(slam.state, target, source, np.eye(3))
    with pytest.raises(ConfigError, match="point_pairs"):
        merge_segments(slam.state, target, source, sim, np.array([[10**9, 1]]))
    assert source.merged_into == -1 and source.slam_map.num_keyframes > 0  # nothing happened
    merge_segments(slam.state, target, source, sim)
    with pytest.raises(ConfigError, match="already merged into segment 0"):
        merge_segments(slam.state, target, source, sim)
    with pytest.raises(ConfigError, match="already merged into segment 0"):
        merge_segments(slam.state, source, target, sim)


def test_a_session_saved_before_segments_could_merge_still_loads(session, tmp_path):
    """Sessions written before ``Segment.merged_into`` existed have no such key: their segments load unmerged
    (-1), and can then be merged."""
    src, folder = session
    old = tmp_path / "old"
    shutil.copytree(folder, old)
    meta = json.loads((old / SESSION_FILE).read_text())
    for seg in meta["segments"]:
        assert seg["extra"].pop("merged_into") == -1  # saved as a segment field like keyframes_culled
    (old / SESSION_FILE).write_text(json.dumps(meta))
    write_manifest(old, SESSION_MARKER)  # as the older version signed it
    slam = Slam.resume(old, source=src)
    assert [s.merged_into for s in slam.segments] == [-1, -1] and slam.summary()["merges"] == 0
    merge_segments(slam.state, slam.segments[0], slam.segments[1], np.eye(4))
    assert slam.summary()["merges"] == 1 and len(slam.summary()["segments"]) == 1


def test_an_earlier_segment_merged_into_the_current_one(session):
    """The other direction: the older segment moves into the one being tracked, whose keyframes, local map
    and cursor stay as they are; both visits end in one trajectory in the current segment's frame."""
    src, slam = _resume(session)
    older, current = slam.segments
    local_map, last_keyframe = slam.state.local_map, slam.state.last_keyframe
    al = segment_alignment(current.slam_map, older.slam_map)
    assert al.accepted, al.verification.reason
    res = merge_segments(slam.state, current, older, al.target_from_source, al.point_pairs)
    assert res.target == 1 and res.last_keyframe == -1 and not res.local_map_stale
    assert slam.state.segment is current and slam.state.local_map is local_map
    assert slam.state.last_keyframe == last_keyframe
    s = slam.summary()
    assert s["main_segment"] == 1 and s["merges"] == 1 and [g["id"] for g in s["segments"]] == [1]
    assert len(slam.trajectory(segment=0)) == s["frames_posed"]
    _check_valid(current.slam_map.reconstruction)
    assert ate(src.ground_truth(), slam.trajectory()).rmse < 0.015


@pytest.fixture(scope="module")
def merged_run():
    """The whole two-visit sequence with loop closing on (the default): (source, Slam, merge step results)."""
    src = TwoVisits()
    slam = Slam(src, SlamConfig(max_lost_frames=5).with_overrides(init_frames=10))
    merges = [r for r in slam if r.map_merge is not None]
    slam.finish()
    return src, slam, merges


def test_pipeline_merges_the_second_visit_into_the_first_map(merged_run):
    """With loop closing on (the default), the new segment recognises the first visit's place a few keyframes
    after it starts and is merged into it: one map, every frame but the noise posed in it, consistent with
    ground truth after one Sim(3); without loop closing the same run ends in two segments."""
    src, slam, merges = merged_run
    s = slam.summary()
    assert len(merges) == 1 and s["merges"] == 1 and len(s["segments"]) == 1
    m, entry = merges[0], s["map_merges"][0]
    assert (m.map_merge.source, m.map_merge.target, entry["segment"], entry["into"]) == (1, 0, 1, 0)
    assert m.merge_candidate is not None and m.merge_candidate.inliers >= 30
    assert 40 <= ORDER[entry["candidate_frame"]] < 80  # a keyframe of the first visit's overlap (frames 40-79)
    assert "merged into segment 0" in str(m)
    assert m.frame_index == entry["query_frame"] < 88 + 60  # soon after the second visit starts (frame 88)
    traj = slam.trajectory()
    assert len(traj) >= len(ORDER) - 8 - 2  # all but the noise (and the frames lost on it)
    res = ate(traj, src.ground_truth())
    assert res.rmse < 0.03 * _extent(src), res  # one consistent map: 1.6 cm here
    assert slam.state.segment is slam.segments[0] and slam.segments[1].merged_into == 0


def _extent(src) -> float:
    """Ground-truth path extent (m): the ATE bound scales with it."""
    c = src.gt_poses[:, :3, 3]
    return float(np.linalg.norm(c.max(0) - c.min(0)))


def test_map_view_draws_the_merge_as_a_loop_edge(merged_run, tmp_path):
    """The 3D view draws a line between the two keyframes that recognised the same place, live and from the
    saved run: its ends are the two frames' camera centres in the merged map."""
    from slamkit.viz.meshcat_view import MapView
    from slamkit.viz.snapshot import state_from_run, state_from_slam

    _, slam, _ = merged_run
    entry = slam.summary()["map_merges"][0]
    ends = [np.linalg.inv(slam.pose_of(entry[k]))[:3, 3] for k in ("query_frame", "candidate_frame")]
    live = state_from_slam(slam)
    assert live.loop_edges.shape == (1, 2, 3) and np.allclose(live.loop_edges[0], ends, atol=1e-9)
    run_dir = slam.save(tmp_path / "run")
    saved = state_from_run(run_dir)
    assert saved.loop_edges.shape == (1, 2, 3) and np.allclose(saved.loop_edges[0], ends, atol=1e-5)
    view = MapView()
    try:
        view.show(live)
        assert view.scene_counts()["loops"] == 1
        sys.path.insert(0, str(Path(__file__).parent))
        from test_viz import attribute, scene_objects  # the decoder of meshcat's replayed commands

        drawn = attribute(scene_objects(view)["/meshcat/slamkit/path/loops"], "position").T  # (2, 3) vertices
        assert np.allclose(drawn, ends, atol=1e-4)
        # and the band that makes it stand out (WebGL lines are 1 px): points from one keyframe to the other
        band = attribute(scene_objects(view)["/meshcat/slamkit/path/loop_band"], "position").T
        assert len(band) == 48 and np.allclose(band[[0, -1]], ends, atol=1e-4)
        along = (band - ends[0]) @ (ends[1] - ends[0]) / np.sum((ends[1] - ends[0]) ** 2)
        assert np.allclose(band, ends[0] + along[:, None] * (ends[1] - ends[0]), atol=1e-4)
    finally:
        view.close()
