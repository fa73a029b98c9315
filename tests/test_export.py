"""Export of a saved run as a Gaussian-splatting / NeRF dataset (issue 21), on real runs of the embedded sequence.

COLMAP layout read back with pycolmap, nerfstudio's transforms.json against trajectory_tum.txt, reprojection
of the exported points, COLMAP undistortion of a distorted copy of the synthetic frames (a rendered straight
edge must come out straight and where the pinhole camera puts it), and inputs calibrated before opening.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

import slamkit
from slamkit import Slam, SlamConfig, open_source
from slamkit.errors import ConfigError, OutputError, SlamkitError
from slamkit.exporter import MARKER, RunFolderError, add_export_parser, export
from slamkit.exporter.nerfstudio import OPENGL_FROM_OPENCV
from slamkit.geometry import tum_from_pose

FRAMES = 50


def _run(source, out: Path, max_frames: int) -> Path:
    slam = Slam(source, SlamConfig(max_frames=max_frames))
    for _ in slam:
        pass
    slam.finish()
    return slam.save(out)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A saved run of the first 50 frames of the embedded sequence."""
    return _run("default", tmp_path_factory.mktemp("export") / "run", FRAMES)


def _index_times(run_dir: Path) -> dict[int, float]:
    with open(run_dir / "frames.csv", newline="") as f:
        return {int(r["index"]): float(r["timestamp"]) for r in csv.DictReader(f)}


def _trajectory(run_dir: Path) -> dict[float, np.ndarray]:
    traj = slamkit.read_tum(run_dir / "trajectory_tum.txt")
    return {round(float(t), 6): p for t, p in zip(traj.timestamps, traj.poses)}


def _world_from_cam(image) -> np.ndarray:
    T = np.eye(4)
    T[:3] = image.cam_from_world().inverse().matrix()
    return T


def _reprojection(rec: pycolmap.Reconstruction) -> tuple[float, np.ndarray]:
    """(mean over points of each point's mean reprojection error, every observation's error), computed by
    projecting with each image's pose and the camera (COLMAP's ComputeMeanReprojectionError averages per point)."""
    per_point, all_errors = [], []
    for pid in rec.point3D_ids():
        p = rec.point3D(pid)
        errs = []
        for el in p.track.elements:
            image = rec.image(el.image_id)
            xc = image.cam_from_world().matrix() @ np.append(p.xyz, 1.0)
            uv = rec.camera(image.camera_id).img_from_cam(xc[None])[0]
            errs.append(np.linalg.norm(uv - image.point2D(el.point2D_idx).xy))
        per_point.append(np.mean(errs))
        all_errors += errs
    return float(np.mean(per_point)), np.asarray(all_errors)


def _run_error(run_dir: Path) -> float:
    run = pycolmap.Reconstruction(str(run_dir / "sparse"))
    run.update_point_3d_errors()
    return float(run.compute_mean_reprojection_error())


def test_colmap_keyframes_round_trip(run_dir, tmp_path):
    res = export(run_dir, tmp_path / "ds", format="colmap")
    rec = pycolmap.Reconstruction(str(tmp_path / "ds" / "sparse" / "0"))
    run = pycolmap.Reconstruction(str(run_dir / "sparse"))
    assert rec.num_reg_images() == run.num_reg_images() == res.num_images > 5
    names = sorted(rec.image(i).name for i in rec.reg_image_ids())
    assert names == sorted(p.name for p in (tmp_path / "ds" / "images").iterdir())
    cam = rec.camera(1)
    fx, fy, cx, cy = run.camera(1).params  # COLMAP's pixel centres are at +0.5, slamkit's at 0
    assert cam.model.name == "PINHOLE" and list(cam.params) == [fx, fy, cx + 0.5, cy + 0.5]
    source = open_source("default")
    run_by_name = {run.image(i).name: run.image(i) for i in run.reg_image_ids()}
    for iid in rec.reg_image_ids():
        image = rec.image(iid)
        stem = Path(image.name).stem
        np.testing.assert_array_equal(image.cam_from_world().matrix(), run_by_name[stem].cam_from_world().matrix())
        pixels = cv2.imread(str(tmp_path / "ds" / "images" / image.name), cv2.IMREAD_COLOR)
        assert pixels.shape == (cam.height, cam.width, 3)
        original = source[int(stem.split("_")[1])].color[:, :, ::-1]
        assert np.array_equal(pixels, original)  # the frame the model's keyframe was made from
    assert rec.num_points3D() == run.num_points3D() == res.num_points
    for pid in run.point3D_ids():
        np.testing.assert_array_equal(rec.point3D(pid).xyz, run.point3D(pid).xyz)


