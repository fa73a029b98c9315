"""The city block of the synthetic generator (issue 18: a loop large enough for drift to build up).

Rendering against geometry (exact depth on a facade), the ``block-loop`` path (closed after each lap, on the
road, at the speed asked), features for a detector, distinct facades, and the spec's parameters."""

from __future__ import annotations

import re

import numpy as np
import pytest

from slamkit.errors import ConfigError
from slamkit.sources import open_source
from slamkit.sources.block import BLOCK_HALF, CENTRE_OFFSET, LAP, OUTER_OFFSET, block_loop, block_scene
from slamkit.sources.scene import project
from slamkit.sources.synthetic import DEFAULT_CAMERA, SCENE_MOTIONS


def test_block_spec_opens_the_block_with_its_own_motion():
    src = open_source("synthetic:block-loop?frames=41&laps=2&seed=3&noise=1")
    assert SCENE_MOTIONS["block-loop"] == (block_loop, block_scene)
    assert src.scene is block_scene() and len(src) == 41 and src.camera == DEFAULT_CAMERA
    np.testing.assert_array_equal(src.gt_poses, block_loop(41, laps=2, seed=3))
    assert len(open_source("synthetic:block-loop?speed=0.5&laps=1")) == round(LAP / 0.5) + 1
    with pytest.raises(ConfigError, match="give frames or speed, not both"):
        open_source("synthetic:block-loop?frames=100&speed=0.3")
    with pytest.raises(ConfigError, match="laps must be an integer >= 1"):
        open_source("synthetic:block-loop?laps=0")
    with pytest.raises(ConfigError, match="weave must be in"):
        open_source("synthetic:block-loop?weave=3")


@pytest.mark.parametrize("laps", [1, 2, 3])
def test_block_loop_closes_after_each_lap_and_stays_on_the_road(laps):
    n = 600 * laps + 1
    poses = block_loop(n, laps=laps, weave=0.3, seed=5)
    for j in range(1, laps + 1):                                             # the end of lap j is the start
        np.testing.assert_allclose(poses[j * 600], poses[0], atol=1e-9)
    c = poses[:, :3, 3]
    step = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert abs(step.mean() * 600 / LAP - 1) < 0.002                          # speed: one lap in 600 frames
    assert step.max() / step.min() < 1.2                                     # no jumps, no stops
    np.testing.assert_allclose(c[:, 2], 1.5, atol=1e-12)
    # distance to the inner block (a rectangle): the road's centre line +- the weave
    d = np.hypot(np.maximum(np.abs(c[:, 0]) - BLOCK_HALF[0], 0), np.maximum(np.abs(c[:, 1]) - BLOCK_HALF[1], 0))
    assert np.all(np.abs(d - CENTRE_OFFSET) <= 0.3 + 1e-9) and np.ptp(d) > 0.4
    gaze = poses[:, :3, 2]
    tangent = np.diff(c, axis=0, append=c[1:2])[:, :2]
    cos = np.sum(gaze[:, :2] * tangent, axis=1) / np.linalg.norm(gaze[:, :2], axis=1) / np.linalg.norm(tangent,
                                                                                                         axis=1)
    assert np.all(cos > np.cos(np.radians(3.0)))                             # looking ahead along the path
    np.testing.assert_allclose(gaze[:, 2], -np.sin(np.radians(2.0)), atol=1e-12)
    a, b = c[1:-1, :2] - c[:-2, :2], c[2:, :2] - c[1:-1, :2]
    turn = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    assert np.all(turn > -1e-3)                                              # counter-clockwise only (weave aside)


def test_block_depth_on_a_facade_equals_the_geometry():
    """Every pixel that sees the largest inner facade in view is at the exact depth of the ray's hit on its
    plane and inside the facade's rectangle; known facade points ray-cast back onto themselves."""
    src = open_source("synthetic:block-loop?frames=400&laps=1&seed=1")
    i = 30
    rendering = src.rendering(i)
    pose, K = src.gt_poses[i], src.camera
    houses = [q for q, quad in enumerate(src.scene.quads) if re.fullmatch(r"house_(inner|outer)_\d_\d+", quad.name)]
    counts = [(rendering.quad == q).sum() for q in houses]
    q = houses[int(np.argmax(counts))]
    quad = src.scene.quads[q]
    vv, uu = np.nonzero(rendering.quad == q)
    assert len(uu) > 5000
    rays = np.stack([(uu - K.cx) / K.fx, (vv - K.cy) / K.fy, np.ones(len(uu))], axis=1) @ pose[:3, :3].T
    axis = int(np.argmax(np.abs(quad.normal)))                               # facades are planes x or y = const
    depth = (quad.origin[axis] - pose[axis, 3]) / rays[:, axis]              # z-depth: rays have unit camera z
    np.testing.assert_allclose(rendering.depth[vv, uu], depth, rtol=1e-9)
    hits = pose[:3, 3] + depth[:, None] * rays
    lo, hi = quad.corners.min(axis=0), quad.corners.max(axis=0)
    assert np.all((hits >= lo - 1e-6) & (hits <= hi + 1e-6))
    if "outer" in quad.name:                                                 # 0 to 1.5 m behind its building line
        assert 0 <= abs(quad.origin[axis]) - BLOCK_HALF[axis] - OUTER_OFFSET <= 1.5 + 1e-9
    else:
        assert 0 <= BLOCK_HALF[axis] - abs(quad.origin[axis]) <= 1.5 + 1e-9
    a, b = np.meshgrid(np.linspace(0.05, 0.95, 10), np.linspace(0.05, 0.95, 10))
    known = quad.point(a.ravel(), b.ravel())
    uv, z = project(pose, K, known)
    seen = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= K.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= K.height - 1)
    hit, hit_depth, hit_quad = src.scene.raycast(pose, K, uv[seen])
    visible = hit_quad == q
    assert visible.sum() >= 10
    np.testing.assert_allclose(hit[visible], known[seen][visible], atol=1e-9)
    np.testing.assert_allclose(hit_depth[visible], z[seen][visible], rtol=1e-12)


# ORB features spread over the image: tests/test_synthetic_scenes.py (parametrized over the scenes)


def test_block_facades_all_differ():
    scene = block_scene()
    facades = [quad for quad in scene.quads if re.fullmatch(r"house_(inner|outer)_\d_\d+", quad.name)]
    assert len(facades) > 30
    assert len({quad.texture.image.tobytes()[:4096] for quad in facades}) == len(facades)
