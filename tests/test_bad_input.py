"""Bad input (issue 7): each case gives a clear message or status, and no work done before it is lost.

Cases covered elsewhere and not repeated here: a corrupt image when accessed directly, a non-finite KITTI
``calib.txt`` value, a frame of another size than the first in a folder or video (tests/test_sources.py);
black frames in the middle of a run, a bad single configuration value (tests/test_pipeline.py).
"""

from __future__ import annotations

import json
import os
import re
import zipfile
from dataclasses import replace

import cv2
import numpy as np
import pycolmap
import pytest

from slamkit.ablate import sweep
from slamkit.camera import Intrinsics
from slamkit.cli import main
from slamkit.config import SlamConfig
from slamkit.errors import CalibrationError, ConfigError, OutputError, SlamkitError, SourceError
from slamkit.eval import ate
from slamkit.features.learned.weights import check_weight_file, load_error_reason
from slamkit.pipeline import Slam
from slamkit.sources import open_euroc, open_kitti, open_sevenscenes, open_source, open_video
from slamkit.sources.base import ImageListSource, read_image
from slamkit.sources.scene import default_room
from slamkit.sources.synthetic import SyntheticSource, open_tum_sequence, synthetic_source, write_tum_sequence

from test_sources import make_7scenes, make_euroc, make_kitti, make_tum, make_video

pycolmap.logging.minloglevel = 2

INIT = {"init_frames": 10}
RUN_MARKER_NAME = ".slamkit-run"


@pytest.fixture(scope="module")
def handheld_folder(tmp_path_factory):
    """40 frames of the hand-held motion written as PNG files (TUM layout with camera.json)."""
    folder = tmp_path_factory.mktemp("seq") / "handheld"
    write_tum_sequence(synthetic_source("handheld", frames=40), folder)
    return folder


# ----------------------------------------------------------------------------- corrupt image mid-sequence
def test_corrupt_image_in_the_middle_is_skipped_and_the_run_goes_on_in_the_same_map(handheld_folder, tmp_path):
    import shutil

    folder = tmp_path / "seq"
    shutil.copytree(handheld_folder, folder)
    src = open_tum_sequence(folder)
    bad = src.paths[25]
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"truncated" * 20)
    slam = Slam(src, SlamConfig().with_overrides(**INIT))
    results = slam.run()  # no exception
    r = results[25]
    assert r.status == "skipped" and not r.has_pose
    assert bad.name in r.message and "could not be decoded" in r.message
    s = slam.summary()
    assert s["frames_unreadable"] == 1 and s["frames_skipped"] == 1
    assert s["unreadable_frames"][0]["frame"] == 25 and bad.name in s["unreadable_frames"][0]["error"]
    assert len(s["segments"]) == 1  # the same map before and after the bad frame
    assert all(x.status == "tracked" for x in results[26:])
    assert s["frames_posed"] == 39
    assert ate(src.ground_truth(), slam.trajectory()).rmse < 0.01
    slam.save(tmp_path / "run")
    saved = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert saved["unreadable_frames"] == s["unreadable_frames"]


# ----------------------------------------------------------------------------- sequence shorter than the window
def test_sequence_shorter_than_the_init_window_is_tried_at_its_end(tmp_path):
    # 6 frames of a 20-frame window: the best pair is tried when the sequence ends and every frame is posed,
    # spaced as in the ground truth (sideways motion is on one line, so compare distances along it)
    src = open_source("synthetic:sideways?frames=6")
    slam = Slam(src, SlamConfig())  # init_frames = 20
    results = slam.run()  # no exception
    assert [r.status for r in results[:5]] == ["initializing"] * 5
    assert results[4].message == "buffered 5/20 frames"
    assert results[-1].has_pose and slam.summary()["frames_posed"] == 6
    est, gt = slam.trajectory().positions, src.ground_truth().positions
    d_est, d_gt = (np.linalg.norm(p - p[0], axis=1) for p in (est, gt))
    np.testing.assert_allclose(d_est / d_est[-1], d_gt / d_gt[-1], atol=0.08)  # 64 points, 1.1 deg parallax: 5 % off
    # 4 frames: too little parallax for any pair; nothing is posed and the summary says why
    src = open_source("synthetic:sideways?frames=4")
    slam = Slam(src, SlamConfig())
    results = slam.run()
    assert len(results) == 4 and not any(r.has_pose for r in results)
    s = slam.summary()
    assert s["frames_posed"] == 0 and s["segments"] == []
    why = s["not_initialized_reason"]
    assert why.startswith("no initial pair found; last attempt: no initial pair in frames 0-3 (") and \
        why.endswith("the sequence ended"), why
    slam.save(tmp_path / "run")  # an empty result is still written
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["not_initialized_reason"] == why