def test_exported_points_reproject_at_their_observations(run_dir, tmp_path):
    export(run_dir, tmp_path / "ds", format="colmap")
    mean, errors = _reprojection(pycolmap.Reconstruction(str(tmp_path / "ds" / "sparse" / "0")))
    assert abs(mean - _run_error(run_dir)) < 1e-6
    assert np.percentile(errors, 95) < 4.0  # the tracker's and mapper's inlier threshold


def test_all_frames_registered_with_trajectory_poses_and_observations(run_dir, tmp_path):
    traj = _trajectory(run_dir)
    times = _index_times(run_dir)
    res = export(run_dir, tmp_path / "ds", format="colmap", frames="all")
    rec = pycolmap.Reconstruction(str(tmp_path / "ds" / "sparse" / "0"))
    assert rec.num_reg_images() == len(traj) == res.num_images == FRAMES
    assert {rec.image(i).name for i in rec.images} == {p.name for p in (tmp_path / "ds" / "images").iterdir()}
    keyframes = {pycolmap.Reconstruction(str(run_dir / "sparse")).image(i).name
                 for i in pycolmap.Reconstruction(str(run_dir / "sparse")).reg_image_ids()}
    observed = []
    for iid in rec.reg_image_ids():
        image = rec.image(iid)
        t = round(times[int(Path(image.name).stem.split("_")[1])], 6)
        np.testing.assert_allclose(_world_from_cam(image), traj[t], atol=1e-9)
        if Path(image.name).stem not in keyframes:
            observed.append(image.num_points3D)
    assert len(observed) == FRAMES - len(keyframes) and min(observed) >= 100
    assert res.num_matched_observations == sum(observed)
    _, errors = _reprojection(rec)
    # keyframes' observations within the chi-square bound at their keypoint's scale (BA's outlier test: 2.45 px
    # at ORB's finest level, 8.8 px at its 8th), the matched frames' within the tracker's 4 px
    assert errors.max() <= np.sqrt(5.991) * 1.2 ** 7 + 1e-6 and np.percentile(errors, 95) < 4.0
    assert np.median(errors) < 1.0
    every = export(run_dir, tmp_path / "every", format="colmap", frames="every=7")
    indices = sorted(times)
    expected = {f"frame_{i:06d}" for k, i in enumerate(indices) if k % 7 == 0} | keyframes
    assert every.num_images == len(expected)


