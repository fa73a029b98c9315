"""Synthetic sequences with exact ground truth, and the embedded default sequence.

Tests and the demo run without any dataset: frames are rendered from a textured room
(:func:`~slamkit.sources.scene.default_room`), a street (:func:`~slamkit.sources.street.street_scene`) or a
repeated-texture corridor (:func:`~slamkit.sources.corridor.corridor_scene`) with exact intrinsics and poses
(:mod:`slamkit.sources.scene` explains the renderer); the motion decides the scene. Specs understood by
:func:`open_synthetic` (and by ``open_source``)::

    default                          the embedded default sequence: 360 frames, 640x480, a hand-held loop
                                     through the room; rendered once and cached on disk as JPEG + TUM files
    synthetic:<motion>               a sequence rendered on the fly, e.g. ``synthetic:sideways``
    synthetic:<motion>?k=v&k=v       with parameters, e.g. ``synthetic:handheld?frames=200&seed=1``

Motions in the room (:data:`MOTIONS`, defined in :mod:`slamkit.sources.motions`): ``sideways``, ``forward``,
``orbit``, ``rotation`` (pure rotation, zero baseline), ``translate-then-rotate`` (sideways, then pure rotation
in place: degenerate motion after initialization), ``loop`` (returns exactly to its start), ``handheld``
(smooth random motion), the hard motions of issue 17 ``fast-forward`` (``forward`` at 0.25 m per frame, with a
sideways drift), ``fast-yaw`` (quick turns at a fixed yaw rate in degrees per frame while walking slowly)
and ``jerky`` (hand-held with sudden jumps: several frames of motion in one), the rotation phases of issue 42
``pure-rotation`` (a pan round the room from one place: +-60 degrees, some tilt) and
``turn-then-walk`` (2 s of turning in place, then a sideways walk), ``handheld-pan`` (looking round from where one
stands, hand-held: mostly rotation, a few centimetres of baseline), and ``default`` (the motion of
the default sequence, rendered live: ``synthetic:default?noise=1`` is the default sequence before JPEG
compression). Motions through their own scene (:data:`SCENE_MOTIONS`): ``street-drive`` (driving down a
street at ``speed`` metres per frame, default 1.0 as KITTI at frame skip 2; :mod:`slamkit.sources.street`)
and ``corridor-walk`` (a straight walk down a corridor whose walls repeat one tile: perceptual aliasing
without any revisit; :mod:`slamkit.sources.corridor`) and ``block-loop`` (driving ``laps`` times round a
city block, a 250 m loop: :mod:`slamkit.sources.block`). Parameters of every motion:

    frames=N     number of frames (2 to 100,000; each motion has its own default)
    seed=S       integer seed of random motions and of the image noise (default 0)
    fps=F        frame rate; timestamps are ``index / fps`` seconds (default 30)
    noise=SIGMA  Gaussian image noise in grey levels (default 0: noise-free)
    scale=K      image size factor of the camera (default 1; intrinsics scaled accordingly)
    wide=1       KITTI's camera, 1226x370 with fx = fy = 707 px (default 0: 640x480, fx = fy = 500 px)
    focal=F      focal length in pixels (fx = fy = F) instead of the camera's own (self-calibration tests)
    k1=K         radial distortion of the images (OpenCV's k1, default 0): each frame is rendered pinhole
                 over the distorted image's field of view and resampled (self-calibration tests)
    k2=K, k3=K   higher radial coefficients (OpenCV's, default 0), e.g. TUM freiburg1's lens:
                 ``k1=0.262&k2=-0.953&k3=1.163``

plus the motion's own keyword parameters (``speed`` in metres per frame, ``radius``, ``amplitude``,
``jitter``, ``weave``, ``sway``, ``yaw_rate``, ``turn``, ``hold``, ``jumps``, ``jump``, ``swings``, ``tilt``,
``turn_frames``: see each motion
function in :mod:`slamkit.sources.motions`, :mod:`~slamkit.sources.street` and
:mod:`~slamkit.sources.corridor`). An unknown motion or parameter, or a bad value, raises ConfigError.
For example ``synthetic:street-drive?frames=120&speed=1.5&seed=2`` or ``synthetic:corridor-walk?frames=300``.

World frame: z up, metres, floor at z = 0; poses are camera-to-world with OpenCV camera axes.

The default sequence is cached in ``$SLAMKIT_CACHE/default-v2/`` (or ``$XDG_CACHE_HOME/slamkit/...``,
else ``~/.cache/slamkit/...``) in TUM RGB-D layout (``rgb/*.jpg``, ``rgb.txt``, ``groundtruth.txt``)
plus ``camera.json``; it is written atomically (rendered into a temporary sibling, then renamed), and the
folder name carries a version that changes whenever the renderer or the scene changes. Its ``meta.json``
lists every file's size and SHA-256; each open checks them (:func:`cache_problem`, about 0.1 s), and a cache
that does not match is rendered again with a one-line note.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import logging
import math
import os
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..camera import Intrinsics
from ..errors import CalibrationError, ConfigError, FormatError, SourceError
from ..io.trajectory import read_tum, write_tum
from ..types import Trajectory
from .base import FrameSource, ImageListSource, select
from .block import block_loop, block_scene
from .corridor import corridor_scene, corridor_walk
from .folder import image_size, resolve_camera
from .motions import (DEFAULT_FRAMES, MAX_FRAMES, MOTIONS, _check_positive, default_motion, forward,  # noqa: F401
                      handheld, loop, orbit, rotation, sideways, translate_then_rotate)
from .render import distortion_maps, undistort_radial_exact
from .scene import Rendering, Scene, default_room, project
from .street import street_drive, street_scene

log = logging.getLogger(__name__)

DEFAULT_CAMERA = Intrinsics(640, 480, 500.0, 500.0, 319.5, 239.5)
"""Camera of the synthetic sequences: 640x480 pinhole, fx = fy = 500 px (65 x 51 degrees), no distortion."""

WIDE_CAMERA = Intrinsics(1226, 370, 707.0912, 707.0912, 601.8873, 183.1104)
"""Camera of ``wide=1``: KITTI odometry's left grey camera of sequences 04-12 (1226x370, 82 x 29 degrees)."""