# ----------------------------------------------------------------------------- intrinsics / image size
def test_intrinsics_that_do_not_fit_the_images_name_the_calibration(tmp_path):
    # 7-Scenes: camera-intrinsics.txt for 640x480 images beside 64x48 images
    make_7scenes(tmp_path / "7s", n=2, seqs=("seq-01",))
    for p in (tmp_path / "7s" / "seq-01").glob("*.color.png"):
        cv2.imwrite(str(p), np.zeros((48, 64, 3), np.uint8))
    with pytest.raises(CalibrationError, match=r"camera-intrinsics\.txt.*\(321\.0, 241\.0\).*64x48"):
        open_sevenscenes(tmp_path / "7s")
    # KITTI: a calib.txt of 1226x370 images (principal point 601, 183) beside 640x480 images: the principal
    # point lies inside the image but far from its centre
    make_kitti(tmp_path / "kitti", "00", n=2)
    seq = tmp_path / "kitti" / "sequences" / "00"
    for p in seq.glob("image_*/*.png"):
        cv2.imwrite(str(p), np.zeros((480, 640), np.uint8))
    P = "707.0912 0 601.8873 0 0 707.0912 183.1104 0 0 0 1 0"
    (seq / "calib.txt").write_text("".join(f"P{k}: {P}\n" for k in range(4)))
    with pytest.raises(CalibrationError, match=r"calib\.txt.*principal point \(601\.9, 183\.1\).*640x480"):
        open_kitti(tmp_path / "kitti")
    # EuRoC: sensor.yaml resolution differs from the images
    make_euroc(tmp_path / "euroc", n=2)
    yaml = tmp_path / "euroc" / "mav0" / "cam0" / "sensor.yaml"
    yaml.write_text(yaml.read_text().replace("resolution: [64, 48]", "resolution: [752, 480]")
                    .replace("31.5, 23.5", "367.2, 248.4"))
    with pytest.raises(CalibrationError, match=r"sensor\.yaml.*752x480.*64x48"):
        open_euroc(tmp_path / "euroc")
    # a sequence written by write_tum_sequence whose camera.json says another size
    folder = write_tum_sequence(synthetic_source("sideways", frames=2, scale=0.25), tmp_path / "tum")
    cam = json.loads((folder / "camera.json").read_text())
    (folder / "camera.json").write_text(json.dumps({**cam, "width": 640, "height": 480, "cx": 319.5, "cy": 239.5}))
    with pytest.raises(CalibrationError, match=r"camera\.json.*160x120.*640x480"):
        open_tum_sequence(folder)


@pytest.mark.parametrize("text", ["500", "500,500,320,240", "500 500 320 240 0 0 0 0", "(500, 500, 320, 240, 0, 0, 0, 0, 0)"])
def test_camera_given_for_an_uncalibrated_folder_replaces_the_guess(handheld_folder, text):
    """A plain image folder has guessed intrinsics (focal 1.2 x 640 = 768 px); SlamConfig.camera (CLI
    --camera) gives the true ones (the synthetic camera: 500 px, centred), used by the map and saved."""
    src = open_source(handheld_folder / "rgb", max_frames=30)
    assert src.camera.fx == pytest.approx(768.0)
    slam = Slam(src, SlamConfig(camera=text).with_overrides(**INIT))
    assert (slam.camera.fx, slam.camera.fy, slam.camera.cx, slam.camera.cy) == (500, 500, 320, 240)
    slam.run()
    slam.finish()
    gt = synthetic_source("handheld", frames=30).ground_truth()
    traj = slam.trajectory()
    assert len(traj) == 30
    assert ate(gt, traj).rmse < 0.01
    assert list(slam.slam_map.reconstruction.camera(1).params) == [500, 500, 320, 240]


