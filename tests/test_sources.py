"""Frame sources: every layout on generated data, every bad input, and the real sequences of ../shared/data."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import shared_data
from slamkit.camera import Intrinsics
from slamkit.errors import (AssociationError, CalibrationError, ConfigError, FormatError, ImageReadError,
                            SlamkitError, SourceError)
from slamkit.geometry import (invert_pose, normalize_quaternion, pose_from_rows, pose_from_tum,
                              quaternion_from_rotation, rotation_from_quaternion, tum_from_pose)
from slamkit.sources import (VideoSource, detect_layout, open_euroc, open_folder, open_kitti, open_sevenscenes,
                             open_source, open_tum, open_video)
import slamkit.sources.open as source_opener
from slamkit.sources.folder import image_size, natural_sorted
from slamkit.sources.groundtruth import associate_nearest
from slamkit.sources.tum import TUM_CALIBRATIONS

W, H = 64, 48
CAM = Intrinsics(W, H, 50.0, 51.0, 31.5, 23.5)


# ---------------------------------------------------------------------------------------------------------
# generators
# ---------------------------------------------------------------------------------------------------------
def write_image(path: Path, value: int = 0, size: tuple[int, int] = (W, H), grey: bool = False) -> Path:
    """An image whose pixel (0, 0) holds ``value`` (the frame's identity) over a gradient."""
    w, h = size
    img = np.add.outer(np.arange(h), np.arange(w)).astype(np.uint8)
    img = img if grey else np.dstack([img, img // 2, 255 - img])
    img[:4, :4] = value
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img)
    return path


def pixel(frame) -> int:
    return int(frame.gray[1, 1])


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return pose_from_tum(rng.normal(size=(n, 3)), rng.normal(size=(n, 4)))


def make_tum(root: Path, n: int = 6, gt_offset: float = 0.0, gt: bool = True, size=(640, 480)) -> tuple:
    """A TUM folder: images at 30 Hz from t0, ground truth at 100 Hz covering them (shifted by gt_offset)."""
    root.mkdir(parents=True, exist_ok=True)
    t0 = 1305031453.359684
    t = t0 + np.arange(n) / 30.0
    lines = ["# color images", "# timestamp filename"]
    for i, ti in enumerate(t):
        write_image(root / "rgb" / f"{ti:.6f}.png", 10 * i, size)
        lines.append(f"{ti:.6f} rgb/{ti:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    gt_t = t0 + gt_offset - 0.05 + np.arange(int((n / 30.0 + 0.1) * 100)) / 100.0
    poses = random_poses(len(gt_t))
    if gt:
        rows = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
        for ti, T in zip(gt_t, poses):
            tr, q = tum_from_pose(T)
            rows.append(f"{ti:.4f} " + " ".join(f"{v:.17g}" for v in (*tr, *q)))
        (root / "groundtruth.txt").write_text("\n".join(rows) + "\n")
    return t, np.round(gt_t, 4), poses


def make_kitti(root: Path, seq: str = "03", n: int = 7, poses: bool = True) -> np.ndarray:
    folder = root / "sequences" / seq
    for i in range(n):
        write_image(folder / "image_0" / f"{i:06d}.png", 10 * i, grey=True)
        write_image(folder / "image_2" / f"{i:06d}.png", 10 * i)
    P0 = [50.0, 0, 31.5, 0, 0, 51.0, 23.5, 0, 0, 0, 1, 0]
    P2 = [50.0, 0, 31.5, 50.0 * 0.06, 0, 51.0, 23.5, 0, 0, 0, 1, 0]  # camera 2 is 6 cm left of camera 0
    (folder / "calib.txt").write_text(
        "P0: " + " ".join(f"{v:e}" for v in P0) + "\nP1: " + " ".join(f"{v:e}" for v in P0)
        + "\nP2: " + " ".join(f"{v:e}" for v in P2) + "\nP3: " + " ".join(f"{v:e}" for v in P2) + "\n")
    (folder / "times.txt").write_text("".join(f"{i * 0.1:e}\n" for i in range(n)))
    T = random_poses(n, 1)
    if poses:
        (root / "poses").mkdir(parents=True, exist_ok=True)
        (root / "poses" / f"{seq}.txt").write_text(
            "".join(" ".join(f"{v:.17g}" for v in p[:3].ravel()) + "\n" for p in T))
    return T


def make_7scenes(root: Path, n: int = 5, seqs=("seq-01", "seq-02"), intrinsics: str | None = "matrix",
                 ext: str = "png") -> dict:
    poses = {}
    for s, seq in enumerate(seqs):
        T = random_poses(n, 10 + s)
        for i in range(n):
            write_image(root / seq / f"frame-{i:06d}.color.{ext}", 10 * i + s, (640, 480))
            cv2.imwrite(str(root / seq / f"frame-{i:06d}.depth.png"), np.zeros((480, 640), np.uint16))
            np.savetxt(root / seq / f"frame-{i:06d}.pose.txt", T[i])
        poses[seq] = T
    if intrinsics == "matrix":
        np.savetxt(root / "camera-intrinsics.txt", np.array([[580.0, 0, 321.0], [0, 582.0, 241.0], [0, 0, 1]]))
    elif intrinsics == "four":
        (root / "camera-intrinsics.txt").write_text("580 582 321 241\n")
    return poses


SENSOR_YAML = """\
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [64, 48]
camera_model: pinhole
intrinsics: [50.0, 51.0, 31.5, 23.5] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""


def make_euroc(root: Path, n: int = 6) -> tuple:
    cam0 = root / "mav0" / "cam0"
    t_ns = 1403636579763555584 + np.arange(n, dtype=np.int64) * 50_000_000
    rows = ["#timestamp [ns],filename"]
    for i, t in enumerate(t_ns):
        write_image(cam0 / "data" / f"{t}.png", 10 * i, grey=True)
        rows.append(f"{t},{t}.png")
    (cam0 / "data.csv").write_text("\r\n".join(rows) + "\r\n")
    (cam0 / "sensor.yaml").write_text(SENSOR_YAML)
    gt_ns = t_ns[0] - 20_000_000 + np.arange(n * 10 + 10, dtype=np.int64) * 5_000_000
    body = random_poses(len(gt_ns), 3)
    gt_rows = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
               "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x, b_w_RS_S_y, b_w_RS_S_z, "
               "b_a_RS_S_x, b_a_RS_S_y, b_a_RS_S_z"]
    for t, T in zip(gt_ns, body):
        tr, q = tum_from_pose(T)
        vals = [*tr, q[3], q[0], q[1], q[2]] + [0.0] * 9
        gt_rows.append(f"{t}," + ",".join(f"{v:.17g}" for v in vals))
    gt_dir = root / "mav0" / "state_groundtruth_estimate0"
    gt_dir.mkdir(parents=True)
    (gt_dir / "data.csv").write_text("\n".join(gt_rows) + "\n")
    return t_ns, gt_ns, body


def make_video(path: Path, n: int = 12, size=(W, H), fps: float = 25.0) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    assert writer.isOpened()
    for i in range(n):
        img = np.full((size[1], size[0], 3), 20 * i, np.uint8)
        writer.write(img)
    writer.release()
    return path


# ---------------------------------------------------------------------------------------------------------
# geometry
# ---------------------------------------------------------------------------------------------------------
def test_quaternion_rotation_roundtrip_and_pycolmap_convention():
    pycolmap = pytest.importorskip("pycolmap")
    rng = np.random.default_rng(0)
    q = normalize_quaternion(rng.normal(size=(200, 4)))
    R = rotation_from_quaternion(q)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(quaternion_from_rotation(R), q, atol=1e-12)
    for i in range(5):  # pycolmap's Rotation3d stores (x, y, z, w) too
        assert np.allclose(pycolmap.Rotation3d(q[i]).matrix(), R[i], atol=1e-12)
    for axis in np.eye(3):  # 180 degree rotations (w = 0), the unstable case of naive conversions
        Rpi = 2 * np.outer(axis, axis) - np.eye(3)
        assert np.allclose(rotation_from_quaternion(quaternion_from_rotation(Rpi)), Rpi)


def test_pose_from_tum_normalises_and_inverts():
    T = pose_from_tum([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 2.0])  # not unit: normalised
    assert np.allclose(T, [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    T = random_poses(4)
    t, q = tum_from_pose(T)
    assert np.allclose(pose_from_tum(t, q), T)
    assert np.allclose(invert_pose(T) @ T, np.eye(4))
    assert np.allclose(pose_from_rows(T[:, :3].reshape(4, 12)), T)
    with pytest.raises(ValueError):
        pose_from_tum([0, 0, 0], [0, 0, 0, 0])


# ---------------------------------------------------------------------------------------------------------
# image folders
# ---------------------------------------------------------------------------------------------------------
def test_natural_order():
    names = ["frame10.png", "frame2.png", "frame1.png", "Frame3.png", "frame02b.png"]
    assert [p.name for p in natural_sorted(Path(n) for n in names)] == [
        "frame1.png", "frame2.png", "frame02b.png", "Frame3.png", "frame10.png"]


def test_folder_opens_in_natural_order_with_skip_and_timestamps(tmp_path):
    for i in [1, 2, 10, 11, 3, 20]:
        write_image(tmp_path / f"frame{i}.png", i)
    write_image(tmp_path / "frame4.jpg", 4)
    (tmp_path / "notes.txt").write_text("not an image")
    src = open_folder(tmp_path, fps=10)
    assert len(src) == 7
    order = [1, 2, 3, 4, 10, 11, 20]
    assert [p.name for p in src.paths] == [f"frame{i}.{'jpg' if i == 4 else 'png'}" for i in order]
    # the names are frame numbers (issue 50): each frame's time is its number / fps, whatever numbers are missing
    assert np.allclose(src.timestamps, np.array(order) / 10) and list(src.frame_ids) == order
    assert src.camera == Intrinsics.from_focal(W, H)  # the documented guess
    assert src.gt_poses is None and src.ground_truth() is None
    f = src[4]
    assert (f.index, f.frame_id, f.gray.shape, f.color.shape) == (4, 10, (H, W), (H, W, 3))
    assert f.path.name == "frame10.png"

    src = open_folder(tmp_path, frame_skip=2, max_frames=3, camera=60.0)
    assert len(src) == 3 and list(src.frame_ids) == [1, 3, 10]
    assert np.allclose(src.timestamps, [1 / 30, 3 / 30, 10 / 30])
    assert [pixel(f) for f in src] == [1, 3, 10]
    assert (src.camera.fx, src.camera.cx) == (60.0, W / 2)
    assert open_folder(tmp_path, camera=CAM).camera == CAM
    assert len(open_folder(tmp_path, max_frames=100)) == 7
    assert len(open_folder(tmp_path, pattern="frame1*.png")) == 3  # frame1, frame10, frame11


def test_folder_with_tum_groundtruth(tmp_path):
    for i in range(4):
        write_image(tmp_path / "img" / f"{i:03d}.png", i)
    T = random_poses(3)
    gt = tmp_path / "gt.txt"
    t, q = tum_from_pose(T)
    gt.write_text("".join(f"{i / 30:.6f} " + " ".join(f"{v:.17g}" for v in (*t[i], *q[i])) + "\n"
                          for i in range(len(T))))
    src = open_folder(tmp_path / "img", groundtruth=gt)
    assert np.allclose(src.gt_poses[:3], T) and np.isnan(src.gt_poses[3]).all()
    assert src[3].gt_pose is None and np.allclose(src[1].gt_pose, T[1])
    assert len(src.ground_truth()) == 3


def test_opening_reads_no_image_and_corrupt_image_fails_on_access(tmp_path, monkeypatch):
    for i in range(4):
        write_image(tmp_path / f"{i}.png", i)
    write_image(tmp_path / "4.jpg", 4)
    (tmp_path / "2.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    src = open_folder(tmp_path)
    assert pixel(src[1]) == 1 and abs(pixel(src[4]) - 4) <= 2  # JPEG
    with pytest.raises(ImageReadError, match=r"2\.png") as e:
        src[2]
    assert e.value.path == tmp_path / "2.png"

    # no decode at all while opening: header reads only, for PNG and JPEG, in every layout
    def no_decode(*a, **k):
        raise AssertionError("an image was decoded while opening")

    make_tum(tmp_path / "rgbd_dataset_freiburg2_x", n=2)
    make_kitti(tmp_path / "kitti", n=2)
    make_7scenes(tmp_path / "7s", n=2, seqs=("seq-01",), ext="jpg")
    make_euroc(tmp_path / "euroc", n=2)
    monkeypatch.setattr(cv2, "imread", no_decode)
    for p in ["folder:" + str(tmp_path), tmp_path / "rgbd_dataset_freiburg2_x", tmp_path / "kitti",
              tmp_path / "7s", tmp_path / "euroc"]:
        assert len(open_source(p)) >= 2


def test_image_size_from_headers(tmp_path):
    for name in ["a.png", "b.jpg", "c.bmp"]:
        write_image(tmp_path / name, 0, (37, 21))
        assert image_size(tmp_path / name) == (37, 21)


# ---------------------------------------------------------------------------------------------------------
# TUM RGB-D
# ---------------------------------------------------------------------------------------------------------
def test_tum_associates_ground_truth(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg2_xyz"
    t, gt_t, poses = make_tum(root, n=6)
    src = open_tum(root)
    assert src.camera == TUM_CALIBRATIONS["fr2"]
    assert len(src) == 6 and np.allclose(src.timestamps, t)
    idx = np.abs(gt_t[None] - t[:, None]).argmin(axis=1)
    assert np.allclose(src.gt_poses, poses[idx], atol=1e-9)
    assert pixel(src[3]) == 30 and np.allclose(src[3].gt_pose, poses[idx[3]], atol=1e-9)

    src = open_tum(root, frame_skip=2, max_frames=2, calibration="fr1")
    assert list(src.frame_ids) == [0, 2] and src.camera == TUM_CALIBRATIONS["fr1"]
    assert np.allclose(src.gt_poses, poses[idx[[0, 2]]], atol=1e-9)
    assert open_tum(root, calibration=TUM_CALIBRATIONS["fr3"]).camera.fx == 535.4


def test_tum_frames_without_ground_truth_get_nan_rows(tmp_path):
    root = tmp_path / "fr1_shifted"
    t, gt_t, poses = make_tum(root, n=6, gt_offset=0.12)  # GT starts 70 ms after the first image
    src = open_tum(root)
    has = np.isfinite(src.gt_poses).all(axis=(1, 2))
    assert list(has) == [np.abs(gt_t - ti).min() <= 0.02 for ti in t]
    assert not has[0] and has[-1] and src[0].gt_pose is None
    assert len(src.ground_truth()) == has.sum()


def test_tum_without_groundtruth_and_unknown_sensor(tmp_path):
    root = tmp_path / "my_recording"
    make_tum(root, n=3, gt=False)
    with pytest.raises(CalibrationError, match="calibration="):
        open_tum(root)
    src = open_tum(root, calibration="freiburg3")
    assert src.gt_poses is None and src.ground_truth() is None
    with pytest.raises(ConfigError):
        open_tum(root, calibration="fr4")


def test_tum_association_below_threshold_names_files(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg1_x"
    make_tum(root, n=6, gt_offset=5.0)
    with pytest.raises(AssociationError) as e:
        open_tum(root)
    assert "rgb.txt" in str(e.value) and "groundtruth.txt" in str(e.value)
    assert open_tum(root, min_gt_fraction=0.0).ground_truth() is not None


def test_associate_nearest():
    ref = np.array([0.0, 1.0, 2.0])
    assert list(associate_nearest([-0.5, 0.01, 0.6, 1.4, 2.02, 3.0], ref, 0.45)) == [-1, 0, 1, 1, 2, -1]


# ---------------------------------------------------------------------------------------------------------
# KITTI
# ---------------------------------------------------------------------------------------------------------
def test_kitti_root_sequence_folder_and_poses(tmp_path):
    T = make_kitti(tmp_path, "03", n=7)
    for spec in [dict(path=tmp_path), dict(path=tmp_path, sequence=3), dict(path=tmp_path / "sequences" / "03")]:
        src = open_kitti(**spec)
        assert len(src) == 7 and src.name == "kitti/03"
        assert (src.camera.fx, src.camera.fy, src.camera.cx, src.camera.cy) == (50.0, 51.0, 31.5, 23.5)
        assert np.allclose(src.timestamps, np.arange(7) * 0.1)
        assert np.allclose(src.gt_poses, T)
    src = open_kitti(tmp_path, frame_skip=3)
    assert list(src.frame_ids) == [0, 3, 6] and pixel(src[1]) == 30 and np.allclose(src[2].gt_pose, T[6])
    # colour camera 2: the pose of camera 0 moved by the 6 cm baseline of P2
    src = open_kitti(tmp_path, camera_index=2)
    assert np.allclose(src.gt_poses[:, :3, 3], T[:, :3, 3] - 0.06 * T[:, :3, 0])
    make_kitti(tmp_path, "04", n=2, poses=False)
    with pytest.raises(SourceError, match="choose one"):
        open_kitti(tmp_path)
    assert open_kitti(tmp_path, sequence="04").gt_poses is None


def test_kitti_count_mismatch(tmp_path):
    make_kitti(tmp_path, "00", n=4)
    times = tmp_path / "sequences" / "00" / "times.txt"
    times.write_text("0.0\n0.1\n0.2\n")
    with pytest.raises(FormatError, match=r"times\.txt.*3 timestamps.*4 images"):
        open_kitti(tmp_path)
    times.write_text("0.0\n0.1\n0.2\n0.3\n")
    poses = tmp_path / "poses" / "00.txt"
    poses.write_text("\n".join(poses.read_text().splitlines()[:2]) + "\n")
    with pytest.raises(FormatError, match=r"00\.txt.*2 poses.*4 images"):
        open_kitti(tmp_path)


# ---------------------------------------------------------------------------------------------------------
# 7-Scenes
# ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("intrinsics", ["matrix", "four", None])
def test_sevenscenes_scene_and_sequence(tmp_path, intrinsics):
    poses = make_7scenes(tmp_path, n=5, intrinsics=intrinsics)
    src = open_sevenscenes(tmp_path)
    assert src.name == f"7scenes/{tmp_path.name}/seq-01" and len(src) == 5
    fx, fy, cx, cy = (585.0, 585.0, 320.0, 240.0) if intrinsics is None else (580.0, 582.0, 321.0, 241.0)
    assert (src.camera.fx, src.camera.fy, src.camera.cx, src.camera.cy) == (fx, fy, cx, cy)
    assert np.allclose(src.timestamps, np.arange(5) / 30)
    assert np.allclose(src.gt_poses, poses["seq-01"])
    src = open_sevenscenes(tmp_path, seq="seq-02", frame_skip=2)
    assert list(src.frame_ids) == [0, 2, 4] and pixel(src[1]) == 21
    assert np.allclose(src.gt_poses, poses["seq-02"][::2])
    assert len(open_sevenscenes(tmp_path / "seq-02", max_frames=2)) == 2
    assert open_sevenscenes(tmp_path, seq=2).name.endswith("seq-02")


def test_sevenscenes_infinite_pose_is_nan_row(tmp_path):
    make_7scenes(tmp_path, n=3, seqs=("seq-01",))
    (tmp_path / "seq-01" / "frame-000001.pose.txt").write_text("-inf -inf -inf -inf\n" * 4)
    src = open_sevenscenes(tmp_path)
    assert np.isnan(src.gt_poses[1]).all() and np.isfinite(src.gt_poses[[0, 2]]).all()
    assert src[1].gt_pose is None and len(src.ground_truth()) == 2


# ---------------------------------------------------------------------------------------------------------
# EuRoC
# ---------------------------------------------------------------------------------------------------------
def test_euroc_intrinsics_timestamps_and_camera_ground_truth(tmp_path):
    t_ns, gt_ns, body = make_euroc(tmp_path, n=6)
    for path in [tmp_path, tmp_path / "mav0"]:
        src = open_euroc(path)
        assert len(src) == 6
        c = src.camera
        assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (W, H, 50.0, 51.0, 31.5, 23.5)
        assert c.dist == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0)
        assert np.allclose(src.timestamps, t_ns * 1e-9)
    T_BS = np.array([[0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
                     [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
                     [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
                     [0.0, 0.0, 0.0, 1.0]])
    idx = np.searchsorted(gt_ns, t_ns)
    assert (gt_ns[idx] == t_ns).all() or np.abs(gt_ns[idx] - t_ns).max() < 5_000_000
    nearest = np.abs(gt_ns[None] - t_ns[:, None]).argmin(axis=1)
    assert np.allclose(src.gt_poses, body[nearest] @ T_BS, atol=1e-9)
    src = open_euroc(tmp_path, frame_skip=2, max_frames=2)
    assert list(src.frame_ids) == [0, 2] and pixel(src[1]) == 20


# ---------------------------------------------------------------------------------------------------------
# video
# ---------------------------------------------------------------------------------------------------------
def test_video_random_access_skip_and_timestamps(tmp_path):
    path = make_video(tmp_path / "clip.avi", n=12, fps=25.0)
    src = open_video(path)
    assert isinstance(src, VideoSource) and len(src) == 12 and src.fps == 25.0
    assert src.camera == Intrinsics.from_focal(W, H)
    assert np.allclose(src.timestamps, np.arange(12) / 25)
    values = [pixel(f) for f in src]
    assert np.allclose(values, 20 * np.arange(12), atol=3)
    # backwards and forwards jumps give the same frames as a sequential read
    for i in [7, 2, 11, 0, 5, 5, 6]:
        assert pixel(src[i]) == values[i]
    src = open_video(path, frame_skip=5, camera=40.0, fps=10)
    assert list(src.frame_ids) == [0, 5, 10] and np.allclose(src.timestamps, [0, 0.5, 1.0])
    assert [pixel(f) for f in src] == [values[0], values[5], values[10]]
    assert src.camera.fx == 40.0
    src.close()
    assert pixel(src[1]) == values[5]  # reopened after close
    assert len(open_video(path, max_frames=4, exact_count=True)) == 4


def test_video_frame_size_change_is_calibration_error(tmp_path):
    path = make_video(tmp_path / "clip.avi", n=3)
    src = open_video(path)
    src.camera = Intrinsics.from_focal(W + 2, H)  # as if a later frame had another size than the first
    with pytest.raises(CalibrationError, match="clip.avi"):
        src[1]


def test_video_frame_that_cannot_be_decoded(tmp_path):
    path = make_video(tmp_path / "clip.avi", n=3)
    src = open_video(path)
    src.frame_ids = np.array([0, 1, 50])  # as if the container had announced more frames than it has
    src.timestamps = src.frame_ids / src.fps
    pixel(src[1])
    with pytest.raises(ImageReadError, match=r"clip\.avi.*frame 50"):
        src[2]
    assert pixel(src[0]) == 0  # the capture recovers by seeking back


# ---------------------------------------------------------------------------------------------------------
# open_source
# ---------------------------------------------------------------------------------------------------------
def test_open_source_detects_every_layout(tmp_path):
    make_tum(tmp_path / "rgbd_dataset_freiburg1_x", n=2)
    make_kitti(tmp_path / "kitti", n=2)
    make_7scenes(tmp_path / "7s", n=2, seqs=("seq-01",))
    make_euroc(tmp_path / "euroc", n=2)
    make_video(tmp_path / "clip.avi", n=3)
    write_image(tmp_path / "imgs" / "a.png")
    expected = {"rgbd_dataset_freiburg1_x": "tum", "kitti": "kitti", "kitti/sequences/03": "kitti",
                "7s": "7scenes", "7s/seq-01": "7scenes", "euroc": "euroc", "euroc/mav0": "euroc",
                "clip.avi": "video", "imgs": "folder"}
    for rel, layout in expected.items():
        assert detect_layout(tmp_path / rel) == layout, rel
        src = open_source(str(tmp_path / rel), max_frames=2)
        assert 1 <= len(src) <= 2
    assert type(open_source(tmp_path / "clip.avi")).__name__ == "VideoSource"
    assert open_source(f"kitti:{tmp_path / 'kitti'}", sequence="03").name == "kitti/03"
    assert open_source(f"folder:{tmp_path / 'kitti/sequences/03/image_0'}").name == "folder/image_0"
    assert open_source(f"7scenes:{tmp_path / '7s'}").name.endswith("seq-01")
    assert open_source(f"video:{tmp_path / 'clip.avi'}", frame_skip=2).frame_ids.tolist() == [0, 2]
    assert open_source(f"euroc:{tmp_path / 'euroc'}").name.startswith("euroc/")
    assert open_source(f"tum:{tmp_path / 'rgbd_dataset_freiburg1_x'}", camera="fr3").camera.fx == 535.4
    assert len(open_source(str(tmp_path / "kitti/sequences/03/image_0/*.png"))) == 2
    assert open_source(tmp_path / "imgs", camera=CAM).camera == CAM
    with pytest.raises(ConfigError, match="fps"):
        open_source(tmp_path / "kitti", fps=10)


def test_open_source_dispatches_synthetic_specs(monkeypatch):
    calls, made = [], []

    class Opened:  # what the stand-in opener returns; open_source records the spec it was opened from on it
        pass

    def open_synthetic(spec, *, frame_skip=1, max_frames=None):
        calls.append((spec, frame_skip, max_frames))
        made.append(Opened())
        return made[-1]

    monkeypatch.setattr(source_opener, "open_synthetic", open_synthetic)
    assert open_source("default") is made[0] and made[0].spec == "default"
    assert open_source("synthetic:loop?n=30", frame_skip=2, max_frames=5) is made[1]
    assert calls == [("default", 1, None), ("synthetic:loop?n=30", 2, 5)]


# ---------------------------------------------------------------------------------------------------------
# bad input: one test per kind; every error is a SlamkitError naming what is at fault
# ---------------------------------------------------------------------------------------------------------
def test_missing_path(tmp_path):
    missing = tmp_path / "nope"
    for spec in [missing, f"kitti:{missing}", f"video:{missing}.mp4"]:
        with pytest.raises(SourceError, match="nope"):
            open_source(spec)
    with pytest.raises(SourceError, match="nope"):
        open_folder(missing)


def test_empty_folder_says_which_extensions(tmp_path):
    (tmp_path / "readme.txt").write_text("x")
    with pytest.raises(SourceError) as e:
        open_source(tmp_path)
    assert str(tmp_path) in str(e.value) and ".png" in str(e.value) and ".jpg" in str(e.value)


def test_no_images_matched(tmp_path):
    write_image(tmp_path / "a.png")
    with pytest.raises(SourceError, match=r"\*\.jpg"):
        open_folder(tmp_path, pattern="*.jpg")
    with pytest.raises(SourceError, match="no files"):
        open_source(str(tmp_path / "*.tif"))


def test_corrupt_image_names_the_file(tmp_path):
    write_image(tmp_path / "0.png")
    (tmp_path / "1.jpg").write_bytes(b"\xff\xd8\xff\xe0 not a jpeg at all")
    src = open_folder(tmp_path)
    with pytest.raises(ImageReadError, match=r"1\.jpg"):
        src[1]
    (tmp_path / "0.png").write_bytes(b"nothing")  # the first image is needed for the size: fails on open
    with pytest.raises(ImageReadError, match=r"0\.png"):
        open_folder(tmp_path)


@pytest.mark.parametrize("content,line", [
    ("# c\n1305031453.3 rgb/a.png\nnot-a-number rgb/b.png\n", 3),
    ("1.0 rgb/a.png\n2.0\n", 2),
    ("1.0 rgb/a.png\n\n2.0 rgb/b.png extra\n", 3),
])
def test_malformed_rgb_txt(tmp_path, content, line):
    root = tmp_path / "fr1_x"
    make_tum(root, n=2, gt=False)
    (root / "rgb.txt").write_text(content)
    with pytest.raises(FormatError, match=rf"rgb\.txt:{line}:") as e:
        open_tum(root)
    assert e.value.line == line and e.value.path.name == "rgb.txt"


@pytest.mark.parametrize("bad,reason", [
    ("1305031453.0 1 2 3 0 0 0\n", "expected 8 fields"),
    ("1305031453.0 1 2 3 0 0 0 x\n", "qw"),
    ("1305031453.0 1 2 nan 0 0 0 1\n", "not finite"),
    ("1305031453.325 1 2 3 0 0 0 0\n", "zero norm"),
])
def test_malformed_groundtruth_txt(tmp_path, bad, reason):
    root = tmp_path / "fr1_x"
    make_tum(root, n=2)
    gt = root / "groundtruth.txt"
    lines = gt.read_text().splitlines(keepends=True)
    lines.insert(4, bad)  # after 2 comment lines and 2 poses
    gt.write_text("".join(lines))
    with pytest.raises(FormatError, match=rf"groundtruth\.txt:5: .*{reason}"):
        open_tum(root)


@pytest.mark.parametrize("content,exc,match", [
    ("P0: 1 2 3\n", FormatError, r"calib\.txt:1: P0 needs 12 numbers"),
    ("P0: " + "1 " * 12 + "\nP1 1 2 3\n", FormatError, r"calib\.txt:2: expected 'KEY: values'"),
    ("P0: 50 0 31.5 0 0 51 23.5 0 0 0 1 zero\n", FormatError, r"calib\.txt:1: field 12"),
    ("P0: 50 0 31.5 0 0 nan 23.5 0 0 0 1 0\n", CalibrationError, r"calib\.txt:1: P0 has non-finite"),
    ("P1: " + "1 " * 12 + "\n", FormatError, r"calib\.txt: no 'P0:' line"),
    ("P0: -50 0 31.5 0 0 51 23.5 0 0 0 1 0\n", CalibrationError, r"calib\.txt.*focal"),
])
def test_malformed_calib_txt(tmp_path, content, exc, match):
    make_kitti(tmp_path, "00", n=2)
    (tmp_path / "sequences" / "00" / "calib.txt").write_text(content)
    with pytest.raises(exc, match=match):
        open_kitti(tmp_path)


@pytest.mark.parametrize("content,match", [
    ("0.0\n0.1 0.2\n", r"times\.txt:2: expected 1 fields"),
    ("0.0\n\n# comment\nabc\n", r"times\.txt:4: field 1 \(timestamp\) is 'abc'"),
])
def test_malformed_times_txt(tmp_path, content, match):
    make_kitti(tmp_path, "00", n=2)
    (tmp_path / "sequences" / "00" / "times.txt").write_text(content)
    with pytest.raises(FormatError, match=match):
        open_kitti(tmp_path)


def test_malformed_pose_files(tmp_path):
    make_kitti(tmp_path, "00", n=2)
    (tmp_path / "poses" / "00.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"00\.txt:2: expected 12 fields"):
        open_kitti(tmp_path)
    make_7scenes(tmp_path / "7s", n=2, seqs=("seq-01",))
    (tmp_path / "7s" / "seq-01" / "frame-000001.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(FormatError, match=r"frame-000001\.pose\.txt: expected 4 lines"):
        open_sevenscenes(tmp_path / "7s")
    make_euroc(tmp_path / "euroc", n=2)
    csv = tmp_path / "euroc" / "mav0" / "cam0" / "data.csv"
    csv.write_text(csv.read_text() + "12x,foo.png\n")
    with pytest.raises(FormatError, match=r"data\.csv:4: field 1 \(timestamp \[ns\]\)"):
        open_euroc(tmp_path / "euroc")


@pytest.mark.parametrize("which", ["rgb", "gt", "times", "euroc"])
def test_timestamps_not_increasing(tmp_path, which):
    if which in ("rgb", "gt"):
        root = tmp_path / "fr1_x"
        make_tum(root, n=3)
        f = root / ("rgb.txt" if which == "rgb" else "groundtruth.txt")
        lines = f.read_text().splitlines()
        lines[3], lines[4] = lines[4], lines[3]  # lines 4 and 5 swapped: line 5 goes back in time
        f.write_text("\n".join(lines) + "\n")
        opener = lambda: open_tum(root)  # noqa: E731
    elif which == "times":
        make_kitti(tmp_path, "00", n=3)
        f = tmp_path / "sequences" / "00" / "times.txt"
        f.write_text("0.0\n# c\n0.2\n0.2\n")
        opener = lambda: open_kitti(tmp_path)  # noqa: E731
    else:
        make_euroc(tmp_path, n=3)
        f = tmp_path / "mav0" / "cam0" / "data.csv"
        lines = f.read_text().splitlines()
        lines[2], lines[3] = lines[3], lines[2]  # line 4 holds an earlier time than line 3
        f.write_text("\n".join(lines) + "\n")
        opener = lambda: open_euroc(tmp_path)  # noqa: E731
    with pytest.raises(FormatError, match="strictly increasing") as e:
        opener()
    assert e.value.path == f and e.value.line in (4, 5)


def test_image_size_inconsistent_with_intrinsics(tmp_path):
    for i in range(3):
        write_image(tmp_path / f"{i}.png", i)
    with pytest.raises(CalibrationError, match=r"0\.png.*64x48.*100x80"):
        open_folder(tmp_path, camera=Intrinsics.from_focal(100, 80))
    write_image(tmp_path / "2.png", 2, size=(W + 8, H))  # a later frame of another size
    src = open_folder(tmp_path)
    pixel(src[1])
    with pytest.raises(CalibrationError, match=r"2\.png"):
        src[2]
    root = tmp_path / "rgbd_dataset_freiburg1_small"
    make_tum(root, n=2, size=(W, H))  # TUM calibrations are for 640x480
    with pytest.raises(CalibrationError, match="640x480"):
        open_tum(root)


def test_video_that_cannot_be_opened(tmp_path):
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00" * 1000)
    with pytest.raises(SourceError, match=r"broken\.mp4.*cannot be opened"):
        open_source(bad)
    (tmp_path / "x.txt").write_text("x")
    with pytest.raises(SourceError, match="not a video"):
        open_source(tmp_path / "x.txt")


def test_bad_options_are_config_errors(tmp_path):
    write_image(tmp_path / "a.png")
    for kw in [dict(frame_skip=0), dict(max_frames=0), dict(fps=0), dict(camera="wide")]:
        with pytest.raises(ConfigError):
            open_folder(tmp_path, **kw)
    assert issubclass(ConfigError, SlamkitError)


# ---------------------------------------------------------------------------------------------------------
# the real sequences of ../shared/data
# ---------------------------------------------------------------------------------------------------------
@pytest.mark.shared_data
def test_real_7scenes_redkitchen():
    root = shared_data("7scenes-redkitchen")
    src = open_source(root)
    assert len(src) == 600 and (src.camera.width, src.camera.height) == (640, 480)
    assert (src.camera.fx, src.camera.fy, src.camera.cx, src.camera.cy) == (585, 585, 320, 240)
    assert np.allclose(src.gt_poses[0], np.loadtxt(root / "seq-01" / "frame-000000.pose.txt"))
    f = src[599]
    assert f.gray.shape == (480, 640) and f.frame_id == 599 and abs(f.timestamp - 599 / 30) < 1e-9
    assert len(open_source(root, frame_skip=10)) == 60


@pytest.mark.shared_data
def test_real_kitti_07():
    root = shared_data("kitti-odometry")
    src = open_source(root)
    assert src.name == "kitti/07" and len(src) == 160
    assert (src.camera.width, src.camera.height, src.camera.fx) == (1226, 370, 707.0912)
    assert np.allclose(src.gt_poses[0], np.eye(4), atol=1e-9)
    row = np.loadtxt(root / "poses" / "07.txt")[100]
    assert np.allclose(src.gt_poses[100][:3].ravel(), row)
    assert src[159].gray.shape == (370, 1226)
    assert np.allclose(src.timestamps[:2], [0.0, 0.1038752])


@pytest.mark.shared_data
def test_real_tum_fr1_desk_all_frames_have_ground_truth():
    src = open_source(shared_data("tum/rgbd_dataset_freiburg1_desk_9frames"))
    assert len(src) == 9 and src.camera == TUM_CALIBRATIONS["fr1"]
    assert np.isfinite(src.gt_poses).all() and len(src.ground_truth()) == 9
    assert src[8].gray.shape == (480, 640)


@pytest.mark.shared_data
def test_real_tum_fr3_first_frame_before_ground_truth():
    src = open_source(shared_data("tum/rgbd_dataset_freiburg3_long_office_household_4frames"))
    assert len(src) == 4 and src.camera == TUM_CALIBRATIONS["fr3"]
    has = np.isfinite(src.gt_poses).all(axis=(1, 2))
    assert list(has) == [False, True, True, True]
    assert src[0].gt_pose is None and src[1].gt_pose is not None


@pytest.mark.shared_data
def test_real_video_with_frame_skip():
    path = shared_data("video/test_kitti984.mp4")
    src = open_source(path)
    assert len(src) == 268 and (src.camera.width, src.camera.height) == (1242, 375)
    src = open_source(path, frame_skip=4, max_frames=10, camera=984.0)
    assert len(src) == 10 and list(src.frame_ids) == list(range(0, 40, 4))
    assert np.allclose(src.timestamps, src.frame_ids / 30.0) and src.camera.fx == 984.0
    later = src[5].gray.copy()
    first = src[0].gray.copy()  # re-seek backwards
    assert np.array_equal(src[5].gray, later) and first.shape == (375, 1242)


# ---------------------------------------------------------------------------------------------------------
# calibration given before opening: camera= (a --camera text) and camera.txt (issue 21)
# ---------------------------------------------------------------------------------------------------------
CAMERA_TXT = "# fx fy cx cy k1 k2 p1 p2\n\n52.0, 53.0 30.5 22.5 -0.1 0.01 0.001 -0.002  # calibrated\n"
TXT_CAM = Intrinsics(W, H, 52.0, 53.0, 30.5, 22.5, (-0.1, 0.01, 0.001, -0.002, 0.0))


def _layouts(root: Path) -> dict[str, tuple[Path, Path]]:
    """{layout: (path to open, folder where camera.txt goes)} for every file-based layout, 64x48 images."""
    folder = root / "images"
    for i in range(3):
        write_image(folder / f"{i}.png", 10 * i)
    tum = root / "my_recording"  # a TUM layout whose name says no freiburg sensor
    make_tum(tum, n=3, gt=False, size=(W, H))
    make_kitti(root / "kitti", n=3)
    make_euroc(root / "euroc", n=3)
    make_7scenes(root / "7scenes", n=2, seqs=("seq-01",), intrinsics=None, ext="png")
    for p in (root / "7scenes" / "seq-01").glob("*.color.png"):  # 7-Scenes images are 640x480: make them W x H
        write_image(p, 0)
    (root / "video").mkdir()
    video = make_video(root / "video" / "clip.avi")
    kitti, scenes = root / "kitti" / "sequences" / "03", root / "7scenes" / "seq-01"
    return {"folder": (folder, folder), "tum": (tum, tum), "kitti": (kitti, kitti / "image_0"),
            "euroc": (root / "euroc", root / "euroc" / "mav0" / "cam0"), "7scenes": (scenes, scenes),
            "video": (video, video.parent)}


def test_every_layout_reads_camera_txt_and_camera_text_wins(tmp_path):
    for layout, (path, calib_dir) in _layouts(tmp_path).items():
        given = open_source(path, camera="40,41,30,20,0.05,0,0,0")
        assert given.camera == Intrinsics(W, H, 40.0, 41.0, 30.0, 20.0, (0.05, 0, 0, 0, 0)), layout
        assert open_source(path, camera="45").camera == Intrinsics.from_focal(W, H, 45.0), layout
        (calib_dir / "camera.txt").write_text(CAMERA_TXT)
        assert open_source(path).camera == TXT_CAM, layout
        assert open_source(path, camera="40,41,30,20").camera.fx == 40.0, layout  # camera= before camera.txt
        assert open_source(f"{layout}:{path}").camera == TXT_CAM, layout


def test_tum_layout_without_sensor_name_opens_with_camera(tmp_path):
    root = tmp_path / "converted_sequence"
    make_tum(root, n=4, size=(W, H))
    with pytest.raises(CalibrationError, match="freiburg"):
        open_source(root)
    src = open_source(root, camera="50,51,31.5,23.5")
    assert src.camera == CAM and len(src) == 4 and src.gt_poses is not None
    with pytest.raises(CalibrationError, match="640x480"):  # a sensor name is still the built-in calibration
        open_source(root, camera="fr3")
    (root / "camera.txt").write_text("50 51 31.5 23.5\n")
    assert open_source(root).camera == CAM
    assert open_source(root, camera="").camera == CAM  # SlamConfig.camera's default: no camera given
    with pytest.raises(ConfigError, match="camera"):
        open_source(root, camera="50,51,31.5")


@pytest.mark.parametrize("content, line, match", [
    ("50 51 31.5\n", 1, "3 numbers"),
    ("# comment\n50 51 31.5 23.5 x 0 0 0\n", 2, "not a number"),
    ("50 51 31.5 23.5\n50 51 31.5 23.5\n", 2, "exactly one line"),
    ("# nothing\n", None, "exactly one line"),
    ("50\n", 1, "got 1"),
])
def test_malformed_camera_txt_names_file_and_line(tmp_path, content, line, match):
    folder = tmp_path / "images"
    write_image(folder / "0.png")
    (folder / "camera.txt").write_text(content)
    with pytest.raises(FormatError, match=match) as info:
        open_source(folder)
    assert info.value.path == folder / "camera.txt" and info.value.line == line


def test_camera_txt_for_another_image_size_is_calibration_error(tmp_path):
    folder = tmp_path / "images"
    write_image(folder / "0.png")
    (folder / "camera.txt").write_text("500 500 320 240\n")
    with pytest.raises(CalibrationError, match="camera.txt:1"):
        open_source(folder)
