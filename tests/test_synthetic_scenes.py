"""The street and the repeated-texture corridor of the synthetic generator (issues 17 and 18).

Rendering against geometry (exact depth on a facade, exact tile periodicity), features for a detector,
the camera paths and their specs; the street driven at about 1 m per frame tracked end to end; and loop
detection down the corridor, which never revisits a place: the place database finds aliased candidates,
and the question is whether verification accepts any of them."""

from __future__ import annotations

import re

import numpy as np
import pycolmap
import pytest

from slamkit.config import SlamConfig
from slamkit.errors import ConfigError
from slamkit.eval import ate
from slamkit.features import create_extractor
from slamkit.loop_verification import update_consistent_groups, verify_loop_candidate
from slamkit.pipeline import Slam
from slamkit.place_recognition import PlaceDatabase, default_vocabulary
from slamkit.sources import open_source
from slamkit.sources.corridor import HALF_WIDTH, HEIGHT, LENGTH, TILE, corridor_scene, corridor_walk
from slamkit.sources.scene import project
from slamkit.sources.street import BUILDING_LINE, LANE_X, ROAD_HALF, street_drive, street_scene
from slamkit.sources.synthetic import DEFAULT_CAMERA, MOTIONS, SCENE_MOTIONS, WIDE_CAMERA

pycolmap.logging.minloglevel = 2


# ---------------------------------------------------------------------------------------------- street


def test_street_spec_opens_the_street_with_its_own_motion():
    src = open_source("synthetic:street-drive?frames=40&speed=1.5&seed=2")
    assert src.scene is street_scene() and len(src) == 40 and src.camera == DEFAULT_CAMERA
    np.testing.assert_array_equal(src.gt_poses, street_drive(40, speed=1.5, seed=2))
    wide = open_source("synthetic:street-drive?frames=3&wide=1")
    assert wide.camera == WIDE_CAMERA and wide[0].gray.shape == (370, 1226)
    room = open_source("synthetic:handheld?frames=3")
    assert room.scene is not src.scene and "street-drive" not in MOTIONS and set(SCENE_MOTIONS) == {
        "street-drive", "corridor-walk", "block-loop"}
    with pytest.raises(ConfigError, match="at most 355 m"):
        open_source("synthetic:street-drive?frames=300&speed=1.5")
    with pytest.raises(ConfigError, match="takes no parameter 'radius'.*weave"):
        open_source("synthetic:street-drive?radius=1")
    with pytest.raises(ConfigError, match="wide must be 0 or 1"):
        open_source("synthetic:street-drive?wide=2")


def test_street_drive_moves_speed_metres_per_frame_along_the_lane():
    for speed in (0.5, 1.0, 1.5):
        poses = street_drive(150, speed=speed, seed=1)
        c = poses[:, :3, 3]
        np.testing.assert_allclose(np.diff(c[:, 1]), speed, rtol=1e-12)    # along the street
        step = np.linalg.norm(np.diff(c, axis=0), axis=1)
        assert abs(step.mean() / speed - 1) < 0.01
        assert np.all(np.abs(c[:, 0] - LANE_X) <= 0.3 + 1e-12) and np.all(np.abs(c[:, 2] - 1.6) <= 0.02 + 1e-12)
        gaze = poses[:, :3, 2]
        assert np.all(gaze[:, 1] > 0.99)                                    # looking ahead, slightly down
        R = poses[:, :3, :3]
        np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)


def test_street_depth_on_a_facade_equals_the_geometry():
    """Every pixel that sees the facade of a house is at the exact depth of the ray's hit on its plane,
    and inside the facade's rectangle."""
    src = open_source("synthetic:street-drive?frames=30&speed=1.0")
    i = 20
    rendering = src.rendering(i)
    pose, K = src.gt_poses[i], src.camera
    houses = [q for q, quad in enumerate(src.scene.quads) if quad.name.startswith("house_left_")
              and not quad.name.endswith(("_start", "_end"))]
    counts = [(rendering.quad == q).sum() for q in houses]
    q = houses[int(np.argmax(counts))]
    quad = src.scene.quads[q]
    vv, uu = np.nonzero(rendering.quad == q)
    assert len(uu) > 5000
    rays = np.stack([(uu - K.cx) / K.fx, (vv - K.cy) / K.fy, np.ones(len(uu))], axis=1) @ pose[:3, :3].T
    x_plane = quad.origin[0]                                                 # facades are planes x = const
    depth = (x_plane - pose[0, 3]) / rays[:, 0]                              # z-depth: rays have unit camera z
    np.testing.assert_allclose(rendering.depth[vv, uu], depth, rtol=1e-9)
    hits = pose[:3, 3] + depth[:, None] * rays
    lo, hi = quad.corners.min(axis=0), quad.corners.max(axis=0)
    assert np.all((hits >= lo - 1e-6) & (hits <= hi + 1e-6))
    assert -BUILDING_LINE - 1.5 - 1e-9 <= x_plane <= -BUILDING_LINE
    # known points of the facade project where a ray cast through their (sub-pixel) projection hits them
    a, b = np.meshgrid(np.linspace(0.05, 0.95, 10), np.linspace(0.05, 0.95, 10))
    known = quad.point(a.ravel(), b.ravel())
    uv, z = project(pose, K, known)
    seen = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= K.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= K.height - 1)
    hit, hit_depth, hit_quad = src.scene.raycast(pose, K, uv[seen])
    visible = hit_quad == q                                                  # not hidden by a car or a pole
    assert visible.sum() >= 10
    np.testing.assert_allclose(hit[visible], known[seen][visible], atol=1e-9)
    np.testing.assert_allclose(hit_depth[visible], z[seen][visible], rtol=1e-12)