SCENE_MOTIONS: dict[str, tuple[Callable[..., np.ndarray], Callable[[], Scene]]] = {
    "street-drive": (street_drive, street_scene),
    "corridor-walk": (corridor_walk, corridor_scene),
    "block-loop": (block_loop, block_scene),
}
"""Motions through a scene of their own: name -> (motion ``(n, ...) -> (N, 4, 4)`` camera-to-world poses,
the scene factory). The motions of :data:`MOTIONS` go through the default room."""

DEFAULT_VERSION = "default-v2"
"""Name of the cache folder of the default sequence; change it whenever the renderer or scene changes."""

DEFAULT_FPS = 30.0
DEFAULT_NOISE = 1.0
"""Image noise (grey levels) of the default sequence."""
DEFAULT_JPEG_QUALITY = 95
_NOISE_PAD = 97


# ----------------------------------------------------------------------------------------------------------
# the source


class SyntheticSource(FrameSource):
    """Frames rendered on access from ``scene`` at the given camera-to-world ``poses`` (N, 4, 4).

    Deterministic: the same arguments give bit-identical images. Frame ``k`` of the pose list has timestamp
    ``k / fps`` and frame id ``k``; ``frame_skip``/``max_frames`` select among the poses as for datasets.
    ``noise`` is the standard deviation (grey levels) of Gaussian noise added to each image, drawn from
    ``(seed, frame id)``. ``gt_poses`` are the exact poses of the delivered frames.
    """

    camera_in_spec = True

    def __init__(self, scene: Scene, poses: np.ndarray, intrinsics: Intrinsics = DEFAULT_CAMERA,
                 fps: float = DEFAULT_FPS, seed: int = 0, *, noise: float = 0.0, frame_skip: int = 1,
                 max_frames: int | None = None, name: str = "synthetic"):
        poses = np.array(poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(poses) == 0 or not np.isfinite(poses).all():
            raise ConfigError("SyntheticSource: poses must be a non-empty (N, 4, 4) array of finite numbers")
        fps = _check_positive("fps", fps)
        if not (math.isfinite(noise) and noise >= 0):
            raise ConfigError(f"noise must be >= 0 grey levels (got {noise})")
        if any(intrinsics.dist[2:4]) or not all(-1.5 <= k <= 1.5 for k in intrinsics.dist):
            raise ConfigError("SyntheticSource: only radial distortion (k1, k2, k3 in [-1.5, 1.5]) is rendered "
                              f"(got dist={tuple(intrinsics.dist)})")
        keep = select(len(poses), frame_skip, max_frames)
        self.name = name
        self.scene = scene
        self.camera = intrinsics
        self.fps = fps
        self.seed = int(seed)
        self.noise = float(noise)
        self.all_poses = poses
        self.frame_ids = keep.astype(np.int64)
        self.timestamps = keep / fps
        self.gt_poses = poses[keep].copy()
        self._noise_field: np.ndarray | None = None
        self._distortion = distortion_maps(intrinsics) if intrinsics.has_distortion else None

    def rendering(self, i: int) -> Rendering:
        """Noise-free :class:`~slamkit.sources.scene.Rendering` (image, exact depth, quad ids) of frame i, by
        the pinhole part of the camera (before distortion)."""
        return self.scene.render(self.gt_poses[i], self.camera.pinhole)

    def depth(self, i: int) -> np.ndarray:
        """(H, W) float64 exact z-depth in metres of the pixel centres of delivered frame ``i`` (pinhole part)."""
        return self.scene.depth(self.gt_poses[i], self.camera.pinhole)

    def points(self, i: int, pixels: np.ndarray) -> np.ndarray:
        """(N, 3) exact world points seen at (N, 2) pixel coordinates of delivered frame ``i`` (of its images,
        distortion included)."""
        pixels = undistort_radial_exact(self.camera, pixels) if self.camera.has_distortion else pixels
        return self.scene.points(self.gt_poses[i], self.camera.pinhole, pixels)

    def flow(self, i: int, j: int | None = None, step: int = 20) -> np.ndarray:
        """(M,) exact image motion in pixels from delivered frame ``i`` to ``j`` (default ``i + 1``): the
        distance between a grid of pixels (every ``step`` px) of frame ``i`` and the projections in frame
        ``j`` of the scene points they see (points behind camera ``j`` left out; occlusion ignored). Its
        median says how fast a sequence is in the units that matter to tracking."""
        j = i + 1 if j is None else j
        w, h = self.camera.width, self.camera.height
        u, v = np.meshgrid(np.arange(step / 2, w, step), np.arange(step / 2, h, step))
        pixels = np.stack([u.ravel(), v.ravel()], axis=1)
        pts = self.points(i, pixels)
        ok = np.isfinite(pts).all(axis=1)
        uv, z = project(self.gt_poses[j], self.camera.pinhole, pts[ok])
        if self.camera.has_distortion:
            uv = self.camera.distort_points(uv)
        return np.linalg.norm(uv[z > 0] - pixels[ok][z > 0], axis=1)

    def image(self, i: int) -> np.ndarray:
        """(H, W, 3) uint8 BGR image of delivered frame ``i`` (with the source's noise)."""
        if self._distortion is None:
            img = self.scene.render(self.gt_poses[i], self.camera).image
        else:  # the pinhole render over the distorted image's view, resampled at each pixel's undistorted place
            canvas, map_x, map_y = self._distortion
            img = cv2.remap(self.scene.render(self.gt_poses[i], canvas).image, map_x, map_y, cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE)
        if self.noise > 0:
            # Gaussian noise, rounded to grey levels: a window of a noise field drawn once from the seed, at
            # an offset drawn from (seed, frame id) -- as random as fresh noise at a fraction of the cost
            h, w = img.shape[:2]
            if self._noise_field is None:
                rng = np.random.default_rng([self.seed, 0x6E6F697365])
                normal = rng.standard_normal((h + _NOISE_PAD, w + _NOISE_PAD, 3))
                self._noise_field = np.round(normal * self.noise).astype(np.int16)
            dy, dx = np.random.default_rng([self.seed, int(self.frame_ids[i])]).integers(0, _NOISE_PAD, 2)
            img = cv2.add(img, self._noise_field[dy:dy + h, dx:dx + w], dtype=cv2.CV_8U)  # saturating
        return img

    def _read(self, i: int) -> tuple[np.ndarray, Path | None]:
        return self.image(i), None


def synthetic_source(motion: str = "default", *, frames: int | None = None, seed: int = 0,
                     fps: float = DEFAULT_FPS, noise: float = 0.0, scale: float = 1.0, wide: int = 0,
                     focal: float | None = None, k1: float = 0.0, k2: float = 0.0, k3: float = 0.0,
                     frame_skip: int = 1, max_frames: int | None = None, **motion_kw) -> SyntheticSource:
    """A :class:`SyntheticSource` for a named motion of :data:`MOTIONS` (in the default room) or of
    :data:`SCENE_MOTIONS` (in its own scene).

    ``frames`` defaults to the motion's own default; ``seed`` goes to the motion (when it is random) and to
    the image noise; ``wide=1`` renders with :data:`WIDE_CAMERA` instead of :data:`DEFAULT_CAMERA`;
    ``motion_kw`` are the motion function's keyword parameters.
    """
    fn, make_scene = _motion(motion)
    params = inspect.signature(fn).parameters
    unknown = sorted(set(motion_kw) - (set(params) - {"n", "seed"}))
    if unknown:
        raise ConfigError(f"synthetic motion {motion!r} takes no parameter {', '.join(map(repr, unknown))} "
                          f"(accepted: {', '.join(_accepted(motion))})")
    kw = dict(motion_kw)
    if frames is not None:
        kw["n"] = frames
    if "seed" in params:
        kw["seed"] = seed
    scale = _check_positive("scale", scale)
    if scale > 4:
        raise ConfigError(f"scale must be <= 4 (got {scale})")
    if wide not in (0, 1):
        raise ConfigError(f"wide must be 0 or 1 (got {wide})")
    camera = WIDE_CAMERA if wide else DEFAULT_CAMERA
    camera = camera if scale == 1 else camera.scaled(scale)
    if focal is not None:
        try:
            camera = replace(camera, fx=float(focal), fy=float(focal))
        except CalibrationError as e:
            raise ConfigError(f"focal={focal:g}: {e}") from None
    if k1 or k2 or k3:
        if not -0.5 <= float(k1) <= 0.5 or not all(-1.5 <= float(k) <= 1.5 for k in (k2, k3)):
            raise ConfigError(f"k1 must be in [-0.5, 0.5], k2 and k3 in [-1.5, 1.5] (got {k1}, {k2}, {k3})")
        camera = replace(camera, dist=(float(k1), float(k2), 0.0, 0.0, float(k3)))
        try:
            camera.check_distortion("synthetic camera")
        except CalibrationError as e:
            raise ConfigError(str(e)) from None
    poses = fn(**kw)
    label = motion if not motion_kw and frames is None else f"{motion}({len(poses)})"
    return SyntheticSource(make_scene(), poses, camera, fps=fps, seed=seed, noise=noise, frame_skip=frame_skip,
                           max_frames=max_frames, name=f"synthetic/{label}")


_COMMON = ("frames", "seed", "fps", "noise", "scale", "wide", "focal", "k1", "k2", "k3")


def _motion(name: str) -> tuple[Callable[..., np.ndarray], Callable[[], Scene]]:
    """(motion function, scene factory) of a motion name; ConfigError for an unknown one."""
    if name in MOTIONS:
        return MOTIONS[name], default_room
    if name in SCENE_MOTIONS:
        return SCENE_MOTIONS[name]
    raise ConfigError(f"unknown synthetic motion {name!r}; choose from {', '.join(_motion_names())}")


def _motion_names() -> list[str]:
    return list(MOTIONS) + [m for m in SCENE_MOTIONS if m not in MOTIONS]


def _accepted(motion: str) -> list[str]:
    own = [p for p in inspect.signature(_motion(motion)[0]).parameters if p not in ("n", "seed")]
    return list(_COMMON) + own


def parse_spec(spec: str) -> tuple[str, dict[str, float | int]]:
    """``"synthetic:<motion>?k=v&..."`` -> (motion, {parameter: number}); ConfigError names what is wrong."""
    text = str(spec).strip()
    if not text.startswith("synthetic:"):
        raise SourceError(f"{spec!r} is not a synthetic spec (expected 'default' or 'synthetic:<motion>[?k=v&...]')")
    body = text[len("synthetic:"):]
    motion, _, query = body.partition("?")
    motion = motion.strip()
    if motion not in MOTIONS and motion not in SCENE_MOTIONS:
        raise ConfigError(f"{spec!r}: unknown synthetic motion {motion!r}; choose from {', '.join(_motion_names())} "
                          "(e.g. 'synthetic:handheld?frames=200&seed=1')")
    params: dict[str, float | int] = {}
    accepted = _accepted(motion)
    for item in filter(None, query.split("&")):
        if "=" not in item:
            raise ConfigError(f"{spec!r}: parameter {item!r} has no value (write {item}=VALUE)")
        key, _, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if key not in accepted:
            raise ConfigError(f"{spec!r}: synthetic motion {motion!r} takes no parameter {key!r} "
                              f"(accepted: {', '.join(accepted)})")
        if key in params:
            raise ConfigError(f"{spec!r}: parameter {key!r} is given twice")
        try:
            number = float(value)
        except ValueError:
            raise ConfigError(f"{spec!r}: parameter {key}={value!r} is not a number") from None
        if not math.isfinite(number):
            raise ConfigError(f"{spec!r}: parameter {key}={value!r} must be a finite number")
        if key in ("frames", "seed", "wide", "laps"):
            if not number.is_integer():
                raise ConfigError(f"{spec!r}: parameter {key}={value!r} must be an integer")
            number = int(value) if value.lstrip("+").isdigit() else int(number)  # a seed of any size, exactly
        if key == "seed" and number < 0:
            raise ConfigError(f"{spec!r}: parameter seed={value!r} must be >= 0 (any non-negative integer)")
        if key == "frames" and not 2 <= number <= MAX_FRAMES:
            raise ConfigError(f"{spec!r}: frames must be an integer >= 2 and <= {MAX_FRAMES} (got {value})")
        params[key] = number
    return motion, params


def open_synthetic(spec: str, *, frame_skip: int = 1, max_frames: int | None = None) -> FrameSource:
    """Open ``default`` (the cached default sequence) or ``synthetic:<motion>[?k=v&...]`` (rendered on
    access); see the module docstring for motions and parameters. ConfigError/SourceError for a bad spec."""
    text = str(spec).strip()
    if text == "default":
        return open_default(frame_skip=frame_skip, max_frames=max_frames)
    motion, params = parse_spec(text)
    source = synthetic_source(motion, frame_skip=frame_skip, max_frames=max_frames, **params)
    return source


# ----------------------------------------------------------------------------------------------------------
# writing sequences to disk (TUM RGB-D layout) and the cached default sequence


def write_tum_sequence(source: FrameSource, folder: str | Path, *, image_format: str = "png",
                       jpeg_quality: int = DEFAULT_JPEG_QUALITY, depth: bool = False) -> Path:
    """Write every frame of ``source`` to ``folder`` in TUM RGB-D layout; returns the folder.

    Writes ``rgb/<timestamp>.<png|jpg>``, ``rgb.txt`` (``timestamp filename``), ``groundtruth.txt``
    (``timestamp tx ty tz qx qy qz qw``, camera-to-world, for the frames that have ground truth) and
    ``camera.json`` (:meth:`Intrinsics.to_dict`). With ``depth=True`` (a :class:`SyntheticSource` only) also
    ``depth/<timestamp>.png`` (uint16, metres x 5000, 0 = none, as TUM) and ``depth.txt``. Timestamps are
    written with 6 decimals, the same string in every file.
    """
    if image_format not in ("png", "jpg"):
        raise ConfigError(f"image_format must be 'png' or 'jpg' (got {image_format!r})")
    if depth and not isinstance(source, SyntheticSource):
        raise ConfigError("write_tum_sequence: depth=True needs a SyntheticSource (exact depth maps)")
    folder = Path(folder)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    if depth:
        (folder / "depth").mkdir(exist_ok=True)
    stamps = [f"{t:.6f}" for t in np.asarray(source.timestamps, dtype=np.float64)]
    if len(set(stamps)) != len(stamps):
        raise ConfigError("write_tum_sequence: timestamps are not distinct at 6 decimals")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if image_format == "jpg" else []
    rgb_lines = ["# color images\n", f"# file: '{source.name}' (slamkit synthetic)\n", "# timestamp filename\n"]
    depth_lines = ["# depth maps (uint16, metres x 5000)\n", f"# file: '{source.name}'\n", "# timestamp filename\n"]
    for i, stamp in enumerate(stamps):
        if isinstance(source, SyntheticSource):
            bgr = source.image(i)
        else:
            bgr = cv2.cvtColor(source[i].color, cv2.COLOR_RGB2BGR)
        name = f"rgb/{stamp}.{image_format}"
        if not cv2.imwrite(str(folder / name), bgr, params):
            raise SourceError(f"{folder / name}: could not be written")
        rgb_lines.append(f"{stamp} {name}\n")
        if depth:
            z = source.depth(i)
            d16 = np.where(np.isfinite(z) & (z * 5000 < 65535), np.round(z * 5000), 0).astype(np.uint16)
            dname = f"depth/{stamp}.png"
            cv2.imwrite(str(folder / dname), d16)
            depth_lines.append(f"{stamp} {dname}\n")
    (folder / "rgb.txt").write_text("".join(rgb_lines))
    if depth:
        (folder / "depth.txt").write_text("".join(depth_lines))
    if source.gt_poses is not None:
        ok = np.isfinite(source.gt_poses).all(axis=(1, 2))
        t = np.array([float(s) for s in stamps])
        write_tum(folder / "groundtruth.txt", Trajectory(t[ok], source.gt_poses[ok]))
    (folder / "camera.json").write_text(json.dumps(source.camera.to_dict(), indent=2) + "\n")
    return folder


def cache_root() -> Path:
    """Folder of slamkit's on-disk caches: ``$SLAMKIT_CACHE``, else ``$XDG_CACHE_HOME/slamkit``, else
    ``~/.cache/slamkit``."""
    env = os.environ.get("SLAMKIT_CACHE")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    if xdg:
        return Path(xdg).expanduser() / "slamkit"
    return Path.home() / ".cache" / "slamkit"


def default_sequence_dir() -> Path:
    """Where the default sequence is cached: ``cache_root() / DEFAULT_VERSION``."""
    return cache_root() / DEFAULT_VERSION


def default_source() -> SyntheticSource:
    """The default sequence rendered live (what the cache holds, before JPEG compression)."""
    return SyntheticSource(default_room(), default_motion(DEFAULT_FRAMES), DEFAULT_CAMERA, fps=DEFAULT_FPS,
                           seed=0, noise=DEFAULT_NOISE, name="default")


def _checksums(folder: Path) -> dict[str, list]:
    """``{relative path: [size in bytes, sha256]}`` of every file under ``folder`` but ``meta.json``."""
    out = {}
    for path in sorted(folder.rglob("*")):
        if path.is_file() and path.name != "meta.json":
            out[path.relative_to(folder).as_posix()] = [path.stat().st_size, _sha256(path)]
    return out


def _sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _default_meta() -> dict:
    return dict(version=DEFAULT_VERSION, frames=DEFAULT_FRAMES, fps=DEFAULT_FPS, noise=DEFAULT_NOISE,
                jpeg_quality=DEFAULT_JPEG_QUALITY)


def cache_problem(folder: str | Path, meta: dict | None = None, camera: Intrinsics = DEFAULT_CAMERA) -> str:
    """Why the cached sequence in ``folder`` cannot be used ("" when it can): missing, written with other
    settings than ``meta`` (default: the default sequence's version, frame count, ...) or another ``camera``, or
    a file missing, of another size or not matching the SHA-256 that its ``meta.json`` lists (written with the
    files, checked at every open: about 0.1 s for the default sequence's 37 MB)."""
    folder, expected = Path(folder), _default_meta() if meta is None else meta
    try:
        written = json.loads((folder / "meta.json").read_text())
        files = written["files"]
        cam = Intrinsics.from_dict(json.loads((folder / "camera.json").read_text()))
    except FileNotFoundError as e:
        return f"{Path(e.filename).name} is missing" if folder.is_dir() else "it does not exist"
    except KeyError:
        return "its meta.json lists no checksums (an older slamkit wrote it)"
    except (OSError, ValueError, TypeError, CalibrationError) as e:
        return f"its meta.json or camera.json is unreadable ({type(e).__name__}: {e})"
    changed = [k for k, v in expected.items() if written.get(k) != v]
    if changed:
        return "it was written with other settings (" + ", ".join(f"{k}={written.get(k)!r}" for k in changed) + ")"
    if cam != camera:
        return f"its camera.json is not the sequence's camera ({cam.width}x{cam.height}, fx={cam.fx:g})"
    images = [name for name in files if name.startswith("rgb/")]
    if len(images) != expected.get("frames", len(images)) or not {"rgb.txt", "camera.json"} <= set(files):
        return f"its checksums list {len(images)} images, not {expected.get('frames')} (and rgb.txt, camera.json)"
    for name, (size, digest) in files.items():
        path = folder / name
        try:
            actual = path.stat().st_size
            if actual != size:
                return f"{name} has {actual} bytes, not {size}"
            if _sha256(path) != digest:
                return f"{name} does not match its checksum"
        except OSError as e:
            return f"{name} cannot be read ({e.strerror or e})"
    return ""


def ensure_default_sequence() -> Path:
    """Render the default sequence into its cache folder unless it is already there; returns the folder
    (:func:`ensure_cached_sequence`)."""
    return ensure_cached_sequence(default_sequence_dir(), default_source, _default_meta(), DEFAULT_CAMERA,
                                  "the default sequence")


def ensure_cached_sequence(folder: str | Path, make_source: Callable[[], SyntheticSource], meta: dict,
                           camera: Intrinsics, what: str = "the sequence") -> Path:
    """Render ``make_source()`` (whose camera is ``camera``) into ``folder`` as JPEGs in TUM layout
    (:func:`write_tum_sequence`) with a ``meta.json`` of ``meta`` and every file's size and SHA-256, unless the
    folder is there and matches them (:func:`cache_problem`); one that does not is rendered again, with a
    one-line note (a warning of this module's logger). Returns the folder.

    The frames are rendered into a temporary sibling folder that is renamed into place when complete, so a
    crash never leaves a partial cache and concurrent first uses are safe (the first rename wins).
    """
    folder = Path(folder)
    problem = cache_problem(folder, meta, camera)
    if not problem:
        return folder
    if folder.is_dir() and any(folder.iterdir()) and not ((folder / "meta.json").is_file() or (
            (folder / "camera.json").is_file() and (folder / "rgb.txt").is_file())):  # not a cache slamkit wrote
        raise SourceError(f"{folder}: holds files but no meta.json, so it is not a cache slamkit wrote and is kept "
                          "(slamkit never deletes what it did not make): move it away, or set SLAMKIT_CACHE to "
                          "another folder")
    if folder.exists():
        log.warning("slamkit: note: the cache of %s in %s is not usable (%s): rendering it again", what, folder,
                    problem)
    root = folder.parent
    try:
        root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=root))
    except OSError as e:
        raise SourceError(f"cannot create the cache folder {root} for {what} ({e}); "
                          "set SLAMKIT_CACHE to a writable folder") from e
    try:
        source = make_source()
        log.info("rendering %s (%d frames) into %s (once)", what, len(source), folder)
        t0 = time.perf_counter()
        write_tum_sequence(source, tmp, image_format="jpg", jpeg_quality=int(meta.get("jpeg_quality",
                                                                                        DEFAULT_JPEG_QUALITY)))
        written = dict(meta, render_seconds=round(time.perf_counter() - t0, 2), files=_checksums(tmp))
        (tmp / "meta.json").write_text(json.dumps(written, indent=1) + "\n")
        done = lambda: not cache_problem(folder, meta, camera)  # noqa: E731
        if done():  # a concurrent first use finished meanwhile: use its folder
            return folder
        if folder.exists():  # unusable leftover (files deleted or changed by hand, an older cache): move it aside
            stale = Path(tempfile.mkdtemp(prefix=f".{folder.name}.stale.", dir=root))
            os.replace(folder, stale / folder.name)
            shutil.rmtree(stale, ignore_errors=True)
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o777 & ~mask)  # mkdtemp made it private; the cache is an ordinary folder
        try:
            os.rename(tmp, folder)
        except OSError:
            if not done():  # not a concurrent writer that won the race
                raise
        log.info("%s rendered in %.1f s", what, time.perf_counter() - t0)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


