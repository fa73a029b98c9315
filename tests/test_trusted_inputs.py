"""Trustworthy inputs (issue 40): names are bytes, a video is read once and forward with its true frame times,
numbers as names in time order, a calibration checked against the images, ground truth that is not a rotation
refused. Every file is real (written here with OpenCV, or with FFmpeg where it is installed)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from slamkit.camera import Intrinsics
from slamkit.config import SlamConfig
from slamkit.errors import CalibrationError, FormatError, ImageReadError
from slamkit.pipeline import Slam
from slamkit.sources import open_folder, open_kitti, open_source, open_video
from slamkit.sources.base import MAX_IMAGE_BYTES, read_image
from slamkit.sources.calibration import camera_from_path, read_camera_txt, write_camera_txt
from slamkit.sources.euroc import read_euroc_groundtruth
from slamkit.sources.groundtruth import read_tum_trajectory
from slamkit.sources.kitti import read_kitti_poses
from slamkit.sources.sevenscenes import read_pose_matrix
from slamkit.sources.tum import TUM_CALIBRATIONS

from conftest import shared_data
from test_sources import make_kitti

pycolmap.logging.minloglevel = 2

W, H, BITS = 320, 240, 7
FFMPEG = shutil.which("ffmpeg")
needs_ffmpeg = pytest.mark.skipif(FFMPEG is None, reason="ffmpeg is not installed (apt-get install ffmpeg); "
                                                          "these videos are written with it")


# ----------------------------------------------------------------------------- frames that say their number
def coded_frame(k: int) -> np.ndarray:
    """A textured 320x240 BGR frame whose top band holds ``k`` in 7 black/white blocks (survives compression)."""
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur((rng.random((H, 2 * W)) * 255).astype(np.uint8), (0, 0), 1.5)
    img = np.ascontiguousarray(texture[:, 3 * k: 3 * k + W])
    img[:48] = 0
    for b in range(BITS):
        if (k >> b) & 1:
            img[:48, b * (W // BITS): (b + 1) * (W // BITS)] = 255
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def frame_number(gray: np.ndarray) -> int:
    """The number :func:`coded_frame` wrote into a decoded (grey) frame."""
    band = gray[8:40].astype(np.float64)
    return sum(1 << b for b in range(BITS) if band[:, b * (W // BITS) + 8: (b + 1) * (W // BITS) - 8].mean() > 128)


def write_avi(path: Path, n: int = 40, fps: float = 25.0) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
    assert writer.isOpened()
    for k in range(n):
        writer.write(coded_frame(k))
    writer.release()
    return path


def ffmpeg(*args: str) -> None:
    subprocess.run([FFMPEG, "-v", "error", "-y", *args], check=True, capture_output=True, timeout=120)


def encoded(tmp_path: Path, name: str, *options: str, n: int = 60, fps: float = 30.0) -> Path:
    """``n`` coded frames (an MJPG avi by OpenCV) re-encoded by FFmpeg with ``options``: H.264 (MPEG-4 part 2
    where FFmpeg is built without x264); ``-fps_mode`` is ``-vsync`` before FFmpeg 5.1."""
    avi = write_avi(tmp_path / "frames.avi", n=n, fps=fps)
    out = tmp_path / name
    tries = [("libx264", options), ("mpeg4", options)]
    if "-fps_mode" in options:
        old = tuple("-vsync" if o == "-fps_mode" else o for o in options)
        tries += [("libx264", old), ("mpeg4", old)]
    for codec, opts in tries:
        try:
            ffmpeg("-i", str(avi), *opts, "-c:v", codec, "-pix_fmt", "yuv420p", "-g", "10", str(out))
            return out
        except subprocess.CalledProcessError as e:
            error = e.stderr.decode(errors="replace")
    pytest.fail(f"ffmpeg could not write {name}: {error}")


def numbers(source, indices) -> list[int]:
    return [frame_number(source[i].gray) for i in indices]


# ----------------------------------------------------------------------------- rule 1: names are bytes
BAD = b"0005\xfe"


def test_an_image_whose_name_is_not_utf8_is_read_and_a_bad_one_named(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for k in range(6):
        name = (BAD if k == 5 else b"%04d" % k) + b".png"
        (folder / os.fsdecode(name)).write_bytes(cv2.imencode(".png", coded_frame(k))[1].tobytes())
    src = open_folder(folder)
    assert numbers(src, range(6)) == list(range(6))  # decoded from memory: OpenCV never sees the name
    assert os.fsencode(src.paths[5].name) == BAD + b".png"
    (folder / os.fsdecode(BAD + b".png")).write_bytes(b"\x89PNG\r\n\x1a\n broken")
    with pytest.raises(ImageReadError) as err:
        src[5]
    text = str(err.value)
    assert "0005\\xfe.png" in text and text.encode("utf-8")  # shown, and printable / savable as UTF-8
    assert os.fsencode(err.value.path) == os.fsencode(src.paths[5])  # the real name is kept


def test_an_image_file_is_read_by_python_with_its_size_bounded(tmp_path):
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(ImageReadError, match=r"empty\.png: is empty \(0 bytes\)"):
        read_image(empty)
    huge = tmp_path / "huge.png"
    with open(huge, "wb") as f:  # sparse: no disk space used
        f.truncate(MAX_IMAGE_BYTES + 1)
    with pytest.raises(ImageReadError, match=r"huge\.png: is 1\.0 GiB, larger than any image slamkit reads"):
        read_image(huge)
    os.mkfifo(tmp_path / "pipe.png")
    with pytest.raises(ImageReadError, match=r"pipe\.png: is not a regular file"):
        read_image(tmp_path / "pipe.png")


def test_a_folder_and_a_video_whose_names_are_not_utf8(tmp_path, monkeypatch):
    folder = tmp_path / os.fsdecode(b"dir\xff")
    folder.mkdir()
    for k in range(3):
        cv2.imwrite(str(tmp_path / "x.png"), coded_frame(k))
        (tmp_path / "x.png").rename(folder / f"{k:03d}.png")
    src = open_source(str(folder))
    assert numbers(src, range(3)) == [0, 1, 2]
    assert src.name == "folder/dir\\xff" and repr(src).encode("utf-8")
    video = write_avi(tmp_path / "clip.avi", n=12)
    named = video.rename(tmp_path / os.fsdecode(b"clip\xfe:%d.avi"))  # not UTF-8, a protocol and a pattern
    links = tmp_path / "tmp"
    links.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(links))
    src = open_source(str(named))
    assert type(src).__name__ == "VideoSource" and len(src) == 12
    assert numbers(src, [0, 5, 11, 2]) == [0, 5, 11, 2]
    assert src.name == "video/clip\\xfe:%d" and list(links.iterdir()) == []  # the temporary links are gone


def test_a_run_on_a_folder_with_such_a_name_exits_normally(tmp_path):
    """End to end in a child process (a crash inside OpenCV would kill it): the bad-named image that is
    corrupt is skipped with its name shown, the others are read, the run folder is written."""
    folder = tmp_path / os.fsdecode(b"seq\xff")
    folder.mkdir()
    for k in range(8):
        name = (BAD if k == 5 else b"%04d" % k) + b".png"
        (folder / os.fsdecode(name)).write_bytes(cv2.imencode(".png", coded_frame(k))[1].tobytes())
    (folder / os.fsdecode(BAD + b".png")).write_bytes(b"not an image")
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "slamkit.cli", "run", os.fsencode(folder), "--camera", "300",
                        "--out", str(out)], capture_output=True, timeout=300, env={**os.environ, "PYTHONPATH": str(
                            Path(__file__).resolve().parents[1])})
    stderr = r.stderr.decode(errors="replace")
    assert r.returncode >= 0 and "Traceback" not in stderr, stderr[-2000:]  # no crash, no traceback
    summary = json.loads((out / "summary.json").read_text())
    [bad] = summary["unreadable_frames"]
    assert bad["frame_id"] == 5 and "seq\\xff/0005\\xfe.png: could not be decoded" in bad["error"]


# ----------------------------------------------------------------------------- rule 2: videos
def test_a_video_is_read_forward_and_asked_again_gives_the_same_frames(tmp_path):
    src = open_video(write_avi(tmp_path / "clip.avi", n=40, fps=25.0))
    assert len(src) == 40 and src.n_decodable == 40 and src.timestamps_from == "container"
    assert np.allclose(src.timestamps, np.arange(40) / 25.0, atol=1e-6)
    order = list(range(30)) + list(range(40)) + [39, 3, 17, 17, 0]  # a calibration pass, the run, then jumps
    assert numbers(src, order) == order
    src = open_video(tmp_path / "clip.avi", frame_skip=3, max_frames=5)
    assert list(src.frame_ids) == [0, 3, 6, 9, 12] and numbers(src, range(5)) == [0, 3, 6, 9, 12]
    assert np.allclose(src.timestamps, src.frame_ids / 25.0, atol=1e-6)
    src = open_video(tmp_path / "clip.avi", fps=10)  # an fps given: frame number / fps
    assert src.timestamps_from == "fps" and np.allclose(src.timestamps, np.arange(40) / 10)
    src.close()
    (tmp_path / "clip.avi").unlink()  # gone since it was opened: the frame is skipped with the reason
    with pytest.raises(ImageReadError, match=r"clip\.avi: frame 2 cannot be read: .*does not exist"):
        src[2]


@needs_ffmpeg
def test_a_transport_stream_gives_the_same_frames_to_the_calibration_and_the_run(tmp_path):
    path = encoded(tmp_path, "clip.ts", "-f", "mpegts")
    src = open_video(path)
    assert len(src) == 60 and np.allclose(src.timestamps, np.arange(60) / 30.0, atol=1e-3)
    assert numbers(src, list(range(60)) + list(range(60))) == list(range(60)) * 2  # seeking back fails in .ts
    # the pipeline's own access: the self-calibration pass over the first frames, then the run from frame 0
    slam = Slam(open_video(path), SlamConfig(camera="auto", prefetch=False))
    slam.calibrate()
    for k in range(3):
        slam.step()
        assert slam.last_frame is not None and frame_number(slam.last_frame.gray) == k


@needs_ffmpeg
def test_an_mp4_cut_short_gives_no_frame_twice_and_names_the_missing_ones(tmp_path):
    full = encoded(tmp_path, "full.mp4", "-movflags", "faststart")
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size * 35 // 100])  # the index (at the front) lists 60
    src = open_video(cut)
    n = src.n_decodable
    assert 0 < n < 60 and len(src) == 60 and src.n_announced == 60
    assert numbers(src, range(n)) == list(range(n))
    for i in [n, n + 1, 59]:
        with pytest.raises(ImageReadError, match=rf"cut\.mp4: frame {i} could not be decoded: .*cut short"):
            src[i]
    assert numbers(src, [n - 1, 0]) == [n - 1, 0]
    slam = Slam(open_video(cut), SlamConfig(camera="300", prefetch=False))
    results = slam.run()
    assert [r.status for r in results[n:]] == ["skipped"] * (60 - n)
    assert slam.summary()["frames_unreadable"] == 60 - n


@needs_ffmpeg
def test_a_variable_frame_rate_video_has_its_true_frame_times(tmp_path):
    # 30 frames at 30 fps, then 30 at 10 fps (as a phone slows down in the dark)
    path = encoded(tmp_path, "vfr.mkv", "-vf", "setpts='if(lt(N,30),N/30,1+(N-30)/10)/TB'",
                   "-fps_mode", "passthrough")
    src = open_video(path)
    truth = np.where(np.arange(60) < 30, np.arange(60) / 30, 1 + (np.arange(60) - 30) / 10)
    assert len(src) == 60 and src.timestamps_from == "container"
    assert np.abs(src.timestamps - truth).max() < 2e-3  # the container rounds to milliseconds
    assert numbers(src, [0, 45, 59, 10]) == [0, 45, 59, 10]


# ----------------------------------------------------------------------------- rule: numbers as names in time order
def test_numbers_as_names_are_taken_in_time_order(tmp_path):
    times = [0.05, 0.1, 0.15, 0.2, 0.25, 0.5, 1.0, 1.05, 2.0, 10.0, 10.5]
    names = ["0.05", "0.1", "0.15", "0.2", "0.25", "0.5", "1", "1.05", "2", "10", "10.5"]
    folder = tmp_path / "stamps"
    folder.mkdir()
    for k, name in sorted(enumerate(names), key=lambda e: e[1]):  # written in lexicographic order
        cv2.imwrite(str(folder / f"{name}.png"), coded_frame(k))
    src = open_folder(folder)
    assert [float(p.stem) for p in src.paths] == times
    assert numbers(src, range(len(names))) == list(range(len(names)))
    for k in range(3):  # integers keep their natural order; other names too
        cv2.imwrite(str(folder / f"frame{[2, 10, 1][k]}.png"), coded_frame(k))
    src = open_folder(folder, pattern="frame*.png")
    assert [p.name for p in src.paths] == ["frame1.png", "frame2.png", "frame10.png"]


# ----------------------------------------------------------------------------- rule 5: a calibration fits the images
def test_a_camera_of_another_image_size_is_refused_naming_both(tmp_path):
    run = tmp_path / "kitti_run"
    run.mkdir()
    write_camera_txt(run / "camera.txt", Intrinsics(1226, 370, 707.09, 707.09, 601.9, 183.1), "a run's camera")
    assert read_camera_txt(run / "camera.txt", 1226, 370).fx == 707.09
    folder = tmp_path / "imgs"
    folder.mkdir()
    for k in range(2):
        cv2.imwrite(str(folder / f"{k}.png"), cv2.resize(coded_frame(k), (640, 480)))
    with pytest.raises(CalibrationError, match=r"camera\.txt:2: the calibration is for 1226x370 images but the "
                                               r"images are 640x480"):
        Slam(open_folder(folder), SlamConfig(camera=str(run)))
    (run / "camera.txt").write_text("707.09 707.09 601.9 183.1\n")  # written before runs recorded the size
    with pytest.raises(CalibrationError, match=r"principal point \(601\.9, 183\.1\) is far from the centre of "
                                               r"the 640x480 images"):
        camera_from_path(run, 640, 480)
    (run / "camera.txt").write_text("500 500 700 240\n")
    with pytest.raises(CalibrationError, match=r"principal point \(700.*outside the 640x480 image"):
        camera_from_path(run, 640, 480)


@pytest.mark.parametrize("text, name", [("500,500,320,240,0,0,0,0,1e6", "k3"),  # stretches the corner 6x
                                        ("500,500,320,240,10,0,0,0,0", "k1"),  # 2.3x
                                        ("500,500,320,240,-0.5,0,0,0,0", "k1"),  # folds back inside the image
                                        ("500,500,320,240,0,-1,0,0,0", "k2"),
                                        ("500,500,320,240,0.1,0,0,0,-2", "k3"),
                                        ("500,500,320,240,0,0,0.5,0,0", "p1")])
def test_distortion_that_no_lens_produces_is_refused_naming_the_coefficient(tmp_path, text, name):
    with pytest.raises(CalibrationError, match=rf"distortion {name}=\S+ is not what a lens produces"):
        Intrinsics.parse(text, 640, 480)
    (tmp_path / "camera.txt").write_text(text.replace(",", " ") + "\n")
    with pytest.raises(CalibrationError, match=rf"camera\.txt:1.*distortion {name}="):
        read_camera_txt(tmp_path / "camera.txt", 640, 480)
    folder = tmp_path / "imgs"
    folder.mkdir()
    cv2.imwrite(str(folder / "0.png"), cv2.resize(coded_frame(0), (640, 480)))
    values = [float(v) for v in text.split(",")]
    with pytest.raises(CalibrationError, match=rf"distortion {name}="):
        open_folder(folder, camera=Intrinsics(640, 480, *values[:4], dist=tuple(values[4:])))


def test_distortion_of_real_lenses_is_accepted_and_undone_exactly():
    cameras = list(TUM_CALIBRATIONS.values())  # fr1 and fr2: k1 0.26, k2 -0.95, k3 1.16
    cameras.append(Intrinsics(752, 480, 458.654, 457.296, 367.215, 248.375,  # EuRoC cam0
                              (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0)))
    cameras.append(Intrinsics(1392, 512, 959.79, 956.93, 696.02, 224.18,  # a KITTI raw colour camera
                              (-0.3691481, 0.1968681, 0.001353473, 0.0005677587, -0.06770705)))
    for camera in cameras:
        camera.check_distortion()
        w, h = camera.width, camera.height
        t = np.linspace(0, 1, 33)[:, None]
        border = np.concatenate([t * [w, 0], [w, 0] + t * [0, h], [w, h] - t * [w, 0], t * [0, h]])
        back = camera.distort_points(camera.undistort_points(border))
        assert np.abs(back - border).max() < 1e-3  # OpenCV's default 5 steps: up to 2.9 px off (KITTI raw)
    for text in ["585,585,320,240,-0.025,0,0,0,0", "500,500,320,240,-0.3,0.1,0,0,0", "500,500,320,240,0.1,0,0,0,0",
                 "500,500,320,240,-0.2,0,0.001,-0.002,0", "500,500,320,240,0,0,0,0,0.5"]:
        Intrinsics.parse(text, 640, 480)


# ----------------------------------------------------------------------------- silently wrong: skew, rotations
def test_kitti_calibration_with_skew_is_refused_naming_the_line(tmp_path):
    root = tmp_path / "kitti"
    make_kitti(root, n=2)
    calib = next(root.rglob("calib.txt"))
    lines = calib.read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if line.startswith("P0:"))
    values = lines[k].split()
    values[2] = "0.5"  # P0[0, 1]: skew
    lines[k] = " ".join(values)
    calib.write_text("\n".join(lines) + "\n")
    with pytest.raises(CalibrationError, match=rf"calib\.txt:{k + 1}: P0 .*skew P\[0,1\]=0\.5"):
        open_kitti(root)


def test_kitti_calibration_and_poses_of_the_real_sequence_pass(tmp_path):
    data = shared_data("kitti-odometry")
    src = open_kitti(data, sequence="07")
    assert src.gt_poses is not None and len(src) == 160


def _refused(path: Path, line: int, reader) -> None:
    with pytest.raises(FormatError) as err:
        reader(path)
    assert err.value.path == path and err.value.line == line and "rotation" in str(err.value)


def test_ground_truth_rotations_that_are_not_rotations_are_refused_naming_the_line(tmp_path):
    # KITTI poses: line 2 holds a rotation scaled by 2, line 3 a reflection
    eye = "1 0 0 0 0 1 0 0 0 0 1 0"
    kitti = tmp_path / "07.txt"
    kitti.write_text(f"{eye}\n2 0 0 1 0 2 0 0 0 0 2 0\n{eye}\n")
    _refused(kitti, 2, read_kitti_poses)
    kitti.write_text(f"{eye}\n{eye}\n-1 0 0 0 0 1 0 0 0 0 1 0\n")
    _refused(kitti, 3, read_kitti_poses)
    kitti.write_text(f"{eye}\n1.0001 0 0 0 0 1 0 0 0 0 0.9999 0\n")  # rounding is fine
    assert read_kitti_poses(kitti).shape == (2, 4, 4)
    # TUM: a quaternion of norm 2 (columns in another order, or not a rotation)
    tum = tmp_path / "groundtruth.txt"
    tum.write_text("# timestamp tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1.2 1.6\n")
    with pytest.raises(FormatError, match=r"groundtruth\.txt:3: quaternion \(qx qy qz qw\) has norm 2"):
        read_tum_trajectory(tum)
    tum.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0.6 0.8\n3.0 0 0 0 0.0001 0 0 0.9999\n")
    assert read_tum_trajectory(tum)[1].shape == (3, 4, 4)
    # EuRoC: timestamp, p, q (w x y z), then velocities and biases
    euroc = tmp_path / "data.csv"
    euroc.write_text("#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z\n1000,0,0,0,1,0,0,0\n2000,0,0,0,0.5,0,0,0\n")
    with pytest.raises(FormatError, match=r"data\.csv:3: quaternion \(q_w q_x q_y q_z\) has norm 0\.5"):
        read_euroc_groundtruth(euroc)
    # 7-Scenes: a sheared matrix, and a last row that is not 0 0 0 1
    pose = tmp_path / "frame-000000.pose.txt"
    pose.write_text("1 0.3 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    _refused(pose, 1, read_pose_matrix)
    pose.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n")
    with pytest.raises(FormatError, match=r"pose\.txt:4: the last row of a pose is 0 0 0 1"):
        read_pose_matrix(pose)
    pose.write_text("-inf -inf -inf -inf\n-inf -inf -inf -inf\n-inf -inf -inf -inf\n0 0 0 1\n")
    assert np.isnan(read_pose_matrix(pose)).all()  # tracking lost in the recording: no pose, not an error


def test_the_real_ground_truth_files_pass():
    data = shared_data("7scenes-redkitchen")
    for f in sorted((data / "seq-01").glob("frame-*.pose.txt"))[::50]:
        read_pose_matrix(f)
    tum = shared_data("tum") / "rgbd_dataset_freiburg1_desk_9frames" / "groundtruth.txt"
    t, poses = read_tum_trajectory(tum)
    assert len(t) > 1000