@pytest.mark.parametrize("spec, frames", [("synthetic:street-drive?frames=150&speed=1.0&noise=1", (0, 75, 149)),
                                          ("synthetic:corridor-walk?frames=120&speed=0.1&noise=1", (0, 60, 119)),
                                          # the city block on its straights and in its corners
                                          ("synthetic:block-loop?frames=1001&laps=1&seed=0&noise=1",
                                           (0, 150, 300, 640, 900))])
def test_frames_have_orb_features_spread_over_the_image(spec, frames):
    """Enough ORB features in every frame, and in most cells of a 4 x 4 grid (the sky may have none)."""
    src = open_source(spec)
    orb = create_extractor("orb", num_features=2000)
    for i in frames:
        kp = orb.extract(src[i].gray).keypoints
        assert len(kp) >= 1500, (i, len(kp))
        cells = np.bincount((kp[:, 1] * 4 // src.camera.height).astype(int) * 4
                            + (kp[:, 0] * 4 // src.camera.width).astype(int), minlength=16)
        assert (cells >= 15).sum() >= 12, (i, cells.reshape(4, 4))


def test_street_is_distinctive_and_textured_at_range():
    """Houses differ (no two facades share a texture), and the road and facades have texture detail:
    the renderer's mipmaps keep contrast in view at 5 to 40 m."""
    scene = street_scene()
    facades = [quad for quad in scene.quads if re.fullmatch(r"house_(left|right)_\d+", quad.name)]
    assert len(facades) > 40
    assert len({quad.texture.image.tobytes()[:4096] for quad in facades}) == len(facades)
    src = open_source("synthetic:street-drive?frames=2")
    r = src.rendering(0)
    near = (r.depth > 5) & (r.depth < 40)
    assert near.mean() > 0.5
    grey = src[0].gray.astype(np.float64)
    lap = np.abs(grey[1:-1, 1:-1] * 4 - grey[:-2, 1:-1] - grey[2:, 1:-1] - grey[1:-1, :-2] - grey[1:-1, 2:])
    assert np.median(lap[near[1:-1, 1:-1]]) > 2.0                           # not blurred flat
    assert np.all(np.abs(street_drive(2)[:, 0, 3]) < ROAD_HALF)


# ---------------------------------------------------------------------------------- street: tracking


def _track(spec: str, config: SlamConfig):
    src = open_source(spec)
    slam = Slam(src, config)
    slam.run()
    return src, slam


@pytest.mark.parametrize("preset", ["default", "driving"])
def test_street_drive_at_1_m_per_frame_is_tracked_end_to_end(preset):
    """Issue 17: forward motion at about 1 m per frame in a street (100 m driven), exact ground truth.
    Measured (seed 0): 100 % posed in one segment, ATE 0.18 m with either config."""
    src, slam = _track("synthetic:street-drive?frames=100&speed=1.0&noise=1", SlamConfig.preset(preset))
    s = slam.summary()
    assert s["fraction_posed"] >= 0.98, [r.status for r in slam.records]
    assert len(slam.segments) == 1
    assert ate(src.ground_truth(), slam.trajectory()).rmse < 0.5                 # metres over 100 m


OLD_DEFAULT = {"initializer.window_overlap": 0.0, "ba.outlier_chi2": 0.0, "ba.local_passes": 1}
"""With ``mapper="colmap"``: the default before issue 39 (a fixed initialization window, COLMAP's BA filter)."""

STREET_1_5 = "synthetic:street-drive?frames=100&speed=1.5&noise=1&seed=1"
"""1.5 m per frame, a start where the default initialization loses the map (seeds 0 and 2 pass)."""


def test_street_drive_at_1_5_m_per_frame_with_the_default_config():
    """Issue 39: the default (local mapping and the initializer's motion window) maps the street at 1.5 m per
    frame in one segment (seed 1, where COLMAP's mapper with a 20-frame window took frames 10 and 13, its map
    was out of view by frame 20 and 61 % of the frames were posed in 2 segments). Measured: 100 % posed in one
    segment, ATE 0.26 m over 150 m (COLMAP's mapper with the motion window: 0.31 m)."""
    src, slam = _track(STREET_1_5, SlamConfig())
    assert slam.config.mapper.method == "local" and slam.config.initializer.window_overlap > 0
    assert slam.summary()["fraction_posed"] >= 0.98 and len(slam.segments) == 1
    assert ate(src.ground_truth(), slam.trajectory()).rmse < 0.6  # metres over 150 m


def test_street_drive_at_1_5_m_per_frame_with_colmaps_mapper_and_a_short_initialization():
    """COLMAP's triangulator with a fixed 20-frame window (the old default) loses the same street; with 8
    initialization frames (12 m of driving) its map is made early enough: measured 100 % posed in one segment,
    ATE 0.42 m over 150 m."""
    src, slam = _track(STREET_1_5, SlamConfig().with_overrides(mapper="colmap", init_frames=8, **OLD_DEFAULT))
    assert slam.summary()["fraction_posed"] >= 0.98 and len(slam.segments) == 1
    assert ate(src.ground_truth(), slam.trajectory()).rmse < 1.5


# ---------------------------------------------------------------------------------------------- corridor


def test_corridor_repeats_one_tile_exactly():
    """Two views one tile apart see the same image wherever both see the walls, floor and ceiling: the
    perceptual aliasing the corridor is built for."""
    scene = corridor_scene()
    pose = corridor_walk(2, speed=0.1, seed=4)[0]
    moved = pose.copy()
    moved[1, 3] += 2 * TILE
    a, b = scene.render(pose, DEFAULT_CAMERA), scene.render(moved, DEFAULT_CAMERA)
    walls = np.array([q.name.startswith(("wall", "floor", "ceiling")) for q in scene.quads])
    same = walls[a.quad] & walls[b.quad] & (a.quad >= 0) & (b.quad >= 0) & (a.depth < 30)
    assert same.mean() > 0.9
    np.testing.assert_allclose(a.depth[same], b.depth[same], rtol=1e-9)
    assert np.abs(a.image[same].astype(int) - b.image[same].astype(int)).max() <= 1   # float32 texel lookup
    c = pose[:3, 3]
    assert abs(c[0]) < HALF_WIDTH and 0 < c[2] < HEIGHT and 0 < c[1] < LENGTH


def test_corridor_walk_never_turns_back():
    poses = corridor_walk(300, speed=0.05, seed=1)
    y = poses[:, 1, 3]
    assert np.all(np.diff(y) > 0) and np.all(poses[:, 1, 2] > 0.9)
    with pytest.raises(ConfigError, match="at most 43 m"):
        corridor_walk(500, speed=0.1)


@pytest.fixture(scope="module")
def corridor_run():
    """SLAM down 12 m of the corridor (4 tiles), then loop detection as ORB-SLAM does it with slamkit's
    components, keyframe by keyframe: query the place database (trained on the room, not on the corridor)
    excluding covisible keyframes, keep candidates scoring at least the query's lowest score with its
    covisible neighbours, check their consistency over successive keyframes, and verify each candidate by
    a robust Sim(3) between the query's map points and those of the candidate and its covisible keyframes.

    0.1 m per frame (3 m/s at 30 fps) with ``init_frames=8``: with a fixed 20-frame window the initial
    pair is 1.2 m apart and the initializer takes a wrong two-view geometry (see
    test_corridor_fast_walk_with_a_fixed_initialization_window). Mapped with COLMAP's mapper (the ``seed``
    preset's): its map holds the aliased stretches these tests witness; local mapping's fused, outlier-tested
    map gives no candidate that passes the Sim(3) verification (issue 39)."""
    src = open_source("synthetic:corridor-walk?frames=120&speed=0.1&noise=1")
    slam = Slam(src, SlamConfig().with_overrides(init_frames=8, mapper="colmap", **OLD_DEFAULT))
    slam.run()
    m = slam.slam_map
    alignment = ate(src.ground_truth(), slam.trajectory()).alignment
    db = PlaceDatabase(default_vocabulary("orb"))

    def points(iid):
        ids = m.point3D_ids(iid)
        keep = np.flatnonzero(ids >= 0)
        return m.points_xyz(ids[keep]), m.keyframes[iid].features.descriptors[keep], ids[keep]

    rows, groups = [], ()
    for iid in sorted(m.keyframes):
        descriptors = m.keyframes[iid].features.descriptors
        covisible = {i for i, _ in m.covisible(iid)}
        hits = db.query(descriptors, k=10, exclude=covisible) if len(db) else []
        db.add(iid, descriptors)
        neighbour_scores = [db.score(iid, i) for i in covisible if i in db]
        min_score = min(neighbour_scores, default=0.0)
        candidates = [c for c, score in hits if score >= min_score]
        groups, consistent = update_consistent_groups(groups, {c: [i for i, _ in m.covisible(c)] for c in candidates})
        qp, qd, _ = points(iid)
        for c in candidates:
            cp, cd, cids = points(c)
            for nb, _ in m.covisible(c, 10):
                p2, d2, i2 = points(nb)
                new = ~np.isin(i2, cids)
                cp, cd, cids = np.vstack([cp, p2[new]]), np.vstack([cd, d2[new]]), np.concatenate([cids, i2[new]])
            v, pairs = verify_loop_candidate(qp, qd, cp, cd, binary=True)
            # ground truth: how far apart the matched points really are (0 for a true revisit)
            apart = np.linalg.norm(alignment.apply_to_points(qp[pairs[:, 0]])
                                   - alignment.apply_to_points(cp[pairs[:, 1]]), axis=1)
            truly = np.median(apart[v.inlier_mask]) if v.inlier_mask.any() else np.median(apart)
            rows.append(dict(query=iid, candidate=c, consistent=c in consistent, accepted=v.accepted,
                             verification=v, apart=float(truly)))
    return src, slam, rows


def test_corridor_walk_is_tracked(corridor_run):
    src, slam, _ = corridor_run
    assert slam.summary()["fraction_posed"] == 1.0 and len(slam.segments) == 1
    assert ate(src.ground_truth(), slam.trajectory()).rmse < 0.1      # metres over a 12 m walk (measured 2.5 cm)


def test_corridor_database_returns_aliased_candidates(corridor_run):
    """The texture repeats, so the database proposes keyframes of other places, as similar to the query as
    its true neighbours, several of them consistent over successive keyframes; their matched map points
    are whole tiles apart in the world (never the same place: the walk never turns back)."""
    _, slam, rows = corridor_run
    assert len({r["query"] for r in rows}) >= 5
    assert sum(r["consistent"] for r in rows) >= 5
    apart = np.array([r["apart"] for r in rows])
    assert np.all(apart > TILE - 0.5)
    tiles = apart / TILE
    assert np.mean(np.abs(tiles - np.round(tiles)) < 0.1) > 0.9      # aliased by a whole number of tiles


def test_corridor_aliasing_passes_the_sim3_verification(corridor_run):
    """Issue 18: the repeated tiles repeat whole stretches of 3D structure, so a robust Sim(3) between a
    keyframe and one 2-3 tiles back is as good as a true loop's (measured: 3 of 110 candidates of 15 query
    keyframes, a translation of 2 tiles = 6.0-6.2 m, ~155 inliers of ~510 matches, consistent over successive
    keyframes). Geometry alone cannot refuse them; the loop closer does, by the size of the correction they
    imply (``loop_closing.max_correction``; tests/test_loop_aliasing.py runs the pipeline down the corridor)."""
    _, _, rows = corridor_run
    false_loops = [r for r in rows if r["accepted"] and r["consistent"]]
    assert false_loops
    assert all(r["apart"] > TILE - 0.5 for r in false_loops)  # never the same place


@pytest.mark.xfail(strict=True, raises=AssertionError,
                   reason="issue 17: at 0.1 m/frame (seed 0) the initializer takes frames 7 and 19 (1.2 m apart) "
                   "with 209 inliers and a median parallax of 58 deg -- a wrong two-view geometry -- and the map "
                   "is wrong from the start: ATE 1.31 m over 6 m (seed 1: frames 11 and 19, ATE 8 mm; "
                   "0.06 m/frame: 4 mm; init_frames=8: 2.5 cm over 12 m)")
def test_corridor_fast_walk_with_a_fixed_initialization_window():
    """A long room walked at 3 m/s (0.1 m per frame at 30 fps) with a fixed 20-frame initialization window and
    COLMAP's mapper (the ``seed`` preset's, the default before issue 39)."""
    src, slam = _track("synthetic:corridor-walk?frames=60&speed=0.1&noise=1",
                       SlamConfig().with_overrides(mapper="colmap", **OLD_DEFAULT))
    assert slam.summary()["fraction_posed"] >= 0.98 and len(slam.segments) == 1
    assert ate(src.ground_truth(), slam.trajectory()).rmse < 0.05


def test_corridor_fast_walk_with_the_default_config():
    """The same walk with the default config (the motion window and local mapping): the pair is tried before
    the view has moved on, not 1.2 m apart; measured 100 % posed, ATE 3.9 mm."""
    src, slam = _track("synthetic:corridor-walk?frames=60&speed=0.1&noise=1", SlamConfig())
    assert slam.summary()["fraction_posed"] >= 0.98 and len(slam.segments) == 1
    assert ate(src.ground_truth(), slam.trajectory()).rmse < 0.05
