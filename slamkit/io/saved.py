"""Checks of a saved run or session before anything reads it.

pycolmap's model reader trusts its input: an empty ``points3D.bin`` makes it loop forever, a truncated one
can make it abort the process. So before a run is evaluated or resumed:

1. every file the save recorded in its manifest (``.slamkit-run``, ``session/.slamkit-session.json``; see
   :mod:`slamkit.io.run_dir`) must exist with the recorded size and SHA-256;
2. whatever the manifest says (folders saved before manifests existed have none), the COLMAP binaries are
   walked record by record — counts consistent with the file size, camera models known, every reference
   (an image's camera, a track's image and keypoint, an image's 3D point, a frame's rig and images) pointing
   at something that exists — JSON files are parsed, and ``.npz`` archives are CRC-checked.

A failed check is a :class:`~slamkit.errors.SessionError` naming the file and what is wrong with it.
"""

from __future__ import annotations

import json
import os
import re
import struct
import zipfile
from pathlib import Path

import numpy as np

from ..errors import SessionError
from .run_dir import RUN_MARKER, SESSION_MARKER, file_sha256, read_manifest

__all__ = ["check_colmap_model", "check_run", "check_session"]

CAMERA_MODEL_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16, 12: 4, 13: 5,
                       14: 3, 15: 4, 16: 6, 17: 2}
"""COLMAP camera model id -> number of parameters (``pycolmap.CameraModelId``)."""

INVALID_ID = 2 ** 64 - 1
_POINT2D = np.dtype([("xy", "<f8", 2), ("point3D_id", "<u8")])
_TRACK = np.dtype([("image_id", "<u4"), ("point2D_idx", "<u4")])


# ----------------------------------------------------------------------------------------------- manifest
def _manifest(folder: Path, marker: str) -> dict | None:
    try:
        return read_manifest(folder, marker)
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise SessionError(f"{folder / marker}: the list of saved files cannot be read ({e}); the run folder is "
                           "damaged") from None


def _check_listed(folder: Path, manifest: dict, parts: tuple[str, ...] | None) -> None:
    """Files of ``manifest`` (those under ``parts``, or all): present, recorded size, recorded SHA-256."""
    for rel, info in manifest["files"].items():
        if parts is not None and not any(rel == p or rel.startswith(p.rstrip("/") + "/") for p in parts):
            continue
        path = folder / rel
        try:
            size = path.stat().st_size
        except FileNotFoundError:
            raise SessionError(f"{path}: missing (it was written when the run was saved)") from None
        except OSError as e:
            raise SessionError(f"{path}: cannot be read ({e.strerror or e})") from None
        if not isinstance(info, dict) or size != info.get("size"):
            raise SessionError(f"{path}: {size} bytes, but {info.get('size') if isinstance(info, dict) else '?'} "
                               "were written when the run was saved (truncated or replaced)")
        try:
            digest = file_sha256(path)
        except OSError as e:
            raise SessionError(f"{path}: cannot be read ({e.strerror or e})") from None
        if digest != info.get("sha256"):
            raise SessionError(f"{path}: content differs from what was saved (SHA-256 mismatch: the file is "
                               "damaged or was edited)")


# ----------------------------------------------------------------------------------------------- formats
def check_json(path: Path) -> object:
    """Parse a JSON file; SessionError naming it when it is not JSON (truncated, empty, not UTF-8)."""
    try:
        return json.loads(Path(path).read_bytes().decode("utf-8"))
    except FileNotFoundError:
        raise SessionError(f"{path}: missing") from None
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:
        raise SessionError(f"{path}: not valid JSON ({type(e).__name__}: {e}); the file is damaged") from None


def check_npz(path: Path) -> None:
    """An ``.npz`` archive whose members all pass their CRC; SessionError naming it otherwise."""
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
            names = z.namelist()
    except FileNotFoundError:
        raise SessionError(f"{path}: missing") from None
    except (OSError, zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, ValueError, NotImplementedError) as e:
        raise SessionError(f"{path}: not a readable .npz archive ({type(e).__name__}: {e}); the file is "
                           "damaged") from None
    if bad is not None:
        raise SessionError(f"{path}: member {bad} fails its checksum; the file is damaged")
    if not all(n.endswith(".npy") for n in names):
        raise SessionError(f"{path}: not a numpy .npz archive (members {names[:3]})")


