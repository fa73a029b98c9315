"""EuRoC MAV sequences (ASL layout), one camera.

Layout (https://projects.asl.ethz.ch/datasets/doku.php?id=kmavvisualinertialdatasets)::

    MH_01_easy/                        # the sequence root ...
        mav0/                          # ... or this folder
            cam0/
                data.csv               # "#timestamp [ns],filename"
                data/1403636579763555584.png
                sensor.yaml            # intrinsics [fu, fv, cu, cv], distortion_coefficients [k1, k2, p1, p2],
                                       # resolution [w, h], T_BS (body-to-sensor extrinsic, 4x4 row-major)
            state_groundtruth_estimate0/data.csv   # timestamp [ns], p_RS_R xyz, q_RS_R wxyz, ...

Ground truth is of the body (IMU) frame: ``world_from_cam = world_from_body @ T_BS``; each image takes
the pose nearest in time within ``max_dt``. ``sensor.yaml`` is read by a small tolerant parser of the few
keys needed (no YAML dependency).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Intrinsics
from ..errors import AssociationError, CalibrationError, ConfigError, FormatError, SourceError
from ..kernels.geometry import pose_from_tum
from .base import ImageListSource, select
from .calibration import find_camera_txt, read_camera_txt
from .folder import image_size, resolve_camera
from .groundtruth import associate_nearest, check_quaternions
from .textfiles import check_finite, check_increasing, parse_rows, require_path, to_float, to_int, to_str


def to_ns(text: str) -> int:
    """A non-negative integer timestamp in nanoseconds that fits int64."""
    value = to_int(text)
    if not 0 <= value < 2**63:
        raise ValueError(f"{text!r} is not a timestamp in nanoseconds")
    return value


@dataclass(frozen=True)
class EurocSensor:
    """The camera part of an EuRoC ``sensor.yaml``.

    ``intrinsics``: (fu, fv, cu, cv) pixels; ``distortion``: radial-tangential (k1, k2, p1, p2);
    ``resolution``: (width, height) pixels; ``T_BS``: (4, 4) sensor-to-body transform (maps camera
    coordinates to body coordinates).
    """

    intrinsics: tuple[float, float, float, float]
    distortion: tuple[float, ...]
    resolution: tuple[int, int]
    T_BS: np.ndarray
    camera_model: str = "pinhole"
    distortion_model: str = "radial-tangential"

    def camera(self) -> Intrinsics:
        fu, fv, cu, cv = self.intrinsics
        k = tuple(self.distortion) + (0.0,) * (5 - len(self.distortion))
        return Intrinsics(self.resolution[0], self.resolution[1], fu, fv, cu, cv, k[:5])


def _line_of(text: str, pos: int) -> int:
    return text.count("\n", 0, pos) + 1


def _yaml_list(path: Path, text: str, key: str, start: int = 0, end: int | None = None) -> list[float]:
    """The numbers of ``key: [a, b, ...]`` (possibly over several lines) in ``text[start:end]``."""
    m = re.compile(rf"^[ \t]*{re.escape(key)}[ \t]*:[ \t]*\[([^\]]*)\]", re.M).search(text, start,
                                                                                    end or len(text))
    if m is None:
        raise FormatError(path, None, f"no '{key}: [...]' list")
    values = []
    for item in m.group(1).split(","):
        item = item.strip()
        if not item:
            continue
        try:
            values.append(to_float(item))
        except ValueError:
            line = _line_of(text, m.start(1) + m.group(1).find(item))
            raise FormatError(path, line, f"{key}: {item[:40]!r} is not a number") from None
    return values


def _yaml_scalar(text: str, key: str) -> str | None:
    m = re.search(rf"^{re.escape(key)}[ \t]*:[ \t]*([^\n]*)$", text, re.M)
    return m.group(1).strip().strip("'\"") if m else None


def read_euroc_sensor(path: str | Path) -> EurocSensor:
    """Parse an EuRoC camera ``sensor.yaml`` (FormatError on a missing/malformed key, CalibrationError on a
    non-finite value or an unsupported camera/distortion model)."""
    path = require_path(path, "EuRoC sensor.yaml")
    try:
        raw = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise FormatError(path, None, "is not UTF-8 text") from None
    lines = raw.replace("\r\n", "\n").replace("\r", "\n").split("\n")  # the line breaks of data_lines
    text = "\n".join(line.split("#", 1)[0] for line in lines)  # drop comments, keep line numbers
    model = _yaml_scalar(text, "camera_model") or "pinhole"
    dmodel = _yaml_scalar(text, "distortion_model") or "radial-tangential"
    if model != "pinhole":
        raise CalibrationError(f"{path}: camera_model {model!r} is not supported (only pinhole)")
    if dmodel not in ("radial-tangential", "radtan", "plumb_bob", "none"):
        raise CalibrationError(f"{path}: distortion_model {dmodel!r} is not supported (only radial-tangential)")
    intr = _yaml_list(path, text, "intrinsics")
    if len(intr) != 4:
        raise FormatError(path, None, f"intrinsics needs 4 numbers [fu, fv, cu, cv], got {len(intr)}")
    dist = _yaml_list(path, text, "distortion_coefficients") if dmodel != "none" else []
    if len(dist) not in (0, 4, 5):
        raise FormatError(path, None, f"distortion_coefficients needs 4 numbers [k1, k2, p1, p2], got {len(dist)}")
    res = _yaml_list(path, text, "resolution")
    if len(res) != 2 or any(r != int(r) or r <= 0 for r in res if np.isfinite(r)):
        raise FormatError(path, None, f"resolution needs 2 positive integers [width, height], got {res}")
    m = re.search(r"^T_BS[ \t]*:", text, re.M)
    if m is None:
        T_BS = np.eye(4)
    else:
        nxt = re.compile(r"^\S", re.M).search(text, m.end())
        data = _yaml_list(path, text, "data", m.end(), nxt.start() if nxt else None)
        if len(data) != 16:
            raise FormatError(path, _line_of(text, m.start()), f"T_BS data needs 16 numbers, got {len(data)}")
        T_BS = np.asarray(data, dtype=np.float64).reshape(4, 4)
    for key, values in (("intrinsics", intr), ("distortion_coefficients", dist), ("resolution", res),
                        ("T_BS", T_BS.ravel())):
        if not np.isfinite(values).all():
            m = re.search(rf"^[ \t]*{key}[ \t]*:", text, re.M)
            where = f"{path}:{_line_of(text, m.start())}" if m else str(path)
            raise CalibrationError(f"{where}: {key} {[float(v) for v in values]} are not all finite")
    return EurocSensor(tuple(intr), tuple(dist), (int(res[0]), int(res[1])), T_BS, model, dmodel)


def read_euroc_images(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """A camera ``data.csv`` -> (timestamps (N,) int64 nanoseconds, strictly increasing; file names)."""
    path = Path(path)
    rows, lines = parse_rows(path, [to_ns, to_str], delimiter=",", what=("timestamp [ns]", "filename"))
    t = np.asarray([r[0] for r in rows], dtype=np.int64).reshape(-1)
    check_increasing(path, t, lines)
    return t, [r[1] for r in rows]


def read_euroc_groundtruth(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``state_groundtruth_estimate0/data.csv`` -> (timestamps (N,) int64 ns, world_from_body (N, 4, 4)).

    Columns: timestamp [ns], p_RS_R x y z [m], q_RS_R w x y z, then velocities and biases (ignored).
    """
    path = Path(path)
    what = ("timestamp [ns]", "p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z")
    rows, lines = parse_rows(path, [to_ns] + [to_float] * 7, delimiter=",", at_least=True, what=what)
    t_ns = np.asarray([r[0] for r in rows], dtype=np.int64).reshape(-1)
    check_increasing(path, t_ns, lines)
    values = np.asarray([r[1:] for r in rows], dtype=np.float64).reshape(len(rows), 7)
    check_finite(path, values, lines)
    check_quaternions(path, values[:, 3:7], lines, "q_w q_x q_y q_z")
    if len(rows) == 0:
        return t_ns, np.zeros((0, 4, 4))
    q_xyzw = values[:, [4, 5, 6, 3]]
    return t_ns, pose_from_tum(values[:, 0:3], q_xyzw)


