"""The cached point ids and positions of ``SlamMap`` (``slamkit.point_ids``): the arrays written through by the
map's own changes (new points, added, deleted and merged observations, culled recent points, BA's outlier removal;
positions set by the compiled BA and the loop correction, forgotten after Ceres' BA and normalization) equal what
pycolmap holds, checked after each stage of whole runs on rendered sequences."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from slamkit.config import SlamConfig
from slamkit.map import SlamMap
from slamkit.pipeline import Slam
from slamkit.point_ids import read_point3D_ids
from slamkit.sources import open_source
from slamkit.stages import ba as ba_stage
from slamkit.stages.local_mapper import LocalMapper

pycolmap.logging.minloglevel = 2


def assert_current(slam_map: SlamMap) -> int:
    """Every cached array equals a fresh read of its image, and every cached position of an existing point its
    position in the reconstruction; returns how many arrays were checked."""
    cached = slam_map._point3D_ids.cached()
    for image_id, ids in cached.items():
        fresh = read_point3D_ids(slam_map.reconstruction.image(image_id))
        assert np.array_equal(ids, fresh), f"image {image_id}: {np.flatnonzero(ids != fresh)[:10]}"
    rec = slam_map.reconstruction
    for p, xyz in slam_map._xyz.cached().items():
        if rec.exists_point3D(p):
            assert np.array_equal(xyz, rec.point3D(p).xyz), f"point {p}: cached {xyz}, map {rec.point3D(p).xyz}"
    return len(cached)


@pytest.fixture
def checked(monkeypatch):
    """Check the cache after local mapping, after each outlier removal of bundle adjustment (whose
    write-through the flush at the end of track maintenance would hide) and after each fusion."""
    counts = {"checks": 0, "arrays": 0}

    def wrap(owner, name, map_arg):
        original = getattr(owner, name)

        def checked_call(*args, **kwargs):
            out = original(*args, **kwargs)
            counts["checks"] += 1
            counts["arrays"] += assert_current(args[map_arg])
            return out

        monkeypatch.setattr(owner, name, checked_call)

    wrap(LocalMapper, "step", 1)
    wrap(LocalMapper, "_fuse_into", 1)
    wrap(LocalMapper, "_cull_recent", 1)
    wrap(ba_stage, "remove_outlier_observations", 0)
    return counts


@pytest.mark.parametrize("engine", ["ceres", "compiled"])
def test_cached_point_ids_stay_equal_to_pycolmap_through_a_run(checked, engine):
    slam = Slam(open_source("synthetic:block-loop?frames=80&laps=1&noise=1&seed=0"),
                SlamConfig().with_overrides(**{"ba.engine": engine}))
    positions = 0
    while not slam.done:
        slam.step()
        for seg in slam.state.segments:
            assert_current(seg.slam_map)
            positions = max(positions, len(seg.slam_map._xyz.cached()))
    assert slam.state.segments[0].slam_map.num_keyframes > 10
    assert checked["checks"] > 100 and checked["arrays"] > 500, checked
    assert positions > 200  # the positions were cached, and so checked


def test_cached_positions_hold_through_a_loop_correction():
    """A loop closed on a rendered block (pose graph, points corrected, global BA, normalization): every cached
    position equals pycolmap's after every frame."""
    slam = Slam(open_source("synthetic:block-loop?frames=160&laps=2&noise=1&seed=0"),
                SlamConfig().with_overrides(**{"ba.engine": "compiled"}))
    after = None  # frames stepped since the first closure (measured: at frame 140)
    while not slam.done and (after is None or after < 5):
        closed = bool(slam.step().loop_closure)
        after = 0 if after is None and closed else (after + 1 if after is not None else None)
        for seg in slam.state.segments:
            assert_current(seg.slam_map)
    assert after is not None, "no loop closed"
