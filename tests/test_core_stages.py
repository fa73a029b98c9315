"""The stages that came out of the pipeline (motion model, relocalizer, keyframe culler) on their own,
against exact poses and the synthetic scene's ground truth; and the state value they work on."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from slamkit.config import SlamConfig
from slamkit.errors import ConfigError
from slamkit.eval.align import estimate_alignment
from slamkit.features import image_signature
from slamkit.geometry import flow_score
from slamkit.pipeline import Slam
from slamkit.sources import open_source
from slamkit.stages.culling import KeyframeCuller, KeyframeCullingConfig, keyframe_redundancy
from slamkit.stages.motion import MotionModel, MotionModelConfig
from slamkit.stages.relocalizer import Relocalizer, RelocalizerConfig
from slamkit.state import FrameRecord, FrameStatus

SPEC = "synthetic:handheld?frames=120&noise=1"


def _twist(w, v) -> np.ndarray:
    xi = np.zeros((4, 4))
    xi[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    xi[:3, 3] = v
    return xi


# ----------------------------------------------------------------------------------------------- motion model
def test_motion_model_predicts_constant_velocity_exactly():
    velocity = scipy.linalg.expm(_twist([0.01, -0.02, 0.005], [0.03, 0.0, -0.01]))
    start = scipy.linalg.expm(_twist([0.3, 0.1, -0.2], [1.0, 2.0, 0.5]))
    poses = [np.linalg.matrix_power(velocity, k) @ start for k in range(6)]
    records = [FrameRecord(k, k, 0.1 * k, FrameStatus.TRACKED, segment=0, rel_pose=poses[k]) for k in range(6)]
    model = MotionModel()
    pred = model.step(records, 5, 0, lambda r: r.rel_pose)
    assert pred.kind == "constant velocity" and pred.frames == (4, 3)
    np.testing.assert_allclose(pred.cam_from_world, poses[5], atol=1e-12)
    # a gap between the two posed frames (frame 3 lost): the last pose, not a velocity over two frames
    records[3] = FrameRecord(3, 3, 0.3, FrameStatus.LOST, segment=0)
    pred = model.step(records, 5, 0, lambda r: r.rel_pose)
    assert pred.kind == "last pose" and pred.frames == (4, 2) and np.array_equal(pred.cam_from_world, poses[4])
    # frames of another segment predict nothing; a frame lost before this segment began stops the search
    assert model.step(records, 5, 1, lambda r: r.rel_pose).cam_from_world is None
    records[4] = FrameRecord(4, 4, 0.4, FrameStatus.LOST, segment=-1)
    assert model.step(records, 5, 0, lambda r: r.rel_pose).kind == "none"
    # one posed frame: its pose; posed frames further back than max_gap: nothing
    records[4] = FrameRecord(4, 4, 0.4, FrameStatus.TRACKED, segment=0, rel_pose=poses[4])
    records[2] = FrameRecord(2, 2, 0.2, FrameStatus.SKIPPED, segment=-1)
    pred = MotionModel(MotionModelConfig(max_gap=2)).step(records, 5, 0, lambda r: r.rel_pose)
    assert pred.kind == "last pose" and pred.frames == (4,) and np.array_equal(pred.cam_from_world, poses[4])
    records[4] = FrameRecord(4, 4, 0.4, FrameStatus.SKIPPED, segment=-1)
    assert MotionModel(MotionModelConfig(max_gap=2)).step(records[:5], 7, 0, lambda r: r.rel_pose).kind == "none"
    with pytest.raises(ConfigError, match="max_gap"):
        MotionModel(MotionModelConfig(max_gap=0))


def test_frame_status_is_a_string():
    rec = FrameRecord(0, 0, 0.0, "tracked")
    assert rec.status is FrameStatus.TRACKED and rec.status == "tracked"
    assert f"[{rec.status}]" == "[tracked]" and str(FrameStatus.ERROR) == "error"
    with pytest.raises(ValueError):
        FrameRecord(0, 0, 0.0, "posed")


# ----------------------------------------------------------------------------------------------- a mapped room
@pytest.fixture(scope="module")
def mapped():
    """The hand-held room sequence mapped without culling (so redundant keyframes remain)."""
    slam = Slam(open_source(SPEC), SlamConfig().with_overrides(**{"keyframes.cull_redundant": 0.0}))
    results = slam.run()
    assert slam.summary()["fraction_posed"] > 0.95 and slam.summary()["keyframes_culled"] == 0
    return slam, results


def test_relocalizer_finds_a_frame_at_the_right_keyframe_near_ground_truth(mapped):
    slam, _ = mapped
    src, slam_map = slam.source, slam.slam_map
    kf_frames = {iid: kf.frame_index for iid, kf in slam_map.keyframes.items()}
    signatures = {iid: image_signature(src[int(slam.indices[i])].gray) for iid, i in kf_frames.items()}
    query = 70  # a frame between keyframes, mapped long before the end of the run
    ff = slam.loader.load(query)[1]
    reloc = Relocalizer(RelocalizerConfig(candidates=3))
    res = reloc.step(ff, slam_map, signatures, last=-1, tracker=slam.tracker)
    assert res.relocalized, res.reason
    # the right keyframe: the one whose view is most like the frame's, taken near it in the sequence
    best = max(signatures, key=lambda i: float(signatures[i] @ ff.signature))
    assert res.keyframe == best == res.tried[0] and abs(kf_frames[res.keyframe] - query) <= 10
    assert res.local_map.ref_image_id == res.keyframe and res.tracking.num_inliers >= 50
    # the pose near ground truth: keyframe centres aligned to the ground truth (Sim(3)), then compared
    ids = sorted(kf_frames)
    est = np.array([slam_map.reconstruction.image(i).projection_center() for i in ids])
    gt = np.array([src.gt_poses[int(slam.indices[kf_frames[i]])][:3, 3] for i in ids])
    a = estimate_alignment(est, gt)
    centre = -res.tracking.cam_from_world[:3, :3].T @ res.tracking.cam_from_world[:3, 3]
    found = a.scale * a.rotation @ centre + a.translation
    assert np.linalg.norm(found - src.gt_poses[int(slam.indices[query])][:3, 3]) < 0.02  # metres
    # an image of nothing the map has seen is not relocalized; no candidates: skipped
    noise = ff.__class__(ff.index, ff.frame_id, ff.timestamp, ff.features, ff.keypoints[::-1].copy(), ff.colors,
                         signature=ff.signature)
    assert not reloc.step(noise, slam_map, signatures, last=-1, tracker=slam.tracker).relocalized
    off = Relocalizer(RelocalizerConfig(candidates=0)).step(ff, slam_map, signatures, -1, slam.tracker)
    assert off.status == "skipped"


def test_culler_removes_a_redundant_keyframe_and_its_frames_keep_their_poses(mapped):
    slam, _ = mapped
    state, seg = slam.state, slam.main_segment
    slam_map = seg.slam_map
    config = KeyframeCullingConfig(redundant=0.9, min_observers=3, keep_recent=5, window=6)
    culler = KeyframeCuller(config)
    before = {r.index: state.pose_of(r) for r in state.records if r.rel_pose is not None and r.segment == seg.id}
    redundancy = {i: keyframe_redundancy(slam_map, i, 3) for i in slam_map.keyframes}
    culled = []
    for iid in sorted(slam_map.keyframes, reverse=True):  # newest first, as new keyframes would come
        if iid not in slam_map.keyframes:
            continue
        res = culler.step(slam_map, iid)
        for c in res.culled:
            state.reanchor(seg, c.image_id, c.anchor, c.culled_from_anchor)
        culled += res.culled
        if len(culled) >= 2:
            break
    assert culled, "no redundant keyframe in a room revisited for 120 frames"
    ids = sorted(redundancy)
    for k, c in enumerate(culled):
        assert redundancy[c.image_id] >= 0.9 and c.image_id not in slam_map.keyframes
        # anchored to a keyframe still in the map then (it may be culled later: its frames move on with it)
        assert c.image_id not in ids[:2] and c.anchor in ids and c.anchor not in [d.image_id for d in culled[:k]]
        assert slam_map.reconstruction.image(c.image_id).num_points3D == 0
    after = {i: state.pose_of(i) for i in before}
    assert max(np.abs(after[i] - before[i]).max() for i in before) < 1e-9
    assert all(state.records[i].ref_image_id in slam_map.keyframes for i in before)
    assert not any(state.records[i].keyframe_image_id == c.image_id for i in before for c in culled)


def test_step_results_carry_the_flow_score_matches(mapped):
    slam, results = mapped
    tracked = [r for r in results if r.status == "tracked"]
    assert len(tracked) > 50
    for r in tracked:
        ref, cur = r.tracked.flow_lines()
        assert len(ref) == len(cur) == r.matches and int(r.tracked.inliers.sum()) == r.inliers
        assert r.reference_keyframe > 0
        if len(ref):  # the very matches of the flow score (stored as float32 pixels)
            assert flow_score(ref, cur, slam.camera.fx, slam.camera.fy) == pytest.approx(r.flow, rel=1e-4, abs=1e-7)
    assert all(len(r.tracked) == 0 for r in results if r.status != "tracked")