@pytest.mark.parametrize("text, error, match", [
    ("500,500", ConfigError, r"camera: expected F .* got '500,500': 2 numbers"),
    ("f=500", ConfigError, r"camera: .*not a number"),
    ("-500", ConfigError, r"camera: .*focal lengths must be positive"),
    ("500,500,nan,240", ConfigError, r"camera: .*not finite"),
    ("500,500,900,240", CalibrationError, r"camera='500,500,900,240': .*principal point \(900\.0, 240\.0\) lies outside the 640x480"),
])
def test_bad_camera_text_names_the_parameter(handheld_folder, text, error, match):
    with pytest.raises(error, match=match):
        Slam(open_source(handheld_folder / "rgb"), SlamConfig(camera=text).validate())


# ----------------------------------------------------------------------------- no motion at all
def test_all_frames_identical_never_initializes_and_says_why(tmp_path):
    pose = synthetic_source("sideways", frames=2).gt_poses[0]
    src = SyntheticSource(default_room(), np.repeat(pose[None], 24, axis=0), noise=1.0, name="still")
    slam = Slam(src, SlamConfig().with_overrides(**INIT))
    results = slam.run()  # no exception from pycolmap on zero baseline
    assert all(r.status == "initializing" and not r.has_pose for r in results)
    failed = [r for r in results if "no initial pair" in r.message]
    assert failed and all("parallax" in r.message for r in failed)
    s = slam.summary()
    assert s["frames_posed"] == 0 and s["segments"] == []
    assert "parallax" in s["not_initialized_reason"]
    slam.save(tmp_path / "run")


# ----------------------------------------------------------------------------- video with a changing resolution
def _video_with_a_resolution_change(path, sizes=((160, 120), (192, 144)), n=4):
    """A video whose resolution changes: MPEG-TS parts of different sizes (cv2.VideoWriter), concatenated
    (a transport stream may change its parameters, e.g. when a recording is appended)."""
    data = b""
    for k, (w, h) in enumerate(sizes):
        part = path.with_name(f"part{k}.ts")
        writer = cv2.VideoWriter(str(part), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"MPG2"), 25.0, (w, h))
        if not writer.isOpened():
            pytest.skip("OpenCV cannot write MPEG-2 transport streams here")
        for i in range(n):
            img = np.full((h, w, 3), 40 * i + 100 * k, np.uint8)
            img[:: 8 * (k + 1)] = 255
            writer.write(img)
        writer.release()
        data += part.read_bytes()
    path.write_bytes(data)
    return path


def test_video_with_a_changing_resolution(tmp_path):
    path = _video_with_a_resolution_change(tmp_path / "clip.ts")
    src = open_video(path, exact_count=True)
    n = len(src)
    assert n > 4 and (src.camera.width, src.camera.height) == (160, 120)  # frames after the change are there
    # depending on codec and OpenCV version, frames after the change cannot be decoded, are scaled to the
    # first size, or come in another size (refused by the source): no exception escapes a run, and a frame
    # that cannot be used is skipped with a message naming the file and the frame
    slam = Slam(src, SlamConfig().with_overrides(**INIT))
    results = slam.run()
    assert len(results) == n
    for r in results:
        assert r.status in ("initializing", "skipped")
        if r.status == "skipped" and "bad frame" in r.message:
            assert re.search(rf"clip\.ts[,:] frame {r.frame_id}\b", r.message), r.message
    assert slam.summary()["frames_unreadable"] == sum("bad frame" in r.message for r in results)
    # a decoded frame of another size than the intrinsics is skipped with a message naming file and frame
    src = open_video(make_video(tmp_path / "clip.avi", n=8, size=(160, 120)))
    read = type(src)._read

    def bigger_from_frame_5(self, i):
        image, p = read(self, i)
        return (cv2.resize(image, (192, 144)) if self.frame_ids[i] >= 5 else image), p

    src._read = bigger_from_frame_5.__get__(src)
    slam = Slam(src, SlamConfig().with_overrides(**INIT))
    results = slam.run()
    for r in results[5:]:
        assert r.status == "skipped" and not r.has_pose
        assert f"clip.avi, frame {r.frame_id}: image is 192x144 but the intrinsics are for 160x120" in r.message
    s = slam.summary()
    assert [u["frame_id"] for u in s["unreadable_frames"]] == [5, 6, 7] and s["frames_unreadable"] == 3