def open_tum_sequence(folder: str | Path, *, name: str | None = None, frame_skip: int = 1,
                      max_frames: int | None = None) -> ImageListSource:
    """Open a folder written by :func:`write_tum_sequence` (its ``camera.json`` gives the intrinsics)."""
    folder = Path(folder)
    for f in ("rgb.txt", "camera.json"):
        if not (folder / f).is_file():
            raise SourceError(f"{folder / f} does not exist (not a sequence written by write_tum_sequence?)")
    try:
        camera = Intrinsics.from_dict(json.loads((folder / "camera.json").read_text()))
    except CalibrationError as e:
        raise CalibrationError(f"{folder / 'camera.json'}: {e}") from None
    except (ValueError, KeyError, TypeError) as e:
        raise CalibrationError(f"{folder / 'camera.json'}: not written by Intrinsics.to_dict ({e})") from None
    stamps, names = [], []
    for lineno, line in enumerate((folder / "rgb.txt").read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2:
            raise FormatError(folder / "rgb.txt", lineno, "expected 'timestamp filename'")
        stamps.append(float(parts[0]))
        names.append(parts[1])
    t = np.asarray(stamps)
    keep = select(len(t), frame_skip, max_frames)
    gt = None
    if (folder / "groundtruth.txt").is_file():
        traj = read_tum(folder / "groundtruth.txt")
        gt = np.full((len(t), 4, 4), np.nan)
        pos = np.searchsorted(traj.timestamps, t)
        pos = np.clip(pos, 0, max(len(traj) - 1, 0))
        ok = np.abs(traj.timestamps[pos] - t) < 1e-7 if len(traj) else np.zeros(len(t), bool)
        gt[ok] = traj.poses[pos[ok]]
        gt = gt[keep]
    paths = [folder / names[i] for i in keep]
    if paths and paths[0].is_file():  # the intrinsics must fit the images (checked on the first, header only)
        resolve_camera(camera, *image_size(paths[0]), where=f"{folder / 'camera.json'} with the image {paths[0]}")
    return ImageListSource(name=name or folder.name, camera=camera, paths=paths, timestamps=t[keep], frame_ids=keep,
                           gt_poses=gt)


def open_default(*, frame_skip: int = 1, max_frames: int | None = None) -> ImageListSource:
    """The embedded default sequence (rendered into the cache on first use, then read from the JPEGs)."""
    folder = ensure_default_sequence()
    source = open_tum_sequence(folder, name="default", frame_skip=frame_skip, max_frames=max_frames)
    source.camera_in_spec = True  # rendered: its camera is part of the spec, as a synthetic: source's
    return source


__all__ = [
    "DEFAULT_CAMERA", "DEFAULT_VERSION", "MOTIONS", "SCENE_MOTIONS", "SyntheticSource", "WIDE_CAMERA", "cache_root",
    "cache_problem", "default_motion", "default_sequence_dir", "default_source", "ensure_cached_sequence",
    "ensure_default_sequence", "forward", "handheld",
    "loop", "open_default", "open_synthetic", "open_tum_sequence", "orbit", "parse_spec", "rotation", "sideways",
    "synthetic_source", "translate_then_rotate", "write_tum_sequence",
]
