"""The camera paths of slamkit.sources.motions: exact properties of the hard motions of issue 17 (yaw rate,
jump sizes), valid rotations, reproducible seeds, and the re-exports of slamkit.sources.synthetic."""

import math

import numpy as np
import pytest

from slamkit.errors import ConfigError
from slamkit.sources import motions, open_source, synthetic
from slamkit.sources.motions import HARD_MOTIONS, MOTIONS, fast_forward, fast_yaw, forward, fast_yaw_angles, handheld, handheld_pan, jerk_frames, jerky
from slamkit.sources.scene import BOXES, ROOM_X, ROOM_Y, ROOM_Z, default_room
from slamkit.sources.synthetic import DEFAULT_CAMERA


def _angle_deg(R: np.ndarray) -> float:
    """Rotation angle of R in degrees (atan2 form: exact near zero, where acos is not)."""
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2
    return math.degrees(math.atan2(s, (np.trace(R) - 1) / 2))


def _relative(poses: np.ndarray) -> np.ndarray:
    """(N-1, 4, 4) motion of each frame relative to the previous one (camera i-1 from camera i)."""
    return np.linalg.inv(poses[:-1]) @ poses[1:]


@pytest.mark.parametrize("name", sorted(MOTIONS))
def test_every_motion_gives_rigid_poses_inside_the_room(name):
    poses = MOTIONS[name](60)
    assert poses.shape == (60, 4, 4)
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_array_equal(poses[:, 3], np.broadcast_to([0, 0, 0, 1], (60, 4)))
    c = poses[:, :3, 3]
    assert (np.abs(c[:, 0]) < ROOM_X - 0.5).all() and (np.abs(c[:, 1]) < ROOM_Y - 0.5).all()
    assert ((c[:, 2] > 1.0) & (c[:, 2] < ROOM_Z - 0.5)).all()
    for box, (bx, by, sx, sy, h) in BOXES.items():  # clear of the furniture
        dx, dy = np.maximum(np.abs(c[:, 0] - bx) - sx / 2, 0), np.maximum(np.abs(c[:, 1] - by) - sy / 2, 0)
        assert (np.sqrt(dx**2 + dy**2 + np.maximum(c[:, 2] - h, 0) ** 2) > 0.2).all(), box


@pytest.mark.parametrize("name", HARD_MOTIONS)
def test_hard_motions_see_textured_surfaces_everywhere(name):
    room, small = default_room(), DEFAULT_CAMERA.scaled(0.125)
    for T in MOTIONS[name]()[::7]:
        assert np.isfinite(room.depth(T, small)).all()


def test_synthetic_reexports_the_motions():
    for name in ("MOTIONS", "sideways", "forward", "orbit", "rotation", "translate_then_rotate", "loop",
                 "handheld", "default_motion", "DEFAULT_FRAMES"):
        assert getattr(synthetic, name) is getattr(motions, name)


@pytest.mark.parametrize("yaw_rate, turn, hold", [(8.0, 80.0, 10), (5.0, 60.0, 3), (10.0, 45.0, 0)])
def test_fast_yaw_turns_at_exactly_the_yaw_rate(yaw_rate, turn, hold):
    n = 150
    poses = fast_yaw(n, yaw_rate=yaw_rate, turn=turn, hold=hold)
    steps = np.array([_angle_deg(T[:3, :3]) for T in _relative(poses)])
    yaw = fast_yaw_angles(n, yaw_rate, turn, hold)
    np.testing.assert_allclose(steps, np.abs(np.diff(yaw)), atol=1e-9)
    assert steps.max() == pytest.approx(yaw_rate, abs=1e-9)
    assert np.isclose(steps, yaw_rate, atol=1e-6).sum() >= n // 3  # most of the time spent turning fast
    assert yaw.max() == pytest.approx(turn / 2) and yaw.min() == pytest.approx(-turn / 2)
    # the heading swings about the front wall (+y), with the camera's right axis horizontal
    gaze = poses[:, :3, 2]
    np.testing.assert_allclose(np.degrees(np.arctan2(-gaze[:, 0], gaze[:, 1])), yaw, atol=1e-9)
    np.testing.assert_allclose(poses[:, 2, 0], 0.0, atol=1e-12)
    # while walking slowly: centre steps never exceed the speed
    assert np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).max() <= 0.01 * math.pi / 2 + 1e-12


def test_fast_yaw_holds_between_turns():
    yaw = fast_yaw_angles(60, 8.0, 80.0, 10)
    np.testing.assert_array_equal(yaw[:11], 0.0)  # hold frames 1-10, then turn
    np.testing.assert_allclose(yaw[11:16], [8, 16, 24, 32, 40])  # +40 reached in 5 steps
    np.testing.assert_array_equal(yaw[16:26], 40.0)
    assert yaw[26] == 32.0


