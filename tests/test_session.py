"""Sessions and interruptions: save mid-run, resume in a fresh Slam (or process), compare with an uninterrupted
run; Ctrl-C in ``slamkit run``; a failing frame source or stage loses nothing before it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from slamkit.config import SlamConfig
from slamkit.errors import ConfigError
from slamkit.eval import ate
from slamkit.io import read_tum
from slamkit.pipeline import Slam
from slamkit.session import SessionError, _max_point3D_id, find_session, save_session
from slamkit.sources import open_source
from slamkit.sources.base import FrameSource
from slamkit.stages.local_mapper import LocalMapper
from slamkit.stages.mapper import Mapper

pycolmap.logging.minloglevel = 2

SPEC = "synthetic:handheld?frames=60&noise=1"
OPTIONS = {"init_frames": 10, "ba.global_min_keyframes": 4}
"""A short sequence with initialization, local and global BA (with normalization) in 60 frames."""
CONFIG = SlamConfig().with_overrides(**OPTIONS)
ATE_BOUND = 0.01
"""metres: the bound of the uninterrupted run (tests/test_pipeline.py), for resumed runs too."""


@pytest.fixture(scope="module")
def uninterrupted():
    slam = Slam(SPEC, CONFIG)
    results = slam.run()
    assert ate(slam.source.ground_truth(), slam.trajectory()).rmse < ATE_BOUND
    return slam, results


# ----------------------------------------------------------------------------------------------- helpers
def _same_features(fa, fb) -> None:
    for name in ("keypoints", "descriptors", "scores", "sizes"):
        x, y = getattr(fa, name), getattr(fb, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert fa.binary == fb.binary and fa.image_size == fb.image_size


def _same_arrays(x, y, what) -> None:
    assert (x is None) == (y is None), what
    if x is not None:
        assert np.asarray(x).dtype == np.asarray(y).dtype and np.array_equal(x, y), what


def _same_frame_features(a: list, b: list) -> None:
    assert [f.index for f in a] == [f.index for f in b]
    for fa, fb in zip(a, b):
        assert (fa.frame_id, fa.timestamp) == (fb.frame_id, fb.timestamp)
        _same_features(fa.features, fb.features)
        for name in ("keypoints", "colors", "thumbnail", "signature"):
            _same_arrays(getattr(fa, name), getattr(fb, name), name)


def _graph_lists(slam_map) -> dict:
    g, rec = slam_map.graph, slam_map.reconstruction
    return {(i, j): [(c.image_id, c.point2D_idx) for c in g.extract_correspondences(i, j)]
            for i in rec.images for j in range(rec.image(i).num_points2D())}


def _same_map(ma, mb) -> None:
    ra, rb = ma.reconstruction, mb.reconstruction
    assert ra.reg_frame_ids() == rb.reg_frame_ids()
    assert sorted(ra.images) == sorted(rb.images)
    assert np.array_equal(ra.camera(1).params, rb.camera(1).params)
    for i in ra.images:
        ia, ib = ra.image(i), rb.image(i)
        assert ia.name == ib.name and ia.has_pose == ib.has_pose
        if ia.has_pose:
            assert np.array_equal(ia.cam_from_world().matrix(), ib.cam_from_world().matrix())
        assert np.array_equal([p.xy for p in ia.points2D], [p.xy for p in ib.points2D])
        assert [p.point3D_id for p in ia.points2D] == [p.point3D_id for p in ib.points2D]
    assert sorted(ra.points3D) == sorted(rb.points3D)
    for p in ra.points3D:
        pa, pb = ra.point3D(p), rb.point3D(p)
        assert np.array_equal(pa.xyz, pb.xyz) and np.array_equal(pa.color, pb.color) and pa.error == pb.error
        assert [(e.image_id, e.point2D_idx) for e in pa.track.elements] == \
               [(e.image_id, e.point2D_idx) for e in pb.track.elements]
    assert _max_point3D_id(ra) == _max_point3D_id(rb)
    assert list(ma.keyframes) == list(mb.keyframes)
    for i, ka in ma.keyframes.items():
        kb = mb.keyframes[i]
        assert (ka.frame_index, ka.timestamp) == (kb.frame_index, kb.timestamp)
        _same_features(ka.features, kb.features)
        for name in ("keypoints", "colors", "thumbnail"):
            _same_arrays(getattr(ka, name), getattr(kb, name), name)
    assert _graph_lists(ma) == _graph_lists(mb)  # every keypoint's correspondences, in the same order
    assert ma.triangulator.get_modified_points3D() == mb.triangulator.get_modified_points3D()
    assert ma._next_image_id == mb._next_image_id
    assert ma.triangulation.todict() == mb.triangulation.todict()


def assert_same_state(a: Slam, b: Slam) -> None:
    """Everything the pipeline holds, compared exactly."""
    for name in ("_cursor", "last_keyframe", "_points_at_last_keyframe", "_consecutive_lost", "finished",
                 "wall_time", "cpu_time", "timings", "errors"):
        assert getattr(a, name) == getattr(b, name), name
    assert a.config == b.config and np.array_equal(a.indices, b.indices)
    assert len(a.records) == len(b.records)
    for ra, rb in zip(a.records, b.records):
        for name, va in vars(ra).items():
            vb = getattr(rb, name)
            if isinstance(va, np.ndarray) or isinstance(vb, np.ndarray):
                _same_arrays(va, vb, f"frame {ra.index} {name}")
            else:
                assert va == vb, f"frame {ra.index} {name}"
    assert (a.segment and a.segment.id) == (b.segment and b.segment.id)
    assert len(a.segments) == len(b.segments)
    for sa, sb in zip(a.segments, b.segments):
        assert (sa.id, sa.frames, sa.relocalizations) == (sb.id, sb.frames, sb.relocalizations)
        assert list(sa.signatures) == list(sb.signatures)
        for i in sa.signatures:
            _same_arrays(sa.signatures[i], sb.signatures[i], "signature")
        _same_frame_features(sa.initial_frames, sb.initial_frames)
        _same_map(sa.slam_map, sb.slam_map)
    assert (a.local_map is None) == (b.local_map is None)
    if a.local_map is not None:
        for name in ("ids", "xyz", "descriptors", "ref_ids", "ref_xy"):
            _same_arrays(getattr(a.local_map, name), getattr(b.local_map, name), f"local map {name}")
        assert (a.local_map.binary, a.local_map.ref_image_id, a.local_map.keyframe_ids) == \
               (b.local_map.binary, b.local_map.ref_image_id, b.local_map.keyframe_ids)
    _same_arrays(a._last_ids, b._last_ids, "last tracked ids")
    _same_frame_features(a.initializer.frames, b.initializer.frames)
    _same_frame_features(a.initializer.history, b.initializer.history)
    assert list(a.initializer._matches) == list(b.initializer._matches)
    for k, m in a.initializer._matches.items():
        _same_arrays(m, b.initializer._matches[k], f"window matches {k}")
    assert a.bundle_adjuster._keyframes_at_last_global == b.bundle_adjuster._keyframes_at_last_global
    assert sorted(a.pose_refiner.tracked) == sorted(b.pose_refiner.tracked)
    for i, oa in a.pose_refiner.tracked.items():
        ob = b.pose_refiner.tracked[i]
        assert (oa.segment, oa.distortion) == (ob.segment, ob.distortion), f"frame {i} correspondences"
        _same_arrays(oa.xy, ob.xy, f"frame {i} correspondences")
        _same_arrays(oa.point3D_ids, ob.point3D_ids, f"frame {i} correspondences")


# ----------------------------------------------------------------------------------------------- resume
def test_resumed_runs_are_bit_identical_to_the_uninterrupted_run(tmp_path, uninterrupted):
    """Interrupted four times — while collecting initialization frames, right after initialization (tracks
    awaiting their first bundle adjustment), between keyframes, near the end — each time saved, rebuilt in a
    fresh Slam and compared field by field with the Slam it was saved from; the final trajectory equals the
    uninterrupted one bit for bit."""
    full, results = uninterrupted
    init = next(r.frame_index for r in results if r.status == "initialized")
    cuts = [5, init + 1, init + 14, len(full) - 3]
    slam = Slam(SPEC, CONFIG)
    done = 0
    for k, cut in enumerate(cuts):
        slam.run(max_steps=cut - done)
        done = cut
        folder = tmp_path / f"cut{cut}"
        if k % 2:
            save_session(slam, folder)       # the session alone
        else:
            slam.save(folder)                # a run folder with its session/
        resumed = Slam.resume(folder)
        assert resumed is not slam and resumed._cursor == cut
        assert_same_state(slam, resumed)
        slam = resumed
    slam.run()
    a, b = full.trajectory(), slam.trajectory()
    np.testing.assert_array_equal(a.timestamps, b.timestamps)
    np.testing.assert_array_equal(a.poses, b.poses)    # max pose difference 0: bit-identical
    assert slam.summary()["keyframes"] == full.summary()["keyframes"]
    assert slam.summary()["points3D"] == full.summary()["points3D"]
    assert ate(slam.source.ground_truth(), b).rmse < ATE_BOUND


def test_resume_with_two_map_segments(tmp_path):
    """Tracking lost for good (unrelated frames 34-39) starts a second segment: saved while the new segment
    initializes and while it tracks, resumed, identical (state, then every segment's trajectory)."""
    from test_pipeline import _Interrupted

    src = _Interrupted(open_source("synthetic:handheld?frames=80&noise=1"), range(34, 40), "unrelated")
    config = SlamConfig(max_lost_frames=3).with_overrides(**OPTIONS)
    slam = Slam(src, config)
    resumed = None
    for cut in (45, 72):
        slam.run(max_steps=cut - len(slam.records))
        slam.save(tmp_path / f"cut{cut}")
        resumed = Slam.resume(tmp_path / f"cut{cut}", source=src)
        assert_same_state(slam, resumed)
        assert (slam.segment is None) == (cut == 45)
    slam.run()
    resumed.run()
    assert len(slam.segments) == len(resumed.segments) == 2
    for seg in slam.segments:
        np.testing.assert_array_equal(slam.trajectory(segment=seg.id).poses, resumed.trajectory(segment=seg.id).poses)
        assert ate(src.source.ground_truth(), resumed.trajectory(segment=seg.id)).rmse < 0.02


def test_a_finished_run_extended_with_resume_equals_the_longer_run(tmp_path, uninterrupted):
    """Issue 28: a *finished* 40-frame run (final global BA, frames re-tracked) saved, then resumed to 60
    frames, gives the uninterrupted 60-frame run bit for bit: the session holds the state before finish()."""
    full = uninterrupted[0]
    short = Slam(SPEC, CONFIG.with_overrides(max_frames=40))
    short.run()
    assert short.finished
    short.save(tmp_path / "run40")
    meta = json.loads((tmp_path / "run40" / "session" / "session.json").read_text())
    assert meta["finished"] is True and meta["state"]["finished"] is False
    as_saved = Slam.resume(tmp_path / "run40")  # the same frames: finished again on load, as it was saved
    assert as_saved.finished
    np.testing.assert_array_equal(as_saved.trajectory().poses, short.trajectory().poses)
    longer = Slam.resume(tmp_path / "run40", config={"max_frames": 60})
    assert not longer.finished and longer._cursor == 40
    longer.run()
    np.testing.assert_array_equal(longer.trajectory().timestamps, full.trajectory().timestamps)
    np.testing.assert_array_equal(longer.trajectory().poses, full.trajectory().poses)
    # a session of the finished state only (as older versions saved it) is refused in one line, not degraded
    short.unfinished_session = None
    short.save(tmp_path / "old40")
    with pytest.raises(SessionError, match=r"saved after its final bundle adjustment.*--max-frames 60") as e:
        Slam.resume(tmp_path / "old40", config={"max_frames": 60})
    assert "\n" not in str(e.value)


@pytest.fixture(scope="module")
def early_session(tmp_path_factory):
    """A session saved after 12 frames (still initializing) of a run limited to 12 frames."""
    slam = Slam(SPEC, CONFIG.with_overrides(max_frames=12))
    slam.run()
    out = tmp_path_factory.mktemp("early") / "run"
    slam.save(out)
    return out


def test_session_files_are_open_formats_without_pickle(early_session):
    folder = find_session(early_session)
    assert folder == early_session / "session"
    suffixes = {p.suffix for p in folder.rglob("*") if p.is_file()}
    assert suffixes <= {".json", ".npz", ".bin"}, suffixes
    for npz in folder.rglob("*.npz"):
        with np.load(npz, allow_pickle=False) as z:
            assert all(z[k].dtype != object for k in z.files)
    meta = json.loads((folder / "session.json").read_text())
    assert meta["format"] == "slamkit-session" and meta["source"]["spec"] == SPEC
    assert SlamConfig.from_dict(meta["config"]) == CONFIG.with_overrides(max_frames=12)


def test_resume_checks_source_and_config(early_session):
    with pytest.raises(SessionError, match=r"60 frames vs 70"):
        Slam.resume(early_session, source="synthetic:handheld?frames=70&noise=1")
    with pytest.raises(SessionError, match=r"name .*sideways"):
        Slam.resume(early_session, source="synthetic:sideways?frames=60")
    with pytest.raises(ConfigError, match=r"differs from the session's in .*seed"):
        Slam.resume(early_session, config=CONFIG.with_overrides(max_frames=12, seed=3))
    with pytest.raises(ConfigError, match="features cannot change"):
        Slam.resume(early_session, config={"features": "sift"})
    with pytest.raises(ConfigError, match="processed 12 frames"):
        Slam.resume(early_session, config={"max_frames": 5})
    with pytest.raises(SessionError, match="no session found"):
        Slam.resume(early_session / "sparse")
    # an explicit override continues the finished 12-frame run to the whole sequence
    slam = Slam.resume(early_session, config={"max_frames": 60, "tracker.min_inliers": 25})
    assert slam.config.tracker.min_inliers == 25 and len(slam) == 60 and not slam.finished
    r = slam.step()
    assert r.frame_index == 12 and len(slam.records) == 13


# ----------------------------------------------------------------------------------------------- interruption
class FlakySource(FrameSource):
    """A source whose frame ``fail_at`` cannot be read the first time it is asked for."""

    def __init__(self, source: FrameSource, fail_at: int):
        self.inner, self.fail_at, self.failed = source, fail_at, False
        self.name, self.camera = source.name, source.camera
        self.timestamps, self.frame_ids, self.gt_poses = source.timestamps, source.frame_ids, source.gt_poses

    def __getitem__(self, i):
        if i == self.fail_at and not self.failed:
            self.failed = True
            raise OSError(f"camera disconnected at frame {i}")
        return self.inner[i]


class FailingMapper(Mapper):
    """Inserts the keyframe into the map, then fails (the worst place: the map changed, the pipeline did not
    get to record it)."""

    def step(self, *args, **kwargs):
        super().step(*args, **kwargs)
        raise RuntimeError("injected mapper failure")


class FailingLocalMapper(LocalMapper):
    """The same failure in local mapping (``mapper.method = "local"``)."""

    def step(self, *args, **kwargs):
        super().step(*args, **kwargs)
        raise RuntimeError("injected mapper failure")


def _use_mapper(slam: Slam, failing: bool) -> None:
    """Give the pipeline the mapper its config uses, failing or not."""
    c = slam.config
    if c.mapper.method == "local":
        slam.local_mapper = (FailingLocalMapper if failing else LocalMapper)(c.local_mapping,
                                                                           c.mapper.min_keyframe_points)
    else:
        slam.mapper = (FailingMapper if failing else Mapper)(c.mapper)


def test_a_failing_source_or_stage_loses_nothing_before_it(tmp_path, uninterrupted):
    snapshots = {}
    slam = Slam(FlakySource(open_source(SPEC), fail_at=35), CONFIG,
                callbacks=[lambda s, r: snapshots.__setitem__(r.frame_index, s.trajectory())])
    with pytest.raises(OSError, match="camera disconnected") as info:
        slam.run()
    assert any("frame 35" in note for note in info.value.__notes__)
    rec = slam.records[35]
    assert rec.status == "error" and rec.rel_pose is None and "camera disconnected" in slam.errors[35]
    np.testing.assert_array_equal(slam.trajectory().poses, snapshots[34].poses)  # nothing lost or changed
    slam.save(tmp_path / "after_source_error")
    saved = tmp_path / "after_source_error"
    assert pycolmap.Reconstruction(str(saved / "sparse")).num_reg_images() == slam.summary()["keyframes"]
    assert len(read_tum(saved / "trajectory_tum.txt")) == len(slam.trajectory()) >= 30
    assert "camera disconnected" in (saved / "frames.csv").read_text().splitlines()[36]

    _use_mapper(slam, failing=True)
    with pytest.raises(RuntimeError, match="injected") as info:
        while True:
            slam.step()
    k = slam.records[-1].index
    assert any(f"frame {k}" in note for note in info.value.__notes__)
    assert slam.records[k].status == "error" and "injected" in slam.errors[k]
    np.testing.assert_array_equal(slam.trajectory().poses, snapshots[k - 1].poses)
    _use_mapper(slam, failing=False)
    slam.save(tmp_path / "after_stage_error")   # saves, and resumes: the state is consistent
    slam = Slam.resume(tmp_path / "after_stage_error", source=slam.source)
    slam.run()
    assert {r.index for r in slam.records if r.status == "error"} == {35, k}
    assert sum(r.rel_pose is not None for r in slam.records) >= len(slam) - 2
    assert ate(slam.source.ground_truth(), slam.trajectory()).rmse < ATE_BOUND


@pytest.fixture
def sigint_raises():
    """Ctrl-C raises KeyboardInterrupt, as in a terminal or a kernel, even when the test run was started in the
    background by a non-interactive shell (which starts it with SIGINT ignored)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def _sigint_default() -> None:  # in the child, before exec: Python then installs its KeyboardInterrupt handler
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_during_a_step_waits_for_the_frame_to_finish(sigint_raises):
    def interrupt(times):
        def callback(slam, result):
            if result.frame_index == 2:
                for _ in range(times):
                    os.kill(os.getpid(), signal.SIGINT)
        return callback

    slam = Slam(SPEC, CONFIG, callbacks=[interrupt(1)])
    with pytest.raises(KeyboardInterrupt):
        slam.run()
    assert len(slam.records) == 3 and slam.last_result.frame_index == 2 and not slam.errors  # frame 2 complete
    assert slam.records[2].status == "initializing"
    slam.callbacks.clear()
    assert slam.step().frame_index == 3                   # and the run goes on
    # a second Ctrl-C does not wait: the frame (here, its callback) is cut short and says so; an interrupt is no
    # failure, so the frame is not recorded as an error
    slam = Slam(SPEC, CONFIG, callbacks=[interrupt(2)])
    with pytest.raises(KeyboardInterrupt) as e:
        slam.run()
    assert len(slam.records) == 3 and not slam.errors and slam.records[2].status == "initializing"
    assert "interrupted at frame 2" in " ".join(e.value.__notes__)


def _wait_for_line(stream, prefix: str, timeout: float) -> list[str]:
    lines, t0 = [], time.monotonic()
    for line in stream:
        lines.append(line)
        if line.startswith(prefix) or time.monotonic() - t0 > timeout:
            break
    return lines


def test_ctrl_c_in_slamkit_run_saves_a_readable_resumable_run(tmp_path, uninterrupted):
    from slamkit.cli import main

    out = tmp_path / "run"
    args = ["--init-frames", "10", "--set", "ba.global_min_keyframes=4"]
    proc = subprocess.Popen([sys.executable, "-m", "slamkit.cli", "run", SPEC, "--out", str(out), "-v", "-q", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"}, cwd=Path(__file__).parents[1],
                            preexec_fn=_sigint_default)
    try:
        lines = _wait_for_line(proc.stdout, "frame 30 [", timeout=600)
        assert lines and lines[-1].startswith("frame 30 ["), lines[-3:]
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=600)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted after frame" in err and "--resume" in err
    summary = json.loads((out / "summary.json").read_text())
    assert 31 <= summary["frames"] < 60
    assert pycolmap.Reconstruction(str(out / "sparse")).num_reg_images() == summary["keyframes"] >= 3
    assert len(read_tum(out / "trajectory_tum.txt")) == summary["frames_posed"]
    assert not list(tmp_path.glob(".run.*"))   # no temporary folders left behind
    # continue in this process (another process than the one that saved it) to the end
    assert main(["run", SPEC, "--out", str(out), "--resume", "-q"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 60 and SlamConfig.from_dict(summary["config"]) == CONFIG
    full = uninterrupted[0].trajectory()
    traj = read_tum(out / "trajectory_tum.txt")
    np.testing.assert_array_equal(traj.timestamps, full.timestamps)
    np.testing.assert_array_equal(traj.positions, full.positions)    # TUM files print exact float64 (repr)
    finished = Slam.resume(out)                                       # the final state, read back: exact too
    assert finished.done and finished.finished
    np.testing.assert_array_equal(finished.trajectory().poses, full.poses)
    assert ate(open_source(SPEC).ground_truth(), traj).rmse < ATE_BOUND


PAN = "synthetic:fast-yaw?frames=16&yaw_rate=15&turn=150&hold=0&noise=1&seed=0&scale=0.5"
"""Issue 50 item 8: a fast pan right after initialization (15 degrees per frame, 320x240): from frame 12 on each
frame is posed by its rotation to the frame before it (the last keyframe is too far behind)."""


def test_a_run_resumed_inside_a_rotation_phase_equals_the_uninterrupted_run(tmp_path):
    """Stopped in the middle of a pan whose frames are chained by rotation to the previous frame
    (``RotationPhase.previous``, DT-SLAM's 2-D-only keyframe), saved, resumed in a fresh Slam and run to the end:
    the same trajectory bit for bit as the run that went on without stopping (the resumed run lost the previous
    frame before: its next frame was lost)."""
    cut = 13
    full = Slam(PAN, SlamConfig().with_overrides(seed=0))
    full.run(max_steps=cut)
    assert full.records[cut - 1].motion_model == "rotation" and full.records[cut - 1].status == "tracked"
    assert full.rotation_phase.previous.index == cut - 1  # inside a rotation phase, chained to the frame before
    save_session(full, tmp_path / "pan")
    resumed = Slam.resume(tmp_path / "pan")
    assert_same_state(full, resumed)
    _same_frame_features([full.rotation_phase.previous], [resumed.rotation_phase.previous])
    ahead, rest = full.run(), resumed.run()  # the uninterrupted run goes on; the resumed one from the session
    assert ahead[0].message.startswith(f"rotation only against frame {cut - 1} ")  # needs the frame before the stop
    assert [r.message for r in rest] == [r.message for r in ahead]
    a, b = full.trajectory(), resumed.trajectory()
    assert len(full) == 16 and len(a) == len(b) >= 12
    assert np.array_equal(a.timestamps, b.timestamps) and np.array_equal(a.poses, b.poses)  # bit-identical
