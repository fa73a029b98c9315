"""A given camera's radial distortion, estimated in the run (``ba.radial_keyframes = 20``; off by default):
rectified KITTI images keep k1 = 0.015, which calib.txt's pinhole does not describe. Against exact rendered geometry: a
lens with k1 = 0.05 given as a plain pinhole."""

from __future__ import annotations

import json

import pytest

from slamkit import Slam, SlamConfig
from slamkit.eval import ate
from slamkit.sources.synthetic import synthetic_source, write_tum_sequence

TRUE_K1 = 0.05
PINHOLE = "500,500,319.5,239.5"  # the renderer's camera without its k1


@pytest.fixture(scope="module")
def given_pinhole(tmp_path_factory):
    """240 frames of the hand-held motion (21 keyframes), rendered with k1 = 0.05, run with the pinhole given."""
    folder = write_tum_sequence(synthetic_source("handheld", frames=240, k1=TRUE_K1, noise=1),
                                tmp_path_factory.mktemp("k1") / "seq")
    slam = Slam(str(folder), SlamConfig().with_overrides(camera=PINHOLE, **{"ba.radial_keyframes": 20}))
    slam.run()
    return slam, slam.save(tmp_path_factory.mktemp("k1run") / "run")


def test_a_given_pinhole_learns_the_lens_k1_and_the_trajectory_gains(given_pinhole):
    slam, out = given_pinhole
    cam = slam.camera
    assert cam.dist[0] == pytest.approx(TRUE_K1, rel=0.15) and cam.dist[1:] == (0, 0, 0, 0)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (500.0, 500.0, 319.5, 239.5)  # only k1 is estimated
    rec = slam.main_segment.slam_map.reconstruction
    assert rec.camera(next(iter(rec.cameras))).model.name == "PINHOLE"  # on undistorted keypoints again
    assert rec.compute_mean_reprojection_error() < 1.0
    assert len(slam.trajectory()) == len(slam)
    # measured: 0.51 cm; the same run without the estimate (radial_keyframes=0) 0.94 cm
    assert ate(slam.source.ground_truth(), slam.trajectory()).rmse < 0.007
    assert json.loads((out / "summary.json").read_text())["camera"]["dist"][0] == pytest.approx(cam.dist[0])


def test_off_by_default_a_given_pinhole_stays_a_pinhole():
    """Off by default: on a rendered pinhole street and on 7-Scenes the estimated k1 made the trajectory worse."""
    assert SlamConfig().ba.radial_keyframes == 0 and SlamConfig.preset("seed").ba.radial_keyframes == 0


def test_a_resumed_run_keeps_the_estimated_k1(given_pinhole):
    """``--resume`` goes on undistorting the next frames with the k1 the run estimated, not the given pinhole."""
    slam, out = given_pinhole
    again = Slam.resume(out)
    assert again.camera.dist[0] == pytest.approx(slam.camera.dist[0]) and again.camera.dist[0] != 0
    assert again.loader.camera == again.camera