def _mav0(root: Path) -> Path:
    if (root / "mav0").is_dir():
        return root / "mav0"
    if root.name == "mav0" or any((root / c / "data.csv").is_file() for c in ("cam0", "cam1")):
        return root
    raise SourceError(f"{root} is not an EuRoC sequence (no mav0/ and no cam0/data.csv)")


def _camera(camera: Intrinsics | float | str | None, sensor, yaml: Path, cam_dir: Path, first_image: Path
            ) -> Intrinsics:
    """The intrinsics: ``camera`` when given, else a ``camera.txt`` beside the images, else ``sensor.yaml``;
    CalibrationError naming the file and the ways to give them."""
    w, h = image_size(first_image)
    where = str(first_image)
    calib = find_camera_txt(cam_dir, cam_dir / "data") if camera is None else None
    if calib is not None:
        camera = read_camera_txt(calib, w, h)
    if camera is None:
        if sensor is None:
            raise CalibrationError(f"{yaml}: missing; give the intrinsics: --camera fx,fy,cx,cy[,k1,k2,p1,p2] on "
                                   "the command line (Python: camera=Intrinsics(...)), or restore sensor.yaml")
        try:
            camera = sensor.camera()
        except CalibrationError as e:
            raise CalibrationError(f"{yaml}: {e}") from None
        where = f"{yaml} (resolution {sensor.resolution[0]}x{sensor.resolution[1]}) with the image {where}"
    return resolve_camera(camera, w, h, where=where)