class _Reader:
    """Bounds-checked little-endian reads from one file's bytes; SessionError naming the file on overrun."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.buf = path.read_bytes()
        except FileNotFoundError:
            raise SessionError(f"{path}: missing (a COLMAP model has cameras.bin, images.bin, points3D.bin)") from None
        except OSError as e:
            raise SessionError(f"{path}: cannot be read ({e.strerror or e})") from None
        self.at = 0

    def fail(self, reason: str) -> SessionError:
        if not self.buf:
            return SessionError(f"{self.path}: empty (0 bytes); not a COLMAP binary file — the file is damaged")
        return SessionError(f"{self.path}: {reason} (byte {self.at} of {len(self.buf)}); not a complete COLMAP "
                            "binary file — the file is damaged")

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.at + size > len(self.buf):
            raise self.fail(f"ends inside {what}")
        out = struct.unpack_from("<" + fmt, self.buf, self.at)
        self.at += size
        return out

    def array(self, dtype: np.dtype, count: int, what: str) -> np.ndarray:
        size = dtype.itemsize * count
        if count < 0 or self.at + size > len(self.buf):
            raise self.fail(f"ends inside {what} ({count} entries announced)")
        out = np.frombuffer(self.buf, dtype, count, self.at)
        self.at += size
        return out

    def count(self, min_record: int, what: str) -> int:
        (n,) = self.take("Q", f"the number of {what}")
        if n * min_record > len(self.buf) - self.at:
            raise self.fail(f"announces {n} {what}, more than its {len(self.buf)} bytes can hold")
        return n

    def end(self) -> None:
        if self.at != len(self.buf):
            raise self.fail(f"{len(self.buf) - self.at} bytes after the last record")


def _cameras(path: Path) -> set[int]:
    r = _Reader(path)
    ids = set()
    for _ in range(r.count(24, "cameras")):
        cam_id, model, width, height = r.take("IiQQ", "a camera")
        if model not in CAMERA_MODEL_PARAMS:
            raise r.fail(f"camera {cam_id} has unknown model id {model}")
        if not (0 < width < 1 << 20 and 0 < height < 1 << 20):
            raise r.fail(f"camera {cam_id} has image size {width}x{height}")
        params = r.take(f"{CAMERA_MODEL_PARAMS[model]}d", f"camera {cam_id}'s parameters")
        if not all(np.isfinite(params)):
            raise r.fail(f"camera {cam_id} has non-finite parameters")
        ids.add(cam_id)
    r.end()
    return ids


def _images(path: Path, cameras: set[int]) -> tuple[dict[int, int], set[int]]:
    """image id -> number of keypoints, and the 3D point ids the images observe."""
    r = _Reader(path)
    images: dict[int, int] = {}
    observed: set[int] = set()
    for _ in range(r.count(72, "images")):
        image_id, *pose, cam_id = r.take("I7dI", "an image")
        if cam_id not in cameras:
            raise r.fail(f"image {image_id} refers to camera {cam_id}, which cameras.bin does not have")
        end = r.buf.find(b"\0", r.at)
        if end < 0:
            raise r.fail(f"ends inside image {image_id}'s name")
        r.at = end + 1
        (n2d,) = r.take("Q", f"image {image_id}'s number of keypoints")
        pts = r.array(_POINT2D, n2d, f"image {image_id}'s keypoints")
        ids = pts["point3D_id"]
        observed.update(ids[ids != INVALID_ID].tolist())
        images[image_id] = n2d
    r.end()
    return images, observed


def _points3D(path: Path, images: dict[int, int], observed: set[int]) -> None:
    r = _Reader(path)
    ids = set()
    for _ in range(r.count(51, "3D points")):
        point_id, x, y, z, _r, _g, _b, _err, length = r.take("Q3d3BdQ", "a 3D point")
        track = r.array(_TRACK, length, f"3D point {point_id}'s track")
        for image_id, idx in track.tolist():
            if idx >= images.get(image_id, 0):
                raise r.fail(f"3D point {point_id} is seen by keypoint {idx} of image {image_id}, which "
                             "images.bin does not have")
        ids.add(point_id)
    r.end()
    missing = observed - ids
    if missing:
        raise SessionError(f"{path}: images.bin refers to {len(missing)} 3D points that points3D.bin does not "
                           f"have (e.g. {min(missing)}); the model is damaged")


def _rigs(path: Path, cameras: set[int]) -> set[int]:
    r = _Reader(path)
    ids = set()
    for _ in range(r.count(16, "rigs")):
        rig_id, num_sensors = r.take("II", "a rig")
        if num_sensors > 0:
            r.take("iI", f"rig {rig_id}'s reference sensor")
        for _ in range(max(0, num_sensors - 1)):
            _t, _s, has_pose = r.take("iIB", f"a sensor of rig {rig_id}")
            if has_pose:
                r.take("7d", f"a sensor pose of rig {rig_id}")
        ids.add(rig_id)
    r.end()
    return ids


def _frames(path: Path, rigs: set[int], images: dict[int, int]) -> None:
    r = _Reader(path)
    for _ in range(r.count(68, "frames")):
        frame_id, rig_id, *pose, n = r.take("II7dI", "a frame")
        if rig_id not in rigs:
            raise r.fail(f"frame {frame_id} refers to rig {rig_id}, which rigs.bin does not have")
        for _ in range(n):
            sensor_type, _sensor_id, data_id = r.take("iIQ", f"frame {frame_id}'s data")
            if sensor_type == 0 and data_id not in images:  # a camera's data is an image
                raise r.fail(f"frame {frame_id} refers to image {data_id}, which images.bin does not have")
    r.end()


def check_colmap_model(folder: str | os.PathLike) -> None:
    """Walk a COLMAP binary model (cameras, images, points3D; rigs and frames when present) and check that
    it is complete and consistent; SessionError naming the first damaged file."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SessionError(f"{folder}: missing (expected a COLMAP binary model folder)")
    cameras = _cameras(folder / "cameras.bin")
    images, observed = _images(folder / "images.bin", cameras)
    _points3D(folder / "points3D.bin", images, observed)
    if (folder / "rigs.bin").exists() or (folder / "frames.bin").exists():
        _frames(folder / "frames.bin", _rigs(folder / "rigs.bin", cameras), images)