def test_nerfstudio_transforms_poses_intrinsics_and_point_cloud(run_dir, tmp_path):
    traj = _trajectory(run_dir)
    times = _index_times(run_dir)
    export(run_dir, tmp_path / "ns", format="nerfstudio", frames="all")
    doc = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    run = pycolmap.Reconstruction(str(run_dir / "sparse"))
    fx, fy, cx, cy = run.camera(1).params
    assert (doc["fl_x"], doc["fl_y"], doc["cx"], doc["cy"], doc["w"], doc["h"]) == (fx, fy, cx + 0.5, cy + 0.5,
                                                                                   640, 480)
    assert doc["camera_model"] == "PINHOLE" and "k1" not in doc
    assert len(doc["frames"]) == len(traj) == FRAMES
    xyz = np.array([run.point3D(p).xyz for p in run.point3D_ids()])
    for frame in doc["frames"]:
        assert (tmp_path / "ns" / frame["file_path"]).is_file()
        t = round(times[int(Path(frame["file_path"]).stem.split("_")[1])], 6)
        gl = np.array(frame["transform_matrix"])
        np.testing.assert_allclose(gl @ OPENGL_FROM_OPENCV, traj[t], atol=1e-9)
        # OpenGL camera: y up, looking down -z: the map points this camera sees lie at negative z
        cam = (np.linalg.inv(gl) @ np.c_[xyz, np.ones(len(xyz))].T)[:3]
        assert np.median(cam[2]) < 0
    ply = (tmp_path / "ns" / doc["ply_file_path"]).read_bytes()
    header, body = ply.split(b"end_header\n", 1)
    assert b"format binary_little_endian 1.0" in header and f"element vertex {len(xyz)}".encode() in header
    vertices = np.frombuffer(body, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    np.testing.assert_allclose(vertices["xyz"], xyz, rtol=1e-6, atol=1e-6)


def test_run_folder_without_model_and_bad_arguments(run_dir, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(run_dir, broken)
    (broken / "sparse" / "points3D.bin").unlink()
    with pytest.raises(RunFolderError, match="points3D.bin"):
        export(broken, tmp_path / "out")
    with pytest.raises(RunFolderError, match="does not exist"):
        export(tmp_path / "nowhere", tmp_path / "out")
    with pytest.raises(ConfigError, match="format"):
        export(run_dir, tmp_path / "out", format="ply")
    with pytest.raises(ConfigError, match="frames"):
        export(run_dir, tmp_path / "out", frames="every=0")
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "notes.txt").write_text("keep me")
    with pytest.raises(OutputError, match="not empty"):
        export(run_dir, precious)
    assert (precious / "notes.txt").read_text() == "keep me"
    with pytest.raises(OutputError, match="run folder"):
        export(run_dir, run_dir)
    assert not (tmp_path / "out").exists()
    export(run_dir, tmp_path / "again")
    export(run_dir, tmp_path / "again", format="nerfstudio")  # a previous export is replaced
    assert (tmp_path / "again" / MARKER).is_file() and not (tmp_path / "again" / "sparse").exists()


def test_run_folder_without_session_needs_the_source(run_dir, tmp_path):
    bare = tmp_path / "bare"
    shutil.copytree(run_dir, bare, ignore=shutil.ignore_patterns("session"))
    with pytest.raises(SlamkitError, match="pass source="):
        export(bare, tmp_path / "out")
    res = export(bare, tmp_path / "out", source=open_source("default"))
    assert res.num_images == pycolmap.Reconstruction(str(run_dir / "sparse")).num_reg_images()


def test_cli_subcommand_handler(run_dir, tmp_path, capsys):
    parser = argparse.ArgumentParser(prog="slamkit")
    add_export_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["export", str(run_dir), "--format", "colmap", "--out", str(tmp_path / "ds"),
                              "--frames", "every=10", "-q"])
    assert args.func(args) == 0
    assert "colmap export" in capsys.readouterr().out
    rec = pycolmap.Reconstruction(str(tmp_path / "ds" / "sparse" / "0"))
    assert all((tmp_path / "ds" / "images" / rec.image(i).name).is_file() for i in rec.reg_image_ids())
    with pytest.raises(SystemExit):
        parser.parse_args(["export", str(run_dir), "--format", "ply", "--out", str(tmp_path / "x")])


def test_progress_callback_counts_every_image(run_dir, tmp_path):
    calls = []
    res = export(run_dir, tmp_path / "ds", frames="every=5", progress=lambda done, total: calls.append((done, total)))
    assert calls == [(k, res.num_images) for k in range(1, res.num_images + 1)]


# ------------------------------------------------------------------------------------------------- undistortion
K1 = 0.2
LINE = ((40.0, 60.0), (600.0, 90.0))
"""A green straight edge painted on the pinhole frames (pixels of the pinhole camera)."""