def open_euroc(path: str | Path, *, cam: str = "cam0", camera: Intrinsics | float | str | None = None,
               max_dt: float = 0.02, min_gt_fraction: float = 0.5, frame_skip: int = 1,
               max_frames: int | None = None) -> ImageListSource:
    """Open an EuRoC MAV sequence.

    Args:
        path: the sequence root (holding ``mav0/``) or ``mav0`` itself.
        cam: ``"cam0"`` (left) or ``"cam1"``.
        camera: override the intrinsics of ``sensor.yaml`` (:class:`Intrinsics`, focal length or ``--camera``
            text); without it a ``camera.txt`` in the camera folder or its ``data/`` folder does.
        max_dt: largest |image time - ground-truth time| in seconds for an image to get a pose.
        min_gt_fraction: AssociationError when ground truth exists but fewer images than this get a pose.
        frame_skip, max_frames: keep every ``frame_skip``-th image, at most ``max_frames``.

    Timestamps are seconds (``ns * 1e-9``). ``gt_poses`` is None without ``state_groundtruth_estimate0``.
    """
    root = require_path(path, "EuRoC folder", kind="dir")
    mav0 = _mav0(root)
    cam_dir = require_path(mav0 / cam, f"EuRoC camera folder ({cam})", kind="dir")
    csv = require_path(cam_dir / "data.csv", "EuRoC image list")
    t_ns, names = read_euroc_images(csv)
    if len(names) == 0:
        raise SourceError(f"{csv} lists no images")
    paths = [cam_dir / "data" / n for n in names]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        raise SourceError(f"{csv} lists {len(missing)} images that do not exist: {', '.join(missing[:3])}{more}")
    if not 0.0 <= min_gt_fraction <= 1.0 or max_dt < 0:
        raise ConfigError(f"need max_dt >= 0 and 0 <= min_gt_fraction <= 1 (got {max_dt}, {min_gt_fraction})")
    keep = select(len(names), frame_skip, max_frames)
    yaml = cam_dir / "sensor.yaml"
    sensor = read_euroc_sensor(yaml) if yaml.is_file() else None
    cam_intr = _camera(camera, sensor, yaml, cam_dir, paths[keep[0]])
    t = t_ns * 1e-9
    gt = None
    gt_file = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if gt_file.is_file():
        gt_t, world_from_body = read_euroc_groundtruth(gt_file)
        match = associate_nearest(t, gt_t * 1e-9, max_dt)
        fraction = float(np.mean(match >= 0))
        if fraction < min_gt_fraction:
            raise AssociationError(f"only {fraction:.0%} of the images of {csv} have a pose in {gt_file} "
                                   f"within {max_dt} s; need {min_gt_fraction:.0%}")
        T_BS = sensor.T_BS if sensor is not None else np.eye(4)
        m = match[keep]
        gt = np.full((len(keep), 4, 4), np.nan)
        gt[m >= 0] = world_from_body[m[m >= 0]] @ T_BS
    seq_name = mav0.parent.name if mav0.name == "mav0" else mav0.name
    return ImageListSource(name=f"euroc/{seq_name}/{cam}", camera=cam_intr, paths=[paths[i] for i in keep],
                           timestamps=t[keep], frame_ids=keep, gt_poses=gt)