# ----------------------------------------------------------------------------- non-finite calibration values
def test_non_finite_calibration_values_name_file_and_line(tmp_path):
    make_7scenes(tmp_path / "7s", n=2, seqs=("seq-01",))
    (tmp_path / "7s" / "camera-intrinsics.txt").write_text("585 0 320\n0 nan 240\n0 0 1\n")
    with pytest.raises(CalibrationError, match=r"camera-intrinsics\.txt:2: .*not all finite"):
        open_sevenscenes(tmp_path / "7s")
    make_euroc(tmp_path / "euroc", n=2)
    yaml = tmp_path / "euroc" / "mav0" / "cam0" / "sensor.yaml"
    text = yaml.read_text()
    line = text.splitlines().index("intrinsics: [50.0, 51.0, 31.5, 23.5] #fu, fv, cu, cv") + 1
    yaml.write_text(text.replace("[50.0, 51.0, 31.5, 23.5]", "[50.0, inf, 31.5, 23.5]"))
    with pytest.raises(CalibrationError, match=rf"sensor\.yaml:{line}: intrinsics .*not all finite"):
        open_euroc(tmp_path / "euroc")
    folder = write_tum_sequence(synthetic_source("sideways", frames=2, scale=0.25), tmp_path / "tum")
    (folder / "camera.json").write_text((folder / "camera.json").read_text().replace('"fx": 125.0', '"fx": NaN'))
    with pytest.raises(CalibrationError, match=r"camera\.json: .*fx=nan is not a finite number"):
        open_tum_sequence(folder)


# ----------------------------------------------------------------------------- output folder not writable
@pytest.fixture(scope="module")
def small_run():
    slam = Slam(open_source("synthetic:sideways?frames=24"), SlamConfig().with_overrides(**INIT))
    slam.run()
    assert slam.summary()["frames_posed"] > 10
    return slam


def test_output_folder_that_cannot_be_created_keeps_the_map(small_run, tmp_path):
    (tmp_path / "file.txt").write_text("not a folder")
    before = small_run.summary()
    with pytest.raises(OutputError, match=r"file\.txt"):
        small_run.save(tmp_path / "file.txt" / "out")
    assert not list(tmp_path.glob("*.tmp*")) and (tmp_path / "file.txt").read_text() == "not a folder"
    out = small_run.save(tmp_path / "good")  # the in-memory map is intact: a good folder works afterwards
    saved = json.loads((out / "summary.json").read_text())
    assert saved["frames_posed"] == before["frames_posed"] and saved["keyframes"] == before["keyframes"]
    assert (out / "trajectory_tum.txt").is_file()


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0,
                    reason="running as root: file permissions do not stop root from writing")