def _distort(rgb: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """The image a camera with OpenCV distortion ``dist`` sees of the pinhole image ``rgb`` (same K)."""
    h, w = rgb.shape[:2]
    grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), -1)
    pin = cv2.undistortPoints(grid.reshape(-1, 1, 2), K, dist, P=K).reshape(h, w, 2).astype(np.float32)
    return cv2.remap(rgb, pin[..., 0], pin[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _edge_points(bgr: np.ndarray) -> np.ndarray:
    """(N, 2) the green edge's centre in every image column it crosses (weighted rows), searched in the top
    160 rows (the scene's own green pictures are darker and lower)."""
    b, g, r = (bgr[:160, :, k].astype(np.float64) for k in range(3))
    weight = np.clip(g - np.maximum(r, b) - 120, 0, None)
    cols = np.flatnonzero(weight.sum(axis=0) > 150)
    rows = np.arange(weight.shape[0], dtype=np.float64)
    return np.array([(x, (weight[:, x] * rows).sum() / weight[:, x].sum()) for x in cols])


def _line_fit(points: np.ndarray) -> tuple[np.ndarray, float]:
    """((slope, intercept) of y = a x + b, RMS residual in pixels)."""
    coef = np.polyfit(points[:, 0], points[:, 1], 1)
    return coef, float(np.sqrt(np.mean((np.polyval(coef, points[:, 0]) - points[:, 1]) ** 2)))


@pytest.fixture(scope="module")
def distorted_run(tmp_path_factory) -> tuple[Path, Path]:
    """(image folder of 40 synthetic frames seen through a lens with k1 = 0.2, with its camera.txt; saved run)."""
    root = tmp_path_factory.mktemp("distorted")
    source = open_source("default")
    K, dist = source.camera.K, np.array([K1, 0.0, 0.0, 0.0, 0.0])
    folder = root / "images"
    folder.mkdir()
    for i in range(40):
        bgr = np.ascontiguousarray(source[i].color[:, :, ::-1])
        cv2.line(bgr, (int(LINE[0][0]), int(LINE[0][1])), (int(LINE[1][0]), int(LINE[1][1])), (0, 255, 0), 3,
                 cv2.LINE_AA)
        cv2.imwrite(str(folder / f"{i:04d}.png"), _distort(bgr, K, dist))
    c = source.camera
    (folder / "camera.txt").write_text(f"# synthetic lens\n{c.fx} {c.fy} {c.cx} {c.cy} {K1} 0 0 0\n")
    return folder, _run(str(folder), root / "run", 40)


def test_undistorted_export_has_straight_edges_and_a_pinhole_camera(distorted_run, tmp_path):
    folder, run_dir = distorted_run
    res = export(run_dir, tmp_path / "ds", format="colmap", undistort=True)
    rec = pycolmap.Reconstruction(str(tmp_path / "ds" / "sparse" / "0"))
    cam = rec.camera(1)
    assert res.camera_model == "PINHOLE" and cam.model.name == "PINHOLE"
    fx, fy, cx, cy = cam.params
    assert (fx, fy) == (500.0, 500.0)  # COLMAP's undistorter keeps the focal lengths
    (_, bent), = [_line_fit(_edge_points(cv2.imread(str(folder / "0000.png"))))]
    assert bent > 2.0  # the lens bends the edge by several pixels
    for iid in rec.reg_image_ids():
        image = cv2.imread(str(tmp_path / "ds" / "images" / rec.image(iid).name))
        assert image.shape == (cam.height, cam.width, 3)
        (a, b), rms = _line_fit(_edge_points(image))
        assert rms < 0.3
        # where the pinhole camera puts the painted edge: the same rays, principal point moved to (cx, cy)
        (x0, y0), (x1, y1) = LINE
        x0, x1 = x0 - 319.5 + (cx - 0.5), x1 - 319.5 + (cx - 0.5)  # exported cx is COLMAP's (+0.5 px)
        y0, y1 = y0 - 239.5 + (cy - 0.5), y1 - 239.5 + (cy - 0.5)
        expected = y0 + (y1 - y0) * (np.array([x0, x1]) - x0) / (x1 - x0)
        assert np.abs(np.polyval((a, b), [x0, x1]) - expected).max() < 0.2  # 0.5 px off without the convention shift
    mean, _ = _reprojection(rec)
    assert abs(mean - _run_error(run_dir)) < 1e-6  # pixels only shifted: same focal lengths


def test_distorted_export_keeps_the_lens_model(distorted_run, tmp_path):
    folder, run_dir = distorted_run
    res = export(run_dir, tmp_path / "ns", format="nerfstudio")
    doc = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    assert doc["camera_model"] == "OPENCV" and (doc["k1"], doc["k2"], doc["p1"], doc["p2"]) == (K1, 0.0, 0.0, 0.0)
    frame = doc["frames"][0]
    name = Path(frame["file_path"]).name
    index = int(Path(name).stem.split("_")[1])
    exported = cv2.imread(str(tmp_path / "ns" / frame["file_path"]))
    assert np.array_equal(exported, cv2.imread(str(folder / f"{index:04d}.png")))  # the distorted input
    colmap = export(run_dir, tmp_path / "ds", format="colmap")
    rec = pycolmap.Reconstruction(str(tmp_path / "ds" / "sparse" / "0"))
    assert colmap.camera_model == res.camera_model == "OPENCV"
    assert list(rec.camera(1).params) == [500.0, 500.0, 320.0, 240.0, K1, 0.0, 0.0, 0.0]  # COLMAP's +0.5 px
    _, errors = _reprojection(rec)  # observations re-distorted: they still sit on their points' projections
    assert np.percentile(errors, 95) < 4.0


# --------------------------------------------------------------------------- inputs calibrated before opening
def _tum_layout(root: Path, n: int) -> Path:
    """A TUM RGB-D layout (rgb.txt, rgb/, groundtruth.txt) of the first ``n`` synthetic frames, in a folder
    whose name says no freiburg sensor."""
    source = open_source("default")
    (root / "rgb").mkdir(parents=True)
    rgb, gt = ["# timestamp filename"], ["# timestamp tx ty tz qx qy qz qw"]
    for i in range(n):
        f = source[i]
        t = 1000.0 + f.timestamp
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), f.color[:, :, ::-1])
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        tr, q = tum_from_pose(f.gt_pose)
        gt.append(f"{t:.6f} " + " ".join(repr(float(v)) for v in (*tr, *q)))
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    return root


