"""Camera paths of the synthetic sequences: functions returning (N, 4, 4) camera-to-world poses inside the
default room (:func:`~slamkit.sources.scene.default_room`), registered by name in :data:`MOTIONS`.

World frame: z up, metres, floor at z = 0; poses are camera-to-world with OpenCV camera axes (x right,
y down, z forward). Every function takes the number of frames ``n`` first; random motions take a ``seed``
and are reproducible from it. Bad parameters raise ConfigError naming the parameter.
:mod:`slamkit.sources.synthetic` renders frames along these paths (``synthetic:<motion>?frames=N&seed=S``).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from ..errors import ConfigError
from .scene import ROOM_Y, look_at

DEFAULT_FRAMES = 360
"""Frames of the default sequence (and default length of :func:`default_motion`)."""


MAX_FRAMES = 100_000
"""The most frames a rendered motion may have (checked before its poses are allocated; an hour at 30 fps)."""


def _check_frames(n: int) -> int:
    if not (math.isfinite(n) and int(n) == n and 2 <= n <= MAX_FRAMES):
        raise ConfigError(f"frames must be an integer >= 2 and <= {MAX_FRAMES} (got {n:g})")
    return int(n)


def _check_positive(name: str, value: float) -> float:
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"{name} must be a positive number (got {value})")
    return float(value)


def _check_range(name: str, value: float, low: float, high: float, unit: str = "", open_low: bool = False
                 ) -> float:
    """``value`` is finite and in [low, high] (``open_low``: in (low, high]), else a ConfigError naming ``name``."""
    if not (math.isfinite(value) and (low < value if open_low else low <= value) and value <= high):
        raise ConfigError(f"{name} must be in {'(' if open_low else '['}{low:g}, {high:g}]{' ' + unit if unit else ''} "
                          f"(got {value})")
    return float(value)


def _travel(n: int, speed: float, length: float) -> np.ndarray:
    """(n,) distances along a path of ``length`` metres at ``speed`` metres per frame: straight through when
    the path is long enough, else back and forth with smooth (cosine) turns."""
    s = np.arange(n) * speed
    if s[-1] <= length:
        return s
    return 0.5 * length * (1.0 - np.cos(np.pi * s / length))


def _poses_looking_at(centers: np.ndarray, targets: np.ndarray, rolls: np.ndarray | None = None) -> np.ndarray:
    rolls = np.zeros(len(centers)) if rolls is None else rolls
    return np.stack([look_at(c, t, roll=r) for c, t, r in zip(centers, targets, rolls)])


def sideways(n: int = 120, speed: float = 0.015) -> np.ndarray:
    """Translation along x (parallel to the front wall, 3.2 m away), looking straight at the wall.

    ``speed`` metres per frame; the path is centred on x = 0 and at most 2.6 m long (longer motions go
    back and forth)."""
    n, speed = _check_frames(n), _check_positive("speed", speed)
    length = 2.6
    s = _travel(n, speed, length)
    x = s - 0.5 * min(s.max(), length)
    centers = np.stack([x, np.full(n, -1.0), np.full(n, 1.45)], axis=1)
    return _poses_looking_at(centers, centers + [0.0, 3.0, -0.15])


def forward(n: int = 120, speed: float = 0.015) -> np.ndarray:
    """Translation along the optical axis towards the front wall, from y = -1.7 m (at most 2.4 m long)."""
    n, speed = _check_frames(n), _check_positive("speed", speed)
    s = _travel(n, speed, 2.4)
    centers = np.stack([np.full(n, 0.2), -1.7 + s, np.full(n, 1.4)], axis=1)
    return _poses_looking_at(centers, centers + [0.0, 3.0, -0.35])


def orbit(n: int = 240, speed: float = 0.015, radius: float = 1.0) -> np.ndarray:
    """Circle of ``radius`` metres (1.45 m high) around the cube in the middle of the room, looking at the
    cube; starts south of it and turns counter-clockwise at ``speed`` metres per frame."""
    n, speed = _check_frames(n), _check_positive("speed", speed)
    radius = _check_positive("radius", radius)
    if radius > 1.1:
        raise ConfigError(f"radius must be <= 1.1 m to stay clear of the furniture (got {radius})")
    centre = np.array([-0.3, 0.2])
    theta = -np.pi / 2 + np.arange(n) * speed / radius
    centers = np.stack([centre[0] + radius * np.cos(theta), centre[1] + radius * np.sin(theta),
                        np.full(n, 1.45)], axis=1)
    targets = np.tile([centre[0], centre[1], 0.8], (n, 1))
    return _poses_looking_at(centers, targets)


def rotation(n: int = 150, amplitude: float = 40.0) -> np.ndarray:
    """Pure rotation in place (zero baseline): the camera pans +-``amplitude`` degrees (one sine period)
    and tilts a little, standing at (0, -1, 1.45)."""
    n = _check_frames(n)
    amplitude = _check_positive("amplitude", amplitude)
    if amplitude > 80:
        raise ConfigError(f"amplitude must be <= 80 degrees (got {amplitude})")
    phase = 2 * np.pi * np.arange(n) / (n - 1)
    yaw = np.radians(amplitude) * np.sin(phase)
    pitch = np.radians(-4.0 + 6.0 * np.sin(2 * phase))
    c = np.array([0.0, -1.0, 1.45])
    dirs = np.stack([np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)], axis=1)
    return _poses_looking_at(np.tile(c, (n, 1)), c + dirs)


def translate_then_rotate(n: int = 150, translation: int = 40, speed: float = 0.015,
                          amplitude: float = 25.0) -> np.ndarray:
    """Degenerate motion after a good start: the first ``translation`` frames move sideways (as
    :func:`sideways`, ``speed`` metres per frame, from x = -0.3 m) looking at the front wall, then the camera
    stops and rotates in place (zero baseline): it pans +-``amplitude`` degrees (one sine period) and tilts
    a little. Frames ``translation - 1`` to ``n - 1`` share one camera centre."""
    n, speed = _check_frames(n), _check_positive("speed", speed)
    amplitude = _check_positive("amplitude", amplitude)
    if int(translation) != translation or not 2 <= translation < n:
        raise ConfigError(f"translation must be an integer number of frames in [2, frames) (got {translation})")
    if amplitude > 60:
        raise ConfigError(f"amplitude must be <= 60 degrees (got {amplitude})")
    if (translation - 1) * speed > 1.5:
        raise ConfigError(f"translation x speed must be <= 1.5 m to stay in the room (got "
                          f"{(translation - 1) * speed:g} m)")
    t = int(translation)
    gaze = np.array([0.0, 3.0, -0.15])
    centers = np.stack([-0.3 + np.arange(t) * speed, np.full(t, -1.0), np.full(t, 1.45)], axis=1)
    moving = _poses_looking_at(centers, centers + gaze)
    m = n - t + 1  # rotation frames, the first of which is the last translation frame
    phase = 2 * np.pi * np.arange(m) / (m - 1)
    yaw = np.radians(amplitude) * np.sin(phase)
    pitch = math.atan2(gaze[2], gaze[1]) + np.radians(3.0) * np.sin(2 * phase)
    dirs = np.stack([np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)], axis=1)
    c = centers[-1]
    turning = _poses_looking_at(np.tile(c, (m, 1)), c + dirs)
    return np.concatenate([moving, turning[1:]])


def _periodic_noise(n: int, rng: np.random.Generator, amplitude: float, cycles: tuple[int, int],
                    terms: int = 4) -> np.ndarray:
    """(n,) smooth random signal, a sum of ``terms`` sinusoids with whole numbers of periods over the n
    frames (so it returns to its first value on the last frame), peak at most ``amplitude``."""
    i = np.arange(n) / (n - 1)
    k = rng.integers(cycles[0], cycles[1] + 1, terms)
    ph = rng.uniform(0, 2 * np.pi, terms)
    w = rng.uniform(0.5, 1.0, terms)
    w *= amplitude / w.sum()
    return (w[:, None] * (np.sin(2 * np.pi * k[:, None] * i + ph[:, None]) - np.sin(ph[:, None]))).sum(0) / 2


def loop(n: int = 240, jitter: float = 0.0, seed: int = 0, laps: int = 1) -> np.ndarray:
    """A closed loop: an ellipse (2.4 m x 1 m, 1.45 m high) in the back half of the room, starting with a
    sideways move, looking at the front half while the gaze sweeps left and right. The last pose equals the
    first. ``jitter`` (0..2) adds periodic hand-held shake: about 3 cm, 0.1 m of gaze and 1.5 degrees of roll
    per unit, drawn from ``seed``. ``laps`` (>= 1): times the ellipse is driven round in the n frames (the
    later laps revisit the places of the first: a sequence for loop closing)."""
    n = _check_frames(n)
    _check_range("jitter", jitter, 0, 2)
    if int(laps) != laps or laps < 1:
        raise ConfigError(f"laps must be an integer >= 1 (got {laps})")
    phi = 2 * np.pi * int(laps) * np.arange(n) / (n - 1)
    centers = np.stack([1.2 * np.sin(phi), -0.6 - 0.5 * (1 - np.cos(phi)), 1.45 + 0.08 * np.sin(2 * phi)], axis=1)
    targets = np.stack([2.6 * np.sin(phi) + 0.5 * np.sin(2 * phi), np.full(n, ROOM_Y),
                        1.15 + 0.2 * np.sin(3 * phi)], axis=1)
    rolls = np.zeros(n)
    if jitter > 0:
        rng = np.random.default_rng(int(seed))
        for k in range(3):
            centers[:, k] += _periodic_noise(n, rng, 0.03 * jitter, (5, 14))
            targets[:, k] += _periodic_noise(n, rng, 0.10 * jitter, (3, 10))
        rolls += np.radians(_periodic_noise(n, rng, 1.5 * jitter, (2, 8)))
    return _poses_looking_at(centers, targets, rolls)


def _random_signal(rng: np.random.Generator, amplitude: float, terms: int = 4) -> Callable[[np.ndarray], np.ndarray]:
    """A smooth random signal ``t -> (len(t),)``: ``terms`` sinusoids of 0.3..1 cycles per unit time with
    random phases, amplitudes summing to ``amplitude``."""
    f = rng.uniform(0.3, 1.0, terms)
    ph = rng.uniform(0, 2 * np.pi, terms)
    w = rng.uniform(0.3, 1.0, terms)
    w *= amplitude / w.sum()
    return lambda t: (w[:, None] * np.sin(2 * np.pi * f[:, None] * np.asarray(t)[None, :] + ph[:, None])).sum(0)


def handheld(n: int = 300, speed: float = 0.015, seed: int = 0) -> np.ndarray:
    """Smooth random hand-held motion: position (within x +-1.2 m, y -1.6..-0.4 m, z 1.3..1.6 m) and gaze
    point (on the front half of the room) are sums of random low-frequency sinusoids, plus up to 2 degrees
    of roll. Time is scaled so that the mean speed is ``speed`` metres per frame."""
    n, speed = _check_frames(n), _check_positive("speed", speed)
    rng = np.random.default_rng(int(seed))
    cx, cy, cz = _random_signal(rng, 1.2), _random_signal(rng, 0.6), _random_signal(rng, 0.15)
    gx, gz, roll = _random_signal(rng, 2.0), _random_signal(rng, 0.4), _random_signal(rng, 2.0)

    def centers(t: np.ndarray) -> np.ndarray:
        return np.stack([cx(t), -1.0 + cy(t), 1.45 + cz(t)], axis=1)

    t = np.linspace(0.0, 1.0, n)
    for _ in range(6):  # fixed point: the mean speed is nearly proportional to the time scale
        mean_speed = np.linalg.norm(np.diff(centers(t), axis=0), axis=1).mean()
        t *= speed / max(mean_speed, 1e-12)
    targets = np.stack([gx(t), np.full(n, ROOM_Y), 1.2 + gz(t)], axis=1)
    return _poses_looking_at(centers(t), targets, np.radians(roll(t)))


def default_motion(n: int = DEFAULT_FRAMES, seed: int = 0) -> np.ndarray:
    """The motion of the default sequence: :func:`loop` with hand-held jitter (1.0)."""
    return loop(n, jitter=1.0, seed=seed)


# ----------------------------------------------------------------------------------------------------------
# hard motions (issue 17): fast forward motion, fast rotation and sudden jumps


def fast_forward(n: int = 80, speed: float = 0.25, weave: float = 0.4) -> np.ndarray:
    """Fast motion along the optical axis: :func:`forward` (the same y and gaze: towards the front wall from
    y = -1.7 m, back and forth over 2.4 m with smooth turns at ``speed`` metres per frame) plus a slow
    sideways drift ``x = 0.2 + weave * sin(2 pi i / (n - 1))`` metres, so that the path is not a line and a
    Sim(3) alignment to it is defined. 0.25 m per frame is a median image motion of ~25 px, as KITTI at
    frame skip 2."""
    n, speed = _check_frames(n), _check_positive("speed", speed)
    _check_range("weave", weave, 0, 0.5, "metres", open_low=True)
    poses = forward(n, speed)
    poses[:, 0, 3] = 0.2 + weave * np.sin(2 * np.pi * np.arange(n) / (n - 1))
    return poses


def fast_yaw(n: int = 120, yaw_rate: float = 8.0, turn: float = 80.0, hold: int = 10,
             speed: float = 0.01) -> np.ndarray:
    """Quick hand-held turns while walking slowly: the camera (1.45 m high, looking 10 degrees down) walks
    sideways along x from (-0.8, -0.9) at ``speed`` metres per frame (back and forth over at most 1.6 m)
    while its heading swings between +``turn``/2 and -``turn``/2 degrees about facing the front wall (+y):
    ``hold`` frames of constant heading, then a turn at exactly ``yaw_rate`` degrees per frame (the last
    step of a turn takes the remainder), and so on (:func:`fast_yaw_angles`). Turns are about the world
    vertical (z), so the rotation between consecutive frames is exactly the yaw step. The walk bends
    forward by up to 0.25 m in the middle (y = -0.9 + 0.25 sin(pi x'/1.6), x' the distance walked), so the
    path is not a line."""
    n, speed = _check_frames(n), _check_positive("speed", speed)
    yaw_rate, turn = _check_positive("yaw_rate", yaw_rate), _check_positive("turn", turn)
    if yaw_rate > 30 or turn > 150:
        raise ConfigError(f"yaw_rate must be <= 30 degrees per frame and turn <= 150 degrees "
                          f"(got {yaw_rate:g}, {turn:g})")
    if int(hold) != hold or hold < 0:
        raise ConfigError(f"hold must be an integer number of frames >= 0 (got {hold})")
    yaw = fast_yaw_angles(n, yaw_rate, turn, int(hold))
    s = _travel(n, speed, 1.6)
    centers = np.stack([-0.8 + s, -0.9 + 0.25 * np.sin(np.pi * s / 1.6), np.full(n, 1.45)], axis=1)
    pitch = np.radians(-10.0)
    a = np.radians(yaw)
    dirs = np.stack([-np.sin(a) * np.cos(pitch), np.cos(a) * np.cos(pitch), np.full(n, np.sin(pitch))], axis=1)
    return _poses_looking_at(centers, centers + dirs)


def fast_yaw_angles(n: int, yaw_rate: float, turn: float, hold: int) -> np.ndarray:
    """(n,) yaw in degrees (positive = to the left, about +z) of :func:`fast_yaw`: ``hold`` frames still,
    then steps of ``yaw_rate`` towards the next target (+turn/2, -turn/2, +turn/2, ...) until reached."""
    yaw = np.zeros(n)
    target, still, cur = turn / 2, 0, 0.0
    for i in range(1, n):
        if still < hold:
            still += 1
        else:
            if abs(target - cur) <= yaw_rate:  # the last step of a turn lands exactly on the target
                cur, target, still = target, -target, 0
            else:
                cur += math.copysign(yaw_rate, target - cur)
        yaw[i] = cur
    return yaw


def jerky(n: int = 200, speed: float = 0.015, jumps: int = 3, jump: int = 10, seed: int = 0) -> np.ndarray:
    """Smooth hand-held motion (:func:`handheld` at ``speed`` metres per frame, from ``seed``) with
    ``jumps`` sudden jerks: at frames :func:`jerk_frames` the camera moves in one frame as far as it
    moves in ``jump`` frames of the smooth path (translation and rotation), i.e. ``jump - 1`` frames of
    the smooth path of ``n + jumps * (jump - 1)`` frames are dropped before each jerk frame."""
    n, speed = _check_frames(n), _check_positive("speed", speed)
    if int(jumps) != jumps or jumps < 0 or int(jump) != jump or jump < 1:
        raise ConfigError(f"jumps must be an integer >= 0 and jump an integer >= 1 (got {jumps}, {jump})")
    jumps, jump = int(jumps), int(jump)
    at = jerk_frames(n, jumps)
    base = handheld(n + jumps * (jump - 1), speed=speed, seed=seed)
    return base[jerk_source_indices(n, jumps, jump)] if len(at) else base


def jerk_frames(n: int, jumps: int) -> np.ndarray:
    """Frames of :func:`jerky` reached by a jerk (the jump is between frame ``k - 1`` and ``k``): ``jumps``
    frames evenly spread, ``round((j + 1) * n / (jumps + 1))`` for j = 0 .. jumps - 1."""
    at = np.round((np.arange(jumps) + 1) * n / (jumps + 1)).astype(int)
    if len(at) and (len(np.unique(at)) != len(at) or at[0] < 1 or at[-1] > n - 1):
        raise ConfigError(f"{jumps} jumps do not fit in {n} frames")
    return at


def jerk_source_indices(n: int, jumps: int, jump: int) -> np.ndarray:
    """(n,) index into the smooth path of :func:`jerky` of each of its frames."""
    steps = np.ones(n, dtype=int)
    steps[0] = 0
    steps[jerk_frames(n, jumps)] = jump
    return np.cumsum(steps)


# ----------------------------------------------------------------------------------------------------------
# rotation phases (issue 42): a phone panned round a room, a clip that starts by turning


def _pan(n: int, centre: np.ndarray, amplitude: float, swings: float, tilt: float, heading: float = 0.0,
         pitch0: float = -5.0) -> np.ndarray:
    """(n, 4, 4) poses at one centre: yaw ``heading + amplitude * sin(2 pi swings i / (n - 1))`` degrees
    (positive to the left, about +z, 0 = facing the front wall, +y), pitch ``pitch0 + tilt * sin(4 pi swings
    i / (n - 1))`` degrees."""
    phase = 2 * np.pi * swings * np.arange(n) / max(n - 1, 1)
    yaw = np.radians(heading + amplitude * np.sin(phase))
    pitch = np.radians(pitch0 + tilt * np.sin(2 * phase))
    dirs = np.stack([-np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)], axis=1)
    return _poses_looking_at(np.tile(centre, (n, 1)), centre + dirs)


def pure_rotation(n: int = 150, amplitude: float = 60.0, swings: float = 1.0, tilt: float = 8.0) -> np.ndarray:
    """A phone panned round the room from one place (zero baseline in every frame): standing at
    (0, -1, 1.45), the heading swings +-``amplitude`` degrees about facing the front wall, ``swings`` full
    periods over the n frames, while the camera tilts by up to ``tilt`` degrees about 5 degrees down (twice
    as fast). Every pair of frames is related by a rotation only: no 3-D structure can be triangulated."""
    n = _check_frames(n)
    amplitude = _check_range("amplitude", amplitude, 0, 75, "degrees", open_low=True)
    swings = _check_range("swings", swings, 0, 20, open_low=True)
    tilt = _check_range("tilt", tilt, 0, 20, "degrees")
    return _pan(n, np.array([0.0, -1.0, 1.45]), amplitude, swings, tilt)


TURN_FRAMES = 60
"""Frames of turning at the start of :func:`turn_then_walk`: 2 s at the default 30 fps."""


def turn_then_walk(n: int = 150, turn_frames: int | None = None, amplitude: float = 25.0, speed: float = 0.015
                   ) -> np.ndarray:
    """A clip that starts by turning: the first ``turn_frames`` frames (default :data:`TURN_FRAMES`, 2 s at
    the default 30 fps; half the frames when there are fewer than twice that) turn in
    place at (-0.6, -1, 1.45) (zero baseline: the heading swings +-``amplitude`` degrees, one period, back to
    facing the front wall, with a few degrees of tilt), then the camera walks sideways along +x at ``speed``
    metres per frame facing the front wall (back and forth over at most 1.4 m). Frames 0 to ``turn_frames``
    share one camera centre. The walk bends forward by up to 0.2 m in the middle (y = -1 + 0.2 sin(pi x'/1.4), x'
    the distance walked), so the path is not a line."""
    n, speed = _check_frames(n), _check_positive("speed", speed)
    amplitude = _check_range("amplitude", amplitude, 0, 60, "degrees", open_low=True)
    if turn_frames is None:
        turn_frames = TURN_FRAMES if n >= 2 * TURN_FRAMES else max(2, n // 2)
    if not math.isfinite(turn_frames) or int(turn_frames) != turn_frames or not 2 <= turn_frames < n:
        raise ConfigError(f"turn_frames must be an integer number of frames in [2, frames) (got {turn_frames})")
    t = int(turn_frames)
    centre = np.array([-0.6, -1.0, 1.45])
    turning = _pan(t + 1, centre, amplitude, 1.0, 3.0)
    s = _travel(n - t, speed, 1.4)
    centers = np.stack([centre[0] + s, centre[1] + 0.2 * np.sin(np.pi * s / 1.4), np.full(n - t, centre[2])], axis=1)
    walking = _pan(n - t, centre, 0.0, 1.0, 0.0)  # facing the front wall, 5 degrees down
    walking[:, :3, 3] = centers
    return np.concatenate([turning[:-1], walking])


def handheld_pan(n: int = 200, amplitude: float = 35.0, swings: float = 1.0, tilt: float = 10.0,
                 shake: float = 0.03, distance: float = 1.5, seed: int = 0) -> np.ndarray:
    """A hand-held camera looked round from where one stands, mostly rotation (as TUM freiburg1's rpy and
    desk clips): standing ``distance`` metres from the front wall (1.45 m high), the heading swings
    +-``amplitude`` degrees about facing it (``swings`` periods over the n frames) and the pitch by up to
    ``tilt`` degrees about 5 degrees down (twice as fast), each with up to 3 degrees of smooth random
    wobble and up to 3 degrees of roll, while the hand moves the camera centre by a smooth random
    signal of at most ``shake`` metres along each axis (from ``seed``; from the first frame's centre up to
    twice that): a small baseline next to the rotation's image motion. ``shake=0``: a pure rotation."""
    n = _check_frames(n)
    amplitude = _check_range("amplitude", amplitude, 0, 75, "degrees", open_low=True)
    swings = _check_range("swings", swings, 0, 20, open_low=True)
    tilt = _check_range("tilt", tilt, 0, 30, "degrees")
    shake = _check_range("shake", shake, 0, 0.5, "metres")
    distance = _check_range("distance", distance, 0.5, 4.0, "metres")
    rng = np.random.default_rng(int(seed))
    t = np.arange(n) / max(n - 1, 1)
    phase = 2 * np.pi * swings * t
    wobble = [_random_signal(rng, 3.0)(swings * t) for _ in range(3)]
    yaw = np.radians(amplitude * np.sin(phase) + wobble[0])
    pitch = np.radians(-5.0 + tilt * np.sin(2 * phase) + wobble[1])
    centre = np.array([0.0, ROOM_Y - distance, 1.45])
    shift = np.stack([_random_signal(rng, shake)(swings * t) for _ in range(3)], axis=1)
    centers = centre + shift - shift[0]
    dirs = np.stack([-np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)], axis=1)
    return _poses_looking_at(centers, centers + dirs, np.radians(wobble[2]))


MOTIONS: dict[str, Callable[..., np.ndarray]] = {
    "sideways": sideways,
    "forward": forward,
    "orbit": orbit,
    "rotation": rotation,
    "translate-then-rotate": translate_then_rotate,
    "loop": loop,
    "handheld": handheld,
    "default": default_motion,
    "fast-forward": fast_forward,
    "fast-yaw": fast_yaw,
    "jerky": jerky,
    "pure-rotation": pure_rotation,
    "turn-then-walk": turn_then_walk,
    "handheld-pan": handheld_pan,
}
"""Motion name -> function ``(n, ...) -> (N, 4, 4)`` camera-to-world poses in the default room."""

HARD_MOTIONS = ("fast-forward", "fast-yaw", "jerky")
"""The motions that are not smooth hand-held motion by design (fast turns, sudden jumps: issue 17)."""