# ----------------------------------------------------------------------------------------------- entry points
def check_session(folder: str | os.PathLike) -> None:
    """Check a session folder before :func:`slamkit.session.load_session` reads it (module docstring)."""
    folder = Path(folder)
    manifest = _manifest(folder, SESSION_MARKER)
    if manifest is not None:
        _check_listed(folder, manifest, None)
    elif folder.name == "session":
        run_manifest = _manifest(folder.parent, RUN_MARKER)
        if run_manifest is not None:
            _check_listed(folder.parent, run_manifest, ("session",))
    meta = check_json(folder / "session.json")
    if not isinstance(meta, dict):
        raise SessionError(f"{folder / 'session.json'}: not a slamkit session (a JSON {type(meta).__name__})")
    check_npz(folder / "state.npz")
    ids = [s.get("id") for s in meta.get("segments", []) if isinstance(s, dict)]
    segs = sorted({*(f"segment_{i:02d}" for i in ids if isinstance(i, int)),
                   *(p.name for p in folder.iterdir() if re.fullmatch(r"segment_\d+", p.name))})
    for name in segs:
        check_npz(folder / name / "arrays.npz")
        check_colmap_model(folder / name / "model")


def check_run(run: str | os.PathLike, parts: tuple[str, ...] | None = None) -> None:
    """Check the files of run folder ``run`` under ``parts`` (relative paths or folders; None: all) against
    its manifest, and the formats of its ``summary.json`` and ``sparse/`` model when they are in ``parts``."""
    run = Path(run)
    manifest = _manifest(run, RUN_MARKER)
    if manifest is not None:
        _check_listed(run, manifest, parts)
    wanted = (lambda rel: parts is None or rel in parts)
    if wanted("summary.json") and (run / "summary.json").exists():
        check_json(run / "summary.json")
    if wanted("sparse") and (run / "sparse").is_dir():
        check_colmap_model(run / "sparse")