@pytest.mark.parametrize("how", ["camera", "camera.txt"])
def test_tum_layout_with_another_name_runs_with_a_camera(tmp_path, how):
    root = _tum_layout(tmp_path / "converted_recording", 30)
    c = open_source("default").camera
    text = f"{c.fx},{c.fy},{c.cx},{c.cy}"
    if how == "camera.txt":
        (root / "camera.txt").write_text(text.replace(",", " ") + "\n")
        source = open_source(root)
    else:
        source = open_source(root, camera=text)
    assert source.camera == c
    slam = Slam(source, SlamConfig(max_frames=30))
    for _ in slam:
        pass
    traj = slam.trajectory()
    assert len(traj) >= 25
    assert slamkit.ate(source.ground_truth(), traj).rmse < 0.05 * traj.path_length


def test_lens_with_k3_maps_pixels_and_images_consistently():
    """TUM fr1's lens (k3 != 0): FULL_OPENCV when kept; after COLMAP's undistortion a blob drawn at a distorted
    pixel lands where the exported pinhole camera puts that pixel's ray."""
    from slamkit.exporter.camera import ExportCamera
    from slamkit.sources.tum import TUM_CALIBRATIONS

    fr1 = TUM_CALIBRATIONS["fr1"]
    kept = ExportCamera.create(fr1)
    assert kept.model_name == "FULL_OPENCV" and list(kept.camera.params[8:]) == [fr1.dist[4], 0.0, 0.0, 0.0]
    rng = np.random.default_rng(0)
    distorted = rng.uniform([60, 60], [580, 420], size=(50, 2))
    # exported pixels are COLMAP's: OpenCV's (array indices) + 0.5
    np.testing.assert_allclose(kept.from_model(fr1.undistort_points(distorted)), distorted + 0.5, atol=0.02)
    flat = ExportCamera.create(fr1, undistort=True)
    assert flat.model_name == "PINHOLE"
    yy, xx = np.mgrid[0:480, 0:640]
    for p in distorted[:5]:
        blob = np.exp(-((xx - p[0]) ** 2 + (yy - p[1]) ** 2) / (2 * 2.0 ** 2))
        rgb = np.repeat((255 * blob).astype(np.uint8)[..., None], 3, axis=2)
        out = flat.undistort_image(rgb)[..., 0].astype(np.float64)
        out[out < 20] = 0
        gy, gx = np.mgrid[0:out.shape[0], 0:out.shape[1]]
        centre = np.array([(gx * out).sum(), (gy * out).sum()]) / out.sum()
        np.testing.assert_allclose(centre + 0.5, flat.from_model(fr1.undistort_points(p[None]))[0], atol=0.15)


def test_export_into_a_folder_whose_name_is_not_utf8(run_dir, tmp_path):
    """OpenCV's image writer crashes on a name that is not UTF-8: the images are encoded by OpenCV and written
    by Python, the same pixels as the source's frames."""
    import os

    out = Path(os.fsdecode(os.fsencode(tmp_path) + b"/ds\xfe"))
    res = export(run_dir, out, format="nerfstudio")
    files = sorted((out / "images").iterdir())
    assert len(files) == res.num_images > 5
    source = open_source("default")
    pixels = cv2.imdecode(np.fromfile(files[0], np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(pixels, source[int(files[0].stem.split("_")[1])].color[:, :, ::-1])