def test_output_folder_without_write_permission_keeps_the_map(small_run, tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(OutputError, match="locked"):
            small_run.save(locked / "out")
    finally:
        locked.chmod(0o700)
    assert (small_run.save(tmp_path / "good") / "summary.json").is_file()


# ----------------------------------------------------------------------------- contradicting configuration
@pytest.mark.parametrize("values,names", [
    ({"tracker.min_inliers": 300, "min_tracked_matches": 50},
     ("tracker.min_inliers", "keyframes.min_tracked_matches")),
    ({"initializer.min_tri_angle_deg": 0.5, "ba.min_tri_angle_deg": 1.0},
     ("initializer.min_tri_angle_deg", "ba.min_tri_angle_deg")),
    ({"mapper.min_keyframe_points": 2000, "initializer.min_points": 80},
     ("mapper.min_keyframe_points", "initializer.min_points")),
])
def test_contradicting_configuration_values_name_both_parameters(values, names):
    with pytest.raises(ConfigError) as e:
        SlamConfig().with_overrides(**values)
    assert all(n in str(e.value) for n in names), str(e.value)
    with pytest.raises(ConfigError):  # the same from a saved configuration (JSON)
        SlamConfig.from_dict(replace(SlamConfig(), **_nested(values)).to_dict())
    assert isinstance(e.value, SlamkitError) and isinstance(e.value, ValueError)


def _nested(values: dict) -> dict:
    """{"a.b": v, "alias": w} -> keyword arguments of SlamConfig replacing the nested stage configs
    (without validation, so a contradiction can be built)."""
    from slamkit.config import ALIASES

    cfg = SlamConfig()
    out: dict = {}
    for key, v in values.items():
        stage, field = ALIASES.get(key, key).split(".")
        out[stage] = replace(out.get(stage, getattr(cfg, stage)), **{field: v})
    return out


# ----------------------------------------------------------------------------- issue 22: clear one-line messages
def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_tiny_frames_name_the_file_and_the_minimum_size(tmp_path, capsys):
    folder = tmp_path / "tiny"
    folder.mkdir()
    for i in range(5):
        cv2.imwrite(str(folder / f"{i:03d}.png"), np.full((1, 1, 3), 100, np.uint8))
    with pytest.raises(SourceError, match=r"000\.png: frames of .* are 1x1 pixels; slamkit needs at least 32x32"):
        open_source(folder)
    assert main(["run", str(folder), "--out", str(tmp_path / "out"), "-q"]) == 2
    assert "1x1 pixels" in _one_line(capsys.readouterr().err) and not (tmp_path / "out").exists()
    # a tiny frame among frames of the right size: skipped with that reason, no OpenCV assertion
    src = ImageListSource("mixed", Intrinsics(640, 480, 500, 500, 320, 240), [folder / "000.png"] * 3,
                          np.arange(3.0), np.arange(3))
    r = Slam(src).step()
    assert r.status == "skipped" and "000.png: is 1x1 pixels; slamkit needs frames of at least 32x32" in r.message


def test_calibration_messages_name_the_command_line_way(tmp_path, capsys):
    make_tum(tmp_path / "mytum")  # TUM layout, no freiburgN in the name
    with pytest.raises(CalibrationError, match=r"mytum: cannot tell the TUM sensor.*--camera fx,fy,cx,cy.*"
                                               r"Python: calibration='fr1'"):
        open_source(tmp_path / "mytum")
    assert main(["run", str(tmp_path / "mytum"), "--out", str(tmp_path / "o1"), "-q"]) == 2
    assert "--camera fx,fy,cx,cy" in _one_line(capsys.readouterr().err)
    make_euroc(tmp_path / "euroc", n=3)
    yaml = tmp_path / "euroc" / "mav0" / "cam0" / "sensor.yaml"
    yaml.unlink()
    with pytest.raises(CalibrationError, match=rf"{yaml}: missing; give the intrinsics: --camera fx,fy,cx,cy.*"
                                               r"Python: camera=Intrinsics"):
        open_euroc(tmp_path / "euroc")
    make_kitti(tmp_path / "kitti", "03", n=3)
    calib = tmp_path / "kitti" / "sequences" / "03" / "calib.txt"
    calib.unlink()
    for path in (tmp_path / "kitti", tmp_path / "kitti" / "sequences" / "03"):  # dataset root or sequence folder
        with pytest.raises(SlamkitError, match=rf"{calib}: missing; a KITTI sequence folder holds calib.txt"):
            open_source(path)


def test_a_failed_initialization_is_explained_on_the_final_line(tmp_path, capsys):
    """A window longer than the sequence: the pair is tried when the sequence ends, and why it failed is the
    summary's last word."""
    folder = write_tum_sequence(synthetic_source("sideways", frames=12, scale=0.25), tmp_path / "seq")
    src = open_tum_sequence(folder)
    src.paths[4].write_bytes(b"\x89PNG\r\n\x1a\n" + b"truncated" * 20)
    out = tmp_path / "out"
    assert main(["run", str(folder / "rgb"), "--out", str(out), "-q", "--camera", "125",
                 "--init-frames", "1000"]) == 3  # ran, posed nothing: exit code 3 (1000: the bound of init_frames)
    err = capsys.readouterr().err.strip().splitlines()
    line = next(x for x in err if x.startswith("frames "))
    assert "posed 0 (0.0 %)" in line and "1 frame skipped (1 unreadable, e.g. frame 4: " in line, line
    assert src.paths[4].name in line
    assert "no map: no initial pair found; last attempt: no initial pair in frames 0-11 (" in line, line
    assert line.endswith("; the sequence ended"), line


def test_resume_with_other_intrinsics_is_refused(tmp_path, capsys):
    folder = write_tum_sequence(synthetic_source("sideways", frames=8, scale=0.25), tmp_path / "seq")
    (folder / "camera.json").unlink()
    (folder / "rgb.txt").rename(folder / "list.txt")  # a plain image folder: intrinsics from --camera
    out = tmp_path / "out"
    assert main(["run", str(folder / "rgb"), "--out", str(out), "-q", "--camera", "585",
                 "--max-frames", "4"]) in (0, 3)  # a map (0) or none (3)
    before = (out / RUN_MARKER_NAME).read_bytes()
    capsys.readouterr()
    assert main(["run", str(folder / "rgb"), "--out", str(out), "-q", "--camera", "300", "--resume"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "camera cannot change when resuming (session: '585', given: '300')" in line
    assert (out / RUN_MARKER_NAME).read_bytes() == before  # the saved run is untouched
    with pytest.raises(ConfigError, match="camera cannot change when resuming"):
        Slam.resume(out, config={"camera": "300"})
    assert Slam.resume(out, config={"camera": "585", "max_frames": 6}).camera.fx == 585  # the same is fine



def test_ablate_refuses_negative_workers_and_a_file_as_out(tmp_path, capsys):
    assert main(["ablate", "synthetic:sideways?frames=8", "--workers", "-3", "--out", str(tmp_path / "s")]) == 2
    assert "--workers -3: must be 0" in _one_line(capsys.readouterr().err)
    (tmp_path / "file").write_text("x")
    assert main(["ablate", "synthetic:sideways?frames=8", "--out", str(tmp_path / "file")]) == 2
    assert f"--out {tmp_path / 'file'}: exists and is not a folder" in _one_line(capsys.readouterr().err)
    assert main(["ablate", "synthetic:sideways?frames=8", "--out", str(tmp_path / "file" / "sub")]) == 2
    assert "is a file" in _one_line(capsys.readouterr().err)
    with pytest.raises(ConfigError, match="workers -3"):
        sweep("synthetic:sideways?frames=8", {"flow_threshold": [0.05]}, tmp_path / "s", workers=-3)
    assert not (tmp_path / "s").exists()


def test_damaged_weight_files_get_one_line_without_torch_advice(tmp_path):

    garbage = tmp_path / "aliked-n16.pth"
    garbage.write_bytes(bytes(range(7, 256)) * 10)
    with pytest.raises(ConfigError) as e:
        check_weight_file(garbage)
    msg = str(e.value)
    assert msg.startswith(f"{garbage}: not a PyTorch weight file") and "github.com/Shiaoming/ALIKED" in msg
    assert "weights_only" not in msg and "\n" not in msg
    empty = tmp_path / "xfeat.pt"
    empty.write_bytes(b"")
    with pytest.raises(ConfigError, match="empty"):
        check_weight_file(empty)
    other_zip = tmp_path / "superpoint_v1.pth"
    with zipfile.ZipFile(other_zip, "w") as z:
        z.writestr("readme.txt", "not weights")
    with pytest.raises(ConfigError, match="a zip archive but not a PyTorch weight file"):
        check_weight_file(other_zip)
    advice = ("Weights only load failed. This file can still be loaded, to do so you have two options, ...\n"
              "(1) In PyTorch 2.6, we changed the default value of the `weights_only` argument ...")
    reason = load_error_reason(RuntimeError(advice))
    assert "weights_only=True" in reason and "\n" not in reason and "two options" not in reason


def test_decoder_warnings_name_the_file(tmp_path, capfd):
    img = (np.random.default_rng(0).random((64, 64, 3)) * 255).astype(np.uint8)
    data = cv2.imencode(".jpg", img)[1].tobytes()
    bad = tmp_path / "frame_0007.jpg"
    bad.write_bytes(data[: len(data) // 2] + b"\xff\xd9")  # libjpeg: "Corrupt JPEG data: premature end ..."
    assert read_image(bad).shape == (64, 64, 3)
    err = capfd.readouterr().err
    assert f"slamkit: {bad}: Corrupt JPEG data" in err, err