@pytest.mark.parametrize("seed", [0, 3])
def test_jerky_jumps_are_several_frames_of_motion_in_one(seed):
    n, jumps, jump, speed = 120, 3, 8, 0.02
    poses = jerky(n, speed=speed, jumps=jumps, jump=jump, seed=seed)
    base = handheld(n + jumps * (jump - 1), speed=speed, seed=seed)
    at = jerk_frames(n, jumps)
    np.testing.assert_array_equal(at, [30, 60, 90])
    # every frame is a pose of the smooth path; a jerk skips jump - 1 of its frames
    k = 0
    for i in range(n):
        k += 0 if i == 0 else (jump if i in at else 1)
        np.testing.assert_array_equal(poses[i], base[k])
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    rot = np.array([_angle_deg(T[:3, :3]) for T in _relative(poses)])
    smooth = np.delete(np.arange(n - 1), at - 1)
    assert step[at - 1].min() > 3 * np.median(step[smooth])
    assert rot[at - 1].min() > 3 * np.median(rot[smooth])
    np.testing.assert_allclose(step[at - 1], np.linalg.norm(base[at + np.arange(1, jumps + 1) * (jump - 1), :3, 3]
                                                            - base[at + np.arange(jumps) * (jump - 1) - 1, :3, 3], axis=1))


@pytest.mark.parametrize("speed", [0.15, 0.3])
def test_fast_forward_moves_along_the_optical_axis_at_speed(speed):
    n = 80
    poses, straight = fast_forward(n, speed=speed, weave=0.4), forward(n, speed=speed)
    np.testing.assert_array_equal(poses[:, :3, :3], straight[:, :3, :3])  # the gaze of forward
    np.testing.assert_array_equal(poses[:, 1:3, 3], straight[:, 1:3, 3])
    np.testing.assert_allclose(poses[:, 0, 3], 0.2 + 0.4 * np.sin(2 * np.pi * np.arange(n) / (n - 1)), atol=1e-15)
    dy = np.abs(np.diff(poses[:, 1, 3]))
    assert dy.mean() == pytest.approx(speed, rel=0.1) and dy.max() <= speed * np.pi / 2 + 1e-12
    # the motion is mostly along the optical axis: camera z is the main component of every step
    steps = np.einsum("nji,nj->ni", poses[:-1, :3, :3], np.diff(poses[:, :3, 3], axis=0))
    moving = np.linalg.norm(steps, axis=1) > speed / 2
    assert moving.sum() > n / 2
    assert (np.abs(steps[moving, 2]) > 0.9 * np.linalg.norm(steps[moving], axis=1)).all()
    # not a line: a Sim(3) alignment is defined
    assert np.linalg.svd(poses[:, :3, 3] - poses[:, :3, 3].mean(0), compute_uv=False)[1] > 0.1


@pytest.mark.parametrize("shake", [0.0, 0.03, 0.1])
def test_a_handheld_pan_turns_about_a_centre_the_hand_moves_by_at_most_twice_its_shake(shake):
    poses = handheld_pan(150, amplitude=35.0, shake=shake, seed=3)
    c = poses[:, :3, 3]
    assert np.abs(c - c[0]).max() <= 2 * shake + 1e-12
    if shake:
        assert np.abs(c - c[0]).max() > 0.2 * shake  # the hand does move
    axis = poses[:, :3, 2]  # the optical axis in the world
    heading = np.degrees(np.arctan2(-axis[:, 0], axis[:, 1]))
    assert 2 * 35.0 - 6.0 <= np.ptp(heading) <= 2 * 35.0 + 6.0  # +-amplitude with up to 3 degrees of wobble
    np.testing.assert_array_equal(poses, handheld_pan(150, amplitude=35.0, shake=shake, seed=3))


def test_seeds_are_reproducible_and_differ():
    np.testing.assert_array_equal(jerky(80, seed=4), jerky(80, seed=4))
    assert not np.allclose(jerky(80, seed=4), jerky(80, seed=5))
    np.testing.assert_array_equal(fast_yaw(50), fast_yaw(50))


def test_hard_motions_by_spec():
    src = open_source("synthetic:jerky?frames=40&seed=2&jumps=2&jump=6")
    np.testing.assert_array_equal(src.gt_poses, jerky(40, jumps=2, jump=6, seed=2))
    src = open_source("synthetic:fast-yaw?frames=30&yaw_rate=6&turn=30&hold=2")
    np.testing.assert_array_equal(src.gt_poses, fast_yaw(30, yaw_rate=6, turn=30, hold=2))
    # fast forward (KITTI at skip 2-3 has a median flow of tens of pixels): 0.25 m per frame in the room
    fast = open_source("synthetic:fast-forward?frames=12")
    assert 15 < np.median([np.median(fast.flow(i)) for i in range(len(fast) - 1)]) < 60
    turning = open_source("synthetic:fast-yaw?frames=8&hold=0&yaw_rate=8")
    assert np.median(turning.flow(2)) == pytest.approx(500 * math.radians(8), rel=0.15)


@pytest.mark.parametrize("spec, what", [
    ("synthetic:fast-yaw?yaw_rate=40", "yaw_rate"), ("synthetic:fast-yaw?hold=1.5", "hold"),
    ("synthetic:jerky?jump=0", "jump"), ("synthetic:jerky?frames=5&jumps=9", "jumps"),
    ("synthetic:jerky?yaw_rate=3", "yaw_rate"), ("synthetic:fast-forward?weave=2", "weave")])
def test_bad_hard_motion_parameters(spec, what):
    with pytest.raises(ConfigError, match=what):
        open_source(spec)
